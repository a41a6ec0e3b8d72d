"""Pinocchio as an engine: a kinematic tree of joints, loops closed by rigid point
constraints, integrated by our own RK4 (or Radau).

Every case goes through one builder: a 2-D case is lifted into 3-D
(:mod:`natcoord.engines.planar`: points (x, y, 0), revolutes about z, prismatic axes (ax, ay,
0), gravity (gx, gy, 0)) and its outputs are dropped back to 2-D in the same module. Body
points are in the body's own frame; its pose and rates at t = 0 come from ``init[body]``,
posed and reference-frame cases alike.

Model (:mod:`.model`)
---------------------
* Tree: :func:`natcoord.engines.tree.point_loop_tree`. A loop-closing *prismatic* joint
  cannot be a ``CONTACT_3D`` constraint (that pins a point), so when the natural tree leaves
  one, the tree is rebuilt with prismatic joints tried first; the joint cut instead is a
  revolute one. For a non-redundant loop the reactions do not depend on where it is cut.
  Joints are added depth-first: Pinocchio's algorithms (crba, Jacobians) assume the joints
  of every subtree contiguous, which breadth-first order breaks as soon as the tree branches
  below its root (wrong mass matrix, no error).
* Every joint frame is world-aligned at t = 0 (q neutral), at its joint point. Revolute ->
  ``JointModelRX/RY/RZ`` or ``JointModelRevoluteUnaligned`` along its axis. Prismatic ->
  ``JointModelPX/PY/PZ`` or ``JointModelPrismaticUnaligned``, placed at the child's point,
  q = displacement since t = 0; the child keeps its assembled rotation relative to the
  parent. Cylindrical -> ``JointModelComposite`` (prismatic then revolute along the axis).
  Universal -> ``JointModelUniversal`` (first axis on the parent). Spherical ->
  ``JointModelSpherical``.
* A body no joint reaches: ``JointModelPlanar`` in a planar case (it stays in the plane),
  else ``JointModelTranslation`` + ``JointModelSphericalZYX`` (six scalar dofs, so the state
  stays a vector: ZYX angles are singular at 90 deg pitch, far from anything here).
* Each body's natcoord frame is a fixed placement ``X`` in its joint frame; its mass and
  inertia are appended there. A planar body's Izz is lifted as Izz * I3: every joint of a
  planar case turns about z, so the other moments never act. Izz = 0 is a point mass at the
  centre of mass: exact, and the joint still sees m r^2 as long as the mass is off its axis.
  A 3-D slender rod keeps its exact singular inertia (the joints never turn it about its
  axis). A particle gets a tiny inertia (``particle_inertia`` kg m^2 per kg) that nothing
  can torque, so its absolute rotation does not feed back; its output frame never turns.
* Massless rod (``constraintDynamics`` has no distance constraint): a *light body*, a
  slender rod of mass ``rod_mass`` kg on a revolute (planar case: about the normal) or
  universal (3-D: two axes normal to the rod, so it cannot spin about itself) joint at one
  end (the end whose body is nearer the ground), closed at the other end by CONTACT_3D. Its
  inertia is the substitute's cost, bounded in the tests. The axial force (tension
  positive) is the constraint force at the closing end along the rod.
* Applied loads (torque, force at a point, constant in world axes) and spring-dampers:
  external forces in ``aba``, or ``tau += J^T f`` for ``constraintDynamics`` (which takes
  no ``fext``; constant when every rotation is about one fixed axis and the loads are pure
  moments), all computed by one compiled call (:mod:`.applied`).
* Drivers (prescribed motions) are not modelled: Unsupported.

Loops (:mod:`.loops`): ``RigidConstraintModel(CONTACT_3D)`` at the joint point, ``LOCAL``;
a loop-closing revolute only when the tree path between its bodies turns about parallel
axes (else CONTACT_6D would also lock its rotation: Unsupported). Planar motion leaves the
contact's z row all zero, hence ``mu > 0``.

Integration (:mod:`.dynamics`): classic RK4 on (q, v), four ``constraintDynamics`` (``aba``
without loops) calls a step (``pinocchio.integrate`` for spherical and planar joints), or
scipy's Radau IIA (``method = "radau"``, unconstrained models only).

Reactions (:mod:`.readout`): ``rnea`` with the constraint forces and applied loads as
external forces.
"""

from __future__ import annotations

import time

from ..base import EngineRun, merged, steps_per_sample
from ..capabilities import Capabilities, misaligned_loop_revolutes
from ..schema import C_INT_MAX, Setting, defaults, particle_inertia

NAME = "pinocchio"
PACKAGE = "pin"
SETTINGS = (
    Setting("dt", "number", 1e-3, "RK4 step; must divide the case's output interval", "s",
            exclusive_minimum=0.0),
    Setting("mu", "number", 1e-8, "proximal regularisation of constraintDynamics (> 0: a "
            "planar loop's out-of-plane rows are zero)", exclusive_minimum=0.0),
    Setting("accuracy", "number", 1e-12, "the proximal iterations' absolute accuracy",
            exclusive_minimum=0.0),
    Setting("max_iter", "integer", 20, "the proximal iteration cap", minimum=1,
            maximum=C_INT_MAX),
    Setting("baumgarte_kp", "number", 0.0, "Baumgarte position gain on the loop "
            "constraints", "1/s^2", minimum=0.0),
    Setting("baumgarte_kd", "number", 0.0, "Baumgarte velocity gain on the loop "
            "constraints", "1/s", minimum=0.0),
    Setting("max_drift", "number", 1e-3, "a loop opening more than this is reported as "
            "divergence", "m", exclusive_minimum=0.0),
    particle_inertia(True),
    Setting("rod_mass", "number", 1e-6, "mass of the light body that stands for a massless "
            "rod", "kg", exclusive_minimum=0.0),
    Setting("method", "choice", "rk4", "rk4 (fixed step dt) or radau (scipy's Radau IIA on "
            "aba: stiff springs, no loops)", choices=("rk4", "radau")),
    Setting("rtol", "number", 1e-8, "Radau's relative tolerance", exclusive_minimum=0.0),
    Setting("atol", "number", 1e-10, "Radau's absolute tolerance", exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)



def _rules(case, s: dict) -> list[str]:
    """Loop revolutes whose axis the tree does not keep (loops.py), Radau's limits."""
    out = [f"loop-closing 3-D revolute {n!r}: the tree does not enforce its axis alignment, "
           "and CONTACT_6D would lock its rotation"
           for n in misaligned_loop_revolutes(case, CAPABILITIES)]
    if str(s.get("method", "")).lower() == "radau":
        from ..capabilities import tree
        if tree(case, CAPABILITIES)[1] or case.rods:
            out.append("method radau: the constrained (constraintDynamics) model uses RK4")
        elif any(j.type == "spherical" for j in case.joints):
            out.append("Radau needs a vector configuration (a spherical joint has a "
                       "quaternion)")
    return out


CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="rigid",  # constraintDynamics: exact constraint accelerations (mu 1e-8)
    body_loads=True,  # fext in joint frames: a body-fixed load is constant there
    loop_joints={"revolute", "spherical"}, recut={"prismatic"},  # tree.point_loop_tree
    drivers=(),
    why={"drivers": "Pinocchio's constraintDynamics has contact constraints only, no "
                    "rheonomic constraint on a joint coordinate",
         "loop_joints": "a point contact (CONTACT_3D) cannot model it"},
    rules=_rules)

def version() -> str:
    import pinocchio

    return pinocchio.__version__


def _integrate(pin, case, b, dyn, s: dict, notes: list[str]):
    """(Q, V, A, L, steps, counters) at the case's sample times, by ``s["method"]``."""
    from ...errors import Unsupported
    from .dynamics import integrate_radau, integrate_rk4

    method = str(s["method"]).lower()
    times = case.times
    if method == "rk4":
        dt = float(s["dt"])
        context = f", mu {s['mu']:g}" if dyn.looped else ""
        Q, V, A, L, n = integrate_rk4(pin, b, dyn, times, steps_per_sample(case, dt), dt,
                                      context)
        call = "constraintDynamics" if dyn.looped else "aba"
        notes.append(f"classic RK4, dt {dt:g} s, 4 {call} calls a step")
        return Q, V, A, L, n, {"steps": n, "rhs": 4 * n + 1}
    if method == "radau":
        if dyn.looped:
            raise Unsupported("method radau: the constrained (constraintDynamics) model "
                              "uses RK4")
        Q, V, A, L, n, counters = integrate_radau(b, dyn, times, s)
        notes.append(f"scipy Radau IIA on pinocchio.aba, rtol {s['rtol']:g}, "
                     f"atol {s['atol']:g}")
        return Q, V, A, L, n, counters | {"steps": n}
    raise ValueError(f"pinocchio: unknown method {s['method']!r} (rk4 | radau)")


def run(case, init, settings: dict) -> EngineRun:
    """Build, integrate and sample ``case`` from ``init`` (see the module docstring)."""
    import pinocchio as pin

    from ..planar import drop
    from . import loops, model, readout
    from .dynamics import Dynamics

    s = merged(DEFAULTS, settings)
    t0 = time.perf_counter()
    lifted = model.Lifted.of(case, init)
    b = model.build(pin, lifted, s)
    cmodels, closures = loops.close(pin, b, b.loop_joints, s)
    dyn = Dynamics(pin, b, cmodels, s)
    build_time = time.perf_counter() - t0
    notes = list(b.notes)
    t0 = time.perf_counter()
    Q, V, A, L, n, counters = _integrate(pin, case, b, dyn, s, notes)
    wall = time.perf_counter() - t0
    origin, rotation, velocity, omega, forces, rod_force, drift = readout.sample(
        pin, b, dyn, closures, Q, V, A, L)
    if drift[0] > s["max_drift"]:
        raise RuntimeError(f"pinocchio: a loop opened by {drift[0]:.3g} m (> max_drift "
                           f"{s['max_drift']:g} m); reduce dt or add Baumgarte gains")
    counters |= {"prox_iter_max": dyn.iters, "drift_max_m": float(drift[0]),
                 "velocity_drift_max_m_s": float(drift[1])}
    if closures:
        notes.append(f"proximal constraintDynamics: mu {s['mu']:g}, accuracy "
                     f"{s['accuracy']:g}, at most {s['max_iter']} iterations "
                     f"(reached {dyn.iters})")
        if dyn.iters >= int(s["max_iter"]):
            notes.append(f"the proximal solver hit its cap of {s['max_iter']} iterations "
                         "(redundant loops?): constraint forces may be unconverged")
    motion = drop(case, case.times, origin, rotation, velocity, omega, forces,
                  rod_force=rod_force)
    return EngineRun(motion, build_time, wall, n, s, counters, notes)


__all__ = ["DEFAULTS", "NAME", "PACKAGE", "SETTINGS", "run", "version"]
