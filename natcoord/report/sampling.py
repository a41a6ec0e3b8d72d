"""How many samples a plotted series keeps: every figure of the report the same way."""

from __future__ import annotations

import numpy as np

MAX_POINTS = 1000  # samples per plotted series


def stride(n: int, m: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most m evenly spread samples of n (all of them when n <= m)."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(int))


def f32(a) -> np.ndarray:
    """A series as float32 (half the page size; plots need no more)."""
    return np.asarray(a, dtype=float).astype(np.float32)


def envelope(t: np.ndarray, e: np.ndarray, m: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Downsample an error series (T,) to at most m samples keeping each bucket's largest
    value (peaks survive; a bucket that is all NaN keeps its first sample)."""
    n = len(e)
    if n <= m:
        return t, e
    edges = np.linspace(0, n, m + 1).astype(int)
    idx = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if b <= a:
            continue
        seg = e[a:b]
        if np.all(np.isnan(seg)):
            idx.append(a)
        else:
            idx.append(a + int(np.nanargmax(seg)))
    idx = np.asarray(idx)
    return t[idx], e[idx]
