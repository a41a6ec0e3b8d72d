"""Compiled (numba) time loop of the index-1 formulation with projection.

One call integrates the whole run: an embedded explicit Runge-Kutta pair (Dormand-Prince
8(5,3) ``dop853`` or 5(4) ``dopri5``) with adaptive steps that cross the output samples,
position/velocity projection after every accepted step, and samples from dop853's
continuous extension (order 7) or, for dopri5, quintic Hermite interpolation of q from
(q, qd, qdd) at both step ends, projected onto Phi = 0, Phi_q qd = 0, with qdd from the
equations of motion there.

Kernels take plain arrays only: the constraint triplets ``k, i, j, v`` over qh = [q, 1]
(:class:`~natcoord.model.constraints.QuadraticConstraints`), scleronomic only, and the applied
forces packed by :func:`pack_forces` (``Q0 + T q``, torques, spring-dampers). Two linear
algebra paths share the loop, compiled apart (the general work arrays ``wg`` or None):
the Schur path for a regular M, constraints of full row rank and forces Q0 + T q, with the
constant ``Minv`` (n, n) and ``W = Phi_q M^-1 Phi_q^T`` (Cholesky once per evaluation,
M-orthogonal projections); the general path (singular M, redundant rows, torques, springs)
with the rank-revealing QR of :mod:`natcoord.compiled.general` (null-space form of Eq. (6),
min-norm projections), as ``Index1`` in its ``qr`` mode. Units: SI (m, s, kg, N).

numba compiles once per machine (``cache=True``; about 30 s cold, both paths, 0.3 s to load
the cache); :func:`natcoord.compiled.cache.ensure_compiled` does it and returns the time it
took, so callers keep it out of the stepping time.
"""

from __future__ import annotations

import functools
import hashlib
import math
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

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

from ..model.kinematics import singular_hint
from . import general as kernels_general
from . import sparse as kernels_sparse
from . import sparsity, stepcontrol
from .general import (  # noqa: F401 - counters, codes, pack_forces re-exported
    C_FACT,
    C_NEWTON,
    C_PHI,
    C_PHID,
    C_PROJ,
    C_REJ,
    C_REPART,
    C_RHS,
    C_STEPS,
    ERR_MASS,
    ERR_MAXSTEPS,
    ERR_NEWTON,
    ERR_NONFINITE,
    ERR_SINGULAR,
    ERR_UNDERFLOW,
    N_COUNTERS,
    OK,
    _gamma,
    _jac,
    _phi,
    acc_general,
    as_f64,
    drift,
    forces,
    jv,
    pack_constraints,
    pack_forces,
    project_general,
    workspace,
)

STATUS_TEXT = {ERR_UNDERFLOW: "step size underflow",
               ERR_SINGULAR: "Phi_q M^-1 Phi_q^T is singular (constraints lost rank)",
               ERR_MASS: "M is singular on ker Phi_q (ker M and ker Phi_q meet, Eq. (37))",
               ERR_NEWTON: "position projection did not converge",
               ERR_MAXSTEPS: "too many steps",
               ERR_NONFINITE: "non-finite state"}


# ---- tableaux ---------------------------------------------------------------------------
def _tableau_dop853():
    from .stepcontrol import DOP853_A as A
    from .stepcontrol import DOP853_C as C
    s = 13  # 12 stages + the stage at (t + h, y_new)
    return (A[:s, :s].copy(), stepcontrol.DOP853_B, C[:s].copy(), stepcontrol.DOP853_E5,
            stepcontrol.DOP853_E3, stepcontrol.EXPONENT["dop853"], A[s:, :].copy(),
            C[s:].copy(), stepcontrol.DOP853_D, True)


def _tableau_dopri5():
    B = stepcontrol.DOPRI5_B
    return (stepcontrol.DOPRI5_A, B, stepcontrol.DOPRI5_C, stepcontrol.DOPRI5_E,
            np.zeros(len(B)), stepcontrol.EXPONENT["dopri5"],
            np.zeros((0, 16)), np.zeros(0), np.zeros((0, 16)), True)


def _tableau_rk4():
    return (stepcontrol.RK4_A, stepcontrol.RK4_B, stepcontrol.RK4_C, np.zeros(4), np.zeros(4),
            0.0, np.zeros((0, 16)), np.zeros(0), np.zeros((0, 16)), False)


TABLEAUX_OF = {"dop853": _tableau_dop853, "dopri5": _tableau_dopri5, "rk4": _tableau_rk4}


@functools.cache
def tableau(name: str) -> tuple:
    """The compiled loop's tableau of ``name`` (:mod:`natcoord.compiled.stepcontrol`'s arrays)."""
    return TABLEAUX_OF[name]()


FIXED_STEP = ("rk4", "dopri5")  # methods the compiled loop runs with a fixed step
ADAPTIVE = ("dop853", "dopri5")  # and with error-controlled steps


# ---- the general path's evaluations ----------------------------------------------------
# (the loop calls the sparse path's kernels directly: a wrapper choosing between the two
# cost 50 ns a call, a quarter of a projection on a small model)
@njit(cache=True)
def _accel_general(gen, y, qdd, wg, cnt):
    """qdd (n,) at the state y = [q, qd] on the general path, ``gen`` = ((k, i, j, v, M,
    rank_tol), frc); a status code."""
    n = qdd.shape[0]
    return acc_general(gen[0], gen[1], y[:n], y[n:], qdd, wg, cnt)


@njit(cache=True)
def _settle_general(gen, q, qd, qdd, ptol, wg, cnt):
    """Project (q, qd) in place and evaluate qdd there on the general path; a status code."""
    kk, ii, jj, vv, _, rank_tol = gen[0]
    st = project_general(kk, ii, jj, vv, rank_tol, q, qd, ptol, wg, cnt)
    if st != OK:
        return st
    return acc_general(gen[0], gen[1], q, qd, qdd, wg, cnt)


@njit(cache=True)
def _sample(y0, f0, y1, f1, n, h, s, q, qd):
    """Quintic Hermite of q (n,) on [0, h] at s in [0, 1] and its derivative qd, from
    y = [q, qd] (2n,) and f = [qd, qdd] at both ends (y0, f0 and y1, f1)."""
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
    for a in range(n):
        q0, v0, a0, q1, v1, a1 = y0[a], y0[n + a], f0[n + a], y1[a], y1[n + a], f1[n + a]
        q[a] = (h00 * q0 + h10 * h * v0 + h20 * hh * a0
                + h01 * q1 + h11 * h * v1 + h21 * hh * a1)
        qd[a] = ((d00 * q0 + d01 * q1) / h + d10 * v0 + d20 * h * a0
                 + d11 * v1 + d21 * h * a1)


@njit(cache=True, inline="always")
def _combine(y, h, C, row, s, K, out):
    """out = y + h sum_{p < s} C[row, p] K[p] (rows of K; zero weights skipped)."""
    N = y.shape[0]
    for a in range(N):
        out[a] = y[a]
    for p in range(s):
        w = h * C[row, p]
        if w != 0.0:
            for a in range(N):
                out[a] += w * K[p, a]


@njit(cache=True, inline="always")
def _weigh(E5, E3, dop853, K, s, x5, x3):
    """x5 (N,) = E5 K, x3 = E3 K over the first s stages (x3 zero unless ``dop853``): per
    component the sum in stage order, zero weights skipped; stages outer, so that each pass
    over the components vectorises."""
    N = x5.shape[0]
    for a in range(N):
        x5[a] = 0.0
        x3[a] = 0.0
    for p in range(s):
        if E5[p] != 0.0:
            for a in range(N):
                x5[a] += E5[p] * K[p, a]
        if dop853 and E3[p] != 0.0:
            for a in range(N):
                x3[a] += E3[p] * K[p, a]


@njit(cache=True, inline="always")
def _stages(sp, gen, wg, cnt, y, h, lo, hi, rk):
    """Stages lo..hi-1 of a step of h from y: K[st] = f(y + h sum_p A[st, p] K[p]), ``rk``
    = (A, K, ys, qdd) (ys, qdd: scratch); ``sp``, ``gen``, ``wg`` as in :func:`run_index1`;
    a status code. Written without slices (see acc_state)."""
    P, gk, frc, ws, _ = sp
    A, K, ys, qdd = rk
    n = qdd.shape[0]
    for st in range(lo, hi):
        _combine(y, h, A, st, st, K, ys)
        if wg is None:
            st_code = kernels_sparse.acc_state(P, gk, frc, ys, K, st, qdd, ws, cnt)
            if st_code != OK:
                return st_code
            continue
        st_code = _accel_general(gen, ys, qdd, wg, cnt)
        if st_code != OK:
            return st_code
        for a in range(n):
            K[st, a] = ys[n + a]
            K[st, n + a] = qdd[a]
    return OK


@njit(cache=True, inline="always")
def _row_dot(ptr, col, val, d, x, off):
    """sum_e val[e] x[off + col[e]] over row d of a CSR map (ptr, col, val)."""
    s = 0.0
    for e in range(ptr[d], ptr[d + 1]):
        s += val[e] * x[off + col[e]]
    return s


@njit(cache=True)
def _dep_norm(dep, x, y, yn, atol, rtol, affine):
    """The error norm's sum over the coordinates an elimination removed
    (:mod:`natcoord.compiled.elimination`), for their positions and velocities alike:
    sum ((T_d x [+ b_d]) / sc)^2 with sc = atol + rtol max(|T_d y + b_d|, |T_d yn + b_d|),
    T_d their rows of T and b_d of b (b on positions only; on x when ``affine``). ``dep``
    = (ptr, col, val, b, keep, drop): T_d by rows (columns over the kept coordinates), b_d,
    the coordinates kept and eliminated (:attr:`natcoord.compiled.elimination.Elimination.dep_map`);
    x, y, yn (2 n_r,)."""
    return _dep_norms(dep, x, x, y, yn, atol, rtol, affine, False)[0]


@njit(cache=True)
def _dep_norms(dep, x, x2, y, yn, atol, rtol, affine, two=True):
    """:func:`_dep_norm` of x and, when ``two``, of x2 (2 n_r,) in one pass (dop853's two
    error estimates share the scales; else the second sum is 0)."""
    ptr, col, val, b = dep[0], dep[1], dep[2], dep[3]
    n = y.shape[0] // 2
    s = 0.0
    s2 = 0.0
    for off in (0, n):
        for d in range(ptr.shape[0] - 1):
            if not affine and ptr[d] == ptr[d + 1]:
                continue  # a constant coordinate (a fixed point's): x's term is 0
            c = b[d] if off == 0 else 0.0
            xv = _row_dot(ptr, col, val, d, x, off) + (c if affine else 0.0)
            x2v = (_row_dot(ptr, col, val, d, x2, off) + (c if affine else 0.0)) if two else 0.0
            yv = _row_dot(ptr, col, val, d, y, off) + c
            ynv = _row_dot(ptr, col, val, d, yn, off) + c
            sc = atol + rtol * max(abs(yv), abs(ynv))
            s += (xv / sc) ** 2
            s2 += (x2v / sc) ** 2
    return s, s2


@njit(cache=True, _nrt=False)
def expand(dep, X, XD, XDD, Q, QD, QDD):
    """The samples X, XD, XDD (T, n_r) over the kept coordinates into Q, QD, QDD (T, n):
    the kept ones copied, the eliminated ones T_d x (+ b_d for positions); ``dep`` as in
    :func:`_dep_norm`. Column by column: the inner loops over the samples run without
    index arithmetic from the maps (row by row took three times as long, a tenth of a
    four_bar run)."""
    ptr, col, val, b, keep, drop = dep
    T = X.shape[0]
    for src, dst, affine in ((X, Q, True), (XD, QD, False), (XDD, QDD, False)):
        for a in range(keep.shape[0]):
            c = keep[a]
            for k in range(T):
                dst[k, c] = src[k, a]
        for d in range(drop.shape[0]):
            c = drop[d]
            bd = b[d] if affine else 0.0
            if ptr[d] == ptr[d + 1]:  # a constant coordinate
                for k in range(T):
                    dst[k, c] = bd
                continue
            e0 = ptr[d]  # T_d x in _row_dot's order, then + b_d
            v, ce = val[e0], col[e0]
            for k in range(T):
                dst[k, c] = v * src[k, ce]
            for e in range(e0 + 1, ptr[d + 1]):
                v, ce = val[e], col[e]
                for k in range(T):
                    dst[k, c] += v * src[k, ce]
            for k in range(T):
                dst[k, c] += bd


@njit(cache=True, inline="always")
def _put(Q, k, x, off, n):
    """Q[k, :n] = x[off:off + n] (element by element: a view costs reference counts)."""
    for a in range(n):
        Q[k, a] = x[off + a]


@njit(cache=True, _nrt=False)
def _settle_sparse(sp, q, qd, qdd, ptol, bound, cnt, factored):
    """Project (q, qd) (n,) in place and evaluate qdd there on the sparse path
    (:func:`kernels_sparse.settle`); a status code. Called straight from the loop and
    compiled without reference counting: unpacking ``sp`` with it, or inlining a wrapper
    that branches to the general path, took 5-10 % of a small model's run. The general
    path (:func:`_settle_general`: its forces allocate) is called from the loop itself: a
    callee first compiled from a function without reference counting inherits that."""
    return kernels_sparse.settle(sp, q, qd, qdd, ptol, bound, cnt, factored)


@njit(cache=True)
def run_index1(sp, gen, wg, tab, ctl, dep, times, q0, qd0, out):
    """Explicit Runge-Kutta over ``times`` (T,) from (q0, qd0) (n_model,) at times[0],
    projected on the constraints first: adaptive (embedded pair, steps cross the samples,
    dense output) or fixed steps (landing on every sample).

    ``wg`` None: the sparse Schur path ``sp`` = (P, gk, frc, ws, w): the work array ``ws``
    and its vector ``w`` (:mod:`natcoord.compiled.sparse`), by the generic kernels on the
    plan ``P`` = (I, F, O) or, P None, by the model's generated kernels ``gk`` (addresses,
    :mod:`natcoord.compiled.codegen`; ``NO_GK`` with a plan); else the general path on
    ``gen`` = (:class:`~natcoord.compiled.general.General`, frc) with ``wg`` its work arrays
    (:func:`kernels_general.workspace`), None off that path, and ``sp`` typed as the
    generated path's (P and frc None: numba types the sparse branch, never taken there,
    with the callees the generated path compiled); ``frc``: :func:`pack_forces`, None with
    generated kernels (they carry the forces). What a path does not use goes as None: a
    tuple's arrays cost time at every call, and numba compiles the None branches away
    (which is why ``wg`` is an argument of its own). ``tab`` =
    (A, B, E5, E3, expo, dop853, n_ext, D, fsal): the method's tableau, A (s + n_ext,
    s + n_ext) the step's s stages and the extension's n_ext (:func:`packed_tableau`);
    ``ctl`` = (rtol, atol, h0, ptol, max_steps, h_fixed, bound): step control (h0 <= 0:
    Hairer's initial step; h_fixed > 0: fixed steps of at most h_fixed, no error control),
    projection tolerance and the plan's Newton bound (:func:`kernels_sparse.newton_bound`;
    (0, 0) on the general path); ``dep``: the coordinates an elimination removed
    (:func:`_dep_norm`), which the error norm counts as the state's, and those it kept
    (q0, qd0 are read there); ``out`` = (X, XD, XDD (T, n_r): the samples over the
    coordinates kept, Q, QD, QDD (T, n_model): all of them (X is Q without an
    elimination), cnt (N_COUNTERS,) zeroed here, tfail (1,): the time the loop had reached
    when it stopped), filled in place. Returns a status code (0 = ok).

    Hot loops index elements and pass offsets: a slice or row view costs two atomic
    reference counts, which on a small model is a tenth of an evaluation.
    """
    A, B, E5, E3, expo, dop853, n_ext, D, fsal = tab
    rtol, atol, h0, ptol, max_steps, h_fixed, bound = ctl
    X, XD, XDD, Q, QD, QDD, cnt, tfail = out
    keep = dep[4]
    for i in range(cnt.shape[0]):
        cnt[i] = 0.0
    fixed = h_fixed > 0.0
    n = keep.shape[0]
    N = 2 * n
    Nn = N + 2 * (dep[0].shape[0] - 1)  # the components the error norm averages over
    s_st = B.shape[0]
    K = np.zeros((s_st + n_ext, N))  # the step's and the extension's stages
    Fd = np.zeros((D.shape[0] + 3, N))  # dop853 continuous extension (order 7)
    x5 = np.zeros(N)   # the error estimates' combinations of the stages
    x3 = np.zeros(N)
    y = np.zeros(N)
    yn = np.zeros(N)
    ys = np.zeros(N)
    f0 = np.zeros(N)   # f at the (projected) start of the step
    f1 = np.zeros(N)   # f at the (projected) end of the step
    qs = np.zeros(n)   # the step's end, projected in place
    qds = np.zeros(n)
    qdd = np.zeros(n)
    zq = np.zeros(n)   # a sample, projected in place
    zqd = np.zeros(n)
    B2 = B.reshape((1, s_st))
    rk = (A, K, ys, qdd)  # what the stages work on
    for a in range(n):
        qs[a] = q0[keep[a]]
        qds[a] = qd0[keep[a]]
    T_out = times.shape[0]
    t = times[0]
    tend = times[T_out - 1]
    fresh = fixed and not fixed  # False, typed bool: a literal False would make numba
    # compile the projection (and all it calls) a second time, for Literal[bool]
    if wg is None:
        st_code = _settle_sparse(sp, qs, qds, qdd, ptol, bound, cnt, fresh)
    else:
        st_code = _settle_general(gen, qs, qds, qdd, ptol, wg, cnt)
    if st_code != OK:
        return st_code
    for a in range(n):
        y[a] = qs[a]
        y[n + a] = qds[a]
        f0[a] = qds[a]
        f0[n + a] = qdd[a]
    _put(X, 0, y, 0, n)
    _put(XD, 0, y, n, n)
    _put(XDD, 0, f0, n, n)
    k_out = 1
    # initial step (Hairer)
    h = h0
    if h <= 0.0 and not fixed:
        d0 = 0.0
        d1 = 0.0
        for a in range(N):
            sc = atol + rtol * abs(y[a])
            d0 += (y[a] / sc) ** 2
            d1 += (f0[a] / sc) ** 2
        d0 = math.sqrt((d0 + _dep_norm(dep, y, y, y, atol, rtol, True)) / Nn)
        d1 = math.sqrt((d1 + _dep_norm(dep, f0, y, y, atol, rtol, False)) / Nn)
        h = stepcontrol.initial_step(d0, d1, tend - t)
    nsteps = 0
    while k_out < T_out:
        tfail[0] = t
        if nsteps >= max_steps:
            return ERR_MAXSTEPS
        if fixed:  # equal steps of at most h_fixed up to the next sample
            span = times[k_out] - t
            hh = span / max(1.0, math.ceil(span / h_fixed - 1e-9))
        else:
            hh = min(h, tend - t)
        # stages
        for a in range(N):
            K[0, a] = f0[a]
        st_code = _stages(sp, gen, wg, cnt, y, hh, 1, s_st, rk)
        if st_code != OK:
            return st_code
        if fsal:  # the last stage is at the new point
            for a in range(N):
                yn[a] = ys[a]
        else:
            _combine(y, hh, B2, 0, s_st, K, yn)
        # error norm: E5 K, E3 K per component (each sum in _combine's order) and its sums
        err = 0.0
        if not fixed:
            _weigh(E5, E3, dop853, K, s_st, x5, x3)
            e5 = 0.0
            e3 = 0.0
            for a in range(N):
                sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
                if dop853:
                    e5 += (x5[a] / sc) ** 2
                    e3 += (x3[a] / sc) ** 2
                else:
                    e5 += (hh * x5[a] / sc) ** 2
            if dop853:
                if Nn > N:
                    d5, d3 = _dep_norms(dep, x5, x3, y, yn, atol, rtol, False)
                    e5 += d5
                    e3 += d3
                err = stepcontrol.dop853_norm(e5, e3, Nn, hh)  # (E5 K, E3 K without h)
            else:
                if Nn > N:
                    e5 += hh * hh * _dep_norm(dep, x5, y, yn, atol, rtol, False)
                err = stepcontrol.rms_norm(e5, Nn)
        if not (err == err):
            return ERR_NONFINITE
        if err > 1.0:
            cnt[C_REJ] += 1
            h = hh * stepcontrol.reject_factor(err, expo)
            if stepcontrol.underflow(h, t):
                return ERR_UNDERFLOW
            continue
        # accept: project the end state, from the last stage's factorization (fsal: at
        # yn), then the dense output from the unprojected step (its stages factor
        # elsewhere: projected after them, the end moved with the output times)
        t1 = t + hh
        if fixed and abs(t1 - times[k_out]) <= 1e-9 * hh:
            t1 = times[k_out]
        if hh == tend - t:
            t1 = tend
        tol_t = stepcontrol.SAMPLE_TOL * max(1.0, abs(t1))
        for a in range(n):
            qs[a] = yn[a]
            qds[a] = yn[n + a]
        if wg is None:
            st_code = _settle_sparse(sp, qs, qds, qdd, ptol, bound, cnt, fsal)
        else:
            st_code = _settle_general(gen, qs, qds, qdd, ptol, wg, cnt)
        if st_code == ERR_NEWTON and not fixed:  # the step left the manifold too far to
            cnt[C_REJ] += 1                     # project back (near a singular position):
            h = stepcontrol.PROJECTION_FAILURE_FACTOR * hh  # and try a shorter one
            if stepcontrol.underflow(h, t):
                return ERR_UNDERFLOW
            continue
        if st_code != OK:
            return st_code
        for a in range(n):
            f1[a] = qds[a]
            f1[n + a] = qdd[a]  # (qdd: the stages' scratch on the generic path)
        if dop853 and k_out < T_out and times[k_out] < t1 - tol_t:  # samples inside
            st_code = _stages(sp, gen, wg, cnt, y, hh, s_st, s_st + n_ext, rk)
            if st_code != OK:
                return st_code
            stepcontrol.dense_dop853(y, yn, hh, K, s_st, D, Fd)
        for a in range(n):
            yn[a] = qs[a]
            yn[n + a] = qds[a]
        nsteps += 1
        cnt[C_STEPS] += 1
        # samples in (t, t1]
        while k_out < T_out and times[k_out] <= t1 + tol_t:
            tk = times[k_out]
            if abs(tk - t1) <= tol_t:
                _put(X, k_out, yn, 0, n)
                _put(XD, k_out, yn, n, n)
                _put(XDD, k_out, f1, n, n)
            else:
                x = (tk - t) / hh
                if dop853:
                    stepcontrol.dense_split(Fd, y, x, n, zq, zqd)
                else:
                    _sample(y, f0, yn, f1, n, hh, x, zq, zqd)
                # true Newton from the sample: the M-orthogonal projection (a
                # factorization from elsewhere lands it elsewhere on the manifold, which
                # near a singular position shows in the reactions)
                if wg is None:
                    st_code = _settle_sparse(sp, zq, zqd, qdd, ptol, bound, cnt, fresh)
                else:
                    st_code = _settle_general(gen, zq, zqd, qdd, ptol, wg, cnt)
                if st_code != OK:
                    return st_code
                _put(X, k_out, zq, 0, n)
                _put(XD, k_out, zqd, 0, n)
                _put(XDD, k_out, qdd, 0, n)
            k_out += 1
        t = t1
        for a in range(N):
            y[a] = yn[a]
            f0[a] = f1[a]
        if not fixed:
            h = hh * stepcontrol.accept_factor(err, expo)
    if dep[5].shape[0] > 0:
        expand(dep, X, XD, XDD, Q, QD, QDD)
    return OK


# ---- compile / load once ----------------------------------------------------------------
def drop_stale_cache(namespace: dict, module: str, deps: tuple) -> None:
    """numba compiles callees into the cached code of their callers but checks only the
    caller's file for changes: flush the cache of every compiled function of ``module``
    (its ``namespace``) when one of the modules ``deps`` changed since it was written."""
    try:
        disp = [v for v in namespace.values() if getattr(v, "_cache", None) is not None
                and getattr(v, "py_func", None) is not None and v.py_func.__module__ == module]
        sha = hashlib.sha1(b"".join(Path(d.__file__).read_bytes() for d in deps)).hexdigest()
        stamp = Path(disp[0]._cache.cache_path) / f"{module}.deps.sha1"
        if stamp.exists() and stamp.read_text() == sha:
            return
        for d in disp:
            d._cache.flush()
        stamp.write_text(sha)
    except (OSError, IndexError, AttributeError):  # caching only saves compile time
        pass


drop_stale_cache(vars(kernels_sparse), kernels_sparse.__name__, (kernels_general,))
drop_stale_cache(globals(), __name__, (kernels_general, kernels_sparse, stepcontrol))
PATHS = ("sparse", "generated", "general")  # index1's compiled paths


def warm_up_model() -> tuple:
    """(constraints, packed forces) of the warm-up runs: a particle on a unit circle under
    gravity, n = 2, m = 1, Phi = (x^2 + y^2 - 1) / 2."""
    con = SimpleNamespace(k=np.zeros(3, np.int64), i=np.arange(3), j=np.arange(3),
                          v=np.array([1.0, 1.0, -1.0]), m=1, n=2)
    return con, pack_forces(np.array([0.0, -9.81]), np.zeros((2, 2)))


def warm_up(path: str) -> None:
    """Compile (or load from numba's cache) index1's loop on ``path`` (:data:`PATHS`: the
    sparse Schur path with generic or generated kernels, the general QR null-space path)
    by tiny runs with every method."""
    from . import codegen
    con, frc = warm_up_model()
    times = np.linspace(0.0, 0.02, 3)
    plan = None if path == "general" else sparsity.schur_plan(con, np.eye(2))
    args = None if plan is None else plan.kernel_args
    kern = codegen.load(plan, frc) if path == "generated" else None
    for name, h in (("dop853", None), ("dopri5", None), ("rk4", 0.005)):
        Q, QD, _ = run(name, con, frc, times, np.array([1.0, 0.0]), np.zeros(2),
                       Steps(rtol=1e-6, atol=1e-8, h=h), Route(args, kern, np.eye(2)))
    if path == "sparse":
        sample_outputs(plan, frc, Q, QD, np.zeros((len(Q), 1)), SimpleNamespace(
            max_phi=0.0, max_phi_dot=0.0), args)


class Steps(NamedTuple):
    """Step control of a compiled index-1 run: ``rtol``/``atol`` of adaptive steps, or a
    fixed step ``h`` (s; None: adaptive), the projection tolerance ``ptol`` (on |Phi|, m),
    the first step ``h0`` (s; 0: Hairer's initial step) and a step budget."""

    rtol: float = 0.0
    atol: float = 0.0
    ptol: float = 1e-13
    h: float | None = None
    h0: float = 0.0
    max_steps: int = 10_000_000


class Route(NamedTuple):
    """Which linear algebra the loop runs: ``plan`` (the ``kernel_args`` of
    :func:`natcoord.compiled.sparsity.schur_plan`, for a regular M) selects the sparse Schur
    path, with ``kern`` its generated kernels (:func:`natcoord.compiled.codegen.load`; None:
    the generic ones); without a plan the general path runs on ``M`` (n, n) and
    ``rank_tol`` (relative, on |R_kk| / |R_00|). ``dep``: an elimination's coordinates
    (:attr:`natcoord.compiled.elimination.Elimination.dep_map`: the loop runs on the kept
    ones, its error norm and samples cover all), None for none."""

    plan: tuple | None = None
    kern: object | None = None
    M: np.ndarray | None = None
    rank_tol: float = 1e-9
    dep: tuple | None = None


@functools.cache
def packed_tableau(name: str) -> tuple:
    """:func:`tableau` of ``name`` as :func:`run_index1` takes it: (A, B, E5, E3, expo,
    dop853, n_ext, D, fsal), A holding the step's and the extension's stages."""
    A, B, _, E5, E3, expo, Aext, _, D, fsal = tableau(name)
    s_st, n_ext = B.shape[0], Aext.shape[0]
    Aall = np.zeros((s_st + n_ext, s_st + n_ext))
    Aall[:s_st, :s_st] = A
    Aall[s_st:, :] = Aext[:, :s_st + n_ext]
    return Aall, B, E5, E3, expo, name == "dop853", n_ext, D, fsal


def prepare(name: str, con, frc, times, steps: Steps, route: Route | None = None):
    """Everything of a compiled run but the start, packed once (a benchmark repeats the
    run): returns ``go(q0, qd0, out, cnt)`` that integrates with method ``name`` from (q0,
    qd0) (n_model,), float64, contiguous) into out = (Q, QD, QDD) (T, n_model) in place,
    adds to the counters ``cnt`` (None: none) and returns the run's counter array
    (N_COUNTERS,), reused by the next run; n_model is the loop's n, or all
    coordinates when ``route.dep`` is given. ``frc`` from :func:`pack_forces`. ``go``
    raises RuntimeError naming the method, the time and a singular position's hint."""
    rtol, atol, ptol, h, h0, max_steps = steps
    plan, kern, M, rank_tol, dep = route or Route()
    if (h is None and name not in ADAPTIVE) or (h is not None and name not in FIXED_STEP):
        raise ValueError(f"{name} (compiled): " + ("give a fixed step h" if h is None else
                                                   "adaptive only"))
    tab = packed_tableau(name)
    times = np.ascontiguousarray(times, float)
    Tn, n = len(times), int(con.n) if dep is None else len(dep[4])  # the loop's n
    if dep is None:  # no coordinate eliminated: the loop's coordinates are the model's
        dep = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
               np.arange(n, dtype=np.int64), np.zeros(0, np.int64))
    elim = len(dep[5]) > 0
    X = tuple(np.zeros((Tn, n)) for _ in range(3)) if elim else None  # the kept ones
    c, tfail = np.zeros(N_COUNTERS), np.zeros(1)
    gen = None if plan is not None else (kernels_general.general(con, M, rank_tol), frc)
    wg = workspace(n, int(con.m)) if plan is None else None  # None: the sparse path
    args = sparsity.empty_plan(n).kernel_args if plan is None else plan
    ws = kernels_sparse.workspace(args)
    w = kernels_sparse.work_vector(args, ws)
    ctl = (float(rtol), float(atol), float(h0), float(ptol), int(max_steps),
           0.0 if h is None else float(h),
           kernels_sparse.newton_bound(plan, n) if plan is not None else (0.0, 0.0))
    generated = kern is not None and plan is not None  # they serve the sparse path
    # the general path hands the sparse branch (typed, never run) the generated path's
    # types, so that numba compiles (or loads) one set of those callees for both
    sparse = plan is not None and not generated
    sp = (args if sparse else None, kern if generated else kernels_sparse.NO_GK,
          frc if sparse else None, ws, w)

    def go(q0, qd0, out, cnt=None):
        status = run_index1(sp, gen, wg, tab, ctl, dep, times, q0, qd0,
                            (*(X or out), *out, c, tfail))
        add_counters(c, cnt)
        if status != OK:
            k = int(np.searchsorted(times, tfail[0], side="right")) - 1  # last sample
            J = np.zeros((int(con.m), n))
            kernels_general.jacobian(con, (X or out)[0][max(k, 0)], J)
            raise RuntimeError(f"{name} (compiled): {STATUS_TEXT.get(status, status)} at "
                               f"t = {tfail[0]:.6g} s" + singular_hint(J, rank_tol))
        return c
    return go


def run(name: str, con, frc, times, q0, qd0, steps: Steps, route: Route | None = None,
        cnt=None):
    """Integrate with the compiled loop by method ``name`` from (q0, qd0) (n_model,):
    returns (Q, QD, QDD) (T, n_model), as :func:`prepare` once. ``cnt``: counters added
    to. Raises RuntimeError."""
    go = prepare(name, con, frc, times, steps, route)
    n = len(q0)
    out = np.zeros((len(times), n)), np.zeros((len(times), n)), np.zeros((len(times), n))
    go(np.ascontiguousarray(q0, float), np.ascontiguousarray(qd0, float), out, cnt)
    return out


_COUNTED = ((C_STEPS, "steps"), (C_REJ, "rejected"), (C_RHS, "rhs"),
            (C_FACT, "factorizations"), (C_PROJ, "projections"), (C_NEWTON, "newton"),
            (C_REPART, "repartitions"))


def add_counters(c: np.ndarray, cnt) -> None:
    """Add a compiled loop's counter array c (N_COUNTERS,) to ``cnt``
    (:class:`natcoord.dynamics.common.Counters`; None: nothing). Read as one list: indexing
    the array element by element took 2 us, a tenth of a short run's fixed cost."""
    if cnt is None:
        return
    v, d = c.tolist(), cnt.__dict__
    for slot, name in _COUNTED:
        d[name] += int(v[slot])
    d["max_phi_step"] = max(d["max_phi_step"], v[C_PHI])
    d["max_phi_dot_step"] = max(d["max_phi_dot_step"], v[C_PHID])


def check(status: int, name: str) -> None:
    """Raise RuntimeError naming the method ``name`` for a status other than OK."""
    if status != OK:
        raise RuntimeError(f"{name} (compiled): {STATUS_TEXT.get(status, status)}")


def sample_outputs(plan, frc, Q, QD, LAM, cnt, args=None) -> np.ndarray:
    """Multipliers LAM (T, m) (case row order) and the drift counters at every sample on
    the sparse path; returns a bool (T,) mask of the samples with a dependent row, where
    lambda is not unique (the caller takes the minimum-norm one there). ``args``: the
    plan's ``kernel_args`` when already packed."""
    args = plan.kernel_args if args is None else args
    lam, dr = np.zeros((len(Q), plan.m)), np.zeros((len(Q), 2))
    dep = kernels_sparse.sample_outputs(*args, frc, np.ascontiguousarray(Q),
                                        np.ascontiguousarray(QD), lam, dr,
                                        kernels_sparse.workspace(args), np.zeros(N_COUNTERS))
    LAM[:, plan.perm] = lam  # plan row r is case row perm[r]
    if len(Q):
        cnt.max_phi = max(cnt.max_phi, float(np.max(dr[:, 0])))
        cnt.max_phi_dot = max(cnt.max_phi_dot, float(np.max(dr[:, 1])))
    return dep.astype(bool)
