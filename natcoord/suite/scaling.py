"""How natcoord's cost grows with the size of a mechanism: whole generated N-four-bar runs.

For each N the IFToMM A02 family's case is generated (:func:`natcoord.case.generate.n_four_bar`)
and run whole the way natcoord's engine runs it: the case's own ``[engines.natcoord]``
settings (coordinates and solver), from the assembled start over every output sample of
the case's duration. Model build and assembly, the kernels' compile or cache load and the
sparsity plan are build time, apart; the stepping time (the compiled loop's, best of the
repeats) gives the cost per step, per right-hand side and per simulated second. Each run is
checked against the exact one-equation reduction (B0's largest distance from it, m). The
engine's per-sample outputs (reactions of every method) are not part of the figure.
Measured in this process, pinned to the bench's core.
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
from ..derivations import exact
from ..dynamics.forward import integrate
from ..dynamics.solver import case_solver
from ..model import casemodel

SIZES = (64, 512)  # the N of the default scaling run
BUDGET_S = 10.0  # stepping time per N after which no further repeat is started


def generated_case(n_couplers: int, duration: float | None = None):
    """The generated N-four-bar case (its file written to a temporary folder and loaded)."""
    with tempfile.TemporaryDirectory(prefix="natcoord-scaling-") as tmp:
        path = Path(tmp) / f"a02_four_bar_n{n_couplers}.toml"
        path.write_text(n_four_bar(n_couplers, duration=duration))
        return casefile.load_case(path)


def measure(n_couplers: int, *, duration: float | None = None, repeats: int = 3) -> dict:
    """One N, run whole at its generated settings: build time, every repeat's stepping time
    (at most ``repeats``, fewer once BUDGET_S is spent), cost per step, per right-hand side
    (us) and per simulated second (s/s), coordinates, rows, steps and B0's error (m)."""
    case = generated_case(n_couplers, duration)
    settings = case.engine("natcoord").settings
    solver = case_solver(settings)
    t0 = time.perf_counter()
    cm = casemodel.build(case, settings.get("coordinates", "joints"))
    state = casemodel.initial_state(cm)
    build = time.perf_counter() - t0
    runs = []
    while len(runs) < max(1, repeats) and sum(r.wall_time_s for r in runs) < BUDGET_S:
        runs.append(integrate(cm.model, state, case.times, solver))
    sol = runs[0]
    c = sol.counters
    if not c["compiled"]:
        raise RuntimeError(f"N = {n_couplers}: the compiled loop did not run")
    C = cm.point_map("crank0", "B0")
    b0 = sol.q @ C[:, :-1].T + C[:, -1]
    ex = exact.n_four_bar(n_couplers, case.times)
    error = float(np.max(np.hypot(b0[:, 0] - ex["x"], b0[:, 1] - ex["y"])))
    samples = [r.wall_time_s for r in runs]
    best = min(samples)
    return {"N": n_couplers, "n": cm.model.n, "m": int(np.shape(sol.lam)[1]),
            "coordinates": settings.get("coordinates", "joints"), "method": solver.method,
            "h": settings.get("h"), "duration_s": case.duration, "path": c.get("path"),
            "steps": c["steps"], "rejected": c["rejected"], "rhs": c["rhs"],
            "factorizations": c["factorizations"],
            "build_time_s": build + c["compile_time_s"] + c["plan_time_s"],
            "plan_time_s": c["plan_time_s"], "samples_s": samples, "wall_time_s": best,
            "us_per_step": 1e6 * best / c["steps"], "us_per_rhs": 1e6 * best / c["rhs"],
            "s_per_simulated_s": best / case.duration, "error_m": error}


def scaling(sizes: Sequence[int] = SIZES, *, repeats: int = 3, duration: float | None = None,
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
            rec = measure(int(n), duration=duration, repeats=repeats)
            records.append(rec)
            if progress:
                progress(f"N = {n}", rec)
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)
    kinds = sorted({f"{r['coordinates']} {r['method']}" + (f" h {r['h']:g} s" if r["h"] else "")
                    for r in records})
    out = {"family": "n_four_bar", "method": "whole generated runs at their own natcoord "
           f"settings ({', '.join(kinds)})", "records": records}
    if len(records) > 1:
        a, b = records[0], records[-1]
        out |= {"size_ratio": b["N"] / a["N"], "step_cost_ratio": b["us_per_step"] /
                a["us_per_step"]}
    return out
