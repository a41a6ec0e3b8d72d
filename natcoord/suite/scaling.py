"""How natcoord's cost per step grows with the size of a mechanism: generated N-four-bars.

For each N the IFToMM A02 family's case is generated (:func:`natcoord.case.generate.n_four_bar`),
its model built, and fixed-step RK4 runs ``steps`` steps of ``h`` in the compiled loop from
the generated pose at rest (exact by construction, so no dense assembly: the loop projects
the start itself), every repeat's time kept. Build and sparsity-plan time are reported
apart; the figure is the cost per step (and per right-hand side), which a sparse, banded
core keeps linear in N. Measured in this process, pinned to the bench's core.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..case import casefile
from ..case.generate import n_four_bar
from ..dynamics.forward import integrate
from ..dynamics.solver import Fixed, Index1, Solver
from ..model import casemodel
from ..model.kinematics import State

SIZES = (64, 512)  # the N of the default scaling run
H = 1e-3  # s, RK4 step
STEPS = 200


def measure(n_couplers: int, *, h: float = H, steps: int = STEPS, repeats: int = 7) -> dict:
    """One N: build time, plan time, every repeat's stepping time, cost per step and per
    right-hand side (us), coordinates and rows."""
    with tempfile.TemporaryDirectory(prefix="natcoord-scaling-") as tmp:
        path = Path(tmp) / f"a02_four_bar_n{n_couplers}.toml"
        path.write_text(n_four_bar(n_couplers))
        case = casefile.load_case(path)
    t0 = time.perf_counter()
    model = casemodel.build(case, "joints").model
    build = time.perf_counter() - t0
    state = State(np.asarray(model.q0, float), np.zeros(model.n))
    times = np.array([0.0, steps * h])
    solver = Solver(Index1(), "rk4", Fixed(h))
    runs = [integrate(model, state, times, solver, check=False) for _ in range(repeats + 1)]
    first, runs = runs[0], runs[1:]  # the first also loads (or compiles) the kernels
    samples = [r.wall_time_s for r in runs]
    best = min(samples)
    c = runs[0].counters
    if not c["compiled"]:
        raise RuntimeError(f"N = {n_couplers}: the compiled loop did not run")
    return {"N": n_couplers, "n": model.n, "m": int(np.shape(runs[0].lam)[1]),
            "h": h, "steps": c["steps"], "rhs": c["rhs"],
            "factorizations": c["factorizations"], "build_time_s": build,
            "plan_time_s": first.counters["plan_time_s"], "samples_s": samples,
            "wall_time_s": best, "us_per_step": 1e6 * best / c["steps"],
            "us_per_rhs": 1e6 * best / c["rhs"]}


def scaling(sizes: Sequence[int] = SIZES, *, repeats: int = 7,
            progress: Callable[[str, dict], None] | None = None) -> dict:
    """Every N of ``sizes``, and the growth of the cost per step from the first to the
    last against the growth of N."""
    core = max(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    before = os.sched_getaffinity(0) if core is not None else None
    if core is not None:
        os.sched_setaffinity(0, {core})
    try:
        records = []
        for n in sizes:
            rec = measure(int(n), repeats=repeats)
            records.append(rec)
            if progress:
                progress(f"N = {n}", rec)
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)
    out = {"family": "n_four_bar", "method": f"rk4 h {H:g} s, {STEPS} steps from rest",
           "records": records}
    if len(records) > 1:
        a, b = records[0], records[-1]
        out |= {"size_ratio": b["N"] / a["N"], "step_cost_ratio": b["us_per_step"] /
                a["us_per_step"]}
    return out
