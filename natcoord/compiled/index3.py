"""Compiled (numba) time loop of the index-3 augmented Lagrangian formulation.

The whole run in one call, step for step what ``Index3Loop`` does in Python (Bayo &
Ledesma): the trapezoidal rule with fixed steps that land on every sample, and per step
Newton on

    M (q - qhat) + h^2/4 (Phi_q^T (lambda* + alpha Phi) - F) = 0,
    qhat = q_n + h qd_n + h^2/4 qdd_n,   beta = alpha h^2/4 = penalty max|M_ii|,

with the tangent ``M + beta Phi_q^T Phi_q + h^2/4 (sum_k mu_k d2Phi_k/dq2 - K)``, K the
forces' dF/dq + 2/h dF/dqd (:func:`force_tangent`), and lambda*
updated by ``alpha Phi`` after every iteration (a failed Newton retries the step with the
penalty x100, up to 1e10); then qd and qdd projected M-orthogonally onto
``Phi_q qd = 0`` and ``Phi_q qdd = c`` by augmented-Lagrangian sweeps on one factor of
``M + beta Phi_q^T Phi_q``. Dense linear algebra (n, n): a singular M is fine where
ker M ∩ ker Phi_q = {0}. Constraints are the scleronomic triplets ``k, i, j, v`` over
qh = [q, 1] (:class:`~natcoord.model.constraints.QuadraticConstraints`), forces the tuple of
:func:`natcoord.compiled.general.pack_forces`. Units: SI (m, s, kg, N).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import general as kernels_general
from .general import (
    C_FACT,
    C_NEWTON,
    C_PROJ,
    C_REJ,
    C_RHS,
    C_STEPS,
    ERR_MASS,
    ERR_NEWTON,
    N_COUNTERS,
    OK,
    _gamma,
    _jac,
    _lu,
    _lu_solve,
    _phi,
    drift,
    forces,
    pack_constraints,
)
from .index1 import add_counters, check, drop_stale_cache, njit, warm_up_model

PENALTY_MAX = 1e10  # the retries' last penalty (relative to max|M_ii|)
FD_STEP = 1e-7  # relative step of the forces' difference quotients in the Newton tangent


def force_tangent(frc: tuple | None, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The applied forces' part of the Newton tangent, K = dF/dq + 2/h dF/dqd, for packed
    forces (:func:`pack_forces`; None: forces natcoord cannot read): (K0 (n, n), cols (c,)
    int) with K0 the constant T of Q0 + T q and cols the coordinates whose columns come
    from forward differences instead (those a spring-damper's ends move: its stiffness
    and damping; every coordinate for unread forces); None for forces without either
    (constant ones). A torque's stiffness, of the order of the torque, is left out."""
    if frc is None:
        return np.zeros((n, n)), np.arange(n, dtype=np.int64)
    _, T, _, _, _, S, _ = frc
    moved = np.any(S[:, :, :n] != 0.0, axis=(0, 1)) if S.shape[0] else np.zeros(n, bool)
    if not (T.shape[0] and T.any()) and not moved.any():
        return None
    K0 = np.array(T, float) if T.shape[0] else np.zeros((n, n))
    return K0, np.flatnonzero(moved).astype(np.int64)


@njit(cache=True)
def _augmented(M, J, beta, JtJ, out):
    """out (n, n) = M + beta J^T J (J^T J into JtJ by BLAS)."""
    np.dot(J.T, J, JtJ)
    for a in range(M.shape[0]):
        for b in range(M.shape[0]):
            out[a, b] = M[a, b] + beta * JtJ[a, b]


@njit(cache=True)
def _force_tangent(frc, K0, cols, h, q, qd, F, Fp, K, cnt):
    """K (n, n) = K0 with the columns ``cols`` by forward differences of the forces F at
    (q, qd) along q and qd = 2/h q (:func:`force_tangent`); Fp (n,) scratch."""
    K[:, :] = K0
    for a in cols:
        e = FD_STEP * max(1.0, abs(q[a]))
        qa, qda = q[a], qd[a]
        q[a] = qa + e
        qd[a] = qda + 2.0 / h * e
        forces(frc, q, qd, Fp)
        q[a], qd[a] = qa, qda
        for b in range(q.shape[0]):
            K[b, a] = (Fp[b] - F[b]) / e
    cnt[C_RHS] += cols.shape[0]


@njit(cache=True)
def _newton(mdl, h, start, qhat, beta, newton_tol, q, lam, w, cnt):
    """Newton on the step's equations from q = q0 + h qd0 + h^2/2 qdd0 (``start`` = (q0,
    qd0, qdd0)): q (n,) and lam (m,) (lambda* on entry, updated) in place; False when it
    does not converge in 30 iterations or leaves the finite numbers. ``mdl`` = (con, M,
    frc, Kt) as in :func:`run_index3`, ``Kt`` = (K0 (n, n), cols (c,)) the forces' tangent
    (:func:`force_tangent`; K0 (0, 0): none). ``w`` = (p (m,), J (m, n), F, g (n,), Tg, JtJ
    (n, n), piv (n,) int, Fp (n,), K (n, n)) scratch."""
    con, M, frc, Kt = mdl
    q0, qd0, qdd0 = start
    kk, ii, jj, vv, m = con
    p, J, F, g, Tg, JtJ, piv, Fp, K = w
    K0, cols = Kt
    n = q.shape[0]
    alpha = 4.0 * beta / (h * h)
    c4 = 0.25 * h * h
    for a in range(n):
        q[a] = q0[a] + h * qd0[a] + 0.5 * h * h * qdd0[a]
    qd = np.empty(n)
    for _ in range(30):
        for a in range(n):
            qd[a] = qd0[a] + 0.5 * h * (qdd0[a] + 4.0 / (h * h) * (q[a] - qhat[a]))
        _phi(kk, ii, jj, vv, m, q, p)
        _jac(kk, ii, jj, vv, q, J)
        forces(frc, q, qd, F)
        cnt[C_RHS] += 1
        for r in range(m):
            p[r] = lam[r] + alpha * p[r]  # mu = lambda* + alpha Phi
        for a in range(n):
            s = -F[a]
            for r in range(m):
                s += J[r, a] * p[r]
            s *= c4
            for b in range(n):
                s += M[a, b] * (q[b] - qhat[b])
            g[a] = -s
        _augmented(M, J, beta, JtJ, Tg)
        for t in range(kk.shape[0]):  # h^2/4 sum_k mu_k d2Phi_k/dq2
            if ii[t] < n and jj[t] < n:
                Tg[ii[t], jj[t]] += c4 * p[kk[t]] * vv[t]
        if K0.shape[0] > 0:
            _force_tangent(frc, K0, cols, h, q, qd, F, Fp, K, cnt)
            for a in range(n):  # - h^2/4 (dF/dq + 2/h dF/dqd)
                for b in range(n):
                    Tg[a, b] -= c4 * K[a, b]
        if not _lu(Tg, piv):
            return False
        _lu_solve(Tg, piv, g)
        dq = g
        cnt[C_FACT] += 1
        cnt[C_NEWTON] += 1
        big = 1.0
        step = 0.0
        for a in range(n):
            q[a] += dq[a]
            big = max(big, abs(q[a]))
            step = max(step, abs(dq[a]))
        _phi(kk, ii, jj, vv, m, q, p)
        for r in range(m):
            lam[r] += alpha * p[r]
        if not (step == step and big < math.inf):
            return False
        if step < newton_tol * 10.0 * big:
            return True
    return False


@njit(cache=True)
def _mproject(M, P, piv, J, beta, x, b, tol, w):
    """x (n,) in place: argmin (x' - x)^T M (x' - x) subject to J x' = b (m,), by
    augmented-Lagrangian sweeps (M + beta J^T J) x' = M x + J^T (beta b - sigma) on P, piv:
    the LU factors of M + beta J^T J; ``w`` = (Mx (n,), sigma (m,)) scratch."""
    Mx, sigma = w
    n, m = x.shape[0], b.shape[0]
    for a in range(n):
        s = 0.0
        for c in range(n):
            s += M[a, c] * x[c]
        Mx[a] = s
    sigma[:] = 0.0
    for _ in range(20):
        for a in range(n):
            s = Mx[a]
            for r in range(m):
                s += J[r, a] * (beta * b[r] - sigma[r])
            x[a] = s
        _lu_solve(P, piv, x)
        res = 0.0
        for r in range(m):
            s = -b[r]
            for a in range(n):
                s += J[r, a] * x[a]
            sigma[r] += beta * s
            res = max(res, abs(s))
        if res < tol:
            break


@njit(cache=True)
def run_index3(con, M, frc, Kt, ctl, times, y0, out):
    """Trapezoidal steps of at most h over ``times`` (T,) from y0 = [q, qd, qdd, lambda*]
    (3n + m) at times[0]; ``con`` = (k, i, j, v, m); ``Kt``: see :func:`_newton`; ``ctl`` =
    (h, penalty, mscale, newton_tol, project_tol); ``out`` = (Q, QD, QDD (T, n),
    cnt (N_COUNTERS,), tfail (1,)) filled in place (tfail: the time a step failed). Returns
    a status code (0 = ok)."""
    kk, ii, jj, vv, m = con
    h_max, penalty0, mscale, newton_tol, ptol = ctl
    Q, QD, QDD, cnt, tfail = out
    n = M.shape[0]
    q0 = y0[:n].copy()
    qd0 = y0[n:2 * n].copy()
    qdd0 = y0[2 * n:3 * n].copy()
    lam0 = y0[3 * n:].copy()
    q, lam, qhat, c = np.empty(n), np.empty(m), np.empty(n), np.empty(m)
    wn = (np.empty(m), np.empty((m, n)), np.empty(n), np.empty(n), np.empty((n, n)),
          np.empty((n, n)), np.empty(n, np.int64), np.empty(n), np.empty((n, n)))
    wp = (np.empty(n), np.empty(m))
    J, P, piv, zero = wn[1], wn[4], wn[6], np.zeros(m)
    mdl, start = (con, M, frc, Kt), (q0, qd0, qdd0)  # the model; the step's start, in place
    Q[0], QD[0], QDD[0] = q0, qd0, qdd0
    for k in range(1, times.shape[0]):
        nsub = max(1, math.ceil((times[k] - times[k - 1]) / h_max - 1e-9))
        h = (times[k] - times[k - 1]) / nsub
        for step in range(nsub):
            penalty = penalty0
            while True:
                beta = penalty * mscale
                for a in range(n):
                    qhat[a] = q0[a] + h * qd0[a] + 0.25 * h * h * qdd0[a]
                lam[:] = lam0
                if _newton(mdl, h, start, qhat, beta, newton_tol, q, lam, wn, cnt):
                    break
                if penalty >= PENALTY_MAX:
                    tfail[0] = times[k - 1] + (step + 1) * h
                    return ERR_NEWTON
                penalty *= 100.0
                cnt[C_REJ] += 1
            for a in range(n):  # qdd, qd of the trapezoidal rule, then their projections
                acc = 4.0 / (h * h) * (q[a] - qhat[a])
                qd0[a] = qd0[a] + 0.5 * h * (qdd0[a] + acc)
                qdd0[a] = acc
            drift(kk, ii, jj, vv, q, qd0, wn[0], J, cnt)
            _augmented(M, J, beta, wn[5], P)
            if not _lu(P, piv):
                tfail[0] = times[k - 1] + (step + 1) * h
                return ERR_MASS
            cnt[C_FACT] += 1
            _mproject(M, P, piv, J, beta, qd0, zero, ptol, wp)
            _gamma(kk, ii, jj, vv, qd0, c)
            _mproject(M, P, piv, J, beta, qdd0, c, ptol, wp)
            cnt[C_PROJ] += 1
            cnt[C_STEPS] += 1
            q0[:] = q
            lam0[:] = lam
        Q[k], QD[k], QDD[k] = q0, qd0, qdd0
    return OK


class Steps(NamedTuple):
    """The trapezoidal steps of a compiled index-3 run: at most ``h`` s, the ``penalty``
    alpha h^2/4 relative to ``mscale`` (max|M_ii|, kg), Newton's and the projections'
    tolerances (:class:`natcoord.dynamics.index3.Index3`)."""

    h: float
    penalty: float
    mscale: float
    newton_tol: float
    project_tol: float


def run(con, frc, M, times, y, steps: Steps, cnt=None):
    """Integrate with the compiled loop from ``y`` = [q, qd, qdd, lambda*] (3n + m,
    consistent, at times[0]); returns (Q, QD, QDD) (T, n). ``con``: the constraints
    (``k, i, j, v, m``); ``frc``: :func:`pack_forces`; ``M`` (n, n) kg; ``cnt``: counters
    added to. Raises RuntimeError when a step's Newton fails at every penalty."""
    n, T = M.shape[0], len(times)
    Q, QD, QDD = np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, n))
    c, tfail = np.zeros(N_COUNTERS), np.zeros(1)
    ctl = tuple(float(x) for x in steps)
    Kt = force_tangent(frc, n)
    status = run_index3(pack_constraints(con), np.ascontiguousarray(M, float), frc,
                        (np.zeros((0, 0)), np.zeros(0, np.int64)) if Kt is None else Kt, ctl,
                        np.ascontiguousarray(times, float), np.asarray(y, float),
                        (Q, QD, QDD, c, tfail))
    add_counters(c, cnt)
    if status == ERR_NEWTON:
        raise RuntimeError(f"index3 (compiled): Newton did not converge at t = "
                           f"{tfail[0]:.6g} s, up to a penalty of {PENALTY_MAX:g}")
    check(status, "index3")
    return Q, QD, QDD


def warm_up() -> None:
    """Compile (or load from numba's cache) the loop by a tiny run: a particle on a unit
    circle under gravity."""
    con, frc = warm_up_model()
    y = np.array([1.0, 0.0, 0.0, 0.0, -0.0, 0.0, 0.0])
    run(con, frc, np.eye(2), np.linspace(0.0, 0.02, 3), y, Steps(0.005, 1e4, 1.0, 1e-13, 1e-13))


drop_stale_cache(globals(), __name__, (kernels_general,))
