"""How many samples a plotted series keeps: every figure of the report the same way.

Series go to plotly in float64 (float32 drew a slowly drifting energy as a staircase); the
page then stores each at 16 bits over its own span (:mod:`natcoord.report.lazy`)."""

from __future__ import annotations

import numpy as np

MAX_POINTS = 300  # samples per plotted series (one per 3-4 pixels of a 1,000-pixel-wide figure)


def stride(n: int, m: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most m evenly spread samples of n (all of them when n <= m)."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(int))


def series(a) -> np.ndarray:
    """A series as a float64 array (T,)."""
    return np.asarray(a, dtype=float)


def _buckets(n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(first, end) indices (K,) of k near-equal buckets of n samples, the empty dropped."""
    edges = np.linspace(0, n, k + 1).astype(int)
    keep = edges[1:] > edges[:-1]
    return edges[:-1][keep], edges[1:][keep]


def _first(y: np.ndarray, value: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per bucket [a, b), the index of the first sample equal to its ``value``."""
    which = np.repeat(np.arange(len(a)), b - a)
    idx = np.where(y == value[which], np.arange(len(y)), len(y))
    return np.minimum.reduceat(idx, a)


def minmax(t: np.ndarray, y: np.ndarray, m: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Downsample a curve (T,) to at most m samples that keep its envelope: each of m/2
    buckets gives its smallest and largest value (the earlier one first), drawn at the
    bucket's first and last sample time (so every series on the same times shares one
    time axis; a value moves by less than a bucket, 1/200 of the span); NaN stays NaN."""
    t, y = series(t), series(y)
    n = len(y)
    if n <= m:
        return t, y
    a, b = _buckets(n, m // 2)
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduceat(y, a), np.fmax.reduceat(y, a)  # NaN: the bucket's all NaN
    later = _first(y, lo, a, b) > _first(y, hi, a, b)  # the minimum after the maximum
    first, second = np.where(later, hi, lo), np.where(later, lo, hi)
    return (np.column_stack([t[a], t[b - 1]]).ravel(),
            np.column_stack([first, second]).ravel())


def envelope(t: np.ndarray, e: np.ndarray, m: int = MAX_POINTS // 2
             ) -> tuple[np.ndarray, np.ndarray]:
    """Downsample an error series (T,) to at most m samples keeping each bucket's largest
    value (peaks survive; an all-NaN bucket gives NaN), drawn at the bucket's last sample
    time (so every series on the same times shares one time axis)."""
    n = len(e)
    if n <= m:
        return t, e
    a, b = _buckets(n, m)
    with np.errstate(invalid="ignore"):
        return series(t)[b - 1], np.fmax.reduceat(series(e), a)
