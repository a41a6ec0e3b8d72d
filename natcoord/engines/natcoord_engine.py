"""natcoord's own solver as an engine: natural coordinates, formulation chosen by settings.

Settings (``[engines.natcoord].settings``): ``coordinates`` (joints | shared, see
:mod:`natcoord.casemodel`) and the solver, read by
:meth:`natcoord.solver.Solver.from_settings`: ``formulation`` (index1 | maggi | index3),
``method`` (dop853 | dopri5 | rk4 | trapezoidal | DOP853 | RK45 | Radau | LSODA | BDF),
``rtol`` and ``atol`` or a fixed step ``h`` (s), and the formulation's options
(``stabilization``, ``linsolve``, ``penalty``, ``compiled``, ...). ``reference`` and
``reference_check`` are solver settings for ``natcoord reference update``.

Every case runs the same way: the case's natural-coordinate model, started from the
assembled state ``init`` (q, qd), every reaction method of the case, and the channels that
N = ker Phi_q^T leaves undetermined. The default (index1, dop853) runs as one compiled numba
loop (:mod:`natcoord.kernels`); its compile or cache-load time goes into ``build_time_s``
(and ``counters["compile_time_s"]``), never into ``wall_time_s``.
"""

from __future__ import annotations

import time

from .. import __version__, casemodel, outputs
from ..dynamics import integrate
from ..kinematics import State
from ..mechanism import Case
from ..solver import case_solver
from .base import EngineRun, InitialState

NAME = "natcoord"
PACKAGE = "natcoord"


def version() -> str:
    return __version__


def run(case: Case, init: InitialState | None, settings: dict) -> EngineRun:
    """Integrate the case from ``init`` (assembled here when None, or when settings ask
    for other coordinates than ``init`` was assembled in)."""
    solver = case_solver(settings)
    coordinates = settings.get("coordinates", "joints")
    t0 = time.perf_counter()
    cm = casemodel.build(case, coordinates)
    fits = init is not None and init.coordinates == coordinates
    state = State(init.q, init.qd) if fits else casemodel.initial_state(cm)
    build = time.perf_counter() - t0
    sol = integrate(cm.model, state, case.times, solver)
    # a cold compile or cache load and the sparsity plan: build time, not wall time
    build += sol.counters["compile_time_s"] + sol.counters["plan_time_s"]
    lams = outputs.reactions_by_method(cm, sol)
    motions = {name: outputs.motion(cm, sol, lam) for name, lam in lams.items()}
    first = next(iter(lams))
    diag = outputs.diagnostics(cm, sol.q[0])
    counters = sol.counters | diag | {
        "undetermined": outputs.undetermined(cm, sol, lams[first]),
        "reaction_methods": list(lams), "coordinates": coordinates}
    notes = [f"natural coordinates ({coordinates}): {diag['n']} coordinates, "
             f"{diag['m']} constraints of rank {diag['rank']}: {diag['dof']} DOF, "
             f"{diag['redundant']} redundant; channel values by the {first} reactions"]
    s = {"coordinates": coordinates, **solver.settings()}
    return EngineRun(motions[first], build, sol.wall_time_s, sol.counters["steps"], s,
                     counters, notes, motions if len(motions) > 1 or case.reactions else {})
