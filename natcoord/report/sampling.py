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
