"""Drake as an engine: a ``MultibodyPlant`` of rigid bodies on a tree of joints, loops closed
by ball constraints, stepped by Drake's ``Simulator``.

Every case goes through one builder (:mod:`.model`): a 2-D case is lifted into 3-D
(:mod:`natcoord.engines.planar`), built at natcoord's assembled pose (q = 0) and rates, and
its samples are dropped back to the case's dimension.

* Plant: ``plant = "discrete"`` (default) is a discrete MultibodyPlant with the SAP solver
  (``DiscreteContactApproximation.kSap``), time step ``dt``; Drake accepts constraints only
  there, and SAP holds them softly (a compliance near the time step), so loop cases converge
  at first order in dt. ``plant = "continuous"`` is a continuous plant integrated by
  ``integrator`` at ``accuracy`` (error-controlled): open trees only, Drake refuses
  constraints there.
* Tree: joints to the ground first, then prismatic ones, then breadth-first
  (:func:`.model.split_tree`): every loop closes between two bodies, never at Drake's world
  body. Revolute -> ``RevoluteJoint``, prismatic -> ``PrismaticJoint``, spherical ->
  ``BallRpyJoint`` (roll-pitch-yaw: singular at 90 deg pitch). A planar body no joint
  reaches gets a ``PlanarJoint``, a 3-D one Drake's free (quaternion) joint.
* Loop-closing revolute or spherical joints: ``AddBallConstraint`` at the joint point (a
  planar loop's axis alignment is kept by the tree). Universal and cylindrical joints,
  massless rods and drivers: :class:`natcoord.errors.Unsupported` with the reason.
* Spring-dampers: ``LinearSpringDamper``; constant torques and forces: the applied spatial
  force input port, fixed.

Reactions and tensions: :mod:`.simulate`.
"""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import Case
from ...errors import Unsupported
from ..base import EngineRun, merged, steps_per_sample
from ..capabilities import Capabilities, massless, refuse
from ..schema import Setting, defaults, particle_inertia

NAME = "drake"
PACKAGE = "drake"
INTEGRATORS = ("runge_kutta2", "runge_kutta3", "runge_kutta5", "radau3", "implicit_euler")
SETTINGS = (
    Setting("plant", "choice", "discrete", "discrete: SAP time-stepping with step dt (loops "
            "allowed, first order); continuous: an error-controlled integrator (open trees "
            "only)", choices=("discrete", "continuous")),
    Setting("dt", "number", 1e-4, "the discrete plant's time step; must divide the case's "
            "output interval", "s", exclusive_minimum=0.0),
    Setting("integrator", "choice", "runge_kutta5", "the continuous plant's integrator",
            choices=INTEGRATORS),
    Setting("accuracy", "number", 1e-10, "the continuous integrator's target accuracy",
            exclusive_minimum=0.0),
    particle_inertia(True, "Drake wants a body; no joint turns it about its point"),
    Setting("sampled_ports", "boolean", False, "the discrete plant's output ports (reactions, "
            "accelerations) sampled: the step that led to the sample (t = 0: no step, no "
            "constraint force); false: the step from the sample on, computed live"),
    Setting("max_loop_gap", "number", 1e-4, "a loop opened wider than this is a failed run",
            "m", exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)

DRIVERS_UNSUPPORTED = (
    "prescribed motions (drivers): Drake's MultibodyPlant constraints (ball, distance, weld, "
    "coupler) have no time argument and no joint follows a given q(t); a stiff PD actuator "
    "would be a substitute of another physics")
RODS_UNSUPPORTED = (
    "massless rods: Drake's AddDistanceConstraint holds the length (SAP, soft) but Drake "
    "reports no constraint force, so the rod's tension (an axial channel) cannot be read, and "
    "a rod ending on the ground would attach a constraint to the world body")


def _rules(case: Case, s: dict) -> list[str]:
    """Bodies with mass, and the tree's refusals (:func:`.model.split_tree`: no loop closed
    at the ground, point-closable loop joints only; loops on the discrete plant only; a 3-D
    loop revolute needs every tree joint a revolute along its axis)."""
    from .model import CONTINUOUS_LOOPS, split_tree

    out = massless(case, "Drake's rigid bodies")
    if out:
        return out
    try:
        tree, loops, _ = split_tree(case)
    except Unsupported as e:
        return [str(e)]
    if loops and s.get("plant") != "discrete":
        return [CONTINUOUS_LOOPS]
    if case.dimension == 3:
        for j in (j for j in loops if j.type == "revolute"):
            u = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
            off = [t.name for t in tree if t.type != "revolute" or np.linalg.norm(
                np.cross(u, np.asarray(t.axis, float) / np.linalg.norm(t.axis))) > 1e-9]
            if off:
                return [f"loop-closing 3-D revolute {j.name}: the tree does not keep its "
                        f"axis (tree joint {off[0]}), and a Drake ball constraint holds only "
                        "the point"]
    return []


CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="soft",  # SAP's ball constraints are compliant: the loop opens by a small gap
    joints={"revolute", "prismatic", "spherical"}, loop_joints={"revolute", "spherical"},
    recut={"prismatic"}, drivers=(), rods=False, step="dt",
    why={"drivers": DRIVERS_UNSUPPORTED.split(": ", 1)[1],
         "body_loads": "the adapter feeds Drake constant ExternallyAppliedSpatialForce in "
                       "world axes; a load that turns with its body is not wired",
         "rods": RODS_UNSUPPORTED.split(": ", 1)[1],
         "joints": "this adapter builds revolute, prismatic and ball joints only",
         "loop_joints": "a Drake ball constraint pins a point and cannot slide"},
    rules=_rules)


def version() -> str:
    import pydrake

    return _version(pydrake)


def _version(pydrake) -> str:
    v = getattr(pydrake, "__version__", None)
    if v:
        return str(v)
    from importlib.metadata import version as dist_version

    return dist_version("drake")


def _loads(case: Case, built):
    """The case's constant loads as ExternallyAppliedSpatialForce (world axes)."""
    from pydrake.multibody.math import SpatialForce
    from pydrake.multibody.plant import ExternallyAppliedSpatialForce

    out = []
    for f in case.forces:
        if f.frame == "body":
            raise Unsupported(f"{f.type} on {f.body} in its body's frame: the adapter's "
                              "applied forces are constant, in world axes")
        x = ExternallyAppliedSpatialForce()
        x.body_index = built.bodies[f.body].index()
        if f.type == "torque":
            x.p_BoBq_B = np.zeros(3)
            x.F_Bq_W = SpatialForce(np.asarray(f.value, float), np.zeros(3))
        else:
            x.p_BoBq_B = np.asarray(case.body(f.body).points[f.point], float)
            x.F_Bq_W = SpatialForce(np.zeros(3), np.asarray(f.value, float))
        out.append(x)
    return out


def run(case: Case, init, settings: dict) -> EngineRun:
    """Simulate ``case`` from ``init`` at the case's sample times (see the module)."""
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator

    from ..planar import drop, lift_case, lift_init
    from . import model, simulate

    s = merged(DEFAULTS, settings)
    discrete = s["plant"] == "discrete"
    if discrete:
        steps_per_sample(case, float(s["dt"]))
    refuse(CAPABILITIES, case, s)
    space = lift_case(case)
    model.split_tree(space)  # an unsupported loop is refused before anything is built
    frames = lift_init(case, init)
    planar = case.dimension == 2
    t0 = time.perf_counter()
    built = model.build(space, frames, s, planar)
    plant = built.plant
    simulator = Simulator(plant)
    ctx = simulator.get_mutable_context()
    model.set_initial_state(built, ctx, frames, planar)
    loads = _loads(space, built)
    if loads:
        plant.get_applied_spatial_force_input_port().FixValue(ctx, loads)
    notes = list(built.notes)
    if discrete:
        notes.append(f"discrete MultibodyPlant, SAP, dt {float(s['dt']):g} s (first order)")
    else:
        ResetIntegratorFromFlags(simulator, str(s["integrator"]), 0.1)
        integ = simulator.get_mutable_integrator()
        integ.set_target_accuracy(float(s["accuracy"]))
        notes.append(f"continuous MultibodyPlant, {s['integrator']} at accuracy "
                     f"{float(s['accuracy']):g}")
    simulator.Initialize()
    build_time = time.perf_counter() - t0
    readout = simulate.Readout(built, space, len(case.times))
    wall = simulate.step(simulator, ctx, case.times, readout)
    if readout.gap > float(s["max_loop_gap"]):
        raise RuntimeError(f"a loop opened by {readout.gap:.3g} m (max_loop_gap "
                           f"{s['max_loop_gap']} m): reduce dt")
    if discrete:
        n_steps = int(round(case.times[-1] / float(s["dt"])))
    else:
        n_steps = int(simulator.get_integrator().get_num_steps_taken())
    counters = {"steps": n_steps, "loop_gap_m": readout.gap}
    motion = drop(case, case.times, readout.origin, readout.rotation, readout.velocity,
                  readout.omega, readout.forces, rod_force=readout.rod_force)
    return EngineRun(motion, build_time, wall, n_steps, s, counters, notes)


__all__ = ["DEFAULTS", "NAME", "PACKAGE", "SETTINGS", "run", "version"]
