"""Position, velocity and acceleration problems (Newton-Raphson on Phi(q, t) = 0).

Redundant constraints are allowed: every linear solve is a least-squares solve, which gives
the minimum-norm correction and tolerates a rank-deficient Phi_q.

Quantities held fixed while assembling (a crank angle, a slider position) are
:class:`Prescribed` rows: a world coordinate ``C @ [q, 1]`` of a point, or the angle of a
difference vector ``d = C @ [q, 1]`` (2 rows of C) in a plane, plus a fixed offset. Both are
linear in q at the position level (``cross(e(value + offset), d) = 0`` for an angle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as spla

from ..errors import AssemblyError
from . import sparserank
from .drivers import ConstraintSystem
from .model import J2


@dataclass(frozen=True)
class State:
    """Assembled state: q (n,) m, qd (n,) m/s."""

    q: np.ndarray
    qd: np.ndarray


@dataclass(frozen=True)
class Prescribed:
    """A value set at t = 0: ``kind`` "position" with C (n + 1,) (a world coordinate, m) or
    "angle" with C (2, n + 1) (a difference vector in a plane whose angle, less ``offset``,
    is the value, rad); ``value`` in m or rad (m/s or rad/s at the velocity level)."""

    name: str
    kind: str
    C: np.ndarray
    value: float
    offset: float = 0.0


def _position_rows(n: int, fix: list[Prescribed]) -> np.ndarray:
    """Rows a (k, n + 1) with a @ [q, 1] = 0 for every fixed value (linear in q)."""
    rows = []
    for p in fix:
        if p.kind == "position":
            a = p.C.copy()
            a[n] -= p.value
        else:  # d parallel to e(value + offset): cross(e, d) = g @ d = 0
            th = p.value + p.offset
            a = np.array([-np.sin(th), np.cos(th)]) @ p.C
        rows.append(a)
    return np.array(rows).reshape(-1, n + 1)


def _velocity_rows(q: np.ndarray, given: list[Prescribed]) -> tuple[np.ndarray, np.ndarray]:
    """Rows B (k, n) and values z (k,) with B @ qd = z for every given rate."""
    n, qh = len(q), np.append(q, 1.0)
    rows = []
    for p in given:
        if p.kind == "position":
            rows.append(p.C[:n])
        else:  # omega = (J2 d) . d_dot / |d|^2
            d = p.C @ qh
            rows.append((J2 @ d) @ p.C[:, :n] / (d @ d))
    return np.array(rows).reshape(-1, n), np.array([p.value for p in given])


def assemble(model, q0: np.ndarray, fix: list[Prescribed] = (), *, tol: float = 1e-12,
             max_iter: int = 50, t: float = 0.0) -> tuple[np.ndarray, int]:
    """Newton-Raphson from q0 to Phi(q, t) = 0 (drivers included) with ``fix`` held.

    Returns (q, iterations). Raises AssemblyError naming the constraints still violated.
    """
    q = np.array(q0, dtype=float)
    con = ConstraintSystem(model)
    B = _position_rows(model.n, list(fix))
    for it in range(1, max_iter + 1):
        r = np.concatenate([con.phi(q, t), B @ np.append(q, 1.0)])
        if np.max(np.abs(r), initial=0.0) < tol and it > 1:
            return q, it - 1
        As = sparserank.certified(con, q, t, extra=B[:, :-1])
        if As is not None:  # the same minimum-norm step, linear in the size
            dq = sparserank.min_norm_solve(As, -r)
        else:
            A = np.vstack([con.jacobian(q, t), B[:, :-1]])
            dq = np.linalg.lstsq(A, -r, rcond=None)[0]
        q += dq
        if np.max(np.abs(dq)) < tol * max(1.0, np.max(np.abs(q))) and \
                np.max(np.abs(con.phi(q, t)), initial=0.0) < tol * 10:
            return q, it
    phi = con.phi(q, t)
    bad = np.argsort(-np.abs(phi))[:3]
    worst = ", ".join(f"{con.labels[k]} ({phi[k]:.3g})" for k in bad if abs(phi[k]) > tol)
    raise AssemblyError(f"the mechanism does not assemble from its initial pose after "
                        f"{max_iter} Newton iterations; violated: {worst or 'fixed values'}")


def solve_velocity(model, q: np.ndarray, given: list[Prescribed] = (),
                   t: float = 0.0) -> np.ndarray:
    """Velocity problem Phi_q qd = -Phi_t with the ``given`` rates: qd (n,).

    With no rates given and no driver the mechanism starts at rest. Otherwise the rates and
    the drivers must fix qd uniquely and consistently (AssemblyError says what is missing).
    """
    con = ConstraintSystem(model)
    given = list(given)
    if not given and not con.rheonomic:
        return np.zeros(model.n)
    B, z = _velocity_rows(q, given)
    rhs = np.concatenate([-con.phi_t(q, t), z])
    As = sparserank.certified(con, q, t, extra=B)
    if As is not None and As.shape[0] == model.n:  # square and regular: the unique qd
        qd = spla.splu(As.tocsc()).solve(rhs)  # by a sparse LU (linear in the size)
        res = np.max(np.abs(As @ qd - rhs), initial=0.0)
        if res <= 1e-9 * max(1.0, np.max(np.abs(qd))):
            return qd
    Jq = con.jacobian(q, t)
    A = np.vstack([Jq, B])
    qd = np.linalg.lstsq(A, rhs, rcond=None)[0]
    dof = model.n - int(np.linalg.matrix_rank(Jq, 1e-9))
    res = np.max(np.abs(A @ qd - rhs), initial=0.0)
    if res > 1e-9 * max(1.0, np.max(np.abs(qd))):
        raise AssemblyError(f"the initial velocities are inconsistent with the constraints "
                            f"and drivers (residual {res:.3g})")
    rank = int(np.linalg.matrix_rank(A, 1e-9))
    if rank < model.n:
        fixed = rank - (model.n - dof)  # what the rates fix beyond the constraints
        which = (f"{len(given)}, of which {fixed} fix a velocity the constraints leave "
                 "free (the others follow from them and the constraints)"
                 if fixed < len(given) else str(len(given)))
        raise AssemblyError(f"the mechanism has {dof} degree(s) of freedom left by its "
                            f"drivers, but initial.velocity sets {which}: {dof - fixed} "
                            "velocity direction(s) left open; the rates given must fix "
                            "every velocity")
    return qd


def mobility(model, q: np.ndarray, tol: float = 1e-9, *,
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


def singular_hint(J: np.ndarray, rank_tol: float) -> str:
    """What a failed step near a singular position should say, from Phi_q (m, n) there:
    how close to a rank drop the constraints are and what to change; "" when they are
    well conditioned (the failure has another cause)."""
    try:
        s = np.linalg.svd(np.asarray(J, float), compute_uv=False)
    except (np.linalg.LinAlgError, ValueError):
        return ""
    if len(s) == 0 or not s[0] > 0:
        return ""
    live = s[s > rank_tol * s[0]]
    ratio = float(live[-1] / s[0]) if len(live) else 0.0
    if ratio >= 1e-2:
        return ""
    near = int(np.sum(s[:len(live)] < 1e-2 * s[0]))  # rows about to drop out of the rank
    return (f": the mechanism is at or near a singular position (the smallest non-zero "
            f"singular value of Phi_q is {ratio:.1e} of the largest; {near} of its "
            f"{len(live)} independent rows are about to drop out), where a state a rounding "
            "error off the constraint manifold turns sharply onto another branch and the "
            "step control cannot follow it; change to coordinates = \"shared\" with "
            "linsolve = \"schur\" (Phi summed in two doubles, projected to round-off), or a "
            "fixed step (method = \"rk4\" with h)")
