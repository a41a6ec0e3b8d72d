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
def _accel_general(gen, frc, y, qdd, wg, cnt):
    """qdd (n,) at the state y = [q, qd] on the general path, ``gen`` = (k, i, j, v, M,
    rank_tol); a status code."""
    n = qdd.shape[0]
    return acc_general(gen, frc, y[:n], y[n:], qdd, wg, cnt)


@njit(cache=True)
def _settle_general(gen, frc, q, qd, qdd, ptol, wg, cnt):
    """Project (q, qd) in place and evaluate qdd there on the general path; a status code."""
    kk, ii, jj, vv, _, rank_tol = gen
    st = project_general(kk, ii, jj, vv, rank_tol, q, qd, ptol, wg, cnt)
    if st != OK:
        return st
    return acc_general(gen, frc, q, qd, qdd, wg, cnt)


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


@njit(cache=True)
def _stages(sp, gen, wg, cnt, y, h, lo, hi, rk):
    """Stages lo..hi-1 of a step of h from y: K[st] = f(y + h sum_p A[st, p] K[p]), ``rk``
    = (A, K, ys, qdd) (ys, qdd: scratch); ``sp``, ``gen``, ``wg`` as in :func:`run_index1`;
    a status code. Written without slices (see acc_state)."""
    P, gk, frc, ws, _ = sp
    A, K, ys, qdd = rk
    n = qdd.shape[0]
    for st in range(lo, hi):
        _combine(y, h, A, st, st, K, ys)
        st_code = (kernels_sparse.acc_state(P, gk, frc, ys, qdd, ws, cnt)
                   if wg is None else _accel_general(gen, frc, ys, qdd, wg, cnt))
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
    ptr, col, val, b = dep[0], dep[1], dep[2], dep[3]
    n = y.shape[0] // 2
    s = 0.0
    for off in (0, n):
        for d in range(ptr.shape[0] - 1):
            c = b[d] if off == 0 else 0.0
            xv = _row_dot(ptr, col, val, d, x, off) + (c if affine else 0.0)
            yv = _row_dot(ptr, col, val, d, y, off) + c
            ynv = _row_dot(ptr, col, val, d, yn, off) + c
            s += (xv / (atol + rtol * max(abs(yv), abs(ynv)))) ** 2
    return s


@njit(cache=True)
def expand(dep, X, XD, XDD, Q, QD, QDD):
    """The samples X, XD, XDD (T, n_r) over the kept coordinates into Q, QD, QDD (T, n):
    the kept ones copied, the eliminated ones T_d x (+ b_d for positions); ``dep`` as in
    :func:`_dep_norm`."""
    ptr, col, val, b, keep, drop = dep
    for src, dst, affine in ((X, Q, True), (XD, QD, False), (XDD, QDD, False)):
        for k in range(src.shape[0]):
            for a in range(keep.shape[0]):
                dst[k, keep[a]] = src[k, a]
            for d in range(drop.shape[0]):
                dst[k, drop[d]] = (_row_dot(ptr, col, val, d, src[k], 0)
                                   + (b[d] if affine else 0.0))


@njit(cache=True)
def run_index1(sp, gen, wg, tab, ctl, dep, times, q0, qd0, out):
    """Explicit Runge-Kutta over ``times`` (T,) from (q0, qd0) (n,) at times[0], projected
    on the constraints first: adaptive (embedded pair, steps cross the samples, dense
    output) or fixed steps (landing on every sample).

    ``wg`` None: the sparse Schur path ``sp`` = (P, gk, frc, ws, w): the work array ``ws``
    and its vector ``w`` (:mod:`natcoord.compiled.sparse`), by the generic kernels on the
    plan ``P`` = (I, F, O) or, P None, by the model's generated kernels ``gk`` (addresses,
    :mod:`natcoord.compiled.codegen`; ``NO_GK`` with a plan); else the general path on
    ``gen`` (:class:`~natcoord.compiled.general.General`) with ``wg`` its work arrays
    (:func:`kernels_general.workspace`), None off that path; ``frc``: :func:`pack_forces`,
    None with generated kernels (they carry the forces). What a path does not use goes as
    None: a tuple's arrays cost time at every call, and numba compiles the None branches
    away (which is why ``wg`` is an argument of its own). ``tab`` =
    (A, B, C, E5, E3, expo, dop853, Aext, Cext, D, fsal): the method's tableau
    (:func:`tableau`); ``ctl`` = (rtol, atol, h0, ptol, max_steps, h_fixed): step
    control (h0 <= 0: Hairer's initial step; h_fixed > 0: fixed steps of at most h_fixed,
    no error control) and projection tolerance; ``dep``: the coordinates an elimination
    removed (:func:`_dep_norm`), which the error norm counts as the state's; ``out`` =
    (Q, QD, QDD (T, n_r), cnt (N_COUNTERS,), tfail (1,)) filled in place (tfail: the time
    the loop had reached when it stopped). Returns a status code (0 = ok).
    """
    A, B, C, E5, E3, expo, dop853, Aext, Cext, D, fsal = tab
    rtol, atol, h0, ptol, max_steps, h_fixed = ctl
    Q, QD, QDD, cnt, tfail = out
    frc = sp[2]  # the forces (None with generated kernels)
    fixed = h_fixed > 0.0
    n = q0.shape[0]
    N = 2 * n
    Nn = N + 2 * (dep[0].shape[0] - 1)  # the components the error norm averages over
    s_st = B.shape[0]
    n_ext = Aext.shape[0]
    K = np.zeros((s_st + n_ext, N))
    Aall = np.zeros((s_st + n_ext, s_st + n_ext))  # the step's and the extension's stages
    Aall[:s_st, :s_st] = A
    Aall[s_st:, :] = Aext[:, :s_st + n_ext]
    B2, E52, E32 = B.reshape((1, s_st)), E5.reshape((1, s_st)), E3.reshape((1, s_st))
    Fd = np.zeros((D.shape[0] + 3, N))  # dop853 continuous extension (order 7)
    zero = np.zeros(N)
    x5 = np.zeros(N)   # the error estimates' combinations of the stages
    x3 = np.zeros(N)
    yu = np.zeros(N)
    y = np.zeros(N)
    yn = np.zeros(N)
    ys = np.zeros(N)
    f0 = np.zeros(N)   # f at the (projected) start of the step
    f1 = np.zeros(N)   # f at the (projected) end of the step
    qs = np.zeros(n)
    qds = np.zeros(n)
    qdd = np.zeros(n)
    rk = (Aall, K, ys, qdd)  # what the stages work on
    y[:n] = q0
    y[n:] = qd0
    T_out = times.shape[0]
    t = times[0]
    tend = times[T_out - 1]
    st_code = (kernels_sparse.settle(sp, y[:n], y[n:], qdd, ptol, cnt, False)
               if wg is None else _settle_general(gen, frc, y[:n], y[n:], qdd, ptol, wg, cnt))
    if st_code != OK:
        return st_code
    f0[:n] = y[n:]
    f0[n:] = qdd
    Q[0] = y[:n]
    QD[0] = y[n:]
    QDD[0] = qdd
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
        K[0] = f0
        st_code = _stages(sp, gen, wg, cnt, y, hh, 1, s_st, rk)
        if st_code != OK:
            return st_code
        if fsal:  # the last stage is at the new point
            yn[:] = ys
        else:
            _combine(y, hh, B2, 0, s_st, K, yn)
        # error norm
        err = 0.0
        if fixed:
            pass
        elif dop853:
            e5 = 0.0
            e3 = 0.0
            _combine(zero, 1.0, E52, 0, s_st, K, x5)
            _combine(zero, 1.0, E32, 0, s_st, K, x3)
            for a in range(N):
                sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
                e5 += (x5[a] / sc) ** 2
                e3 += (x3[a] / sc) ** 2
            if Nn > N:
                e5 += _dep_norm(dep, x5, y, yn, atol, rtol, False)
                e3 += _dep_norm(dep, x3, y, yn, atol, rtol, False)
            err = stepcontrol.dop853_norm(e5, e3, Nn, hh)  # (E5 K, E3 K without h)
        else:
            e5 = 0.0
            _combine(zero, 1.0, E52, 0, s_st, K, x5)
            for a in range(N):
                sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
                e5 += (hh * x5[a] / sc) ** 2
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
        # accept: dense output from the unprojected step, then project the end state
        t1 = t + hh
        if fixed and abs(t1 - times[k_out]) <= 1e-9 * hh:
            t1 = times[k_out]
        if hh == tend - t:
            t1 = tend
        tol_t = stepcontrol.SAMPLE_TOL * max(1.0, abs(t1))
        inner = k_out < T_out and times[k_out] < t1 - tol_t
        if dop853 and inner:
            st_code = _stages(sp, gen, wg, cnt, y, hh, s_st, s_st + n_ext, rk)
            if st_code != OK:
                return st_code
            stepcontrol.dense_dop853(y, yn, hh, K, s_st, D, Fd)
        st_code = (  # a last stage at yn (fsal) factored there: Newton from it
            kernels_sparse.settle(sp, yn[:n], yn[n:], qdd, ptol, cnt, fsal)
            if wg is None else _settle_general(gen, frc, yn[:n], yn[n:], qdd, ptol, wg, cnt))
        if st_code == ERR_NEWTON and not fixed:  # the step left the manifold too far to
            cnt[C_REJ] += 1                     # project back (near a singular position):
            h = stepcontrol.PROJECTION_FAILURE_FACTOR * hh  # and try a shorter one
            if stepcontrol.underflow(h, t):
                return ERR_UNDERFLOW
            continue
        if st_code != OK:
            return st_code
        f1[:n] = yn[n:]
        f1[n:] = qdd
        nsteps += 1
        cnt[C_STEPS] += 1
        # samples in (t, t1]
        while k_out < T_out and times[k_out] <= t1 + tol_t:
            tk = times[k_out]
            if abs(tk - t1) <= tol_t:
                Q[k_out] = yn[:n]
                QD[k_out] = yn[n:]
                QDD[k_out] = f1[n:]
            else:
                x = (tk - t) / hh
                if dop853:
                    stepcontrol.dense_at(Fd, y, x, yu)
                    qs[:] = yu[:n]
                    qds[:] = yu[n:]
                else:
                    _sample(y[:n], y[n:], f0[n:], yn[:n], yn[n:], f1[n:], hh, x, qs, qds)
                st_code = (  # true Newton from the sample: the M-orthogonal projection
                    # (a factorization from elsewhere lands it elsewhere on the manifold,
                    # which near a singular position shows in the reactions)
                    kernels_sparse.settle(sp, qs, qds, qdd, ptol, cnt, False)
                    if wg is None else _settle_general(gen, frc, qs, qds, qdd, ptol, wg, cnt))
                if st_code != OK:
                    return st_code
                Q[k_out] = qs
                QD[k_out] = qds
                QDD[k_out] = qdd
            k_out += 1
        t = t1
        y[:] = yn
        f0[:] = f1
        if not fixed:
            h = hh * stepcontrol.accept_factor(err, expo)
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
                          v=np.array([1.0, 1.0, -1.0]), m=1)
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
    # an elimination expands the samples after the loop
    dep = (np.array([0, 1], np.int64), np.zeros(1, np.int64), np.ones(1),
           np.zeros(1), np.arange(2, dtype=np.int64),
           np.array([2], np.int64))  # a third coordinate equal to the first
    expand(dep, Q, QD, Q, *(np.zeros((len(Q), 3)) for _ in range(3)))


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


def run(name: str, con, frc, times, q0, qd0, steps: Steps, route: Route | None = None,
        cnt=None):
    """Integrate with the compiled loop by method ``name``; returns (Q, QD, QDD) (T, n) (n
    of the model when ``route.dep`` is given). ``frc`` from :func:`pack_forces`; ``cnt``:
    counters added to. Raises RuntimeError."""
    rtol, atol, ptol, h, h0, max_steps = steps
    plan, kern, M, rank_tol, dep = route or Route()
    A, B, C, E5, E3, expo, Aext, Cext, D, fsal = tableau(name)
    tab = (A, B, C, E5, E3, expo, name == "dop853", Aext, Cext, D, fsal)
    if (h is None and name not in ADAPTIVE) or (h is not None and name not in FIXED_STEP):
        raise ValueError(f"{name} (compiled): " + ("give a fixed step h" if h is None else
                                                   "adaptive only"))
    Tn, n = len(times), len(q0)
    if dep is None:  # no coordinate eliminated
        dep = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
               np.arange(n, dtype=np.int64), np.zeros(0, np.int64))
    Q, QD, QDD = np.zeros((Tn, n)), np.zeros((Tn, n)), np.zeros((Tn, n))
    c, tfail = np.zeros(N_COUNTERS), np.zeros(1)
    gen = None if plan is not None else kernels_general.general(con, M, rank_tol)
    wg = workspace(n, int(con.m)) if plan is None else None  # None: the sparse path
    args = sparsity.empty_plan(n).kernel_args if plan is None else plan
    ws = kernels_sparse.workspace(args)
    w = kernels_sparse.work_vector(args, ws)
    ctl = (float(rtol), float(atol), float(h0), float(ptol), int(max_steps),
           0.0 if h is None else float(h))
    generated = kern is not None and plan is not None  # they serve the sparse path
    sp = (None if generated else args, kern if generated else kernels_sparse.NO_GK,
          None if generated else frc, ws, w)
    status = run_index1(sp, gen, wg, tab, ctl, dep, np.ascontiguousarray(times, float),
                        np.array(q0, float), np.array(qd0, float), (Q, QD, QDD, c, tfail))
    add_counters(c, cnt)
    if status != OK:
        k = int(np.searchsorted(times, tfail[0], side="right")) - 1  # last sample reached
        J = np.zeros((int(con.m), n))
        kernels_general.jacobian(con, Q[max(k, 0)], J)
        raise RuntimeError(f"{name} (compiled): {STATUS_TEXT.get(status, status)} at "
                           f"t = {tfail[0]:.6g} s" + singular_hint(J, rank_tol))
    if len(dep[5]) == 0:
        return Q, QD, QDD
    nq = n + len(dep[5])
    out = np.zeros((Tn, nq)), np.zeros((Tn, nq)), np.zeros((Tn, nq))
    expand(dep, Q, QD, QDD, *out)
    return out


def add_counters(c: np.ndarray, cnt) -> None:
    """Add a compiled loop's counter array c (N_COUNTERS,) to ``cnt``
    (:class:`natcoord.dynamics.common.Counters`; None: nothing)."""
    if cnt is None:
        return
    for slot, name in ((C_STEPS, "steps"), (C_REJ, "rejected"), (C_RHS, "rhs"),
                       (C_FACT, "factorizations"), (C_PROJ, "projections"),
                       (C_NEWTON, "newton"), (C_REPART, "repartitions")):
        setattr(cnt, name, getattr(cnt, name) + int(c[slot]))
    cnt.max_phi_step = max(cnt.max_phi_step, float(c[C_PHI]))
    cnt.max_phi_dot_step = max(cnt.max_phi_dot_step, float(c[C_PHID]))


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
