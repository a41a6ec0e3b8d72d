"""Constraint reactions with redundant constraints (García de Jalón & Gutiérrez-López,
Sections 3.2-3.6).

The resultant of the constraint forces is always determined when the accelerations are
(Eq. (54)):

    Phi_q^T lambda = F - M qdd                      Phi_q (m, n), lambda (m,)

but with redundant constraints (rank Phi_q = r < m) every ``lambda + N alpha`` with
``N`` (m, m - r) a basis of ker Phi_q^T is an equally valid answer: ``Phi_q^T N alpha`` is
a set of *self-equilibrating* constraint forces (Eq. (60)). This module picks one:

* :func:`min_norm`        the minimum Euclidean norm lambda (Eq. (70): lambda ⊥ ker Phi_q^T);
* :func:`unit_invariant`  the minimum norm after each row is made non-dimensional, so the
                          answer does not depend on the length unit (Section 3.5, Eq. (74));
* :func:`weighted`        the minimum norm of the weighted constraints W Phi = 0 (Eq. (75)),
                          with W from the stiffness of the members (Eqs. (94), (115)) so the
                          answer is the one the flexible system would carry.

All three are one singular value decomposition of ``W Phi_q`` (the rank counts the singular
values above RANK_RTOL of the largest): the minimum-norm solution and an orthonormal basis
of the null space come from the same factors. :func:`solve` factors T samples at once
(numpy's stacked LAPACK loop, no Python call per sample); :func:`weighted` and
:func:`left_null_space` are its one-sample case. Multipliers are always returned for the
*original* rows, so ``Phi_q^T lambda = F - M qdd`` holds for every method and the methods
differ only by a self-equilibrating set.

Units: lambda_k has units of force / (units of row k per metre): N / m for a distance row
``|d|^2 - L^2`` (length dimension 2), N for a linear row in point coordinates (dimension 1),
N m for a row between unit vectors (dimension 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from ..errors import ExistenceError
from ..model.drivers import ConstraintSystem

RANK_RTOL = 1e-10  # relative to the largest pivot of Phi_q^T
DETERMINED_TOL = 1e-8  # on the rows of an orthonormal N (Eq. (61) uses 1e-10 on any N)


@dataclass(frozen=True)
class Reactions:
    """Multipliers chosen among the solutions of Phi_q^T lambda = F - M qdd.

    Attributes
    ----------
    lam : (m,) float          multipliers of the original (unweighted) rows
    N : (m, m - rank) float   orthonormal basis of ker Phi_q^T (self-equilibrating sets)
    determined : (m,) bool    rows outside every self-equilibrating set (Eq. (61)): their
                              multiplier is the same for every method
    rank : int                numerical rank of Phi_q
    residual : float          max |Phi_q^T lam - (F - M qdd)|, N; large means F - M qdd is
                              not a constraint resultant (wrong accelerations)
    weights : (m,) float      row weights w of W Phi = 0 used for the minimum norm
    """

    lam: np.ndarray
    N: np.ndarray
    determined: np.ndarray
    rank: int
    residual: float
    weights: np.ndarray

    @property
    def redundant(self) -> int:
        """Number of redundant rows, m - rank."""
        return len(self.lam) - self.rank


@dataclass(frozen=True)
class ReactionsAlong:
    """:class:`Reactions` at T samples; ``at(k)`` is sample k's.

    Attributes
    ----------
    lam : (T, m) float        multipliers of the original rows
    null : (T, m, kmax) float columns ``:m - rank[k]`` of ``null[k]`` an orthonormal basis of
                              ker Phi_q^T at sample k, the rest zero (kmax = m - min rank)
    rank : (T,) int
    residual : (T,) float     max |Phi_q^T lam - f| per sample, N
    weights : (T, m) float
    """

    lam: np.ndarray
    null: np.ndarray
    rank: np.ndarray
    residual: np.ndarray
    weights: np.ndarray

    def at(self, k: int, det_tol: float = DETERMINED_TOL) -> Reactions:
        N = self.null[k][:, :self.lam.shape[1] - int(self.rank[k])]
        return Reactions(self.lam[k], N, determined_rows(N, det_tol), int(self.rank[k]),
                         float(self.residual[k]), self.weights[k])


def solve(Phi_q: np.ndarray, f: np.ndarray, w: np.ndarray | None = None, *,
          rtol: float = RANK_RTOL) -> ReactionsAlong:
    """Weighted minimum-norm multipliers (Eq. (75)) at T samples at once.

    Solves ``(Phi_q^T W) mu = f`` for the minimum-norm ``mu`` and returns ``lam = W mu``,
    the multipliers of the original rows (Phi_q^T lam = f). Equivalently lam minimises
    ``sum((lam / w)**2)``: a large weight makes a row's multiplier cheap, so stiff members
    carry the self-equilibrating share. The rank may differ between samples (a singular
    position); each sample's solution uses its own.

    Parameters
    ----------
    Phi_q : (T, m, n)   constraint Jacobians of the original rows
    f : (T, n)          F - M qdd, the constraint resultants, N (N m on unit-vector
                        coordinates)
    w : (m,) or (T, m) > 0   row weights, diagonal of W; None for the plain minimum norm
    """
    Phi_q, f = np.asarray(Phi_q, float), np.asarray(f, float)
    T, m, n = Phi_q.shape
    W = np.ones((T, m)) if w is None else np.broadcast_to(np.asarray(w, float), (T, m))
    if np.any(~np.isfinite(W)) or np.any(W <= 0):
        raise ValueError(f"weights must be {m} positive finite numbers, got {w!r}")
    if m == 0 or n == 0:
        return ReactionsAlong(np.zeros((T, m)), np.broadcast_to(np.eye(m), (T, m, m)).copy(),
                              np.zeros(T, int), np.max(np.abs(f), 1, initial=0.0), W)
    # W Phi_q = U diag(s) Vh; Phi_q^T W = Vh^T diag(s) U^T, so mu = U diag(1/s) Vh f and
    # ker(Phi_q^T W) is spanned by U's columns past the rank
    U, s, Vh = np.linalg.svd(W[:, :, None] * Phi_q, full_matrices=m > n)
    big = s > rtol * s[:, :1]
    rank = np.count_nonzero(big, 1)
    inv = np.where(big, 1.0 / np.where(big, s, 1.0), 0.0)
    mu = np.einsum("tmr,tr->tm", U[:, :, :s.shape[1]], inv * np.einsum("trn,tn->tr", Vh, f))
    lam = W * mu
    kmax = m - int(rank.min(initial=m))
    null = np.zeros((T, m, kmax))
    for r in np.unique(rank):  # ker(Phi_q^T) = W ker(Phi_q^T W), made orthonormal again
        at = rank == r
        N = W[at][:, :, None] * U[at][:, :, r:]
        if w is not None and r < m:
            N = np.linalg.qr(N)[0]
        null[at, :, :m - r] = N
    resid = np.max(np.abs(np.einsum("tmn,tm->tn", Phi_q, lam) - f), 1)
    return ReactionsAlong(lam, null, rank, resid, W)


def left_null_space(Phi_q: np.ndarray, *, rtol: float = RANK_RTOL) -> tuple[np.ndarray, int]:
    """Orthonormal basis N (m, m - r) of ker Phi_q^T and the rank r of Phi_q (m, n)."""
    Phi_q = np.asarray(Phi_q, float)
    r = solve(Phi_q[None], np.zeros((1, Phi_q.shape[1])), rtol=rtol).at(0)
    return r.N, r.rank


def determined_rows(N: np.ndarray, tol: float = DETERMINED_TOL) -> np.ndarray:
    """Eq. (61): rows whose multiplier no self-equilibrating set touches, (m,) bool.

    ``N`` should be orthonormal (as :func:`left_null_space` returns it), so that ``tol`` is
    relative.
    """
    return np.sum(np.abs(N), axis=1) <= tol


def weighted(Phi_q: np.ndarray, f: np.ndarray, w: np.ndarray | None = None, *,
             rtol: float = RANK_RTOL, det_tol: float = DETERMINED_TOL) -> Reactions:
    """Weighted minimum-norm multipliers (Eq. (75)) at one sample: :func:`solve`'s.

    Parameters
    ----------
    Phi_q : (m, n)   constraint Jacobian of the original rows
    f : (n,)         F - M qdd, the constraint resultant, N (N m on unit-vector coordinates)
    w : (m,) > 0     row weights, diagonal of W; None for the plain minimum norm
    """
    Phi_q = np.asarray(Phi_q, float)
    m = Phi_q.shape[0]
    if w is not None and np.shape(w) != (m,):
        raise ValueError(f"weights must be {m} positive finite numbers, got {w!r}")
    return solve(Phi_q[None], np.asarray(f, float)[None], None if w is None else
                 np.asarray(w, float)[None], rtol=rtol).at(0, det_tol)


def min_norm(Phi_q: np.ndarray, f: np.ndarray, *, rtol: float = RANK_RTOL) -> Reactions:
    """Minimum Euclidean norm multipliers (Eq. (70)); the unique ones if rank Phi_q = m."""
    return weighted(Phi_q, f, None, rtol=rtol)


def unit_scales(length_dim: np.ndarray, length: float = 1.0) -> np.ndarray:
    """Row scales ``length**-length_dim`` (m,) that make every row non-dimensional.

    ``length`` is a characteristic length of the model *in the model's units* (e.g. 1.0 for
    a 1 m model built in metres, 1000.0 for the same model in millimetres).
    """
    return float(length) ** -np.asarray(length_dim, float)


def unit_invariant(Phi_q: np.ndarray, f: np.ndarray, *, length_dim: np.ndarray | None = None,
                   length: float = 1.0, row_scales: np.ndarray | None = None,
                   rtol: float = RANK_RTOL) -> Reactions:
    """Minimum norm of the non-dimensional rows (Section 3.5): independent of length units.

    Give either ``row_scales`` (m,) (e.g. the paper's 1/L1^2, 1/(k L1), 1/L2^2 for the
    five-bar) or ``length_dim`` (m,) (``QuadraticConstraints.length_dim``) with a
    characteristic ``length``. Every scaled row then has the same dimension, the unit-change
    matrix H1 is a multiple of the identity (Eq. (74)) and the forces do not depend on the
    unit.
    """
    if row_scales is None:
        if length_dim is None:
            raise ValueError("unit_invariant needs row_scales or length_dim")
        row_scales = unit_scales(length_dim, length)
    return weighted(Phi_q, f, np.abs(np.asarray(row_scales, float)), rtol=rtol)


# ---- weights from stiffness (Eqs. (93)-(94), (113)-(115)) ---------------------------------
def stiffness_weight(k: float, lever: float) -> float:
    """Weight of a row whose multiplier lambda loads a spring of stiffness ``k`` with the
    generalized force ``lever * lambda``: ``w = sqrt(k) / lever``.

    The minimum of sum((lam / w)^2) is then the minimum of the complementary energy
    sum(s^2 / k) / 2 of the spring forces s: Menabrea's theorem, the flexible answer.

    * distance row ``|d|^2 - L^2`` with axial stiffness k (N/m): lever ``2 L`` (axial force
      ``2 L lambda``), ``w = sqrt(k) / (2 L)`` (Eq. (94), w7 and w8);
    * linear row whose multiplier times ``L`` is the moment on a torsion spring k (N m/rad):
      lever ``L``, ``w = sqrt(k) / L`` (Eq. (94), w3 and w5).
    """
    if k <= 0 or lever <= 0:
        raise ValueError(f"stiffness and lever must be positive, got k={k}, lever={lever}")
    return float(np.sqrt(k) / lever)


def stiffness_weights(m: int, springs: Mapping[int, tuple[float, float]],
                      default: float = 1.0) -> np.ndarray:
    """Diagonal of W (m,) from ``{row: (stiffness, lever)}``; other rows get ``default``.

    Rows whose multiplier is determined do not depend on their weight, so the default only
    matters for undetermined rows that have no stiffness data.
    """
    w = np.full(m, float(default))
    for row, (k, lever) in springs.items():
        w[row] = stiffness_weight(k, lever)
    return w


# ---- model-level helpers ----------------------------------------------------------------
def resultant(model, t, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """F - M qdd, the constraint resultant Phi_q^T lambda of Eq. (54): (n,) at one sample
    t, q, qd, qdd (n,), or (T, n) along samples t (T,), q, qd, qdd (T, n)."""
    if np.ndim(q) == 1:
        return model.forces(t, q, qd) - model.M @ qdd
    if any(getattr(model, k, ()) for k in ("torques", "springs", "body_forces")):
        F = np.array([model.forces(*x) for x in zip(t, q, qd, strict=True)])
    else:
        F = np.broadcast_to(model.Q0, np.shape(q))
    return F - qdd @ model.M.T


CHUNK = 1 << 21  # entries of W Phi_q factored at once (bounds the memory of the factors)


def along_all(model, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
              w: np.ndarray | None = None, *, rtol: float = RANK_RTOL,
              unique: tuple[np.ndarray, np.ndarray] | None = None) -> ReactionsAlong:
    """Weighted minimum-norm reactions along samples t (T,), q, qd, qdd (T, n) (driver rows
    after the m constraint rows), factored by :func:`solve` a chunk of samples at a time.

    ``w`` (m,) or (T, m): weights of the constraint rows (None: plain minimum norm); driver
    rows weigh 1. ``unique`` (lam (T, m_all), mask (T,) bool): multipliers already known
    to be the unique ones at the masked samples (every row independent there, e.g. the
    sparse Schur path's, :attr:`natcoord.dynamics.forward.Solution.unique`): those samples
    take them as they are (the same for every weighting: rank m_all, no null space; only
    their residual is evaluated, sparsely), the others are factored.
    """
    con = ConstraintSystem(model)
    T = len(t)
    W = None
    if w is not None:
        W = np.ones((T, con.m))
        W[:, :model.m] = np.broadcast_to(np.asarray(w, float), (T, model.m))
    known = np.zeros(T, bool) if unique is None else np.asarray(unique[1], bool)
    rest = np.flatnonzero(~known)
    step = max(1, CHUNK // max(1, con.m * max(con.m, con.n)))
    parts = []
    with threadpool_limits(1, user_api="blas"):  # threads on small matrices: 6x slower
        for a in range(0, len(rest), step):
            b = rest[a:a + step]
            parts.append(solve(con.jacobian(q[b], t[b]), resultant(model, t[b], q[b], qd[b],
                                                                   qdd[b]),
                               None if W is None else W[b], rtol=rtol))
    kmax = max((p.null.shape[2] for p in parts), default=0)
    out = ReactionsAlong(np.zeros((T, con.m)), np.zeros((T, con.m, kmax)),
                         np.full(T, con.m), np.zeros(T),
                         np.ones((T, con.m)) if W is None else W)
    for a, p in zip(range(0, len(rest), step), parts, strict=True):
        b = rest[a:a + step]
        out.lam[b], out.rank[b], out.residual[b] = p.lam, p.rank, p.residual
        out.null[b, :, :p.null.shape[2]] = p.null
    if known.any():
        k = np.flatnonzero(known)
        out.lam[k] = np.asarray(unique[0], float)[k]
        out.residual[k] = _residual(model, con, t[k], q[k], qd[k], qdd[k], out.lam[k])
    return out


def _residual(model, con: ConstraintSystem, t, q, qd, qdd, lam) -> np.ndarray:
    """max |Phi_q^T lam - (F - M qdd)| (T,) along samples, from the constraint triplets and
    a sparse M (cost linear in the non-zeros, no (m, n) matrix)."""
    c = con.con
    sel = c.i < c.n
    i, j, k, v = c.i[sel], c.j[sel], c.k[sel], c.v[sel]
    S = sp.csr_matrix((np.ones(len(i)), (i, np.arange(len(i)))), shape=(c.n, len(i)))
    qh = np.concatenate([q, np.ones((len(q), 1))], 1)
    g = np.zeros((len(q), c.n))  # Phi_q^T lam: entry (k, i) of Phi_q is sum v qh_j
    step = max(1, CHUNK // max(1, len(i)))
    for a in range(0, len(q), step):
        b = slice(a, a + step)
        g[b] = (S @ (v * qh[b][:, j] * lam[b][:, k]).T).T
    if con.k:
        g += np.einsum("tkn,tk->tn", con._coef(t)[0][..., :-1], lam[:, con.m0:])
    if any(getattr(model, k, ()) for k in ("torques", "springs", "body_forces")):
        F = np.array([model.forces(*x) for x in zip(t, q, qd, strict=True)])
    else:
        F = np.broadcast_to(model.Q0, np.shape(q))
    f = F - (sp.csr_matrix(model.M) @ qdd.T).T
    return np.max(np.abs(g - f), 1, initial=0.0)


def along(model, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
          w: np.ndarray | None = None) -> np.ndarray:
    """Weighted minimum-norm multipliers (T, m_all) along samples (see :func:`along_all`)."""
    return along_all(model, t, q, qd, qdd, w).lam


def check_existence(M: np.ndarray, Phi_q: np.ndarray, *, rtol: float = 1e-10) -> None:
    """Raise ExistenceError if ker M ∩ ker Phi_q ≠ {0} (Eq. (37)).

    A motion allowed by the constraints that carries no kinetic energy (a massless body free
    to move) leaves the accelerations undetermined, and with them the reactions.
    """
    M, Phi_q = np.asarray(M, float), np.asarray(Phi_q, float)
    n = M.shape[0]
    A = np.vstack([M / max(np.max(np.abs(M)), 1e-300), Phi_q / max(np.max(np.abs(Phi_q),
                                                                         initial=0.0), 1e-300)])
    s = np.linalg.svd(A, compute_uv=False)
    r = int(np.count_nonzero(s > rtol * s[0]))
    if r < n:
        _, _, Vt = np.linalg.svd(A)
        v = Vt[-1]
        worst = np.argsort(-np.abs(v))[:4]
        raise ExistenceError(
            f"rank [M; Phi_q] = {r} < n = {n}: {n - r} motion(s) allowed by the constraints "
            f"carry no kinetic energy (coordinates {sorted(worst.tolist())} move most); give "
            "the bodies involved mass or constrain them (ker M ∩ ker Phi_q must be {0})")
