"""PyBullet as an engine: a fixed-base multibody (Featherstone, reduced coordinates) with its
loops closed by point-to-point constraints, stepped by PyBullet's semi-implicit Euler.

A 2-D case is lifted into 3-D (:mod:`natcoord.engines.planar`), built as one multibody
(:mod:`.multibody`), stepped and sampled (:mod:`.stepping`), its reactions read over the
step after each sample (:mod:`.reactions`), and dropped back to a planar Motion.

Modelling choices (repeated in ``EngineRun.notes``):

* Tree: :func:`natcoord.engines.tree.point_loop_tree` (a loop cut at a revolute or
  spherical joint, never at a slide). Tree joints revolute, prismatic, spherical; a
  particle on a revolute or spherical tree joint is welded (a fixed joint: exact).
* Loops: ``JOINT_POINT2POINT`` user constraints, three rows at the joint point (a loop
  revolute's axis is left to the tree, as in MuJoCo). They are velocity-level rows solved
  by PyBullet's iterative constraint solver each step, with the position gap fed back by
  ``erp``: soft, so the motion is first order in dt (the step is semi-implicit Euler and
  the gap is closed over ~1/erp steps). four_bar, 1 s, crank angle against the reference:
  2e-3 rad at dt 1e-3, 2e-4 at 1e-4.
* PyBullet's own defaults that change the physics are overridden, each one tested
  (:data:`.multibody.TRAPS`): link damping, velocity motors, inertia from shapes,
  constraint pivots relative to the centre of mass, the 100 rad/s joint speed cap.
* A 3-D loop-closing revolute whose axis the tree does not keep (Bricard) needs
  ``loop_axis_offset``: a second point-to-point constraint along the axis.
* Loads: constant torques (``applyExternalTorque``, world axes), forces at body points and
  spring-dampers (``applyExternalForce`` at the points' world positions), all evaluated at
  the start of every step: explicit, first order like the step itself.
* PyBullet returns link states in single precision after building a multibody from
  ``createMultiBody`` (link frames rounded to ~1e-7 relative): the start is checked
  against the assembled state to :data:`START_TOLERANCE`.

Unsupported, with the reason: prescribed motions (drivers), massless rods, universal and
cylindrical joints, bodies not joined to the ground, a slide that must close a loop.
"""

from __future__ import annotations

from ...case.mechanism import Case
from ...errors import Unsupported
from ..base import EngineRun, merged, steps_per_sample
from ..capabilities import Capabilities, massless, misaligned_loop_revolutes, refuse
from ..schema import C_INT_MAX, Setting, defaults, particle_inertia

NAME = "pybullet"
PACKAGE = "pybullet"
SETTINGS = (
    Setting("dt", "number", 1e-4, "time step (semi-implicit Euler, first order); must divide "
            "the case's output interval", "s", exclusive_minimum=0.0),
    Setting("solver_iterations", "integer", 100, "iterations of the constraint solver per "
            "step (setPhysicsEngineParameter numSolverIterations)", minimum=1,
            maximum=C_INT_MAX),
    Setting("residual", "number", 1e-10, "the constraint solver stops when its residual "
            "falls below this (solverResidualThreshold)", minimum=0.0),
    Setting("erp", "number", 0.5, "error reduction of the constraint solver: the fraction of "
            "a loop's position gap fed back per step (setPhysicsEngineParameter erp; "
            "changeConstraint's erp has no effect on a multibody's point-to-point rows)",
            minimum=0.0, maximum=1.0),
    Setting("max_constraint_force", "number", 1e9, "force cap of every loop constraint "
            "(changeConstraint maxForce; PyBullet's default is 500 N)", "N",
            exclusive_minimum=0.0),
    Setting("max_loop_drift", "number", 1e-3, "a loop opened wider than this is a failed "
            "run", "m", exclusive_minimum=0.0),
    Setting("loop_axis_offset", "number", 0.0, "> 0 holds a loop-closing 3-D revolute's "
            "axis by a second point-to-point constraint this far along it (0: one, a ball "
            "joint)", "m", minimum=0.0),
    particle_inertia(False, "on a slide: PyBullet needs one; its joint cannot turn it"),
    Setting("zero_inertia", "number", 1e-6, "inertia given along a zero principal axis "
            "(a slender rod's own), times the largest principal moment",
            exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)
START_TOLERANCE = 1e-6  # relative; the link frames PyBullet builds are single precision

DRIVERS_UNSUPPORTED = (
    "prescribed motions (drivers): PyBullet has no rheonomic constraint; its joint motors "
    "are velocity or PD targets with a force cap (a servo, not a prescribed motion)")
RODS_UNSUPPORTED = (
    "massless rods: PyBullet's user constraints are point-to-point, fixed, gear and "
    "prismatic; none holds a distance between two points")


def version() -> str:
    from importlib.metadata import version as dist_version

    import pybullet  # noqa: F401 - ImportError when missing

    return dist_version("pybullet")


def _rules(case: Case, s: dict) -> list[str]:
    """Bodies with mass, and what the multibody refuses (:func:`.multibody.split`: loop joints
    that hold a point; every body joined to the ground, one fixed-base multibody), and a 3-D
    loop revolute whose axis the tree does not keep when ``loop_axis_offset`` is 0 (one
    point-to-point constraint would leave the loop a degree of freedom too many)."""
    from ..planar import lift_case
    from ..tree import tree_parents
    from .multibody import GROUND, split

    out = massless(case, "PyBullet links")
    if out:
        return out
    try:
        tree_joints, _, _ = split(lift_case(case))
    except Unsupported as e:
        return [str(e)]
    reached = {GROUND} | {c for _, _, c in tree_parents(tree_joints)}
    free = [b.name for b in case.bodies if b.name not in reached]
    if free:
        return [f"bodies {', '.join(free)} are not joined to the ground: the adapter builds "
                "one fixed-base multibody"]
    if not s.get("loop_axis_offset", 0.0) > 0:
        return [f"loop-closing 3-D revolute {n!r}: the tree does not keep its axis, and one "
                "point-to-point constraint holds only the point (setting loop_axis_offset "
                "> 0: a second one along the axis)"
                for n in misaligned_loop_revolutes(case, CAPABILITIES)]
    return []


CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="soft",  # point-to-point constraints with error reduction (erp): a small gap
    joints={"revolute", "prismatic", "spherical"}, loop_joints={"revolute", "spherical"},
    recut={"prismatic"}, drivers=(), rods=False, step="dt",
    why={"drivers": DRIVERS_UNSUPPORTED.split(": ", 1)[1],
         "body_loads": "the adapter applies loads in world axes (PyBullet's LINK_FRAME is "
                       "the link's inertial frame, not the case's body frame: not wired)",
         "rods": RODS_UNSUPPORTED.split(": ", 1)[1],
         "joints": "a PyBullet multibody joint is revolute, prismatic, spherical or fixed",
         "loop_joints": "a point-to-point constraint holds a point and cannot slide"},
    rules=_rules)


def run(case: Case, init, settings: dict) -> EngineRun:
    """Simulate ``case`` from ``init`` at the case's sample times (see the module)."""
    return simulate(case, init, settings)


def simulate(case: Case, init, settings: dict, keep: tuple[str, ...] = ()) -> EngineRun:
    """:func:`run`, with ``keep`` naming PyBullet defaults left in place
    (:data:`.multibody.TRAPS`; the tests' way to show what each one does)."""
    import time

    import pybullet as pb

    from ..planar import drop, lift_case, lift_init
    from . import multibody, sampling

    s = merged(DEFAULTS, settings)
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    refuse(CAPABILITIES, case, s)
    space = lift_case(case)
    multibody.split(space)  # an unsupported loop is refused before the state is read
    frames = lift_init(case, init)
    cid = pb.connect(pb.DIRECT)
    try:
        t0 = time.perf_counter()
        pb.setGravity(*[float(g) for g in space.gravity], physicsClientId=cid)
        pb.setPhysicsEngineParameter(fixedTimeStep=dt, numSubSteps=0,
                                     numSolverIterations=int(s["solver_iterations"]),
                                     solverResidualThreshold=float(s["residual"]),
                                     erp=float(s["erp"]), physicsClientId=cid)
        built = multibody.build(pb, cid, space, frames, s, case.dimension == 2, keep)
        multibody.set_velocities(pb, cid, built, space, frames)
        build = time.perf_counter() - t0
        out, wall, n_steps, counters = sampling.simulate(pb, cid, built, space, frames, s, k)
    finally:
        pb.disconnect(physicsClientId=cid)
    counters = {"steps": n_steps, **counters}
    notes = built.notes + [f"semi-implicit Euler, dt {dt} s, {s['solver_iterations']} solver "
                           f"iterations, residual {s['residual']}, erp {s['erp']}; "
                           "reactions from the step after each sample (one extra step "
                           "after the last)"]
    motion = drop(case, case.times, out.origin, out.rotation, out.velocity, out.omega,
                  out.forces, rod_force=out.rod_force)
    return EngineRun(motion, build, wall, n_steps, s, counters, notes)
