"""Forward dynamics: one entry point, :func:`integrate`, over the formulations of
:mod:`natcoord.dynamics.formulations` and the integrators of :mod:`natcoord.dynamics.integrators`,
configured by a :class:`~natcoord.dynamics.solver.Solver`.

    sol = integrate(model, state, times)                       # index1, dop853, rtol 1e-10
    sol = integrate(model, state, times, Solver(Index3(), "trapezoidal", Fixed(1e-3)))

Before integrating, the existence condition ker M ∩ ker Phi_q = {0} (Eq. (37)) is checked
at the initial state (ExistenceError names the motion without kinetic energy). Every
sample carries q, qd, qdd and the minimum-norm multipliers of all rows (joints first,
drivers after them).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from .. import timing
from ..compiled import cache as kernel_cache
from ..compiled import index1 as kernels
from ..model.drivers import ConstraintSystem
from ..model.kinematics import State
from .common import Counters, check_existence, multipliers
from .formulations import FORMULATIONS
from .index1 import Index1Loop
from .integrators import time_loop
from .solver import Solver

__all__ = ["Counters", "Solution", "Solver", "integrate", "accelerations", "project"]


@dataclass(frozen=True)
class Solution:
    """Samples of an integration: t (T,), q (T, n), qd (T, n), qdd (T, n), lam (T, m_all)
    with m_all = m constraint rows + driver rows; ``counters`` see
    :class:`~natcoord.dynamics.common.Counters`."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    lam: np.ndarray
    counters: dict = field(default_factory=dict)
    wall_time_s: float = 0.0
    unique: np.ndarray | None = None  # (T,) bool: lam there is the unique one (no dependent
    # row on the sparse Schur path), the same for every reaction method


MAX_FIXED_STEPS = kernels.Steps().max_steps  # a fixed-step run's budget, as an adaptive one's


def integrate(model, state: State, times: np.ndarray, solver: Solver | None = None, *,
              check: bool = True) -> Solution:
    """Integrate from ``state`` at times[0] and sample at ``times`` (T,).

    ``solver`` (default ``Solver()``: index1, dop853, rtol 1e-10, atol 1e-12). Every
    formulation runs as one compiled numba loop when the model allows (index1 with dop853,
    dopri5 or rk4, maggi with dop853 or dopri5, index3); its compile/cache-load time
    (``counters["compile_time_s"]``) and the model's sparsity plan and generated kernels
    (``counters["plan_time_s"]``) are never in ``wall_time_s``; ``counters["path"]`` names
    the loop that ran (:data:`natcoord.compiled.cache.PATHS`, or ``python``). ``check``: test Eq.
    (37) at the initial state first.
    """
    solver = Solver() if solver is None else solver
    name, method, h = solver.formulation.name, solver.method, solver.h
    options = solver.formulation.options()
    rtol, atol = (solver.step.rtol, solver.step.atol) if h is None else (0.0, 0.0)
    times = np.asarray(times, dtype=float)
    t0 = float(times[0])
    if h is not None:  # refused before it runs: a count past int64 took one step a sample
        steps = (float(times[-1]) - t0) / h  # in the compiled loops, and none stops the
        if not steps <= MAX_FIXED_STEPS:     # Python loop
            raise RuntimeError(f"{method}: h = {h:.3g} s takes {steps:.3g} fixed steps over "
                               f"{float(times[-1]) - t0:.6g} s, more than {MAX_FIXED_STEPS:,}"
                               ": too many steps")
    if check:
        check_existence(model, state.q, t0)
    cnt = Counters()
    form = FORMULATIONS[name].loop(model, options, cnt)
    cs = ConstraintSystem(model)
    n, T = model.n, len(times)
    Q, QD, QDD, LAM = np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, cs.m))
    compiled = form.compiled_candidate(method, h)
    q0, qd0 = np.asarray(state.q, float), np.asarray(state.qd, float)
    if name == "maggi" or (name == "index1" and not compiled):  # a consistent start (index3
        q0, qd0 = Index1Loop(model, {**options, "linsolve": "qr"}, Counters()).project(
            t0, q0, qd0)             # and the compiled index1 loop project it themselves)

    def record(k, t, y):
        q, qd = form.state(t, y)
        Q[k], QD[k] = q, qd
        QDD[k] = form.accelerations(t, q, qd)

    plan0 = time.perf_counter()  # model-only set-up (plan, kernels): not stepping time
    prep = form.prepare_compiled(q0) if compiled else None
    plan_s = time.perf_counter() - plan0
    compile_s = kernel_cache.ensure_compiled(prep.path) if compiled else 0.0
    go = form.compiled_runner(times, t0, q0, qd0, method, rtol, atol, h) if compiled else None
    start = dataclasses.replace(cnt)

    def stepping():  # one whole run from the start (a benchmark repeats it: natcoord.timing)
        vars(cnt).update(vars(start))  # every run counts its own steps
        if compiled:  # packed once above: the run's own work only
            return go(Q, QD, QDD)
        time_loop(form, form.init(t0, q0, qd0), times, method=method, h=h, rtol=rtol,
                  atol=atol, record=record)
        return None

    counted, wall, batches = timing.timed(stepping)
    if counted is not None:  # index1's loop returns its counter array: added once, here,
        kernels.add_counters(counted, cnt)  # not in each timed run (2 us of Python each)
    # outputs only: min-norm multipliers and drift at the samples
    done = np.zeros(T, bool)
    if prep is not None and prep.plan is not None:  # index1's Schur plan: sparse, linear in
        done[:] = ~kernels.sample_outputs(  # the model's size; lambda unique where no row
            prep.plan, prep.frc, Q, QD, LAM, cnt, prep.out_args)  # is dependent
    rest = np.flatnonzero(~done)  # all samples at once
    if rest.size:
        LAM[rest] = multipliers(model, cs, times[rest], Q[rest], QD[rest], QDD[rest])
        phi, phi_dot = cs.drift(Q[rest], QD[rest], times[rest])
        cnt.max_phi, cnt.max_phi_dot = max(cnt.max_phi, phi), max(cnt.max_phi_dot, phi_dot)
    counters = cnt.as_dict() | {"formulation": name, "method": method,
                                "compiled": bool(compiled), "compile_time_s": compile_s,
                                "path": prep.path if compiled else "python",
                                "plan_time_s": plan_s} | batches.counters()
    return Solution(times, Q, QD, QDD, LAM, counters, wall, done)


def accelerations(model, q: np.ndarray, qd: np.ndarray,
                  t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Index-1 solve at one state: (qdd (n,), minimum-norm lambda (m_all,)).

    Rank-revealing (pivoted QR), so redundant constraints and a singular M are fine as
    long as ker M ∩ ker Phi_q = {0}.
    """
    qdd = Index1Loop(model, {"linsolve": "qr"}, Counters()).accelerations(t, q, qd)
    return qdd, multipliers(model, ConstraintSystem(model), t, q, qd, qdd)


def project(model, q: np.ndarray, qd: np.ndarray, tol: float = 1e-13,
            counters: Counters | None = None, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Project q onto Phi(q, t) = 0 (Newton) and qd onto Phi_q qd = -Phi_t (min-norm)."""
    form = Index1Loop(model, {"linsolve": "qr", "project_tol": tol}, counters or Counters())
    form.mode = "qr"
    return form.project(t, np.asarray(q, float), np.asarray(qd, float))
