"""Forward dynamics: index-1 Lagrange equations (paper Eq. (6)) with projection.

    [ M      Phi_q^T ] [ qdd    ]   [ Q(q)              ]
    [ Phi_q  0       ] [ lambda ] = [ -qd^T H_k qd      ]

integrated by an adaptive explicit Runge-Kutta method between output samples, with q and qd
projected back onto Phi = 0 and Phi_q qd = 0 at every sample (the drift is then bounded by
the integrator tolerance over one sample interval, not over the whole run).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from .kinematics import State
from .model import Model


@dataclass
class Counters:
    """Cost counters of one integration; they do not depend on machine noise."""

    steps: int = 0
    rhs: int = 0
    factorizations: int = 0
    projections: int = 0
    newton: int = 0
    max_phi: float = 0.0
    max_phi_dot: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Solution:
    """Samples of an integration: t (T,), q (T, n), qd (T, n), qdd (T, n), lam (T, m)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    lam: np.ndarray
    counters: dict = field(default_factory=dict)
    wall_time_s: float = 0.0


def accelerations(model: Model, q: np.ndarray, qd: np.ndarray,
                  t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Index-1 solve at one state: (qdd (n,), lambda (m,)).

    The augmented matrix is singular with redundant constraints; lstsq then returns the
    minimum-norm lambda while qdd stays unique when ker M ∩ ker Phi_q = {0}.
    """
    n, m = model.n, model.m
    Jq = model.constraints.jacobian(q)
    A = np.zeros((n + m, n + m))
    A[:n, :n], A[:n, n:], A[n:, :n] = model.M, Jq.T, Jq
    b = np.concatenate([model.forces(t, q, qd), -model.constraints.quad_velocity(qd)])
    try:
        x = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(A, b, rcond=None)[0]
    return x[:n], x[n:]


def project(model: Model, q: np.ndarray, qd: np.ndarray, tol: float = 1e-13,
            counters: Counters | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares projection of q onto Phi = 0 (Newton) and of qd onto Phi_q qd = 0."""
    con = model.constraints
    q = q.copy()
    for _ in range(10):
        phi = con.phi(q)
        if np.max(np.abs(phi), initial=0.0) < tol:
            break
        q -= np.linalg.lstsq(con.jacobian(q), phi, rcond=None)[0]
        if counters:
            counters.newton += 1
    Jq = con.jacobian(q)
    qd = qd - np.linalg.lstsq(Jq, Jq @ qd, rcond=None)[0]
    if counters:
        counters.projections += 1
    return q, qd


def integrate(model: Model, state: State, times: np.ndarray, *, method: str = "DOP853",
              rtol: float = 1e-10, atol: float = 1e-12) -> Solution:
    """Integrate from ``state`` at times[0] and sample at ``times`` (T,)."""
    n = model.n
    cnt = Counters()

    def rhs(t, y):
        cnt.rhs += 1
        cnt.factorizations += 1
        qdd, _ = accelerations(model, y[:n], y[n:], t)
        return np.concatenate([y[n:], qdd])

    T = len(times)
    Q, QD, QDD, LAM = (np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, n)),
                       np.zeros((T, model.m)))
    q, qd = project(model, state.q, state.qd, counters=cnt)
    t0 = time.perf_counter()
    first_step = None
    for k, t in enumerate(times):
        if k > 0:
            h = t - times[k - 1]
            sol = solve_ivp(rhs, (times[k - 1], t), np.concatenate([q, qd]), method=method,
                            rtol=rtol, atol=atol,
                            first_step=None if first_step is None else min(first_step, h))
            if not sol.success:
                raise RuntimeError(f"integration failed at t = {times[k - 1]:.6g} s: "
                                   f"{sol.message}")
            cnt.steps += len(sol.t) - 1
            first_step = float(np.diff(sol.t)[-1]) if len(sol.t) > 1 else None
            drift = np.max(np.abs(model.constraints.phi(sol.y[:n, -1])), initial=0.0)
            cnt.max_phi = max(cnt.max_phi, float(drift))
            q, qd = project(model, sol.y[:n, -1], sol.y[n:, -1], counters=cnt)
        qdd, lam = accelerations(model, q, qd, t)
        Q[k], QD[k], QDD[k], LAM[k] = q, qd, qdd, lam
    wall = time.perf_counter() - t0
    cnt.max_phi_dot = float(max(np.max(np.abs(model.constraints.jacobian(Q[k]) @ QD[k]),
                                       initial=0.0) for k in range(T)))
    return Solution(times, Q, QD, QDD, LAM, cnt.as_dict(), wall)
