"""Figures drawn on demand: each plotly figure is kept in the page as JSON and drawn by
``report.js.j2`` when the ``<details>`` sections around it are open, so a page with a
hundred figures loads as fast as one without.

Array data is plotly's typed-array form (``{"dtype": "f4", "bdata": <base64>}``); arrays
that occur in several figures (the time axis of every channel of a case) are stored once in
the page's shared table and referenced as ``{"dtype": ..., "ref": k}``.
"""

from __future__ import annotations

import json
from typing import Any

import plotly.graph_objects as go
import plotly.io as pio
from markupsafe import Markup


def _script_safe(text: str) -> str:
    """JSON that cannot close its ``<script>`` element (``<\\/`` is the same JSON string)."""
    return text.replace("</", "<\\/").replace("<!--", "<\\!--")


class FigureStore:
    """Collects the page's figures: ``add(fig)`` gives the template's payload of one figure;
    after the last, ``finalize()`` moves arrays used by several figures to the shared table
    (``shared``) and fills every payload's ``json``."""

    def __init__(self, prefix: str = "fig"):
        self.prefix = prefix
        self._specs: list[tuple[dict, dict]] = []
        self._uses: dict[str, int] = {}
        self._index: dict[str, int] = {}
        self.table: list[str] = []

    def _count(self, node: Any) -> None:
        if isinstance(node, dict):
            if isinstance(node.get("bdata"), str):
                self._uses[node["bdata"]] = self._uses.get(node["bdata"], 0) + 1
            for v in node.values():
                self._count(v)
        elif isinstance(node, list):
            for v in node:
                self._count(v)

    def _dedupe(self, node: Any) -> Any:
        if isinstance(node, dict):
            b = node.get("bdata")
            if isinstance(b, str) and self._uses.get(b, 0) > 1:
                k = self._index.get(b)
                if k is None:
                    k = self._index[b] = len(self.table)
                    self.table.append(b)
                return {**{a: v for a, v in node.items() if a != "bdata"}, "ref": k}
            return {k: self._dedupe(v) for k, v in node.items()}
        if isinstance(node, list):
            return [self._dedupe(v) for v in node]
        return node

    def add(self, fig: go.Figure, config: dict, height: int | None = None) -> dict:
        """Payload of one figure: ``{"id", "height" (px), "json" (Markup, after
        finalize)}``."""
        spec = json.loads(pio.to_json(fig, validate=False))
        spec = {"data": spec.get("data", []), "layout": spec.get("layout", {}),
                "config": config}
        self._count(spec)
        payload = {"id": f"{self.prefix}-{len(self._specs) + 1}",
                   "height": height or int(fig.layout.height or 450), "json": Markup("{}")}
        self._specs.append((spec, payload))
        return payload

    def finalize(self) -> None:
        for spec, payload in self._specs:
            payload["json"] = Markup(_script_safe(json.dumps(self._dedupe(spec),
                                                             separators=(",", ":"))))

    def shared(self) -> Markup:
        return Markup(_script_safe(json.dumps(self.table, separators=(",", ":"))))

    def __len__(self) -> int:
        return len(self._specs)
