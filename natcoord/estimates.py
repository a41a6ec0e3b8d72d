"""Error estimates of stored solutions (numbers only: no model, so that every derivation,
natcoord's and the independent one, states its error the same way)."""

from __future__ import annotations

import numpy as np


def estimated_error(best: np.ndarray, check: np.ndarray, steps: int) -> float:
    """An error estimate of a reference channel: max |best - check| (a run at another
    tolerance), never below the round-off a run of ``steps`` steps accumulates on values of
    this size (8 eps max|best| sqrt(steps)): two runs that agree to the last bit bound the
    truncation error, not the rounding, so zero is never an estimate."""
    b, c = np.asarray(best, float), np.asarray(check, float)
    diff = float(np.nanmax(np.abs(b - c))) if len(b) else 0.0
    scale = float(np.nanmax(np.abs(b))) if len(b) else 0.0
    return max(diff, roundoff(scale, steps))


def roundoff(scale: float, steps: int) -> float:
    """The round-off a run of ``steps`` steps accumulates on values of size ``scale``:
    8 eps scale sqrt(steps) (a random walk of a few ulps per step)."""
    return 8 * np.finfo(float).eps * max(scale, np.finfo(float).tiny) * np.sqrt(max(steps, 1))


