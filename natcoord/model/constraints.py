"""Constraint equations held as one sparse quadratic form per row.

Every natural-coordinate constraint is at most quadratic in q, so all of them share one
representation over the extended vector ``qh = [q, 1]`` (n + 1,):

    Phi_k(q) = 1/2 qh^T H_k qh,     H_k symmetric,

which carries the quadratic, linear (column n) and constant (entry (n, n)) parts alike.
All rows of all kinds are stored as COO triplets ``(k, i, j, v)``; the Jacobian, the
constraint values and the velocity-dependent acceleration term are then three vectorised
passes over the triplets, with no Python object per equation at run time:

    Phi_q[k, i] = sum_j H_k[i, j] qh[j]                  (m, n)
    Phi_q_dot qd = qd^T H_k qd   (qh_dot = [qd, 0])      (m,)

so the acceleration right-hand side is ``c = -qd^T H_k qd`` (rheonomic terms are added by
the drivers). Derivatives are exact by construction; tests compare them with finite
differences anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# cross(a, b) = a^T S b in 2-D
S2 = np.array([[0.0, 1.0], [-1.0, 0.0]])
ROUNDOFF = 1e-14  # relative size of a coefficient taken for round-off (see _emit)


class ConstraintBuilder:
    """Collects constraint rows at build time (a Python loop here is fine: once per model).

    Linear maps are (d, n + 1) arrays ``A`` with ``A @ qh`` a vector expression (a point,
    a direction); only their non-zero columns are kept.
    """

    def __init__(self, n: int):
        self.n = n
        self.k: list[np.ndarray] = []
        self.i: list[np.ndarray] = []
        self.j: list[np.ndarray] = []
        self.v: list[np.ndarray] = []
        self.labels: list[str] = []
        self.scale: list[float] = []  # length dimension of the row: 0, 1 or 2 (for units)

    @property
    def m(self) -> int:
        return len(self.labels)

    def _emit(self, rows_i, rows_j, vals):
        """One row's triplets, its round-off dropped: a coefficient below ROUNDOFF of the
        largest of its kind in the row (quadratic, or linear in q) is the trace of an exact
        zero (a direction at 90 degrees, a rotated frame) and goes, so that the row's
        structure is its exact one (build drops the zeros)."""
        ii, jj = np.asarray(rows_i, dtype=np.int64), np.asarray(rows_j, dtype=np.int64)
        vv = np.array(vals, dtype=float)
        for kind in ((ii < self.n) & (jj < self.n), (ii < self.n) != (jj < self.n)):
            big = np.max(np.abs(vv[kind]), initial=0.0)
            vv[kind & (np.abs(vv) < ROUNDOFF * big)] = 0.0
        self.k.append(np.full(len(vv), self.m, dtype=np.int64))
        self.i.append(ii)
        self.j.append(jj)
        self.v.append(vv)

    def linear(self, a: np.ndarray, label: str, length_dim: int = 1) -> int:
        """Add ``a @ qh = 0`` for a (n + 1,) row ``a``; returns the row index."""
        nz = np.flatnonzero(a)
        n = self.n
        lin = nz[nz < n]
        # 1/2 qh^T H qh with H[i, n] = H[n, i] = a_i and H[n, n] = 2 a_n gives a @ qh
        ii = np.concatenate([lin, np.full(len(lin), n)])
        jj = np.concatenate([np.full(len(lin), n), lin])
        vv = np.concatenate([a[lin], a[lin]])
        if a[n] != 0.0:
            ii, jj, vv = np.append(ii, n), np.append(jj, n), np.append(vv, 2.0 * a[n])
        return self.row(ii, jj, vv, label, length_dim)

    def bilinear(self, A: np.ndarray, K: np.ndarray, B: np.ndarray, const: float, label: str,
                 length_dim: int = 2) -> int:
        """Add ``(A qh)^T K (B qh) + const = 0``; A (d, n+1), K (d, d), B (d, n+1)."""
        ca, cb = np.flatnonzero(np.any(A, 0)), np.flatnonzero(np.any(B, 0))
        Ksub = A[:, ca].T @ K @ B[:, cb]  # (|ca|, |cb|)
        ii, jj = np.meshgrid(ca, cb, indexing="ij")
        ii, jj, vv = ii.ravel(), jj.ravel(), Ksub.ravel()
        n = self.n
        # H = Ksym + Ksym^T so that 1/2 qh^T H qh = qh^T Ksym qh
        rows_i = np.concatenate([ii, jj, [n]])
        rows_j = np.concatenate([jj, ii, [n]])
        vals = np.concatenate([vv, vv, [2.0 * const]])
        return self.row(rows_i, rows_j, vals, label, length_dim)

    def row(self, rows_i, rows_j, vals, label: str, length_dim: int) -> int:
        """Add ``1/2 qh^T H qh = 0`` from H's triplets (i, j, v) over qh (n + 1), both
        halves of the symmetric H; returns the row index."""
        self._emit(rows_i, rows_j, vals)
        self.labels.append(label)
        self.scale.append(length_dim)
        return self.m - 1

    def dot(self, A: np.ndarray, B: np.ndarray, value: float, label: str,
            length_dim: int = 2) -> int:
        """Add ``(A qh) . (B qh) - value = 0`` for maps A, B (d, n + 1); returns the row."""
        return self.bilinear(A, np.eye(A.shape[0]), B, -float(value), label, length_dim)

    def linear_rows(self, C: np.ndarray, label: str, length_dim: int = 1) -> list[int]:
        """Add ``C qh = 0`` row by row for a map C (d, n + 1); returns the d row indices."""
        axes = "xyz" if C.shape[0] <= 3 else range(C.shape[0])
        return [self.linear(C[a], f"{label}: {ax}", length_dim) for a, ax in
                zip(range(C.shape[0]), axes, strict=False)]

    def build(self) -> QuadraticConstraints:
        k = np.concatenate(self.k) if self.k else np.zeros(0, np.int64)
        i = np.concatenate(self.i) if self.i else np.zeros(0, np.int64)
        j = np.concatenate(self.j) if self.j else np.zeros(0, np.int64)
        v = np.concatenate(self.v) if self.v else np.zeros(0)
        keep = v != 0.0
        return QuadraticConstraints(self.n, self.m, k[keep], i[keep], j[keep], v[keep],
                                    tuple(self.labels), np.array(self.scale, dtype=int))


@dataclass(frozen=True)
class QuadraticConstraints:
    """m constraint rows over n coordinates as symmetric quadratic forms in ``[q, 1]``.

    Attributes
    ----------
    n, m : int
    k, i, j : (nnz,) int     row, and entry (i, j) of H_k over qh (n + 1)
    v : (nnz,) float         value of H_k[i, j]
    labels : tuple[str]      one human-readable name per row
    length_dim : (m,) int    length dimension of each row (0, 1, 2), for unit scaling
    """

    n: int
    m: int
    k: np.ndarray
    i: np.ndarray
    j: np.ndarray
    v: np.ndarray
    labels: tuple[str, ...]
    length_dim: np.ndarray

    def _qh(self, q: np.ndarray, last: float = 1.0) -> np.ndarray:
        return np.append(q, last)

    def phi(self, q: np.ndarray) -> np.ndarray:
        """Constraint values Phi(q): (m,) at q (n,), or (T, m) at T samples q (T, n)."""
        q = np.asarray(q, float)
        if q.ndim == 1:
            qh = self._qh(q)
            return 0.5 * np.bincount(self.k, self.v * qh[self.i] * qh[self.j],
                                     minlength=self.m)
        qh = np.concatenate([q, np.ones((len(q), 1))], 1)
        flat = (np.arange(len(q))[:, None] * self.m + self.k).ravel()
        vals = (self.v * qh[:, self.i] * qh[:, self.j]).ravel()
        return 0.5 * np.bincount(flat, vals, minlength=len(q) * self.m).reshape(len(q), -1)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Phi_q: (m, n) dense Jacobian at q (n,), or (T, m, n) at T samples q (T, n) (one
        pass over the triplets for all samples)."""
        q = np.asarray(q, float)
        sel = self.i < self.n
        size, flat = self.m * self.n, self.k[sel] * self.n + self.i[sel]
        if q.ndim == 1:
            vals = np.bincount(flat, self.v[sel] * self._qh(q)[self.j[sel]], minlength=size)
            return vals.reshape(self.m, self.n)
        qh = np.concatenate([q, np.ones((len(q), 1))], 1)
        flat = (np.arange(len(q))[:, None] * size + flat).ravel()
        vals = np.bincount(flat, (self.v[sel] * qh[:, self.j[sel]]).ravel(),
                           minlength=len(q) * size)
        return vals.reshape(len(q), self.m, self.n)

    def quad_velocity(self, qd: np.ndarray) -> np.ndarray:
        """qd^T H_k qd for every row (= Phi_q_dot @ qd): (m,)."""
        qh = self._qh(qd, 0.0)
        return np.bincount(self.k, self.v * qh[self.i] * qh[self.j], minlength=self.m)

    def scaled(self, w: np.ndarray) -> QuadraticConstraints:
        """The same constraints multiplied row-wise by ``w`` (m,): W Phi = 0."""
        return QuadraticConstraints(self.n, self.m, self.k, self.i, self.j,
                                    self.v * np.asarray(w)[self.k], self.labels, self.length_dim)
