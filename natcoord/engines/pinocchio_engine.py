"""Pinocchio as an engine: a kinematic tree of planar joints, loops closed by rigid constraints.

3-D cases and cases with massless rods or spring-dampers (all reference-frame cases) are
built by :mod:`natcoord.engines.pinocchio_3d`; this module keeps the planar joint cases.

Model
-----
* Tree: :func:`natcoord.engines.tree.spanning_tree`. A loop-closing *prismatic* joint cannot be a
  ``CONTACT_3D`` constraint (that pins a point), so when the natural tree leaves one, the tree
  is rebuilt with prismatic joints tried first; the joint cut instead is a revolute one. For a
  non-redundant loop the reactions do not depend on where it is cut.
* Revolute -> ``JointModelRZ`` placed at the parent's joint point, q = relative angle.
  Prismatic -> ``JointModelPX/PY`` or ``JointModelPrismaticUnaligned`` along the axis in the
  parent frame, q = displacement of the child's joint point; the child keeps its assembled
  angle relative to the parent.
* Each body's natcoord frame is a fixed placement ``X_b`` in its Pinocchio joint frame; its mass
  and inertia are appended there. Only the z inertia matters in the plane; the others are a
  slender rod's (tiny axial term so the 3x3 stays positive definite). A particle gets a tiny
  inertia (``particle_inertia`` kg m^2 per kg) that nothing can torque, so its absolute
  rotation stays constant and does not feed back.
* Loop-closing revolute joints: ``RigidConstraintModel(CONTACT_3D)`` between the two bodies at
  the joint point, ``LOCAL``. Planar motion leaves its z row all zero, hence ``mu > 0``.
* Integration: classic RK4 on (q, v), four ``constraintDynamics`` calls a step.

Reactions
---------
``data.lambda_c`` is the force on joint1's contact frame (first body of the case joint), in
that frame's axes: the force on the second body is ``-R_c1 lambda``. Tree joints: ``rnea`` with
the constraint forces (and applied torques) as external forces; ``data.f[i]`` is then the
force of the parent on the subtree through joint i in joint-i axes, rotated to world and
signed with :func:`natcoord.mechanism.tree_orientation`. ``data.f`` after
``constraintDynamics`` is zero, hence the separate ``rnea``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun, merged, steps_per_sample
from .pinocchio_3d import rk4_samples
from .tree import point_loop_tree, tree_orientation

NAME = "pinocchio"
PACKAGE = "pin"
DEFAULTS = {
    "dt": 1e-3,  # RK4 step, s; must divide the case's output_dt
    "mu": 1e-8,  # proximal regularisation of constraintDynamics (> 0: planar zero rows)
    "accuracy": 1e-12,  # proximal absolute accuracy
    "max_iter": 20,  # proximal iteration cap
    "baumgarte_kp": 0.0,  # Baumgarte gains on the loop constraints (1/s^2, 1/s)
    "baumgarte_kd": 0.0,
    "max_drift": 1e-3,  # m: a loop opening more than this is reported as divergence
    "particle_inertia": 1e-6,  # kg m^2 per kg: rotational inertia given to a particle
    # 3-D, rods and springs (pinocchio_3d):
    "rod_mass": 1e-6,  # kg: mass of the light body that stands for a massless rod
    "method": "rk4",  # rk4 | radau (scipy Radau IIA on aba: stiff springs, no loops)
    "rtol": 1e-8,  # Radau tolerances
    "atol": 1e-10,
}


def version() -> str:
    import pinocchio

    return pinocchio.__version__


@dataclass(frozen=True)
class _Loop:
    """A loop-closing joint: its constraint and what maps lambda to world forces."""

    joint: str
    j1: int
    j2: int
    M1: object  # SE3 contact frame in joint1
    M2: object  # SE3 contact frame in joint2


@dataclass(frozen=True)
class _Built:
    """The Pinocchio model of a case and the maps back to natcoord quantities.

    ``frame``: body -> (joint id, SE3 of the natcoord body frame in that joint frame).
    ``tree``: (joint name, pinocchio joint id, sign) with sign from tree_orientation.
    ``tau``: (nv,) generalized applied forces (constant torques), N m or N.
    """

    model: object
    cmodels: object
    loops: list[_Loop]
    frame: dict[str, tuple[int, object]]
    tree: list[tuple[str, int, int]]
    torques: list[tuple[int, float]]
    tau: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    notes: list[str]


def _rot2(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _rot3(a: float) -> np.ndarray:
    R = np.eye(3)
    R[:2, :2] = _rot2(a)
    return R


def _v3(p) -> np.ndarray:
    return np.array([p[0], p[1], 0.0])


def _tree_of(case: Case):
    tree, loops, recut = point_loop_tree(case, "a rigid point constraint cannot slide")
    notes = []
    if recut:
        notes.append("loop-closing prismatic joint moved into the tree (prismatic joints first); "
                     f"loops cut at {', '.join(j.name for j in loops)} instead")
    return tree, loops, notes


def _depth_first(tree):
    """Tree joints reordered depth-first: Pinocchio's algorithms (crba, Jacobians) assume
    the joints of every subtree contiguous, which breadth-first order breaks as soon as the
    tree branches below its root (wrong mass matrix, no error)."""
    seen, edge = {GROUND}, {}
    for j in tree:
        a, b = j.bodies
        edge[j.name] = (a, b) if a in seen else (b, a)
        seen.add(edge[j.name][1])
    kids: dict[str, list] = {}
    for j in tree:
        kids.setdefault(edge[j.name][0], []).append(j)
    order = []

    def visit(body):
        for j in kids.get(body, ()):
            order.append(j)
            visit(edge[j.name][1])

    visit(GROUND)
    return order


def _inertia(pin, body, X, s) -> object:
    """Spatial inertia of a natcoord body expressed in its joint frame (X: body frame there)."""
    if body.kind == "particle":
        I3 = np.eye(3) * s["particle_inertia"] * body.mass
    else:
        pts = list(body.points.values())
        d = _v3((pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0]))
        Izz = body.inertia
        # slender rod along d: Izz about both transverse axes, ~0 about d (kept definite).
        # Izz = 0 is a point mass at the centre of mass: exact, and the joint still sees
        # m r^2 as long as the mass is off its axis (Pinocchio's ABA reports otherwise).
        I3 = Izz * (np.eye(3) - np.outer(d, d)) + 1e-3 * Izz * np.outer(d, d)
    R = X.rotation
    return pin.Inertia(body.mass, X.act(_v3(body.com)), R @ I3 @ R.T)


def build(case: Case, init, s: dict) -> _Built:
    """Pinocchio model, loop constraints and initial (q, v) of a 2-D case."""
    import pinocchio as pin

    if case.dimension != 2:
        raise Unsupported(f"dimension {case.dimension}: the adapter models planar cases only")
    if getattr(case, "drivers", ()):
        raise Unsupported("drivers (prescribed motions) are not modelled by this adapter")
    for f in case.forces:
        if f.type != "torque":
            raise Unsupported(f"force type {f.type!r}")
        if case.body(f.body).kind == "particle":
            raise Unsupported(f"torque on particle {f.body!r}")
    tree, loops, notes = _tree_of(case)
    tree = _depth_first(tree)
    points = {b.name: b.points for b in case.bodies} | {GROUND: case.ground}
    angle0 = {n: st.angle for n, st in init.items()} | {GROUND: 0.0}
    omega0 = {n: st.omega for n, st in init.items()} | {GROUND: 0.0}

    def world_point(b, p):  # position and velocity of body point p (2,) at init
        if b == GROUND:
            return p, np.zeros(2)
        st = init[b]
        rp = _rot2(st.angle) @ p
        return st.origin + rp, st.velocity + st.omega * np.array([-rp[1], rp[0]])

    model = pin.Model()
    model.gravity = pin.Motion(np.r_[_v3(case.gravity), 0.0, 0.0, 0.0])
    frame = {GROUND: (0, pin.SE3.Identity())}
    q0, v0, tree_out = [], [], []
    for jt in tree:
        # orient from the case's own joint: its axis lives in its first body's frame
        j = case.joint(jt.name)
        sign = 1 if j.bodies[0] in frame else -1
        parent, child = j.bodies[::sign]
        if tree_orientation(j, parent) != sign or child in frame:
            raise AssertionError(f"joint {j.name!r} is not a tree edge from {parent!r}")
        pp, pc = (points[b][p] for b, p in zip(j.bodies[::sign], j.points[::sign], strict=True))
        jp, Xp = frame[parent]
        rel = angle0[child] - angle0[parent]
        placement = Xp * pin.SE3(np.eye(3), _v3(pp))
        if j.type == "revolute":
            jm, Rc, qj = pin.JointModelRZ(), np.eye(3), rel
            vj = omega0[child] - omega0[parent]
        else:
            axis_w = _rot2(angle0[j.bodies[0]]) @ j.axis
            u = _rot2(angle0[parent]).T @ axis_w
            u /= np.linalg.norm(u)
            if np.allclose(u, [1, 0], atol=1e-14):
                jm = pin.JointModelPX()
            elif np.allclose(u, [0, 1], atol=1e-14):
                jm = pin.JointModelPY()
            else:
                jm = pin.JointModelPrismaticUnaligned(_v3(u))
            Rc = _rot3(rel)
            rP, vP = world_point(parent, pp)
            rC, vC = world_point(child, pc)
            uw = _rot2(angle0[parent]) @ u
            qj, vj = float((rC - rP) @ uw), float((vC - vP) @ uw)
        jid = model.addJoint(jp, jm, placement, f"{j.name}")
        Xc = pin.SE3(Rc, -Rc @ _v3(pc))
        frame[child] = (jid, Xc)
        model.appendBodyToJoint(jid, _inertia(pin, case.body(child), Xc, s), pin.SE3.Identity())
        q0.append(qj)
        v0.append(vj)
        tree_out.append((j.name, jid, sign))

    free = [x.name for x in case.bodies if x.name not in frame]
    if free:
        raise Unsupported(f"body(ies) {', '.join(free)} not joined to the ground: the adapter "
                          "builds no free-floating base")

    cmodels = pin.StdVec_RigidConstraintModel()
    loop_out = []
    for jl in loops:
        j = case.joint(jl.name)
        (a, b), (pa, pb) = j.bodies, j.points
        (j1, X1), (j2, X2) = frame[a], frame[b]
        M1, M2 = X1 * pin.SE3(np.eye(3), _v3(points[a][pa])), \
            X2 * pin.SE3(np.eye(3), _v3(points[b][pb]))
        cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, j1, M1, j2, M2,
                                      pin.ReferenceFrame.LOCAL)
        if s["baumgarte_kp"] or s["baumgarte_kd"]:
            cm.setBaumgarteCorrectorParameters(
                pin.BaumgarteCorrectorParameters(float(s["baumgarte_kp"]),
                                                 float(s["baumgarte_kd"])))
        cm.name = j.name
        cmodels.append(cm)
        loop_out.append(_Loop(j.name, j1, j2, M1, M2))

    torques = [(frame[f.body][0], f.value) for f in case.forces]
    tau = np.zeros(model.nv)
    if torques:
        data = model.createData()
        pin.computeJointJacobians(model, data, np.array(q0))
        for jid, value in torques:
            J = pin.getJointJacobian(model, data, jid, pin.ReferenceFrame.LOCAL)
            tau += J[5] * value  # a pure moment about z: planar, so constant in q
    spinning = [case.body(name).name for name, (jid, _) in frame.items() if name != GROUND
                and case.body(name).kind == "particle"
                and model.joints[jid].shortname() == "JointModelRZ"]
    if spinning:
        notes.append(f"particle(s) {', '.join(spinning)} on a revolute tree joint get a "
                     f"rotational inertia of {s['particle_inertia']:g} kg m^2/kg (a free, "
                     "untorqued rotation that does not feed back)")
    if loop_out:
        notes.append(f"loops ({', '.join(lp.joint for lp in loop_out)}) closed by "
                     f"RigidConstraintModel CONTACT_3D (LOCAL), proximal mu {s['mu']:g}")
    notes.append(f"classic RK4, dt {s['dt']:g} s, 4 constraintDynamics calls a step")
    return _Built(model, cmodels, loop_out, frame, tree_out, torques, tau, np.array(q0),
                  np.array(v0), notes)


def run(case: Case, init, settings: dict) -> EngineRun:
    import pinocchio as pin

    s = merged(DEFAULTS, settings)
    if case.dimension == 3 or case.rods or case.springs:
        from . import pinocchio_3d

        return pinocchio_3d.run(case, init, s)
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    t0 = time.perf_counter()
    b = build(case, init, s)
    model, cmodels = b.model, b.cmodels
    data = model.createData()
    cdatas = pin.StdVec_RigidConstraintData()
    for cm in cmodels:
        cdatas.append(cm.createData())
    pin.initConstraintDynamics(model, data, cmodels, cdatas)
    prox = pin.ProximalSettings(float(s["accuracy"]), float(s["mu"]), int(s["max_iter"]))
    build_time = time.perf_counter() - t0

    times = case.times
    tau = b.tau
    iters = 0

    def acc(q, v):
        nonlocal iters
        a = pin.constraintDynamics(model, data, q, v, tau, cmodels, cdatas, prox).copy()
        iters = max(iters, prox.iter)
        return a

    t0 = time.perf_counter()
    Q, V, A, L, n_steps = rk4_samples(acc, lambda: data.lambda_c, lambda q, dv: q + dv,
                                      b.q0, b.v0, model.nv, 3 * len(b.loops), times, k, dt,
                                      f", mu {s['mu']:g}")
    wall = time.perf_counter() - t0

    motion, drift = _motion(pin, case, b, times, Q, V, A, L)
    if drift[0] > s["max_drift"]:
        raise RuntimeError(f"pinocchio: a loop opened by {drift[0]:.3g} m (> max_drift "
                           f"{s['max_drift']:g} m); reduce dt or add Baumgarte gains")
    counters = {"steps": n_steps, "rhs": 4 * n_steps + 1, "prox_iter_max": iters,
                "drift_max_m": drift[0], "velocity_drift_max_m_s": drift[1]}
    notes = list(b.notes)
    if iters >= int(s["max_iter"]) and b.loops:
        notes.append(f"the proximal solver hit its cap of {s['max_iter']} iterations "
                     "(redundant loops?): constraint forces may be unconverged")
    return EngineRun(motion, build_time, wall, n_steps, s, counters, notes)


def _motion(pin, case: Case, b: _Built, times, Q, V, A, L):
    """Neutral motion from sampled (q, v, a, lambda) and the loop drift (position, velocity)."""
    model = b.model
    data = model.createData()
    T = len(times)
    bodies = [x.name for x in case.bodies]
    origin = {n: np.empty((T, 2)) for n in bodies}
    velocity = {n: np.empty((T, 2)) for n in bodies}
    angle = {n: np.zeros(T) for n in bodies}
    omega = {n: np.zeros(T) for n in bodies}
    forces = {j: np.empty((T, 2)) for j in [x.name for x in case.joints]}
    drift = np.zeros(2)
    zero3 = np.zeros(3)
    for i in range(T):
        q, v = Q[i], V[i]
        pin.forwardKinematics(model, data, q, v)
        for x in case.bodies:
            jid, X = b.frame[x.name]
            oMi = data.oMi[jid]
            R = oMi.rotation
            if x.kind == "particle":  # frame never turns: follow its (only) point
                p = _v3(next(iter(x.points.values())))
                pl = X.act(p)
                vel = data.v[jid]
                origin[x.name][i] = oMi.act(pl)[:2] - p[:2]
                velocity[x.name][i] = (R @ (vel.linear + np.cross(vel.angular, pl)))[:2]
                continue
            oMb = oMi * X
            vel = data.v[jid]
            origin[x.name][i] = oMb.translation[:2]
            velocity[x.name][i] = (R @ (vel.linear + np.cross(vel.angular, X.translation)))[:2]
            angle[x.name][i] = np.arctan2(oMb.rotation[1, 0], oMb.rotation[0, 0])
            omega[x.name][i] = (R @ vel.angular)[2]
        fext = pin.StdVec_Force()
        for _ in range(model.njoints):
            fext.append(pin.Force.Zero())
        for n, lp in enumerate(b.loops):
            lam = L[i, 3 * n:3 * n + 3]
            oMc1, oMc2 = data.oMi[lp.j1] * lp.M1, data.oMi[lp.j2] * lp.M2
            fw = oMc1.rotation @ lam  # force on body 1's contact point, world axes
            fext[lp.j1] = fext[lp.j1] + lp.M1.act(pin.Force(lam, zero3))
            fext[lp.j2] = fext[lp.j2] + lp.M2.act(pin.Force(-oMc2.rotation.T @ fw, zero3))
            forces[lp.joint][i] = -fw[:2]
            drift[0] = max(drift[0], np.linalg.norm(oMc1.translation - oMc2.translation))
            vc1 = oMc1.rotation @ lp.M1.actInv(data.v[lp.j1]).linear
            vc2 = oMc2.rotation @ lp.M2.actInv(data.v[lp.j2]).linear
            drift[1] = max(drift[1], np.linalg.norm(vc1 - vc2))
        for jid, value in b.torques:
            fext[jid] = fext[jid] + pin.Force(zero3, np.array([0.0, 0.0, value]))
        pin.rnea(model, data, q, v, A[i], fext)
        for name, jid, sign in b.tree:
            forces[name][i] = sign * (data.oMi[jid].rotation @ data.f[jid].linear)[:2]
    for x in case.bodies:
        angle[x.name] = np.unwrap(angle[x.name])
    return Motion(np.asarray(times), origin, angle, velocity, omega, forces), drift
