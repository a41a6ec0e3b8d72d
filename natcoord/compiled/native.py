"""Machine code of a model's generated kernels (:mod:`natcoord.compiled.codegen`) straight from
their source, through LLVM (llvmlite), without numba's front end.

The kernels are long straight-line functions, thousands of statements for a 3-D model;
numba types and lowers them statement by statement (about 20 s for a spatial slider-crank,
over a minute for Bricard's mechanism), while LLVM compiles the same IR in well under a
second. This module translates the small subset of Python that codegen writes:

- functions of pointer arguments (``double*``) returning nothing, ``int64`` or ``double``;
- assignments to names, to ``p[k]`` (k an integer literal) and to ``(s, e)`` from
  ``_two_prod(a, b)`` / ``_two_sum(a, b)``; ``+=``, ``-=`` on either;
- ``+ - * /``, unary ``-``, ``abs``, ``max(a, b)``, ``math.sqrt``, float and integer literals;
- ``if`` / ``else`` on comparisons joined by ``and``; ``return``.

The arithmetic is numba's, operation for operation (IEEE, no fast-math, no contraction:
``_two_prod``'s error term is LLVM's ``fma``, ``max(a, b)`` keeps ``a`` unless ``b > a``),
so results are bit-identical to the numba-compiled kernels. Anything else in a source is
a ``NotImplementedError`` (the caller falls back to numba). Object code is cached on disk
next to the source; the execution engines stay alive for the process.
"""

from __future__ import annotations

import ast
import hashlib
import os
import tempfile
from pathlib import Path

import llvmlite
import llvmlite.binding as llvm
from llvmlite import ir

D, I64, BOOL = ir.DoubleType(), ir.IntType(64), ir.IntType(1)
PTR = D.as_pointer()
RETURNS = {"void": ir.VoidType(), "int64": I64, "float64": D}
_SELF = hashlib.sha1(Path(__file__).read_bytes()).hexdigest()  # a new translator: new code
_ENGINES: list = []  # the engines that hold every loaded kernel's code
_TARGET = None


class _Function:
    """One function's translation: every local an ``alloca`` (LLVM's mem2reg makes them
    registers), every statement in order."""

    def __init__(self, module: ir.Module, node: ast.FunctionDef, ret: str):
        self.ret = RETURNS[ret]
        fn = ir.Function(module, ir.FunctionType(self.ret, [PTR] * len(node.args.args)),
                         name=node.name)
        self.args = {a.arg: v for a, v in zip(node.args.args, fn.args, strict=True)}
        self.module = module
        entry = fn.append_basic_block("entry")
        self.b = ir.IRBuilder(entry)
        self.vars: dict[str, tuple] = {}  # name -> (alloca, type)
        for name, kind in _kinds(node).items():
            self.vars[name] = (self.b.alloca(kind, name=name), kind)
        self._block(node.body)
        if not self.b.block.is_terminated:
            if isinstance(self.ret, ir.VoidType):
                self.b.ret_void()
            else:
                self.b.unreachable()

    # ---- statements ----
    def _block(self, body: list[ast.stmt]) -> None:
        for st in body:
            if self.b.block.is_terminated:
                return
            self._stmt(st)

    def _stmt(self, st: ast.stmt) -> None:
        b = self.b
        if isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant):
            return  # a docstring
        if isinstance(st, ast.Assign) and len(st.targets) == 1:
            t = st.targets[0]
            if isinstance(t, ast.Tuple):
                values = self._pair(st.value)
                if len(t.elts) != len(values):
                    raise NotImplementedError("tuple assignment of another length")
                for name, v in zip(t.elts, values, strict=True):
                    self._store(name, v)
                return
            self._store(t, self._expr(st.value))
            return
        if isinstance(st, ast.AugAssign):
            cur = self._expr(st.target)  # a name or p[k], read as it stands
            self._store(st.target, self._binop(st.op, cur, self._expr(st.value)))
            return
        if isinstance(st, ast.If):
            cond = self._test(st.test)
            then, other = b.append_basic_block(), b.append_basic_block()
            after = b.append_basic_block()
            b.cbranch(cond, then, other)
            for block, body in ((then, st.body), (other, st.orelse)):
                b.position_at_end(block)
                self._block(body)
                if not b.block.is_terminated:
                    b.branch(after)
            b.position_at_end(after)
            return
        if isinstance(st, ast.Return):
            if st.value is None:
                b.ret_void()
            else:
                b.ret(self._cast(self._expr(st.value), self.ret))
            return
        raise NotImplementedError(f"statement {type(st).__name__}")

    def _store(self, target: ast.expr, value) -> None:
        if isinstance(target, ast.Name):
            slot, kind = self.vars[target.id]
            self.b.store(self._cast(value, kind), slot)
        elif isinstance(target, ast.Subscript):
            self.b.store(self._cast(value, D), self._address(target))
        else:
            raise NotImplementedError(f"assignment to {type(target).__name__}")

    def _address(self, node: ast.Subscript):
        if not (isinstance(node.value, ast.Name) and node.value.id in self.args
                and isinstance(node.slice, ast.Constant)
                and isinstance(node.slice.value, int)):
            raise NotImplementedError("only p[k] with k an integer literal")
        return self.b.gep(self.args[node.value.id], [ir.Constant(I64, node.slice.value)])

    # ---- expressions ----
    def _expr(self, e: ast.expr):
        b = self.b
        if isinstance(e, ast.Constant):
            if isinstance(e.value, bool) or not isinstance(e.value, (int, float)):
                raise NotImplementedError(f"literal {e.value!r}")
            return ir.Constant(I64 if isinstance(e.value, int) else D, e.value)
        if isinstance(e, ast.Name):
            if e.id not in self.vars:
                raise NotImplementedError(f"name {e.id}")
            slot, _ = self.vars[e.id]
            return b.load(slot)
        if isinstance(e, ast.Subscript):
            return b.load(self._address(e))
        if isinstance(e, ast.BinOp):
            return self._binop(e.op, self._expr(e.left), self._expr(e.right))
        if isinstance(e, ast.UnaryOp) and isinstance(e.op, ast.USub):
            v = self._expr(e.operand)
            return b.fneg(v) if v.type == D else b.neg(v)
        if isinstance(e, ast.Call):
            return self._call(e)
        raise NotImplementedError(f"expression {type(e).__name__}")

    def _binop(self, op: ast.operator, x, y):
        b = self.b
        if x.type == I64 and y.type == I64 and not isinstance(op, ast.Div):
            f = {ast.Add: b.add, ast.Sub: b.sub, ast.Mult: b.mul}.get(type(op))
        else:
            x, y = self._cast(x, D), self._cast(y, D)
            f = {ast.Add: b.fadd, ast.Sub: b.fsub, ast.Mult: b.fmul,
                 ast.Div: b.fdiv}.get(type(op))
        if f is None:
            raise NotImplementedError(f"operator {type(op).__name__}")
        return f(x, y)

    def _cast(self, v, kind):
        if v.type == kind:
            return v
        if v.type == I64 and kind == D:
            return self.b.sitofp(v, D)
        raise NotImplementedError(f"{v.type} as {kind}")

    def _intrinsic(self, name: str, n: int):
        return self.module.declare_intrinsic(name, [D], ir.FunctionType(D, [D] * n))

    def _call(self, e: ast.Call):
        b, f = self.b, e.func
        args = [self._cast(self._expr(a), D) for a in e.args]
        name = (f.id if isinstance(f, ast.Name) else
                f"{f.value.id}.{f.attr}" if isinstance(f, ast.Attribute)
                and isinstance(f.value, ast.Name) else "")
        if name == "abs" and len(args) == 1:
            return b.call(self._intrinsic("llvm.fabs", 1), args)
        if name == "math.sqrt" and len(args) == 1:
            return b.call(self._intrinsic("llvm.sqrt", 1), args)
        if name == "max" and len(args) == 2:  # numba's (and Python's): a unless b > a
            return b.select(b.fcmp_ordered(">", args[1], args[0]), args[1], args[0])
        raise NotImplementedError(f"call {name or type(f).__name__}")

    def _pair(self, e: ast.expr) -> tuple:
        """``_two_prod(a, b)``: (a*b, fma(a, b, -a*b)); ``_two_sum(a, b)``: Knuth's."""
        b = self.b
        if not (isinstance(e, ast.Call) and isinstance(e.func, ast.Name) and len(e.args) == 2):
            raise NotImplementedError("tuple from anything but _two_prod / _two_sum")
        x, y = (self._cast(self._expr(a), D) for a in e.args)
        if e.func.id == "_two_prod":
            p = b.fmul(x, y)
            return p, b.call(self._intrinsic("llvm.fma", 3), [x, y, b.fneg(p)])
        if e.func.id == "_two_sum":
            s = b.fadd(x, y)
            bb = b.fsub(s, x)
            return s, b.fadd(b.fsub(x, b.fsub(s, bb)), b.fsub(y, bb))
        raise NotImplementedError(f"call {e.func.id}")

    def _test(self, e: ast.expr):
        b = self.b
        if isinstance(e, ast.BoolOp) and isinstance(e.op, ast.And):
            out = self._test(e.values[0])
            for v in e.values[1:]:  # no side effects: both sides evaluated
                out = b.and_(out, self._test(v))
            return out
        if isinstance(e, ast.Compare) and len(e.ops) == 1:
            ops = {ast.Gt: ">", ast.Lt: "<", ast.GtE: ">=", ast.LtE: "<=", ast.Eq: "=="}
            op = ops.get(type(e.ops[0]))
            if op is None:
                raise NotImplementedError(f"comparison {type(e.ops[0]).__name__}")
            x, y = self._expr(e.left), self._expr(e.comparators[0])
            if x.type == I64 and y.type == I64:
                return b.icmp_signed(op, x, y)
            return b.fcmp_ordered(op, self._cast(x, D), self._cast(y, D))
        raise NotImplementedError(f"condition {type(e).__name__}")


def _kinds(node: ast.FunctionDef) -> dict:
    """Every local name's type: int64 when every value given to it is an integer literal
    (``dep = 0``, ``dep += 1``), else double (numba unifies the same way)."""
    kinds: dict[str, ir.Type] = {}

    def give(target: ast.expr, value: ast.expr | None) -> None:
        names = target.elts if isinstance(target, ast.Tuple) else [target]
        for name in names:
            if isinstance(name, ast.Name):
                lit = (isinstance(value, ast.Constant) and type(value.value) is int
                       and not isinstance(target, ast.Tuple))
                kinds[name.id] = I64 if lit and kinds.get(name.id, I64) == I64 else D

    for st in ast.walk(node):
        if isinstance(st, ast.Assign):
            for t in st.targets:
                give(t, st.value)
        elif isinstance(st, ast.AugAssign):
            give(st.target, st.value)
    return kinds


def translate(text: str, returns: dict[str, str]) -> str:
    """LLVM IR (text) of the functions ``returns`` ({name: 'void' | 'int64' | 'float64'})
    of the Python source ``text``. Raises NotImplementedError outside the subset."""
    module = ir.Module(name="natcoord_kernels")
    module.triple = llvm.get_process_triple()
    found = {n.name: n for n in ast.parse(text).body if isinstance(n, ast.FunctionDef)}
    for name, ret in returns.items():
        if name not in found:
            raise NotImplementedError(f"no function {name}")
        _Function(module, found[name], ret)
    return str(module)


def _target_machine():
    global _TARGET
    if _TARGET is None:
        llvm.initialize_native_target()
        llvm.initialize_native_asmprinter()
        target = llvm.Target.from_triple(llvm.get_process_triple())
        _TARGET = target.create_target_machine(cpu=llvm.get_host_cpu_name(),
                                               features=llvm.get_host_cpu_features()
                                               .flatten(), opt=3, codemodel="jitdefault")
    return _TARGET


def _object_code(ir_text: str) -> bytes:
    if not hasattr(llvm, "create_pass_builder"):  # llvmlite < 0.44: numba compiles instead
        raise NotImplementedError("llvmlite without the new pass manager")
    mod = llvm.parse_assembly(ir_text)
    mod.verify()
    tm = _target_machine()
    mod.data_layout = str(tm.target_data)
    pto = llvm.create_pipeline_tuning_options(speed_level=3)
    pb = llvm.create_pass_builder(tm, pto)
    pb.getModulePassManager().run(mod, pb)
    return tm.emit_object(mod)


def load(text: str, returns: dict[str, str], folder: Path) -> dict[str, int]:
    """The addresses of the functions ``returns`` of ``text`` compiled to machine code
    (object code cached in ``folder`` under the hash of the source, this translator, the
    host CPU and LLVM's version). Raises NotImplementedError outside the subset, OSError
    on the cache."""
    key = hashlib.sha1("\n".join((text, repr(sorted(returns.items())), _SELF,
                                  llvm.get_host_cpu_name(),
                                  llvm.get_host_cpu_features().flatten(),
                                  llvmlite.__version__)).encode()).hexdigest()[:20]
    path = Path(folder) / f"natcoord_native_{key}.o"
    if path.exists():
        obj = path.read_bytes()
    else:
        obj = _object_code(translate(text, returns))
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("wb", dir=folder, suffix=".tmp", delete=False) as f:
            f.write(obj)
        os.replace(f.name, path)  # atomic: a concurrent run sees all of it or nothing
    engine = llvm.create_mcjit_compiler(llvm.parse_assembly(""), _target_machine())
    engine.add_object_file(llvm.ObjectFileRef.from_data(obj))
    engine.finalize_object()
    _ENGINES.append(engine)
    addresses = {name: engine.get_function_address(name) for name in returns}
    if not all(addresses.values()):
        raise NotImplementedError("a function's address is missing from its object code")
    return addresses
