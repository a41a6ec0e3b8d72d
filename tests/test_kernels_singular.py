"""Compiled index-1 loop on its general path (natcoord.compiled.general): singular M,
redundant constraints, Model torques and spring-dampers, against the Python loop in
``linsolve="qr"`` mode on the paper's reference-frame cases."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest

from natcoord.case import casefile
from natcoord.compiled import cache as kernel_cache
from natcoord.compiled import general as kg
from natcoord.dynamics.common import Counters, compiled_forces
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.index1 import Index1Loop
from natcoord.dynamics.solver import Adaptive, Index1, Solver
from natcoord.model import casemodel
from natcoord.model.model import Model, Spring
from tests.models import build_model, initial_state

from .conftest import CASES

# coordinates setting of each case's natcoord engine, end time (s), integrator, rtol
RUNS = {"five_bar": ("shared", 0.9, "dop853", 1e-10),  # before the -180 deg singularity
        "four_bar_3d": ("joints", None, "dop853", 1e-10),
        "parallelogram_3d": ("shared", None, "dop853", 1e-10),
        "parallelogram_3d_flexible": ("shared", 0.02, "dop853", 1e-10)}  # stiff: ~35 steps/ms

# at the springs' stability limit the accept / reject pattern follows round-off: the same
# trajectory to 1e-14 took 449 steps in the Python loop and 470 and 492 compiled (with M
# regularised, and on the coordinates the elimination keeps)
STEP_SPREAD = {"parallelogram_3d_flexible": 0.12}


@cache
def _case(name):
    case = casefile.load_case(CASES / f"{name}.toml")
    cm = casemodel.build(case, RUNS[name][0])
    return case, cm.model, casemodel.initial_state(cm)


def _times(name):
    case, _, _ = _case(name)
    end = RUNS[name][1]
    return case.times if end is None else case.times[case.times <= end + 1e-12]


@cache
def _python_loop(name, method=None, rtol=None, end=None):
    _, model, st = _case(name)
    times = _times(name) if end is None else _case(name)[0].times
    method, rtol = method or RUNS[name][2], rtol or RUNS[name][3]
    return integrate(model, st, times, Solver(Index1(compiled=False), method,
                                              Adaptive(rtol, rtol * 1e-2)))


def run_compiled(model, state, times, method, rtol, atol, **options):
    """What ``integrate`` runs on the compiled path: (mode, Q, QD, QDD, counters)."""
    cnt = Counters()
    q0, qd0 = Index1Loop(model, {**options, "linsolve": "qr"}, Counters()).project(
        times[0], np.asarray(state.q, float), np.asarray(state.qd, float))
    form = Index1Loop(model, options, cnt)
    assert form.compiled_candidate(method, None)
    kernel_cache.ensure_compiled()
    y = form.init(times[0], q0, qd0)
    assert form.compiled_ready()
    Q, QD, QDD = form.run_compiled(times, y, method, rtol, atol)
    return form.mode, Q, QD, QDD, cnt


def _with_extra_forces(model: Model, rng) -> Model:
    """four_bar_3d with 3-D torques on a full body (3 difference vectors), on a rod (one)
    and on a body of two collinear ones, and three spring-dampers between random maps."""
    crank = model.bodies["crank"]
    G = crank.G
    bodies = {**model.bodies, "rod": dataclasses.replace(crank, name="rod", G=G[:1]),
              "pair": dataclasses.replace(crank, name="pair", G=np.stack([G[0], 2.0 * G[0]]))}
    torques = tuple((b, rng.normal(size=3), None) for b in ("crank", "rod", "pair", "coupler"))
    springs = tuple(Spring(f"s{k}", rng.normal(size=(3, model.n + 1)),
                           rng.normal(size=(3, model.n + 1)), 1e3 * rng.random(),
                           10.0 * rng.random(), rng.random()) for k in range(3))
    return dataclasses.replace(model, bodies=bodies, torques=torques, springs=springs)


@pytest.mark.parametrize("name", [*RUNS, "four_bar_3d+extra"])
def test_forces_kernel_matches_model_forces(name):
    rng = np.random.default_rng(7)
    model = _case(name.split("+")[0])[1]
    if name.endswith("+extra"):
        model = _with_extra_forces(model, rng)
    frc = compiled_forces(model)
    assert frc is not None
    out = np.zeros(model.n)
    for _ in range(20):
        q, qd = rng.normal(size=model.n), rng.normal(size=model.n)
        kg.forces(frc, q, qd, out)
        ref = model.forces(0.0, q, qd)
        assert np.max(np.abs(out - ref)) <= 1e-12 * max(1.0, np.max(np.abs(ref)))


def test_forces_of_2d_model_and_unknown_force_models():
    model = build_model(casefile.load_case(CASES / "four_bar.toml"))
    frc, out = compiled_forces(model), np.zeros(model.n)
    q = np.random.default_rng(1).normal(size=model.n)
    kg.forces(frc, q, q, out)
    assert np.allclose(out, model.forces(0.0, q, q), rtol=1e-14, atol=1e-12)

    class Custom(Model):
        def forces(self, t, q, qd):
            return self.Q0

    nm = _case("five_bar")[1]
    custom = Custom(**{f.name: getattr(nm, f.name) for f in dataclasses.fields(nm)})
    assert compiled_forces(custom) is None
    assert not Index1Loop(custom, {}, Counters()).compiled_candidate("dop853", None)
    bad = dataclasses.replace(nm, torques=(("135", np.ones(3), None),))  # 3-D torque in 2-D
    assert compiled_forces(bad) is None


@pytest.mark.parametrize("name", RUNS)
def test_general_path_matches_python_qr_mode(name):
    """Projection and qdd of the kernels equal Index1's qr mode to round-off near the
    constraint manifold (drift 1e-10, as after a step)."""
    _, model, st = _case(name)
    frc = compiled_forces(model)
    form = Index1Loop(model, {"linsolve": "qr"}, Counters())
    form.mode = "qr"
    rng = np.random.default_rng(3)
    for _ in range(10):
        q = st.q + 1e-10 * rng.normal(size=model.n)
        qd = st.qd + rng.normal(size=model.n)
        qp, qdp = form.project(0.0, q, qd)
        qk, qdk, _ = kg.evaluate(form.cs.con, frc, model.M, q, qd, ptol=1e-13)
        assert np.max(np.abs(qk - qp)) < 1e-13
        assert np.max(np.abs(qdk - qdp)) < 1e-12 * max(1.0, np.max(np.abs(qdp)))
        qdd = form.accelerations(0.0, qp, qdp)
        _, _, qddk = kg.evaluate(form.cs.con, frc, model.M, qp, qdp)
        assert np.max(np.abs(qddk - qdd)) < 1e-12 * max(1.0, np.max(np.abs(qdd)))


def test_compiled_candidate_takes_natural_models_and_refuses_the_rest():
    _, model, _ = _case("five_bar")
    assert Index1Loop(model, {}, Counters()).compiled_candidate("dop853", None)
    assert Index1Loop(model, {"linsolve": "qr"}, Counters()).compiled_candidate("dopri5", None)
    assert Index1Loop(model, {}, Counters()).compiled_candidate("dopri5", 1e-3)  # fixed h
    assert Index1Loop(model, {}, Counters()).compiled_candidate("rk4", 1e-3)
    assert not Index1Loop(model, {}, Counters()).compiled_candidate("rk4", None)
    assert not Index1Loop(model, {}, Counters()).compiled_candidate("dop853", 1e-3)
    assert not Index1Loop(model, {"stabilization": "baumgarte"},
                      Counters()).compiled_candidate("dop853", None)
    assert not Index1Loop(model, {"compiled": False}, Counters()).compiled_candidate("dop853", None)
    driven = build_model(casefile.load_case(CASES / "slider_crank_driven.toml"))
    assert not Index1Loop(driven, {}, Counters()).compiled_candidate("dop853", None)
    plain = build_model(casefile.load_case(CASES / "four_bar.toml"))
    form = Index1Loop(plain, {}, Counters())
    assert form.compiled_candidate("dop853", None)
    st = initial_state(plain)
    form.init(0.0, st.q, st.qd)
    assert form.mode == "schur"  # the regular-M, full-rank models keep the Schur path


@pytest.mark.parametrize("name", RUNS)
def test_compiled_general_loop_matches_python_loop(name):
    """Same trajectory as the Python loop (qr mode; the compiled loop on the coordinates an
    elimination keeps, four_bar_3d's on the general path): measured |dq| <= 3.4e-10 m,
    |dqd| <= 1.3e-9 m/s (dop853, rtol 1e-10; the loops differ in step control only)."""
    _, model, st = _case(name)
    _, _, method, rtol = RUNS[name]
    mode, Q, QD, _, cnt = run_compiled(model, st, _times(name), method, rtol, rtol * 1e-2)
    ref = _python_loop(name)
    assert mode == "qr" and not ref.counters["compiled"]
    spread = STEP_SPREAD.get(name, 0.05)
    assert cnt.steps > 0 and abs(cnt.steps - ref.counters["steps"]) <= spread * cnt.steps + 2
    assert np.max(np.abs(Q - ref.q)) < 3e-9
    assert np.max(np.abs(QD - ref.qd)) < 1e-8
    cs = Index1Loop(model, {}, Counters()).cs
    assert max(np.max(np.abs(cs.phi(q, 0.0))) for q in Q) < 1e-12  # samples are projected
    assert max(np.max(np.abs(cs.jacobian(q, 0.0) @ v))
               for q, v in zip(Q, QD, strict=True)) < 1e-11


def test_five_bar_passes_its_singular_positions():
    """dopri5 at rtol 1e-6 through the -180 deg (t ~ 1.03 s) and the following singular
    position; compiled and Python loops agree to 4e-7 m measured."""
    case, model, st = _case("five_bar")
    _, Q, QD, _, cnt = run_compiled(model, st, case.times, "dopri5", 1e-6, 1e-8)
    ref = _python_loop("five_bar", "dopri5", 1e-6, end="all")
    assert cnt.steps < 200
    assert np.max(np.abs(Q - ref.q)) < 1e-5


@pytest.mark.parametrize("name", ["five_bar", "parallelogram_3d"])
def test_integrate_runs_natural_models_compiled(name):
    _, model, st = _case(name)
    _, _, method, rtol = RUNS[name]
    sol = integrate(model, st, _times(name), Solver(method=method,
                                                    step=Adaptive(rtol, rtol * 1e-2)))
    ref = _python_loop(name)
    assert sol.counters["compiled"]
    assert np.max(np.abs(sol.q - ref.q)) < 3e-9
    assert np.max(np.abs(sol.lam - ref.lam)) < 1e-6 * max(1.0, np.max(np.abs(ref.lam)))
