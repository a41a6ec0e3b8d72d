"""Compiled index-1 loop (natcoord.compiled.index1): agreement with the Python loop, dense output
accuracy against the references, fallbacks, and compile time kept out of the stepping time."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from natcoord import CaseError, load_case
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.solver import Adaptive, Fixed, Index1, Index3, Solver
from tests.models import body_angle, build_model, initial_state

from .conftest import CASES, REFERENCES, ROOT


def _theta_error(name, sol, model):
    ang = body_angle(model, "crank", sol.q, sol.qd)
    ref = pd.read_csv(REFERENCES / f"{name}.csv")["theta"].to_numpy()
    return float(np.max(np.abs(ang - ref)))


@pytest.mark.parametrize("name", ["slider_crank", "four_bar"])
@pytest.mark.parametrize("method, rtol, bound", [("dop853", 1e-7, 1e-6), ("dop853", 1e-10, 1e-9),
                                                 ("dopri5", 1e-7, 1e-6)])
def test_compiled_loop_reaches_the_reference(name, method, rtol, bound):
    case = load_case(CASES / f"{name}.toml")
    model = build_model(case)
    sol = integrate(model, initial_state(model), case.times,
                    Solver(method=method, step=Adaptive(rtol, rtol * 1e-2)))
    c = sol.counters
    assert c["compiled"] and c["steps"] < len(case.times)  # steps cross the samples
    assert _theta_error(name, sol, model) < bound
    assert c["max_phi"] < 1e-12 and c["max_phi_dot"] < 1e-11  # samples are projected


def test_compiled_and_python_loops_agree():
    case = load_case(CASES / "four_bar.toml")
    model = build_model(case)
    times = case.times[:51]
    step = Adaptive(1e-11, 1e-13)
    fast = integrate(model, initial_state(model), times, Solver(step=step))
    slow = integrate(model, initial_state(model), times, Solver(Index1(compiled=False),
                                                                step=step))
    assert fast.counters["compiled"] and not slow.counters["compiled"]
    assert np.max(np.abs(fast.q - slow.q)) < 1e-9
    assert np.max(np.abs(fast.qd - slow.qd)) < 1e-8
    assert np.max(np.abs(fast.lam - slow.lam)) < 1e-6


def test_drivers_fall_back_to_the_python_loop():
    case = load_case(CASES / "slider_crank_driven.toml")
    model = build_model(case)
    sol = integrate(model, initial_state(model), case.times[:11],
                    Solver(step=Adaptive(1e-9, 1e-11)))
    assert not sol.counters["compiled"] and np.all(np.isfinite(sol.q))


def test_invalid_solver_combinations_cannot_be_made():
    """The combination is refused when the Solver is made, before any model or time loop."""
    with pytest.raises(ValueError, match="adaptive"):
        Solver(method="dop853", step=Fixed(1e-3))
    with pytest.raises(ValueError, match="fixed-step"):
        Solver(method="rk4")
    with pytest.raises(ValueError, match="does not run with"):
        Solver(Index3(), "dop853")
    with pytest.raises(ValueError, match="not an option of index1"):
        Solver.from_settings({"penalty": 1e5})
    with pytest.raises(ValueError, match="positive"):
        Adaptive(rtol=-1.0)


def test_case_file_asking_for_an_invalid_solver_is_refused(tmp_path):
    text = (CASES / "slider_crank.toml").read_text()
    for setting, why in (('method = "rk4"', "fixed-step"), ('h = 1e-3', "adaptive"),
                         ('formulation = "index3", method = "dop853"', "does not run")):
        bad = text.replace("[engines.natcoord]\n",
                           f"[engines.natcoord]\nsettings = {{ {setting} }}\n", 1)
        assert bad != text
        p = tmp_path / "slider_crank.toml"
        p.write_text(bad)
        with pytest.raises(CaseError, match=f"engines.natcoord.settings: .*{why}"):
            load_case(p)


def test_compile_time_is_reported_apart_and_cached():
    """A fresh process loads the cached kernels; the load is build time, not wall time."""
    code = ("from natcoord.case.casefile import load_case\n"
            "from natcoord.engines import natcoord_engine as ne\n"
            "from natcoord.engines.base import initial_body_states\n"
            "c = load_case('cases/slider_crank.toml')\n"
            "r = ne.run(c, initial_body_states(c), {})\n"
            "print(r.counters['compile_time_s'], r.build_time_s, r.wall_time_s,"
            " r.counters['compiled'])\n")
    out = [subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, check=True).stdout.split() for _ in range(2)]
    compile_s, build_s, wall_s, compiled = out[-1]
    assert compiled == "True"
    assert float(build_s) >= float(compile_s)
    assert float(compile_s) < 5.0  # cache hit (a cold compile takes 15-30 s)
    assert float(wall_s) < 0.1


def test_general_path_agrees_with_the_schur_path():
    """On a regular-M, full-rank model the general path (QR null-space form, min-norm
    projections) and the Schur path (M-orthogonal projections) give the same run."""
    from .test_kernels_singular import run_compiled

    case = load_case(CASES / "four_bar.toml")
    model = build_model(case)
    times, st = case.times[:51], initial_state(model)
    schur = run_compiled(model, st, times, "dop853", 1e-11, 1e-13)
    general = run_compiled(model, st, times, "dop853", 1e-11, 1e-13, linsolve="qr")
    assert (schur[0], general[0]) == ("schur", "qr")
    for a, b in zip(schur[1:4], general[1:4], strict=True):
        assert np.max(np.abs(a - b)) < 1e-9 * max(1.0, np.max(np.abs(a)))
