"""natcoord's own solver as an engine: natural coordinates, formulation chosen by settings.

Settings (``[engines.natcoord].settings``): ``coordinates`` (joints | shared, see
:mod:`natcoord.model.casemodel`) and the solver, read by
:meth:`natcoord.dynamics.solver.Solver.from_settings`: ``formulation`` (index1 | maggi | index3),
``method`` (dop853 | dopri5 | rk4 | trapezoidal | DOP853 | RK45 | Radau | LSODA | BDF),
``rtol`` and ``atol`` or a fixed step ``h`` (s), and the formulation's options
(``stabilization``, ``linsolve``, ``penalty``, ``compiled``, ...). ``reference`` and
``reference_check`` are solver settings for ``natcoord reference update``. They are declared
in :data:`SETTINGS` (checked when a case is loaded; combinations by :func:`check_settings`).
The solver and the model are imported when a run starts, not with this module.

Every case runs the same way: the case's natural-coordinate model, started from the
assembled state ``init`` (q, qd), every reaction method of the case, and the channels that
N = ker Phi_q^T leaves undetermined. The default (index1, dop853) runs as one compiled numba
loop (:mod:`natcoord.compiled.index1`); its compile or cache-load time goes into ``build_time_s``
(and ``counters["compile_time_s"]``), never into ``wall_time_s``.
"""

from __future__ import annotations

import time

from .. import __version__
from ..case.mechanism import Case
from ..dynamics.solver import (
    DEFAULT_METHOD,
    DEFAULT_TOLERANCES,
    FORMULATIONS,
    METHODS,
    REFERENCE_KEYS,
    Formulation,
    Index1,
    Index3,
    Maggi,
    case_solver,
)
from ..model.casemodel import COORDINATES
from .base import EngineRun, InitialState
from .capabilities import Capabilities
from .schema import Setting

NAME = "natcoord"
PACKAGE = "natcoord"

_POSITIVE = {"exclusive_minimum": 0.0}
SOLVER_SETTINGS = (
    Setting("formulation", "choice", "index1", "the equations of motion: index1 "
            "(Lagrange with acceleration constraints), maggi (null space), index3 "
            "(augmented Lagrangian, trapezoidal)", choices=tuple(FORMULATIONS)),
    Setting("method", "choice", None, "the integrator (none: "
            + ", ".join(f"{m} for {f}" for f, m in DEFAULT_METHOD.items()) + ")",
            choices=METHODS),
    Setting("rtol", "number", DEFAULT_TOLERANCES["rtol"], "relative tolerance of adaptive "
            "steps (at most 1: a relative error past 100 % controls nothing)",
            exclusive_minimum=0.0, maximum=1.0),
    Setting("atol", "number", DEFAULT_TOLERANCES["atol"], "absolute tolerance of adaptive "
            "steps (m, m/s)", **_POSITIVE),
    Setting("h", "number", None, "a fixed step instead of tolerances (rk4, trapezoidal; "
            "none: adaptive): the longest step, each output interval taken in equal steps "
            "of at most h", "s", **_POSITIVE),
    Setting("project_tol", "number", Formulation.project_tol, "tolerance of the "
            "projections on |Phi|", "m", **_POSITIVE),
    Setting("newton_tol", "number", Formulation.newton_tol, "Newton tolerance on |Phi|", "m",
            **_POSITIVE),
    Setting("rank_tol", "number", Formulation.rank_tol, "relative rank tolerance of Phi_q "
            "(below 1: a pivot is relative to the largest)", exclusive_minimum=0.0,
            exclusive_maximum=1.0),
    Setting("compiled", "boolean", Formulation.compiled, "run the integration as one "
            "compiled numba loop where the model allows"),
    Setting("stabilization", "choice", Index1.stabilization, "index1: drift control",
            choices=("projection", "baumgarte", "none")),
    Setting("baumgarte", "numbers", list(Index1.baumgarte), "index1: Baumgarte's (alpha, "
            "beta)", "1/s", length=2, **_POSITIVE),
    Setting("linsolve", "choice", Index1.linsolve, "index1: the linear solve (auto, Schur "
            "complement or QR)", choices=("auto", "schur", "qr")),
    Setting("generated", "boolean", Index1.generated, "index1: kernels written out for the "
            "model on its Schur path; maggi: Phi and accelerations by them"),
    Setting("repartition_growth", "number", Maggi.repartition_growth, "maggi: re-partition "
            "when max|R^d| grows by this factor", **_POSITIVE),
    Setting("penalty", "number", Index3.penalty, "index3: penalty alpha h^2/4 relative to "
            "max|M|", **_POSITIVE),
)
CAPABILITIES = Capabilities(loops="rigid", body_loads=True,  # every element of a case file
                            step="h", step_with={"method": "rk4"})
SETTINGS = (
    Setting("coordinates", "choice", "joints", "joints: every body its own points, joints "
            "as rows; shared: point joints as shared points (the paper's way)",
            choices=COORDINATES),
    *SOLVER_SETTINGS,
    *(Setting(key, "table", None, f"solver settings of `natcoord reference update`'s "
              f"{'stored reference' if key == 'reference' else 'check run'} (the keys "
              "above but coordinates)", fields=SOLVER_SETTINGS) for key in REFERENCE_KEYS),
)


def check_settings(settings: dict) -> list[tuple[str, str]]:
    """The settings, and its ``reference`` and ``reference_check`` tables, must each make
    a valid solver (formulation, integrator and step control that fit together)."""
    out = []
    for key in ("", *REFERENCE_KEYS):
        try:
            case_solver(settings if not key else settings.get(key, {}))
        except (ValueError, TypeError) as e:
            out.append((key or "", str(e)))
    return out


def version() -> str:
    return __version__


def run(case: Case, init: InitialState | None, settings: dict) -> EngineRun:
    """Integrate the case from ``init`` (assembled here when None, or when settings ask
    for other coordinates than ``init`` was assembled in)."""
    from ..dynamics.forward import integrate
    from ..dynamics.integrators import substeps
    from ..model import casemodel
    from ..model.kinematics import State
    from ..outputs import channels as outputs

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
    motions = {name: outputs.motion(cm, sol, r.lam) for name, r in lams.items()}
    first = next(iter(lams))
    diag = outputs.diagnostics(cm, sol.q[0])
    counters = sol.counters | diag | {
        "undetermined": outputs.undetermined(cm, sol, lams[first]),
        "reaction_methods": list(lams), "coordinates": coordinates}
    notes = [f"natural coordinates ({coordinates}): {diag['n']} coordinates, "
             f"{diag['m']} constraints of rank {diag['rank']}: {diag['dof']} DOF, "
             f"{diag['redundant']} redundant; channel values by the {first} reactions"]
    if solver.h is not None and len(case.times) > 1:
        span = float(case.times[1] - case.times[0])
        k = substeps(span, solver.h)
        notes.append(f"fixed steps of {span / k:.6g} s: {k} per output interval of {span:g} s"
                     f" (h = {solver.h:g} s is the longest step)")
    s = {"coordinates": coordinates, **solver.settings()}
    return EngineRun(motions[first], build, sol.wall_time_s, sol.counters["steps"], s,
                     counters, notes, motions if len(motions) > 1 or case.reactions else {})
