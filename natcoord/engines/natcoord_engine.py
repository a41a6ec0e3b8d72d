"""natcoord's own solver as an engine: natural coordinates, formulation chosen by settings.

Settings (``[engines.natcoord].settings``): ``formulation`` (index1 | maggi | index3),
``method`` (dop853 | dopri5 | rk4 | trapezoidal | DOP853 | RK45 | Radau | LSODA | BDF), ``rtol``,
``atol``, ``h`` (fixed step, s; required for rk4 and trapezoidal), ``coordinates`` (joints |
shared, see :mod:`natcoord.casemodel`) and the formulation options of
:data:`natcoord.formulations.DEFAULT_OPTIONS` (``stabilization``, ``linsolve``, ``penalty``,
``compiled``, ...).

Every case runs the same way: the case's natural-coordinate model, started from the
assembled state ``init`` (q, qd), every reaction method of the case, and the channels that
N = ker Phi_q^T leaves undetermined. The default (index1, dop853) runs as one compiled numba
loop (:mod:`natcoord.kernels`); its compile or cache-load time goes into ``build_time_s``
(and ``counters["compile_time_s"]``), never into ``wall_time_s``.
"""

from __future__ import annotations

import time

from .. import __version__, casemodel
from ..dynamics import integrate
from ..formulations import DEFAULT_OPTIONS
from ..kinematics import State
from ..mechanism import Case
from .base import EngineRun, InitialState, merged

NAME = "natcoord"
PACKAGE = "natcoord"
DEFAULTS = {"formulation": "index1", "method": "dop853", "rtol": 1e-12, "atol": 1e-14,
            "h": None, "coordinates": "joints"}


def version() -> str:
    return __version__


def settings_of(settings: dict) -> dict:
    """The case's settings over the defaults; unknown keys are refused."""
    s = {k: v for k, v in merged(DEFAULTS, settings).items()
         if k not in ("reference", "reference_check")}  # used by `natcoord reference update`
    unknown = sorted(set(s) - set(DEFAULTS) - set(DEFAULT_OPTIONS))
    if unknown:
        raise ValueError(f"natcoord settings: unknown key {unknown[0]!r}; keys are "
                         f"{', '.join([*DEFAULTS, *DEFAULT_OPTIONS])}")
    return s


def run(case: Case, init: InitialState | None, settings: dict) -> EngineRun:
    """Integrate the case from ``init`` (assembled here when None)."""
    s = settings_of(settings)
    t0 = time.perf_counter()
    cm = casemodel.build(case, s["coordinates"])
    state = State(init.q, init.qd) if init is not None else casemodel.initial_state(cm)
    build = time.perf_counter() - t0
    options = {k: v for k, v in s.items() if k in DEFAULT_OPTIONS}
    method = s["method"]
    if s["formulation"] == "index3" and method == DEFAULTS["method"]:
        method = "trapezoidal"
    sol = integrate(cm.model, state, case.times, formulation=s["formulation"], method=method,
                    rtol=s["rtol"], atol=s["atol"], h=s["h"], **options)
    build += sol.counters["compile_time_s"]  # a cold compile or cache load: build, not wall
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
                     counters, notes, motions if len(motions) > 1 or case.reactions else {})
