"""Exact elimination of coordinates through the constant linear rows.

In natural coordinates many rows are constant and linear,

    A q + c = 0        (l, n):

a body's points beyond its basis (a rod's middle and far points, a plate's fourth corner),
which carry no mass of their own (M is singular on them), and the points two bodies share
at a joint. Solving those rows for one coordinate each (a massless one where the row has
one) gives every admissible q as

    q = T q_r + b,     T (n, n_r), b (n,),   q_r = q[keep]

(T's rows at ``keep`` are the identity). In q_r every other row is again a quadratic form,
H_r = Th^T H Th with Th = [[T, b], [0, 1]] (n + 1, n_r + 1), the mass matrix is
M_r = T^T M T and the applied forces are T^T Q. Where the eliminated coordinates span ker M,
M_r is regular and the model runs on the regular-M Schur path: the same dynamics (the linear
rows hold exactly at every stage, since q - b lies in T's range) on fewer coordinates and
rows, with no regularisation; an M-orthogonal projection in q_r is the model's own (for a
regular M) or the kinetic metric's where the model's M has none. Where massless coordinates
remain that no linear row fixes (a slender body's unit vector), M_r stays singular
(``regular`` False) and the general path runs on q_r: fewer coordinates and rows for its QR,
minimum-norm projections in q_r. The elimination is sparse: linear in the size of a
chain. Units: those of the model (SI).
"""

from __future__ import annotations

import functools
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ..model.constraints import ROUNDOFF, ConstraintBuilder, QuadraticConstraints

MAX_BLOCK = 32  # coordinates M_r may couple in one block once a massive coordinate is
# eliminated: a chain's shared points couple all its bodies (M_r^-1 dense, the Schur path
# no longer linear in the chain's length), so there only massless ones go


@dataclass(frozen=True)
class Elimination:
    """q = T q_r + b and the model in q_r.

    Attributes
    ----------
    T : (n, n_r) sparse      dq / dq_r (``scipy.sparse.csr_array``)
    b : (n,) float           q at q_r = 0 (m)
    keep : (n_r,) int        the coordinates kept (q_r = q[keep])
    dep : (n - n_r,) int     the coordinates eliminated
    rows : (l,) int          the rows solved for them (hold identically in q_r)
    con : QuadraticConstraints   the other rows over q_r
    M : (n_r, n_r) float     T^T M T
    regular : bool           whether M_r is positive definite
    frc : tuple | None       the forces over q_r (:func:`natcoord.compiled.general.pack_forces`;
                             None when the model's are not packed)
    dep_map : tuple          (ptr, col, val, b, keep, dep): T's rows at ``dep`` by rows
                             (CSR) and b there, for the compiled loop (its error norm counts
                             the eliminated coordinates as the model's, its samples hold
                             all of q)
    """

    T: sp.csr_array
    b: np.ndarray
    keep: np.ndarray
    dep: np.ndarray
    rows: np.ndarray
    con: QuadraticConstraints
    M: np.ndarray
    regular: bool
    frc: tuple | None
    dep_map: tuple

    @functools.cached_property
    def Lt(self) -> np.ndarray | None:
        """L^-T (n_r, n_r) of M_r = L L^T: dq_r = L^-T z turns dq_r^T M_r dq_r into |z|^2
        (None for a singular M_r)."""
        if not self.regular:
            return None
        L = np.linalg.cholesky(self.M)
        return scipy.linalg.solve_triangular(L, np.eye(len(L)), lower=True).T


def linear_rows(con) -> tuple[np.ndarray, sp.csr_array]:
    """The constant linear rows of ``con``: their indices (l,) and [A | c] (l, n + 1)
    with Phi = A q + c."""
    n = con.n
    quad = np.zeros(con.m, bool)
    np.logical_or.at(quad, con.k, (con.i < n) & (con.j < n))
    rows = np.flatnonzero(~quad)
    pos = np.full(con.m, -1)
    pos[rows] = np.arange(len(rows))
    # H[i, n] = H[n, i] = a_i (one of the two) and H[n, n] = 2 c
    sel = (pos[con.k] >= 0) & (con.j == n)
    half = np.where(con.i[sel] == n, 0.5, 1.0)
    Ac = sp.coo_array((con.v[sel] * half, (pos[con.k[sel]], con.i[sel])),
                      shape=(len(rows), n + 1)).tocsr()
    Ac.sum_duplicates()
    return rows, Ac


def _pivots(Ac: sp.csr_array, massless: np.ndarray, massive: bool):
    """Sparse Gauss-Jordan on [A | c], a pivot per row where it has one: a massless column
    where the row has one, else (``massive``) its largest (the lowest such column on a
    tie). Returns the pivot rows, their columns, and every row as {column: value} (a pivot
    row holds its pivot, 1, and kept columns only)."""
    n = Ac.shape[1] - 1
    R = [dict(zip(Ac.indices[Ac.indptr[r]:Ac.indptr[r + 1]].tolist(),
                  Ac.data[Ac.indptr[r]:Ac.indptr[r + 1]].tolist(), strict=True))
         for r in range(Ac.shape[0])]
    where = defaultdict(set)  # column -> the rows that hold it
    for r, row in enumerate(R):
        for c in row:
            where[c].add(r)
    prow, pcol = [], []
    for r, row in enumerate(R):
        big = max((abs(v) for c, v in row.items() if c < n), default=0.0)
        cand = [c for c, v in row.items() if c < n and abs(v) > 1e-10 * big]
        pool = [c for c in cand if massless[c]] or (cand if massive else [])
        if not pool:
            continue
        p = max(pool, key=lambda c: (abs(row[c]), -c))
        inv = 1.0 / row[p]
        for c in row:
            row[c] *= inv
        row[p] = 1.0
        for s in where[p] - {r}:
            f = R[s].pop(p)
            for c, v in row.items():
                if c != p:
                    R[s][c] = R[s].get(c, 0.0) - f * v
                    where[c].add(s)
        where[p] = {r}
        prow.append(r)
        pcol.append(p)
    return np.array(prow, int), np.array(pcol, int), R


def _solve(Ac: sp.csr_array, massless: np.ndarray, massive: bool):
    """(pivot rows, eliminated and kept coordinates, T (n, n_r) sparse, b (n,)) of
    q = T q_r + b (see :func:`_pivots`)."""
    n = Ac.shape[1] - 1
    prow, dep, R = _pivots(Ac, massless, massive)
    keep = np.setdiff1d(np.arange(n), dep)
    at = np.full(n, -1)
    at[keep] = np.arange(len(keep))
    ti, tj, tv = [keep], [np.arange(len(keep))], [np.ones(len(keep))]
    b = np.zeros(n)
    for r, p in zip(prow, dep, strict=True):
        cols = [c for c in R[r] if c < n and c != p]
        ti.append(np.full(len(cols), p))
        tj.append(at[cols])
        tv.append([-R[r][c] for c in cols])
        b[p] = -R[r].get(n, 0.0)
    tv = _clean(np.concatenate(tv))
    T = sp.csr_array((tv, (np.concatenate(ti), np.concatenate(tj))), shape=(n, len(keep)))
    T.eliminate_zeros()
    T.sort_indices()
    return prow, dep, keep, T, _clean(b)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """arange(s, s + c) for every (s, c), concatenated."""
    return np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())


def _substitute(con, Th: sp.csr_array) -> sp.csr_array:
    """Every row's Th^T H_k Th as one sparse (m, N * N) matrix (N = n_r + 1; column
    a * N + b holds entry (a, b) of row k), from the triplets and Th's non-zeros."""
    ptr, ind, dat = Th.indptr, Th.indices, Th.data
    ci = ptr[con.i + 1] - ptr[con.i]
    ea = _ranges(ptr[con.i], ci)  # every (triplet, Th[i, a])
    t1 = np.repeat(np.arange(len(con.v)), ci)
    cj = (ptr[con.j + 1] - ptr[con.j])[t1]
    eb = _ranges(ptr[con.j][t1], cj)  # and Th[j, b]
    t2 = np.repeat(np.arange(len(t1)), cj)
    t, ea = t1[t2], ea[t2]
    N = Th.shape[1]
    H = sp.coo_array((con.v[t] * dat[ea] * dat[eb], (con.k[t], ind[ea] * N + ind[eb])),
                     shape=(con.m, N * N)).tocsr()
    H.sum_duplicates()
    return H


def _clean(X: np.ndarray) -> np.ndarray:
    """X with entries below ROUNDOFF of its largest set to exact zeros."""
    X = np.array(X, float)
    X[np.abs(X) < ROUNDOFF * np.max(np.abs(X), initial=0.0)] = 0.0
    return X


def eliminate(con, M: np.ndarray, frc: tuple | None) -> Elimination | None:
    """The elimination of coordinates by ``con``'s constant linear rows (see the module),
    or None where there is none. Massive coordinates go too while M_r couples at most
    :data:`MAX_BLOCK` of them in one block. ``frc``: the packed forces over q, or None."""
    from .sparsity import blocks, is_spd
    M = np.asarray(M, float)
    lin, Ac = linear_rows(con)
    massless = ~np.any(M != 0.0, axis=0)
    for massive in (True, False):
        prow, dep, keep, T, b = _solve(Ac, massless, massive)
        if len(dep) == 0:
            return None
        MT = (T.T @ M).T  # M T (n, n_r), M symmetric
        Mr = _clean(T.T @ MT)
        Mr = 0.5 * (Mr + Mr.T)
        if massless[dep].all() or max(map(len, blocks(Mr))) <= MAX_BLOCK:
            break  # else a chain's bodies now share one block: massless ones only
    Th = sp.csr_array(sp.block_array([[T, sp.csr_array(b[:, None])],
                                      [None, sp.csr_array(np.ones((1, 1)))]]))
    Th.eliminate_zeros()
    Th.sort_indices()
    H = _substitute(con, Th)
    N = Th.shape[1]
    big = np.zeros(con.m)  # each row's largest coefficient, for what counts as zero
    np.maximum.at(big, con.k, np.abs(con.v))
    floor = 1e-12 * big * max(1.0, np.max(np.abs(Th.data))) ** 2
    gone = np.zeros(con.m, bool)
    gone[lin[prow]] = True
    builder = ConstraintBuilder(len(keep))
    for r in np.flatnonzero(~gone):
        cols, vals = H.indices[H.indptr[r]:H.indptr[r + 1]], H.data[H.indptr[r]:H.indptr[r + 1]]
        if np.max(np.abs(vals), initial=0.0) <= floor[r]:
            continue  # a linear row the eliminated ones imply: 0 = 0 in q_r
        builder.row(cols // N, cols % N, vals, con.labels[r], int(con.length_dim[r]))
    Td = T[dep]
    dep_map = (Td.indptr.astype(np.int64), Td.indices.astype(np.int64),
               Td.data.astype(float), b[dep].copy(), keep.astype(np.int64),
               dep.astype(np.int64))
    return Elimination(T, b, keep, dep, lin[prow], builder.build(), Mr, is_spd(Mr),
                       None if frc is None else _forces(frc, T, b, Th), dep_map)


def _forces(frc: tuple, T: sp.csr_array, b: np.ndarray, Th: sp.csr_array) -> tuple:
    """The packed forces over q carried to q_r: T^T Q at q = T q_r + b."""
    from .general import pack_forces
    Q0, Tq, G, toff, tau, S, spr = frc
    n1, N = Th.shape  # n + 1, n_r + 1

    def over_r(X):  # maps (K, d, n + 1) -> (K, d, n_r + 1)
        return (Th.T @ X.reshape(-1, n1).T).T.reshape(X.shape[:-1] + (N,))

    Q0r = T.T @ Q0
    Tr = None
    if Tq.shape[0]:  # a linear force Tq q: T^T Tq (T q_r + b)
        Q0r = Q0r + T.T @ (Tq @ b)
        Tr = T.T @ (T.T @ Tq.T).T
    return pack_forces(Q0r, Tr, over_r(G), toff, tau, over_r(S), spr)
