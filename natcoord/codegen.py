"""Straight-line kernels of one model: the Schur path of the compiled loop, generated from
the model's sparsity plan and compiled once per model.

The plan (:mod:`natcoord.sparsity`) holds every product of one evaluation as index lists,
which the generic kernels (:mod:`natcoord.kernels_sparse`) walk at run time. For a small
model the walk costs more than the arithmetic: this module writes those lists out as
Python source with one statement per entry -- constants folded (M^-1 Q0, the rows'
coefficients), structural zeros of the Cholesky factor dropped, no index array, no loop --
and compiles it with numba into six C-callable functions (``cfunc``) of one signature
each, whatever the model:

    phi(q, out)              out (m,) = Phi(q), every row summed in two doubles
    refactor(q, ws) -> int   J, Y = M^-1 J^T and L L^T = J Y at q into ws; dependent rows
    rhs(q, qd, qdd, ws)      qdd (n,) of Eq. (6) with the factorization in ws
    newton(ws, w, x)         x (n,) -= Y (L L^T)^-1 w, w (m,) overwritten
    jx(ws, x, w) -> float    w (m,) = J x; max |w|
    acc(q, qd, qdd, ws)      refactor and rhs in one

The compiled loop (:func:`natcoord.kernels.run_index1`) takes them as first-class
functions, so it is compiled once for every model; a model's functions are compiled on
its first run (a fraction of a second to a few seconds: build time) and cached on disk
under the hash of their source (``NATCOORD_CACHE_DIR``, default ``~/.cache/natcoord``).
``ws`` is the plan's work array (:func:`natcoord.kernels_sparse.workspace`); L's diagonal
slots hold the inverse pivots here (0 for a dependent row), so that only these functions
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


def cache_dir() -> Path:
    """Where generated kernels and their compiled code live."""
    root = os.environ.get("NATCOORD_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "natcoord")
    return Path(root) / "kernels"


def supported(plan: SchurPlan, frc: tuple) -> bool:
    """Whether the generated kernels serve this model: forces Q0 + T q only (torques and
    spring-dampers stay in the generic kernels) and a plan small enough to write out."""
    _, T, _, toff, _, S, _ = frc
    terms = (len(plan.phi_k) + len(plan.jac_other) + len(plan.y_coef) + len(plan.w_j)
             + 4 * plan.envelope + len(plan.gam_k))
    return toff.shape[0] <= 1 and S.shape[0] == 0 and terms <= MAX_TERMS


def _num(x: float) -> str:
    return repr(float(x))


def _lin(terms: list[tuple[float | None, str]]) -> str:
    """A sum of ``coef * name`` (coef None: the name alone) as source; '0.0' when empty."""
    out = []
    for c, name in terms:
        if c is None:
            out.append(f"+ {name}")
        elif c == 1.0:
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
    """Phi row by row in two doubles, as :func:`natcoord.kernels_sparse.phi` (products by a
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


class _Structure:
    """Names and the structural pattern of J, Y and L for the generated statements."""

    def __init__(self, plan: SchurPlan, offsets: tuple[int, int, int]):
        self.plan = plan
        self.oJ, self.oY, self.oL = offsets
        m = plan.m
        first, ptr = plan.env_first, plan.env_ptr
        self.slot = lambda r, c: int(ptr[r] + c - first[r])
        # L's non-zeros: W's entries and their fill, in the order the factor makes them
        nz = {self.slot(r, c) for r in range(m) for c in range(first[r], r + 1)
              if plan.w_ptr[self.slot(r, c) + 1] > plan.w_ptr[self.slot(r, c)]}
        self.row_terms: list[list[tuple[int, list[int]]]] = []  # per r: (c, [k...]) c < r
        for r in range(m):
            terms = []
            for c in range(first[r], r):
                ks = [k for k in range(max(first[r], first[c]), c)
                      if self.slot(r, k) in nz and self.slot(c, k) in nz]
                if ks or self.slot(r, c) in nz:
                    nz.add(self.slot(r, c))
                    terms.append((c, ks))
            self.row_terms.append(terms)
        self.nz = nz
        self.below = [[c for c, _ in t] for t in self.row_terms]  # L[r, c] != 0, c < r

    def load(self, w: _Writer, J=False, Y=False, L=False) -> None:
        p = self.plan
        if J:
            for e in range(len(p.J_row)):
                w(f"j{e} = ws[{self.oJ + e}]")
        if Y:
            for e in range(len(p.Y_col)):
                w(f"y{e} = ws[{self.oY + e}]")
        if L:
            for r in range(p.m):
                for c in self.below[r]:
                    w(f"l{self.slot(r, c)} = ws[{self.oL + self.slot(r, c)}]")
                w(f"d{r} = ws[{self.oL + self.slot(r, r)}]")

    def solve(self, w: _Writer, b: str) -> None:
        """b0..b{m-1} <- (L L^T)^-1 b (dependent rows 0), with the inverse pivots d."""
        m = self.plan.m
        for r in range(m):
            terms = [(-1.0, f"l{self.slot(r, c)} * {b}{c}") for c in self.below[r]]
            w(f"{b}{r} = ({_lin([(None, f'{b}{r}')] + terms)}) * d{r}")
        for r in range(m - 1, -1, -1):
            w(f"{b}{r} = {b}{r} * d{r}")
            for c in self.below[r]:
                w(f"{b}{c} -= l{self.slot(r, c)} * {b}{r}")

    def sub_y(self, w: _Writer, b: str, target: str, base: str | None) -> None:
        """target[a] = base_a - sum_e Y[e] b[col e] over the coordinates a."""
        p = self.plan
        for a in range(len(p.Y_ptr) - 1):
            s, t = p.Y_ptr[a], p.Y_ptr[a + 1]
            terms = [(-1.0, f"y{e} * {b}{p.Y_col[e]}") for e in range(s, t)]
            if base is None:
                if terms:
                    w(f"{target}[{a}] -= {' + '.join(t for _, t in terms)}")
            else:
                w(f"{target}[{a}] = {_lin([(None, base.format(a))] + terms)}")

    def jx(self, w: _Writer, x: str, out: str) -> None:
        """out_r = sum_e J[e] x[col e] (locals ``out{r}``)."""
        p = self.plan
        by_row: list[list[str]] = [[] for _ in range(p.m)]
        for e, (r, c) in enumerate(zip(p.J_row, p.J_col, strict=True)):
            by_row[r].append(f"j{e} * {x.format(c)}")
        for r in range(p.m):
            w(f"{out}{r} = {_lin([(None, t) for t in by_row[r]])}")


def _refactor(plan: SchurPlan, n: int, st: _Structure, w: _Writer, head: bool = True) -> None:
    """J, Y and the envelope Cholesky, as :func:`natcoord.kernels_sparse.factor`."""
    if head:
        w("def refactor(q, ws):", 0)
    for e in range(len(plan.jac_ptr) - 1):
        s, t = plan.jac_ptr[e], plan.jac_ptr[e + 1]
        terms = [(float(plan.jac_v[p]), f"q[{plan.jac_other[p]}]" if plan.jac_other[p] < n
                  else "1.0") for p in range(s, t)]
        w(f"j{e} = {_lin(terms)}")
        w(f"ws[{st.oJ + e}] = j{e}")
    for e in range(len(plan.y_ptr) - 1):
        s, t = plan.y_ptr[e], plan.y_ptr[e + 1]
        w(f"y{e} = {_lin([(float(plan.y_coef[p]), f'j{plan.y_j[p]}') for p in range(s, t)])}")
        w(f"ws[{st.oY + e}] = y{e}")
    dep_tol = plan.dep_tol
    w("dep = 0")
    for r in range(plan.m):
        for c, ks in st.row_terms[r]:
            sl = st.slot(r, c)
            s, t = plan.w_ptr[sl], plan.w_ptr[sl + 1]
            wrc = [(None, f"j{plan.w_j[p]} * y{plan.w_y[p]}") for p in range(s, t)]
            fill = [(-1.0, f"l{st.slot(r, k)} * l{st.slot(c, k)}") for k in ks]
            w(f"l{sl} = ({_lin(wrc + fill)}) * d{c}")
            w(f"ws[{st.oL + sl}] = l{sl}")
        sl = st.slot(r, r)
        s, t = plan.w_ptr[sl], plan.w_ptr[sl + 1]
        w(f"wd = {_lin([(None, f'j{plan.w_j[p]} * y{plan.w_y[p]}') for p in range(s, t)])}")
        sq = [(-1.0, f"l{st.slot(r, c)} * l{st.slot(r, c)}") for c in st.below[r]]
        w(f"s = {_lin([(None, 'wd')] + sq)}")
        w(f"if s > {_num(dep_tol)} * wd and s > 0.0:")
        w(f"d{r} = 1.0 / math.sqrt(s)", 2)
        w("else:")
        w(f"d{r} = 0.0", 2)
        w("dep += 1", 2)
        w(f"ws[{st.oL + sl}] = d{r}")
    if head:
        w("return dep")
        w("")


def _rhs(plan: SchurPlan, n: int, frc: tuple, st: _Structure, w: _Writer,
         fused: bool = False) -> None:
    """qdd = M^-1 F - Y lambda, (L L^T) lambda = J M^-1 F - c, as
    :func:`natcoord.kernels_sparse.accelerations` with the factorization in ws, or
    ``fused``: factoring at q first (J, Y, L kept in registers, and stored)."""
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
        st.load(w, J=True, Y=True, L=True)
    if T.shape[0] == 0:  # M^-1 F constant
        mf = Mi @ Q0
        for a in range(n):
            w(f"mf{a} = {_num(mf[a])}")
    else:
        for a in range(n):
            terms = [(float(T[a, b]), f"q[{b}]") for b in np.flatnonzero(T[a])]
            w(f"f{a} = {_lin([(float(Q0[a]), '1.0')] + terms) if Q0[a] else _lin(terms)}")
        for a in range(n):
            w(f"mf{a} = {_lin([(float(Mi[a, b]), f'f{b}') for b in np.flatnonzero(Mi[a])])}")
    gam: list[list[tuple[float, str]]] = [[] for _ in range(plan.m)]
    for k, i, j, v in zip(plan.gam_k, plan.gam_i, plan.gam_j, plan.gam_v, strict=True):
        gam[k].append((float(v), f"qd[{i}] * qd[{j}]"))
    st.jx(w, "mf{}", "b")
    for r in range(plan.m):
        if gam[r]:  # b - c = b + sum v qd_i qd_j
            w(f"b{r} += {_lin(gam[r])}")
    st.solve(w, "b")
    st.sub_y(w, "b", "qdd", "mf{}")
    w("")


def _newton(plan: SchurPlan, st: _Structure, w: _Writer) -> None:
    w("def newton(ws, w, x):", 0)
    st.load(w, Y=True, L=True)
    for r in range(plan.m):
        w(f"b{r} = w[{r}]")
    st.solve(w, "b")
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


def source(plan: SchurPlan, frc: tuple) -> str:
    """The module text of the model's six kernels (see the module doc)."""
    from . import kernels_sparse
    n = len(plan.Mi_ptr) - 1
    O = plan.kernel_args[2]
    offsets = tuple(int(O[kernels_sparse._WO + k]) for k in range(3))  # J, Y, L in ws
    w = _Writer()
    w('"""natcoord: generated kernels of one model (see natcoord.codegen)."""', 0)
    w("import math", 0)
    w("from numba import cfunc, types", 0)
    w("from natcoord.kernels_sparse import _two_prod, _two_sum", 0)
    w("P = types.CPointer(types.float64)", 0)
    # the helpers are compiled into the kernels: new helpers, new file
    w("# helpers: " + hashlib.sha1(Path(kernels_sparse.__file__).read_bytes()).hexdigest(), 0)
    w("", 0)
    st = _Structure(plan, offsets)
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


def load(plan: SchurPlan, frc: tuple) -> np.ndarray | None:
    """The addresses (int64, NAMES order) of the model's six compiled kernels, generated,
    written and compiled on the first call for this model and loaded from the disk cache
    after; None when the model is not :func:`supported` or the cache cannot be written.
    The kernels stay alive with their module (in ``sys.modules``)."""
    if not supported(plan, frc):
        return None
    text = source(plan, frc)
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
        except OSError:
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
