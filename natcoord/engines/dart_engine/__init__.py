"""DART (dartpy) as an engine: a kinematic tree in joint coordinates plus loop-closing joint
constraints, integrated by DART's semi-implicit (symplectic) Euler.

One model for every case: a 2-D case is lifted to its planar 3-D case in one place
(:mod:`natcoord.engines.planar`, shared with MuJoCo and Pinocchio), built by one skeleton
builder (:mod:`.skeleton`), stepped and read in 3-D (:mod:`.stepping`) and dropped back to
2-D outputs in one place (again :mod:`natcoord.engines.planar`). Modelling, in short (every
choice is also written into ``EngineRun.notes``):

* Body frames at t = 0 are natcoord's assembled ones (``init``); each tree joint's frame sits
  at the joint point with the child's axes at t = 0 on both sides, so rotation coordinates
  start at 0 and a prismatic coordinate at the joints' offset along the axis.
* One ``Skeleton`` holds the spanning tree of :func:`natcoord.engines.tree.point_loop_tree`:
  ``RevoluteJoint`` (a 2-D revolute turns about z), ``PrismaticJoint``, ``BallJoint``,
  ``UniversalJoint``. DART has no prismatic joint *constraint*, so when the plain tree leaves
  a prismatic joint to close a loop the tree is recomputed with the prismatic joints tried
  first and the loop is cut at a revolute joint instead (same motion; only which joint is
  "cut" changes). A loop-closing prismatic, universal or cylindrical joint is unsupported,
  and so is a cylindrical joint anywhere (DART has no such joint).
* Bodies the tree does not reach: in a 2-D case they stay in the plane (``PlanarJoint``; a
  ``TranslationalJoint2D`` for a particle), in 3-D they get a ``FreeJoint``.
* A loop-closing spherical joint is a ``BallJointConstraint``; so is a loop-closing revolute
  joint when every revolute axis of the case is parallel (every 2-D case: the tree already
  keeps the loop's bodies turning about that axis, the z row is empty because every body
  keeps z = 0, and the constraint's rotation rows would be redundant). Otherwise (or with
  ``loop_constraint = "revolute"``) it is a ``RevoluteJointConstraint``.
* The loop constraints' error-reduction parameter (ERP) is a process-wide static of
  ``DynamicJointConstraint`` (``JointConstraint.setErrorReductionParameter`` is a different
  static, for joint limits, and has no effect here); it is set for the run and restored
  afterwards. Measured on the four-bar at dt 1e-4: ERP 0.01 (DART's default) leaves a loop
  gap of 2.2e-5 m, 0.2 -> 1.1e-6 m, 1.0 -> 2.2e-7 m (~20 dt^2); the angle error is 1.1-1.2e-3
  rad for all of them. ``RevoluteJointConstraint`` diverges within 0.01 s for ERP >= 0.05
  and costs about twice as much per step; at ERP 0.01 it matches the ball constraint.
* Particles are point masses with a tiny rotational inertia about their point
  (``particle_radius_of_gyration``); their frame is reported at angle 0 (identity rotation),
  the origin following their point (natcoord's convention). A 2-D rigid body's I_zz is
  lifted as I_zz * I3 (only I_zz acts in planar motion) and raised to that radius of
  gyration when smaller (:func:`floor_planar_inertia`). A slender rod (``uniform_rod``)
  has no inertia about its own axis; DART needs a positive definite inertia, so
  ``axial_inertia`` times its transverse inertia is added about it (no effect on planar
  motion).
* A massless rod (``[[rods]]``) becomes a light uniform rod of ``rod_mass`` kg: a tree joint
  at its first end (revolute about z in 2-D, ball in 3-D; the ground end first when there is
  one) and a ``BallJointConstraint`` at its other end. Its axial force is the force its tree
  joint applies to it, projected on the rod, plus half its own inertial load
  (``-F_joint . u + m/2 (a_G - g) . u``: the mid-length value).
* Spring-dampers (``[[springs]]``) are external forces (``addExtForce``) computed from the
  state at the start of every step: explicit in DART's semi-implicit Euler, so the step has
  to resolve the damping (h c / m well below 2).
* Drivers: a ``VELOCITY`` actuator on the tree joint whose coordinate is the driven value
  (:mod:`.drivers`); the driver's effort is read from that joint's transmitted wrench.
* Tree-joint reactions come from ``Joint.getWrenchToParentBodyNode(World)`` (layout moment,
  force; its force part is the force of the tree parent on the child, whatever the reference
  point). DART computes it inside the step that *starts* at the sample time (with the
  constraint impulses of that step folded in), so it is read after that step, with the
  skeleton put back for the read at the state of the sample time (it is zero before the
  first step).
* DART does not expose constraint impulses to Python, so a loop joint's force follows from
  the Newton-Euler balance of one body it joins, at the same instant and with the same
  discrete acceleration DART used: ``F_loop = m a_G - m g - F_applied - F_parent + sum
  F_children``. A loop joint whose bodies both close other loops too is left out (its
  channels are NaN).
* At t = 0 a moving loop's first two steps are transients (step 0 enforces the loop at
  velocity level only, step 1 overshoots), so the t = 0 reactions are extrapolated from
  steps 2 and 3.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ...case.mechanism import Case
from ...errors import Unsupported
from ..base import EngineRun, merged, steps_per_sample
from ..capabilities import Capabilities, drivers_off_ground_joints, misaligned_loop_revolutes
from ..schema import Setting, defaults

NAME = "dart"
PACKAGE = "dartpy"
SETTINGS = (
    Setting("dt", "number", 1e-4, "time step of DART's semi-implicit Euler; must divide "
            "the case's output interval", "s", exclusive_minimum=0.0),
    Setting("erp", "number", 1.0, "error-reduction parameter of the loop-joint constraints "
            "(DART's static)", minimum=0.0, maximum=1.0),
    Setting("loop_constraint", "choice", "ball", "a loop-closing revolute as a "
            "BallJointConstraint (every revolute axis parallel) or a "
            "RevoluteJointConstraint", choices=("ball", "revolute")),
    Setting("max_error_reduction_velocity", "number", 10.0, "DART's cap on the constraint "
            "correction's velocity", "m/s", exclusive_minimum=0.0),
    Setting("particle_radius_of_gyration", "number", 1e-3, "a particle's tiny rotational "
            "inertia, as a radius of gyration (also the floor of a 2-D body's)", "m",
            exclusive_minimum=0.0),
    Setting("max_drift", "number", 1e-2, "a loop-joint gap above which the run counts as "
            "diverged", "m", exclusive_minimum=0.0),
    Setting("rod_mass", "number", 1e-5, "mass of the light rod that stands for a massless "
            "rod", "kg", exclusive_minimum=0.0),
    Setting("axial_inertia", "number", 1e-3, "slender rods: inertia about their axis, "
            "times their transverse inertia (DART needs it positive)",
            exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)



def _rules(case: Case, s: dict) -> list[str]:
    """Drivers on a tree joint from the ground (drivers.py; the joint's direction is
    checked when the skeleton is built), loop revolutes with other axes (skeleton.py)."""
    out = [f"driver {d!r}: DART can prescribe a tree-joint coordinate only; {b!r} is not on "
           f"a {want} joint from the ground"
           for d, b, want in drivers_off_ground_joints(case, CAPABILITIES)]
    bad = misaligned_loop_revolutes(case, CAPABILITIES)
    if bad and s.get("loop_constraint") != "revolute":
        out.append(f"loop joint(s) {', '.join(bad)}: revolute joints with different axes "
                   "close the loop, a BallJointConstraint would drop their rotation rows "
                   "(setting loop_constraint = 'revolute' uses DART's "
                   "RevoluteJointConstraint)")
    return out


CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="soft",  # constraint impulses with error reduction (erp): the loop drifts back
    body_loads=True,  # addExtForce / addExtTorque with local axes
    joints={"revolute", "prismatic", "spherical", "universal"},
    loop_joints={"revolute", "spherical"}, recut={"prismatic"},  # tree.point_loop_tree
    why={"joints": "DART has no cylindrical joint",
         "loop_joints": "DART has joint constraints for ball and revolute joints only"},
    rules=_rules)

def version() -> str:
    import dartpy

    return dartpy.__version__


def floor_planar_inertia(case3: Case, r_gyr: float, notes: list[str]) -> Case:
    """A lifted 2-D case (``Izz * I3`` per body, :func:`natcoord.engines.planar.lift_case`)
    with every rigid body's Izz raised to ``mass * r_gyr**2`` (``r_gyr`` m) when smaller: DART
    needs a positive definite inertia. Particles and slender rods get theirs in the skeleton
    builder."""
    bodies = []
    for b in case3.bodies:
        izz = float(b.inertia[2, 2])
        if b.kind not in ("uniform_rod", "particle") and izz < b.mass * r_gyr**2:
            izz = b.mass * r_gyr**2
            notes.append(f"body {b.name!r}: inertia raised to {izz:.3g} kg m^2 (DART needs "
                         "it > 0)")
            b = dataclasses.replace(b, inertia=izz * np.eye(3))
        bodies.append(b)
    return dataclasses.replace(case3, bodies=tuple(bodies))


def check_supported(case: Case) -> None:
    """Refuse, with the reason, what the adapter does not model."""
    for b in case.bodies:
        if not b.mass > 0:
            raise Unsupported(f"body {b.name!r} has no mass; DART bodies need a positive mass")
    for j in case.joints:
        if j.type == "cylindrical":
            raise Unsupported(f"cylindrical joint {j.name!r}: DART has no cylindrical joint")


def run(case: Case, init, settings: dict) -> EngineRun:
    import dartpy as dart

    from ..planar import drop, lift_case, lift_init, plane_normal
    from .drivers import make_drivers
    from .loads import make_loads
    from .skeleton import add_loop_constraints, build, choose_tree
    from .stepping import Sampler, loop_bodies, make_world, simulate, simulate_with_erp, stepper

    s = merged(DEFAULTS, settings)
    if s["loop_constraint"] not in ("ball", "revolute"):
        raise ValueError(f"loop_constraint must be 'ball' or 'revolute', got "
                         f"{s['loop_constraint']!r}")
    check_supported(case)
    choose_tree(case, [])  # refuse unclosable loops before the state is used
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)

    t0 = time.perf_counter()
    notes: list[str] = []
    case3 = lift_case(case)
    if case.dimension == 2:
        case3 = floor_planar_inertia(case3, float(s["particle_radius_of_gyration"]), notes)
    frames = lift_init(case, init)
    normal = plane_normal(case)
    sk = build(dart, case3, frames, s, normal, notes)
    drivers = make_drivers(case3, sk, frames, notes)
    world, solver = make_world(dart, sk.skel, np.asarray(case3.gravity, float), dt)
    add_loop_constraints(dart, case3, sk, frames, s, solver, notes)
    loop_body = loop_bodies(sk.loops, sk.rods, notes)
    loads = make_loads(case3, sk.nodes)
    if case3.springs:
        notes.append("spring-dampers " + ", ".join(sp.name for sp in case3.springs) + ": "
                     "external forces from the state at the start of each step (explicit)")
    sampler = Sampler(dart, case3, sk, loop_body, drivers, loads)

    def before_step():
        loads[0]()
        for d in drivers:
            d.command(world.getTime(), dt)

    steps, clock = stepper(world, before_step)
    build_time = time.perf_counter() - t0
    extrapolate0 = bool(sk.loops or sk.rods) and k >= 4
    samples, force, axial, effort, counters = simulate_with_erp(
        dart, s, notes, dt, extrapolate0, lambda: simulate(
            case3, world, sk, sampler, steps, clock, loads[2], k, float(s["max_drift"]),
            extrapolate0))
    motion = drop(case, case.times.copy(), samples["origin"], samples["R"],
                  samples["velocity"], samples["omega"], force,
                  acceleration=samples["acceleration"], alpha=samples["alpha"],
                  driver_effort=effort, rod_force=axial)
    return EngineRun(motion, build_time, clock["wall"], clock["steps"], s, counters, notes)
