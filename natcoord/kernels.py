"""Compiled (numba) time loop of the index-1 formulation with projection.

One call integrates the whole run: an embedded explicit Runge-Kutta pair (Dormand-Prince
8(5,3) ``dop853`` or 5(4) ``dopri5``) with adaptive steps that cross the output samples,
position/velocity projection after every accepted step, and samples produced by quintic
Hermite interpolation of q from (q, qd, qdd) at both step ends (qd from its derivative),
projected onto Phi = 0, Phi_q qd = 0, with qdd from the equations of motion there.

Kernels take plain arrays only: the constraint triplets ``k, i, j, v`` over qh = [q, 1]
(:class:`~natcoord.constraints.QuadraticConstraints`), the constant inverse mass matrix
``Minv`` (n, n), the applied forces ``Q = Q0 + T q``. Scleronomic constraints of full row
rank and a regular M only (the Schur complement ``W = Phi_q M^-1 Phi_q^T`` is factored by
Cholesky once per evaluation); everything else runs in the Python loop.

numba compiles once per machine (``cache=True``, a few seconds); :func:`ensure_compiled`
does it (or loads the cache) and returns the time it took, so callers keep it out of the
stepping time.
"""

from __future__ import annotations

import math
import time

import numpy as np

try:
    import numba
    from numba import njit
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a dependency, but stay importable
    HAVE_NUMBA = False
    numba = None

    def njit(*args, **kwargs):
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

# counter slots of the ``cnt`` array
C_STEPS, C_REJ, C_RHS, C_FACT, C_PROJ, C_NEWTON, C_PHI, C_PHID = range(8)
N_COUNTERS = 8
# status codes
OK, ERR_UNDERFLOW, ERR_SINGULAR, ERR_NEWTON, ERR_MAXSTEPS, ERR_NONFINITE = range(6)
STATUS_TEXT = {ERR_UNDERFLOW: "step size underflow",
               ERR_SINGULAR: "Phi_q M^-1 Phi_q^T is singular (constraints lost rank)",
               ERR_NEWTON: "position projection did not converge",
               ERR_MAXSTEPS: "too many steps",
               ERR_NONFINITE: "non-finite state"}


# ---- tableaux ---------------------------------------------------------------------------
def _tableau_dop853():
    from scipy.integrate._ivp import dop853_coefficients as d
    s = 13  # 12 stages + the stage at (t + h, y_new)
    A = np.zeros((s, s))
    A[:12, :12] = d.A[:12, :12]
    A[12, :12] = d.B
    C = np.zeros(s)
    C[:12] = d.C[:12]
    C[12] = 1.0
    B = np.zeros(s)
    B[:12] = d.B
    Aext = np.zeros((3, 16))
    Aext[:, :] = d.A[13:16, :16]
    return (A, B, C, np.array(d.E5, float), np.array(d.E3, float), 7,  # order for the control
            Aext, np.array(d.C[13:16], float), np.array(d.D, float))


def _tableau_dopri5():
    from .integrators import DormandPrince5 as D
    A = np.array(D.A, float)
    B = np.array(D.B, float)
    return (A, B, np.array(D.C, float), np.array(D.E, float), np.zeros(len(B)), 4,
            np.zeros((0, 16)), np.zeros(0), np.zeros((0, 16)))


TABLEAUX = {"dop853": _tableau_dop853(), "dopri5": _tableau_dopri5()}


# ---- model pieces -----------------------------------------------------------------------
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


@njit(cache=True)
def _schur(J, Minv, MiJt, L):
    """MiJt = M^-1 J^T (n, m); L = Cholesky factor of W = J MiJt (m, m). False if singular."""
    m, n = J.shape
    for a in range(n):
        for r in range(m):
            s = 0.0
            for b in range(n):
                s += Minv[a, b] * J[r, b]
            MiJt[a, r] = s
    for r in range(m):
        for c in range(r + 1):
            s = 0.0
            for a in range(n):
                s += J[r, a] * MiJt[a, c]
            L[r, c] = s
    # in-place Cholesky (lower)
    scale = 0.0
    for r in range(m):
        scale = max(scale, abs(L[r, r]))
    for r in range(m):
        s = L[r, r]
        for p in range(r):
            s -= L[r, p] * L[r, p]
        if not s > 1e-14 * scale:
            return False
        d = math.sqrt(s)
        L[r, r] = d
        for c in range(r + 1, m):
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
def _acc(kk, ii, jj, vv, Minv, Q0, T, q, qd, qdd, J, MiJt, L, w_m, w_m2, w_n, cnt):
    """qdd of Eq. (6) by the Schur complement; False if W is singular."""
    n = q.shape[0]
    m = J.shape[0]
    cnt[C_RHS] += 1
    cnt[C_FACT] += 1
    _jac(kk, ii, jj, vv, q, J)
    _gamma(kk, ii, jj, vv, qd, w_m2)
    if not _schur(J, Minv, MiJt, L):
        return False
    for a in range(n):  # F = Q0 + T q
        s = Q0[a]
        for b in range(n):
            s += T[a, b] * q[b]
        w_n[a] = s
    for a in range(n):  # M^-1 F
        s = 0.0
        for b in range(n):
            s += Minv[a, b] * w_n[b]
        qdd[a] = s
    for r in range(m):  # J M^-1 F - c
        s = -w_m2[r]
        for a in range(n):
            s += J[r, a] * qdd[a]
        w_m[r] = s
    _chol_solve(L, w_m)
    for a in range(n):
        s = qdd[a]
        for r in range(m):
            s -= MiJt[a, r] * w_m[r]
        qdd[a] = s
    return True


@njit(cache=True)
def _sub_matvec(A, w, x):
    """x -= A @ w (the mass-weighted correction M^-1 Phi_q^T w of a projection)."""
    for a in range(A.shape[0]):
        s = 0.0
        for r in range(A.shape[1]):
            s += A[a, r] * w[r]
        x[a] -= s


@njit(cache=True)
def _project(kk, ii, jj, vv, Minv, q, qd, tol, J, MiJt, L, w_m, cnt):
    """Newton projection of q on Phi = 0 (simplified: one factorization), then qd on
    Phi_q qd = 0, both M-orthogonal. Returns a status code."""
    n = q.shape[0]
    m = J.shape[0]
    _phi(kk, ii, jj, vv, m, q, w_m)
    e = 0.0
    for r in range(m):
        e = max(e, abs(w_m[r]))
    if e > cnt[C_PHI]:
        cnt[C_PHI] = e
    _jac(kk, ii, jj, vv, q, J)
    ev = 0.0
    for r in range(m):
        s = 0.0
        for a in range(n):
            s += J[r, a] * qd[a]
        ev = max(ev, abs(s))
    if ev > cnt[C_PHID]:
        cnt[C_PHID] = ev
    factored = False
    for it in range(11):
        e = 0.0
        for r in range(m):
            e = max(e, abs(w_m[r]))
        if e < tol:
            break
        if it == 10:
            return ERR_NEWTON
        if not factored:
            if not _schur(J, Minv, MiJt, L):
                return ERR_SINGULAR
            cnt[C_FACT] += 1
            factored = True
        _chol_solve(L, w_m)
        _sub_matvec(MiJt, w_m, q)
        cnt[C_NEWTON] += 1
        _phi(kk, ii, jj, vv, m, q, w_m)
    if factored:
        _jac(kk, ii, jj, vv, q, J)
    e = 0.0
    for r in range(m):
        s = 0.0
        for a in range(n):
            s += J[r, a] * qd[a]
        w_m[r] = s
        e = max(e, abs(s))
    if e > tol:
        if not _schur(J, Minv, MiJt, L):
            return ERR_SINGULAR
        cnt[C_FACT] += 1
        _chol_solve(L, w_m)
        _sub_matvec(MiJt, w_m, qd)
    cnt[C_PROJ] += 1
    return OK


@njit(cache=True)
def _sample(q0, v0, a0, q1, v1, a1, h, s, q, qd):
    """Quintic Hermite of q on [0, h] at s in [0, 1] and its derivative."""
    s2 = s * s
    s3 = s2 * s
    s4 = s3 * s
    s5 = s4 * s
    h00 = 1 - 10 * s3 + 15 * s4 - 6 * s5
    h10 = s - 6 * s3 + 8 * s4 - 3 * s5
    h20 = 0.5 * (s2 - 3 * s3 + 3 * s4 - s5)
    h01 = 10 * s3 - 15 * s4 + 6 * s5
    h11 = -4 * s3 + 7 * s4 - 3 * s5
    h21 = 0.5 * (s3 - 2 * s4 + s5)
    d00 = -30 * s2 + 60 * s3 - 30 * s4
    d10 = 1 - 18 * s2 + 32 * s3 - 15 * s4
    d20 = 0.5 * (2 * s - 9 * s2 + 12 * s3 - 5 * s4)
    d01 = -d00
    d11 = -12 * s2 + 28 * s3 - 15 * s4
    d21 = 0.5 * (3 * s2 - 8 * s3 + 5 * s4)
    hh = h * h
    for a in range(q0.shape[0]):
        q[a] = (h00 * q0[a] + h10 * h * v0[a] + h20 * hh * a0[a]
                + h01 * q1[a] + h11 * h * v1[a] + h21 * hh * a1[a])
        qd[a] = ((d00 * q0[a] + d01 * q1[a]) / h + d10 * v0[a] + d20 * h * a0[a]
                 + d11 * v1[a] + d21 * h * a1[a])


@njit(cache=True)
def run_index1(kk, ii, jj, vv, m, Minv, Q0, T, times, q0, qd0, rtol, atol, h0, ptol,
               A, B, C, E5, E3, order, dop853, Aext, Cext, D, max_steps, Q, QD, QDD, cnt):
    """Adaptive embedded RK over ``times`` from a consistent (q0, qd0) at times[0].

    Fills Q, QD, QDD (T, n) and cnt (N_COUNTERS,); returns a status code (0 = ok), with
    the failing time in cnt[...] left to the caller via the filled samples.
    """
    n = q0.shape[0]
    N = 2 * n
    s_st = B.shape[0]
    J = np.zeros((m, n))
    MiJt = np.zeros((n, m))
    L = np.zeros((m, m))
    w_m = np.zeros(m)
    w_m2 = np.zeros(m)
    w_n = np.zeros(n)
    n_ext = Aext.shape[0]
    K = np.zeros((s_st + n_ext, N))
    Fd = np.zeros((D.shape[0] + 3, N))  # dop853 continuous extension (order 7)
    yu = np.zeros(N)
    y = np.zeros(N)
    yn = np.zeros(N)
    ys = np.zeros(N)
    f0 = np.zeros(N)   # f at the (projected) start of the step
    f1 = np.zeros(N)   # f at the (projected) end of the step
    qs = np.zeros(n)
    qds = np.zeros(n)
    qdd = np.zeros(n)
    y[:n] = q0
    y[n:] = qd0
    T_out = times.shape[0]
    t = times[0]
    tend = times[T_out - 1]
    if not _acc(kk, ii, jj, vv, Minv, Q0, T, y[:n], y[n:], qdd, J, MiJt, L, w_m, w_m2,
                w_n, cnt):
        return ERR_SINGULAR
    f0[:n] = y[n:]
    f0[n:] = qdd
    Q[0] = y[:n]
    QD[0] = y[n:]
    QDD[0] = qdd
    k_out = 1
    # initial step (Hairer)
    h = h0
    if h <= 0.0:
        d0 = 0.0
        d1 = 0.0
        for a in range(N):
            sc = atol + rtol * abs(y[a])
            d0 += (y[a] / sc) ** 2
            d1 += (f0[a] / sc) ** 2
        d0 = math.sqrt(d0 / N)
        d1 = math.sqrt(d1 / N)
        h = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
        h = min(h, tend - t)
    expo = -1.0 / (order + 1.0)
    nsteps = 0
    while k_out < T_out:
        if nsteps >= max_steps:
            return ERR_MAXSTEPS
        hh = min(h, tend - t)
        # stages
        K[0] = f0
        for st in range(1, s_st):
            for a in range(N):
                s = y[a]
                for p in range(st):
                    if A[st, p] != 0.0:
                        s += hh * A[st, p] * K[p, a]
                ys[a] = s
            if st == s_st - 1:
                yn[:] = ys
            K[st, :n] = ys[n:]
            if not _acc(kk, ii, jj, vv, Minv, Q0, T, ys[:n], ys[n:], qdd, J, MiJt, L, w_m,
                        w_m2, w_n, cnt):
                return ERR_SINGULAR
            K[st, n:] = qdd
        # error norm
        if dop853:
            e5 = 0.0
            e3 = 0.0
            for a in range(N):
                sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
                x5 = 0.0
                x3 = 0.0
                for p in range(s_st):
                    x5 += E5[p] * K[p, a]
                    x3 += E3[p] * K[p, a]
                e5 += (x5 / sc) ** 2
                e3 += (x3 / sc) ** 2
            if e5 == 0.0 and e3 == 0.0:
                err = 0.0
            else:
                err = hh * e5 / math.sqrt((e5 + 0.01 * e3) * N)
        else:
            e5 = 0.0
            for a in range(N):
                sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
                x5 = 0.0
                for p in range(s_st):
                    x5 += E5[p] * K[p, a]
                e5 += (hh * x5 / sc) ** 2
            err = math.sqrt(e5 / N)
        if not (err == err):
            return ERR_NONFINITE
        if err > 1.0:
            cnt[C_REJ] += 1
            h = hh * max(0.2, 0.9 * err ** expo)
            if h < 1e-14 * max(1.0, abs(t)):
                return ERR_UNDERFLOW
            continue
        # accept: dense output from the unprojected step, then project the end state
        t1 = t + hh
        if hh == tend - t:
            t1 = tend
        inner = k_out < T_out and times[k_out] < t1 - 1e-13 * max(1.0, abs(t1))
        if dop853 and inner:
            for e in range(n_ext):
                st = s_st + e
                for a in range(N):
                    s = y[a]
                    for p in range(st):
                        if Aext[e, p] != 0.0:
                            s += hh * Aext[e, p] * K[p, a]
                    ys[a] = s
                K[st, :n] = ys[n:]
                if not _acc(kk, ii, jj, vv, Minv, Q0, T, ys[:n], ys[n:], qdd, J, MiJt, L,
                            w_m, w_m2, w_n, cnt):
                    return ERR_SINGULAR
                K[st, n:] = qdd
            for a in range(N):
                dy = yn[a] - y[a]
                Fd[0, a] = dy
                Fd[1, a] = hh * K[0, a] - dy
                Fd[2, a] = 2.0 * dy - hh * (K[s_st - 1, a] + K[0, a])
                for r in range(D.shape[0]):
                    s = 0.0
                    for p in range(s_st + n_ext):
                        s += D[r, p] * K[p, a]
                    Fd[3 + r, a] = hh * s
        st_code = _project(kk, ii, jj, vv, Minv, yn[:n], yn[n:], ptol, J, MiJt, L, w_m, cnt)
        if st_code != OK:
            return st_code
        if not _acc(kk, ii, jj, vv, Minv, Q0, T, yn[:n], yn[n:], qdd, J, MiJt, L, w_m,
                    w_m2, w_n, cnt):
            return ERR_SINGULAR
        f1[:n] = yn[n:]
        f1[n:] = qdd
        nsteps += 1
        cnt[C_STEPS] += 1
        # samples in (t, t1]
        while k_out < T_out and times[k_out] <= t1 + 1e-13 * max(1.0, abs(t1)):
            tk = times[k_out]
            if abs(tk - t1) <= 1e-13 * max(1.0, abs(t1)):
                Q[k_out] = yn[:n]
                QD[k_out] = yn[n:]
                QDD[k_out] = f1[n:]
            else:
                x = (tk - t) / hh
                if dop853:
                    nF = Fd.shape[0]
                    for a in range(N):
                        v = 0.0
                        for i2 in range(nF):
                            v += Fd[nF - 1 - i2, a]
                            v *= x if i2 % 2 == 0 else 1.0 - x
                        yu[a] = y[a] + v
                    qs[:] = yu[:n]
                    qds[:] = yu[n:]
                else:
                    _sample(y[:n], y[n:], f0[n:], yn[:n], yn[n:], f1[n:], hh, x, qs, qds)
                st_code = _project(kk, ii, jj, vv, Minv, qs, qds, ptol, J, MiJt, L, w_m,
                                   cnt)
                if st_code != OK:
                    return st_code
                if not _acc(kk, ii, jj, vv, Minv, Q0, T, qs, qds, qdd, J, MiJt, L, w_m,
                            w_m2, w_n, cnt):
                    return ERR_SINGULAR
                Q[k_out] = qs
                QD[k_out] = qds
                QDD[k_out] = qdd
            k_out += 1
        t = t1
        y[:] = yn
        f0[:] = f1
        fac = 10.0 if err == 0.0 else min(10.0, 0.9 * err ** expo)
        h = hh * fac
    return OK


# ---- compile / load once ----------------------------------------------------------------
_READY = False
COMPILE_TIME_S = 0.0


def ensure_compiled() -> float:
    """Compile (or load from numba's cache) the kernels by one tiny run; returns the seconds
    this call took (0 when already done in this process)."""
    global _READY, COMPILE_TIME_S
    if _READY or not HAVE_NUMBA:
        return 0.0
    t0 = time.perf_counter()
    # a pendulum particle on a unit circle: n = 2, m = 1, Phi = (x^2 + y^2 - 1) / 2
    kk = np.zeros(3, np.int64)
    ii = np.array([0, 1, 2], np.int64)
    jj = np.array([0, 1, 2], np.int64)
    vv = np.array([1.0, 1.0, -1.0])
    Minv = np.eye(2)
    Q0 = np.array([0.0, -9.81])
    T = np.zeros((2, 2))
    times = np.linspace(0.0, 0.02, 3)
    for name in ("dop853", "dopri5"):
        A, B, C, E5, E3, order, Aext, Cext, D = TABLEAUX[name]
        Q, QD, QDD = np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 2))
        cnt = np.zeros(N_COUNTERS)
        run_index1(kk, ii, jj, vv, 1, Minv, Q0, T, times, np.array([1.0, 0.0]), np.zeros(2),
                   1e-6, 1e-8, 0.0, 1e-13, A, B, C, E5, E3, order, name == "dop853",
                   Aext, Cext, D, 1000000, Q, QD, QDD, cnt)
    _READY = True
    COMPILE_TIME_S = time.perf_counter() - t0
    return COMPILE_TIME_S


def run(name: str, con, Minv, Q0, T, times, q0, qd0, *, rtol, atol, ptol, cnt,
        h0: float = 0.0, max_steps: int = 10_000_000):
    """Integrate with the compiled loop; returns (Q, QD, QDD). Raises RuntimeError."""
    A, B, C, E5, E3, order, Aext, Cext, D = TABLEAUX[name]
    Tn, n = len(times), len(q0)
    Q, QD, QDD = np.zeros((Tn, n)), np.zeros((Tn, n)), np.zeros((Tn, n))
    c = np.zeros(N_COUNTERS)
    status = run_index1(np.ascontiguousarray(con.k, np.int64),
                        np.ascontiguousarray(con.i, np.int64),
                        np.ascontiguousarray(con.j, np.int64),
                        np.ascontiguousarray(con.v, float), int(con.m),
                        np.ascontiguousarray(Minv, float),
                        np.ascontiguousarray(Q0, float), np.ascontiguousarray(T, float),
                        np.ascontiguousarray(times, float), np.array(q0, float),
                        np.array(qd0, float), float(rtol), float(atol), float(h0),
                        float(ptol), A, B, C, E5, E3, order, name == "dop853", Aext, Cext, D,
                        max_steps,
                        Q, QD, QDD, c)
    cnt.steps += int(c[C_STEPS])
    cnt.rejected += int(c[C_REJ])
    cnt.rhs += int(c[C_RHS])
    cnt.factorizations += int(c[C_FACT])
    cnt.projections += int(c[C_PROJ])
    cnt.newton += int(c[C_NEWTON])
    cnt.max_phi_step = max(cnt.max_phi_step, float(c[C_PHI]))
    cnt.max_phi_dot_step = max(cnt.max_phi_dot_step, float(c[C_PHID]))
    if status != OK:
        raise RuntimeError(f"{name} (compiled): {STATUS_TEXT.get(status, status)}")
    return Q, QD, QDD
