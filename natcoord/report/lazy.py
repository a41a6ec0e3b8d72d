"""Figures drawn on demand: every plotly figure of the page travels in one gzip blob
(``#nc-figures``, in the page's text form ``to_text``), unpacked once by ``report.js.j2``;
each figure is drawn when the ``<details>`` sections around it are open, so a page with a
hundred figures loads as fast as one without.

Every float array of a figure is stored in one of two forms, decoded by the page's loader
into a Float64Array before plotly sees it:

- ``{"grid": [start, step, n]}``: evenly spaced values (a time axis), exact;
- ``{"q": <base64 uint16>, "lo": a, "hi": b, "log": bool}``: 16 bits over the array's own
  span, value = a + (b - a) k / 65534 (of log10 values when ``log``: positive arrays spanning
  more than a decade, the |error| panels), 65535 = NaN; so a value is kept to 1/65534 of its
  array's span (0.04 % of a value on a log scale), a quarter of float64's bytes.

The blob (:func:`pack`) is gzip of: a 4-byte little-endian length L, L bytes of UTF-8
JSON ``{"figs": {id: {data, layout, config}}, "n": N}``, then the N 16-bit codes of every
distinct array, delta-coded twice per array (the change of the step from one code to the
next, mod 2**16; a smooth curve's is small) and split into two byte planes (all low bytes,
then all high bytes), which gzip packs 1.5x tighter than the codes themselves. In the JSON
a coded array is ``{"q": [offset, n], "lo", "hi", "log"}`` (offset in codes); identical
arrays share their codes.
"""

from __future__ import annotations

import base64
import gzip
import json
import re
from typing import Any

import numpy as np
import plotly.graph_objects as go
import plotly.io as pio
from markupsafe import Markup

# Binary data in the page: base85 (RFC 1924's alphabet, Python's b85encode) with "<" written
# as "." (absent from the alphabet), so the text can neither end nor escape its <script>
# element; 5 characters per 4 bytes where base64 takes 5.33.
_B85_SAFE = str.maketrans("<", ".")
_B85_BACK = str.maketrans(".", "<")


def to_text(data: bytes) -> str:
    """Bytes as the page's text form (decoded by ``report.js.j2``'s ``bytesOf``)."""
    return base64.b85encode(data).decode("ascii").translate(_B85_SAFE)


def from_text(text: str) -> bytes:
    """The bytes of ``to_text``'s text."""
    return base64.b85decode(text.strip().translate(_B85_BACK))


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
    """A figure's spec with every float typed array (plotly's form, or a float array of a
    spec written as data) in the stored form."""
    if isinstance(node, np.ndarray) and node.dtype.kind == "f" and node.ndim == 1:
        return encode(node)
    if isinstance(node, dict):
        if isinstance(node.get("bdata"), str):
            y = _decode(node)
            return node if y is None else encode(y)
        return {k: _compact(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_compact(v) for v in node]
    return node


def _codes(node: dict) -> np.ndarray:
    return np.frombuffer(base64.b64decode(node["q"]), dtype="<u2")


class FigureStore:
    """Collects the page's figures: ``add(fig)`` gives the template's payload of one figure
    (``{"id", "height"}``); ``blob()`` the page's figures packed (see the module)."""

    def __init__(self, prefix: str = "fig"):
        self.prefix = prefix
        self.specs: dict[str, dict] = {}

    def add(self, fig: go.Figure | dict, config: dict, height: int | None = None) -> dict:
        """Payload of one figure (a plotly figure, or its spec ``{"data", "layout"}`` with
        numpy arrays): ``{"id", "height" (px)}``."""
        spec = fig if isinstance(fig, dict) else json.loads(pio.to_json(fig, validate=False))
        fid = f"{self.prefix}-{len(self.specs) + 1}"
        layout = spec.get("layout", {})
        self.specs[fid] = {"data": _compact(spec.get("data", [])), "layout": layout,
                           "config": config}
        return {"id": fid, "height": height or int(layout.get("height") or 450)}

    def blob(self) -> Markup:
        return Markup(to_text(pack(self.specs)))

    def __len__(self) -> int:
        return len(self.specs)


def pack(specs: dict[str, dict]) -> bytes:
    """Figures {id: spec} with arrays in ``encode``'s form -> the page's gzip blob."""
    offsets: dict[bytes, int] = {}
    chunks: list[np.ndarray] = []
    n = 0

    def place(node: Any) -> Any:
        nonlocal n
        if isinstance(node, dict):
            if isinstance(node.get("q"), str):
                codes = _codes(node)
                key = codes.tobytes()
                if key not in offsets:
                    offsets[key] = n
                    step = np.diff(codes, prepend=np.uint16(0))  # mod 2**16
                    chunks.append(np.diff(step, prepend=np.uint16(0)).astype("<u2"))
                    n += len(codes)
                return {**node, "q": [offsets[key], len(codes)]}
            return {k: place(v) for k, v in node.items()}
        if isinstance(node, list):
            return [place(v) for v in node]
        return node

    head = json.dumps({"figs": place(specs), "n": n}, separators=(",", ":")).encode("utf-8")
    deltas = np.concatenate(chunks) if chunks else np.zeros(0, "<u2")
    planes = deltas.view(np.uint8).reshape(-1, 2).T.tobytes()  # low bytes, then high bytes
    raw = len(head).to_bytes(4, "little") + head + planes
    return gzip.compress(raw, compresslevel=9, mtime=0)


def unpack(blob: bytes) -> dict[str, dict]:
    """The page loader's reading of a blob: {id: spec}, every coded array in ``encode``'s
    form again (for tests and tools; ``decoded`` gives its values)."""
    raw = gzip.decompress(blob)
    size = int.from_bytes(raw[:4], "little")
    head = json.loads(raw[4:4 + size])
    planes = np.frombuffer(raw[4 + size:], dtype=np.uint8).reshape(2, -1)
    deltas = (planes[0].astype(np.uint16) | (planes[1].astype(np.uint16) << 8))

    def restore(node: Any) -> Any:
        if isinstance(node, dict):
            if isinstance(node.get("q"), list):
                o, k = node["q"]
                step = np.cumsum(deltas[o:o + k], dtype=np.uint16)
                codes = np.cumsum(step, dtype=np.uint16).astype("<u2")
                return {**node, "q": base64.b64encode(codes.tobytes()).decode("ascii")}
            return {k: restore(v) for k, v in node.items()}
        if isinstance(node, list):
            return [restore(v) for v in node]
        return node

    return restore(head["figs"])


def page_figures(html: str) -> dict[str, dict]:
    """{id: spec} of a report page's figure blob (``unpack`` of ``#nc-figures``)."""
    m = re.search(r'id="nc-figures"[^>]*>([^<]*)<', html)
    return unpack(from_text(m[1])) if m else {}
