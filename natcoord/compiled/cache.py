"""Compile (or load from numba's cache) the compiled loops once per process.

Every compiled loop is named by a path (:data:`PATHS`): index1's ``sparse`` Schur path with
generic or ``generated`` kernels and its ``general`` QR null-space path
(:mod:`natcoord.compiled.index1`), the ``maggi`` (:mod:`natcoord.compiled.maggi`) and ``index3``
(:mod:`natcoord.compiled.index3`) loops; ``outputs`` names the sparse kernels that give the
samples' multipliers of an index1 run with a regular M
(:func:`natcoord.compiled.index1.sample_outputs`). Each has a warm-up, tiny runs on a particle
on a circle, that numba compiles once per machine (``cache=True``) and loads in every later
process.
"""

from __future__ import annotations

import time
from functools import partial
from types import SimpleNamespace

import numpy as np

from . import index1 as kernels
from . import index3 as kernels_index3
from . import maggi as kernels_maggi
from . import sparsity


def _warm_outputs() -> None:
    """The samples' multipliers and drift on the sparse path, on the warm-up model."""
    con, frc = kernels.warm_up_model()
    Q = np.array([[1.0, 0.0]])
    kernels.sample_outputs(sparsity.schur_plan(con, np.eye(2)), frc, Q, np.zeros_like(Q),
                           np.zeros((1, 1)), SimpleNamespace(max_phi=0.0, max_phi_dot=0.0))


PATHS = (*kernels.PATHS, "maggi", "index3")  # the compiled loops
WARM_UP = {**{p: partial(kernels.warm_up, p) for p in kernels.PATHS},
           "maggi": kernels_maggi.warm_up, "index3": kernels_index3.warm_up,
           "outputs": _warm_outputs}
_READY: set[str] = set()  # the paths compiled or loaded in this process


def ensure_compiled(*paths: str) -> float:
    """Compile or load the code of ``paths`` (keys of :data:`WARM_UP`; none given: all);
    returns the seconds this call took (0 when already done in this process). A run loads
    only the path it takes."""
    todo = [p for p in (paths or tuple(WARM_UP)) if p not in _READY]
    if not todo or not kernels.HAVE_NUMBA:
        return 0.0
    t0 = time.perf_counter()
    for path in todo:
        WARM_UP[path]()
        _READY.add(path)
    return time.perf_counter() - t0
