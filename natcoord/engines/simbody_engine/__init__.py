"""Simbody 3.9 as an engine, through the bindings of the ``opensim`` 4.6 wheel: an OpenSim
Model (whose components become Simbody mobilized bodies, constraints and forces), exact
holonomic constraints, an error-controlled Simbody integrator driven by OpenSim's Manager.

Every case goes through one builder (:mod:`.model`): a 2-D case is lifted into 3-D by
:mod:`natcoord.engines.planar` and dropped back there; body points are in each body's own
frame and its pose and rates at t = 0 come from ``init[body]``.

Model
-----
* Tree: :func:`natcoord.engines.tree.point_loop_tree` (loops are cut at revolute or
  spherical joints; a prismatic joint stays in the tree). Revolute -> ``PinJoint``,
  prismatic -> ``SliderJoint`` (the parent frame sits where the child's point is at t = 0),
  spherical -> ``BallJoint``, universal -> ``UniversalJoint`` (first axis on the tree
  parent); cylindrical: Unsupported (no OpenSim joint wired up). Joint frames are at the
  joint point, their Z (pin) or X (slider, universal) along the axis, so every coordinate
  is 0 at t = 0; speeds come from the relative rates and the start is checked against
  ``init`` (1e-9). A body no joint reaches: ``PlanarJoint`` (2-D) or ``FreeJoint``.
* Inertia about the centre of mass in body axes, exact (a point mass or a slender rod keeps
  its singular tensor when it cannot turn about the missing axis); a particle gets
  ``particle_inertia`` kg m^2 per kg, which acts only when it can turn.
* Loops: ``PointConstraint`` at the joint point. A 3-D loop revolute whose axis the tree
  path does not keep aligned needs ``loop_axis_offset`` > 0 (m): a second PointConstraint
  that far along the axis (one axial row redundant; the joint force is the sum of both);
  otherwise Unsupported (a WeldConstraint would lock it). Massless
  rods: ``ConstantDistanceConstraint`` (exact, no substitute body).
* Springs: ``ExpressionBasedPointToPointForce`` with expression ``k*(d-l0)+c*ddot``
  (positive pulls the points together). Constant loads: ``PrescribedForce`` with constant
  functions, force in world axes at a body point.
* Drivers: the driven coordinate is prescribed (``Coordinate.setPrescribedFunction``,
  Simbody's PrescribedMotion): an angle driver on a body pinned to the ground, or a
  coordinate driver on a body sliding on the ground along that world axis; anything else is
  Unsupported. Its effort is the mobilizer reaction along the joint axis.

Reactions
---------
Tree joints: ``Joint.calcReactionOnChildExpressedInGround`` (Simbody's mobilizer reaction,
constraint forces included: the force of the tree parent on the child, world axes), signed
by :func:`natcoord.engines.tree.tree_orientation`. Loops and rods:
``Constraint.calcConstraintForces`` fills one [moment, force] per constrained body, in the
order the bodies were given (ground included), in ground axes, as *minus* the force applied
(checked on a pendulum hung by a PointConstraint listed either way round). Redundant
constraints (a planar PointConstraint's out-of-plane row, five_bar's couplers,
parallelogram_3d's rods) are fine: Simbody's multipliers are the least-squares
(minimum-norm) solution, e.g. five_bar N34 : N56 = 1 : 2.

Integration
-----------
``integrator`` (rk_merson default; rk_feldberg, rk3, rk2, cpodes for stiff springs, ...)
at relative ``accuracy`` with ``constraint_tolerance``, or a fixed ``dt``; the Manager
integrates to each sample time exactly and the state there is sampled. ``wall_time_s`` is
the Manager's initialize and integrate calls alone; the readout at the sample times
(accelerations, reactions) goes to ``counters["readout_time_s"]``.

Traps
-----
* ``opensim.simbody`` wraps only Simbody's math types, ``State`` and
  ``SimbodyMatterSubsystem``: no MobilizedBody_* or Constraint_* classes, so models are
  built from OpenSim components.
* ``Manager.getIntegrator()`` is an unwrapped SwigPyObject (no step counts): steps are
  counted from the Manager's in-memory state storage (one row per internal step; the
  states trajectory counts the same but copies a whole State per step, ~400 us).
* OpenSim writes ``opensim.log`` into the working directory and logs to stdout unless its
  Logger's file sink is removed and its level set to Off (done before anything is built).
* ``ExpressionBasedPointToPointForce`` takes body *names* (5 arguments), not frames.
* A prescribed coordinate's speed is only overwritten when the integrator starts: set it
  anyway so that the state can be checked against ``init``.
* five_bar at accuracy 1e-10 stalls at its -180 deg singular position (no progress in
  100 s; ``step_limit`` and ``min_step`` do not stop it: the Manager keeps calling the
  integrator), while 1e-9 passes in 0.6 s; the runner's time limit turns a stall into
  ``failed``. ``setIntegratorAccuracy`` accepts a negative value silently.
"""

from __future__ import annotations

import time

from ..base import EngineRun, merged
from ..capabilities import Capabilities, drivers_off_ground_joints, misaligned_loop_revolutes
from ..schema import C_INT_MAX, Setting, defaults, particle_inertia
from .simulate import INTEGRATORS

NAME = "simbody"
PACKAGE = "opensim"
SETTINGS = (
    Setting("integrator", "choice", "rk_merson", "Simbody's integrator (cpodes for stiff "
            "springs; explicit_euler, rk2, ... with a fixed dt)", choices=tuple(INTEGRATORS)),
    Setting("accuracy", "number", 1e-10, "the integrator's relative accuracy "
            "(error-controlled methods)", exclusive_minimum=0.0),
    Setting("constraint_tolerance", "number", 1e-12, "projection tolerance of the "
            "constraint manifold", exclusive_minimum=0.0),
    Setting("dt", "number", None, "a fixed step instead of error control (fixed-step "
            "integrators; none: error-controlled at accuracy)", "s", exclusive_minimum=0.0),
    Setting("step_limit", "integer", 100_000, "internal steps per output interval before "
            "Simbody gives up (a stall fails fast)", minimum=1, maximum=C_INT_MAX),
    Setting("loop_axis_offset", "number", 0.0, "> 0 holds a loop-closing 3-D revolute's "
            "axis by a second PointConstraint this far along it (0: such a loop is "
            "unsupported)", "m", minimum=0.0),
    Setting("min_step", "number", 1e-12, "a step Simbody would shrink below this is an "
            "error, not a stall", "s", exclusive_minimum=0.0),
    particle_inertia(True),
    Setting("velocity_check", "number", 1e-9, "the start must match natcoord's initial "
            "rates to this (m/s, rad/s)", exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)



def _rules(case, s: dict) -> list[str]:
    """Drivers as prescribed coordinates of a pin or slider to the ground, loop revolutes
    whose axis the tree does not keep (model.py)."""
    out = [f"driver {d!r}: a prescribed coordinate needs the driven body on a pin (angle) "
           "or slider (coordinate) to the ground"
           for d, _, _ in drivers_off_ground_joints(case, CAPABILITIES)]
    if not s.get("loop_axis_offset", 0.0) > 0:
        out += [f"loop-closing 3-D revolute {n!r}: the tree does not keep its axis aligned, "
                "and a WeldConstraint would lock its rotation (setting loop_axis_offset > 0: "
                "a second PointConstraint along the axis)"
                for n in misaligned_loop_revolutes(case, CAPABILITIES)]
    return out


CAPABILITIES = Capabilities(
    loops="rigid",  # PointConstraints, projected at every step
    body_loads=True,  # PrescribedForce in the body frame
    joints={"revolute", "prismatic", "spherical", "universal"},
    loop_joints={"revolute", "spherical"}, recut={"prismatic"},  # tree.point_loop_tree
    why={"joints": "no OpenSim joint is wired up for it",
         "loop_joints": "Simbody's loop constraints here pin a point (PointConstraint); a "
                        "sliding loop joint would need PointOnLine plus an orientation lock"},
    rules=_rules)

def version() -> str:
    import opensim

    return opensim.__version__


def _quiet(osim) -> None:
    """No opensim.log in the working directory, nothing on stdout."""
    osim.Logger.removeFileSink()
    osim.Logger.setLevel(osim.Logger.Level_Off)


def run(case, init, settings: dict) -> EngineRun:
    """Build, integrate and sample ``case`` from ``init`` (see the module docstring)."""
    import opensim as osim

    from ..planar import drop, lift_case, lift_init
    from . import model, simulate

    _quiet(osim)
    s = merged(DEFAULTS, settings)
    t0 = time.perf_counter()
    case3 = lift_case(case)
    frames = lift_init(case3, init)
    b = model.build(osim, case3, frames, case.dimension == 2, s)
    state = simulate.initial_state(osim, b, float(s["velocity_check"]))
    build_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    times = case.times
    states = simulate.integrate(osim, b, state, times, s)
    (origin, rotation, velocity, omega, accel, alpha, forces, rod_force, effort, counters,
     drift) = simulate.sample(osim, b, states, len(times))
    # wall time is the stepping alone (as every adapter's); the sample readout between the
    # Manager's calls (realizeAcceleration, reactions, through the bindings) is kept apart
    wall = counters.pop("stepping_time_s")
    counters["readout_time_s"] = time.perf_counter() - t0 - wall
    notes = list(b.notes)
    what = f"fixed step {s['dt']:g} s" if s.get("dt") else f"accuracy {s['accuracy']:g}"
    notes.append(f"Simbody {s['integrator']}, {what}, constraint tolerance "
                 f"{s['constraint_tolerance']:g}, via OpenSim Manager")
    counters |= {"qerr_max": float(drift[0]), "uerr_max": float(drift[1])}
    motion = drop(case, times, origin, rotation, velocity, omega, forces,
                  acceleration=accel, alpha=alpha, driver_effort=effort, rod_force=rod_force)
    return EngineRun(motion, build_time, wall, counters["steps"], s, counters, notes)


__all__ = ["DEFAULTS", "NAME", "PACKAGE", "SETTINGS", "run", "version"]
