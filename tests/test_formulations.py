"""Formulations of natcoord.dynamics.formulations: derivatives, agreement, order, energy,
existence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from natcoord import ExistenceError, load_case
from natcoord.case.mechanism import Body, Driver, Joint
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.integrators import INTEGRATORS, DormandPrince5
from natcoord.dynamics.solver import FORMULATIONS, Adaptive, Index1, Solver
from natcoord.model.drivers import ConstraintSystem
from natcoord.model.kinematics import State
from tests.models import body_angle, body_columns, build_model, initial_state, replace


def _case(name):
    return load_case(f"cases/{name}.toml")


def _rigid_slider_model():
    """slider_crank with a rigid slider (prismatic 'no rotation' row) plus an angle driver
    and a coordinate driver: every constraint kind in one model."""
    c = _case("slider_crank")
    bodies = tuple(b if b.name != "slider" else Body(
        "slider", "rigid", 1.0, {"B": np.zeros(2), "E": np.array([0.5, 0.0])},
        np.array([0.25, 0.0]), 0.02) for b in c.bodies)
    drivers = (Driver("motor", "angle", "crank", 0.3, 2.0, 0.7),
               Driver("push", "coordinate", "rod", 0.1, -0.4, 1.3, point="B", axis="y"))
    return build_model(dataclasses.replace(c, bodies=bodies, drivers=drivers))


KINDS_MODEL = _rigid_slider_model()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_jacobian_and_acceleration_terms_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    cs = ConstraintSystem(KINDS_MODEL)
    kinds = {lab.split(": ")[-1] for lab in cs.labels}
    assert {"x", "y", "line.0", "no spin", "driver motor", "driver push"} <= \
        kinds | set(cs.labels)
    assert any(lab.startswith("rod: |") for lab in cs.labels)  # a body's length row
    n = cs.n
    q, qd, t = rng.normal(size=n), rng.normal(size=n), float(rng.uniform(0, 2))
    eps = 1e-6
    J = cs.jacobian(q, t)
    Jfd = np.stack([(cs.phi(q + eps * e, t) - cs.phi(q - eps * e, t)) / (2 * eps)
                    for e in np.eye(n)], 1)
    np.testing.assert_allclose(J, Jfd, atol=1e-7)
    pt_fd = (cs.phi(q, t + eps) - cs.phi(q, t - eps)) / (2 * eps)
    np.testing.assert_allclose(cs.phi_t(q, t), pt_fd, atol=1e-7)
    # along q(s) = q + s qd, t(s) = t + s (qdd = 0): d2 Phi / ds2 = -c
    e2 = 1e-4
    d2 = (cs.phi(q + e2 * qd, t + e2) - 2 * cs.phi(q, t) + cs.phi(q - e2 * qd, t - e2)) / e2**2
    np.testing.assert_allclose(-cs.gamma(q, qd, t), d2, atol=1e-5 * (1 + np.max(np.abs(d2))))


def _run(name, times, **settings):
    m = build_model(_case(name))
    return m, integrate(m, initial_state(m), times, Solver.from_settings(settings))


@pytest.mark.parametrize("name", ["slider_crank", "four_bar"])
def test_three_formulations_agree(name):
    times = np.linspace(0.0, 0.2, 5)
    m, ref = _run(name, times, formulation="index1", method="DOP853", rtol=1e-13, atol=1e-14)
    _, i1 = _run(name, times, formulation="index1", rtol=1e-12, atol=1e-13)
    _, mg = _run(name, times, formulation="maggi", rtol=1e-12, atol=1e-13)
    # index3 (order 2): Richardson extrapolation of h and h/2
    _, a = _run(name, times, formulation="index3", h=5e-4)
    _, b = _run(name, times, formulation="index3", h=2.5e-4)
    i3q, i3lam = (4 * b.q - a.q) / 3, (4 * b.lam - a.lam) / 3
    ang = {k: body_angle(m, "crank", s, s) for k, s in
           (("ref", ref.q), ("index1", i1.q), ("maggi", mg.q), ("index3", i3q))}
    scale = np.max(np.abs(ref.lam))
    for label, lam in (("index1", i1.lam), ("maggi", mg.lam), ("index3", i3lam)):
        assert np.max(np.abs(ang[label] - ang["ref"])) < 1e-8, f"{label}: crank angle"
        assert np.max(np.abs(lam - ref.lam)) < 1e-8 * scale, \
            f"{label}: reactions"
    for s in (i1, mg, a):
        assert s.counters["max_phi"] < 1e-11 and s.counters["max_phi_dot"] < 1e-9
        assert s.counters["steps"] > 0 and s.counters["factorizations"] > 0


@pytest.mark.parametrize("formulation, method, hs, order", [
    ("index1", "rk4", (0.02, 0.01, 0.005), 4),
    ("maggi", "rk4", (0.02, 0.01, 0.005), 4),
    ("index1", "dopri5", (0.025, 0.02, 0.0125, 0.01), 5),
    ("index3", "trapezoidal", (4e-3, 2e-3, 1e-3), 2),
])
def test_measured_order_of_convergence(formulation, method, hs, order):
    times = np.linspace(0.0, 0.2, 3)
    _, ref = _run("four_bar", times, formulation="index1", method="DOP853", rtol=1e-13,
                  atol=1e-14)
    err = [np.max(np.abs(_run("four_bar", times, formulation=formulation, method=method,
                              h=h)[1].q - ref.q)) for h in hs]
    slope = np.polyfit(np.log(hs), np.log(err), 1)[0]
    assert abs(slope - order) < 0.35, f"{formulation}/{method}: slope {slope:.2f}, {err}"


def test_dopri5_tableau_is_consistent():
    rk = DormandPrince5
    np.testing.assert_allclose(rk.A.sum(1), rk.C, atol=1e-15)
    assert abs(rk.B.sum() - 1) < 1e-15 and abs(rk.E.sum()) < 1e-15
    assert abs(rk.B @ rk.C - 0.5) < 1e-15 and abs(rk.B @ rk.C**4 - 0.2) < 1e-15
    assert {"rk4", "dopri5", "trapezoidal", "DOP853"} <= set(INTEGRATORS)
    assert set(FORMULATIONS) == {"index1", "maggi", "index3"}


@pytest.mark.parametrize("formulation", ["index1", "maggi", "index3"])
def test_energy_is_conserved(formulation):
    c = _case("four_bar")
    m = build_model(c)
    kw = {"h": 1e-3} if formulation == "index3" else {"rtol": 1e-10, "atol": 1e-12}
    sol = integrate(m, initial_state(m), np.linspace(0, 1.0, 11),
                    Solver.from_settings({"formulation": formulation, **kw}))
    e = 0.5 * np.einsum("ti,ij,tj->t", sol.qd, m.M, sol.qd) - sol.q @ m.Q0
    scale = np.max(np.abs(sol.q @ m.Q0))  # potential energy scale, J
    # index3: order 2 and the projections of qd are dissipative at O(h^2)
    assert np.ptp(e) < (1e-4 if formulation == "index3" else 5e-9) * scale, np.ptp(e) / scale


def _four_bar_variant(extra_joints=(), drop=(), massless=None):
    c = _case("four_bar")
    joints = tuple(j for j in c.joints if j.name not in drop) + tuple(extra_joints)
    m = build_model(dataclasses.replace(c, joints=joints))
    if massless:
        M = m.M.copy()
        cols = body_columns(m, massless)
        M[cols, :], M[:, cols] = 0.0, 0.0
        m = replace(m, M=M, Q0=np.where(np.isin(np.arange(m.n), cols), 0, m.Q0))
    return m


def test_existence_check_refuses_a_motion_without_kinetic_energy():
    # rocker free at D and massless: it can swing about C without kinetic energy
    m = _four_bar_variant(drop=("D",), massless="rocker")
    full = build_model(_case("four_bar"))
    s = initial_state(full)
    with pytest.raises(ExistenceError, match="rocker"):
        integrate(m, State(s.q, np.zeros_like(s.qd)), [0.0, 0.01])
    integrate(full, s, [0.0, 0.01])  # the same pose with the pivot D is fine


@pytest.mark.parametrize("formulation", ["index1", "maggi", "index3"])
def test_singular_mass_and_redundant_constraints(formulation):
    """A massless coupler (singular M) and a duplicated pivot (2 redundant rows) give the
    motion of the plain four-bar with a massless coupler."""
    times = np.linspace(0, 0.2, 3)
    base = _four_bar_variant(massless="coupler")
    D2 = Joint("D2", "revolute", ("ground", "rocker"), ("D", "D"))
    red = _four_bar_variant(extra_joints=(D2,), massless="coupler")
    assert red.m == base.m + 2
    ref = integrate(base, initial_state(base), times,
                    Solver(Index1(linsolve="qr"), "dop853", Adaptive(1e-12, 1e-13)))
    kw = {"h": 2.5e-4} if formulation == "index3" else {"rtol": 1e-12, "atol": 1e-13}
    sol = integrate(red, initial_state(red), times,
                    Solver.from_settings({"formulation": formulation, **kw}))
    tol = 1e-6 if formulation == "index3" else 1e-9
    assert np.max(np.abs(sol.q - ref.q)) < tol
    # the resultant constraint forces Phi_q^T lambda are determined (Eq. (54))
    Jr, Jb = ConstraintSystem(red), ConstraintSystem(base)
    for k in range(len(times)):
        fr = Jr.jacobian(sol.q[k]).T @ sol.lam[k]
        fb = Jb.jacobian(ref.q[k]).T @ ref.lam[k]
        assert np.max(np.abs(fr - fb)) < (1e-3 if formulation == "index3" else 1e-6)


@pytest.mark.parametrize("formulation, method", [("index1", "dop853"), ("index1", "dopri5"),
                                                 ("maggi", "dop853"), ("maggi", "dopri5")])
def test_adaptive_steps_cross_the_samples(formulation, method):
    """The Python loop steps across output samples and fills them from the continuous
    extension: the step count does not depend on the sampling, and samples inside steps
    are as accurate as step ends."""
    ref_times = np.linspace(0.0, 0.5, 501)
    _, ref = _run("four_bar", ref_times, formulation="index1", method="DOP853", rtol=1e-13,
                  atol=1e-14)
    kw = dict(formulation=formulation, method=method, rtol=1e-9, atol=1e-11,
              compiled=False)  # the Python loop (tests/test_compiled_* check the compiled)
    _, coarse = _run("four_bar", ref_times[::250], **kw)
    _, fine = _run("four_bar", ref_times, **kw)
    assert not fine.counters["compiled"]
    assert abs(fine.counters["steps"] - coarse.counters["steps"]) <= 2, \
        (fine.counters["steps"], coarse.counters["steps"])
    assert fine.counters["steps"] < 0.5 * len(ref_times)  # most samples are interpolated
    err_ends = np.max(np.abs(coarse.q - ref.q[::250]))
    err_all = np.max(np.abs(fine.q - ref.q))
    assert err_all < max(10 * err_ends, 1e-8), (err_all, err_ends)
    # interpolated samples lie on the constraints like step ends
    cs = ConstraintSystem(build_model(_case("four_bar")))
    drift = max(np.max(np.abs(cs.phi(q))) for q in fine.q)
    assert drift < (1e-11 if formulation == "index1" else 1e-9), drift
