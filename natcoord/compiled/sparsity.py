"""The sparsity plan of the compiled Schur path: every product of Eq. (6) as index arrays.

With a regular, constant M, one evaluation of the index-1 equations needs

    J = Phi_q(q)              from the constraint triplets (one entry per triplet)
    Y = M^-1 J^T              (n, m), M^-1 block-diagonal over M's coupled coordinates
    W = J Y = J M^-1 J^T      (m, m), symmetric positive semi-definite
    W = L L^T                 envelope (skyline) Cholesky, rows in reverse Cuthill-McKee order

and every entry of these is a fixed list of multiply-adds once the model is known, held
here in gather form (the products of one entry contiguous, summed in a register). This
module works the lists out once per model (numpy and scipy, no numba), so that the compiled
kernels (:mod:`natcoord.compiled.sparse`) are straight loops over flat arrays: no dense
(m, n) matrix, no test on zeros, a cost linear in the number of non-zeros. The reverse
Cuthill-McKee order keeps the envelope of W narrow for chains (the N-four-bar's W has a
constant bandwidth), so a step costs linearly in the size of the mechanism.

Redundant rows need no special path: the envelope Cholesky takes a pivot below ``dep_tol``
of its row's diagonal as a dependent row (its multiplier is set to zero), which gives one
solution of the consistent system W lambda = b and so the unique qdd = M^-1 (F - J^T lambda).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, reverse_cuthill_mckee

DEP_TOL = 1e-12  # a Cholesky pivot below this fraction of its row's diagonal: dependent row


INT = ("phi_k", "phi_i", "phi_j", "jac_ptr", "jac_other", "gam_k", "gam_i", "gam_j", "J_row",
       "J_col", "Mi_ptr", "Mi_col", "y_ptr", "y_j", "Y_ptr", "Y_col", "w_ptr", "w_j", "w_y",
       "env_first", "env_ptr")
FLOAT = ("phi_v", "jac_v", "gam_v", "Mi_val", "y_coef")
WORK = ("J", "Y", "L", "w", "c", "F", "G")  # the compiled path's work array (values; G:
# scratch of the generated kernels, see natcoord.compiled.codegen)


class SchurPlan(NamedTuple):
    """Flat index arrays of one model (all int64 / float64, C-contiguous).

    phi_k, phi_i, phi_j, phi_v (nt,)   every triplet over qh = [q, 1], rows permuted, sorted by row
    jac_ptr (nJ+1,), jac_other, jac_v   J[e] = sum v qh[other] over jac_ptr[e]:jac_ptr[e+1]
    gam_k, gam_i, gam_j, gam_v (ng,)   c[k] -= v qd_i qd_j (triplets with i, j < n)
    J_row, J_col (nJ,)                 the entries of J (sorted by row)
    Mi_ptr (n+1,), Mi_col, Mi_val      M^-1 in CSR
    y_ptr (nY+1,), y_coef, y_j         Y[e] = sum y_coef J[y_j] over y_ptr[e]:y_ptr[e+1]
    Y_ptr (n+1,), Y_col (nY,)          Y in CSR (rows: coordinates, columns: constraint rows)
    w_ptr (nL+1,), w_j, w_y            L[e] = sum J[w_j] Y[w_y] over w_ptr[e]:w_ptr[e+1] (W)
    env_first (m,), env_ptr (m+1,)     row r of L holds columns env_first[r]..r at env_ptr[r]
    m                                  rows; ``perm`` (m,) the case row of each plan row
    scratch, alpha                     see :func:`dense_plan` (0 for a regular M)
    """

    phi_k: np.ndarray
    phi_i: np.ndarray
    phi_j: np.ndarray
    phi_v: np.ndarray
    jac_ptr: np.ndarray
    jac_other: np.ndarray
    jac_v: np.ndarray
    gam_k: np.ndarray
    gam_i: np.ndarray
    gam_j: np.ndarray
    gam_v: np.ndarray
    J_row: np.ndarray
    J_col: np.ndarray
    Mi_ptr: np.ndarray
    Mi_col: np.ndarray
    Mi_val: np.ndarray
    y_ptr: np.ndarray
    y_coef: np.ndarray
    y_j: np.ndarray
    Y_ptr: np.ndarray
    Y_col: np.ndarray
    w_ptr: np.ndarray
    w_j: np.ndarray
    w_y: np.ndarray
    env_first: np.ndarray
    env_ptr: np.ndarray
    m: int
    dep_tol: float
    perm: np.ndarray
    scratch: int = 0  # work the generated kernels keep beside these (M + alpha J_S^T J_S's L)
    alpha: float = 0.0  # > 0: the regularised route of a singular M (see dense_plan)
    reg: np.ndarray | None = None  # the rows regularising it (dense_plan)

    @property
    def kernel_args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(I, F, O): the integer and float arrays concatenated, and O the offsets of each
        (:data:`INT`, :data:`FLOAT`, then :data:`WORK`, the work array's segments), then
        m, then the dependent-pivot tolerance as O[-1] / 1e18 -- three arrays, so that a
        compiled call passes three pointers, not thirty arrays."""
        ints = [getattr(self, k) for k in INT]
        floats = [getattr(self, k) for k in FLOAT]
        m, nJ, nY = self.m, len(self.jac_ptr) - 1, len(self.y_ptr) - 1
        work = [nJ, nY, self.envelope, m, m, len(self.Mi_ptr) - 1, self.scratch]
        off = [np.concatenate([[0], np.cumsum([len(a) for a in arrs])])
               for arrs in (ints, floats)] + [np.concatenate([[0], np.cumsum(work)])]
        O = np.concatenate(off + [[m, round(self.dep_tol * 1e18)]]).astype(np.int64)
        return (_i64(np.concatenate(ints)), _f64(np.concatenate(floats)), O)

    @property
    def envelope(self) -> int:
        """Stored entries of L (the envelope of W)."""
        return int(self.env_ptr[-1])


def empty_plan(n: int) -> SchurPlan:
    """A plan with no rows (typed like any other: the compiled loop's general path carries
    one it never reads)."""
    z, zf, z1 = np.zeros(0, np.int64), np.zeros(0), np.zeros(1, np.int64)
    zp = np.zeros(n + 1, np.int64)
    return SchurPlan(z, z, z, zf, z1, z, zf, z, z, z, zf, z, z, zp, z, zf, z1, zf, z, zp, z,
                     z1, z, z, z, z1, 0, DEP_TOL, z)


def blocks(M: np.ndarray) -> list[np.ndarray]:
    """Index sets (sorted) of the coordinates M couples: the connected components of its
    pattern (M block-diagonal up to a permutation)."""
    k, label = connected_components(sp.csr_matrix(np.asarray(M) != 0.0), directed=False)
    order = np.argsort(label, kind="stable")
    return np.split(order, np.cumsum(np.bincount(label, minlength=k))[:-1])


def is_spd(M: np.ndarray) -> bool:
    """M (n, n) symmetric positive definite, judged block by block over its coupled
    coordinates (:func:`blocks`; cheap for a large, block-diagonal M)."""
    for idx in blocks(M):
        B = M[np.ix_(idx, idx)]
        try:
            np.linalg.cholesky(B)
        except np.linalg.LinAlgError:
            return False
        w = np.linalg.eigvalsh(B)
        if not w[0] > 1e-10 * w[-1]:
            return False
    return True


def block_inverse(M: np.ndarray) -> sp.csr_matrix:
    """M^-1 of a symmetric positive definite M (n, n), inverted block by block over the
    connected components of its pattern (so M^-1 has exactly M's block pattern)."""
    M = np.asarray(M, float)
    n = len(M)
    rows, cols, vals = [], [], []
    for idx in blocks(M):
        inv = np.linalg.inv(M[np.ix_(idx, idx)])
        r, c = np.meshgrid(idx, idx, indexing="ij")
        rows.append(r.ravel())
        cols.append(c.ravel())
        vals.append(inv.ravel())
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def _i64(x) -> np.ndarray:
    return np.ascontiguousarray(x, np.int64)


def _f64(x) -> np.ndarray:
    return np.ascontiguousarray(x, float)


def _ptr(slot: np.ndarray, size: int) -> np.ndarray:
    """CSR pointers (size + 1,) of items whose target ``slot`` they are sorted by."""
    return _i64(np.searchsorted(np.sort(slot), np.arange(size + 1)))


def _entries(k, i, n):
    """The entries of J: one slot per (row, column) of the triplets on q, sorted by row:
    (rows, columns, the slot of each triplet on q)."""
    onq = i < n
    ukey, inv = np.unique(k[onq] * n + i[onq], return_inverse=True)
    return ukey // n, ukey % n, inv


def _triplet_lists(k, i, j, v, n, inv, nJ) -> tuple:
    """The plan's first eleven fields (Phi's terms sorted by row, J's gather lists, gamma's
    triplets) from the triplets with rows k in plan order, ``inv`` of :func:`_entries`
    and its nJ entries."""
    onq = i < n
    jo = np.argsort(inv, kind="stable")
    gam = onq & (j < n)
    po = np.argsort(k, kind="stable")  # Phi's terms row by row (one running sum per row)
    return (_i64(k[po]), _i64(i[po]), _i64(j[po]), _f64(v[po]),
            _ptr(inv, nJ), _i64(j[onq][jo]),
            _f64(v[onq][jo]), _i64(k[gam]), _i64(i[gam]), _i64(j[gam]), _f64(v[gam]))


def dense_plan(con, M: np.ndarray, alpha: float, dep_tol: float = DEP_TOL) -> SchurPlan:
    """The plan of a singular M's regularised route, for the generated kernels only:

        (M + alpha J_S^T J_S) qdd + J^T lambda = F + alpha J_S^T c_S,     J qdd = c

    has the solution qdd of Eq. (6) for any alpha > 0 and any set S of rows. With S the
    rows that touch a coordinate moved by ker M (``reg``: a massless point's), J_S v = J v
    for every v in ker M, so M + alpha J_S^T J_S is positive definite wherever ker M and
    ker J meet only in 0 (the existence condition), and it couples fewer coordinates than
    M + alpha J^T J. Its factor changes with q, so Y = (M + alpha J_S^T J_S)^-1 J^T is dense
    (n, m), W = J Y is factored over its full lower triangle, and ``scratch`` keeps the
    factor (n (n + 1) / 2 entries); the M^-1 and Y-product lists are empty."""
    k, i, j, v = (np.asarray(con.k, np.int64), np.asarray(con.i, np.int64),
                  np.asarray(con.j, np.int64), np.asarray(con.v, float))
    m, n = int(con.m), len(M)
    J_row, J_col, inv = _entries(k, i, n)
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    null = V[:, lam <= 1e-12 * max(float(lam[-1]), 1e-300)]  # a basis of ker M
    moved = np.flatnonzero(np.any(np.abs(null) > 1e-12, axis=1))
    reg = np.unique(J_row[np.isin(J_col, moved)])
    Y_row, Y_col = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)  # dense, by row
    first = np.zeros(m, np.int64)
    env_ptr = np.concatenate([[0], np.cumsum(np.arange(m) + 1)])
    wj, wy, slot = [], [], []  # W[r, s] = sum_a J[r, a] Y[a, s], s <= r
    for e, (r, a) in enumerate(zip(J_row, J_col, strict=True)):
        for s_ in range(r + 1):
            wj.append(e)
            wy.append(a * m + s_)
            slot.append(env_ptr[r] + s_)
    wo = np.argsort(np.asarray(slot, np.int64), kind="stable")
    z, zf = np.zeros(0, np.int64), np.zeros(0)
    return SchurPlan(
        *_triplet_lists(k, i, j, v, n, inv, len(J_row)),
        _i64(J_row), _i64(J_col), np.zeros(n + 1, np.int64), z, zf,
        np.zeros(n * m + 1, np.int64), zf, z,
        _i64(np.searchsorted(Y_row, np.arange(n + 1))), _i64(Y_col),
        _ptr(np.asarray(slot, np.int64), int(env_ptr[-1])),
        _i64(np.asarray(wj, np.int64)[wo]), _i64(np.asarray(wy, np.int64)[wo]),
        first, _i64(env_ptr), m, float(dep_tol), np.arange(m, dtype=np.int64),
        n * (n + 1) // 2, float(alpha), _i64(reg))


def schur_plan(con, M: np.ndarray, dep_tol: float = DEP_TOL) -> SchurPlan:
    """The plan for constraint triplets ``con`` (k, i, j, v, m over qh, see
    :class:`~natcoord.model.constraints.QuadraticConstraints`) and a regular mass matrix
    M (n, n)."""
    k, i, j, v = (np.asarray(con.k, np.int64), np.asarray(con.i, np.int64),
                  np.asarray(con.j, np.int64), np.asarray(con.v, float))
    m, n = int(con.m), len(M)
    Mi = block_inverse(M)
    onq = i < n
    # the structure of J and of W = J M^-1 J^T, then rows in reverse Cuthill-McKee order
    Js = sp.csr_matrix((np.ones(int(onq.sum())), (k[onq], i[onq])), shape=(m, n))
    Js.data[:] = 1.0
    Ws = (Js @ (Mi != 0).astype(float) @ Js.T).tocsr()
    perm = reverse_cuthill_mckee(Ws, symmetric_mode=True) if m else np.zeros(0, np.int64)
    new = np.empty(m, np.int64)
    new[perm] = np.arange(m)
    k = new[k]
    J_row, J_col, inv = _entries(k, i, n)
    # Y = M^-1 J^T: Y[a, r] = sum_b Mi[a, b] J[r, b]; one product per (J entry, Mi[:, b] entry)
    MiT = Mi.tocsc()
    ya, yr, ycoef, yj = [], [], [], []
    for e, (r, b) in enumerate(zip(J_row, J_col, strict=True)):
        s, t = MiT.indptr[b], MiT.indptr[b + 1]
        ya.append(MiT.indices[s:t])
        yr.append(np.full(t - s, r))
        ycoef.append(MiT.data[s:t])
        yj.append(np.full(t - s, e))
    ya, yr = np.concatenate(ya) if ya else np.zeros(0, np.int64), \
        np.concatenate(yr) if yr else np.zeros(0, np.int64)
    ykey = ya * max(m, 1) + yr
    uy, y_slot = np.unique(ykey, return_inverse=True)
    Y_row, Y_col = uy // max(m, 1), uy % max(m, 1)
    Y_ptr = np.searchsorted(Y_row, np.arange(n + 1))
    # W[r, s] (s <= r) = sum_a J[r, a] Y[a, s]: one product per (Y entry, J entry in column a)
    Jc = sp.csc_matrix((np.arange(len(J_row)) + 1.0, (J_row, J_col)), shape=(m, n))
    wr, ws, wj, wy = [], [], [], []
    for y, (a, s_) in enumerate(zip(Y_row, Y_col, strict=True)):
        lo, hi = Jc.indptr[a], Jc.indptr[a + 1]
        rows = Jc.indices[lo:hi]
        ent = Jc.data[lo:hi].astype(np.int64) - 1
        keep = rows >= s_
        wr.append(rows[keep])
        ws.append(np.full(int(keep.sum()), s_))
        wj.append(ent[keep])
        wy.append(np.full(int(keep.sum()), y))
    wr = np.concatenate(wr) if wr else np.zeros(0, np.int64)
    ws = np.concatenate(ws) if ws else np.zeros(0, np.int64)
    first = np.arange(m)
    np.minimum.at(first, wr, ws)
    env_ptr = np.concatenate([[0], np.cumsum(np.arange(m) - first + 1)])
    w_slot = env_ptr[wr] + (ws - first[wr])
    ycoef = np.concatenate(ycoef) if ycoef else np.zeros(0)
    yj = np.concatenate(yj) if yj else np.zeros(0, np.int64)
    wj = np.concatenate(wj) if wj else np.zeros(0, np.int64)
    wy = np.concatenate(wy) if wy else np.zeros(0, np.int64)
    yo, wo = (np.argsort(x, kind="stable") for x in (y_slot, w_slot))
    return SchurPlan(
        *_triplet_lists(k, i, j, v, n, inv, len(J_row)),
        _i64(J_row), _i64(J_col),
        _i64(Mi.indptr), _i64(Mi.indices), _f64(Mi.data),
        _ptr(y_slot, len(Y_row)), _f64(ycoef[yo]), _i64(yj[yo]),
        _i64(Y_ptr), _i64(Y_col),
        _ptr(w_slot, int(env_ptr[-1])), _i64(wj[wo]), _i64(wy[wo]),
        _i64(first), _i64(env_ptr), m, float(dep_tol), _i64(perm))
