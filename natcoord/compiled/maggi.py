"""Compiled (numba) time loop of the Maggi formulation (R-method, Eq. (23)).

One call integrates the whole run, step for step what ``MaggiLoop`` and the time loop of
:mod:`natcoord.dynamics.integrators` do in Python. The state is y = [q^i, qd^i] (2f) over the
independent coordinates of a partition of Phi_q (m, n) by Gaussian elimination with full
pivoting (rows (r,) of independent constraints, dependent coordinates dep (r,), independent
indep (f,), f = n - r). Every evaluation of dy/dt

1. rebuilds q (n,): the last solution moved along the last R by the change of q^i, then
   Newton on Phi[rows](q) = 0 over q^d (at most 20 iterations, stopped at |Phi| <
   ``newton_tol`` or when |dq| reaches round-off, 10 newton_tol max(1, ptp q));
2. R (n, f) with R^d = -(Phi_q^d)^-1 Phi_q^i, R^i = I; qd = R qd^i; S c (n,) with
   (S c)^d = (Phi_q^d)^-1 c[rows], c = -qd^T H_k qd;
3. qdd^i from (R^T M R) qdd^i = R^T (F - M S c)  (Eq. (23)).

Integrators: adaptive ``dop853`` (Hairer's error norm, dense output of order 7) and
``dopri5`` (order-4 dense output, Hairer's P), fixed-step ``rk4`` and ``dopri5`` (equal
steps landing on every sample); step control as the Python loop (Hairer's initial step,
the functions of :mod:`natcoord.compiled.stepcontrol`; a failed Newton in a stage rejects the
step with h/4). After every
accepted step the partition is renewed when max|R^d| has grown by ``repartition_growth``
over its value at the first step after the last partition (the Gaussian elimination is
ported here, so the loop never leaves numba); a change of rank there stops the run
(ERR_SINGULAR: the Python loop would carry on with another f). Samples: q, qd from step
2 at the step end or the dense output, qdd = S c + R qdd^i.

The generated path (``gen``, :func:`generated`: index-1's kernels of the model, written
out by :mod:`natcoord.compiled.codegen`) does steps 1-3 cheaper (:func:`_kin_gen`), with no
dense Jacobian or LU. ``MaggiLoop`` runs it on the coordinates index-1's elimination keeps
where that leaves M regular (:mod:`natcoord.compiled.elimination`: q = T q_r + b, the
constant linear rows hold identically), with index-1's kernels of that model: four_bar 12
-> 4 coordinates, slider_crank 10 -> 3, and the Schur complement of a regular M_r instead
of the regularised dense factor of the model's singular M, 1.7-1.9x less time per step;
the partition, the state and the samples are then over the kept coordinates, written back
to all of them after the run:

1. q from a prediction by the step's own Runge-Kutta sums of the full coordinates
   (:func:`_stages`): the loop keeps the full q, qd at the step's start and the full qd,
   qdd of every stage, and predicts stage s by qn + h sum_p A[s, p] Kq[p] (its q^i is
   the stage's exactly), the step's end by the weights B and a sample by the continuous
   extension of the full q (:func:`_step_end`, ``stepcontrol.dense_*``). DOP853's
   stages from the sixth on have stage order 5, so the prediction misses Phi = 0 by the
   stage's error (~1e-8 m) where the last solution moved along the last R missed by
   ~1e-3 m: 1.1 Newton steps per evaluation instead of 2.1, and 2.1 factorizations
   instead of 3.1. Each Newton step (:func:`_positions_gen`) is the M-weighted
   least-norm step of index-1's sparse factorization at q (``refactor``) with q^i held,
   Phi_q (d - R d^i) = -Phi (:func:`_step_gen`); its R is R at q (:func:`_null_gen`) or,
   for the first step of one degree of freedom, the predicted full qd over qd^i
   (:func:`_velocity_basis`: one projection less). Newton stops at |Phi| < ``newton_tol``
   (a prediction within it is still corrected once unless |Phi| < 1e-3 newton_tol, so
   that q is Newton's to round-off like the generic path's: the two agree to 3.4e-14
   relative over a run) or when its step reaches round-off.
2. The factorization at the solution and R there, by the last R projected on ker Phi_q
   (:func:`_null_gen`); qd = R qd^i.
3. qdd whole from index-1's Eq. (6) at (q, qd) (:func:`_acc_gen`) -- for a consistent
   state the same accelerations as Eq. (23), to round-off.

Nothing is redone at the y of the last evaluation (the step's end after
:func:`_post_step` is the next step's first stage). The path is compiled without numba's
reference counting (``_nrt=False``: it allocates nothing): counting cost more than the
arithmetic (a call at an unchanged y 550 -> 116 ns). (A simplified Newton with the last
evaluation's LU from the last solution moved along the last R took 2.7x the iterations
for no gain in time and converged to the other assembly branch of four_bar and five_bar
at rtol 1e-8: errors of 7.6 and 4.0 rad; each step here is a true Newton step from a
prediction 1e5 times closer.) Without generated kernels (a model
:func:`natcoord.compiled.codegen.load` declines, or ``generated = false``) the generic
kernels above run.

Kernels take plain arrays: the scleronomic constraint triplets ``k, i, j, v`` over qh =
[q, 1] (:class:`~natcoord.model.constraints.QuadraticConstraints`), M (n, n) as its non-zeros
(i, j, v), forces packed by :func:`natcoord.compiled.general.pack_forces`. Dense LU with
partial pivoting on the small blocks (r, r) and (f, f). Units: SI (m, s, kg, N).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import types

from . import general as kernels_general
from . import sparse as kernels_sparse
from . import stepcontrol
from .general import (
    C_FACT,
    C_NEWTON,
    C_REJ,
    C_REPART,
    C_RHS,
    C_STEPS,
    ERR_MASS,
    ERR_NEWTON,
    ERR_NONFINITE,
    ERR_SINGULAR,
    ERR_UNDERFLOW,
    N_COUNTERS,
    OK,
    _gamma,
    _jac,
    _lu,
    _lu_solve,
    _phi,
    forces,
    pack_constraints,
)
from .index1 import (
    add_counters,
    check,
    drop_stale_cache,
    njit,
    tableau,
    warm_up_model,
)
from .sparse import _call2, _call3, _call4, _ptr

NEWTON_ITER = 20


# ---- small dense algebra -----------------------------------------------------------------
@njit(cache=True)
def partition(J, tol, A, rows, cols):
    """Gaussian elimination with full pivoting of J = Phi_q (m, n), as
    :func:`natcoord.dynamics.common.full_pivot_partition`: returns the rank r, with rows[:r]
    the independent rows, cols[:r] the dependent coordinates (elimination order) and
    cols[r:] the independent ones (sorted). Work: A (m, n); rows (m,), cols (n,) int."""
    m, n = J.shape
    big = 0.0
    for i in range(m):
        rows[i] = i
        for j in range(n):
            A[i, j] = J[i, j]
            big = max(big, abs(J[i, j]))
    for j in range(n):
        cols[j] = j
    scale = max(big, 1e-300)
    r = 0
    for k in range(min(m, n)):
        best, bi, bj = -1.0, k, k
        for i in range(k, m):  # the first largest in row-major order (np.argmax)
            for j in range(k, n):
                if abs(A[i, j]) > best:
                    best, bi, bj = abs(A[i, j]), i, j
        if best <= tol * scale:
            break
        for j in range(n):
            A[k, j], A[bi, j] = A[bi, j], A[k, j]
        rows[k], rows[bi] = rows[bi], rows[k]
        for i in range(m):
            A[i, k], A[i, bj] = A[i, bj], A[i, k]
        cols[k], cols[bj] = cols[bj], cols[k]
        r += 1
        for i in range(k + 1, m):
            lr = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= lr * A[k, j]
    for a in range(r + 1, n):  # cols[r:] sorted (insertion: a few entries, no allocation)
        x, b = cols[a], a
        while b > r and cols[b - 1] > x:
            cols[b] = cols[b - 1]
            b -= 1
        cols[b] = x
    return r


# ---- one evaluation ----------------------------------------------------------------------
@njit(cache=True)
def workspace(n, m, r, f):
    """Work arrays: 0 ql (n,) the last q solved, 1 R (n, f) the last R, 2 (1,) int: 1 when
    R serves the next predictor (not right after a partition), [1] 1 when ws holds the
    kinematics at the last y (generated path: ``gen[4]``), 3 q, 4 qd, 5 Sc (n,), 6 p
    (m,), 7 J (m, n), 8 Jd (r, r), 9 piv (r,) int, 10 b (r,), 11 F, 12 w (n,), 13 MR (n, f),
    14 A3 (f, f), 15 piv3 (f,) int, 16 (2,): max|R^d| of the last R and R0 (< 0: not set
    since the last partition); 17 A (m, n), 18 rows (m,), 19 cols (n,) int: a re-partition's;
    20 qdd^i (f,) of a sample."""
    return (np.zeros(n), np.zeros((n, f)), np.zeros(2, np.int64), np.zeros(n), np.zeros(n),
            np.zeros(n), np.zeros(m), np.zeros((m, n)), np.zeros((r, r)),
            np.zeros(r, np.int64), np.zeros(r), np.zeros(n), np.zeros(n), np.zeros((n, f)),
            np.zeros((f, f)), np.zeros(f, np.int64), np.full(2, -1.0), np.zeros((m, n)),
            np.zeros(m, np.int64), np.zeros(n, np.int64), np.zeros(f))


@njit(cache=True, _nrt=False)
def _factor_dep(J, rows, dep, Jd, piv, cnt):
    """Jd = Phi_q[rows][:, dep] (r, r) factored in place; False when singular."""
    r = dep.shape[0]
    for i in range(r):
        for j in range(r):
            Jd[i, j] = J[rows[i], dep[j]]
    cnt[C_FACT] += 1
    return _lu(Jd, piv)


@njit(cache=True, _nrt=False, inline="always")
def _predict(part, y, ws):
    """The Newton's start, q (ws[3]): the last solution ws[0] moved along the last R by
    the change of q^i (while R serves, ws[2][0]), with q^i = y[:f]; returns the span of
    the last solution, m (round-off scale of the Newton's stop)."""
    indep = part[2]
    ql, R, flags, q = ws[0], ws[1], ws[2], ws[3]
    n, f = q.shape[0], indep.shape[0]
    lo, hi = ql[0], ql[0]
    for a in range(n):
        q[a] = ql[a]
        lo = min(lo, ql[a])
        hi = max(hi, ql[a])
    if flags[0]:  # q += R (q^i - q_last^i)
        for a in range(n):
            s = 0.0
            for c in range(f):
                s += R[a, c] * (y[c] - ql[indep[c]])
            q[a] += s
    for c in range(f):
        q[indep[c]] = y[c]
    return max(hi - lo, 1e-300)


@njit(cache=True, _nrt=False)
def _positions(con, part, tol, y, ws, cnt):
    """q (ws[3]) at the independent positions y[:f] by Newton on Phi[rows] = 0 from
    :func:`_predict` (``MaggiLoop._positions``), by the triplets and a dense LU of the
    dependent block; kept in ws[0] when it converges. A status code. Allocates nothing:
    compiled without reference counting."""
    kk, ii, jj, vv, m = con
    rows, dep, indep = part
    ql, q, p, J, Jd, piv, b = ws[0], ws[3], ws[6], ws[7], ws[8], ws[9], ws[10]
    n, r = q.shape[0], dep.shape[0]
    size = _predict(part, y, ws)
    for _ in range(NEWTON_ITER):
        _phi(kk, ii, jj, vv, m, q, p)
        e = 0.0
        for i in range(r):
            e = max(e, abs(p[rows[i]]))
        if e < tol:
            break
        _jac(kk, ii, jj, vv, q, J)
        if not _factor_dep(J, rows, dep, Jd, piv, cnt):
            return ERR_SINGULAR
        for i in range(r):
            b[i] = p[rows[i]]
        _lu_solve(Jd, piv, b)
        step = 0.0
        for i in range(r):
            q[dep[i]] -= b[i]
            step = max(step, abs(b[i]))
        cnt[C_NEWTON] += 1
        if step < tol * 10.0 * max(1.0, size):  # round-off reached
            break
    else:
        return ERR_NEWTON
    for a in range(n):
        ql[a] = q[a]
    return OK


@njit(cache=True, _nrt=False)
def _rates(con, part, y, ws, cnt):
    """At q (ws[3]): Phi_q (ws[7]) and the LU of its dependent block (ws[8], ws[9]), R
    (ws[1]: R^d = -(Phi_q^d)^-1 Phi_q^i, R^i = I), max|R^d| (ws[16][0]) and qd = R qd^i
    (ws[4]) from y[f:]; OK or ERR_SINGULAR."""
    kk, ii, jj, vv, m = con
    rows, dep, indep = part
    R, q, qd, J, Jd, piv, b = ws[1], ws[3], ws[4], ws[7], ws[8], ws[9], ws[10]
    n, r, f = q.shape[0], dep.shape[0], indep.shape[0]
    _jac(kk, ii, jj, vv, q, J)
    if not _factor_dep(J, rows, dep, Jd, piv, cnt):
        return ERR_SINGULAR
    g = 0.0
    for c in range(f):
        for i in range(r):
            b[i] = J[rows[i], indep[c]]
        _lu_solve(Jd, piv, b)
        for i in range(r):
            R[dep[i], c] = -b[i]
            g = max(g, abs(b[i]))
        for c2 in range(f):
            R[indep[c2], c] = 1.0 if c2 == c else 0.0
    ws[16][0] = g
    for a in range(n):
        s = 0.0
        for c in range(f):
            s += R[a, c] * y[f + c]
        qd[a] = s
    return OK


@njit(cache=True)
def _kinematics(con, part, tol, y, ws, cnt):
    """q, qd, R, S c (ws[3], ws[4], ws[1], ws[5]) and max|R^d| (ws[16][0]) at the
    integrated y = [q^i, qd^i] (``MaggiLoop._kinematics``); a status code."""
    st = _positions(con, part, tol, y, ws, cnt)
    if st != OK:
        return st
    st = _rates(con, part, y, ws, cnt)
    if st != OK:
        return st
    kk, ii, jj, vv, m = con
    rows, dep, indep = part
    flags, qd, Sc, p, Jd, piv, b = ws[2], ws[4], ws[5], ws[6], ws[8], ws[9], ws[10]
    r = dep.shape[0]
    flags[0] = 1
    _gamma(kk, ii, jj, vv, qd, p)  # c (m,)
    for i in range(r):
        b[i] = p[rows[i]]
    _lu_solve(Jd, piv, b)
    Sc[:] = 0.0
    for i in range(r):
        Sc[dep[i]] = b[i]
    return OK


@njit(cache=True)
def _acc(Msp, frc, ws, qddi, cnt):
    """qdd^i (f,) of Eq. (23) at the kinematics in ws; OK or ERR_MASS (R^T M R singular)."""
    Mi, Mj, Mv = Msp
    R, q, qd, Sc, F, w, MR, A3, piv3 = ws[1], ws[3], ws[4], ws[5], ws[11], ws[12], ws[13], \
        ws[14], ws[15]
    n, f = R.shape
    cnt[C_RHS] += 1
    cnt[C_FACT] += 1
    if f == 0:
        return OK
    forces(frc, q, qd, F)
    for a in range(n):
        w[a] = F[a]
    MR[:, :] = 0.0
    for e in range(Mv.shape[0]):  # w = F - M S c, MR = M R
        a, b2, v = Mi[e], Mj[e], Mv[e]
        w[a] -= v * Sc[b2]
        for c in range(f):
            MR[a, c] += v * R[b2, c]
    for c in range(f):
        s = 0.0
        for a in range(n):
            s += R[a, c] * w[a]
        qddi[c] = s
        for c2 in range(f):
            s = 0.0
            for a in range(n):
                s += R[a, c] * MR[a, c2]
            A3[c, c2] = s
    if not _lu(A3, piv3):
        return ERR_MASS
    _lu_solve(A3, piv3, qddi)
    return OK


# ---- the generated path (a regular M) ----------------------------------------------------
@njit(cache=True)
def _rows_gen(gen, rows):
    """gen[3] (r,) = the generated kernels' rows of the partition's rows ``rows``."""
    prow, prr = gen[2], gen[3]
    for i in range(prr.shape[0]):
        prr[i] = prow[rows[i]]


@njit(cache=True, _nrt=False, inline="always")
def _null_gen(gen, part, ws, R):
    """R (n, f) at the q of the last ``refactor``, and max|R^d| returned (< 0: X^i
    singular, the independent coordinates are not): X = V - Y W^-1 J V (n, f), f vectors
    of ker Phi_q by the generated ``jx`` and ``newton`` kernels from V the last R (ws[1],
    nearly in ker Phi_q: a small correction; E_i would fail for a massless point's
    coordinate, which the metric M + alpha J_S^T J_S projects to 0), then R = X Z, Z =
    (X^i)^-1 (R^i = I exactly). Scratch: ws[12], ws[14], ws[15], ws[20], gen[8] X and
    gen[10] Z (f, f)."""
    gk, gws, w, X, Z = gen[0], gen[1], gen[6], gen[8], gen[10]
    rows, dep, indep = part
    V, A3, piv3, col, v = ws[1], ws[14], ws[15], ws[12], ws[20]
    n, r, f = R.shape[0], dep.shape[0], indep.shape[0]
    for c in range(f):
        for a in range(n):
            col[a] = V[a, c]
        _call3(types.float64, gk[4], _ptr(gws), _ptr(col), _ptr(w))  # w = J e_c
        _call3(types.void, gk[3], _ptr(gws), _ptr(w), _ptr(col))  # col -= Y W^-1 w
        for a in range(n):
            X[a, c] = col[a]
    if f == 1:  # the usual case: no factorization
        if X[indep[0], 0] == 0.0:
            return -1.0
        Z[0, 0] = 1.0 / X[indep[0], 0]
    elif f > 1:
        for c in range(f):
            for c2 in range(f):
                A3[c, c2] = X[indep[c], c2]
        if not _lu(A3, piv3):
            return -1.0
        for c in range(f):  # column c of Z: X^i z = e_c
            for c2 in range(f):
                v[c2] = 1.0 if c2 == c else 0.0
            _lu_solve(A3, piv3, v)
            for c2 in range(f):
                Z[c2, c] = v[c2]
    g = 0.0
    for i in range(r):
        a = dep[i]
        for c in range(f):
            s = 0.0
            for c2 in range(f):
                s += X[a, c2] * Z[c2, c]
            R[a, c] = s
            g = max(g, abs(s))
    for c in range(f):
        for c2 in range(f):
            R[indep[c2], c] = 1.0 if c2 == c else 0.0
    return g


@njit(cache=True, _nrt=False, inline="always")
def _step_gen(gen, part, q, p, Rc):
    """One Newton step on Phi[rows] = 0 over q^d, q (n,) in place, with the factorization
    in the kernels' work array and Rc (n, f) the R at its q: the M-weighted least-norm
    step d = -Y W^-1 Phi (p (m,): Phi at q), then q^d += d^d - Rc^d d^i (q^i held;
    Phi_q (d - Rc d^i) = -Phi, the Newton step of the dependent block). Returns max |dq^d|
    (m)."""
    gk, gws, w, d = gen[0], gen[1], gen[6], gen[7]
    rows, dep, indep = part
    n, r, f = q.shape[0], dep.shape[0], indep.shape[0]
    for i in range(p.shape[0]):
        w[i] = p[i]
    for a in range(n):
        d[a] = 0.0
    _call3(types.void, gk[3], _ptr(gws), _ptr(w), _ptr(d))  # d = -Y W^-1 Phi
    step = 0.0
    for i in range(r):
        a = dep[i]
        s = d[a]
        for c in range(f):
            s -= Rc[a, c] * d[indep[c]]
        q[a] += s
        step = max(step, abs(s))
    return step


@njit(cache=True, _nrt=False, inline="always")
def _residual_gen(gen, q, p):
    """max |Phi[rows](q)| (m) by the generated ``phi`` kernel, Phi (m,) into p."""
    prr = gen[3]
    _call2(types.void, gen[0][0], _ptr(q), _ptr(p))
    e = 0.0
    for i in range(prr.shape[0]):
        e = max(e, abs(p[prr[i]]))
    return e


@njit(cache=True, _nrt=False, inline="always")
def _velocity_basis(part, y, qdp, Rc):
    """f = 1: Rc (n, 1) = qdp / qd^i, R predicted from the predicted full qd (n,) (on Phi
    = 0, qd = R qd^i), when qdp is a prediction at this y (its qd^i that of y, to 1e-9)
    and qd^i is not small (> 1e-3 max|qdp|); False (Rc untouched) otherwise."""
    indep = part[2]
    f = indep.shape[0]
    if f != 1:
        return False
    v, big = y[1], 0.0
    for a in range(qdp.shape[0]):
        big = max(big, abs(qdp[a]))
    if not (abs(v) > 1e-3 * big and abs(qdp[indep[0]] - v) <= 1e-9 * abs(v)):
        return False
    for a in range(qdp.shape[0]):
        Rc[a, 0] = qdp[a] / v
    Rc[indep[0], 0] = 1.0
    return True


REST = 0.5  # _rest_gen's bound below this fraction of the Newton tolerance: converged
EPS = float(np.finfo(np.float64).eps)


@njit(cache=True, _nrt=False, inline="always")
def _rest_gen(gen, part, y, qdp, step, big, basis):
    """A bound on max |Phi| after a Newton step of :func:`_step_gen` from the q the
    kernels' work array is factored at (no dependent row): every row quadratic, Phi(q0 +
    dq) = Phi(q0) + J dq + Phi_2(dq) exactly, and J dq = -Phi(q0) - J Rc d^i, so |Phi| <=
    |J Rc| |d^i| + hq max|dq|^2 + gq EPS (max|q| + max|dq|)^2 (the rounding of storing q0 +
    dq; hq, gq = gen[11], :func:`natcoord.compiled.sparse.newton_bound`; < 0: no bound).
    Rc is R at q0 (J R = 0) or, ``basis``, the predicted qd over qd^i (f = 1,
    :func:`_velocity_basis`), whose J Rc is max|J qdp| / |qd^i| by the ``jx`` kernel on
    the stored J. ``step`` = max|dq| (q^i is held)."""
    hq, gq = gen[11][0], gen[11][1]
    if hq < 0.0:
        return math.inf
    r = hq * step * step + gq * EPS * (big + step) ** 2
    if basis:
        indep, d, w = part[2], gen[7], gen[6]
        jq = _call3(types.float64, gen[0][4], _ptr(gen[1]), _ptr(qdp), _ptr(w))
        r += jq * abs(d[indep[0]]) / abs(y[indep.shape[0]])
    return r


@njit(cache=True, _nrt=False, inline="always")
def _positions_gen(part, gen, tol, y, qp, qdp, ws, cnt):
    """q (ws[3]) at y[:f] by Newton on Phi[rows] = 0 over q^d from the prediction qp (n,)
    with q^i = y[:f] (the stages' own Runge-Kutta sums of the full qd,
    :func:`_stages`: far closer to Phi = 0 than the last solution moved along the last
    R), each step a Newton step by the generated kernels with q^i held (:func:`_step_gen`:
    J, Y and the factor of W = J M^-1 J^T at q, ``refactor``, and R at q,
    :func:`_null_gen`; the first step of f = 1 takes R from the predicted full qd, qdp
    (n,), where it serves, :func:`_velocity_basis`: one ``_null_gen`` less), stopped at
    |Phi| < ``tol`` -- a prediction within it is still corrected once unless |Phi| < 1e-3
    tol, so that q is Newton's to round-off as the generic path's -- or when the step
    reaches round-off. On return (OK) the kernels' work array holds the factorization at
    q, ws[1] R at q and ws[16][0] max|R^d|. A status code."""
    gk, gws, Rp = gen[0], gen[1], gen[9]
    R, q, p = ws[1], ws[3], ws[6]
    indep = part[2]
    n, f = q.shape[0], indep.shape[0]
    for a in range(n):
        q[a] = qp[a]
    for c in range(f):
        q[indep[c]] = y[c]
    e = _residual_gen(gen, q, p)
    it = 0
    size = 0.0
    big = 1.0
    while e >= tol or (it == 0 and e > 1e-3 * tol):
        if it >= NEWTON_ITER:
            return ERR_NEWTON
        if it == 0:  # the span of q: round-off scale of the Newton's stop
            lo, hi = q[0], q[0]
            for a in range(n):
                lo = min(lo, q[a])
                hi = max(hi, q[a])
            size = max(hi - lo, 1e-300)
            big = max(1.0, abs(lo), abs(hi))
        full = _call2(types.int64, gk[1], _ptr(q), _ptr(gws)) == 0  # J, Y, L D L^T at q
        cnt[C_FACT] += 1
        basis = it == 0 and _velocity_basis(part, y, qdp, Rp)
        if basis:
            step = _step_gen(gen, part, q, p, Rp)
        else:
            if _null_gen(gen, part, ws, R) < 0.0:
                return ERR_SINGULAR
            step = _step_gen(gen, part, q, p, R)
        cnt[C_NEWTON] += 1
        it += 1
        if step < tol * 10.0 * max(1.0, size):  # round-off reached
            break
        if full and _rest_gen(gen, part, y, qdp, step, big, basis) < REST * tol:
            break  # |Phi| is below tol: its evaluation would end the loop here
        e = _residual_gen(gen, q, p)
    _call2(types.int64, gk[1], _ptr(q), _ptr(gws))  # the factorization at q
    cnt[C_FACT] += 1
    g = _null_gen(gen, part, ws, R)
    if g < 0.0:
        return ERR_SINGULAR
    ws[16][0] = g
    return OK


@njit(cache=True, _nrt=False, inline="always")
def _kin_gen(part, gen, tol, y, pr, ws, cnt):
    """:func:`_kinematics` on the generated path from the prediction pr = (q, qd) (n,) of
    the full coordinates at y (:func:`_stages`), ``gen`` = (gk, gws, prow (m,), prr (r,),
    yl (2f,), qdd (n,), w (m,), d (n,), X, Rp (n, f), Z (f, f), bound (2,)): the model's
    generated kernels (addresses, :mod:`natcoord.compiled.codegen`) and their work array,
    the kernels' row of every constraint row and of the partition's, the y of the last
    evaluation, the accelerations' array, scratch, R predicted (Rp) and the plan's Newton
    bound (:func:`_rest_gen`). q by
    :func:`_positions_gen`, R there, qd = R qd^i (S c is not formed: :func:`_acc_gen`
    gives qdd whole, with the factorization at q left in gws); at the y of the last
    evaluation nothing is redone. Compiled without reference counting: it allocates
    nothing. (Why not a simplified Newton: the module docstring.)"""
    flags, yl = ws[2], gen[4]
    f = part[2].shape[0]
    if flags[1]:
        same = True
        for c in range(2 * f):
            if y[c] != yl[c]:
                same = False
                break
        if same:
            return OK
    flags[1] = 0
    st = _positions_gen(part, gen, tol, y, pr[0], pr[1], ws, cnt)
    if st != OK:
        return st
    R, qd = ws[1], ws[4]
    for a in range(qd.shape[0]):
        s = 0.0
        for c in range(f):
            s += R[a, c] * y[f + c]
        qd[a] = s
    for c in range(2 * f):
        yl[c] = y[c]
    flags[0], flags[1] = 1, 1
    return OK


@njit(cache=True, inline="always")
def _acc_gen(gen, ws, cnt):
    """qdd (n,) into gen[5] at the q, qd of ws by the generated ``rhs`` kernel with the
    factorization :func:`_kin_gen` left at q: index-1's Eq. (6) (Schur complement of the
    regular M), the same constrained accelerations as Eq. (23) at a consistent (q, qd)."""
    cnt[C_RHS] += 1
    _call4(types.void, gen[0][2], _ptr(ws[3]), _ptr(ws[4]), _ptr(gen[5]), _ptr(gen[1]))


@njit(cache=True, inline="always")
def _kin(con, part, tol, y, pr, ws, cnt, gen):
    """The kinematics at y: :func:`_kinematics`, or on the generated path :func:`_kin_gen`
    from the prediction pr = (q, qd) (n,)."""
    if gen is None:
        return _kinematics(con, part, tol, y, ws, cnt)
    return _kin_gen(part, gen, tol, y, pr, ws, cnt)


@njit(cache=True, inline="always")
def _rhs(con, Msp, frc, part, tol, y, pr, dy, ws, cnt, gen):
    """dy = [qd^i, qdd^i] (2f) at y (``gen``: the generated path from the prediction pr =
    (q, qd) (n,), :func:`_acc_gen`); a status code."""
    st = _kin(con, part, tol, y, pr, ws, cnt, gen)
    if st != OK:
        return st
    f = part[2].shape[0]
    for c in range(f):
        dy[c] = y[f + c]
    if gen is None:
        return _acc(Msp, frc, ws, dy[f:], cnt)
    _acc_gen(gen, ws, cnt)
    qdd, indep = gen[5], part[2]
    for c in range(f):
        dy[f + c] = qdd[indep[c]]
    return OK


@njit(cache=True, _nrt=False)
def _sample(con, Msp, frc, part, tol, y, pr, k, out, ws, cnt, gen):
    """Sample k of out = (Q, QD, QDD, ...) at y: q, qd from the kinematics, qdd = S c + R
    qdd^i from a second evaluation there (``MaggiLoop.state`` then ``accelerations``); on
    the generated path (``gen``) from the prediction pr = (q, qd) (n,), qdd of the
    generated kernel at that q, qd."""
    Q, QD, QDD = out[0], out[1], out[2]
    if gen is not None:
        st = _kin_gen(part, gen, tol, y, pr, ws, cnt)
        if st != OK:
            return st
        _acc_gen(gen, ws, cnt)
        q, qd, qdd = ws[3], ws[4], gen[5]
        for a in range(q.shape[0]):
            Q[k, a], QD[k, a], QDD[k, a] = q[a], qd[a], qdd[a]
        return OK
    st = _kinematics(con, part, tol, y, ws, cnt)
    if st != OK:
        return st
    q, qd = ws[3], ws[4]
    for a in range(q.shape[0]):
        Q[k, a], QD[k, a] = q[a], qd[a]
    st = _kinematics(con, part, tol, y, ws, cnt)
    if st != OK:
        return st
    f = part[2].shape[0]
    qddi = ws[20]
    st = _acc(Msp, frc, ws, qddi, cnt)
    if st != OK:
        return st
    R, Sc = ws[1], ws[5]
    for a in range(R.shape[0]):
        s = Sc[a]
        for c in range(f):
            s += R[a, c] * qddi[c]
        QDD[k, a] = s
    return OK


@njit(cache=True, _nrt=False)
def _post_step(con, part, ctl, y, pr, ws, cnt, gen):
    """After an accepted step (``MaggiLoop.post_step``): the kinematics at the step end y
    (the generated path from the prediction pr = (q, qd) (n,)), re-partition there when max|R^d|
    exceeds ``growth`` R0, then y = [q^i, qd^i] in the new partition; a status code
    (ERR_SINGULAR when the rank of Phi_q changed)."""
    tol, rank_tol, growth = ctl[3], ctl[4], ctl[5]
    st = _kin(con, part, tol, y, pr, ws, cnt, gen)
    if st != OK:
        return st
    gs = ws[16]
    if gs[1] < 0.0:
        gs[1] = max(gs[0], 1.0)
        return OK
    if gs[0] <= growth * gs[1]:
        return OK
    kk, ii, jj, vv, m = con
    rows, dep, indep = part
    q, qd, J, A, rows_all, cols = ws[3], ws[4], ws[7], ws[17], ws[18], ws[19]
    r, f = dep.shape[0], indep.shape[0]
    _jac(kk, ii, jj, vv, q, J)
    if partition(J, rank_tol, A, rows_all, cols) != r:
        return ERR_SINGULAR
    cnt[C_FACT] += 1
    cnt[C_REPART] += 1
    for i in range(r):
        rows[i], dep[i] = rows_all[i], cols[i]
    for c in range(f):
        indep[c] = cols[r + c]
    for c in range(f):
        y[c] = q[indep[c]]
        y[f + c] = qd[indep[c]]
    gs[1] = -1.0
    ws[2][0] = 0  # no predictor right after a partition
    ws[2][1] = 0  # nor kinematics to reuse
    if gen is not None:
        _rows_gen(gen, rows)
    return OK


# ---- the loop ------------------------------------------------------------------------------
@njit(cache=True, _nrt=False, inline="always")
def _rk_sum(x0, h, A, s, K, out):
    """out (N,) = x0 + h sum_{p < s} A[s, p] K[p] (zero weights skipped; per component the
    terms in the order of p)."""
    N = x0.shape[0]
    for a in range(N):
        out[a] = 0.0
    for p in range(s):
        w = A[s, p]
        if w != 0.0:
            for a in range(N):
                out[a] += w * K[p, a]
    for a in range(N):
        out[a] = x0[a] + h * out[a]


@njit(cache=True, _nrt=False, inline="always")
def _rk_sum3(y, qn, qdn, h, A, s, K, Kq, Kqd, ys, qp, qdp):
    """:func:`_rk_sum` of y (N,), qn and qdn (n,) with the stages K, Kq and Kqd in one pass
    over the weights (the same operations per component): three passes took a fifth of
    a stage on a small model."""
    N, n = y.shape[0], qn.shape[0]
    for a in range(N):
        ys[a] = 0.0
    for a in range(n):
        qp[a] = 0.0
        qdp[a] = 0.0
    for p in range(s):
        w = A[s, p]
        if w != 0.0:
            for a in range(N):
                ys[a] += w * K[p, a]
            for a in range(n):
                qp[a] += w * Kq[p, a]
                qdp[a] += w * Kqd[p, a]
    for a in range(N):
        ys[a] = y[a] + h * ys[a]
    for a in range(n):
        qp[a] = qn[a] + h * qp[a]
        qdp[a] = qdn[a] + h * qdp[a]


@njit(cache=True, _nrt=False)
def _stages(mdl, gen, y, h, A, lo, hi, K, ys, ws, cnt, qk):
    """K[s] = f(y + h sum_{p < s} A[s, p] K[p]) for s in lo..hi-1, ``mdl`` = (con, Msp,
    frc, part, tol) as in :func:`run_maggi`; a status code. The generated path (``gen``)
    also keeps the stages of the full q, ``qk`` = (qn, qdn (n,) the full q, qd at y, Kq,
    Kqd (stages, n) the full qd, qdd of every stage (written), pr = (qp, qdp) (n,)
    scratch), and predicts stage s by the same sums: qp = qn + h sum_p A[s, p] Kq[p], whose
    q^i is y_s[:f], and so qdp; their distance from Phi = 0 is the stage's error as a
    Runge-Kutta stage of the full q' = qd, qd' = qdd (DOP853's stages from the sixth on
    have stage order 5: ~1e-8 m where the last solution moved along the last R missed by
    ~1e-3 m)."""
    con, Msp, frc, part, tol = mdl
    qn, qdn, Kq, Kqd, pr = qk
    for s in range(lo, hi):
        if gen is None:
            _rk_sum(y, h, A, s, K, ys)
        else:
            _rk_sum3(y, qn, qdn, h, A, s, K, Kq, Kqd, ys, pr[0], pr[1])
        st = _rhs(con, Msp, frc, part, tol, ys, pr, K[s], ws, cnt, gen)
        if st != OK:
            return st
        if gen is not None:
            qd, qdd = ws[4], gen[5]
            for a in range(qd.shape[0]):
                Kq[s, a], Kqd[s, a] = qd[a], qdd[a]
    return OK


@njit(cache=True, inline="always")
def _step_end(gen, B, qk, s, h, pr1):
    """The generated path's prediction of the full q, qd at the step's end, pr1 = (q, qd)
    (n,): qn + h sum_p B[p] Kq[p] over the first s stages (its q^i is the step's y[:f]),
    and so qd (``qk``: :func:`_stages`)."""
    if gen is not None:
        for x0, Kx, out in ((qk[0], qk[2], pr1[0]), (qk[1], qk[3], pr1[1])):
            _weights(B, Kx, s, out, h)
            for a in range(x0.shape[0]):
                out[a] += x0[a]


@njit(cache=True)
def _weights(W, K, s, out, h):
    """out = h sum_p W[p] K[p] over the first s stages."""
    for a in range(out.shape[0]):
        acc = 0.0
        for p in range(s):
            if W[p] != 0.0:
                acc += W[p] * K[p, a]
        out[a] = h * acc


@njit(cache=True)
def run_maggi(con, Msp, frc, part, ctl, tab, times, y0, q0, out, gen):
    """Integrate y = [q^i, qd^i] over ``times`` (T,) from y0 (2f) at times[0], with q0 (n,)
    the consistent positions there and ``part`` = (rows (r,), dep (r,), indep (f,)) their
    partition (renewed in place). ``con`` = (k, i, j, v, m); ``Msp`` = M's non-zeros (i, j,
    v); ``frc``: :func:`pack_forces`; ``ctl`` = (rtol, atol, h_fixed (> 0: fixed steps),
    newton_tol, rank_tol, repartition_growth); ``tab`` = (A, B, C, E5, E3, expo, dop853,
    Aext (3, 16), Cext, D (4, 16), P (s, 4)): the method's tableau
    (:func:`natcoord.compiled.index1.tableau`), the exponent of the step control and dopri5's dense
    output P (0 rows: none); ``out`` = (Q, QD, QDD (T, n), cnt (N_COUNTERS,), tfail (1,))
    filled in place (tfail: the time of a failure). Returns a status code (0 = ok)."""
    rows, dep, indep = part
    rtol, atol, h_fixed, tol = ctl[0], ctl[1], ctl[2], ctl[3]
    mdl = (con, Msp, frc, part, tol)  # what every evaluation reads
    A, B, C, E5, E3, expo, dop853, Aext, Cext, D, P = tab
    cnt, tfail = out[3], out[4]
    n, m = q0.shape[0], con[4]
    r, f = dep.shape[0], indep.shape[0]
    N = 2 * f
    ws = workspace(n, m, r, f)
    ws[0][:] = q0
    if gen is not None:  # the first R of the generated path (:func:`_null_gen`)
        ws[3][:] = q0
        st = _rates(con, part, y0, ws, cnt)
        if st != OK:
            return st
    T = times.shape[0]
    t, tend = times[0], times[T - 1]
    tfail[0] = t
    y = y0.copy()
    s_st, n_ext = B.shape[0], Aext.shape[0]
    # the full q, qd of the generated path's predictions (:func:`_stages`): at y, the
    # stages' full qd and qdd, a prediction, at the step's end, their continuous extension
    S = s_st + n_ext
    qn, qdn, Kq, Kqd = q0.copy(), np.zeros(n), np.zeros((S, n)), np.zeros((S, n))
    pr, pr1 = (q0.copy(), np.zeros(n)), (np.zeros(n), np.zeros(n))
    Fq, Fqd = np.zeros((3 + D.shape[0], n)), np.zeros((3 + D.shape[0], n))
    qk = (qn, qdn, Kq, Kqd, pr)
    now = (qn, qdn)  # the prediction at y: the solution there
    st = _sample(con, Msp, frc, part, tol, y, now, 0, out, ws, cnt, gen)
    if st != OK:
        return st
    if f == 0:  # no degrees of freedom: kinematics at every sample
        for k in range(1, T):
            tfail[0] = times[k]
            st = _sample(con, Msp, frc, part, tol, y, now, k, out, ws, cnt, gen)
            if st != OK:
                return st
        return OK
    Aall = np.zeros((s_st + n_ext, s_st + n_ext))  # the step's and the extension's stages
    Aall[:s_st, :s_st] = A
    Aall[s_st:, :] = Aext[:, :s_st + n_ext]
    K = np.zeros((s_st + n_ext, N))
    Fd = np.zeros((3 + D.shape[0], N))  # dop853's continuous extension
    qdn[:] = ws[4]
    ys, yn, yu, e5v, e3v = np.zeros(N), np.zeros(N), np.zeros(N), np.zeros(N), np.zeros(N)
    if h_fixed > 0.0:  # equal steps of at most h_fixed landing on every sample
        for k in range(1, T):
            t0, t1 = times[k - 1], times[k]
            nsub = max(1, math.ceil((t1 - t0) / h_fixed - 1e-9))
            hh = (t1 - t0) / nsub
            for i in range(nsub):
                tfail[0] = t0 + i * hh
                st = _stages(mdl, gen, y, hh, Aall, 0, s_st, K, ys, ws, cnt, qk)
                if st != OK:
                    return st
                _weights(B, K, s_st, yn, hh)
                for a in range(N):
                    y[a] += yn[a]
                _step_end(gen, B, qk, s_st, hh, pr1)
                st = _post_step(con, part, ctl, y, pr1, ws, cnt, gen)
                if st != OK:
                    return st
                qn[:] = ws[3]
                qdn[:] = ws[4]
                cnt[C_STEPS] += 1
            tfail[0] = t1
            st = _sample(con, Msp, frc, part, tol, y, now, k, out, ws, cnt, gen)
            if st != OK:
                return st
        return OK
    # adaptive: Hairer's initial step
    st = _rhs(con, Msp, frc, part, tol, y, now, ys, ws, cnt, gen)
    if st != OK:
        return st
    d0, d1 = 0.0, 0.0
    for a in range(N):
        sc = atol + rtol * abs(y[a])
        d0 += (y[a] / sc) ** 2
        d1 += (ys[a] / sc) ** 2
    d0, d1 = math.sqrt(d0 / N), math.sqrt(d1 / N)
    h = stepcontrol.initial_step(d0, d1, tend - t)
    k = 1
    while k < T:
        hh = min(h, tend - t)
        tfail[0] = t
        st = _stages(mdl, gen, y, hh, Aall, 0, s_st, K, ys, ws, cnt, qk)
        if st == ERR_NEWTON:  # the step is too long for the dependent positions
            if stepcontrol.underflow(hh * 1e-4, t):
                return ERR_UNDERFLOW
            cnt[C_REJ] += 1
            h = stepcontrol.STAGE_FAILURE_FACTOR * hh
            continue
        if st != OK:
            return st
        _weights(B, K, s_st, yn, hh)
        _weights(E5, K, s_st, e5v, hh)
        if dop853:
            _weights(E3, K, s_st, e3v, hh)
        e5, e3 = 0.0, 0.0
        for a in range(N):
            yn[a] += y[a]
            sc = atol + rtol * max(abs(y[a]), abs(yn[a]))
            e5 += (e5v[a] / sc) ** 2
            e3 += (e3v[a] / sc) ** 2
        err = stepcontrol.dop853_norm(e5, e3, N, 1.0) if dop853 else stepcontrol.rms_norm(e5, N)
        if not math.isfinite(err):
            return ERR_NONFINITE
        if err > 1.0:
            cnt[C_REJ] += 1
            h = hh * stepcontrol.reject_factor(err, expo)
            if stepcontrol.underflow(h, t):
                return ERR_UNDERFLOW
            continue
        t1 = tend if hh == tend - t else t + hh
        tol_t = stepcontrol.SAMPLE_TOL * max(1.0, abs(t1))
        _step_end(gen, B, qk, s_st, hh, pr1)
        inner = False
        while k < T and times[k] < t1 - tol_t:  # samples inside the step: dense output
            tfail[0] = times[k]
            if dop853 and not inner:
                st = _stages(mdl, gen, y, hh, Aall, s_st, s_st + n_ext, K, ys, ws, cnt, qk)
                if st != OK:
                    return st
                stepcontrol.dense_dop853(y, yn, hh, K, s_st, D, Fd)
                if gen is not None:  # and of the full q, qd: the samples' predictions
                    stepcontrol.dense_dop853(qn, pr1[0], hh, Kq, s_st, D, Fq)
                    stepcontrol.dense_dop853(qdn, pr1[1], hh, Kqd, s_st, D, Fqd)
            inner = True
            x = (times[k] - t) / hh
            if dop853:
                stepcontrol.dense_at(Fd, y, x, yu)
                if gen is not None:
                    stepcontrol.dense_at(Fq, qn, x, pr[0])
                    stepcontrol.dense_at(Fqd, qdn, x, pr[1])
            else:
                stepcontrol.dense_dopri5(K, P, y, hh, x, yu)
                if gen is not None:
                    stepcontrol.dense_dopri5(Kq, P, qn, hh, x, pr[0])
                    stepcontrol.dense_dopri5(Kqd, P, qdn, hh, x, pr[1])
            st = _sample(con, Msp, frc, part, tol, yu, pr, k, out, ws, cnt, gen)
            if st != OK:
                return st
            k += 1
        t = t1
        y[:] = yn
        tfail[0] = t
        st = _post_step(con, part, ctl, y, pr1, ws, cnt, gen)
        if st != OK:
            return st
        qn[:] = ws[3]
        qdn[:] = ws[4]
        cnt[C_STEPS] += 1
        if k < T and times[k] <= t1 + tol_t:
            st = _sample(con, Msp, frc, part, tol, y, now, k, out, ws, cnt, gen)
            if st != OK:
                return st
            k += 1
        h = hh * stepcontrol.accept_factor(err, expo)
    return OK


# ---- Python side ---------------------------------------------------------------------------
def pack(con, M) -> tuple:
    """(con, Msp): the constraint triplets as (k, i, j, v, m) and M (n, n) kg as its
    non-zeros (i, j, v), the arrays :func:`run_maggi` takes (model only)."""
    Mi, Mj = np.nonzero(M)
    return (pack_constraints(con),
            (Mi.astype(np.int64), Mj.astype(np.int64), np.ascontiguousarray(M[Mi, Mj], float)))


def _tab(method: str) -> tuple:
    A, B, C, E5, E3, expo, Aext, Cext, D, _ = tableau(method)
    P = stepcontrol.DOPRI5_P if method == "dopri5" else np.zeros((0, 4))
    return (A, B, C, E5, E3, expo, method == "dop853", Aext, Cext, D, P)


class Steps(NamedTuple):
    """Step control and options of a compiled Maggi run: ``rtol``/``atol`` of adaptive
    steps or a fixed step ``h`` (s; None: adaptive), and the options of
    :class:`natcoord.dynamics.maggi.Maggi` (``newton_tol`` m, ``rank_tol`` relative,
    ``repartition_growth``)."""

    rtol: float = 0.0
    atol: float = 0.0
    h: float | None = None
    newton_tol: float = 1e-13
    rank_tol: float = 1e-9
    repartition_growth: float = 1.5


def generated(con, M, frc, alpha: float = 1.0) -> tuple | None:
    """(kernel addresses, their plan's ``kernel_args``, prow (m,): the kernels' row of each
    constraint row, the plan's Newton bound (hq, gq) (2,) or (-1, -1): none) of index-1's
    generated kernels for the Maggi loop's generated path (:func:`_kin_gen`): the Schur
    plan of a regular M (with its bound, :func:`_rest_gen`), a singular M's regularised
    dense plan with ``alpha`` (:func:`natcoord.compiled.sparsity.dense_plan`); None where
    :func:`natcoord.compiled.codegen.load` declines the model (model only)."""
    from . import codegen, sparsity
    regular = sparsity.is_spd(M)
    plan = sparsity.schur_plan(con, M) if regular else sparsity.dense_plan(con, M, alpha)
    gk = codegen.load(plan, frc, None if regular else M)
    if gk is None:
        return None
    n = M.shape[0]
    bound = np.array(kernels_sparse.newton_bound(plan.kernel_args, n) if regular
                     else (-1.0, -1.0))
    return gk, plan.kernel_args, np.argsort(plan.perm).astype(np.int64), bound


def run(packed, frc, times, y, q, part, method: str, steps: Steps, cnt=None, gen=None):
    """Integrate with the compiled loop by ``method`` from y = [q^i, qd^i] (2f) at times[0]
    with q (n,) the consistent positions there and ``part`` = (rows, dep (r,), indep (f,))
    their partition (``MaggiLoop.init``); returns (Q, QD, QDD) (T, n) at ``times`` (T,) s.
    ``packed``: :func:`pack`; ``frc``: :func:`pack_forces`; ``steps``: a fixed step (s) for
    rk4 or dopri5, else adaptive dop853 or dopri5; ``cnt``: counters added to. Raises
    RuntimeError. ``gen``: :func:`generated` (None: the generic kernels)."""
    rtol, atol, h, newton_tol, rank_tol, repartition_growth = steps
    con, Msp = packed
    n, T = len(q), len(times)
    Q, QD, QDD = np.zeros((T, n)), np.zeros((T, n)), np.zeros((T, n))
    c, tfail = np.zeros(N_COUNTERS), np.zeros(1)
    part = tuple(np.array(x, np.int64) for x in part)
    ctl = (float(rtol), float(atol), 0.0 if h is None else float(h), float(newton_tol),
           float(rank_tol), float(repartition_growth))
    if gen is not None:  # the kernels, their work array, rows, and scratch
        gk, args, prow, bound = gen
        f = len(part[2])
        gen = (gk, kernels_sparse.workspace(args), prow, prow[part[0]].copy(),
               np.zeros(len(y)), np.zeros(n), np.zeros(con[4]), np.zeros(n),
               np.zeros((n, f)), np.zeros((n, f)), np.zeros((f, f)), bound)
    status = run_maggi(con, Msp, frc, part, ctl, _tab(method),
                       np.ascontiguousarray(times, float), np.array(y, float),
                       np.array(q, float), (Q, QD, QDD, c, tfail), gen)
    add_counters(c, cnt)
    check(status, f"maggi {method} at t = {tfail[0]:.6g} s")
    return Q, QD, QDD


def warm_up() -> None:
    """Compile (or load from numba's cache) the loop by tiny runs, adaptive and fixed-step:
    a particle on a unit circle under gravity (x dependent, y independent)."""
    con, frc = warm_up_model()
    packed = pack(con, np.eye(2))
    q, part = np.array([0.8, -0.6]), ([0], [0], [1])
    for gen in (None, generated(con, np.eye(2), frc)):  # both paths
        for method, h in (("dop853", None), ("dopri5", None), ("rk4", 0.005),
                          ("dopri5", 0.005)):
            run(packed, frc, np.linspace(0.0, 0.02, 3), np.array([-0.6, 0.0]), q, part,
                method, Steps(rtol=1e-6, atol=1e-8, h=h), gen=gen)


drop_stale_cache(globals(), __name__, (kernels_general, kernels_sparse, stepcontrol))
