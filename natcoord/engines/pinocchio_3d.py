"""Pinocchio for reference-frame cases: 3-D joints, massless rods, spring-dampers.

Used by :mod:`natcoord.engines.pinocchio_engine` for every case that is 3-D or has rods or
springs. These cases give every point at its world position at t = 0 and every body frame
equal to the world frame there, so the model is built in that configuration: every
Pinocchio joint frame is world-aligned at q = neutral, placed at its joint point.

Model
-----
* Tree: breadth-first from the ground over the case joints (file order), added to the
  model depth-first (Pinocchio's algorithms assume every subtree's joints contiguous). A
  body no joint reaches floats on ``JointModelTranslation`` + ``JointModelSphericalZYX``
  (3-D only; six scalar dofs, so the state stays a vector: ZYX angles are singular at 90
  deg pitch, far from anything here).
* Revolute: ``JointModelRZ`` (2-D), ``JointModelRX/RY/RZ`` or ``JointModelRevoluteUnaligned``
  along ``axis`` (3-D). Spherical: ``JointModelSpherical``.
* Loop-closing revolute (2-D) or spherical joint: ``RigidConstraintModel(CONTACT_3D)`` at the
  joint point. A 3-D revolute loop is accepted only when the tree path between its bodies is
  made of revolutes parallel to it (then CONTACT_3D loses nothing: the alignment holds
  already); otherwise Unsupported (CONTACT_6D would also lock the rotation).
* Massless rod (``constraintDynamics`` has no distance constraint): a *light body*, a slender
  rod of mass ``rod_mass`` kg on a revolute (2-D) or universal (3-D: two axes normal to the
  rod, so it cannot spin about itself) joint at one end (the end whose body is nearer the
  ground), closed at the other end by CONTACT_3D. Its inertia is the substitute's cost, bounded
  in the tests. The axial force (tension positive) is the constraint force at the closing end
  along the rod.
* Spring-damper: external forces ``fext`` in ``aba`` (no constraint then) or added to ``tau``
  through the joint Jacobians (with constraints); its tension is reported as its axial force.
* Applied loads (torque, force at a point, constant in world axes): external forces in
  ``aba``, or ``tau += J^T f`` for ``constraintDynamics`` (which takes no ``fext``).
* Integration: classic RK4 on (q, v) (``pinocchio.integrate`` for spherical joints), or
  scipy's Radau IIA (``method = "radau"``, unconstrained models only).

Reactions: ``rnea`` with the constraint forces and applied loads as external forces, as the
2-D adapter.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun, steps_per_sample


@dataclass(frozen=True)
class Loop:
    """A CONTACT_3D closure: ``name`` is a case joint or a rod; M1, M2 contact frames."""

    name: str
    kind: str  # "joint" | "rod"
    j1: int
    j2: int
    M1: object
    M2: object


@dataclass
class Model3:
    """The Pinocchio model of a reference-frame case and the maps back to natcoord.

    ``frame``: body -> (joint id, SE3 of the natcoord body frame in that joint frame).
    ``tree``: (case joint name, joint id, sign): sign +1 if the joint's second body is the
    child. ``loads``: (joint id, point in joint frame (3,), force (3,), torque (3,)), world.
    ``springs``: (name, (jid, p), (jid, p), k, c, l0), points in joint frames, jid 0 ground.
    """

    dim: int
    model: object
    cmodels: object
    loops: list[Loop]
    frame: dict
    tree: list
    loads: list
    springs: list
    q0: np.ndarray
    v0: np.ndarray
    notes: list[str] = field(default_factory=list)


def v3(p) -> np.ndarray:
    p = np.asarray(p, float)
    return p if p.size == 3 else np.array([p[0], p[1], 0.0])


def cross(a, b) -> np.ndarray:
    """a x b for 3-vectors (np.cross costs ~30 us a call here)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def _perp(d: np.ndarray) -> np.ndarray:
    """A unit vector normal to the unit vector d (the world axis least aligned with it)."""
    a = np.eye(3)[int(np.argmin(np.abs(d)))]
    u = a - (a @ d) * d
    return u / np.linalg.norm(u)


def _rod_inertia(pin, mass: float, p: np.ndarray, r: np.ndarray, axial: float = 0.0):
    """Uniform slender rod p-r (world-aligned frame) as a Pinocchio Inertia."""
    L = np.linalg.norm(r - p)
    d = (r - p) / L
    Ic = mass * L**2 / 12 * (np.eye(3) - np.outer(d, d)) + axial * np.outer(d, d)
    return pin.Inertia(mass, (p + r) / 2, Ic)


def _body_inertia(pin, case: Case, body, s: dict) -> tuple[object, bool]:
    """Spatial inertia about the body frame (world-aligned), and whether the 3x3 is
    singular (a slender rod in 3-D: zero about its own axis). A particle gets
    ``particle_inertia`` kg m^2 per kg (a rotation nothing torques)."""
    com = v3(body.com)
    if body.kind == "particle":
        return pin.Inertia(body.mass, com, s["particle_inertia"] * body.mass * np.eye(3)), False
    if case.dimension == 2:  # only the z moment acts in the plane
        return pin.Inertia(body.mass, com, float(body.inertia) * np.eye(3)), False
    I3 = np.asarray(body.inertia, float)
    return pin.Inertia(body.mass, com, I3), bool(np.linalg.eigvalsh(I3)[0] <= 1e-12 * np.trace(I3))


def _revolute(pin, axis: np.ndarray):
    a = axis / np.linalg.norm(axis)
    for k, jm in enumerate((pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ)):
        if abs(abs(a[k]) - 1.0) < 1e-14:
            return jm(), np.eye(3)[k]  # q counts about +e_k whatever the case's sign
    return pin.JointModelRevoluteUnaligned(a), a


def _check_reference(case: Case, init) -> None:
    for name, st in init.items():
        R = getattr(st, "rotation", None)
        ok = np.allclose(st.origin, 0.0, atol=1e-8)
        ok &= np.allclose(R, np.eye(3), atol=1e-8) if R is not None and case.dimension == 3 \
            else abs(float(np.atleast_1d(st.angle)[0]) if st.angle is not None else 0.0) < 1e-8
        if not ok:
            raise ValueError(f"pinocchio: body {name!r} does not start at its reference pose "
                             "(reference-frame case: body frame = world frame at t = 0)")


def build(case: Case, init, s: dict) -> Model3:
    """The Pinocchio model of a reference-frame case (2-D or 3-D, rods, springs)."""
    import pinocchio as pin

    dim = case.dimension
    if not getattr(case, "reference_frame", False):
        raise Unsupported("3-D, rods and springs are modelled for reference-frame cases only "
                          "(body frames = world at t = 0)")
    if getattr(case, "drivers", ()):
        raise Unsupported("drivers (prescribed motions) are not modelled by this adapter")
    _check_reference(case, init)
    pts = {b.name: {k: v3(p) for k, p in b.points.items()} for b in case.bodies}
    pts[GROUND] = {k: v3(p) for k, p in case.ground.items()}

    def omega_of(b):
        if b == GROUND:
            return np.zeros(3)
        w = init[b].omega
        return np.array([0.0, 0.0, float(w)]) if dim == 2 else np.asarray(w, float)

    def vel_of(b, r):  # world velocity of the body point at world position r (t = 0)
        if b == GROUND:
            return np.zeros(3)
        return v3(init[b].velocity) + np.cross(omega_of(b), r - v3(init[b].origin))

    # A. the tree: edges parent -> child (a body, or "rod <name>" for a light rod), each with
    # its joint model, world position at t = 0, q0 and v0. Pinocchio wants every subtree
    # contiguous, so the joints are added depth-first afterwards.
    children: dict[str, list] = {GROUND: []}
    reached = {GROUND: 0}  # node -> depth
    loop_joints, notes = [], []

    def edge(parent, child, name, jm, r, qj, vj, kind, sign=1):
        children[parent].append((child, name, jm, r, qj, vj, kind, sign))
        children[child] = []
        reached[child] = reached[parent] + 1

    remaining = deque(case.joints)
    stalled = 0
    while remaining and stalled <= len(remaining):
        j = remaining.popleft()
        a, b = j.bodies
        if (a in reached) == (b in reached):
            if a in reached:
                loop_joints.append(j)
                stalled = 0
            else:
                remaining.append(j)
                stalled += 1
            continue
        stalled = 0
        sign = 1 if a in reached else -1
        parent, child = j.bodies[::sign]
        wrel = omega_of(child) - omega_of(parent)
        if j.type == "revolute":
            axis = np.array([0.0, 0.0, 1.0]) if dim == 2 else v3(j.axis)
            jm, a_ = _revolute(pin, axis)
            qj, vj = [0.0], [float(a_ @ wrel)]
        elif j.type == "spherical" and dim == 3:
            jm, qj, vj = pin.JointModelSpherical(), [0.0, 0.0, 0.0, 1.0], list(wrel)
        else:
            raise Unsupported(f"joint {j.name!r} of type {j.type!r} in a {dim}-D "
                              "reference-frame case")
        edge(parent, child, j.name, jm, pts[j.bodies[0]][j.points[0]], qj, vj, j.type, sign)
    for x in case.bodies:  # free bodies (joined only by rods or springs): free-flyer
        if x.name in reached:
            continue
        if dim == 2:
            raise Unsupported(f"body {x.name!r} is joined to the ground by no joint: a planar "
                              "free body is not modelled")
        # six scalar dofs (a vector state for RK4 and Radau): translation, then ZYX angles
        # whose rates at zero angles are (w_z, w_y, w_x)
        edge(GROUND, f"{x.name} translation", f"{x.name} translation",
             pin.JointModelTranslation(), np.zeros(3), [0.0] * 3,
             list(v3(init[x.name].velocity)), "translation")
        edge(f"{x.name} translation", x.name, x.name, pin.JointModelSphericalZYX(),
             np.zeros(3), [0.0] * 3, list(omega_of(x.name)[::-1]), "free")
        notes.append(f"body {x.name} joined by no joint: floating on JointModelTranslation + "
                     "JointModelSphericalZYX (6 dof, ZYX angles: singular at 90 deg pitch)")
    rod_loops = []
    m_rod = float(s["rod_mass"])
    for rod in getattr(case, "rods", ()):  # light bodies, rooted at the end nearer the ground
        ends = list(rod.ends)
        for e in ends:
            if e[0] not in reached:
                raise Unsupported(f"rod {rod.name!r}: end body {e[0]!r} is not modelled")
        if reached[ends[1][0]] < reached[ends[0][0]]:
            ends.reverse()
        (ba, pa), (bb, pb) = ends
        rP, rQ = pts[ba][pa], pts[bb][pb]
        L = float(np.linalg.norm(rQ - rP))
        d = (rQ - rP) / L
        wrel = np.cross(d, vel_of(bb, rQ) - vel_of(ba, rP)) / L - omega_of(ba)
        if dim == 2:
            jm, qj, vj = pin.JointModelRZ(), [0.0], [float(wrel[2])]
        else:
            u1 = _perp(d)
            u2 = np.cross(d, u1)
            jm, qj = pin.JointModelUniversal(u1, u2), [0.0, 0.0]
            vj = list(np.linalg.lstsq(np.c_[u1, u2], wrel, rcond=None)[0])
        edge(ba, f"rod {rod.name}", f"rod {rod.name}", jm, rP, qj, vj, "rod")
        rod_loops.append((rod.name, rP, rQ, bb))

    # B. the Pinocchio model, depth-first
    model = pin.Model()
    model.gravity = pin.Motion(np.r_[v3(case.gravity), 0.0, 0.0, 0.0])
    frame = {GROUND: (0, pin.SE3.Identity())}
    origin_w = {0: np.zeros(3)}  # joint id -> world position of the joint frame at t = 0
    parent_j = {0: None}
    kinds = {0: "ground"}
    q0, v0, tree, singular = [], [], [], []
    def add(node):  # depth-first: Pinocchio wants every subtree contiguous
        jp = frame[node][0]
        for child, name, jm, r, qj, vj, kind, sign in children[node]:
            jid = model.addJoint(jp, jm, pin.SE3(np.eye(3), r - origin_w[jp]), name)
            origin_w[jid], parent_j[jid], kinds[jid] = r, jp, kind
            X = pin.SE3(np.eye(3), -r)
            frame[child] = (jid, X)
            if kind == "translation":
                inertia = pin.Inertia.Zero()
            elif kind == "rod":
                rod = next(x for x in rod_loops if f"rod {x[0]}" == child)
                inertia = _rod_inertia(pin, m_rod, np.zeros(3), rod[2] - rod[1])
            else:
                inertia, sing = _body_inertia(pin, case, case.body(child), s)
                inertia = inertia.se3Action(X)
                if sing:
                    singular.append(child)
            model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
            q0.extend(qj)
            v0.extend(vj)
            if kind in ("revolute", "spherical"):
                tree.append((name, jid, sign))
            add(child)

    add(GROUND)

    # C. loop closures: CONTACT_3D
    cmodels = pin.StdVec_RigidConstraintModel()
    loops: list[Loop] = []

    def contact(name, kind, j1, r1, j2, r2):
        M1 = pin.SE3(np.eye(3), r1 - origin_w[j1])
        M2 = pin.SE3(np.eye(3), r2 - origin_w[j2])
        cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, j1, M1, j2, M2,
                                      pin.ReferenceFrame.LOCAL)
        if s["baumgarte_kp"] or s["baumgarte_kd"]:
            cm.setBaumgarteCorrectorParameters(pin.BaumgarteCorrectorParameters(
                float(s["baumgarte_kp"]), float(s["baumgarte_kd"])))
        cm.name = name
        cmodels.append(cm)
        loops.append(Loop(name, kind, j1, j2, M1, M2))

    def path(j1, j2):
        def up(j):
            out = []
            while j:
                out.append(j)
                j = parent_j[j]
            return out
        u1, u2 = up(j1), up(j2)
        common = set(u1) & set(u2)
        return [j for j in u1 + u2 if j not in common]

    for j in loop_joints:
        a, b = j.bodies
        if j.type == "revolute" and dim == 3:
            axis = v3(j.axis) / np.linalg.norm(j.axis)
            for jid in path(frame[a][0], frame[b][0]):
                ok = kinds[jid] == "revolute" and np.linalg.norm(
                    np.cross(v3(case.joint(model.names[jid]).axis), axis)) < 1e-12
                if not ok:
                    raise Unsupported(f"loop-closing 3-D revolute {j.name!r}: the tree does "
                                      "not enforce its axis alignment, and CONTACT_6D would "
                                      "lock its rotation")
        elif j.type not in ("revolute", "spherical"):
            raise Unsupported(f"loop-closing {j.type} joint {j.name!r}")
        r = pts[a][j.points[0]]
        contact(j.name, "joint", frame[a][0], r, frame[b][0], r)
    if loop_joints:
        notes.append(f"loop joint(s) {', '.join(j.name for j in loop_joints)} closed by "
                     "RigidConstraintModel CONTACT_3D (LOCAL)")
    for name, _, rQ, bb in rod_loops:
        contact(name, "rod", frame[f"rod {name}"][0], rQ, frame[bb][0], rQ)
    if rod_loops:
        joint = "revolute" if dim == 2 else "universal (axes normal to the rod)"
        notes.append(f"massless rods ({', '.join(x[0] for x in rod_loops)}) as light bodies: "
                     f"uniform slender rods of {m_rod:g} kg on a {joint} joint at one end, "
                     "CONTACT_3D at the other; axial force from the closing constraint")

    # 5. loads and springs
    loads = []
    for f in case.forces:
        jid, X = frame[f.body]
        if f.type == "torque":
            tq = np.array([0.0, 0.0, float(f.value)]) if dim == 2 else v3(f.value)
            loads.append((jid, np.zeros(3), np.zeros(3), tq))
        elif f.type == "force":
            loads.append((jid, X.act(pts[f.body][f.point]), v3(f.value), np.zeros(3)))
        else:
            raise Unsupported(f"force type {f.type!r}")
    springs = []
    for sp in getattr(case, "springs", ()):
        ends = []
        for b, p in sp.ends:
            jid, X = frame[b]
            ends.append((jid, X.act(pts[b][p])))
        springs.append((sp.name, ends[0], ends[1], float(sp.stiffness), float(sp.damping),
                        float(sp.length)))
    if springs:
        notes.append(f"spring-dampers ({', '.join(x[0] for x in springs)}) as external forces")
    if singular and dim == 3:
        notes.append(f"body(ies) {', '.join(singular)} keep their exact singular rotational "
                     "inertia (zero about a slender rod's axis): the joints never turn them "
                     "about it")
    return Model3(dim, model, cmodels, loops, frame, tree, loads, springs, np.array(q0),
                  np.array(v0), notes)


class Dynamics:
    """Accelerations of a :class:`Model3` at (q, v), counting proximal iterations."""

    def __init__(self, pin, b: Model3, s: dict):
        self.pin, self.b = pin, b
        self.model = b.model
        self.data = b.model.createData()
        self.aux = b.model.createData()  # kinematics for loads and springs
        self.cdatas = pin.StdVec_RigidConstraintData()
        for cm in b.cmodels:
            self.cdatas.append(cm.createData())
        if b.loops:
            pin.initConstraintDynamics(self.model, self.data, b.cmodels, self.cdatas)
        self.prox = pin.ProximalSettings(float(s["accuracy"]), float(s["mu"]),
                                         int(s["max_iter"]))
        self.iters = 0
        self.zero = np.zeros(b.model.nv)
        self.loaded = sorted({x[0] for x in b.loads} | {e[0] for sp in b.springs
                                                         for e in sp[1:3]} - {0})
        groups = {}
        for name, (ja, pa), (jb, pb), k, c, l0 in b.springs:
            groups.setdefault((ja, jb), []).append((name, pa, pb, k, c, l0))
        self.groups = [(ja, jb, np.array([x[1] for x in g]), np.array([x[2] for x in g]),
                        *(np.array([x[i] for x in g]) for i in (3, 4, 5)),
                        [x[0] for x in g]) for (ja, jb), g in groups.items()]
        self.const_tau = None
        if not self.loaded:
            self.const_tau = self.zero
        elif b.dim == 2 and not b.springs and all(not x[2].any() for x in b.loads):
            self.const_tau = self.tau(b.q0, b.v0)  # a moment about z: planar, constant

    def fext(self, q, v):
        """Applied loads and spring forces as Pinocchio external forces, (njoints, 6) in
        joint frames (linear, angular), and the spring tensions."""
        pin, data = self.pin, self.aux
        pin.forwardKinematics(self.model, data, q, v)
        F = np.zeros((self.model.njoints, 6))
        frames = {}
        for jid in self.loaded:
            M, vel = data.oMi[jid], data.v[jid]
            frames[jid] = (M.rotation, M.translation, vel.linear, vel.angular)
        for jid, p, fw, mw in self.b.loads:
            R = frames[jid][0]
            fl = R.T @ fw
            F[jid, :3] += fl
            F[jid, 3:] += cross(p, fl) + R.T @ mw
        tension = {}
        for ja, jb, Pa, Pb, k, c, l0, names in self.groups:  # vectorized per joint pair
            ra, va = self._ends(frames, ja, Pa)
            rb, vb = self._ends(frames, jb, Pb)
            d = rb - ra
            ln = np.sqrt(np.einsum("ij,ij->i", d, d))
            e = d / ln[:, None]
            T = k * (ln - l0) + c * np.einsum("ij,ij->i", vb - va, e)
            tension.update(zip(names, T, strict=True))
            for jid, P, sgn in ((ja, Pa, 1.0), (jb, Pb, -1.0)):
                if jid:
                    fl = (sgn * T[:, None] * e) @ frames[jid][0]  # rows R^T f
                    F[jid, :3] += fl.sum(0)
                    F[jid, 3:] += cross(P.T, fl.T).sum(1)
        return F, tension

    @staticmethod
    def _ends(frames, jid, P):
        """World positions and velocities (n, 3) of points P (n, 3) of joint jid."""
        if jid == 0:
            return P, 0.0
        R, tr, vl, w = frames[jid]
        return P @ R.T + tr, (vl[:, None] + cross(w[:, None], P.T)).T @ R.T

    def tau(self, q, v):
        """Generalized applied forces J^T f (constant for planar torques only)."""
        if self.const_tau is not None:
            return self.const_tau
        f, _ = self.fext(q, v)
        pin = self.pin
        pin.computeJointJacobians(self.model, self.aux, q)
        tau = np.zeros(self.model.nv)
        for jid in self.loaded:
            J = pin.getJointJacobian(self.model, self.aux, jid, pin.ReferenceFrame.LOCAL)
            tau += J.T @ f[jid]
        return tau

    def __call__(self, q, v):
        pin = self.pin
        if self.b.loops:
            a = pin.constraintDynamics(self.model, self.data, q, v, self.tau(q, v),
                                       self.b.cmodels, self.cdatas, self.prox)
            self.iters = max(self.iters, self.prox.iter)
            return a.copy()
        if not self.loaded:
            return pin.aba(self.model, self.data, q, v, self.zero).copy()
        f, _ = self.fext(q, v)
        fext = pin.StdVec_Force()
        for x in f:
            fext.append(pin.Force(x))
        return pin.aba(self.model, self.data, q, v, self.zero, fext).copy()

    @property
    def lam(self):
        return self.data.lambda_c if self.b.loops else np.zeros(0)


def rk4_samples(acc, lam, step, q0, v0, nq: int, nl: int, times, k: int, dt: float,
                context: str = ""):
    """Classic RK4 from (q0, v0), k steps per sample, ``acc(q, v)`` the acceleration, ``lam()``
    the constraint forces of its last call, ``step(q, dv)`` the position update: sampled
    (Q, V, A, L) and step count. ``context`` is added to the error's dt."""
    T, nv = len(times), len(v0)
    Q, V, A, L = (np.empty((T, nq)), np.empty((T, nv)), np.empty((T, nv)), np.empty((T, nl)))
    h, dt6 = dt / 2, dt / 6
    q, v = q0.copy(), v0.copy()
    n = 0
    for i in range(T):
        a1 = acc(q, v)  # the sample's own state: its lambda gives the reactions
        Q[i], V[i], A[i], L[i] = q, v, a1, lam()
        if not (np.isfinite(a1).all() and np.isfinite(L[i]).all()):
            raise RuntimeError(f"pinocchio: non-finite acceleration or constraint force at "
                               f"t = {times[i]:g} s (dt {dt:g} s{context})")
        if i == T - 1:
            break
        for j in range(k):
            if j:
                a1 = acc(q, v)
            v2 = v + h * a1
            a2 = acc(step(q, h * v), v2)
            v3_ = v + h * a2
            a3 = acc(step(q, h * v2), v3_)
            v4 = v + dt * a3
            a4 = acc(step(q, dt * v3_), v4)
            q = step(q, dt6 * (v + 2 * v2 + 2 * v3_ + v4))
            v = v + dt6 * (a1 + 2 * a2 + 2 * a3 + a4)
            n += 1
    return Q, V, A, L, n


def integrate(pin, b: Model3, dyn: Dynamics, times, k: int, dt: float):
    """Classic RK4 from (q0, v0), k steps per sample: sampled (Q, V, A, L) and step count."""
    model = b.model
    lie = model.nq != model.nv
    step = (lambda q, dv: pin.integrate(model, q, dv)) if lie else (lambda q, dv: q + dv)
    return rk4_samples(dyn, lambda: dyn.lam, step, b.q0, b.v0, model.nq, 3 * len(b.loops),
                       times, k, dt)


def integrate_radau(b: Model3, dyn: Dynamics, times, s: dict):
    """Implicit Radau IIA (scipy, adaptive) for stiff spring-dampers, sampled by its dense
    output: (Q, V, A, L, steps, counters). Needs a vector state (nq == nv)."""
    from scipy.integrate import Radau

    nv = b.model.nv
    if b.model.nq != nv:
        raise Unsupported("Radau needs a vector configuration (a spherical joint has a "
                          "quaternion)")

    def rhs(t, y):
        return np.concatenate([y[nv:], dyn(y[:nv], y[nv:])])

    T = len(times)
    Y = np.empty((T, 2 * nv))
    Y[0] = np.r_[b.q0, b.v0]
    solver = Radau(rhs, times[0], Y[0], times[-1], rtol=float(s["rtol"]),
                   atol=float(s["atol"]))
    i, n = 1, 0
    while i < T:
        msg = solver.step()
        n += 1
        if solver.status == "failed" or not np.isfinite(solver.y).all():
            raise RuntimeError(f"pinocchio: Radau failed at t = {solver.t:g} s: {msg}")
        dense = solver.dense_output()
        while i < T and times[i] <= solver.t + 1e-12:
            Y[i] = dense(times[i])
            i += 1
    Q, V = Y[:, :nv], Y[:, nv:]
    A = np.array([dyn(q, v) for q, v in zip(Q, V, strict=True)])
    counters = {"rhs": solver.nfev, "jacobians": solver.njev, "lu": solver.nlu}
    return Q, V, A, np.zeros((T, 0)), n, counters


def motion(pin, case: Case, b: Model3, dyn: Dynamics, times, Q, V, A, L):
    """Neutral motion dicts from the samples, and the loop drift (position, velocity).

    Returns (origin, angle, velocity, omega, rotation, joint_force, rod_force, drift)."""
    model = b.model
    data = model.createData()
    T, dim = len(times), b.dim
    names = [x.name for x in case.bodies]
    origin = {n: np.empty((T, dim)) for n in names}
    velocity = {n: np.empty((T, dim)) for n in names}
    rotation = {n: np.empty((T, 3, 3)) for n in names}
    omega = {n: np.empty((T, 3)) for n in names}
    forces = {j.name: np.empty((T, dim)) for j in case.joints}
    rod_force = {x.name: np.empty(T) for x in getattr(case, "rods", ())}
    rod_force |= {sp[0]: np.empty(T) for sp in b.springs}
    drift = np.zeros(2)
    zero3 = np.zeros(3)
    for i in range(T):
        q, v = Q[i], V[i]
        pin.forwardKinematics(model, data, q, v)
        for n in names:
            jid, X = b.frame[n]
            oMb = data.oMi[jid] * X
            R, vel = data.oMi[jid].rotation, data.v[jid]
            origin[n][i] = oMb.translation[:dim]
            velocity[n][i] = (R @ (vel.linear + cross(vel.angular, X.translation)))[:dim]
            rotation[n][i] = oMb.rotation
            omega[n][i] = R @ vel.angular
        fl, tension = dyn.fext(q, v)
        for name, T_ in tension.items():
            rod_force[name][i] = T_
        fext = pin.StdVec_Force()
        for x in fl:
            fext.append(pin.Force(x))
        for n, lp in enumerate(b.loops):
            lam = L[i, 3 * n:3 * n + 3]
            oMc1, oMc2 = data.oMi[lp.j1] * lp.M1, data.oMi[lp.j2] * lp.M2
            fw = oMc1.rotation @ lam  # force on joint1's contact point, world axes
            fext[lp.j1] = fext[lp.j1] + lp.M1.act(pin.Force(lam, zero3))
            fext[lp.j2] = fext[lp.j2] + lp.M2.act(pin.Force(-oMc2.rotation.T @ fw, zero3))
            if lp.kind == "joint":
                forces[lp.name][i] = -fw[:dim]
            else:  # rod: tension pulls the tip towards the root
                e = oMc1.translation - data.oMi[lp.j1].translation
                rod_force[lp.name][i] = fw @ e / np.linalg.norm(e)
            drift[0] = max(drift[0], np.linalg.norm(oMc1.translation - oMc2.translation))
            vc1 = oMc1.rotation @ lp.M1.actInv(data.v[lp.j1]).linear
            vc2 = oMc2.rotation @ lp.M2.actInv(data.v[lp.j2]).linear
            drift[1] = max(drift[1], np.linalg.norm(vc1 - vc2))
        pin.rnea(model, data, q, v, A[i], fext)
        for name, jid, sign in b.tree:
            forces[name][i] = sign * (data.oMi[jid].rotation @ data.f[jid].linear)[:dim]
    if dim == 2:
        angle = {n: np.unwrap(np.arctan2(rotation[n][:, 1, 0], rotation[n][:, 0, 0]))
                 for n in names}
        omega2 = {n: omega[n][:, 2].copy() for n in names}
        return origin, angle, velocity, omega2, {}, forces, rod_force, drift
    return origin, {}, velocity, omega, rotation, forces, rod_force, drift


def run(case: Case, init, s: dict) -> EngineRun:
    """Build, integrate (RK4, or Radau with ``method = "radau"``) and sample a case."""
    import time

    import pinocchio as pin

    t0 = time.perf_counter()
    b = build(case, init, s)
    dyn = Dynamics(pin, b, s)
    build_time = time.perf_counter() - t0
    times = case.times
    method = str(s["method"]).lower()
    t0 = time.perf_counter()
    if method == "rk4":
        dt = float(s["dt"])
        Q, V, A, L, n = integrate(pin, b, dyn, times, steps_per_sample(case, dt), dt)
        counters = {"steps": n, "rhs": 4 * n + 1}
        b.notes.append(f"classic RK4, dt {dt:g} s")
    elif method == "radau":
        if b.loops:
            raise Unsupported("method radau: the constrained (constraintDynamics) model "
                              "uses RK4")
        Q, V, A, L, n, counters = integrate_radau(b, dyn, times, s)
        counters["steps"] = n
        b.notes.append(f"scipy Radau IIA on pinocchio.aba, rtol {s['rtol']:g}, "
                       f"atol {s['atol']:g}")
    else:
        raise ValueError(f"pinocchio: unknown method {s['method']!r} (rk4 | radau)")
    wall = time.perf_counter() - t0
    origin, angle, velocity, omega, rotation, forces, rod_force, drift = motion(
        pin, case, b, dyn, times, Q, V, A, L)
    if drift[0] > s["max_drift"]:
        raise RuntimeError(f"pinocchio: a loop opened by {drift[0]:.3g} m (> max_drift "
                           f"{s['max_drift']:g} m); reduce dt or add Baumgarte gains")
    counters |= {"prox_iter_max": dyn.iters, "drift_max_m": float(drift[0]),
                 "velocity_drift_max_m_s": float(drift[1])}
    if b.loops:
        b.notes.append(f"proximal constraintDynamics: mu {s['mu']:g}, accuracy "
                       f"{s['accuracy']:g}, at most {s['max_iter']} iterations "
                       f"(reached {dyn.iters})")
    m = Motion(np.asarray(times), origin, angle, velocity, omega, forces, rotation=rotation,
               rod_force=rod_force)
    return EngineRun(m, build_time, wall, n, s, counters, b.notes)
