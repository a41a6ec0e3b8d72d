"""How many samples a plotted series keeps: every figure of the report the same way.

Series go to plotly in float64 (float32 drew a slowly drifting energy as a staircase); the
page then stores each at 16 bits over its own span (:mod:`natcoord.report.lazy`)."""

from __future__ import annotations

import numpy as np

MAX_POINTS = 400  # samples per plotted series (about one per pixel of a figure's width)


def stride(n: int, m: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most m evenly spread samples of n (all of them when n <= m)."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(int))


def series(a) -> np.ndarray:
    """A series as a float64 array (T,)."""
    return np.asarray(a, dtype=float)


def _buckets(n: int, k: int) -> list[tuple[int, int]]:
    edges = np.linspace(0, n, k + 1).astype(int)
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def minmax(t: np.ndarray, y: np.ndarray, m: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Downsample a curve (T,) to at most m samples that keep its envelope: each of m/2
    buckets gives its smallest and largest value (the earlier one first), drawn at the
    bucket's first and last sample time (so every series on the same times shares one
    time axis; a value moves by less than a bucket, 1/200 of the span); NaN stays NaN."""
    t, y = series(t), series(y)
    n = len(y)
    if n <= m:
        return t, y
    xs, ys = [], []
    for a, b in _buckets(n, m // 2):
        seg = y[a:b]
        if np.all(np.isnan(seg)):
            pair = (np.nan, np.nan)
        else:
            lo, hi = int(np.nanargmin(seg)), int(np.nanargmax(seg))
            pair = (seg[lo], seg[hi]) if lo <= hi else (seg[hi], seg[lo])
        xs += [t[a], t[b - 1]]
        ys += pair
    return np.asarray(xs), np.asarray(ys)


def envelope(t: np.ndarray, e: np.ndarray, m: int = MAX_POINTS // 2
             ) -> tuple[np.ndarray, np.ndarray]:
    """Downsample an error series (T,) to at most m samples keeping each bucket's largest
    value (peaks survive; an all-NaN bucket gives NaN), drawn at the bucket's last sample
    time (so every series on the same times shares one time axis)."""
    n = len(e)
    if n <= m:
        return t, e
    xs, ys = [], []
    for a, b in _buckets(n, m):
        seg = e[a:b]
        xs.append(t[b - 1])
        ys.append(np.nan if np.all(np.isnan(seg)) else np.nanmax(seg))
    return np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)
