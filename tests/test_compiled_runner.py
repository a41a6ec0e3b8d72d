"""The compiled index-1 run packed once (Index1Loop.compiled_runner, what ``integrate`` times
and a benchmark repeats): every repeat is the whole run again, bit for bit, and counts
only its own work."""

from __future__ import annotations

import numpy as np
import pytest

from natcoord.case import casefile
from natcoord.compiled import cache as kernel_cache
from natcoord.compiled import index1 as kernels
from natcoord.dynamics.common import Counters
from natcoord.dynamics.index1 import Index1Loop
from natcoord.model import casemodel
from natcoord.model.drivers import ConstraintSystem

from .conftest import CASES

# slider_crank's default: an elimination (3 of 7 coordinates kept) and generated kernels;
# the generic sparse kernels; the general QR path (no elimination with linsolve qr)
ROUTES = {"generated": {}, "sparse": {"generated": False}, "general": {"linsolve": "qr"}}


@pytest.mark.parametrize("path", ROUTES)
@pytest.mark.parametrize("method,rtol,h", [("dop853", 1e-8, None), ("rk4", 0.0, 2e-3)])
def test_a_repeated_run_is_the_first_again(path, method, rtol, h):
    case = casefile.load_case(CASES / "slider_crank.toml")
    cm = casemodel.build(case, "joints")
    st = casemodel.initial_state(cm)
    cnt = Counters()
    form = Index1Loop(cm.model, ROUTES[path], cnt)
    assert form.compiled_candidate(method, h)
    form.prepare_compiled(st.q)
    assert form.compiled_path == path
    kernel_cache.ensure_compiled(path)
    times = case.times[:101]
    T, n = len(times), cm.model.n
    go = form.compiled_runner(times, float(times[0]), st.q, st.qd, method, rtol,
                              rtol * 1e-2, h)
    out = [np.full((T, n), np.nan) for _ in range(3)]
    c = go(*out)
    assert c.shape == (kernels.N_COUNTERS,) and dict(vars(cnt)) == dict(vars(Counters()))
    kernels.add_counters(c, cnt)  # returned, not added: integrate adds them once, after
    first, counts = [x.copy() for x in out], dict(vars(cnt))
    assert counts["steps"] > 0 and counts["projections"] > counts["steps"]
    assert all(np.isfinite(x).all() for x in first)  # every sample written
    phi, phi_dot = ConstraintSystem(cm.model).drift(first[0], first[1], times)
    assert phi < 1e-10 and phi_dot < 1e-8  # every sample projected
    for x in out:
        x[:] = np.nan
    vars(cnt).update(vars(Counters()))  # as integrate's stepping() before every run
    kernels.add_counters(go(*out), cnt)  # the same buffers, the same packed arrays
    for a, b in zip(out, first, strict=True):
        np.testing.assert_array_equal(a, b)
    assert dict(vars(cnt)) == counts  # its own steps only (the loop zeroes its counters)
    fresh = form.run_compiled(times, np.concatenate([st.q, st.qd]), method, rtol,
                              rtol * 1e-2, h)
    for a, b in zip(fresh, first, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("settings", [
    {"method": "rk4", "h": 1e-25},                                      # compiled index-1
    {"method": "rk4", "h": 1e-300, "compiled": False},                  # the Python loop
    {"formulation": "maggi", "method": "rk4", "h": 1e-25},
    {"formulation": "index3", "method": "trapezoidal", "h": 1e-25}])
def test_a_fixed_step_past_the_step_budget_is_refused_not_run(settings):
    """A step whose count over the run passes the budget fails the run, before it runs:
    past int64 the compiled loops' count of steps per sample wrapped to one step a sample
    (the run took h = 1e-25 as h = output_dt and reported ok), and the Python loop never
    stopped."""
    from natcoord.dynamics.forward import integrate
    from natcoord.dynamics.solver import Solver
    case = casefile.load_case(CASES / "pendulum.toml")
    cm = casemodel.build(case, "joints")
    solver = Solver.from_settings(settings)
    with pytest.raises(RuntimeError, match="too many steps"):
        integrate(cm.model, casemodel.initial_state(cm), case.times[:11], solver)


@pytest.mark.parametrize("path", ["general", "sparse"])
def test_a_compiled_run_that_fails_raises_naming_the_method_and_the_time(path):
    """A compiled index-1 run that stops (here its step budget, 3 adaptive steps for 2 s)
    raises RuntimeError with the method and the time; it returned its partial output as a
    result once (the status check sat after the return)."""
    from natcoord.compiled import index1, sparsity
    con, frc = index1.warm_up_model()
    plan = None if path == "general" else sparsity.schur_plan(con, np.eye(2)).kernel_args
    with pytest.raises(RuntimeError, match=r"dop853 \(compiled\): too many steps at t = "):
        index1.run("dop853", con, frc, np.linspace(0.0, 2.0, 21), np.array([1.0, 0.0]),
                   np.zeros(2), index1.Steps(rtol=1e-6, atol=1e-8, max_steps=3),
                   index1.Route(plan, None, np.eye(2)))
