"""Figures drawn on demand: each plotly figure is kept in the page as JSON and drawn by
``report.js.j2`` when the ``<details>`` sections around it are open, so a page with a
hundred figures loads as fast as one without.

Every float array of a figure is stored in one of two forms, decoded by the page's loader
into a Float64Array before plotly sees it:

- ``{"grid": [start, step, n]}``: evenly spaced values (a time axis), exact;
- ``{"q": <base64 uint16>, "lo": a, "hi": b, "log": bool}``: 16 bits over the array's own
  span, value = a + (b - a) k / 65534 (of log10 values when ``log``: positive arrays spanning
  more than a decade, the |error| panels), 65535 = NaN; so a value is kept to 1/65534 of its
  array's span (0.04 % of a value on a log scale), a quarter of float64's bytes.

Arrays that occur in several figures are stored once in the page's shared table and
referenced as ``{"ref": k}``.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np
import plotly.graph_objects as go
import plotly.io as pio
from markupsafe import Markup


def _script_safe(text: str) -> str:
    """JSON that cannot close its ``<script>`` element (``<\\/`` is the same JSON string)."""
    return text.replace("</", "<\\/").replace("<!--", "<\\!--")


LEVELS = 65534  # largest code of a value; 65535 codes NaN


def _decode(node: dict) -> np.ndarray | None:
    """The float64 values of plotly's typed-array form, None for other dtypes or shapes."""
    if node.get("dtype") not in ("f4", "f8") or "shape" in node:
        return None
    return np.frombuffer(base64.b64decode(node["bdata"]), dtype="<" + node["dtype"]).astype(float)


def encode(y: np.ndarray) -> dict:
    """One float array (T,) in the page's stored form (see the module's docstring)."""
    y = np.asarray(y, dtype=float)
    n = len(y)
    ok = np.isfinite(y)
    if n > 2 and ok.all():
        step = (y[-1] - y[0]) / (n - 1)
        grid = y[0] + step * np.arange(n)
        if step > 0 and np.all(np.abs(grid - y) <= 1e-9 * max(abs(step), 1e-300)):
            return {"grid": [float(y[0]), float(step), n]}
    fin = y[ok]
    log = bool(fin.size and fin.min() > 0 and fin.max() > 10 * fin.min())
    v = np.log10(np.where(ok & (y > 0), y, 1.0)) if log else np.where(ok, y, 0.0)
    lo, hi = (float(v[ok].min()), float(v[ok].max())) if fin.size else (0.0, 0.0)
    k = np.zeros(n) if hi <= lo else np.rint((v - lo) / (hi - lo) * LEVELS)
    codes = np.where(ok, k, LEVELS + 1).astype("<u2")
    return {"q": base64.b64encode(codes.tobytes()).decode("ascii"), "lo": lo, "hi": hi,
            "log": log}


def decoded(node: dict) -> np.ndarray:
    """The values of a stored array (the page loader's arithmetic, for tests)."""
    if "grid" in node:
        a, h, n = node["grid"]
        return a + h * np.arange(n)
    k = np.frombuffer(base64.b64decode(node["q"]), dtype="<u2").astype(float)
    v = node["lo"] + (node["hi"] - node["lo"]) * k / LEVELS
    v = 10.0 ** v if node["log"] else v
    return np.where(k > LEVELS, np.nan, v)


def _compact(node: Any) -> Any:
    """A figure's spec with every float typed array in the stored form."""
    if isinstance(node, dict):
        if isinstance(node.get("bdata"), str):
            y = _decode(node)
            return node if y is None else encode(y)
        return {k: _compact(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_compact(v) for v in node]
    return node


def _key(node: dict) -> str | None:
    """Identity of a stored array (for sharing), None for anything else."""
    if "q" in node or "grid" in node or isinstance(node.get("bdata"), str):
        return json.dumps(node, sort_keys=True)
    return None


class FigureStore:
    """Collects the page's figures: ``add(fig)`` gives the template's payload of one figure;
    after the last, ``finalize()`` moves arrays used by several figures to the shared table
    (``shared``) and fills every payload's ``json``."""

    def __init__(self, prefix: str = "fig"):
        self.prefix = prefix
        self._specs: list[tuple[dict, dict]] = []
        self._uses: dict[str, int] = {}
        self._index: dict[str, int] = {}
        self.table: list[dict] = []

    def _count(self, node: Any) -> None:
        if isinstance(node, dict):
            key = _key(node)
            if key is not None:
                self._uses[key] = self._uses.get(key, 0) + 1
                return
            for v in node.values():
                self._count(v)
        elif isinstance(node, list):
            for v in node:
                self._count(v)

    def _dedupe(self, node: Any) -> Any:
        if isinstance(node, dict):
            key = _key(node)
            if key is not None:
                if self._uses.get(key, 0) < 2 or "grid" in node:  # a grid is shorter inline
                    return node
                k = self._index.get(key)
                if k is None:
                    k = self._index[key] = len(self.table)
                    self.table.append(node)
                return {"ref": k}
            return {k: self._dedupe(v) for k, v in node.items()}
        if isinstance(node, list):
            return [self._dedupe(v) for v in node]
        return node

    def add(self, fig: go.Figure, config: dict, height: int | None = None) -> dict:
        """Payload of one figure: ``{"id", "height" (px), "json" (Markup, after
        finalize)}``."""
        spec = json.loads(pio.to_json(fig, validate=False))
        spec = {"data": _compact(spec.get("data", [])), "layout": spec.get("layout", {}),
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
