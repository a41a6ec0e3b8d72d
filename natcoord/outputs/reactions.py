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

All three are one complete orthogonal factorization of ``Phi_q^T`` (QR with column pivoting,
then a QR of the leading rows): no pseudo-inverse, no SVD. Multipliers are always returned
for the *original* rows, so ``Phi_q^T lambda = F - M qdd`` holds for every method and the
methods differ only by a self-equilibrating set.

Units: lambda_k has units of force / (units of row k per metre): N / m for a distance row
``|d|^2 - L^2`` (length dimension 2), N for a linear row in point coordinates (dimension 1),
N m for a row between unit vectors (dimension 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, solve_triangular

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


def _cod(A: np.ndarray, rtol: float):
    """Complete orthogonal factorization A[:, P] = Q1 T1^T Z1^T of A (n, m), rank r.

    Returns (Q1 (n, r), T1 (r, r) upper, Z (m, m) orthogonal, P (m,), r).
    """
    n, m = A.shape
    if m == 0:
        return np.zeros((n, 0)), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros(0, int), 0
    Q, R, P = qr(A, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    r = int(np.count_nonzero(d > rtol * d[0])) if d.size and d[0] > 0 else 0
    Z, T = qr(R[:r, :].T, mode="full")  # R1^T = Z T, so R1 = T1^T Z1^T
    return Q[:, :r], T[:r, :r], Z, P, r


def left_null_space(Phi_q: np.ndarray, *, rtol: float = RANK_RTOL) -> tuple[np.ndarray, int]:
    """Orthonormal basis N (m, m - r) of ker Phi_q^T and the rank r of Phi_q (m, n)."""
    _, _, Z, P, r = _cod(np.asarray(Phi_q, float).T, rtol)
    N = np.zeros((Phi_q.shape[0], Phi_q.shape[0] - r))
    N[P] = Z[:, r:]
    return N, r


def determined_rows(N: np.ndarray, tol: float = DETERMINED_TOL) -> np.ndarray:
    """Eq. (61): rows whose multiplier no self-equilibrating set touches, (m,) bool.

    ``N`` should be orthonormal (as :func:`left_null_space` returns it), so that ``tol`` is
    relative.
    """
    return np.sum(np.abs(N), axis=1) <= tol


def weighted(Phi_q: np.ndarray, f: np.ndarray, w: np.ndarray | None = None, *,
             rtol: float = RANK_RTOL, det_tol: float = DETERMINED_TOL) -> Reactions:
    """Weighted minimum-norm multipliers, Eq. (75).

    Solves ``(Phi_q^T W) mu = f`` for the minimum-norm ``mu`` and returns ``lam = W mu``,
    the multipliers of the original rows (Phi_q^T lam = f). Equivalently lam minimises
    ``sum((lam / w)**2)``: a large weight makes a row's multiplier cheap, so stiff members
    carry the self-equilibrating share.

    Parameters
    ----------
    Phi_q : (m, n)   constraint Jacobian of the original rows
    f : (n,)         F - M qdd, the constraint resultant, N (N m on unit-vector coordinates)
    w : (m,) > 0     row weights, diagonal of W; None for the plain minimum norm
    """
    Phi_q = np.asarray(Phi_q, float)
    m = Phi_q.shape[0]
    w = np.ones(m) if w is None else np.asarray(w, float)
    if w.shape != (m,) or np.any(~np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"weights must be {m} positive finite numbers, got {w!r}")
    f = np.asarray(f, float)
    Q1, T1, Z, P, r = _cod(Phi_q.T * w, rtol)
    mu_p = Z[:, :r] @ solve_triangular(T1, Q1.T @ f, trans="T", lower=False)
    lam = np.zeros(m)
    lam[P] = w[P] * mu_p
    N = np.zeros((m, m - r))
    N[P] = w[P, None] * Z[:, r:]  # ker(Phi_q^T) = W ker(Phi_q^T W)
    if m > r:
        N, _ = np.linalg.qr(N)
    resid = float(np.max(np.abs(Phi_q.T @ lam - f), initial=0.0))
    return Reactions(lam, N, determined_rows(N, det_tol), r, resid, w)


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
def resultant(model, t: float, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """F - M qdd (n,), the constraint resultant Phi_q^T lambda of Eq. (54)."""
    return model.forces(t, q, qd) - model.M @ qdd


def along(model, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
          w: np.ndarray | None = None) -> np.ndarray:
    """Weighted minimum-norm multipliers (T, m_all) along samples t (T,), q, qd, qdd (T, n)
    (driver rows after the m constraint rows).

    ``w`` (m,) or (T, m): weights of the constraint rows (None: plain minimum norm); driver
    rows weigh 1.
    """
    con = ConstraintSystem(model)
    T = len(t)
    lam = np.zeros((T, con.m))
    W = None
    if w is not None:
        W = np.ones((T, con.m))
        W[:, :model.m] = np.broadcast_to(np.asarray(w, float), (T, model.m))
    for k in range(T):
        Jq = con.jacobian(q[k], t[k])
        f = resultant(model, t[k], q[k], qd[k], qdd[k])
        lam[k] = weighted(Jq, f, None if W is None else W[k]).lam
    return lam


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
