"""What acts on the skeleton besides its joints: constant forces and torques, spring-dampers
(external forces from the state at the start of each step) and massless rods built as light
bodies. Everything is 3-D (see :mod:`natcoord.engines.planar`)."""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Case
from ..planar import Frame, frame_of, node_point

ROD_NOTE = ("massless rod(s) {names}: light uniform rods of {m:g} kg (DART has no distance "
            "constraint; bodies need mass), {joint} joint at one end and a "
            "BallJointConstraint at the other; axial force from the rod's joint force "
            "projected on the rod plus half its own inertial load")


def iso(dart, p, R=None):
    """A DART Isometry3 from a translation p (3,) m and a rotation R (3, 3)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = p
    out = dart.math.Isometry3()
    out.set_matrix(T)
    return out


def slender_inertia(mass: float, a: np.ndarray, b: np.ndarray, axial: float) -> np.ndarray:
    """Uniform rod a-b (3,): m L^2 / 12 across it, ``axial`` times that along it (3, 3)."""
    d = b - a
    L = float(np.linalg.norm(d))
    e = d / L
    return mass * L**2 / 12 * (np.eye(3) - (1.0 - axial) * np.outer(e, e))


# ---- massless rods as light bodies --------------------------------------------------------
class LightRod:
    """A ``[[rods]]`` entry built as a light body: tree joint at ``ends[0]``, ball constraint
    at ``ends[1]`` (ends reordered so that a ground end carries the tree joint).

    The rod's own frame is the world frame at t = 0, so its ends ``x0``, ``x1`` (3,) are
    their world positions then; they follow from the end bodies' frames at t = 0.
    """

    def __init__(self, rod, case: Case, frames: dict[str, Frame]):
        ends = rod.ends if rod.ends[1][0] != GROUND else rod.ends[::-1]
        self.name, self.ends = rod.name, ends
        self.p = [node_point(case, *e) for e in ends]  # each end in its body's frame
        self.f = [frame_of(frames, e[0]) for e in ends]
        self.x0, self.x1 = (f.point(p) for f, p in zip(self.f, self.p, strict=True))
        self.node = self.joint = None

    def build(self, dart, skel, nodes: dict, mass: float, axial: float, normal):
        """Body node and tree joint: revolute about ``normal`` (3,) when the model is planar
        (None: a ball joint)."""
        parent = None if self.ends[0][0] == GROUND else nodes[self.ends[0][0]]
        if normal is not None:
            joint, node = skel.createRevoluteJointAndBodyNodePair(parent)
            joint.setAxis(normal)
        else:
            joint, node = skel.createBallJointAndBodyNodePair(parent)
        # joint frame at the end point, with world axes at t = 0 on both sides
        joint.setTransformFromParentBodyNode(iso(dart, self.p[0], self.f[0].R.T))
        joint.setTransformFromChildBodyNode(iso(dart, self.x0))
        joint.setName(f"rod {self.name}")
        node.setName(f"rod {self.name}")
        node.setInertia(dart.dynamics.Inertia(mass, (self.x0 + self.x1) / 2,
                                              slender_inertia(mass, self.x0, self.x1, axial)))
        self.node, self.joint, self.mass = node, joint, mass
        return node

    def constraint(self, dart, nodes: dict):
        """The BallJointConstraint at the far end (create it once the state is set)."""
        other = self.ends[1][0]
        if other == GROUND:
            return dart.constraint.BallJointConstraint(self.node, self.x1)
        return dart.constraint.BallJointConstraint(self.node, nodes[other], self.x1)

    def set_rate(self, normal) -> None:
        """Joint rate with both ends moving as natcoord assembled them (no spin)."""
        v0, v1 = (f.point_velocity(p) for f, p in zip(self.f, self.p, strict=True))
        d = self.x1 - self.x0
        w = np.cross(d, v1 - v0) / (d @ d) - self.f[0].omega  # relative, world = rod axes
        if normal is not None:
            self.joint.setVelocity(0, float(normal @ w))
        else:
            self.joint.setVelocities(w)

    def gap(self, nodes: dict) -> float:
        """Distance (m) between the rod's far end and its point on the other body."""
        M = self.node.getWorldTransform().matrix()
        x = M[:3, :3] @ self.x1 + M[:3, 3]
        b = self.ends[1][0]
        y = self.x1
        if b != GROUND:
            N = nodes[b].getWorldTransform().matrix()
            y = N[:3, :3] @ self.p[1] + N[:3, 3]
        return float(np.linalg.norm(x - y))

    def axis(self) -> np.ndarray:
        R = self.node.getWorldTransform().rotation()
        d = R @ (self.x1 - self.x0)
        return d / np.linalg.norm(d)

    def tension(self, W, g3: np.ndarray) -> float:
        """Axial force (N, tension positive) at mid-length, at the state the skeleton holds,
        with the last step's accelerations: ``-F_joint . u + m/2 (a_G - g) . u``."""
        u = self.axis()
        f = np.asarray(self.joint.getWrenchToParentBodyNode(W))[3:]
        a = np.asarray(self.node.getCOMLinearAcceleration(W, W))
        return float(-f @ u + 0.5 * self.mass * (a - g3) @ u)


# ---- constant loads and spring-dampers ----------------------------------------------------
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


def make_loads(case: Case, nodes):
    """Constant forces/torques and springs of a 3-D case: ``(apply, resultant,
    spring_forces)``: apply them before a step; a node's applied resultant force (3,) N at the
    current state (for Newton-Euler); the springs' tensions (n,) N."""
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    const = [(nodes[f.body], f.type, np.asarray(f.value, float) * np.ones(3),
              None if f.point is None else node_point(case, f.body, f.point),
              f.frame == "body") for f in case.forces]  # local: in the node's (body's) axes
    names = [b.name for b in case.bodies]
    sp_list = list(case.springs)
    # per end side: body index (-1 ground) and the point in body axes
    side = [(np.array([-1 if sp.ends[e][0] == GROUND else names.index(sp.ends[e][0])
                       for sp in sp_list], int),
             np.array([node_point(case, *sp.ends[e]) for sp in sp_list]).reshape(-1, 3))
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
        for node, kind, value, p, local in const:
            if kind == "force":
                node.addExtForce(value, p, local, True)
            else:
                node.addExtTorque(value, local)
        if not sp_list:
            return
        for i, (F, Mo) in spring_loads()[1].items():
            node = nodes[names[i]]
            node.addExtForce(F, np.zeros(3), False, True)
            node.addExtTorque(Mo, False)

    def resultant(node) -> np.ndarray:
        f = np.zeros(3)
        for n, kind, value, _, local in const:
            if n is node and kind == "force":
                f += node.getWorldTransform().matrix()[:3, :3] @ value if local else value
        if sp_list:
            for i, (F, _) in spring_loads()[1].items():
                if nodes[names[i]] is node:
                    f += F
        return f

    return apply, resultant, spring_forces
