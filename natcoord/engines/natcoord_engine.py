"""natcoord's own solver as an engine: natural coordinates, formulation chosen by settings.

Settings (``[engines.natcoord].settings``): ``formulation`` (index1 | maggi | index3),
``method`` (dop853 | dopri5 | rk4 | trapezoidal | DOP853 | RK45 | Radau | LSODA | BDF), ``rtol``,
``atol``, ``h`` (fixed step, s; required for rk4 and trapezoidal) and the formulation options
of :data:`natcoord.formulations.DEFAULT_OPTIONS` (``stabilization``, ``linsolve``,
``penalty``, ``compiled``, ...).

The default (index1, dop853) runs as one compiled numba loop (:mod:`natcoord.kernels`); its
compile or cache-load time goes into ``build_time_s`` (and ``counters["compile_time_s"]``),
never into ``wall_time_s``.
"""

from __future__ import annotations

import time

import numpy as np

from .. import __version__
from ..dynamics import integrate
from ..formulations import DEFAULT_OPTIONS
from ..kinematics import initial_state
from ..mechanism import Case
from ..model import J2, build_model
from ..result import Motion
from .base import EngineRun, merged

NAME = "natcoord"
PACKAGE = "natcoord"
DEFAULTS = {"formulation": "index1", "method": "dop853", "rtol": 1e-12, "atol": 1e-14,
            "h": None, "coordinates": "joints"}


def version() -> str:
    return __version__


def run(case: Case, init, settings: dict) -> EngineRun:
    s = {k: v for k, v in merged(DEFAULTS, settings).items()
         if k not in ("reference", "reference_check")}  # used by `natcoord reference update`
    unknown = sorted(set(s) - set(DEFAULTS) - set(DEFAULT_OPTIONS))
    if unknown:
        raise ValueError(f"natcoord settings: unknown key {unknown[0]!r}; keys are "
                         f"{', '.join([*DEFAULTS, *DEFAULT_OPTIONS])}")
    if case.reference_frame:
        return _run_reference_frame(case, s)
    t0 = time.perf_counter()
    model = build_model(case)
    state = initial_state(model)
    compile_s = 0.0
    if s.get("compiled", True) and s["formulation"] == "index1" and s["h"] is None:
        from .. import kernels
        compile_s = kernels.ensure_compiled()  # cold compile or cache load: build, not wall
    build = time.perf_counter() - t0
    options = {k: v for k, v in s.items() if k in DEFAULT_OPTIONS}
    method = s["method"]
    if s["formulation"] == "index3" and method == DEFAULTS["method"]:
        method = "trapezoidal"
    sol = integrate(model, state, case.times, formulation=s["formulation"], method=method,
                    rtol=s["rtol"], atol=s["atol"], h=s["h"], **options)
    counters = sol.counters | {"compile_time_s": compile_s}
    return EngineRun(motion_of(model, sol), build, sol.wall_time_s, sol.counters["steps"], s,
                     counters)


def motion_of(model, sol) -> Motion:
    """Neutral motion from a natcoord solution (accelerations and driver efforts included)."""
    origin, angle, velocity, omega, acc, alpha = {}, {}, {}, {}, {}, {}
    for name, b in model.bodies.items():
        origin[name], angle[name], velocity[name], omega[name] = model.body_pose(
            name, sol.q, sol.qd)
        C0 = model.point_map(name, np.zeros(2))[:, :-1]
        if b.p_j is None:  # particle: its frame origin is its point translated
            C0 = np.zeros((2, model.n))
            C0[:, b.cols] = np.eye(2)
            alpha[name] = np.zeros(len(sol.t))
        else:  # alpha = (d x d_ddot) / |d|^2 for d = r_j - r_i (d . d_dot = 0)
            d = sol.q[:, b.cols[2:]] - sol.q[:, b.cols[:2]]
            ddd = sol.qdd[:, b.cols[2:]] - sol.qdd[:, b.cols[:2]]
            alpha[name] = np.sum((d @ J2.T) * ddd, 1) / np.sum(d * d, 1)
        acc[name] = sol.qdd @ C0.T
    forces = {name: j.force(sol.lam, sol.q) for name, j in model.joints.items()}
    m0 = model.constraints.m
    efforts = {d.name: d.effort(sol.lam[:, m0 + k], sol.q, sol.t)
               for k, d in enumerate(getattr(model, "drivers", ()))}
    return Motion(sol.t, origin, angle, velocity, omega, forces, acc, alpha, efforts)


def _run_reference_frame(case: Case, s: dict) -> EngineRun:
    """Reference-frame cases (3-D, rods, springs): :mod:`natcoord.casemodel`, every
    reaction method of the case, and the channels N = ker Phi_q^T leaves undetermined."""
    from .. import casemodel

    t0 = time.perf_counter()
    cm = casemodel.build(case, s["coordinates"])
    state = casemodel.initial_state(cm)
    build = time.perf_counter() - t0
    options = {k: v for k, v in s.items() if k in DEFAULT_OPTIONS}
    method = s["method"]
    if s["formulation"] == "index3" and method == DEFAULTS["method"]:
        method = "trapezoidal"
    sol = integrate(cm.model, state, case.times, formulation=s["formulation"], method=method,
                    rtol=s["rtol"], atol=s["atol"], h=s["h"], **options)
    lams = casemodel.reactions_by_method(cm, sol)
    motions = {name: casemodel.motion(cm, sol, lam) for name, lam in lams.items()}
    first = next(iter(lams))
    diag = casemodel.diagnostics(cm, sol.q[0])
    counters = sol.counters | diag | {
        "undetermined": casemodel.undetermined(cm, sol, lams[first]),
        "reaction_methods": list(lams), "coordinates": s["coordinates"]}
    notes = [f"natural coordinates ({s['coordinates']}): {diag['n']} coordinates, "
             f"{diag['m']} constraints of rank {diag['rank']}: {diag['dof']} DOF, "
             f"{diag['redundant']} redundant; channel values by the {first} reactions"]
    return EngineRun(motions[first], build, sol.wall_time_s, sol.counters["steps"], s,
                     counters, notes, motions)
