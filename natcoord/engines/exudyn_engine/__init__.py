"""Exudyn as an engine: redundant (absolute) coordinates, implicit index-3 generalized-alpha.

Every body is a free node at its centre of mass whose frame is the body frame; every joint,
rod, spring and driver is a constraint or connector, so loops need no tree. Output is read
from Exudyn sensors stored in memory at the case's output interval. One builder for every
case: the case's dimension only picks the element set (:data:`.bodies.ELEMENTS`,
:data:`.joints.JOINTS`); every body starts from its assembled frame state ``init[body]``.

Conventions handled here (measured with exudyn 1.13.6, see tests/test_engine_exudyn.py),
detailed where each element is built:

* 2-D cases keep Exudyn's 2-D elements (:class:`.bodies.Planar`): building them with the
  3-D ones was measured to cost 4-11x per step and, on ``pendulum`` (a body without
  inertia, which a 3-D rigid body cannot take unpadded), to triple the reaction error
  (O_x 3.3e-3 -> 1.0e-2 N, over its 7e-3 N tolerance); four_bar came out the same
  (7.6e-5 vs 7.7e-5 rad).
* Revolute (2-D ``ObjectJointRevolute2D``, 3-D ``ObjectJointRevoluteZ`` with joint frames)
  and spherical joints: reaction = minus the force output on the first marker's body.
* 2-D prismatic: ``ObjectJointPrismatic2D`` with markers [second, first]; reaction =
  +lambda_0 times the first body's normal, lambda_0 read by a sensor user function. A
  particle in one becomes a 2-D rigid node with its rotation locked.
* 3-D prismatic, cylindrical, universal: ``ObjectJointGeneric`` with constrained axes per
  joint type in a joint frame with x on the case's axis; reaction as the 3-D revolute's.
* Massless rods ``ObjectConnectorDistance`` (exact), spring-dampers
  ``ObjectConnectorSpringDamper``; drivers ``CoordinateConstraint`` with an
  ``offsetUserFunction`` (exact rheonomic), effort = -Force output.
* Redundant constraints (rods closing a loop, every 3-D case): the Jacobian is singular,
  so the linear solver is ``EigenDense`` with ``ignoreSingularJacobian`` (the split of the
  redundant multipliers is whatever its pivoting picks).
"""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import GROUND, Case
from ...errors import Unsupported
from ...outputs.result import Motion
from ..base import EngineRun, merged
from ..capabilities import Capabilities
from ..schema import Setting, defaults
from .bodies import AXIAL_INERTIA

NAME = "exudyn"
PACKAGE = "exudyn"
SETTINGS = (
    Setting("solver", "choice", "generalized_alpha", "Exudyn's solver: implicit "
            "generalized-alpha, index 3 (the only one offered: the index-2 trapezoidal "
            "variants drift by ~h^2)", choices=("generalized_alpha",)),
    Setting("dt", "number", 1e-3, "fixed time step h; must divide the output interval", "s",
            exclusive_minimum=0.0),
    Setting("spectral_radius", "number", 0.9, "rho_inf of generalized-alpha (1.0 makes the "
            "reactions noisy)", minimum=0.0, maximum=1.0),
    Setting("newton_rtol", "number", 1e-10, "Newton's relative tolerance (Exudyn's default "
            "1e-8)", exclusive_minimum=0.0),
    Setting("newton_atol", "number", 1e-10, "Newton's absolute tolerance",
            exclusive_minimum=0.0),
    Setting("modified_newton", "boolean", False, "modified Newton (Jacobian kept over "
            "iterations; Exudyn's default) instead of full Newton (~2 iterations a step)"),
    Setting("linear_solver", "choice", "auto", "auto: EigenDense with "
            "ignoreSingularJacobian when the constraints may be redundant (rods, 3-D), else "
            "Exudyn's default EXUdense; default; singular (EigenDense, "
            "ignoreSingularJacobian); sparse (EigenSparse: many bodies)",
            choices=("auto", "default", "singular", "sparse")),
    Setting("axial_inertia", "number", AXIAL_INERTIA, "3-D uniform rods: inertia added about "
            "their own axis, times their largest moment", exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)

COORDINATES = {2: "redundant absolute coordinates: one NodeRigidBody2D + ObjectRigidBody2D "
                  "per body at its centre of mass; every joint is a constraint (no tree)",
               3: "redundant absolute coordinates: one NodeRigidBodyEP (Euler parameters) + "
                  "ObjectRigidBody per body at its centre of mass; every joint is a "
                  "constraint"}



def _rules(case: Case, s: dict) -> list[str]:
    """The pre-build checks (:func:`_check`) that are not settings errors."""
    try:
        _check(case, {**DEFAULTS, **s})
    except Unsupported as e:
        return [str(e)]
    except ValueError:  # a bad setting is the loader's to report, not a capability
        pass
    return []


CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="rigid",  # every joint a constraint, index-3 generalized-alpha: no tree, no cut
    body_loads=True,  # LoadTorqueVector / LoadForceVector with bodyFixed
    joints={"revolute", "prismatic", "spherical", "cylindrical", "universal"},
    particles={2},
    why={"particles": "3-D particles are not modelled by the Exudyn adapter"},
    rules=_rules)

def version() -> str:
    import exudyn

    return exudyn.__version__


def _check(case: Case, s: dict) -> None:
    """Raise Unsupported (or ValueError for bad settings) before anything is built."""
    from . import drivers
    from .bodies import ELEMENTS
    from .joints import JOINTS

    if case.dimension not in ELEMENTS:
        raise Unsupported(f"{case.name} is {case.dimension}-D: the Exudyn adapter models "
                          "2-D and 3-D cases")
    if s["solver"] != "generalized_alpha":
        raise Unsupported(f"solver {s['solver']!r}: only 'generalized_alpha' (index 3) is "
                          "offered; the index-2 trapezoidal variants drift by ~h^2")
    if s["linear_solver"] not in ("auto", "default", "singular", "sparse"):
        raise ValueError(f"linear_solver {s['linear_solver']!r}: 'auto', 'default', "
                         "'singular' or 'sparse'")
    for j in case.joints:
        if j.type not in JOINTS[case.dimension]:
            raise Unsupported(f"joint {j.name}: type {j.type!r} is not modelled in "
                              f"{case.dimension}-D by the Exudyn adapter")
    for f in case.forces:
        if f.type not in ("torque", "force"):
            raise Unsupported(f"force on {f.body}: type {f.type!r} is not modelled")
    ELEMENTS[case.dimension].check(case)
    drivers.check(case)


def _loads(build, case: Case) -> None:
    """Gravity on every body; applied torques and forces at body points (world axes, or
    ``bodyFixed`` for ``frame = "body"``)."""
    from .system import v3

    ei, mbs = build.ei, build.mbs
    for b in case.bodies:
        if any(case.gravity != 0):
            mm = mbs.AddMarker(ei.MarkerBodyMass(bodyNumber=build.objs[b.name]))
            mbs.AddLoad(ei.LoadMassProportional(markerNumber=mm, loadVector=v3(case.gravity)))
    for f in case.forces:
        if f.body == GROUND:
            continue
        fixed = f.frame == "body"  # bodyFixed: in the node's frame, the body's own
        if f.type == "torque":  # a scalar (2-D) is about z
            mr = mbs.AddMarker(ei.MarkerBodyRigid(bodyNumber=build.objs[f.body]))
            value = f.value if np.ndim(f.value) else [0.0, 0.0, f.value]
            mbs.AddLoad(ei.LoadTorqueVector(markerNumber=mr, loadVector=v3(value),
                                            bodyFixed=fixed))
        else:  # a follower force needs the marker's orientation: a rigid marker
            mbs.AddLoad(ei.LoadForceVector(markerNumber=build.marker(f.body, f.point,
                                                                     rigid=fixed),
                                           loadVector=v3(f.value), bodyFixed=fixed))


def run(case: Case, init, settings: dict) -> EngineRun:
    s = merged(DEFAULTS, settings)
    _check(case, s)
    from .solve import step_plan

    h, n_steps = step_plan(case, s)

    import exudyn as exu
    from exudyn import itemInterface as ei

    from . import drivers
    from .bodies import ELEMENTS
    from .joints import JOINTS, connectors
    from .solve import engine_run, integrator_notes, solve, stored
    from .system import Build

    kit, joint_kits = ELEMENTS[case.dimension], JOINTS[case.dimension]
    t0 = time.perf_counter()
    build = Build(exu, ei, case, init, s)
    build.notes += [COORDINATES[case.dimension], *integrator_notes(case, s, h)]
    oriented = {b for j in case.joints if j.type == "prismatic" for b in j.bodies}
    for b in case.bodies:
        build.nodes[b.name], build.objs[b.name] = kit.add(build, b, b.name in oriented)
    kit.note(build, oriented)
    _loads(build, case)
    reactions = {j.name: joint_kits[j.type](build, j) for j in case.joints}
    tensions = connectors(build)
    efforts = {d.name: drivers.add(build, d) for d in case.drivers}
    sensors = {b.name: kit.sensors(build, b) for b in case.bodies}
    build.mbs.Assemble()
    build_time = time.perf_counter() - t0

    wall, solver = solve(exu, build.mbs, case, s, n_steps, h)

    def get(sn: int):
        return stored(build.mbs, case, sn)

    frames = {b.name: kit.read(get, b, sensors[b.name]) for b in case.bodies}
    m = Motion(case.times.copy(),
               {n: f["origin"] for n, f in frames.items()},
               {n: f["angle"] for n, f in frames.items() if "angle" in f},
               {n: f["velocity"] for n, f in frames.items()},
               {n: f["omega"] for n, f in frames.items()},
               {n: read(get, frames) for n, read in reactions.items()},
               acceleration={n: f["acceleration"] for n, f in frames.items()
                             if "acceleration" in f},
               alpha={n: f["alpha"] for n, f in frames.items() if "alpha" in f},
               driver_effort={n: read(get) for n, read in efforts.items()},
               rotation={n: f["rotation"] for n, f in frames.items() if "rotation" in f},
               rod_force={n: read(get) for n, read in tensions.items()})
    return engine_run(case, s, m, build_time, wall, solver, n_steps, build.notes)
