"""Position, velocity and acceleration problems (Newton-Raphson on Phi(q) = 0).

Redundant constraints are allowed: every linear solve is a least-squares solve, which gives
the minimum-norm correction and tolerates a rank-deficient Phi_q.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .drivers import ConstraintSystem
from .errors import AssemblyError
from .mechanism import Case
from .model import J2, Model


@dataclass(frozen=True)
class State:
    """Assembled state: q (n,) m, qd (n,) m/s."""

    q: np.ndarray
    qd: np.ndarray


def _drivers(model: Model, q: np.ndarray, values: dict[str, float], velocity: bool):
    """Rows B (k, n) and right-hand sides (k,) that set channels to values.

    Position (velocity=False): linearised about q, so that B @ (q + dq) - z = 0 is one
    Newton row. Velocity: B @ qd = z exactly.
    """
    case, rows, rhs = model.case, [], []
    for name, value in values.items():
        ch = case.channel(name)
        b = model.bodies[ch.body]
        if ch.kind == "position":
            C = model.point_map(ch.body, case.body(ch.body).points[ch.point])
            k = {"x": 0, "y": 1}[ch.axis]
            rows.append(C[k, :-1])
            rhs.append(value - (0.0 if velocity else C[k, -1]))
        elif ch.kind == "angle":
            if b.p_j is None:
                raise AssemblyError(f"channel {name!r}: a particle has no angle to set")
            d = q[b.cols[2:]] - q[b.cols[:2]]
            row = np.zeros(model.n)
            if velocity:  # omega = (d x dd) / |d|^2
                g = J2 @ d / (d @ d)
                row[b.cols[2:]], row[b.cols[:2]] = g, -g
                rows.append(row)
                rhs.append(value)
            else:  # d parallel to R(value) dloc: cross(e0, d) = 0, linear in q
                dloc = b.p_j - b.p_i
                th = value + np.arctan2(dloc[1], dloc[0])
                e0 = np.array([np.cos(th), np.sin(th)])
                g = np.array([-e0[1], e0[0]])  # cross(e0, d) = g @ d
                row[b.cols[2:]], row[b.cols[:2]] = g, -g
                rows.append(row)
                rhs.append(0.0)
    return np.array(rows).reshape(-1, model.n), np.array(rhs)


def assemble(model: Model, q0: np.ndarray, fix: dict[str, float], *, tol: float = 1e-12,
             max_iter: int = 50, t: float = 0.0) -> tuple[np.ndarray, int]:
    """Newton-Raphson from q0 to Phi(q, t) = 0 (drivers included) with ``fix`` channels held.

    Returns (q, iterations). Raises AssemblyError naming the constraints still violated.
    """
    q = np.array(q0, dtype=float)
    con = ConstraintSystem(model)
    for it in range(1, max_iter + 1):
        B, z = _drivers(model, q, fix, velocity=False)
        r = np.concatenate([con.phi(q, t), B @ q - z])
        if np.max(np.abs(r), initial=0.0) < tol and it > 1:
            return q, it - 1
        A = np.vstack([con.jacobian(q, t), B])
        dq = np.linalg.lstsq(A, -r, rcond=None)[0]
        q += dq
        if np.max(np.abs(dq)) < tol * max(1.0, np.max(np.abs(q))) and \
                np.max(np.abs(con.phi(q, t)), initial=0.0) < tol * 10:
            return q, it
    phi = con.phi(q, t)
    bad = np.argsort(-np.abs(phi))[:3]
    worst = ", ".join(f"{con.labels[k]} ({phi[k]:.3g})" for k in bad if abs(phi[k]) > tol)
    raise AssemblyError(f"case {model.case.name!r} does not assemble from its initial pose "
                        f"after {max_iter} Newton iterations; "
                        f"violated: {worst or 'fixed channels'}")


def solve_velocity(model: Model, q: np.ndarray, velocity: dict[str, float],
                   t: float = 0.0) -> np.ndarray:
    """Velocity problem Phi_q qd = -Phi_t with the ``velocity`` channels prescribed: qd (n,)."""
    B, z = _drivers(model, q, velocity, velocity=True)
    con = ConstraintSystem(model)
    Jq = con.jacobian(q, t)
    A = np.vstack([Jq, B])
    rhs = np.concatenate([-con.phi_t(q, t), z])
    qd, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    res = A @ qd - rhs
    if np.max(np.abs(res), initial=0.0) > 1e-9 * max(1.0, np.max(np.abs(qd))):
        raise AssemblyError("the initial velocities are inconsistent with the constraints "
                            f"(residual {np.max(np.abs(res)):.3g})")
    dof = model.n - np.linalg.matrix_rank(Jq)
    if len(z) < dof:
        raise AssemblyError(f"the mechanism has {dof} degrees of freedom but initial.velocity "
                            f"sets {len(z)}")
    return qd


def initial_state(model: Model) -> State:
    """Assemble the case's initial pose and solve its initial velocities."""
    case: Case = model.case
    q, _ = assemble(model, model.q_from_poses(case.guess), case.fix)
    return State(q, solve_velocity(model, q, case.velocity))


def mobility(model: Model, q: np.ndarray, tol: float = 1e-9, *,
             drivers: bool = False, t: float = 0.0) -> tuple[int, int, int]:
    """(rank r of Phi_q, degrees of freedom n - r, redundant constraints m - r) at q.

    ``drivers=True`` counts the driver rows too (a fully driven mechanism has 0 DOF).
    """
    if drivers:
        con = ConstraintSystem(model)
        J, m = con.jacobian(q, t), con.m
    else:
        J, m = model.constraints.jacobian(q), model.constraints.m
    r = int(np.linalg.matrix_rank(J, tol))
    return r, model.n - r, m - r


def solve_position(model, q0: np.ndarray, t: float, *, tol: float = 1e-12,
                   max_iter: int = 30) -> tuple[np.ndarray, int]:
    """Driven position problem Phi(q, t) = 0 by Newton-Raphson from q0 (min-norm steps).

    Returns (q (n,), iterations); raises AssemblyError when it does not converge.
    """
    con = ConstraintSystem(model)
    q = np.array(q0, dtype=float)
    for it in range(max_iter):
        phi = con.phi(q, t)
        if np.max(np.abs(phi), initial=0.0) < tol:
            return q, it
        q -= np.linalg.lstsq(con.jacobian(q, t), phi, rcond=None)[0]
    raise AssemblyError(f"driven position problem at t = {t:.6g} s did not converge "
                        f"(max |Phi| = {np.max(np.abs(con.phi(q, t))):.3g})")


def solve_acceleration(model, q: np.ndarray, qd: np.ndarray, t: float = 0.0,
                       qdd_indep: dict[int, float] | None = None) -> np.ndarray:
    """Acceleration problem Phi_q qdd = c (drivers included): qdd (n,), min-norm.

    For a fully driven mechanism (0 DOF) the answer is unique; ``qdd_indep`` {coordinate
    index: value} prescribes further accelerations otherwise.
    """
    con = ConstraintSystem(model)
    J, c = con.jacobian(q, t), con.gamma(q, qd, t)
    if qdd_indep:
        B = np.zeros((len(qdd_indep), model.n))
        for row, k in enumerate(qdd_indep):
            B[row, k] = 1.0
        J, c = np.vstack([J, B]), np.concatenate([c, list(qdd_indep.values())])
    return np.linalg.lstsq(J, c, rcond=None)[0]


def kinematic_analysis(model, q0: np.ndarray, times: np.ndarray):
    """Positions, velocities and accelerations of a fully driven mechanism at ``times``.

    Returns (q, qd, qdd), each (T, n). Each sample starts Newton from a second-order
    prediction of the previous one.
    """
    con = ConstraintSystem(model)
    T, n = len(times), model.n
    Q, QD, QDD = np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, n))
    q = np.array(q0, dtype=float)
    for k, t in enumerate(times):
        if k:
            h = t - times[k - 1]
            q = Q[k - 1] + h * QD[k - 1] + 0.5 * h * h * QDD[k - 1]
        q, _ = solve_position(model, q, t)
        J = con.jacobian(q, t)
        qd = np.linalg.lstsq(J, -con.phi_t(q, t), rcond=None)[0]
        qdd = np.linalg.lstsq(J, con.gamma(q, qd, t), rcond=None)[0]
        Q[k], QD[k], QDD[k] = q, qd, qdd
    return Q, QD, QDD
