"""How natcoord's cost grows with the size of a mechanism: whole generated N-four-bar runs.

For each N the IFToMM A02 family's case is generated (:func:`natcoord.case.generate.n_four_bar`)
and run whole the way natcoord's engine runs it: the case's own ``[engines.natcoord]``
settings (coordinates and solver), from the assembled start over every output sample of
the case's duration. Model build and assembly, the kernels' compile or cache load and the
sparsity plan are build time, apart; the stepping time (the compiled loop's, best of its
runs, taken in rounds over the sizes) gives the cost per step, per right-hand side and per
simulated second. Each run is
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
BUDGET_S = 10.0  # stepping time of a round after which no further round is started ...
MIN_ROUNDS = 2  # ... once this many rounds ran (the largest N's one run passes the budget)


def generated_case(n_couplers: int, duration: float | None = None):
    """The generated N-four-bar case (its file written to a temporary folder and loaded)."""
    with tempfile.TemporaryDirectory(prefix="natcoord-scaling-") as tmp:
        path = Path(tmp) / f"a02_four_bar_n{n_couplers}.toml"
        path.write_text(n_four_bar(n_couplers, duration=duration))
        return casefile.load_case(path)


class _Member:
    """One N of the family, built once (case, model, start, solver; build time in s), its
    first whole run's solution and every run's stepping time (s)."""

    def __init__(self, n_couplers: int, duration: float | None):
        self.N = n_couplers
        self.case = generated_case(n_couplers, duration)
        self.settings = self.case.engine("natcoord").settings
        self.solver = case_solver(self.settings)
        t0 = time.perf_counter()
        self.cm = casemodel.build(self.case, self.settings.get("coordinates", "joints"))
        self.state = casemodel.initial_state(self.cm)
        self.build = time.perf_counter() - t0
        self.first = None
        self.samples: list[float] = []

    def run(self) -> float:
        """One whole run; its stepping time (s)."""
        sol = integrate(self.cm.model, self.state, self.case.times, self.solver)
        if not sol.counters["compiled"]:
            raise RuntimeError(f"N = {self.N}: the compiled loop did not run")
        if self.first is None:
            self.first = sol
        self.samples.append(sol.wall_time_s)
        return sol.wall_time_s

    def record(self) -> dict:
        """Build time, every run's stepping time, cost per step, per right-hand side (us)
        and per simulated second (s/s), coordinates, rows, steps and B0's error (m)."""
        case, sol, samples = self.case, self.first, self.samples
        c = sol.counters
        C = self.cm.point_map("crank0", "B0")
        b0 = sol.q @ C[:, :-1].T + C[:, -1]
        ex = exact.n_four_bar(self.N, case.times)
        error = float(np.max(np.hypot(b0[:, 0] - ex["x"], b0[:, 1] - ex["y"])))
        best = min(samples)
        return {"N": self.N, "n": self.cm.model.n, "m": int(np.shape(sol.lam)[1]),
                "coordinates": self.settings.get("coordinates", "joints"),
                "method": self.solver.method, "h": self.settings.get("h"),
                "duration_s": case.duration, "path": c.get("path"), "steps": c["steps"],
                "rejected": c["rejected"], "rhs": c["rhs"],
                "factorizations": c["factorizations"],
                "build_time_s": self.build + c["compile_time_s"] + c["plan_time_s"],
                "plan_time_s": c["plan_time_s"], "samples_s": samples, "wall_time_s": best,
                "us_per_step": 1e6 * best / c["steps"], "us_per_rhs": 1e6 * best / c["rhs"],
                "s_per_simulated_s": best / case.duration, "error_m": error}


def scaling(sizes: Sequence[int] = SIZES, *, repeats: int = 3, duration: float | None = None,
            progress: Callable[[str, dict], None] | None = None) -> dict:
    """Every N of ``sizes`` (once each, smallest first), and the growth of the cost per
    step from the smallest N to the largest against the growth of N. Timed in rounds,
    each one whole run of every N in turn (so that a change in the machine's load falls on
    all of them alike), at most ``repeats`` rounds and at least MIN_ROUNDS (or
    ``repeats`` when fewer); no further round once one took BUDGET_S of stepping. Each
    N's figure is the best of its runs."""
    core = max(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    before = os.sched_getaffinity(0) if core is not None else None
    if core is not None:
        os.sched_setaffinity(0, {core})
    try:
        members = [_Member(n, duration) for n in sorted({int(n) for n in sizes})]
        rounds = 0
        while rounds < max(1, repeats):
            spent = sum(m.run() for m in members)
            rounds += 1
            if rounds >= min(MIN_ROUNDS, max(1, repeats)) and spent >= BUDGET_S:
                break
        records = [m.record() for m in members]
        if progress:
            for rec in records:
                progress(f"N = {rec['N']}", rec)
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
