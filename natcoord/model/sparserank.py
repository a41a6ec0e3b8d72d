"""Sparse rank certificates: the cheap first answer to "has Phi_q full row rank?".

A large mechanism's Jacobian Phi_q (m, n) has a few entries a row, but an SVD of it costs
O(m n min(m, n)): minutes for the 4,100 coordinates of a 512-four-bar. Most questions asked
of it (the model check, the diagnostics, the initial velocities) have a quick answer when its
rows are independent, which they are away from singular positions. :func:`full_row_rank`
certifies that in time linear in the non-zeros of a banded Phi_q; when it cannot (a
redundant row, a singular or nearly singular position), the caller takes its dense,
rank-revealing path, whose answers and messages then stay exactly what they were.

The certificate: with G = A A^T (m, m), sparse and symmetric,
``sigma_min(A)^2 = lambda_min(G)`` (shift-invert Lanczos on a sparse LU of G) and
``sigma_max(A)^2 <= ||G||_1``; the rows are certified independent when
``sigma_min > CERT_RTOL sigma_max``. CERT_RTOL (1e-6) is 10^4 above the dense rank
tolerance (1e-10 on the singular values), so a certified matrix has full rank by the dense
test too, and G's own round-off (1e-16 of ||G||) stays far below the eigenvalue tested.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .drivers import ConstraintSystem

CERT_RTOL = 1e-6  # certified: sigma_min > CERT_RTOL * sigma_max
SPARSE_FROM = 256  # coordinates: a smaller model keeps the dense path (milliseconds there),
# whose answers its results and references were made with, bit for bit


def large(n: int) -> bool:
    """Whether a model of n coordinates takes the sparse shortcuts (:data:`SPARSE_FROM`)."""
    return n >= SPARSE_FROM


def jacobian(cs: ConstraintSystem, q: np.ndarray, t: float = 0.0) -> sp.csr_matrix:
    """Phi_q (m_all, n) at q (n,), t as a sparse matrix (driver rows after the constraint
    rows): the same entries as ``cs.jacobian(q, t)``, duplicates summed."""
    c = cs.con
    sel = c.i < c.n
    qh = np.append(np.asarray(q, float), 1.0)
    J = sp.csr_matrix((c.v[sel] * qh[c.j[sel]], (c.k[sel], c.i[sel])), shape=(c.m, c.n))
    if cs.k:
        J = sp.vstack([J, sp.csr_matrix(cs._coef(t)[0][:, :-1])], format="csr")
    return J


def full_row_rank(A, rtol: float = CERT_RTOL) -> bool:
    """True when the rows of A (m, n) are certified independent (see the module); False
    means "not certified" (dependent, nearly so, more rows than columns, or fewer columns
    than :data:`SPARSE_FROM`): ask the dense rank-revealing path."""
    A = sp.csr_matrix(A, dtype=float)
    m, n = A.shape
    if not large(n):
        return False  # a small model: the dense path answers
    if m == 0:
        return True
    if m > n:
        return False
    G = (A @ A.T).tocsc()
    top = float(abs(G).sum(axis=0).max())  # ||G||_1 >= lambda_max(G)
    if not top > 0.0:
        return False
    if m <= 2:
        low = float(np.linalg.eigvalsh(G.toarray())[0])
    else:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # SuperLU's "matrix is exactly singular"
                low = float(spla.eigsh(G, k=1, sigma=0.0, which="LM", v0=np.ones(m),
                                       return_eigenvectors=False, tol=1e-8)[0])
        except (RuntimeError, spla.ArpackError, spla.ArpackNoConvergence):
            return False  # G singular (a dependent row) or no convergence: not certified
    return bool(low > (rtol * rtol) * top)


def certified(cs: ConstraintSystem, q: np.ndarray, t: float = 0.0, *,
              rows: int | None = None, extra: np.ndarray | None = None):
    """The sparse Phi_q at q, t (its first ``rows`` rows; ``extra`` (k, n) stacked below)
    when its rows are certified independent (:func:`full_row_rank`), else None: at once,
    with nothing sparse built, for a model under :data:`SPARSE_FROM` coordinates."""
    if not large(cs.con.n):
        return None
    A = jacobian(cs, q, t)[slice(rows)]
    if extra is not None:
        A = sp.vstack([A, sp.csr_matrix(extra)], format="csr")
    return A if full_row_rank(A) else None


def min_norm_solve(A, b: np.ndarray) -> np.ndarray:
    """The minimum-norm x of A x = b for A (m, n) of independent rows (certify first), by a
    sparse LU of the augmented system [[I, A^T], [A, 0]] [x; y] = [0; b] (conditioned like
    A, not like A A^T)."""
    A = sp.csr_matrix(A, dtype=float)
    m, n = A.shape
    K = sp.bmat([[sp.eye(n), A.T], [A, None]], format="csc")
    return spla.splu(K).solve(np.concatenate([np.zeros(n), np.asarray(b, float)]))[:n]
