"""Exact elimination of a singular M's massless coordinates through constant linear rows.

In natural coordinates a body's points beyond its basis (a rod's middle and far points, a
plate's fourth corner) are tied to the basis by constant linear rows

    A q + c = 0        (l, n),

and carry no mass of their own: M is singular on them. Solving those rows for the massless
coordinates gives every admissible q as

    q = T q_r + b,     T (n, n_r), b (n,),   q_r = q[keep]

(T's rows at ``keep`` are the identity). In q_r every other row is again a quadratic form,
H_r = Th^T H Th with Th = [[T, b], [0, 1]] (n + 1, n_r + 1), the mass matrix is
M_r = T^T M T and the applied forces are T^T Q. Where the eliminated coordinates span ker M,
M_r is regular and the model runs on the regular-M Schur path: the same dynamics (the linear
rows hold exactly at every stage, since q - b lies in T's range) on fewer coordinates, with
no regularisation. Units: those of the model (SI).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .constraints import ROUNDOFF, ConstraintBuilder, QuadraticConstraints

MAX_DENSE = 2_000_000  # linear rows x coordinates solved densely; a larger model keeps
# the regularised or the QR path


@dataclass(frozen=True)
class Elimination:
    """q = T q_r + b and the model in q_r.

    Attributes
    ----------
    T : (n, n_r) float       dq / dq_r
    b : (n,) float           q at q_r = 0 (m)
    keep : (n_r,) int        the coordinates kept (q_r = q[keep])
    dep : (n - n_r,) int     the coordinates eliminated (massless)
    rows : (l,) int          the rows solved for them (hold identically in q_r)
    con : QuadraticConstraints   the other rows over q_r (m - l rows)
    M : (n_r, n_r) float     T^T M T, regular
    frc : tuple | None       the forces over q_r (:func:`natcoord.kernels_general.pack_forces`;
                             None when the model's are not packed)
    dep_map : tuple          (ptr, col, val, b, keep, dep): T's rows at ``dep`` by rows
                             (CSR) and b there, for the compiled loop (its error norm counts
                             the eliminated coordinates as the model's, its samples hold
                             all of q)
    """

    T: np.ndarray
    b: np.ndarray
    keep: np.ndarray
    dep: np.ndarray
    rows: np.ndarray
    con: QuadraticConstraints
    M: np.ndarray
    frc: tuple
    dep_map: tuple

    @functools.cached_property
    def L(self) -> np.ndarray:
        """M_r's Cholesky factor (n_r, n_r), lower."""
        return np.linalg.cholesky(self.M)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """arange(s, s + c) for every (s, c), concatenated."""
    return np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())


def _substitute(con, Th: np.ndarray):
    """Every row's Th^T H_k Th as one sparse (m, N * N) matrix (N = n_r + 1; column
    a * N + b holds entry (a, b) of row k), from the triplets and Th's non-zeros."""
    import scipy.sparse as sp
    T = sp.csr_matrix(Th)
    ptr, ind, dat = T.indptr, T.indices, T.data
    ci = ptr[con.i + 1] - ptr[con.i]
    ea = _ranges(ptr[con.i], ci)  # every (triplet, Th[i, a])
    t1 = np.repeat(np.arange(len(con.v)), ci)
    cj = (ptr[con.j + 1] - ptr[con.j])[t1]
    eb = _ranges(ptr[con.j][t1], cj)  # and Th[j, b]
    t2 = np.repeat(np.arange(len(t1)), cj)
    t, ea = t1[t2], ea[t2]
    N = Th.shape[1]
    H = sp.coo_matrix((con.v[t] * dat[ea] * dat[eb], (con.k[t], ind[ea] * N + ind[eb])),
                      shape=(con.m, N * N)).tocsr()
    H.sum_duplicates()
    return H


def _clean(X: np.ndarray) -> np.ndarray:
    """X with entries below ROUNDOFF of its largest set to exact zeros."""
    X = np.array(X, float)
    X[np.abs(X) < ROUNDOFF * np.max(np.abs(X), initial=0.0)] = 0.0
    return X


def linear_rows(con) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The constant linear rows of ``con``: their indices (l,), A (l, n) and c (l,) with
    Phi = A q + c."""
    n = con.n
    quad = np.zeros(con.m, bool)
    np.logical_or.at(quad, con.k, (con.i < n) & (con.j < n))
    rows = np.flatnonzero(~quad)
    pos = np.full(con.m, -1)
    pos[rows] = np.arange(len(rows))
    A, c = np.zeros((len(rows), n)), np.zeros(len(rows))
    sel = pos[con.k] >= 0
    for k, i, j, v in zip(pos[con.k[sel]], con.i[sel], con.j[sel], con.v[sel], strict=True):
        if i < n and j == n:  # H[i, n] = H[n, i] = a_i: one of the two
            A[k, i] += v
        elif i == n and j == n:  # H[n, n] = 2 c
            c[k] += 0.5 * v
    return rows, A, c


def _pivots(A: np.ndarray, c: np.ndarray, massless: np.ndarray):
    """Gauss-Jordan on [A | c] with pivots among the massless columns (largest first):
    the pivot rows, their columns, and the reduced [A | c] (each pivot row holds its
    pivot, 1, and kept columns only)."""
    R = np.column_stack([A, c])
    n = A.shape[1]
    rows, cols = [], []
    for r in range(len(R)):
        big = np.max(np.abs(R[r, :n]), initial=0.0)
        cand = massless & (np.abs(R[r, :n]) > 1e-10 * big)
        cand[cols] = False
        if big == 0.0 or not cand.any():
            continue
        p = int(np.flatnonzero(cand)[np.argmax(np.abs(R[r, :n][cand]))])
        R[r] /= R[r, p]
        other = np.abs(R[:, p]) > 0.0
        other[r] = False
        R[other] -= np.outer(R[other, p], R[r])
        R[other, p] = 0.0
        rows.append(r)
        cols.append(p)
    return np.array(rows, int), np.array(cols, int), R


def eliminate(con, M: np.ndarray, frc: tuple) -> Elimination | None:
    """The elimination of M's massless coordinates by ``con``'s constant linear rows, or
    None where it does not leave a regular M_r (a massless coordinate no linear row fixes,
    or no massless coordinate at all) or the model is too large (:data:`MAX_DENSE`).
    ``frc``: the packed forces over q, or None."""
    from .formulations import _is_spd
    from .kernels_general import pack_forces
    M = np.asarray(M, float)
    n = len(M)
    massless = ~np.any(M != 0.0, axis=0)
    if not massless.any():
        return None
    lin, A, c = linear_rows(con)
    if len(lin) * n > MAX_DENSE:
        return None
    prow, dep, R = _pivots(A, c, massless)
    if len(dep) < massless.sum():
        return None
    keep = np.setdiff1d(np.arange(n), dep)
    T = np.zeros((n, len(keep)))
    T[keep, np.arange(len(keep))] = 1.0
    T[dep] = -R[prow][:, keep]
    b = np.zeros(n)
    b[dep] = -R[prow, n]
    T, b = _clean(T), _clean(b)
    Mr = _clean(0.5 * (T.T @ M @ T + (T.T @ M @ T).T))
    if not _is_spd(Mr):
        return None
    Th = np.zeros((n + 1, len(keep) + 1))
    Th[:n, :-1], Th[:n, -1], Th[n, -1] = T, b, 1.0
    H = _substitute(con, Th)
    N = Th.shape[1]
    big = np.zeros(con.m)  # each row's largest coefficient, for what counts as zero
    np.maximum.at(big, con.k, np.abs(con.v))
    floor = 1e-12 * big * np.max(np.abs(Th)) ** 2
    gone = np.zeros(con.m, bool)
    gone[lin[prow]] = True
    builder = ConstraintBuilder(len(keep))
    for r in np.flatnonzero(~gone):
        cols, vals = H.indices[H.indptr[r]:H.indptr[r + 1]], H.data[H.indptr[r]:H.indptr[r + 1]]
        if np.max(np.abs(vals), initial=0.0) <= floor[r]:
            continue  # a linear row the eliminated ones imply: 0 = 0 in q_r
        builder.row(cols // N, cols % N, vals, con.labels[r], int(con.length_dim[r]))
    Td = T[dep]
    ptr = np.concatenate([[0], np.cumsum(np.count_nonzero(Td, axis=1))]).astype(np.int64)
    nz_row, nz_col = np.nonzero(Td)
    dep_map = (ptr, nz_col.astype(np.int64), Td[nz_row, nz_col].astype(float), b[dep].copy(),
               keep.astype(np.int64), dep.astype(np.int64))
    if frc is None:
        return Elimination(T, b, keep, dep, lin[prow], builder.build(), Mr, None, dep_map)
    Q0, Tq, G, toff, tau, S, spr = frc
    Q0r = T.T @ Q0
    if Tq.shape[0]:  # a linear force T q: T^T Tq (T q_r + b)
        Q0r = Q0r + T.T @ Tq @ b
    frc_r = pack_forces(Q0r, T.T @ Tq @ T if Tq.shape[0] else None, G @ Th, toff, tau,
                        S @ Th, spr)
    return Elimination(T, b, keep, dep, lin[prow], builder.build(), Mr, frc_r, dep_map)
