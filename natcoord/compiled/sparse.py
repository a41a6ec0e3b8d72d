"""Compiled evaluation of Eq. (6) on the sparsity plan (:mod:`natcoord.compiled.sparsity`).

The Schur path of the compiled loop for a regular, constant M, redundant rows included:

    qdd = M^-1 F - Y lambda,    W lambda = J M^-1 F - c,    Y = M^-1 J^T,  W = J Y = L L^T

The plan arrives packed as three arrays ``I, F, O`` (:attr:`SchurPlan.kernel_args
<natcoord.compiled.sparsity.SchurPlan.kernel_args>`: its integer and float arrays and their offsets;
three pointers per call instead of thirty arrays, whose passing and reference counting
cost more than the arithmetic), and the work array ``ws`` (:func:`workspace`) holds the
values of J, Y and L of the last factorization, so that a projection can take
simplified-Newton steps with it before factoring again. Every loop runs over the plan's
flat index arrays: no dense (m, n) matrix, no test on zeros.
Units: SI.
"""

from __future__ import annotations

import math

import numpy as np

from .general import (
    C_FACT,
    C_NEWTON,
    C_PHI,
    C_PHID,
    C_PROJ,
    C_RHS,
    ERR_NEWTON,
    OK,
    forces,
    njit,
    reachable,
)
from .sparsity import FLOAT, INT, WORK

try:
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a dependency
    intrinsic = None

NO_GK = np.zeros(0, np.int64)  # no generated kernels (see refactor)
NEWTON_MAX = 12  # simplified-Newton iterations of one projection
NEWTON_RATE = 0.25  # a slower contraction refreshes the factorization at the current q

# segment numbers in O (see SchurPlan.kernel_args): ints, then floats, then work, then m
_FO = len(INT) + 1
_WO = _FO + len(FLOAT) + 1
_M = _WO + len(WORK) + 1
(PHI_K, PHI_I, PHI_J, JAC_PTR, JAC_OTHER, GAM_K, GAM_I, GAM_J, J_ROW, J_COL, MI_PTR, MI_COL,
 Y_PTR, Y_J, YPTR, YCOL, W_PTR, W_J, W_Y, ENV_FIRST, ENV_PTR) = range(len(INT))
PHI_V, JAC_V, GAM_V, MI_VAL, Y_COEF = range(_FO, _FO + len(FLOAT))
W_J_, W_Y_, W_L_, W_W, W_C, W_F, W_G = range(_WO, _WO + len(WORK))


if intrinsic is not None:
    @intrinsic
    def _ptr(typingctx, arr):
        """The data pointer of a contiguous float64 array (for the generated kernels of
        :mod:`natcoord.compiled.codegen`, which take pointers)."""
        def codegen(context, builder, sig, args):
            return cgutils.create_struct_proxy(sig.args[0])(context, builder,
                                                            value=args[0]).data
        return types.CPointer(arr.dtype)(arr), codegen

    @intrinsic
    def _ptr_at(typingctx, arr, k):
        """The pointer to arr[k] of a contiguous 1-D float64 array: a part of it for a
        generated kernel without the slice (a view costs two atomic reference counts)."""
        def codegen(context, builder, sig, args):
            data = cgutils.create_struct_proxy(sig.args[0])(context, builder,
                                                            value=args[0]).data
            return builder.gep(data, [args[1]])
        return types.CPointer(arr.dtype)(arr, k), codegen

    # call(ret, address, p0, p1[, p2[, p3]]): the generated kernels travel as an array of
    # addresses, which the dispatcher types for nothing (first-class function objects cost
    # it tens of microseconds a call)
    def _lower_call(context, builder, sig, args):
        """Call the C function at address args[1] (int64) with the pointers args[2:],
        returning sig.return_type (args[0] only carries that type)."""
        void = sig.return_type == types.void
        rty = ir.VoidType() if void else context.get_value_type(sig.return_type)
        fnty = ir.FunctionType(rty, [context.get_value_type(a) for a in sig.args[2:]])
        out = builder.call(builder.inttoptr(args[1], fnty.as_pointer()), args[2:])
        return context.get_dummy_value() if void else out

    @intrinsic
    def _call2(typingctx, ret, address, p0, p1):
        return ret.instance_type(ret, address, p0, p1), _lower_call

    @intrinsic
    def _call3(typingctx, ret, address, p0, p1, p2):
        return ret.instance_type(ret, address, p0, p1, p2), _lower_call

    @intrinsic
    def _call4(typingctx, ret, address, p0, p1, p2, p3):
        return ret.instance_type(ret, address, p0, p1, p2, p3), _lower_call

    @intrinsic
    def _fma(typingctx, a, b, c):
        """a * b + c rounded once (LLVM's fma: the processor's instruction where it has
        one)."""
        def codegen(context, builder, sig, args):
            d = ir.DoubleType()
            f = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]),
                                               "llvm.fma.f64")
            return builder.call(f, args)
        return types.float64(types.float64, types.float64, types.float64), codegen
else:  # pragma: no cover - numba is a dependency
    def _fma(a, b, c):
        from fractions import Fraction
        return float(Fraction(a) * Fraction(b) + Fraction(c))


@njit(cache=True, inline="always")
def _seg(A, O, k):
    """Segment k of the packed array A (an integer, float or work segment by k)."""
    return A[O[k]:O[k + 1]]


def workspace(plan: tuple) -> np.ndarray:
    """The work array of plan (I, F, O): values of J, Y, L, three vectors (m, m, n) and
    the generated kernels' scratch (:data:`natcoord.compiled.sparsity.WORK`)."""
    O = plan[2]
    return np.zeros(int(O[_M - 1] - O[_WO]))


def work_vector(plan: tuple, ws: np.ndarray) -> np.ndarray:
    """The (m,) work vector of ``ws`` (a view: segment W_W of :func:`workspace`)."""
    return ws[plan[2][W_W]:plan[2][W_W + 1]]


@njit(cache=True, inline="always")
def _two_prod(a, b):
    """a * b = p + e exactly (the error of the product by one fused multiply-add)."""
    p = a * b
    return p, _fma(a, b, -p)


@njit(cache=True, inline="always")
def _two_sum(a, b):
    """a + b = s + e exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@njit(cache=True)
def phi(I, F, O, q, out):
    """out (m,) = Phi(q), summed without cancellation error: every product and sum carried
    in two doubles (error-free transformations), so a row |r_b - r_a|^2 - L^2 of points
    40 m from the origin is exact to its last bit rather than to u max|q|^2 ~ 4e-13 m^2,
    which near a singular position is what decides how well a projection pins the motion
    down. The plan holds the terms sorted by row."""
    kk, ii, jj, vv = _seg(I, O, PHI_K), _seg(I, O, PHI_I), _seg(I, O, PHI_J), _seg(F, O, PHI_V)
    n = q.shape[0]
    out[:] = 0.0
    r, hi, lo = -1, 0.0, 0.0  # the current row's sum, as hi + lo
    for t in range(kk.shape[0]):
        if kk[t] != r:
            if r >= 0:
                out[r] = hi + lo
            r, hi, lo = kk[t], 0.0, 0.0
        a = q[ii[t]] if ii[t] < n else 1.0
        b = q[jj[t]] if jj[t] < n else 1.0
        p, e = _two_prod(0.5 * vv[t], a)
        p2, e2 = _two_prod(p, b)
        hi, e3 = _two_sum(hi, p2)
        lo += e3 + e2 + e * b
    if r >= 0:
        out[r] = hi + lo


@njit(cache=True)
def jacobian(I, F, O, q, Jv):
    """Jv (nJ,) = the entries of Phi_q(q)."""
    ptr, other, vv = _seg(I, O, JAC_PTR), _seg(I, O, JAC_OTHER), _seg(F, O, JAC_V)
    n = q.shape[0]
    for e in range(Jv.shape[0]):
        s = 0.0
        for t in range(ptr[e], ptr[e + 1]):
            o = other[t]
            s += vv[t] * (q[o] if o < n else 1.0)
        Jv[e] = s


@njit(cache=True)
def gamma(I, F, O, qd, c):
    """c (m,) = -qd^T H_k qd."""
    kk, ii, jj, vv = _seg(I, O, GAM_K), _seg(I, O, GAM_I), _seg(I, O, GAM_J), _seg(F, O, GAM_V)
    c[:] = 0.0
    for t in range(kk.shape[0]):
        c[kk[t]] -= vv[t] * qd[ii[t]] * qd[jj[t]]


@njit(cache=True)
def jx(I, O, Jv, x, w):
    """w (m,) = J x; returns max |w|."""
    row, col = _seg(I, O, J_ROW), _seg(I, O, J_COL)
    w[:] = 0.0
    for e in range(row.shape[0]):
        w[row[e]] += Jv[e] * x[col[e]]
    big = 0.0
    for r in range(w.shape[0]):
        big = max(big, abs(w[r]))
    return big


@njit(cache=True)
def minv(I, F, O, f, out):
    """out (n,) = M^-1 f."""
    ptr, col, val = _seg(I, O, MI_PTR), _seg(I, O, MI_COL), _seg(F, O, MI_VAL)
    for a in range(out.shape[0]):
        s = 0.0
        for e in range(ptr[a], ptr[a + 1]):
            s += val[e] * f[col[e]]
        out[a] = s


@njit(cache=True)
def sub_y(I, O, Yv, w, x):
    """x (n,) -= Y w."""
    ptr, col = _seg(I, O, YPTR), _seg(I, O, YCOL)
    for a in range(x.shape[0]):
        s = 0.0
        for e in range(ptr[a], ptr[a + 1]):
            s += Yv[e] * w[col[e]]
        x[a] -= s


@njit(cache=True)
def factor(I, F, O, Jv, Yv, Lv):
    """Y = M^-1 J^T and the envelope Cholesky L of W = J Y, in place; returns the number
    of dependent rows (a pivot below dep_tol of its row's diagonal: its L[r, r] = 0)."""
    y_ptr, y_j, y_coef = _seg(I, O, Y_PTR), _seg(I, O, Y_J), _seg(F, O, Y_COEF)
    w_ptr, w_j, w_y = _seg(I, O, W_PTR), _seg(I, O, W_J), _seg(I, O, W_Y)
    first, ptr = _seg(I, O, ENV_FIRST), _seg(I, O, ENV_PTR)
    m, dep_tol = O[_M], O[_M + 1] * 1e-18
    for e in range(Yv.shape[0]):
        s = 0.0
        for p in range(y_ptr[e], y_ptr[e + 1]):
            s += y_coef[p] * Jv[y_j[p]]
        Yv[e] = s
    for e in range(Lv.shape[0]):
        s = 0.0
        for p in range(w_ptr[e], w_ptr[e + 1]):
            s += Jv[w_j[p]] * Yv[w_y[p]]
        Lv[e] = s
    dependent = 0
    for r in range(m):
        fr, pr = first[r], ptr[r]
        for c in range(fr, r):  # L[r, c] = (W[r, c] - sum_k L[r, k] L[c, k]) / L[c, c]
            pc = ptr[c]
            dc = Lv[pc + c - first[c]]
            if dc == 0.0:
                Lv[pr + c - fr] = 0.0
                continue
            s = Lv[pr + c - fr]
            for k in range(max(fr, first[c]), c):
                s -= Lv[pr + k - fr] * Lv[pc + k - first[c]]
            Lv[pr + c - fr] = s / dc
        d = Lv[pr + r - fr]
        s = d
        for k in range(fr, r):
            s -= Lv[pr + k - fr] * Lv[pr + k - fr]
        if s > dep_tol * d and s > 0.0:
            Lv[pr + r - fr] = math.sqrt(s)
        else:
            Lv[pr + r - fr] = 0.0
            dependent += 1
    return dependent


@njit(cache=True)
def solve(I, O, Lv, b):
    """b (m,) <- a solution of L L^T x = b (dependent rows: x_r = 0)."""
    first, ptr, m = _seg(I, O, ENV_FIRST), _seg(I, O, ENV_PTR), O[_M]
    for r in range(m):
        fr, pr = first[r], ptr[r]
        d = Lv[pr + r - fr]
        if d == 0.0:
            b[r] = 0.0
            continue
        s = b[r]
        for k in range(fr, r):
            s -= Lv[pr + k - fr] * b[k]
        b[r] = s / d
    for r in range(m - 1, -1, -1):
        fr, pr = first[r], ptr[r]
        d = Lv[pr + r - fr]
        if d == 0.0:
            b[r] = 0.0
            continue
        x = b[r] / d
        b[r] = x
        for k in range(fr, r):
            b[k] -= Lv[pr + k - fr] * x


@njit(cache=True, _nrt=False)
def refactor(P, gk, q, ws, cnt):
    """J, Y and L at q into the work array ``ws``: by the generic kernels on the plan
    ``P`` = (I, F, O), or, P None, by the model's generated kernels ``gk`` (addresses, see
    :mod:`natcoord.compiled.codegen`; :data:`NO_GK` with a plan). Returns the number of
    dependent rows. The generated path passes no plan and no force tuple: their arrays cost
    more to pass than its kernels take to run, and numba compiles the None branches
    away."""
    cnt[C_FACT] += 1
    if P is None:
        return _call2(types.int64, gk[1], _ptr(q), _ptr(ws))
    I, F, O = P
    jacobian(I, F, O, q, _seg(ws, O, W_J_))
    return factor(I, F, O, _seg(ws, O, W_J_), _seg(ws, O, W_Y_), _seg(ws, O, W_L_))


@njit(cache=True, _nrt=False)
def accelerations(P, gk, frc, q, qd, qdd, ws, cnt, fresh):
    """qdd (n,) of Eq. (6) at (q, qd); ``fresh``: factor at q first (else ``ws`` holds
    the factorization at this q already). ``frc``: the packed forces, None with generated
    kernels (they carry them)."""
    if P is None:
        _generated_acc(gk, _ptr(q), _ptr(qd), _ptr(qdd), ws, cnt, fresh)
    else:
        cnt[C_RHS] += 1
        if fresh:
            refactor(P, gk, q, ws, cnt)
        _plan_acc(P, frc, q, qd, qdd, ws)
    return OK


@njit(cache=True, _nrt=True)
def _plan_acc(P, frc, q, qd, qdd, ws):
    """qdd (n,) of Eq. (6) by the generic kernels with the factorization in ``ws``. Kept
    apart from :func:`accelerations`, which is compiled without reference counting: the
    view :func:`multipliers` returns must be released by a counting caller (``_nrt=True``
    stated: a callee that leaves it unset inherits its first caller's)."""
    I, F, O = P
    w = multipliers(I, F, O, frc, q, qd, qdd, ws)
    sub_y(I, O, _seg(ws, O, W_Y_), w, qdd)


@njit(cache=True, inline="always")
def _generated_acc(gk, pq, pqd, pqdd, ws, cnt, fresh):
    """qdd by the generated kernels from pointers to q, qd and qdd (factoring there first
    when ``fresh``)."""
    cnt[C_RHS] += 1
    if fresh:
        cnt[C_FACT] += 1
    _call4(types.void, gk[5] if fresh else gk[2], pq, pqd, pqdd, _ptr(ws))


@njit(cache=True, inline="always")
def acc_state(P, gk, frc, y, K, st, qdd, ws, cnt):
    """The stage K[st] = [qd, qdd] (2n,) at the state y = [q, qd] (2n,), factoring there
    (a stage of the loop); qdd (n,): scratch; a status code. The generated kernels get
    pointers into y and K: slicing costs two atomic reference counts, a tenth of a stage
    on a small model, and their qdd written into K's row is not loaded back while their
    stores are in flight (copied from qdd, a stage stalled on it)."""
    n = qdd.shape[0]
    if P is None:
        _generated_acc(gk, _ptr(y), _ptr_at(y, n), _ptr_at(K, st * 2 * n + n), ws, cnt, True)
    else:
        st_code = accelerations(P, gk, frc, y[:n], y[n:], qdd, ws, cnt, True)
        if st_code != OK:
            return st_code
        for a in range(n):
            K[st, n + a] = qdd[a]
    for a in range(n):
        K[st, a] = y[n + a]
    return OK


@njit(cache=True, _nrt=False)
def _phi_max(P, gk, q, w):
    """w (m,) = Phi(q); returns max |w|."""
    if P is None:
        _call2(types.void, gk[0], _ptr(q), _ptr(w))
    else:
        I, F, O = P
        phi(I, F, O, q, w)
    e = 0.0
    for r in range(w.shape[0]):
        e = max(e, abs(w[r]))
    return e


@njit(cache=True, _nrt=False)
def _jx(P, gk, ws, x, w):
    """w (m,) = J x with the stored J; returns max |w|."""
    if P is None:
        return _call3(types.float64, gk[4], _ptr(ws), _ptr(x), _ptr(w))
    else:
        I, F, O = P
        return jx(I, O, _seg(ws, O, W_J_), x, w)


@njit(cache=True)
def multipliers(I, F, O, frc, q, qd, f_over_m, ws):
    """lambda (m,) from W lambda = J M^-1 F - c with the factorization in ``ws`` (returned
    as the work vector it was solved in); ``f_over_m`` (n,) receives M^-1 F."""
    w, c, f = _seg(ws, O, W_W), _seg(ws, O, W_C), _seg(ws, O, W_F)
    gamma(I, F, O, qd, c)
    forces(frc, q, qd, f)
    minv(I, F, O, f, f_over_m)
    jx(I, O, _seg(ws, O, W_J_), f_over_m, w)
    for r in range(w.shape[0]):
        w[r] -= c[r]
    solve(I, O, _seg(ws, O, W_L_), w)
    return w


@njit(cache=True, _nrt=False)
def _newton_step(P, gk, ws, w, x):
    """x -= Y (L L^T)^-1 w (an M-orthogonal correction with the stored factorization)."""
    if P is None:
        _call3(types.void, gk[3], _ptr(ws), _ptr(w), _ptr(x))
    else:
        I, F, O = P
        solve(I, O, _seg(ws, O, W_L_), w)
        sub_y(I, O, _seg(ws, O, W_Y_), w, x)


NEWTON_REST = 0.5  # a Newton step's bound on |Phi| below this fraction of the tolerance:
# converged without evaluating Phi (:func:`settle`). Any fraction below 1 leaves the motion
# as it was (Phi's exact sum would have ended the loop there); at 0.1 the rounding term
# alone (gq EPS max|q|^2: 1.5-2.2e-14 on slider_crank, four_bar) never let it pass at the
# default tolerance 1e-13, and every sample paid a second Phi
EPS = float(np.finfo(np.float64).eps)


def newton_bound(plan: tuple, n: int) -> tuple[float, float]:
    """(hq, gq) of the plan (I, F, O) over n coordinates: the largest sum over one row of
    Phi of |v| for its terms v q_i q_j quadratic in q (hq) and for its terms with a
    coordinate (gq). Every row being quadratic, Phi(q0 + d) = Phi(q0) + Phi_q
    d + Phi_2(d) exactly, so a Newton step from q0 leaves |Phi| <= hq max|d|^2 in exact
    arithmetic, and storing q0 + d rounds each coordinate by EPS/2 |q|, which moves a row
    by at most gq EPS max(1, max|q|)^2 (:func:`settle`)."""
    I, F, O = plan
    k, i, j = _seg(I, O, PHI_K), _seg(I, O, PHI_I), _seg(I, O, PHI_J)
    v = np.abs(_seg(F, O, PHI_V))
    if not len(k):
        return 0.0, 0.0
    hq = np.bincount(k, v * ((i < n) & (j < n)))
    gq = np.bincount(k, v * ((i < n) | (j < n)))
    return float(hq.max()), float(gq.max())


@njit(cache=True, _nrt=False, inline="always")
def _newton_rest(q, q0, bound):
    """The bound of :func:`newton_bound` on max |Phi(q)| after a Newton step from q0 (n,)
    with the factorization at q0, ``bound`` = (hq, gq)."""
    d, big = 0.0, 1.0
    for a in range(q.shape[0]):
        d = max(d, abs(q[a] - q0[a]))
        big = max(big, abs(q[a]))
    return bound[0] * d * d + bound[1] * EPS * big * big


@njit(cache=True, _nrt=False)
def settle(sp, q, qd, qdd, tol, bound, cnt, factored):
    """Project q on Phi = 0 by M-orthogonal simplified-Newton steps with the factorization
    in ``ws`` (``factored``: one made at q, by the last stage; else factor at q first;
    refreshed when the contraction is slow), factor once at the projected q, project qd on
    Phi_q qd = 0 with it and evaluate qdd there. Returns a status code. ``sp`` = (P, gk,
    frc, ws, w): the Schur path (plan or generated kernels, forces, work array and its work
    vector (m,), :func:`work_vector`). After a true Newton step (factored here, at the
    step's start, with no dependent row: a dropped row's Phi is not bounded by the others')
    Phi is not evaluated when ``bound`` = (hq, gq) (:func:`newton_bound`; (0, 0): always
    evaluated) puts it below NEWTON_REST tol: a sample near the constraints takes one Phi
    instead of two.

    It and the kernels it calls are compiled without numba's reference counting (they
    allocate nothing): on four_bar and slider_crank the counting took 13-15 % of a whole
    run, most of it at the output samples, which each settle once."""
    P, gk, frc, ws, w = sp
    tol = reachable(tol, q, 1)  # phi adds no round-off: q's resolution is the floor
    e = _phi_max(P, gk, q, w)
    cnt[C_PHI] = max(cnt[C_PHI], e)
    full = False  # the factorization here has no dependent row (its step solves every row)
    if not factored and e >= tol:
        full = refactor(P, gk, q, ws, cnt) == 0
    prev = math.inf
    fresh = False  # the factorization is at the current q (true Newton this iteration)
    it = 0
    while e >= tol:
        if it >= NEWTON_MAX:
            return ERR_NEWTON
        if e > NEWTON_RATE * prev and not fresh:
            full = refactor(P, gk, q, ws, cnt) == 0
            fresh = True
        else:
            fresh = False
        exact = (it == 0 or fresh) and full  # a true Newton step on every row
        if exact:
            for a in range(q.shape[0]):
                qdd[a] = q[a]  # the step's start (qdd: scratch until the end)
        _newton_step(P, gk, ws, w, q)
        cnt[C_NEWTON] += 1
        it += 1
        if exact and _newton_rest(q, qdd, bound) <= NEWTON_REST * tol:
            break
        prev = e
        e = _phi_max(P, gk, q, w)
    refactor(P, gk, q, ws, cnt)
    ev = _jx(P, gk, ws, qd, w)
    cnt[C_PHID] = max(cnt[C_PHID], ev)
    if ev > tol:
        _newton_step(P, gk, ws, w, qd)
    cnt[C_PROJ] += 1
    return accelerations(P, gk, frc, q, qd, qdd, ws, cnt, False)


@njit(cache=True)
def sample_outputs(I, F, O, frc, Q, QD, LAM, drift, ws, cnt):
    """After a run, at every sample k: the multipliers LAM[k] (m,) in plan row order (the
    unique ones when no row is dependent), and drift[k] = (max |Phi|, max |Phi_q qd|).
    Returns a flag per sample (T,): 1 where a row was dependent (lambda not unique: the
    caller takes the minimum-norm one there)."""
    T = Q.shape[0]
    n = Q.shape[1]
    dep = np.zeros(T, np.int64)
    mf = np.zeros(n)  # M^-1 F, scratch
    w = _seg(ws, O, W_W)
    for k in range(T):
        q, qd = Q[k], QD[k]
        drift[k, 0] = _phi_max((I, F, O), NO_GK, q, w)
        jacobian(I, F, O, q, _seg(ws, O, W_J_))
        drift[k, 1] = jx(I, O, _seg(ws, O, W_J_), qd, w)
        if factor(I, F, O, _seg(ws, O, W_J_), _seg(ws, O, W_Y_), _seg(ws, O, W_L_)) > 0:
            dep[k] = 1
        LAM[k] = multipliers(I, F, O, frc, q, qd, mf, ws)
    return dep
