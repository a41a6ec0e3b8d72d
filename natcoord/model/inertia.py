"""Inertia helpers for rigid bodies: second moments ``∫ (x - g)(x - g)^T dm`` about the com.

Natural-coordinate mass matrices use the second moment (d, d), kg m^2, rather than the
inertia tensor; :func:`second_moment` converts one to the other in 3-D.
"""

from __future__ import annotations

import numpy as np


def second_moment(inertia: np.ndarray) -> np.ndarray:
    """∫ (x - g)(x - g)^T dm from an inertia tensor about the com (3, 3), kg m^2."""
    inertia = np.asarray(inertia, float)
    return 0.5 * np.trace(inertia) * np.eye(3) - inertia


def rod_second_moment(mass: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Second moment (d, d) of a slender uniform rod from a to b about its centre."""
    e = np.asarray(b, float) - np.asarray(a, float)
    return mass / 12.0 * np.outer(e, e)


def plate_second_moment(mass: float, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Second moment (d, d) of a thin uniform parallelogram plate with edges e1, e2."""
    e1, e2 = np.asarray(e1, float), np.asarray(e2, float)
    return mass / 12.0 * (np.outer(e1, e1) + np.outer(e2, e2))
