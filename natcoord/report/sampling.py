"""How many samples a plotted series keeps: every figure of the report the same way.

Series go to plotly in float64 (float32 drew a slowly drifting energy as a staircase); the
page then stores each at 16 bits over its own span (:mod:`natcoord.report.lazy`)."""

from __future__ import annotations

import numpy as np

MAX_POINTS = 600  # samples per plotted series (about one per pixel of a figure's width)


def stride(n: int, m: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most m evenly spread samples of n (all of them when n <= m)."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(int))


def series(a) -> np.ndarray:
    """A series as a float64 array (T,)."""
    return np.asarray(a, dtype=float)


def minmax(t: np.ndarray, y: np.ndarray, m: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Downsample a curve (T,) to at most m samples that keep its envelope: each of m/2
    buckets keeps its smallest and largest value at their own times, in time order (a
    bucket that is all NaN keeps its first sample, so gaps stay gaps)."""
    t, y = series(t), series(y)
    n = len(y)
    if n <= m:
        return t, y
    edges = np.linspace(0, n, m // 2 + 1).astype(int)
    idx: list[int] = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if b <= a:
            continue
        seg = y[a:b]
        if np.all(np.isnan(seg)):
            idx.append(a)
            continue
        lo, hi = a + int(np.nanargmin(seg)), a + int(np.nanargmax(seg))
        idx.extend(sorted({lo, hi}))
    i = np.asarray(idx)
    return t[i], y[i]


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
