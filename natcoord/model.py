"""Natural-coordinate model of a 2-D mechanism (García de Jalón & Bayo, 1994).

Each moving body owns its basic points as coordinates (two points for a rigid body, one for a
particle); every other point of the body is a constant linear combination of them, so the
mass matrix is constant. Joints are coincidence or point-on-line equations between points
of different bodies, so that their Lagrange multipliers are directly the joint forces.

``q`` is ordered body by body: ``[x_i, y_i, x_j, y_j]`` for a rigid body, ``[x, y]`` for a
particle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constraints import S2, ConstraintBuilder, QuadraticConstraints
from .drivers import build_drivers
from .mechanism import GROUND, Case

J2 = np.array([[0.0, -1.0], [1.0, 0.0]])  # +90 deg rotation


@dataclass(frozen=True)
class BodyMap:
    """Where a body lives in q and how its frame follows from its basic points.

    ``cols``: (2k,) indices in q (k = 2 basic points, or 1 for a particle).
    ``p_i, p_j``: basic points in the body frame (2,), ``L = |p_j - p_i|``.
    """

    name: str
    cols: np.ndarray
    p_i: np.ndarray
    p_j: np.ndarray | None
    L: float


@dataclass(frozen=True)
class JointMap:
    """Rows of a joint in Phi and the map lambda -> force on its second body (world, N).

    Revolute: force = lambda[rows]. Prismatic: force = -lambda[rows[0]] * n with n the
    joint normal ``J2 @ axis_map @ qh``; ``axis_map`` (2, n + 1) gives the world axis.
    """

    name: str
    rows: np.ndarray
    axis_map: np.ndarray | None = None

    def force(self, lam: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Force on the second body (T, 2) from lambda (T, m) and q (T, n)."""
        if self.axis_map is None:
            return lam[:, self.rows]
        u = np.append(q, np.ones((len(q), 1)), axis=1) @ self.axis_map.T
        return -lam[:, self.rows[:1]] * (u @ J2.T)


@dataclass(frozen=True)
class Model:
    """A frozen natural-coordinate model.

    Attributes
    ----------
    n : int                       number of coordinates
    M : (n, n)                    constant mass matrix, kg
    Q0 : (n,)                     constant generalized forces (gravity), N
    T : (n, n)                    generalized force linear in q (applied torques): Q = Q0 + T q
    constraints : QuadraticConstraints   m rows
    bodies : dict[str, BodyMap]
    joints : dict[str, JointMap]
    drivers : tuple[DriverRow, ...]      rheonomic rows, appended after the m rows in lambda
    """

    case: Case
    n: int
    M: np.ndarray
    Q0: np.ndarray
    T: np.ndarray
    constraints: QuadraticConstraints
    bodies: dict[str, BodyMap]
    joints: dict[str, JointMap]
    drivers: tuple = ()

    @property
    def m(self) -> int:
        return self.constraints.m

    def forces(self, t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Generalized applied forces Q(t, q, qd): (n,), N (or N m for unit-vector rows)."""
        return self.Q0 + self.T @ q

    # ---- body frames from coordinates -------------------------------------------------
    def point_map(self, body: str, x: np.ndarray) -> np.ndarray:
        """(2, n + 1) map from qh = [q, 1] to the world position of body point x (2,)."""
        C = np.zeros((2, self.n + 1))
        if body == GROUND:
            C[:, self.n] = x
            return C
        b = self.bodies[body]
        if b.p_j is None:  # particle: the point is the body's only point, translated
            C[:, b.cols] = np.eye(2)
            C[:, self.n] = x - b.p_i
            return C
        e1 = (b.p_j - b.p_i) / b.L
        e2 = J2 @ e1
        a, c = (x - b.p_i) @ e1 / b.L, (x - b.p_i) @ e2 / b.L
        C[:, b.cols[:2]] = (1 - a) * np.eye(2) - c * J2
        C[:, b.cols[2:]] = a * np.eye(2) + c * J2
        return C

    def body_pose(self, body: str, q: np.ndarray, qd: np.ndarray):
        """Frame origin (T, 2), angle (T,), origin velocity (T, 2), omega (T,) from q, qd (T, n)."""
        b = self.bodies[body]
        ri, vi = q[:, b.cols[:2]], qd[:, b.cols[:2]]
        if b.p_j is None:
            z = np.zeros(len(q))
            return ri - b.p_i, z, vi, z
        d, dd = q[:, b.cols[2:]] - ri, qd[:, b.cols[2:]] - vi
        dloc = b.p_j - b.p_i
        angle = np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(dloc[1], dloc[0])
        omega = (d[:, 0] * dd[:, 1] - d[:, 1] * dd[:, 0]) / np.sum(d**2, 1)
        c, s = np.cos(angle), np.sin(angle)
        rp = np.stack([c * b.p_i[0] - s * b.p_i[1], s * b.p_i[0] + c * b.p_i[1]], -1)
        origin = ri - rp
        velocity = vi - omega[:, None] * np.stack([-rp[:, 1], rp[:, 0]], -1)
        return origin, np.unwrap(angle), velocity, omega

    def q_from_poses(self, poses: dict) -> np.ndarray:
        """Coordinates (n,) placing each body at a pose {body: Pose}."""
        q = np.zeros(self.n)
        for name, b in self.bodies.items():
            pose = poses[name]
            c, s = np.cos(pose.angle), np.sin(pose.angle)
            R = np.array([[c, -s], [s, c]])
            q[b.cols[:2]] = pose.origin + R @ b.p_i
            if b.p_j is not None:
                q[b.cols[2:]] = pose.origin + R @ b.p_j
        return q


def build_model(case: Case) -> Model:
    """Natural coordinates, constant mass matrix and constraint rows of a 2-D case."""
    bodies: dict[str, BodyMap] = {}
    col = 0
    for body in case.bodies:
        pts = list(body.points.values())
        if body.kind == "particle":
            bodies[body.name] = BodyMap(body.name, np.arange(col, col + 2), pts[0], None, 0.0)
            col += 2
        else:
            L = float(np.linalg.norm(pts[1] - pts[0]))
            bodies[body.name] = BodyMap(body.name, np.arange(col, col + 4), pts[0], pts[1], L)
            col += 4
    n = col
    M, Q0, T = np.zeros((n, n)), np.zeros(n), np.zeros((n, n))
    shell = Model(case, n, M, Q0, T, None, bodies, {})  # type: ignore[arg-type]

    for body in case.bodies:
        b = bodies[body.name]
        CG = shell.point_map(body.name, body.com)[:, b.cols]  # (2, 2k)
        Mb = body.mass * CG.T @ CG
        if b.p_j is not None:
            D = np.hstack([-np.eye(2), np.eye(2)])  # d = r_j - r_i
            Mb += body.inertia / b.L**2 * D.T @ D
        M[np.ix_(b.cols, b.cols)] += Mb
        Q0[b.cols] += body.mass * CG.T @ case.gravity
    for f in case.forces:  # torque tau: Q_d = tau / L^2 J d, linear in q
        b = bodies[f.body]
        if b.p_j is None:
            raise ValueError(f"torque on particle {f.body!r} has no effect")
        D = np.hstack([-np.eye(2), np.eye(2)])
        T[np.ix_(b.cols, b.cols)] += f.value / b.L**2 * D.T @ J2 @ D

    cb = ConstraintBuilder(n)
    for name, b in bodies.items():
        if b.p_j is not None:  # rigid-body distance |r_j - r_i|^2 - L^2 = 0
            A = np.zeros((2, n + 1))
            A[:, b.cols[:2]], A[:, b.cols[2:]] = -np.eye(2), np.eye(2)
            cb.bilinear(A, np.eye(2), A, -b.L**2, f"{name}: length")
    joints: dict[str, JointMap] = {}
    points_of = {b.name: b.points for b in case.bodies} | {GROUND: case.ground}
    for j in case.joints:
        (a, b), (pa, pb) = j.bodies, j.points
        Ca, Cb = shell.point_map(a, points_of[a][pa]), shell.point_map(b, points_of[b][pb])
        if j.type == "revolute":  # r_Pa - r_Pb = 0: lambda is the force on b
            rows = [cb.linear(Ca[0] - Cb[0], f"{j.name}: x"),
                    cb.linear(Ca[1] - Cb[1], f"{j.name}: y")]
            joints[j.name] = JointMap(j.name, np.array(rows))
        else:  # prismatic: cross(u, r_Pb - r_Pa) = 0, u the axis in world axes
            U = _direction_map(shell, a, j.axis)
            row = cb.bilinear(U, S2, Cb - Ca, 0.0, f"{j.name}: on line", length_dim=1)
            rows = [row]
            if bodies.get(b) is not None and bodies[b].p_j is not None:
                rel = case.guess[b].angle - (case.guess[a].angle if a != GROUND else 0.0)
                Da, Db = _direction_map(shell, a, np.array([1.0, 0.0])), \
                    _direction_map(shell, b, np.array([1.0, 0.0]))
                rows.append(cb.bilinear(Da, S2, Db, -np.sin(rel), f"{j.name}: no rotation",
                                        length_dim=0))
            joints[j.name] = JointMap(j.name, np.array(rows), U)
    return Model(case, n, M, Q0, T, cb.build(), bodies, joints, build_drivers(case, shell))


def _direction_map(shell: Model, body: str, u_local: np.ndarray) -> np.ndarray:
    """(2, n + 1) map from qh to the world direction of a body-frame unit vector."""
    return shell.point_map(body, u_local) - shell.point_map(body, np.zeros(2))
