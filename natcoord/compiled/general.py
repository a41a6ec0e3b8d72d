"""Model and linear-algebra pieces of the compiled index-1 loop
(:func:`natcoord.compiled.index1.run_index1`): constraints from their triplets, applied forces, the
Schur complement of a regular M with constraints of full rank, and the general case (a
singular mass matrix, redundant constraints) below.

Linear algebra: the null-space form of Eq. (6), as ``Index1`` in ``linsolve="qr"`` mode.
A Householder QR of Phi_q^T (n, m) with column pivoting (columns of Phi_q^T are rows of
Phi_q, so the pivots pick independent constraint rows) stops at the rank r, the first pivot
with ``|R_kk| <= rank_tol |R_00|``. Then

    v1 = Q1 R11^-T c[P[:r]]             (min-norm solution of the independent rows)
    Z  = Q2^T  (n - r, n)               (orthonormal basis of ker Phi_q, rows)
    qdd = v1 + Z^T (Z M Z^T)^-1 Z (F - M v1)

and a min-norm correction ``dx = Q1 R11^-T rhs[P[:r]]`` for the projections. The work array
``W`` (m, n) holds Phi_q with its rows permuted: after the factorization row k holds
R[:k+1, k] in its first k+1 entries and the Householder vector of step k below (implicit
leading 1), ``th`` (m,) the Householder factors, ``piv`` (m,) the row permutation P.

Forces (:func:`forces`, ``Model.forces`` and ``NaturalModel.forces`` in numba) take the
tuple of :func:`pack_forces` (filled by :func:`natcoord.dynamics.common.compiled_forces`):
``Q0`` (n,), ``T`` (n, n) or (0, 0), torque difference maps ``G`` (nG, d, n+1) with torque t
on rows ``toff[t]:toff[t+1]``, torques ``tau`` (nt, 3) (2-D: tau[:, 0]; with body-fixed
torques (nt, 4 + K): world torque ``tau[t, :3] + tau[t, 3] d_0 x d_1 + sum_k tau[t, 4 + k]
d_k`` over the torque's difference vectors d_k = G[toff[t] + k] qh), spring maps
``S = B - A`` (ns, d, n+1) and ``spr`` (ns, 3) = (k N/m, c N s/m, l0 m).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover
    def njit(*args, **kwargs):
        if args and callable(args[0]):
            return args[0]
        return lambda f: f


# counter slots of the ``cnt`` array, status codes (shared with natcoord.compiled.index1)
C_STEPS, C_REJ, C_RHS, C_FACT, C_PROJ, C_NEWTON, C_PHI, C_PHID, C_REPART = range(9)
N_COUNTERS = 9
OK, ERR_UNDERFLOW, ERR_SINGULAR, ERR_NEWTON, ERR_MAXSTEPS, ERR_NONFINITE, ERR_MASS = range(7)


# ---- constraints over qh = [q, 1] (triplets k, i, j, v) ----------------------------------
@njit(cache=True)
def _phi(kk, ii, jj, vv, m, q, out):
    n = q.shape[0]
    for r in range(m):
        out[r] = 0.0
    for t in range(kk.shape[0]):
        a = q[ii[t]] if ii[t] < n else 1.0
        b = q[jj[t]] if jj[t] < n else 1.0
        out[kk[t]] += 0.5 * vv[t] * a * b


@njit(cache=True)
def _jac(kk, ii, jj, vv, q, J):
    n = q.shape[0]
    J[:, :] = 0.0
    for t in range(kk.shape[0]):
        if ii[t] < n:
            b = q[jj[t]] if jj[t] < n else 1.0
            J[kk[t], ii[t]] += vv[t] * b


@njit(cache=True)
def _gamma(kk, ii, jj, vv, qd, c):
    """c = -qd^T H_k qd (velocity part of the acceleration constraints)."""
    n = qd.shape[0]
    c[:] = 0.0
    for t in range(kk.shape[0]):
        if ii[t] < n and jj[t] < n:
            c[kk[t]] -= vv[t] * qd[ii[t]] * qd[jj[t]]


# ---- drift before a projection ---------------------------------------------------------
@njit(cache=True)
def drift(kk, ii, jj, vv, q, qd, w, J, cnt):
    """Before a projection: w = Phi(q) (m,), J = Phi_q (m, n), and the largest |Phi| and
    |Phi_q qd| so far in cnt[C_PHI], cnt[C_PHID] (what one step let drift)."""
    m, n = J.shape
    _phi(kk, ii, jj, vv, m, q, w)
    for r in range(m):
        cnt[C_PHI] = max(cnt[C_PHI], abs(w[r]))
    _jac(kk, ii, jj, vv, q, J)
    for r in range(m):
        s = 0.0
        for a in range(n):
            s += J[r, a] * qd[a]
        cnt[C_PHID] = max(cnt[C_PHID], abs(s))


ROUNDOFF = 4 * 2.2e-16  # |Phi| that evaluating a quadratic row at |q| ~ 1 m cannot beat


@njit(cache=True)
def reachable(tol, q, power):
    """The projection tolerance (m) that Phi's evaluation can reach at q: ``tol``, or
    ROUNDOFF max|q|^power when that is larger. ``power`` 2: a plain sum of products, whose
    rows quadratic in coordinates as large as max|q| carry that round-off (a chain 60 m long
    cannot be projected to 1e-13 m); 1: an exact sum (:func:`kernels_sparse.phi`), left
    with the resolution of q itself."""
    big = 1.0
    for a in range(q.shape[0]):
        big = max(big, abs(q[a]))
    return max(tol, ROUNDOFF * (big if power == 1 else big * big))  # (no pow call)


@njit(cache=True)
def jv(J, x, w):
    """w = J x (m,) in place; returns max |w|."""
    e = 0.0
    for r in range(J.shape[0]):
        s = 0.0
        for a in range(J.shape[1]):
            s += J[r, a] * x[a]
        w[r] = s
        e = max(e, abs(s))
    return e


@njit(cache=True)
def _cholesky(L, k):
    """In-place lower Cholesky of the leading (k, k) block of L (its lower triangle holds
    the matrix); False when a pivot falls below 1e-14 of the largest diagonal entry."""
    scale = 0.0
    for r in range(k):
        scale = max(scale, abs(L[r, r]))
    for r in range(k):
        s = L[r, r]
        for p in range(r):
            s -= L[r, p] * L[r, p]
        if not s > 1e-14 * scale:
            return False
        d = math.sqrt(s)
        L[r, r] = d
        for c in range(r + 1, k):
            s2 = L[c, r]
            for p in range(r):
                s2 -= L[c, p] * L[r, p]
            L[c, r] = s2 / d
    return True


@njit(cache=True)
def _chol_solve(L, b):
    m = b.shape[0]
    for r in range(m):
        s = b[r]
        for p in range(r):
            s -= L[r, p] * b[p]
        b[r] = s / L[r, r]
    for r in range(m - 1, -1, -1):
        s = b[r]
        for p in range(r + 1, m):
            s -= L[p, r] * b[p]
        b[r] = s / L[r, r]


@njit(cache=True)
def _lu(A, piv):
    """In-place LU with partial pivoting of A (k, k) (rows swapped whole, as LAPACK's
    getrf); False at a zero pivot."""
    k = A.shape[0]
    for c in range(k):
        p = c
        big = abs(A[c, c])
        for r in range(c + 1, k):
            if abs(A[r, c]) > big:
                big = abs(A[r, c])
                p = r
        piv[c] = p
        if big == 0.0:
            return False
        if p != c:
            for j in range(k):
                A[c, j], A[p, j] = A[p, j], A[c, j]
        d = A[c, c]
        for r in range(c + 1, k):
            lr = A[r, c] / d
            A[r, c] = lr
            if lr != 0.0:
                for j in range(c + 1, k):
                    A[r, j] -= lr * A[c, j]
    return True


@njit(cache=True)
def _lu_solve(A, piv, b):
    """b <- A^-1 b (k,) in place from :func:`_lu`."""
    k = A.shape[0]
    for c in range(k):
        p = piv[c]
        if p != c:
            b[c], b[p] = b[p], b[c]
    for r in range(k):
        s = b[r]
        for j in range(r):
            s -= A[r, j] * b[j]
        b[r] = s
    for r in range(k - 1, -1, -1):
        s = b[r]
        for j in range(r + 1, k):
            s -= A[r, j] * b[j]
        b[r] = s / A[r, r]


@njit(cache=True)
def pqr(J, rank_tol, W, th, piv, pn, on, sup):
    """Pivoted Householder QR of J^T for J (m, n); returns the rank r (see module doc).

    Work: pn, on (m,) partial squared row norms and their value at the last exact sum,
    sup (n,) int."""
    m, n = J.shape
    for j in range(m):
        s = 0.0
        for a in range(n):
            x = J[j, a]
            W[j, a] = x
            s += x * x
        pn[j] = s
        on[j] = s
        piv[j] = j
    d0 = 0.0
    for k in range(min(m, n)):
        p = k
        for j in range(k + 1, m):
            if pn[j] > pn[p]:
                p = j
        if p != k:
            for a in range(n):
                W[k, a], W[p, a] = W[p, a], W[k, a]
            pn[k], pn[p] = pn[p], pn[k]
            on[k], on[p] = on[p], on[k]
            piv[k], piv[p] = piv[p], piv[k]
        sig = 0.0  # exact norm of the pivot row's remaining part
        for a in range(k + 1, n):
            sig += W[k, a] * W[k, a]
        alpha = W[k, k]
        nrm = math.sqrt(alpha * alpha + sig)
        if k == 0:
            d0 = max(nrm, 1e-300)
        if not nrm > rank_tol * d0:
            return k
        beta = -nrm if alpha >= 0.0 else nrm
        v0 = alpha - beta
        th[k] = (beta - alpha) / beta
        for a in range(k + 1, n):
            W[k, a] /= v0
        W[k, k] = beta
        tk = th[k]
        nz = 0  # the support of the Householder vector (Phi_q is sparse: rows stay short)
        for a in range(k + 1, n):
            if W[k, a] != 0.0:
                sup[nz] = a
                nz += 1
        for j in range(k + 1, m):  # H_k on the remaining rows (columns of J^T)
            s = W[j, k]
            for i in range(nz):
                s += W[k, sup[i]] * W[j, sup[i]]
            if s != 0.0:
                s *= tk
                W[j, k] -= s
                for i in range(nz):
                    W[j, sup[i]] -= s * W[k, sup[i]]
            x = pn[j] - W[j, k] * W[j, k]  # W[j, k] leaves the remaining part
            if x == pn[j]:
                continue
            if x <= 1e-6 * on[j]:  # cancellation: sum again
                x = 0.0
                for a in range(k + 1, n):
                    x += W[j, a] * W[j, a]
                on[j] = x
            pn[j] = x
    return min(m, n)


@njit(cache=True)
def _apply_q(W, th, r, x):
    """x <- Q x = H_0 ... H_{r-1} x (in place), x (n,)."""
    n = x.shape[0]
    for k in range(r - 1, -1, -1):
        s = x[k]
        for a in range(k + 1, n):
            s += W[k, a] * x[a]
        s *= th[k]
        x[k] -= s
        for a in range(k + 1, n):
            x[a] -= s * W[k, a]


@njit(cache=True)
def min_norm(W, th, piv, r, b, x):
    """x (n,) = Q1 R11^-T b[P[:r]]: the min-norm solution of the independent rows
    ``Phi_q[P[:r]] x = b[P[:r]]`` (a projection correction, or v1 of Eq. (6))."""
    x[:] = 0.0
    for j in range(r):  # R11^T is lower triangular; its row j is W[j, :j+1]
        s = b[piv[j]]
        for k in range(j):
            s -= W[j, k] * x[k]
        x[j] = s / W[j, j]
    _apply_q(W, th, r, x)


@njit(cache=True)
def acc_nullspace(wg, r, M, F, c, qdd):
    """qdd (n,) of Eq. (6) from the factorization of rank r in ``wg`` (:func:`workspace`:
    W, th, piv), forces F (n,), c (m,); False when Z M Z^T is not positive definite (ker M
    and ker Phi_q meet: Eq. (37) fails). Work: wg's Z, MZ, K (n, n) and two (n,)."""
    W, th, piv, Z, MZ, Kf, w, y = wg[4], wg[5], wg[6], wg[10], wg[11], wg[12], wg[13], wg[14]
    n = qdd.shape[0]
    f = n - r
    min_norm(W, th, piv, r, c, qdd)
    if f == 0:
        return True
    for j in range(f):  # rows of Z: Q e_{r+j}
        for a in range(n):
            Z[j, a] = 0.0
        Z[j, r + j] = 1.0
        _apply_q(W, th, r, Z[j])
    for a in range(n):  # w = F - M v1
        s = F[a]
        for b in range(n):
            s -= M[a, b] * qdd[b]
        w[a] = s
    for j in range(f):  # MZ[j] = M Z[j] (M symmetric)
        for a in range(n):
            s = 0.0
            for b in range(n):
                s += M[a, b] * Z[j, b]
            MZ[j, a] = s
    for i in range(f):
        for j in range(i + 1):
            s = 0.0
            for a in range(n):
                s += Z[i, a] * MZ[j, a]
            Kf[i, j] = s
    if not _cholesky(Kf, f):  # K = Z M Z^T
        return False
    for i in range(f):  # y2 = K^-1 Z w
        s = 0.0
        for a in range(n):
            s += Z[i, a] * w[a]
        y[i] = s
    _chol_solve(Kf, y[:f])
    for i in range(f):
        for a in range(n):
            qdd[a] += Z[i, a] * y[i]
    return True


@njit(cache=True)
def workspace(n, m):
    """Work arrays ``wg`` of the general path: 0 J (m, n), 1 w (m,), 2 c (m,), 3 F (n,),
    4 W (m, n), 5 th (m,), 6 piv (m,) int, 7 pn, 8 on (m,), 9 sup (n,) int, 10-12 Z, MZ, K
    (n, n), 13-14 (n,), 15 (1,) int: the rank of a QR left valid for the current q by a
    velocity projection, else -1."""
    return (np.zeros((m, n)), np.zeros(m), np.zeros(m), np.zeros(n), np.zeros((m, n)),
            np.zeros(m), np.zeros(m, np.int64), np.zeros(m), np.zeros(m),
            np.zeros(n, np.int64), np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n)),
            np.zeros(n), np.zeros(n), np.full(1, -1, np.int64))


@njit(cache=True)
def acc_general(gen, frc, q, qd, qdd, wg, cnt):
    """qdd (n,) of Eq. (6) in the null-space form (as ``Index1`` qr mode) for ``gen`` =
    (k, i, j, v, M, rank_tol) (:class:`General`), reusing the QR a velocity projection left
    for this q; OK or ERR_MASS (Eq. (37) fails)."""
    kk, ii, jj, vv, M, rank_tol = gen
    J, c, F = wg[0], wg[2], wg[3]
    cnt[C_RHS] += 1
    _gamma(kk, ii, jj, vv, qd, c)
    forces(frc, q, qd, F)
    r = wg[15][0]
    wg[15][0] = -1
    if r < 0:
        cnt[C_FACT] += 1
        _jac(kk, ii, jj, vv, q, J)
        r = pqr(J, rank_tol, wg[4], wg[5], wg[6], wg[7], wg[8], wg[9])
    if acc_nullspace(wg, r, M, F, c, qdd):
        return OK
    return ERR_MASS


@njit(cache=True)
def _min_norm_step(wg, r, b, x):
    """x -= Q1 R11^-T b[P[:r]] (the min-norm correction of ``Index1._corrector``)."""
    dx = wg[14]
    min_norm(wg[4], wg[5], wg[6], r, b, dx)
    for a in range(x.shape[0]):
        x[a] -= dx[a]


@njit(cache=True)
def project_general(kk, ii, jj, vv, rank_tol, q, qd, tol, wg, cnt):
    """Simplified-Newton projection of q on Phi = 0 (one QR), then of qd on Phi_q qd = 0,
    with min-norm corrections (``Index1.project`` in qr mode); a status code. Leaves the QR
    of Phi_q at the final q for the next :func:`acc_general` when it made one there."""
    J, w = wg[0], wg[1]
    m = J.shape[0]
    wg[15][0] = -1
    tol = reachable(tol, q, 2)
    drift(kk, ii, jj, vv, q, qd, w, J, cnt)
    rk = -1
    for it in range(11):
        e = 0.0
        for r in range(m):
            e = max(e, abs(w[r]))
        if e < tol:
            break
        if it == 10:
            return ERR_NEWTON
        if rk < 0:
            cnt[C_FACT] += 1
            rk = pqr(J, rank_tol, wg[4], wg[5], wg[6], wg[7], wg[8], wg[9])
        _min_norm_step(wg, rk, w, q)
        cnt[C_NEWTON] += 1
        _phi(kk, ii, jj, vv, m, q, w)
    if rk >= 0:
        _jac(kk, ii, jj, vv, q, J)
    if jv(J, qd, w) > tol:
        cnt[C_FACT] += 1
        rk = pqr(J, rank_tol, wg[4], wg[5], wg[6], wg[7], wg[8], wg[9])
        _min_norm_step(wg, rk, w, qd)
        wg[15][0] = rk
    cnt[C_PROJ] += 1
    return OK


@njit(cache=True)
def _evaluate(gen, frc, q, qd, qdd, ptol, wg):
    cnt = np.zeros(N_COUNTERS)
    if ptol > 0.0:
        kk, ii, jj, vv, _, rank_tol = gen
        st = project_general(kk, ii, jj, vv, rank_tol, q, qd, ptol, wg, cnt)
        if st != OK:
            return st
    return acc_general(gen, frc, q, qd, qdd, wg, cnt)


def evaluate(con, frc, M, q, qd, *, rank_tol: float = 1e-9, ptol: float = 0.0):
    """One state through the general path (for checks): (q, qd, qdd) (n,) each, with q, qd
    projected first when ``ptol`` > 0; ``con`` the constraint triplets, M (n, n), frc of
    :func:`pack_forces`. Returns None when a status is not OK."""
    q, qd, qdd = np.array(q, float), np.array(qd, float), np.zeros(len(q))
    st = _evaluate(general(con, M, rank_tol), frc, q, qd, qdd, float(ptol),
                   workspace(len(q), int(con.m)))
    return (q, qd, qdd) if st == OK else None


# ---- applied forces ---------------------------------------------------------------------
def jacobian(con, q: np.ndarray, J: np.ndarray) -> None:
    """J (m, n) = Phi_q at q (n,), in place, from the constraint triplets ``con``."""
    k, i, j, v = pack_constraints(con)[:4]
    _jac(k, i, j, v, np.asarray(q, float), J)


def as_f64(x, ndim: int) -> np.ndarray:
    """x as a C-contiguous float64 array; None as an empty array of ``ndim`` dims."""
    return np.ascontiguousarray(np.zeros((0,) * ndim) if x is None else x, float)


class General(NamedTuple):
    """What the general path (pivoted-QR null space) evaluates: the constraint triplets over
    qh = [q, 1] (k, i, j int64, v float), M (n, n) kg and the relative rank tolerance of
    Phi_q (on |R_kk| / |R_00|)."""

    k: np.ndarray
    i: np.ndarray
    j: np.ndarray
    v: np.ndarray
    M: np.ndarray
    rank_tol: float


def general(con, M, rank_tol: float) -> General:
    """The :class:`General` tuple of constraints ``con``, M (n, n; None: empty) and
    ``rank_tol``."""
    k, i, j, v, _ = pack_constraints(con)
    return General(k, i, j, v, as_f64(M, 2), float(rank_tol))


def pack_constraints(con) -> tuple:
    """The triplets of ``con`` (:class:`~natcoord.model.constraints.QuadraticConstraints`) as the
    compiled loops take them: (k, i, j (int64), v (float), m)."""
    return (np.ascontiguousarray(con.k, np.int64), np.ascontiguousarray(con.i, np.int64),
            np.ascontiguousarray(con.j, np.int64), np.ascontiguousarray(con.v, float),
            int(con.m))


def pack_forces(Q0, T=None, G=None, toff=None, tau=None, S=None, spr=None) -> tuple:
    """The ``frc`` tuple of :func:`natcoord.compiled.general.forces` with the dtypes and
    layouts the compiled loop expects: Q0 (n,) N; T (n, n) or None; torques G (nG, d, n+1),
    toff (nt+1,), tau (nt, 3) N m; springs S (ns, d, n+1), spr (ns, 3) = (k, c, l0)."""
    Q0 = as_f64(Q0, 1)
    n = len(Q0)
    d = 3 if G is None and S is None else (G if G is not None else S).shape[1]
    G = np.zeros((0, d, n + 1)) if G is None else G
    S = np.zeros((0, d, n + 1)) if S is None else S
    toff = np.zeros(1, np.int64) if toff is None else toff
    return (Q0, as_f64(T, 2), as_f64(G, 3), np.ascontiguousarray(toff, np.int64),
            as_f64(np.zeros((0, 3)) if tau is None else tau, 2), as_f64(S, 3),
            as_f64(np.zeros((0, 3)) if spr is None else spr, 2))


@njit(cache=True)
def _map(C, q, affine, out):
    """out (d,) = C[:, :n] q (+ C[:, n] when affine) for a map C (d, n+1)."""
    n = q.shape[0]
    for a in range(C.shape[0]):
        s = C[a, n] if affine else 0.0
        for b in range(n):
            s += C[a, b] * q[b]
        out[a] = s


@njit(cache=True, inline="always")
def forces(frc, q, qd, out):
    """Generalized applied forces (n,), N: Q0 + T q + torques + spring-dampers (see the
    module doc for the arrays of ``frc``), as ``Model.forces`` / ``NaturalModel.forces``."""
    Q0, T, G, toff, tau, S, spr = frc
    n = q.shape[0]
    for a in range(n):
        out[a] = Q0[a]
    if T.shape[0] > 0:
        for a in range(n):
            s = 0.0
            for b in range(n):
                s += T[a, b] * q[b]
            out[a] += s
    if toff.shape[0] > 1 or S.shape[0] > 0:
        _torques_springs(G, toff, tau, S, spr, q, qd, out)


@njit(cache=True, _nrt=True)
def _torques_springs(G, toff, tau, S, spr, q, qd, out):
    """Adds the torques' and spring-dampers' generalized forces to out (n,). (It allocates:
    ``_nrt=True`` stated, because a callee that leaves it unset inherits the first caller's
    setting, and the compiled loops' kernels run without reference counting.)"""
    n = q.shape[0]
    dim = G.shape[1]
    d = np.empty(3)
    g = np.empty(3)
    tw = np.empty(3)
    Sm = np.empty((3, 3))
    for t in range(toff.shape[0] - 1):
        # min-norm f_k with sum d_k x f_k = tau: f_k = B_k^T g, (sum B_k B_k^T) g = tau
        Sm[:, :] = 0.0
        for k in range(toff[t], toff[t + 1]):
            _map(G[k], q, True, d)
            if dim == 2:
                Sm[0, 0] += d[0] * d[0] + d[1] * d[1]
            else:
                dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                for a in range(3):
                    for b in range(3):
                        Sm[a, b] += (dd if a == b else 0.0) - d[a] * d[b]
        if dim == 2:
            g[0] = tau[t, 0] / Sm[0, 0]
        elif tau.shape[1] > 3:  # body-fixed columns: tau + c_K d_0 x d_1 + sum_k c_k d_k
            _body_torque(G, toff[t], toff[t + 1], tau[t], q, tw)
            _torque_solve(Sm, tw, g)
        else:
            _torque_solve(Sm, tau[t], g)
        for k in range(toff[t], toff[t + 1]):
            _map(G[k], q, True, d)
            if dim == 2:  # B_k = [-d_y, d_x]
                f0 = -d[1] * g[0]
                f1 = d[0] * g[0]
                for b in range(n):
                    out[b] += G[k, 0, b] * f0 + G[k, 1, b] * f1
            else:  # B_k = [d_k]x, f_k = g x d_k
                f0 = g[1] * d[2] - g[2] * d[1]
                f1 = g[2] * d[0] - g[0] * d[2]
                f2 = g[0] * d[1] - g[1] * d[0]
                for b in range(n):
                    out[b] += G[k, 0, b] * f0 + G[k, 1, b] * f1 + G[k, 2, b] * f2
    ln_d = np.empty(dim)
    v = np.empty(dim)
    for s_ in range(S.shape[0]):
        _map(S[s_], q, True, ln_d)
        _map(S[s_], qd, False, v)
        ln = 0.0
        for a in range(dim):
            ln += ln_d[a] * ln_d[a]
        ln = math.sqrt(ln)
        ev = 0.0
        for a in range(dim):
            ev += ln_d[a] / ln * v[a]
        ten = spr[s_, 0] * (ln - spr[s_, 2]) + spr[s_, 1] * ev
        for a in range(dim):
            fa = -ten * ln_d[a] / ln
            for b in range(n):
                out[b] += S[s_, a, b] * fa


@njit(cache=True)
def _body_torque(G, k0, k1, row, q, out):
    """World torque (3,) of a torque row (``tau`` columns, see the module doc) at q: its
    constant part row[:3] plus the body-fixed part ``row[3] d_0 x d_1 + sum_k row[4 + k]
    d_k`` (d_k = G[k0 + k] qh, the frame R(q) = D(q) D0^+ of the outputs)."""
    d0 = np.empty(3)
    d1 = np.empty(3)
    for a in range(3):
        out[a] = row[a]
    for k in range(k0, k1):
        _map(G[k], q, True, d1)
        c = row[4 + k - k0]
        for a in range(3):
            out[a] += c * d1[a]
    if row[3] != 0.0:
        _map(G[k0], q, True, d0)
        _map(G[k0 + 1], q, True, d1)
        out[0] += row[3] * (d0[1] * d1[2] - d0[2] * d1[1])
        out[1] += row[3] * (d0[2] * d1[0] - d0[0] * d1[2])
        out[2] += row[3] * (d0[0] * d1[1] - d0[1] * d1[0])


@njit(cache=True)
def _torque_solve(Sm, tau, g):
    """g (3,) = Sm^+ tau for Sm = sum (|d_k|^2 I - d_k d_k^T) (3, 3): a solve when the d_k
    span more than a line, else (collinear d_k, e.g. a rod: Sm = s (I - u u^T), s = tr/2,
    so Sm^+ = Sm / s^2) the torque about the line drops out, as in numpy's lstsq."""
    c00 = Sm[1, 1] * Sm[2, 2] - Sm[1, 2] * Sm[2, 1]
    c01 = Sm[1, 2] * Sm[2, 0] - Sm[1, 0] * Sm[2, 2]
    c02 = Sm[1, 0] * Sm[2, 1] - Sm[1, 1] * Sm[2, 0]
    det = Sm[0, 0] * c00 + Sm[0, 1] * c01 + Sm[0, 2] * c02
    tr = Sm[0, 0] + Sm[1, 1] + Sm[2, 2]
    if det > 1e-10 * tr * tr * tr:
        c11 = Sm[0, 0] * Sm[2, 2] - Sm[0, 2] * Sm[2, 0]
        c12 = Sm[0, 1] * Sm[2, 0] - Sm[0, 0] * Sm[2, 1]
        c22 = Sm[0, 0] * Sm[1, 1] - Sm[0, 1] * Sm[1, 0]
        g[0] = (c00 * tau[0] + c01 * tau[1] + c02 * tau[2]) / det
        g[1] = (c01 * tau[0] + c11 * tau[1] + c12 * tau[2]) / det
        g[2] = (c02 * tau[0] + c12 * tau[1] + c22 * tau[2]) / det
        return
    s2 = 0.25 * tr * tr if tr > 0.0 else 1.0
    for a in range(3):
        g[a] = (Sm[a, 0] * tau[0] + Sm[a, 1] * tau[1] + Sm[a, 2] * tau[2]) / s2
