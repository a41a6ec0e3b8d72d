"""DART (dartpy) as an engine: a kinematic tree in joint coordinates plus loop-closing joint
constraints, integrated by DART's semi-implicit (symplectic) Euler.

Modelling, in short (every choice is also written into ``EngineRun.notes``):

* One ``Skeleton`` holds the spanning tree of :func:`natcoord.engines.tree.spanning_tree`: a
  revolute joint about world z or a prismatic joint per tree joint, rooted at the world.
  DART has no prismatic joint *constraint*, so when that tree leaves a prismatic joint to
  close a loop the tree is recomputed with the prismatic joints tried first (the same
  breadth-first rule, prismatic joints first in file order); the loop is then cut at a
  revolute joint instead. Motion is the same; only which joint is "cut" changes.
* Each loop-closing revolute joint is a ``BallJointConstraint`` (default; the in-plane
  rows are the planar revolute joint, the z row is empty because every body keeps z = 0)
  or a ``RevoluteJointConstraint`` (setting ``loop_constraint = "revolute"``), added to the
  world's constraint solver after the skeleton is set to natcoord's assembled state.
* The loop constraints' error-reduction parameter (ERP) is a process-wide static of
  ``DynamicJointConstraint`` (``JointConstraint.setErrorReductionParameter`` is a different
  static, for joint limits, and has no effect here); it is set for the run and restored
  afterwards. Measured on the four-bar at dt 1e-4: ERP 0.01 (DART's default) leaves a loop
  gap of 2.2e-5 m, 0.2 -> 1.1e-6 m, 1.0 -> 2.2e-7 m (~20 dt^2); the angle error is 1.1-1.2e-3
  rad for all of them. ``RevoluteJointConstraint`` diverges within 0.01 s for ERP >= 0.05
  and costs about twice as much per step; at ERP 0.01 it matches the ball constraint.
* Particles are point masses with a tiny rotational inertia about their point
  (``particle_radius_of_gyration``); their frame is reported at angle 0, the origin following
  their point (natcoord's convention). Bodies the tree does not reach fly free on a planar
  joint (a 2-D translational joint for a particle).
* Tree-joint reactions come from ``Joint.getWrenchToParentBodyNode(World)`` (layout moment,
  force; its force part is the force of the tree parent on the child, whatever the reference
  point). DART computes it inside the step that *starts* at the sample time (with the
  constraint impulses of that step folded in), so it is read after that step, with the
  skeleton put back for the read at the state of the sample time (it is zero before the
  first step).
* DART does not expose constraint impulses to Python, so a loop joint's force follows from
  the Newton-Euler balance of one body it joins, at the same instant and with the same
  discrete acceleration DART used: ``F_loop = m a_G - m g - F_parent + sum F_children``.
  A loop joint whose bodies both close other loops too is left out (its channels are NaN).
* At t = 0 a moving loop's first two steps are transients (step 0 enforces the loop at
  velocity level only, step 1 overshoots), so the t = 0 reactions are extrapolated from
  steps 2 and 3.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case, Joint
from .base import EngineRun, merged, steps_per_sample
from .dart_3d import (
    ROD_NOTE,
    LightRod,
    check_drift,
    check_state,
    loop_bodies,
    make_motion,
    make_world,
    sample_reactions,
    simulate_with_erp,
    step_and_read,
    stepper,
)
from .tree import point_loop_tree, tree_orientation, tree_parents

NAME = "dart"
PACKAGE = "dartpy"
DEFAULTS = {
    "dt": 1e-4,  # s; must divide the case's output interval
    "erp": 1.0,  # error-reduction parameter of the loop-joint constraints (DART static)
    "loop_constraint": "ball",  # "ball" or "revolute"
    "max_error_reduction_velocity": 10.0,  # m/s, DART's default cap on the correction
    "particle_radius_of_gyration": 1e-3,  # m: a particle's tiny rotational inertia
    "max_drift": 1e-2,  # m: loop-joint gap above which the run counts as diverged
    "rod_mass": 1e-5,  # kg: a massless rod's light-body substitute (dart_3d.LightRod)
    "axial_inertia": 1e-3,  # 3-D slender rod: inertia about its axis / transverse inertia
}


def version() -> str:
    import dartpy

    return dartpy.__version__


# ---- small 2-D helpers ------------------------------------------------------------------
def _rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _perp(v: np.ndarray) -> np.ndarray:
    """k x v for a 2-D v."""
    return np.array([-v[1], v[0]])


def _v3(v2, z: float = 0.0) -> np.ndarray:
    return np.array([float(v2[0]), float(v2[1]), z])


def _iso(dart, p2: np.ndarray, angle: float = 0.0):
    """Isometry3 from a 2-D translation and a rotation about z."""
    T = np.eye(4)
    T[:2, :2] = _rot(angle)
    T[:2, 3] = p2
    iso = dart.math.Isometry3()
    iso.set_matrix(T)
    return iso


def _angle_of(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


# ---- tree --------------------------------------------------------------------------------
def choose_tree(case: Case) -> tuple[list[Joint], list[Joint], bool]:
    """Tree and loop joints (loops revolute: DART has no prismatic joint constraint), and
    whether the tree was recut with prismatic joints first."""
    tree, loops, recut = point_loop_tree(case, "DART has no prismatic joint constraint")
    return tree, loops, bool(recut)


_parents = tree_parents


def _point(case: Case, body: str, name: str) -> np.ndarray:
    return np.asarray(case.ground[name] if body == GROUND else case.body(body).points[name],
                      dtype=float)


def _inertia_tensor(case: Case, body, r_gyr: float) -> tuple[np.ndarray, str | None]:
    """3x3 moment of inertia about the centre of mass with the case's I_zz; the out-of-plane
    components only have to make a valid rigid body (they never enter planar motion)."""
    if body.kind == "particle":
        i = body.mass * r_gyr**2
        return i * np.eye(3), f"{i:.3g} kg m^2"
    izz = float(body.inertia)
    if body.kind == "uniform_rod":
        ends = getattr(body, "ends", None) or list(body.points)[:2]
        d = body.points[ends[1]] - body.points[ends[0]]
        e = np.append(d / np.linalg.norm(d), 0.0)
        # thin rod: I_zz about every axis normal to the rod, ~0 along it
        return izz * (np.eye(3) - (1.0 - 1e-6) * np.outer(e, e)), None
    note = None
    if izz < body.mass * r_gyr**2:
        izz = body.mass * r_gyr**2
        note = f"{izz:.3g} kg m^2"
    return np.diag([izz / 2, izz / 2, izz]), note  # planar lamina: I_xx + I_yy = I_zz


# ---- run ---------------------------------------------------------------------------------
def run(case: Case, init, settings: dict) -> EngineRun:
    import dartpy as dart

    s = merged(DEFAULTS, settings)
    if s["loop_constraint"] not in ("ball", "revolute"):
        raise ValueError(f"loop_constraint must be 'ball' or 'revolute', got "
                         f"{s['loop_constraint']!r}")
    if case.dimension == 3:
        from .dart_3d import run_3d

        return run_3d(case, init, s)
    if getattr(case, "springs", ()):
        raise Unsupported("spring-dampers in 2-D cases are not modelled by the DART adapter")
    if getattr(case, "drivers", ()):
        raise Unsupported("drivers (prescribed motions) are not modelled by the DART adapter")
    for f in case.forces:
        if f.type != "torque":
            raise Unsupported(f"force type {f.type!r}")
    for b in case.bodies:
        if not b.mass > 0:
            raise Unsupported(f"body {b.name!r} has no mass; DART bodies need a positive mass")
    for j in case.joints:
        if j.type not in ("revolute", "prismatic"):
            raise Unsupported(f"joint type {j.type!r} of joint {j.name!r}")
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    notes: list[str] = []

    t0 = time.perf_counter()
    tree, loops, recut = choose_tree(case)
    if recut:
        notes.append("natcoord's spanning tree closes a loop with a prismatic joint, which "
                     "DART cannot constrain; tree recomputed with prismatic joints first, "
                     "loops cut at " + ", ".join(j.name for j in loops))
    oriented = _parents(tree)
    g = np.asarray(case.gravity, dtype=float)
    gravity = np.array([g[0], g[1], 0.0])

    skel = dart.dynamics.Skeleton(case.name)
    nodes, joints, sign = {}, {}, {}
    children: dict[str, list[str]] = {}
    for j, parent, child in oriented:
        pj = j.points[j.bodies.index(parent)]
        cj = j.points[j.bodies.index(child)]
        p0, p1 = _point(case, parent, pj), _point(case, child, cj)
        pnode = None if parent == GROUND else nodes[parent]
        ap = 0.0 if parent == GROUND else init[parent].angle
        ac = init[child].angle
        if j.type == "revolute":
            joint, node = skel.createRevoluteJointAndBodyNodePair(pnode)
            joint.setAxis(np.array([0.0, 0.0, 1.0]))
            joint.setTransformFromParentBodyNode(_iso(dart, p0))
            joint.setTransformFromChildBodyNode(_iso(dart, p1))
        else:
            phi = ac - ap  # constant relative rotation, from the assembled state
            axis = np.asarray(j.axis, dtype=float)
            a_p = axis if j.bodies[0] == parent else _rot(phi) @ axis  # in the parent frame
            a_p = a_p / np.linalg.norm(a_p)
            joint, node = skel.createPrismaticJointAndBodyNodePair(pnode)
            joint.setAxis(_v3(a_p))
            joint.setTransformFromParentBodyNode(_iso(dart, p0))
            joint.setTransformFromChildBodyNode(_iso(dart, p1, -phi))
        joint.setName(j.name)
        node.setName(child)
        b = case.body(child)
        moment, tiny = _inertia_tensor(case, b, s["particle_radius_of_gyration"])
        if tiny:
            notes.append(f"particle {child!r}: point mass given a tiny rotational inertia "
                         f"({tiny}) about its point; its angle is reported as 0"
                         if b.kind == "particle" else
                         f"body {child!r}: inertia raised to {tiny} (DART needs it > 0)")
        node.setInertia(dart.dynamics.Inertia(b.mass, _v3(b.com), moment))
        nodes[child], joints[j.name] = node, joint
        sign[j.name] = tree_orientation(case.joint(j.name), parent)
        children.setdefault(parent, []).append(child)
    for b in case.bodies:  # not reached from the ground: free in the plane
        if b.name in nodes:
            continue
        st = init[b.name]
        if b.kind == "particle":
            joint, node = skel.createTranslationalJoint2DAndBodyNodePair(None)  # x-y plane
            joint.setPositions(np.asarray(st.origin, float))
            joint.setVelocities(np.asarray(st.velocity, float))
        else:
            joint, node = skel.createPlanarJointAndBodyNodePair(None)  # x-y plane: x, y, phi
            joint.setPositions(np.array([st.origin[0], st.origin[1], st.angle]))
            joint.setVelocities(np.array([st.velocity[0], st.velocity[1], st.omega]))
        joint.setName(f"free {b.name}")
        node.setName(b.name)
        moment, tiny = _inertia_tensor(case, b, s["particle_radius_of_gyration"])
        if tiny:
            notes.append(f"particle {b.name!r}: point mass given a tiny rotational inertia "
                         f"({tiny}); its angle is reported as 0" if b.kind == "particle" else
                         f"body {b.name!r}: inertia raised to {tiny} (DART needs it > 0)")
        node.setInertia(dart.dynamics.Inertia(b.mass, _v3(b.com), moment))
        nodes[b.name] = node
        notes.append(f"body {b.name!r} is not joined to the ground by the tree: free in the "
                     "plane (DART planar joint)")
    rods = [LightRod(r, case) for r in getattr(case, "rods", ())]
    for r in rods:
        r.build(dart, skel, nodes, float(s["rod_mass"]), 1e-6, planar=True)
    if rods:
        notes.append(ROD_NOTE.format(names=", ".join(r.name for r in rods), m=s["rod_mass"],
                                     joint="revolute"))
    _set_initial_state(case, oriented, joints, init)
    _set_rod_rates(rods, init)
    _check_assembly(case, nodes, init)

    world, solver = make_world(dart, skel, gravity, dt, rods, nodes)
    for j in loops:
        a, b = j.bodies
        on = (b, j.points[1]) if b != GROUND else (a, j.points[0])
        pos = _v3(_world_point(nodes, case, *on))
        ends = [nodes[x] for x in (a, b) if x != GROUND]
        z = np.array([0.0, 0.0, 1.0])
        if s["loop_constraint"] == "ball":
            c = dart.constraint.BallJointConstraint(*ends, pos)
        elif len(ends) == 2:
            c = dart.constraint.RevoluteJointConstraint(*ends, pos, z, z)
        else:
            c = dart.constraint.RevoluteJointConstraint(*ends, pos, z)
        solver.addConstraint(c)
    if loops:
        kind = "Ball" if s["loop_constraint"] == "ball" else "Revolute"
        notes.append(f"loop joint(s) {', '.join(j.name for j in loops)}: DART "
                     f"{kind}JointConstraint, error-reduction parameter {s['erp']}")

    # loop-joint force: Newton-Euler of a body that only this loop joint closes
    loop_body = loop_bodies(loops, rods, notes)

    torques = [(nodes[f.body], f.value) for f in case.forces]
    build = time.perf_counter() - t0

    out, wall, n_steps, counters = simulate_with_erp(
        dart, s, notes, dt, bool(loops or rods) and k >= 4, lambda: _simulate(
            case, world, skel, nodes, joints, sign, children, loops, loop_body,
            torques, gravity, k, float(s["max_drift"]), rods))
    return EngineRun(out, build, wall, n_steps, s, counters, notes)


def _set_rod_rates(rods, init) -> None:
    """Light rods start moving with the ends natcoord assembled (reference-frame cases)."""
    def state(body):
        if body == GROUND:
            return np.zeros(3), np.zeros(3), np.zeros(3)
        b = init[body]
        return (_v3(b.origin), _v3(b.velocity), np.array([0.0, 0.0, float(b.omega)]))

    def vel_of(body, p):
        o, v, w = state(body)
        return v + np.cross(w, p - o)

    for r in rods:
        r.set_rate(lambda b: state(b)[2], vel_of, planar=True)


def _world_point(nodes, case: Case, body: str, point: str) -> np.ndarray:
    if body == GROUND:
        return np.asarray(case.ground[point], dtype=float)
    T = nodes[body].getWorldTransform().matrix()
    return T[:2, :2] @ case.body(body).points[point] + T[:2, 3]


def _set_initial_state(case: Case, oriented, joints, init) -> None:
    """Joint coordinates and rates from natcoord's assembled body states."""
    ground = dict(origin=np.zeros(2), angle=0.0, velocity=np.zeros(2), omega=0.0)

    def state(body):
        if body == GROUND:
            return ground
        b = init[body]
        return dict(origin=np.asarray(b.origin, float), angle=float(b.angle),
                    velocity=np.asarray(b.velocity, float), omega=float(b.omega))

    for j, parent, child in oriented:
        P, C = state(parent), state(child)
        joint = joints[j.name]
        if j.type == "revolute":
            joint.setPosition(0, C["angle"] - P["angle"])
            joint.setVelocity(0, C["omega"] - P["omega"])
            continue
        p0 = _point(case, parent, j.points[j.bodies.index(parent)])
        p1 = _point(case, child, j.points[j.bodies.index(child)])
        RP = _rot(P["angle"])
        r0, r1 = RP @ p0, _rot(C["angle"]) @ p1
        x0, x1 = P["origin"] + r0, C["origin"] + r1
        v0 = P["velocity"] + P["omega"] * _perp(r0)
        v1 = C["velocity"] + C["omega"] * _perp(r1)
        a_p = np.asarray(joint.getAxis())[:2]
        r = x1 - x0
        joint.setPosition(0, float(a_p @ RP.T @ r))
        joint.setVelocity(0, float(a_p @ RP.T @ (v1 - v0 - P["omega"] * _perp(r))))


def _check_assembly(case: Case, nodes, init, tol: float = 1e-7) -> None:
    """The skeleton must reproduce every body's assembled pose and velocity."""
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    for name, node in nodes.items():
        T = node.getWorldTransform().matrix()
        st = init[name]
        e_o = np.linalg.norm(T[:2, 3] - st.origin)
        v = np.asarray(node.getLinearVelocity(W, W))[:2]
        e_v = np.linalg.norm(v - st.velocity)
        e_w = abs(float(node.getAngularVelocity(W, W)[2]) - st.omega)
        e_a = abs(math.remainder(_angle_of(T[:2, :2]) - st.angle, 2 * math.pi))
        if case.body(name).kind == "particle":
            e_a = e_w = 0.0  # a particle's orientation is meaningless
        if max(e_o, e_a, e_v, e_w) > tol * max(1.0, np.linalg.norm(st.velocity)):
            raise RuntimeError(
                f"DART adapter: body {name!r} does not match the assembled state "
                f"(origin {e_o:.2e} m, angle {e_a:.2e} rad, velocity {e_v:.2e} m/s, "
                f"omega {e_w:.2e} rad/s)")


def _simulate(case, world, skel, nodes, joints, sign, children, loops, loop_body,
              torques, gravity, k, max_drift, rods=()):
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    times = case.times
    T = len(times)
    names = [b.name for b in case.bodies]
    particle = {b.name: b.kind == "particle" for b in case.bodies}
    pts = {b.name: next(iter(b.points.values())) for b in case.bodies}
    origin = {n: np.zeros((T, 2)) for n in names}
    angle = {n: np.zeros(T) for n in names}
    vel = {n: np.zeros((T, 2)) for n in names}
    omega = {n: np.zeros(T) for n in names}
    force = {name: np.zeros((T, 2)) for name in list(joints) + list(loop_body)}
    acc = {n: np.zeros((T, 2)) for n in names}
    alpha = {n: np.zeros(T) for n in names}
    mass = {n: nodes[n].getMass() for n in names}
    rod_force = {r.name: np.zeros(T) for r in rods}
    drift = 0.0

    def apply_torques():
        for node, tz in torques:
            node.setExtTorque(np.array([0.0, 0.0, tz]))

    steps, clock = stepper(world, apply_torques)

    def read() -> dict[str, np.ndarray]:
        """The reactions of the step just taken, read at the state it started from."""
        Fp = {n: np.asarray(nodes[n].getParentJoint().getWrenchToParentBodyNode(W))[3:5]
              for n in names}
        out = {name: sign[name] * Fp[joint.getChildBodyNode().getName()]
               for name, joint in joints.items()}
        for n in names:  # the step's (discrete) accelerations, same instant
            node = nodes[n]
            if particle[n]:
                out["acc:" + n] = np.asarray(node.getLinearAcceleration(_v3(pts[n]), W, W))[:2]
                out["alpha:" + n] = np.zeros(1)
            else:
                out["acc:" + n] = np.asarray(node.getLinearAcceleration(W, W))[:2]
                out["alpha:" + n] = np.asarray(node.getAngularAcceleration(W, W))[2:3]
        for name, (b, sg) in loop_body.items():
            a = np.asarray(nodes[b].getCOMLinearAcceleration(W, W))[:2]
            f = mass[b] * (a - gravity[:2]) - Fp[b]
            for c in children.get(b, []):
                f = f + Fp[c]
            for r in rods:
                if r.ends[0][0] == b:
                    f = f + np.asarray(r.joint.getWrenchToParentBodyNode(W))[3:5]
            out[name] = sg * f
        for r in rods:
            out["rod:" + r.name] = r.tension(W, gravity)
        return out

    # With loops and a moving start, the first two steps' reactions are off by O(1): step 0
    # enforces the loop at velocity level only (it misses the J_dot v part, the
    # error-reduction term that supplies it later is still zero) and step 1 overshoots by
    # about half that; from step 2 on they settle. So the t = 0 reactions are extrapolated
    # linearly from steps 2 and 3 (exact at rest to O(dt^2)).
    extrapolate0 = bool(loops or rods) and k >= 4
    for i in range(T):
        # state at the sample time
        check_state(skel, world, times[i])
        for n in names:
            node = nodes[n]
            M = node.getWorldTransform().matrix()
            if particle[n]:  # frame = its point minus the point's body coordinates
                p = pts[n]
                origin[n][i] = M[:2, :2] @ p + M[:2, 3] - p
                vel[n][i] = np.asarray(node.getLinearVelocity(_v3(p), W, W))[:2]
            else:
                origin[n][i] = M[:2, 3]
                angle[n][i] = _angle_of(M[:2, :2])
                vel[n][i] = np.asarray(node.getLinearVelocity(W, W))[:2]
                omega[n][i] = node.getAngularVelocity(W, W)[2]
        for j in loops:
            gap = np.linalg.norm(_world_point(nodes, case, j.bodies[0], j.points[0])
                                 - _world_point(nodes, case, j.bodies[1], j.points[1]))
            drift = max(drift, gap)
        for r in rods:
            drift = max(drift, r.gap(nodes))
        check_drift(drift, max_drift, times[i])
        # the step that starts here carries the reactions of this instant
        f, done = sample_reactions(lambda: step_and_read(skel, steps, read),
                                   i == 0 and extrapolate0)
        for name in force:
            force[name][i] = f[name]
        for r in rods:
            rod_force[r.name][i] = f["rod:" + r.name]
        for n in names:
            acc[n][i], alpha[n][i] = f["acc:" + n], f["alpha:" + n][0]
        if i + 1 < T:
            steps(k - done)
    for n in names:
        angle[n] = np.unwrap(angle[n])
    for name, f in list(force.items()) + list(rod_force.items()):
        if not np.all(np.isfinite(f)):
            raise RuntimeError(f"DART returned a non-finite force at {name!r}")
    counters = {"steps": clock["steps"], "loop_drift_max_m": float(drift)}
    motion = make_motion(times.copy(), origin, angle, vel, omega, force, acceleration=acc,
                         alpha=alpha, rod_force=rod_force)
    return motion, clock["wall"], clock["steps"], counters
