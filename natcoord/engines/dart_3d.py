"""DART adapter, 3-D cases and the light-body substitute for massless rods (used in 2-D too).

Modelling (every choice is also written into ``EngineRun.notes``):

* Reference-frame cases only (every body frame is the world frame at t = 0): each body is
  built at its world position with identity orientation, so every tree joint starts at
  position 0 and only rates come from natcoord's ``init``.
* The spanning tree is :func:`natcoord.engines.tree.point_loop_tree` (the 2-D adapter's rule):
  revolute joints about their axis (``RevoluteJoint``), spherical joints ``BallJoint``;
  bodies the tree does not reach get a ``FreeJoint``.
* A loop-closing spherical joint is a ``BallJointConstraint``; so is a loop-closing revolute
  joint when every revolute joint of the case has the same axis (a planar loop: the tree
  already keeps the loop's bodies turning about that axis and the constraint's rotation
  rows would be redundant). Otherwise a ``RevoluteJointConstraint`` is needed
  (``loop_constraint = "revolute"``; it diverges at a high error-reduction parameter).
* A slender rod (``uniform_rod``) has no inertia about its own axis; DART needs a positive
  definite inertia, so ``axial_inertia`` times its transverse inertia is added about it.
* A massless rod (``[[rods]]``) becomes a light uniform rod of ``rod_mass`` kg: a tree joint
  at its first end (revolute about z in 2-D, ball in 3-D; the ground end first when there is
  one) and a ``BallJointConstraint`` at its other end. Its axial force is the force its tree
  joint applies to it, projected on the rod, plus half its own inertial load
  (``-F_joint . u + m/2 (a_G - g) . u``: the mid-length value).
* Spring-dampers (``[[springs]]``) are external forces (``addExtForce``) computed from the
  state at the start of every step: explicit in DART's semi-implicit Euler, so the step has
  to resolve the damping (h c / m well below 2).
* Loop-joint forces: Newton-Euler of a body that only that joint closes, as in 2-D.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun, steps_per_sample
from .tree import point_loop_tree, tree_orientation, tree_parents


def iso(dart, p, R=None):
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[: len(p), 3] = p
    out = dart.math.Isometry3()
    out.set_matrix(T)
    return out


def slender_inertia(mass: float, a: np.ndarray, b: np.ndarray, axial: float) -> np.ndarray:
    """Uniform rod a-b (3-D points): m L^2 / 12 across, ``axial`` times that along it."""
    d = b - a
    L = float(np.linalg.norm(d))
    e = d / L
    return mass * L**2 / 12 * (np.eye(3) - (1.0 - axial) * np.outer(e, e))


def point3(case: Case, body: str, name: str) -> np.ndarray:
    x = np.asarray(case.ground[name] if body == GROUND else case.body(body).points[name], float)
    return np.append(x, 0.0) if x.size == 2 else x


def point_local(body: str, name: str, case: Case) -> np.ndarray:
    """A body point in its body frame, as a 3-vector (2-D points get z = 0)."""
    return point3(case, body, name)


# ---- massless rods as light bodies (2-D and 3-D) ------------------------------------------
class LightRod:
    """A ``[[rods]]`` entry built as a light body: tree joint at ``ends[0]``, ball constraint
    at ``ends[1]`` (ends reordered so that a ground end carries the tree joint)."""

    def __init__(self, rod, case: Case):
        ends = rod.ends if rod.ends[1][0] != GROUND else rod.ends[::-1]
        self.name, self.ends, self.length = rod.name, ends, float(rod.length)
        self.p0, self.p1 = point3(case, *ends[0]), point3(case, *ends[1])
        self.node = self.joint = None
        self._case = case

    def build(self, dart, skel, nodes: dict, mass: float, axial: float, planar: bool):
        parent = None if self.ends[0][0] == GROUND else nodes[self.ends[0][0]]
        if planar:
            joint, node = skel.createRevoluteJointAndBodyNodePair(parent)
            joint.setAxis(np.array([0.0, 0.0, 1.0]))
        else:
            joint, node = skel.createBallJointAndBodyNodePair(parent)
        joint.setTransformFromParentBodyNode(iso(dart, self.p0))
        joint.setTransformFromChildBodyNode(iso(dart, self.p0))
        joint.setName(f"rod {self.name}")
        node.setName(f"rod {self.name}")
        node.setInertia(dart.dynamics.Inertia(mass, (self.p0 + self.p1) / 2,
                                              slender_inertia(mass, self.p0, self.p1, axial)))
        self.node, self.joint, self.mass = node, joint, mass
        return node

    def constraint(self, dart, nodes: dict):
        """The BallJointConstraint at the far end (create it once the state is set)."""
        other = self.ends[1][0]
        if other == GROUND:
            return dart.constraint.BallJointConstraint(self.node, self.p1)
        return dart.constraint.BallJointConstraint(self.node, nodes[other], self.p1)

    def gap(self, nodes: dict) -> float:
        """Distance between the rod's far end and its point on the other body."""
        M = self.node.getWorldTransform().matrix()
        x = M[:3, :3] @ self.p1 + M[:3, 3]
        b = self.ends[1][0]
        if b != GROUND:
            N = nodes[b].getWorldTransform().matrix()
            p = np.asarray(point_local(b, self.ends[1][1], self._case))
            y = N[:3, :3] @ p + N[:3, 3]
        else:
            y = self.p1
        return float(np.linalg.norm(x - y))

    def set_rate(self, omega_of, vel_of, planar: bool):
        """Joint rate with both ends moving as natcoord assembled them (no spin)."""
        v0, w0 = vel_of(self.ends[0][0], self.p0), omega_of(self.ends[0][0])
        v1 = vel_of(self.ends[1][0], self.p1)
        d = self.p1 - self.p0
        w = np.cross(d, v1 - v0) / (d @ d)  # identity orientation at t = 0
        if planar:
            self.joint.setVelocity(0, float(w[2] - w0[2]))
        else:
            self.joint.setVelocities(w - w0)

    def axis(self) -> np.ndarray:
        R = self.node.getWorldTransform().rotation()
        d = R @ (self.p1 - self.p0)
        return d / np.linalg.norm(d)

    def tension(self, W, g3: np.ndarray) -> float:
        """At the state the skeleton holds, with the last step's accelerations."""
        u = self.axis()
        f = np.asarray(self.joint.getWrenchToParentBodyNode(W))[3:]
        a = np.asarray(self.node.getCOMLinearAcceleration(W, W))
        return float(-f @ u + 0.5 * self.mass * (a - g3) @ u)


ROD_NOTE = ("massless rod(s) {names}: light uniform rods of {m:g} kg (DART has no distance "
            "constraint; bodies need mass), {joint} joint at one end and a "
            "BallJointConstraint at the other; axial force from the rod's joint force "
            "projected on the rod plus half its inertial load")


# ---- shared by the 2-D adapter (dart_engine) and the 3-D one below -----------------------
def loop_bodies(loops, rods, notes: list) -> dict[str, tuple[str, int]]:
    """Loop joint -> (body only it closes, sign): its force by that body's Newton-Euler
    balance (rod ends count as closing); notes the joints without one."""
    closing: dict[str, int] = {}
    for x in [b for j in loops for b in j.bodies] + [r.ends[1][0] for r in rods]:
        closing[x] = closing.get(x, 0) + 1
    loop_body: dict[str, tuple[str, int]] = {}
    for j in loops:
        for x, sg in ((j.bodies[1], 1), (j.bodies[0], -1)):
            if x != GROUND and closing[x] == 1:
                loop_body[j.name] = (x, sg)
                break
        else:
            notes.append(f"loop joint {j.name!r}: no body closed by it alone; its force is "
                         "not reported")
    if loop_body:
        notes.append("loop-joint force(s) " + ", ".join(loop_body) + " from the Newton-Euler "
                     "balance of the body (DART does not expose constraint impulses)")
    return loop_body


def simulate_with_erp(dart, s: dict, notes: list, dt: float, extrapolated: bool, simulate):
    """``simulate()`` with the settings' error reduction on every joint constraint (restored
    afterwards), and the integrator's note."""
    JC = dart.constraint.DynamicJointConstraint  # statics of Ball/Weld/RevoluteJointConstraint
    saved = (JC.getErrorReductionParameter(), JC.getMaxErrorReductionVelocity())
    JC.setErrorReductionParameter(float(s["erp"]))
    JC.setMaxErrorReductionVelocity(float(s["max_error_reduction_velocity"]))
    try:
        result = simulate()
    finally:
        JC.setErrorReductionParameter(saved[0])
        JC.setMaxErrorReductionVelocity(saved[1])
    notes.append(f"semi-implicit Euler (DART's only integrator, first order), dt {dt:g} s; "
                 "reactions and accelerations are those of the step starting at each sample "
                 "time" + (", at t = 0 extrapolated from steps 2 and 3 (the first two steps "
                           "of a loop constraint are transients)" if extrapolated else ""))
    return result


def stepper(world, before_step):
    """``steps(n)``: n world steps, ``before_step()`` ahead of each; wall time and count in
    the returned clock."""
    clock = {"wall": 0.0, "steps": 0}

    def steps(n):
        t0 = time.perf_counter()
        for _ in range(n):
            before_step()
            world.step()
        clock["wall"] += time.perf_counter() - t0
        clock["steps"] += n

    return steps, clock


def step_and_read(skel, steps, read) -> dict:
    """One step; ``read()`` of the reactions it carries, at the state it started from
    (accelerations stay (v1 - v0) / dt as DART left them); then on from the step's end."""
    q, qd = skel.getPositions(), skel.getVelocities()
    steps(1)
    q1, qd1 = skel.getPositions(), skel.getVelocities()
    skel.setPositions(q)
    skel.setVelocities(qd)
    out = read()
    skel.setPositions(q1)
    skel.setVelocities(qd1)
    return out


def check_state(skel, world, t: float) -> None:
    q, qd = skel.getPositions(), skel.getVelocities()
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
        raise RuntimeError(f"DART diverged: NaN/inf state at t = {t:.4g} s "
                           f"(dt {world.getTimeStep():g} s)")


def check_drift(drift: float, max_drift: float, t: float) -> None:
    if drift > max_drift or not np.isfinite(drift):
        raise RuntimeError(f"DART diverged: loop joint gap {drift:.3g} m exceeds "
                           f"{max_drift:g} m by t = {t:.4g} s")


def sample_reactions(read, extrapolate: bool) -> tuple[dict, int]:
    """The reactions at a sample and the steps taken: with loops and a moving start, the
    first two steps' reactions are off by O(1) (step 0 enforces the loop at velocity level
    only, step 1 overshoots by about half that), so at t = 0 (``extrapolate``) they are
    extrapolated linearly from steps 2 and 3 (exact at rest to O(dt^2))."""
    f = read()
    if not extrapolate:
        return f, 1
    read()
    f2, f3 = read(), read()
    return {name: 3 * f2[name] - 2 * f3[name] for name in f}, 4


# ---- 3-D ----------------------------------------------------------------------------------
def _planar_revolutes(case: Case) -> bool:
    axes = [np.asarray(j.axis, float) for j in case.joints if j.type == "revolute"]
    return all(abs(abs(a @ axes[0]) - np.linalg.norm(a) * np.linalg.norm(axes[0])) < 1e-12
               for a in axes)


def make_world(dart, skel, gravity, dt: float, rods, nodes):
    """A DART world (gravity (3,) m/s^2, time step dt s) holding ``skel`` and the light
    rods' end constraints; returns (world, its constraint solver)."""
    world = dart.simulation.World()
    world.setGravity(gravity)
    world.setTimeStep(dt)
    world.addSkeleton(skel)
    solver = world.getConstraintSolver()
    for r in rods:
        solver.addConstraint(r.constraint(dart, nodes))
    return world, solver


def run_3d(case: Case, init, s: dict) -> EngineRun:
    import dartpy as dart

    if not getattr(case, "reference_frame", False):
        raise Unsupported("the DART adapter builds 3-D cases from world positions at t = 0 "
                          "(reference-frame cases only)")
    if getattr(case, "drivers", ()):
        raise Unsupported("drivers (prescribed motions) are not modelled by the DART adapter")
    for b in case.bodies:
        if not b.mass > 0:
            raise Unsupported(f"body {b.name!r} has no mass; DART bodies need a positive mass")
        if b.kind == "particle":
            raise Unsupported(f"particle {b.name!r} in a 3-D case")
    for j in case.joints:
        if j.type not in ("revolute", "spherical"):
            raise Unsupported(f"joint type {j.type!r} of joint {j.name!r} in 3-D")
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    axial = float(s["axial_inertia"])
    notes: list[str] = []

    t0 = time.perf_counter()
    tree, loops, _ = point_loop_tree(case, "DART has no prismatic joint constraint")
    planar = _planar_revolutes(case)
    ball_loops = [j for j in loops if j.type == "spherical"
                  or (s["loop_constraint"] == "ball" and planar)]
    rev_loops = [j for j in loops if j not in ball_loops]
    if rev_loops and s["loop_constraint"] != "revolute":
        raise Unsupported(
            f"loop joint(s) {', '.join(j.name for j in rev_loops)}: revolute joints with "
            "different axes close the loop, a BallJointConstraint would drop their rotation "
            "rows (setting loop_constraint = 'revolute' uses DART's RevoluteJointConstraint)")
    g3 = np.asarray(case.gravity, float)

    skel = dart.dynamics.Skeleton(case.name)
    nodes, joints, sign = {}, {}, {}
    children: dict[str, list] = {}
    slender = []
    for j, parent, child in tree_parents(tree):
        pnode = None if parent == GROUND else nodes[parent]
        x = point3(case, child, j.points[j.bodies.index(child)])
        if j.type == "revolute":
            joint, node = skel.createRevoluteJointAndBodyNodePair(pnode)
            joint.setAxis(np.asarray(j.axis, float) / np.linalg.norm(j.axis))
        else:
            joint, node = skel.createBallJointAndBodyNodePair(pnode)
        joint.setTransformFromParentBodyNode(iso(dart, x))
        joint.setTransformFromChildBodyNode(iso(dart, x))
        joint.setName(j.name)
        nodes[child], joints[j.name] = node, joint
        sign[j.name] = tree_orientation(case.joint(j.name), parent)
        children.setdefault(parent, []).append(joint)
    for b in case.bodies:
        if b.name not in nodes:
            joint, node = skel.createFreeJointAndBodyNodePair(None)
            joint.setName(f"free {b.name}")
            nodes[b.name] = node
            notes.append(f"body {b.name!r} is not joined to the ground by the tree: DART "
                         "FreeJoint")
    for b in case.bodies:
        node = nodes[b.name]
        node.setName(b.name)
        J = np.asarray(b.inertia, float)
        if b.kind == "uniform_rod":
            e0, e1 = b.ends or list(b.points)[:2]
            J = slender_inertia(b.mass, b.points[e0], b.points[e1], axial)
            slender.append(b.name)
        node.setInertia(dart.dynamics.Inertia(b.mass, np.asarray(b.com, float), J))
    if slender:
        notes.append(f"slender rod(s) {', '.join(slender)}: inertia about the rod axis "
                     f"{axial:g} x the transverse one (DART needs it positive definite)")

    rods = [LightRod(r, case) for r in case.rods]
    for r in rods:
        r.build(dart, skel, nodes, float(s["rod_mass"]), axial, planar=False)
        if r.ends[0][0] != GROUND:
            children.setdefault(r.ends[0][0], []).append(r.joint)
    if rods:
        notes.append(ROD_NOTE.format(names=", ".join(r.name for r in rods), m=s["rod_mass"],
                                     joint="ball"))
    _set_initial_rates(case, init, tree, nodes, joints, rods)
    _check_assembly(case, nodes, init)
    world, solver = make_world(dart, skel, g3, dt, rods, nodes)
    for j in loops:
        pos = point3(case, j.bodies[1], j.points[1])
        ends = [nodes[x] for x in j.bodies if x != GROUND]
        if j in ball_loops:
            c = dart.constraint.BallJointConstraint(*ends, pos)
        else:
            axis = np.asarray(j.axis, float)
            c = (dart.constraint.RevoluteJointConstraint(*ends, pos, axis, axis)
                 if len(ends) == 2 else dart.constraint.RevoluteJointConstraint(*ends, pos, axis))
        solver.addConstraint(c)
    if ball_loops:
        why = ("" if all(j.type == "spherical" for j in ball_loops) else
               " (every revolute axis is parallel: the loop is planar and the tree keeps its "
               "rotations, so only the point rows are needed)")
        notes.append(f"loop joint(s) {', '.join(j.name for j in ball_loops)}: DART "
                     f"BallJointConstraint, error-reduction parameter {s['erp']}{why}")
    if rev_loops:
        notes.append(f"loop joint(s) {', '.join(j.name for j in rev_loops)}: DART "
                     f"RevoluteJointConstraint, error-reduction parameter {s['erp']}")

    loop_body = loop_bodies(loops, rods, notes)
    loads = _loads(case, nodes)
    if case.springs:
        notes.append("spring-dampers " + ", ".join(sp.name for sp in case.springs) + ": "
                     "external forces from the state at the start of each step (explicit)")
    build = time.perf_counter() - t0

    out, wall, n_steps, counters = simulate_with_erp(
        dart, s, notes, dt, bool(loops or rods) and k >= 4, lambda: _simulate(
            case, world, skel, nodes, joints, sign, children, loops, loop_body, rods, loads,
            g3, k, float(s["max_drift"])))
    return EngineRun(out, build, wall, n_steps, s, counters, notes)


def _state(init, body):
    if body == GROUND:
        return np.zeros(3), np.zeros(3)
    st = init[body]
    return np.asarray(st.velocity, float), np.asarray(st.omega, float)


def _set_initial_rates(case, init, tree, nodes, joints, rods) -> None:
    """All frames are the world at t = 0: joint positions 0, rates from ``init``."""

    def omega_of(body):
        return _state(init, body)[1]

    def vel_of(body, p):
        v, w = _state(init, body)
        return v + np.cross(w, p)  # origin of every frame at the world origin

    for j in tree:
        joint = joints[j.name]
        a, b = j.bodies
        wr = omega_of(b) - omega_of(a)
        if j.type == "revolute":
            axis = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
            parent = joint.getParentBodyNode()
            pname = GROUND if parent is None else parent.getName()
            joint.setVelocity(0, float(axis @ wr) * (1 if pname == a else -1))
        else:
            joint.setVelocities(wr if joint.getParentBodyNode() is None
                                or joint.getParentBodyNode().getName() == a else -wr)
    for name, node in nodes.items():
        joint = node.getParentJoint()
        if joint.getType() == "FreeJoint":
            v, w = _state(init, name)
            joint.setVelocities(np.concatenate([w, v]))
    for r in rods:
        r.set_rate(omega_of, vel_of, planar=False)


def _check_assembly(case, nodes, init, tol: float = 1e-7) -> None:
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    for name, node in nodes.items():
        st = init[name]
        T = node.getWorldTransform().matrix()
        R0 = np.eye(3) if getattr(st, "rotation", None) is None else np.asarray(st.rotation)
        errs = (np.linalg.norm(T[:3, 3] - st.origin), np.abs(T[:3, :3] - R0).max(),
                np.linalg.norm(np.asarray(node.getLinearVelocity(W, W)) - st.velocity),
                np.linalg.norm(np.asarray(node.getAngularVelocity(W, W)) - st.omega))
        if max(errs) > tol * max(1.0, np.linalg.norm(st.velocity)):
            raise RuntimeError(
                f"DART adapter: body {name!r} does not match the assembled state (origin "
                "{:.2e} m, rotation {:.2e}, velocity {:.2e} m/s, omega {:.2e} rad/s); 3-D "
                "cases must start with every body frame at the world frame".format(*errs))


_KERNEL = []


def _spring_kernel():
    """Compiled spring-damper loads (numba; plain Python if numba is missing): tension (n,),
    and per body row the resultant force and its moment about the body frame origin."""
    if _KERNEL:
        return _KERNEL[0]
    try:
        from numba import njit
    except ImportError:  # pragma: no cover - numba is a natcoord dependency
        def njit(**_):
            return lambda f: f

    @njit(cache=True)
    def loads(R, o, v, w, b0, P0, b1, P1, k, c, l0):  # pragma: no cover - compiled
        n, nb = k.shape[0], o.shape[0]
        tension = np.zeros(n)
        F, Mo = np.zeros((nb, 3)), np.zeros((nb, 3))
        x = np.zeros((2, 3))
        xd = np.zeros((2, 3))
        r = np.zeros((2, 3))
        for s in range(n):
            for e in range(2):
                b = b0[s] if e == 0 else b1[s]
                P = P0[s] if e == 0 else P1[s]
                if b < 0:
                    for a in range(3):
                        x[e, a], xd[e, a], r[e, a] = P[a], 0.0, 0.0
                    continue
                for a in range(3):
                    r[e, a] = R[b, a, 0] * P[0] + R[b, a, 1] * P[1] + R[b, a, 2] * P[2]
                    x[e, a] = r[e, a] + o[b, a]
                xd[e, 0] = v[b, 0] + w[b, 1] * r[e, 2] - w[b, 2] * r[e, 1]
                xd[e, 1] = v[b, 1] + w[b, 2] * r[e, 0] - w[b, 0] * r[e, 2]
                xd[e, 2] = v[b, 2] + w[b, 0] * r[e, 1] - w[b, 1] * r[e, 0]
            d0, d1, d2 = x[1, 0] - x[0, 0], x[1, 1] - x[0, 1], x[1, 2] - x[0, 2]
            L = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            u0, u1, u2 = d0 / L, d1 / L, d2 / L
            rate = (u0 * (xd[1, 0] - xd[0, 0]) + u1 * (xd[1, 1] - xd[0, 1])
                    + u2 * (xd[1, 2] - xd[0, 2]))
            t = k[s] * (L - l0[s]) + c[s] * rate
            tension[s] = t
            for e in range(2):
                b = b0[s] if e == 0 else b1[s]
                if b < 0:
                    continue
                g = t if e == 0 else -t  # end 0 pulled along +u, end 1 along -u
                f0, f1, f2 = g * u0, g * u1, g * u2
                F[b, 0] += f0
                F[b, 1] += f1
                F[b, 2] += f2
                Mo[b, 0] += r[e, 1] * f2 - r[e, 2] * f1
                Mo[b, 1] += r[e, 2] * f0 - r[e, 0] * f2
                Mo[b, 2] += r[e, 0] * f1 - r[e, 1] * f0
        return tension, F, Mo

    _KERNEL.append(loads)
    return loads


def _loads(case: Case, nodes):
    """Constant forces/torques and springs: a function applying them before a step, and one
    giving each body's applied resultant (for Newton-Euler) at the current state."""
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    const = [(nodes[f.body], f.type, np.asarray(f.value, float) * np.ones(3),
              None if f.point is None else point3(case, f.body, f.point))
             for f in case.forces]
    names = [b.name for b in case.bodies]
    sp_list = list(case.springs)
    # per end side: body index (-1 ground) and the point in body (= world at t = 0) axes
    side = [(np.array([-1 if sp.ends[e][0] == GROUND else names.index(sp.ends[e][0])
                       for sp in sp_list], int),
             np.array([point3(case, *sp.ends[e]) for sp in sp_list]).reshape(-1, 3))
            for e in (0, 1)]
    k_, c_ = (np.array([getattr(sp, a) for sp in sp_list]) for a in ("stiffness", "damping"))
    l0 = np.array([sp.length for sp in sp_list])
    used = sorted({int(i) for idx, _ in side for i in idx if i >= 0})
    slot = {i: n for n, i in enumerate(used)}  # body index -> row of the frame arrays
    sides = [(np.array([slot.get(int(i), -1) for i in idx], np.int64), P) for idx, P in side]
    kernel = _spring_kernel() if sp_list else None
    nb = len(used)
    R_all, o_all = np.zeros((nb, 3, 3)), np.zeros((nb, 3))
    v_all, w_all = np.zeros((nb, 3)), np.zeros((nb, 3))

    def spring_loads():
        """Tension (n,), and per body index (force, moment about its frame origin)."""
        for n, i in enumerate(used):
            node = nodes[names[i]]
            M = node.getWorldTransform().matrix()
            R_all[n], o_all[n] = M[:3, :3], M[:3, 3]
            v_all[n] = node.getLinearVelocity(W, W)
            w_all[n] = node.getAngularVelocity(W, W)
        tension, F, Mo = kernel(R_all, o_all, v_all, w_all, sides[0][0], sides[0][1],
                                sides[1][0], sides[1][1], k_, c_, l0)
        return tension, {i: (F[n], Mo[n]) for n, i in enumerate(used)}

    def spring_forces():
        return spring_loads()[0] if sp_list else np.zeros(0)

    def apply():
        for node, kind, value, p in const:
            if kind == "force":
                node.addExtForce(value, p, False, True)
            else:
                node.addExtTorque(value, False)
        if not sp_list:
            return
        for i, (F, Mo) in spring_loads()[1].items():
            node = nodes[names[i]]
            node.addExtForce(F, np.zeros(3), False, True)
            node.addExtTorque(Mo, False)

    def resultant(node) -> np.ndarray:
        f = np.zeros(3)
        for n, kind, value, _ in const:
            if n is node and kind == "force":
                f += value
        if sp_list:
            for i, (F, _) in spring_loads()[1].items():
                if nodes[names[i]] is node:
                    f += F
        return f

    return apply, resultant, spring_forces


def _simulate(case, world, skel, nodes, joints, sign, children, loops, loop_body, rods,
              loads, g3, k, max_drift):
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    apply, resultant, spring_forces = loads
    times = case.times
    T = len(times)
    names = [b.name for b in case.bodies]
    origin = {n: np.zeros((T, 3)) for n in names}
    rot = {n: np.zeros((T, 3, 3)) for n in names}
    vel = {n: np.zeros((T, 3)) for n in names}
    omega = {n: np.zeros((T, 3)) for n in names}
    acc = {n: np.zeros((T, 3)) for n in names}
    alpha = {n: np.zeros((T, 3)) for n in names}
    force = {name: np.zeros((T, 3)) for name in list(joints) + list(loop_body)}
    rod_force = {r.name: np.zeros(T) for r in rods} | {sp.name: np.zeros(T)
                                                        for sp in case.springs}
    mass = {n: nodes[n].getMass() for n in names}
    loop_pts = [(j.bodies, [point3(case, b, p) for b, p in zip(j.bodies, j.points,
                                                                 strict=True)])
                for j in loops]
    drift = 0.0
    steps, clock = stepper(world, apply)

    def world_point(body, p):
        if body == GROUND:
            return p
        node = nodes[body]
        M = node.getWorldTransform().matrix()
        return M[:3, :3] @ p + M[:3, 3]

    def read():
        out = {}
        Fp = {n: np.asarray(nodes[n].getParentJoint().getWrenchToParentBodyNode(W))[3:]
              for n in names}
        for name, joint in joints.items():
            out[name] = sign[name] * Fp[joint.getChildBodyNode().getName()]
        for n in names:
            out["acc:" + n] = np.asarray(nodes[n].getLinearAcceleration(W, W))
            out["alpha:" + n] = np.asarray(nodes[n].getAngularAcceleration(W, W))
        for name, (b, sg) in loop_body.items():
            a = np.asarray(nodes[b].getCOMLinearAcceleration(W, W))
            f = mass[b] * (a - g3) - Fp[b] - resultant(nodes[b])
            for cj in children.get(b, []):
                f = f + np.asarray(cj.getWrenchToParentBodyNode(W))[3:]
            out[name] = sg * f
        for r in rods:
            out[r.name] = r.tension(W, g3)
        return out

    extrapolate0 = bool(loops or rods) and k >= 4
    for i in range(T):
        check_state(skel, world, times[i])
        for n in names:
            node = nodes[n]
            M = node.getWorldTransform().matrix()
            origin[n][i], rot[n][i] = M[:3, 3], M[:3, :3]
            vel[n][i] = np.asarray(node.getLinearVelocity(W, W))
            omega[n][i] = np.asarray(node.getAngularVelocity(W, W))
        for (a, b), (pa, pb) in loop_pts:
            drift = max(drift, float(np.linalg.norm(world_point(a, pa) - world_point(b, pb))))
        for r in rods:
            drift = max(drift, r.gap(nodes))
        check_drift(drift, max_drift, times[i])
        for sp, tension in zip(case.springs, spring_forces(), strict=True):
            rod_force[sp.name][i] = tension
        f, done = sample_reactions(lambda: step_and_read(skel, steps, read),
                                   i == 0 and extrapolate0)
        for name in force:
            force[name][i] = f[name]
        for r in rods:
            rod_force[r.name][i] = f[r.name]
        for n in names:
            acc[n][i], alpha[n][i] = f["acc:" + n], f["alpha:" + n]
        if i + 1 < T:
            steps(k - done)
    for name, f in list(force.items()) + list(rod_force.items()):
        if not np.all(np.isfinite(f)):
            raise RuntimeError(f"DART returned a non-finite force for {name!r}")
    counters = {"steps": clock["steps"], "loop_drift_max_m": float(drift)}
    motion = make_motion(times.copy(), origin, {}, vel, omega, force, rotation=rot,
                         rod_force=rod_force, acceleration=acc, alpha=alpha)
    return motion, clock["wall"], clock["steps"], counters


def make_motion(t, origin, angle, vel, omega, force, **extra) -> Motion:
    """A Motion with the optional fields this natcoord version has (empty ones dropped)."""
    import dataclasses

    have = {f.name for f in dataclasses.fields(Motion)}
    return Motion(t, origin, angle, vel, omega, force,
                  **{k: v for k, v in extra.items() if k in have and v})


