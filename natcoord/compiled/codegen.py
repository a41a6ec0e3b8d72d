"""Straight-line kernels of one model: the Schur path of the compiled loop, generated from
the model's sparsity plan and compiled once per model.

The plan (:mod:`natcoord.compiled.sparsity`) holds every product of one evaluation as index lists,
which the generic kernels (:mod:`natcoord.compiled.sparse`) walk at run time. For a small
model the walk costs more than the arithmetic: this module writes those lists out as
Python source with one statement per entry -- constants folded (M^-1 Q0, the rows'
coefficients), W factored as L D L^T without square roots and the factor's structural zeros
dropped, no index array, no loop --
and compiles it to machine code (:mod:`natcoord.compiled.native`: through LLVM, in well under
a second; numba's ``cfunc`` where the source leaves the translator's subset) as six
C-callable functions of one signature each, whatever the model:

    phi(q, out)              out (m,) = Phi(q), every row summed in two doubles
    refactor(q, ws) -> int   J, Y = M^-1 J^T and L D L^T = J Y at q into ws; dependent rows
    rhs(q, qd, qdd, ws)      qdd (n,) of Eq. (6) with the factorization in ws
    newton(ws, w, x)         x (n,) -= Y (L D L^T)^-1 w, w (m,) overwritten
    jx(ws, x, w) -> float    w (m,) = J x; max |w|
    acc(q, qd, qdd, ws)      refactor and rhs in one

A singular M's model gets the same six from its dense plan
(:func:`natcoord.compiled.sparsity.dense_plan`: M + alpha J_S^T J_S factored at every evaluation).
The compiled loop (:func:`natcoord.compiled.index1.run_index1`) takes their addresses and calls them
through a numba intrinsic, so it is compiled once for every model; a model's functions are
compiled on its first run (a few seconds: build time) and cached on disk under the hash of
their source (``NATCOORD_CACHE_DIR``, default ``~/.cache/natcoord``).
``ws`` is the plan's work array (:func:`natcoord.compiled.sparse.workspace`); L's diagonal
slots hold the inverse pivots D^-1 here (0 for a dependent row), so that only these functions
may read a work array they wrote. Units: SI.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from .sparsity import SchurPlan

MAX_TERMS = 6000  # a larger model keeps the generic kernels (compile time grows with size)
MAX_DENSE = 2500  # and a singular M's route above this many dense terms the QR path


def cache_dir() -> Path:
    """Where generated kernels and their compiled code live."""
    root = os.environ.get("NATCOORD_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "natcoord")
    return Path(root) / "kernels"


_WARNED: list[str] = []  # the cache problem said in this process (once)


def cache_problem() -> str | None:
    """Why generated kernels cannot be cached in :func:`cache_dir` (None: they can),
    making nothing: a file in its path, or a folder this process may not write."""
    from ..errors import unwritable

    bad = unwritable(cache_dir())
    if bad is None:
        return None
    part, is_file = bad
    return (f"not a writable folder ({part} is a file)" if is_file else
            f"not a writable folder ({part}: permission denied or read-only)")


def warn_uncached(problem: str | None = None) -> None:
    """Say on stderr, once per process, that the generated kernels cannot be cached (so a
    run takes the generic kernels, many times slower): ``problem``, else
    :func:`cache_problem`'s (nothing said when there is none)."""
    problem = problem or cache_problem()
    if problem is None or _WARNED:
        return
    _WARNED.append(problem)
    where = (f"NATCOORD_CACHE_DIR={os.environ['NATCOORD_CACHE_DIR']}"
             if os.environ.get("NATCOORD_CACHE_DIR") else f"kernel cache {cache_dir()}")
    print(f"warning: {where}: {problem}: the generated kernels cannot be cached; natcoord "
          "runs its generic kernels (slower)", file=sys.stderr, flush=True)


def _uncached(e: OSError) -> None:
    warn_uncached(cache_problem() or f"cannot be written ({e.strerror or e})")


def supported(plan: SchurPlan, frc: tuple) -> bool:
    """Whether the generated kernels serve this model: forces Q0 + T q, spring-dampers and
    planar torques (a spatial torque keeps the generic kernels), and a plan small enough
    to write out."""
    _, T, G, toff, _, S, _ = frc
    n = len(plan.Y_ptr) - 1
    terms = (len(plan.phi_k) + len(plan.jac_other) + len(plan.y_coef) + len(plan.w_j)
             + 4 * plan.envelope + len(plan.gam_k))
    if plan.alpha > 0:  # the factor of M + alpha J_S^T J_S and m solves with it: dense, so
        dense = n * n * (plan.m + n) // 2  # kept to small models (compile time)
        if dense > MAX_DENSE:
            return False
        terms += dense
    return (toff.shape[0] <= 1 or G.shape[1] == 2) and terms <= MAX_TERMS


def _num(x: float) -> str:
    return repr(float(x))


def _lin(terms: list[tuple[float | None, str]]) -> str:
    """A sum of ``coef * name`` (coef None: the name alone) as source; '0.0' when empty."""
    out = []
    for c, name in terms:
        if c is None or c == 1.0:
            out.append(f"+ {name}")
        elif c == -1.0:
            out.append(f"- {name}")
        else:
            out.append(f"+ {_num(c)} * {name}")
    if not out:
        return "0.0"
    s = " ".join(out)
    return s[2:] if s.startswith("+ ") else "-" + s[2:]


class _Writer:
    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, line: str = "", indent: int = 1) -> None:
        self.lines.append("    " * indent + line if line else "")


def _exact_power_of_two(x: float) -> bool:
    return x != 0.0 and math.isfinite(x) and abs(math.frexp(x)[0]) == 0.5


def _phi(plan: SchurPlan, n: int, w: _Writer) -> None:
    """Phi row by row in two doubles, as :func:`natcoord.compiled.sparse.phi` (products by a
    power of two and by the constant 1 are exact and written as plain products)."""
    w("def phi(q, out):", 0)
    k, i, j, v = plan.phi_k, plan.phi_i, plan.phi_j, plan.phi_v
    rows = np.split(np.arange(len(k)), np.flatnonzero(np.diff(k)) + 1) if len(k) else []
    done = set()
    for idx in rows:
        r = int(k[idx[0]])
        done.add(r)
        pairs: dict[tuple[int, int], float] = {}  # the terms (i, j) and (j, i) as one
        for t in idx:
            key = (int(min(i[t], j[t])), int(max(i[t], j[t])))
            pairs[key] = pairs.get(key, 0.0) + 0.5 * float(v[t])
        first = True
        for (a_, b_), c in pairs.items():
            if c == 0.0:
                continue
            a = f"q[{a_}]" if a_ < n else None
            b = f"q[{b_}]" if b_ < n else None
            if a is None and b is None:
                p2, e2 = _num(c), None
            else:
                x, y = (a, b) if a is not None else (b, None)
                if _exact_power_of_two(c):
                    w(f"p = {_num(c)} * {x}")
                    e = None
                else:
                    w(f"p, e = _two_prod({_num(c)}, {x})")
                    e = "e"
                if y is None:
                    p2, e2 = "p", e
                else:
                    w(f"p2, e2 = _two_prod(p, {y})")
                    p2 = "p2"
                    e2 = "e2" if e is None else f"e2 + e * {y}"
            if first:
                w(f"hi = {p2}")
                w(f"lo = {e2 or '0.0'}")
                first = False
            else:
                w(f"hi, e3 = _two_sum(hi, {p2})")
                w(f"lo += e3 + {e2}" if e2 else "lo += e3")
        w(f"out[{r}] = hi + lo" if not first else f"out[{r}] = 0.0")
    for r in range(plan.m):
        if r not in done:
            w(f"out[{r}] = 0.0")
    w("")


class _Chol:
    """A root-free Cholesky factor L D L^T of a symmetric (size, size) matrix written out
    entry by entry: the non-zeros of the unit lower L (the matrix's ``pattern`` below the
    diagonal and their fill) named ``{prefix}{r}_{c}``, the inverse pivots D^-1
    ``{prefix}d{r}``, stored in ws at ``base + slot(r, c)``. No square roots: each pivot
    costs one division on the factorization's critical path."""

    def __init__(self, size: int, pattern: set, prefix: str, base: int, slot):
        self.size, self.prefix, self.base, self.slot = size, prefix, base, slot
        nz = set(pattern)
        self.terms: list[list[tuple[int, list[int]]]] = []  # per r: (c, [k, ...]), c < r
        for r in range(size):
            row = []
            for c in range(r):
                ks = [k for k in range(c) if (r, k) in nz and (c, k) in nz]
                if ks or (r, c) in nz:
                    nz.add((r, c))
                    row.append((c, ks))
            self.terms.append(row)
        self.below = [[c for c, _ in t] for t in self.terms]  # L[r, c] != 0, c < r

    def name(self, r: int, c: int) -> str:
        return f"{self.prefix}{r}_{c}" if r != c else f"{self.prefix}d{r}"

    def factor(self, w: _Writer, value, dep_tol: float | None) -> None:
        """Factor the matrix whose entry (r, c), c <= r, is the expression ``value(r, c)``
        (None: zero). ``dep_tol``: a semi-definite matrix, whose pivots below dep_tol of
        their diagonal mark dependent rows (inverse pivot 0, counted in ``dep``); None: a
        definite one (a non-positive pivot gives NaN or inf, which the loop reports)."""
        p = self.prefix
        for r in range(self.size):
            for c, ks in self.terms[r]:  # u = L[r, c] D[c], then L[r, c]
                fill = [(-1.0, f"{p}u{r}_{k} * {self.name(c, k)}") for k in ks]
                v = value(r, c)
                w(f"{p}u{r}_{c} = {_lin(([(None, v)] if v else []) + fill)}")
                w(f"{self.name(r, c)} = {p}u{r}_{c} * {self.name(c, c)}")
                w(f"ws[{self.base + self.slot(r, c)}] = {self.name(r, c)}")
            w(f"wd = {value(r, r) or '0.0'}")
            sq = [(-1.0, f"{p}u{r}_{c} * {self.name(r, c)}") for c in self.below[r]]
            w(f"s = {_lin([(None, 'wd')] + sq)}")
            d = self.name(r, r)
            if dep_tol is None:
                w(f"{d} = 1.0 / s")
            else:
                w(f"if s > {_num(dep_tol)} * wd and s > 0.0:")
                w(f"{d} = 1.0 / s", 2)
                w("else:")
                w(f"{d} = 0.0", 2)
                w("dep += 1", 2)
            w(f"ws[{self.base + self.slot(r, r)}] = {d}")

    def load(self, w: _Writer) -> None:
        for r in range(self.size):
            for c in self.below[r] + [r]:
                w(f"{self.name(r, c)} = ws[{self.base + self.slot(r, c)}]")

    def solve(self, w: _Writer, b: str, zeros: set | None = None) -> set:
        """Locals b0.. <- (L D L^T)^-1 b (a dependent row's 0); ``zeros``: the entries of b
        known to be zero (not assigned by the caller, skipped until they fill). Returns the
        entries of the solution that stay structurally zero."""
        zero = set(zeros or ())
        for r in range(self.size):  # L z = b
            terms = [(-1.0, f"{self.name(r, c)} * {b}{c}") for c in self.below[r]
                     if c not in zero]
            if r in zero and not terms:
                continue
            own = [] if r in zero else [(None, f"{b}{r}")]
            w(f"{b}{r} = {_lin(own + terms)}")
            zero.discard(r)
        for r in range(self.size):  # D^-1 z: independent products, off the critical path
            if r not in zero:
                w(f"{b}{r} = {b}{r} * {self.name(r, r)}")
        for r in range(self.size - 1, -1, -1):  # L^T x = D^-1 z
            if r in zero:
                continue
            for c in self.below[r]:
                if c in zero:
                    w(f"{b}{c} = -{self.name(r, c)} * {b}{r}")
                    zero.discard(c)
                else:
                    w(f"{b}{c} -= {self.name(r, c)} * {b}{r}")
        for r in sorted(zero):
            w(f"{b}{r} = 0.0")
        return zero


class _Structure:
    """Names and the structural pattern of J, Y, the factor of W = J Y and, on a singular
    M's route (``plan.alpha > 0``), the factor of M + alpha J_S^T J_S and the structural
    non-zeros of Y = (M + alpha J_S^T J_S)^-1 J^T."""

    def __init__(self, plan: SchurPlan, offsets: tuple[int, int, int, int], M):
        self.plan = plan
        self.oJ, self.oY, self.oL, self.oG = offsets
        m, n = plan.m, len(plan.Y_ptr) - 1
        first, ptr = plan.env_first, plan.env_ptr

        def slot(r, c):
            return int(ptr[r] + c - first[r])
        self.wslot = slot
        self.rows: list[list[tuple[int, int]]] = [[] for _ in range(m)]  # (entry, column)
        for e, (r, a) in enumerate(zip(plan.J_row, plan.J_col, strict=True)):
            self.rows[r].append((e, int(a)))
        pattern = {(r, c) for r in range(m) for c in range(first[r], r)
                   if plan.w_ptr[slot(r, c) + 1] > plan.w_ptr[slot(r, c)]}
        self.G, self.ynz = None, None
        if plan.alpha > 0:  # M + alpha J_S^T J_S: M's pattern and the pairs of the S rows
            self.M = np.asarray(M, float)
            self.reg = [int(r) for r in plan.reg]
            pm = {(a, b) for a in range(n) for b in range(a) if self.M[a, b] != 0.0}
            pm |= {(max(a, b), min(a, b)) for r in self.reg for _, a in self.rows[r]
                   for _, b in self.rows[r] if a != b}
            self.G = _Chol(n, pm, "g", self.oG, lambda a, b: a * (a + 1) // 2 + b)
            # column r of Y solves with that factor: its structural non-zeros, and W's
            self.ynz = [set(range(n)) - self.G.solve(_Writer(), "z", set(range(n)) - {
                a for _, a in self.rows[r]}) for r in range(m)]
            pattern = {(r, c) for r in range(m) for c in range(r) if self.y_hits(r, c)}
        self.L = _Chol(m, pattern, "l", self.oL, slot)

    def y_hits(self, r: int, c: int) -> bool:
        """Whether J[r] Y[:, c] has a structural non-zero term (always on a regular M's
        route, whose plan lists only those)."""
        return self.ynz is None or any(a in self.ynz[c] for _, a in self.rows[r])

    def y_nonzero(self, a: int, c: int) -> bool:
        """Whether Y[a, c] can be non-zero."""
        return self.ynz is None or a in self.ynz[c]

    def mbar(self, a: int, b: int) -> str | None:
        """Entry (a, b), b <= a, of M + alpha J_S^T J_S as an expression (None: zero)."""
        terms = [(self.plan.alpha, f"j{e} * j{f}") for r in self.reg
                 for e, x in self.rows[r] for f, y in self.rows[r] if x == a and y == b]
        if self.M[a, b] != 0.0:
            terms.append((float(self.M[a, b]), "1.0"))
        return _lin(terms) if terms else None

    def load(self, w: _Writer, J=False, Y=False, L=False, G=False) -> None:
        p = self.plan
        if J:
            for e in range(len(p.J_row)):
                w(f"j{e} = ws[{self.oJ + e}]")
        if Y:
            for e in range(len(p.Y_col)):
                w(f"y{e} = ws[{self.oY + e}]")
        if L:
            self.L.load(w)
        if G and self.G is not None:
            self.G.load(w)

    def sub_y(self, w: _Writer, b: str, target: str, base: str | None) -> None:
        """target[a] = base_a - sum_e Y[e] b[col e] over the coordinates a."""
        p = self.plan
        for a in range(len(p.Y_ptr) - 1):
            s, t = p.Y_ptr[a], p.Y_ptr[a + 1]
            terms = [(-1.0, f"y{e} * {b}{p.Y_col[e]}") for e in range(s, t)
                     if self.y_nonzero(a, int(p.Y_col[e]))]
            if base is None:
                if terms:
                    w(f"{target}[{a}] -= {' + '.join(t for _, t in terms)}")
            else:
                w(f"{target}[{a}] = {_lin([(None, base.format(a))] + terms)}")

    def jx(self, w: _Writer, x: str, out: str) -> None:
        """out_r = sum_e J[e] x[col e] (locals ``out{r}``)."""
        for r in range(self.plan.m):
            w(f"{out}{r} = {_lin([(None, f'j{e} * {x.format(a)}') for e, a in self.rows[r]])}")


def _refactor(plan: SchurPlan, n: int, st: _Structure, w: _Writer, head: bool = True) -> None:
    """J, Y and the factor of W, as :func:`natcoord.compiled.sparse.factor` (a singular M's
    route: Y by solves with the factor of M + alpha J_S^T J_S, made first)."""
    if head:
        w("def refactor(q, ws):", 0)
    for e in range(len(plan.jac_ptr) - 1):
        s, t = plan.jac_ptr[e], plan.jac_ptr[e + 1]
        terms = [(float(plan.jac_v[p]), f"q[{plan.jac_other[p]}]" if plan.jac_other[p] < n
                  else "1.0") for p in range(s, t)]
        w(f"j{e} = {_lin(terms)}")
        w(f"ws[{st.oJ + e}] = j{e}")
    if st.G is None:
        for e in range(len(plan.y_ptr) - 1):
            s, t = plan.y_ptr[e], plan.y_ptr[e + 1]
            w(f"y{e} = {_lin([(float(plan.y_coef[p]), f'j{plan.y_j[p]}') for p in range(s, t)])}")
            w(f"ws[{st.oY + e}] = y{e}")
    else:
        st.G.factor(w, st.mbar, None)
        m = plan.m
        for r in range(m):  # column r of Y: (M + alpha J_S^T J_S) y = J[r]^T
            cols = {a: e for e, a in st.rows[r]}
            for a, e in cols.items():
                w(f"z{a} = j{e}")
            st.G.solve(w, "z", set(range(n)) - set(cols))
            for a in range(n):
                w(f"y{a * m + r} = z{a}")
                w(f"ws[{st.oY + a * m + r}] = z{a}")
    w("dep = 0")

    def value(r, c):
        sl = st.wslot(r, c)
        terms = [(None, f"j{plan.w_j[p]} * y{plan.w_y[p]}")
                 for p in range(plan.w_ptr[sl], plan.w_ptr[sl + 1])
                 if st.y_nonzero(int(plan.w_y[p]) // max(plan.m, 1), c)]
        return _lin(terms) if terms else None
    st.L.factor(w, value, plan.dep_tol)
    if head:
        w("return dep")
        w("")


def _rhs(plan: SchurPlan, n: int, frc: tuple, st: _Structure, w: _Writer,
         fused: bool = False) -> None:
    """qdd = M^-1 F - Y lambda, (L D L^T) lambda = J M^-1 F - c, as
    :func:`natcoord.compiled.sparse.accelerations` with the factorization in ws, or
    ``fused``: factoring at q first (J, Y, L kept in registers, and stored). A singular
    M's route: M + alpha J_S^T J_S for M and F + alpha J_S^T c_S for F."""
    Q0, T = frc[0], frc[1]
    Mi = np.zeros((n, n))
    for a in range(n):
        for e in range(plan.Mi_ptr[a], plan.Mi_ptr[a + 1]):
            Mi[a, plan.Mi_col[e]] = plan.Mi_val[e]
    if fused:
        w("def acc(q, qd, qdd, ws):", 0)
        _refactor(plan, n, st, w, head=False)
    else:
        w("def rhs(q, qd, qdd, ws):", 0)
        st.load(w, J=True, Y=True, L=True, G=True)
    gam: list[list[tuple[float, str]]] = [[] for _ in range(plan.m)]
    for k, i, j, v in zip(plan.gam_k, plan.gam_i, plan.gam_j, plan.gam_v, strict=True):
        gam[k].append((float(v), f"qd[{i}] * qd[{j}]"))
    if st.G is None and T.shape[0] == 0 and len(frc[3]) <= 1 and not len(frc[5]):
        mf = Mi @ Q0  # M^-1 F constant
        for a in range(n):
            w(f"mf{a} = {_num(mf[a])}")
    else:
        _forces(frc, n, w)
        if st.G is None:
            for a in range(n):
                w(f"mf{a} = {_lin([(float(Mi[a, b]), f'f{b}') for b in np.flatnonzero(Mi[a])])}")
        else:  # mf = (M + alpha J_S^T J_S)^-1 (F + alpha J_S^T c_S), c = -qd^T H qd
            for r in st.reg:
                w(f"c{r} = {_lin([(-v, t) for v, t in gam[r]])}")
            for a in range(n):
                terms = [(plan.alpha, f"j{e} * c{r}") for r in st.reg
                         for e, x in st.rows[r] if x == a]
                w(f"mf{a} = {_lin([(None, f'f{a}')] + terms)}")
            st.G.solve(w, "mf")
    st.jx(w, "mf{}", "b")
    for r in range(plan.m):
        if gam[r]:  # b - c = b + sum v qd_i qd_j
            w(f"b{r} += {_lin(gam[r])}")
    st.L.solve(w, "b")
    st.sub_y(w, "b", "qdd", "mf{}")
    w("")


def _affine(C: np.ndarray, x: str, affine: bool) -> list[str]:
    """The rows of C[:, :n] x (+ C[:, n]) as expressions, C (d, n + 1)."""
    n = C.shape[1] - 1
    return [_lin(([(float(C[a, n]), "1.0")] if affine and C[a, n] else [])
                 + [(float(C[a, b]), f"{x}[{b}]") for b in np.flatnonzero(C[a, :n])])
            for a in range(C.shape[0])]


def _forces(frc: tuple, n: int, w: _Writer) -> None:
    """Locals f0.. = F(q, qd), as :func:`natcoord.compiled.general.forces`: Q0 + T q, planar
    torques (min-norm point forces f_k = B_k^T g, (sum B_k B_k^T) g = tau) and
    spring-dampers."""
    Q0, T, G, toff, tau, S, spr = frc
    for a in range(n):
        terms = [(float(T[a, b]), f"q[{b}]") for b in np.flatnonzero(T[a])] \
            if T.shape[0] else []
        w(f"f{a} = {_lin(([(float(Q0[a]), '1.0')] if Q0[a] else []) + terms)}")

    def add(C, comps):
        for b in range(n):
            terms = [(float(C[a, b]), comps[a]) for a in range(C.shape[0]) if C[a, b]]
            if terms:
                w(f"f{b} += {_lin(terms)}")
    for t in range(len(toff) - 1):  # planar: d_k = G_k qh, B_k = [-d_y, d_x]
        ks = range(toff[t], toff[t + 1])
        for k in ks:
            dx, dy = _affine(G[k], "q", True)
            w(f"tx{k} = {dx}")
            w(f"ty{k} = {dy}")
        w(f"tg = {_num(tau[t, 0])} / ({' + '.join(f'tx{k} * tx{k} + ty{k} * ty{k}' for k in ks)})")
        for k in ks:
            add(G[k], [f"(-ty{k} * tg)", f"(tx{k} * tg)"])
    for s_ in range(len(S)):  # spring-damper: tension k (l - l0) + c dl/dt along S qh
        k_, c_, l0 = (float(x) for x in spr[s_])
        ld, v = _affine(S[s_], "q", True), _affine(S[s_], "qd", False)
        for a in range(len(ld)):
            w(f"sx{a} = {ld[a]}")
            w(f"sv{a} = {v[a]}")
        w(f"sl = math.sqrt({' + '.join(f'sx{a} * sx{a}' for a in range(len(ld)))})")
        w(f"ten = ({_num(k_)} * (sl - {_num(l0)}) + {_num(c_)} * "
          f"({' + '.join(f'sx{a} * sv{a}' for a in range(len(ld)))}) / sl) / sl")
        add(S[s_], [f"(-ten * sx{a})" for a in range(len(ld))])


def _newton(plan: SchurPlan, st: _Structure, w: _Writer) -> None:
    w("def newton(ws, w, x):", 0)
    st.load(w, Y=True, L=True)
    for r in range(plan.m):
        w(f"b{r} = w[{r}]")
    st.L.solve(w, "b")
    for r in range(plan.m):
        w(f"w[{r}] = b{r}")
    st.sub_y(w, "b", "x", None)
    w("")


def _jx(plan: SchurPlan, st: _Structure, w: _Writer) -> None:
    w("def jx(ws, x, w):", 0)
    st.load(w, J=True)
    st.jx(w, "x[{}]", "b")
    w("big = 0.0")
    for r in range(plan.m):
        w(f"w[{r}] = b{r}")
        w(f"big = max(big, abs(b{r}))")
    w("return big")
    w("")


SIGNATURES = {"phi": "types.void(P, P)", "refactor": "types.int64(P, P)",
              "rhs": "types.void(P, P, P, P)", "newton": "types.void(P, P, P)",
              "jx": "types.float64(P, P, P)", "acc": "types.void(P, P, P, P)"}
NAMES = tuple(SIGNATURES)
RETURNS = {k: v.split("(")[0].removeprefix("types.") for k, v in SIGNATURES.items()}


def source(plan: SchurPlan, frc: tuple, M: np.ndarray | None = None) -> str:
    """The module text of the model's six kernels (see the module doc); ``M`` (n, n): the
    mass matrix, for a singular M's route (:func:`natcoord.compiled.sparsity.dense_plan`)."""
    from . import sparse as kernels_sparse
    n = len(plan.Y_ptr) - 1
    O = plan.kernel_args[2]
    offsets = tuple(int(O[kernels_sparse._WO + k]) for k in (0, 1, 2, 6))  # J, Y, L, G
    w = _Writer()
    w('"""natcoord: generated kernels of one model (see natcoord.compiled.codegen)."""', 0)
    w("import math", 0)
    w("from numba import cfunc, types", 0)
    w("from natcoord.compiled.sparse import _two_prod, _two_sum", 0)
    w("P = types.CPointer(types.float64)", 0)
    # the helpers are compiled into the kernels: new helpers, new file
    w("# helpers: " + hashlib.sha1(Path(kernels_sparse.__file__).read_bytes()).hexdigest(), 0)
    w("", 0)
    st = _Structure(plan, offsets, M)
    body = _Writer()
    _phi(plan, n, body)
    _refactor(plan, n, st, body)
    _rhs(plan, n, frc, st, body)
    _rhs(plan, n, frc, st, body, fused=True)
    _newton(plan, st, body)
    _jx(plan, st, body)
    text = "\n".join(body.lines)
    for name, sig in SIGNATURES.items():
        text = text.replace(f"def {name}(", f'@cfunc({sig}, cache=True, error_model="numpy")'
                            f"\ndef {name}(", 1)
    return "\n".join(w.lines) + "\n" + text + "\n"


def load(plan: SchurPlan, frc: tuple, M: np.ndarray | None = None) -> np.ndarray | None:
    """The addresses (int64, NAMES order) of the model's six compiled kernels, generated,
    written and compiled on the first call for this model and loaded from the disk cache
    after; None when the model is not :func:`supported` or the cache cannot be written.
    The kernels stay alive with their module (in ``sys.modules``)."""
    if not supported(plan, frc):
        return None
    text = source(plan, frc, M)
    try:  # straight to machine code through LLVM: well under a second
        from . import native
        addresses = native.load(text, RETURNS, cache_dir())
        return np.array([addresses[k] for k in NAMES], np.int64)
    except NotImplementedError:  # outside the translator's subset: numba compiles it
        pass
    except OSError as e:
        _uncached(e)
        return None
    import numba
    digest = hashlib.sha1((text + numba.__version__).encode()).hexdigest()[:20]
    name = f"natcoord_kernels_{digest}"
    if name in sys.modules:
        mod = sys.modules[name]
    else:
        folder = cache_dir()
        path = folder / f"{name}.py"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            if not path.exists():  # atomic: a concurrent run sees all of it or nothing
                with tempfile.NamedTemporaryFile("w", dir=folder, suffix=".tmp",
                                                 delete=False) as f:
                    f.write(text)
                os.replace(f.name, path)
        except OSError as e:
            _uncached(e)
            return None
        spec = importlib.util.spec_from_file_location(name, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # numba's cache finds the module by name when loading
        try:
            spec.loader.exec_module(mod)
        except BaseException:
            del sys.modules[name]
            raise
    return np.array([getattr(mod, k).address for k in NAMES], np.int64)
