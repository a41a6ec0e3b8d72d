"""The generated kernels compiled straight through LLVM (natcoord.compiled.native) are the
numba-compiled ones bit for bit, are cached as object code, and hand anything outside their
subset back to numba."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.compiled import codegen, native, sparsity
from natcoord.compiled.sparse import workspace
from natcoord.dynamics.common import compiled_forces
from natcoord.model import casemodel
from natcoord.model.drivers import ConstraintSystem

from .conftest import CASES

ARGS = {"phi": 2, "refactor": 2, "rhs": 4, "newton": 3, "jx": 3, "acc": 4}
RESTYPE = {"void": None, "int64": ctypes.c_int64, "float64": ctypes.c_double}


def _plan(name: str, regular: bool):
    model = casemodel.build(load_case(CASES / f"{name}.toml")).model
    M = np.asarray(model.M, float)
    con = ConstraintSystem(model).con
    plan = sparsity.schur_plan(con, M) if regular else sparsity.dense_plan(con, M, 1.0)
    return model, plan, compiled_forces(model), None if regular else M


def _calls(addresses, n: int, size: int, seed: int) -> list:
    """Every kernel called on the same random arrays: (return value, arrays after)."""
    rng = np.random.default_rng(seed)
    q, qd = rng.standard_normal(n), rng.standard_normal(n)
    out = []
    for k, name in enumerate(codegen.NAMES):
        ws = np.linspace(0.1, 2.0, size)
        w, x, o = np.full(size, 0.5), np.linspace(-1.0, 1.0, size), np.zeros(size)
        arrays = {"phi": (q, o), "refactor": (q, ws), "rhs": (q, qd, o, ws),
                  "acc": (q, qd, o, ws), "newton": (ws, w, x), "jx": (ws, x, w)}[name]
        arrays = [a.copy() for a in arrays]
        f = ctypes.CFUNCTYPE(RESTYPE[codegen.RETURNS[name]],
                             *[ctypes.c_void_p] * ARGS[name])(int(addresses[k]))
        out.append((f(*[a.ctypes.data for a in arrays]), arrays))
    return out


@pytest.mark.parametrize("name, regular", [("four_bar", True), ("pendulum", False)])
def test_native_kernels_are_the_numba_kernels_bit_for_bit(name, regular, monkeypatch,
                                                          tmp_path):
    model, plan, frc, M = _plan(name, regular)
    monkeypatch.setenv("NATCOORD_CACHE_DIR", str(tmp_path))
    fast = codegen.load(plan, frc, M)
    with monkeypatch.context() as m:  # the same source through numba's cfunc
        m.setattr(native, "load", lambda *a: (_ for _ in ()).throw(NotImplementedError()))
        slow = codegen.load(plan, frc, M)
    assert fast is not None and slow is not None and not np.array_equal(fast, slow)
    size = len(workspace(plan.kernel_args)) + model.n  # every work slot, and q's length
    for seed in range(3):
        a, b = _calls(fast, model.n, size, seed), _calls(slow, model.n, size, seed)
        for (ra, xa), (rb, xb) in zip(a, b, strict=True):
            assert ra == rb or (ra != ra and rb != rb)
            for u, v in zip(xa, xb, strict=True):
                assert np.array_equal(u, v, equal_nan=True)
    assert list(tmp_path.glob("kernels/natcoord_native_*.o"))


def test_object_code_is_cached_and_reloaded(monkeypatch, tmp_path):
    _, plan, frc, M = _plan("slider_crank", True)
    monkeypatch.setenv("NATCOORD_CACHE_DIR", str(tmp_path))
    first = codegen.load(plan, frc, M)
    monkeypatch.setattr(native, "_object_code", lambda *a: pytest.fail("compiled again"))
    again = codegen.load(plan, frc, M)
    assert first is not None and again is not None


def test_outside_the_subset_is_refused_by_name():
    for text, what in (("def phi(q, out):\n    out[0] = q[0] ** 2\n", "operator Pow"),
                       ("def phi(q, out):\n    for i in range(3):\n        out[i] = 0.0\n",
                        "statement For"),
                       ("def phi(q, out):\n    out[0] = math.exp(q[0])\n", "call math.exp"),
                       ("def phi(q, out):\n    out[0] = q[1 + 1]\n", "integer literal")):
        with pytest.raises(NotImplementedError, match=what):
            native.translate(text, {"phi": "void"})
