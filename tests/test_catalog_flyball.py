"""IFToMM A05, the stiff flyball governor (cases/a05_flyball_governor.toml): geometry and
initial state as specified, energy balance with the damper work, conservation of the
angular momentum about the shaft, convergence of natcoord's s(t), and agreement of the best
engine with natcoord's stored reference."""

import dataclasses
import tomllib

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.engines import adapter
from natcoord.outputs.channels import initial_body_states
from natcoord.outputs.result import evaluate_channels, point_position, point_velocity
from natcoord.suite.references import load_reference
from tests.conftest import CASES, REFERENCES

OMEGA0 = 2 * np.pi  # rad/s, the specification's shaft rate at t = 0


@pytest.fixture(scope="module")
def case():
    return load_case(CASES / "a05_flyball_governor.toml")


def _run(case, settings: dict, duration: float, output_dt: float | None = None):
    """natcoord's run of the case cut to ``duration`` s (samples every ``output_dt`` s)."""
    short = dataclasses.replace(case, duration=duration,
                                output_dt=output_dt or case.output_dt)
    run = adapter("natcoord").run(short, None, settings)
    return short, run.motion


def test_spring_rest_length_is_the_specified_half_metre(case):
    """The rest length is the distance at t = 0 (the case format has no other); the file's
    points must make it the specification's 0.5 m, before and after assembly."""
    assert [s.name for s in case.springs] == ["kA", "kB"]
    for s in case.springs:
        assert s.length == pytest.approx(0.5, abs=1e-12)
        assert (s.stiffness, s.damping) == (8e5, 4e4)
    short, motion = _run(case, {"method": "dop853", "rtol": 1e-10, "atol": 1e-12}, 0.0)
    for s in case.springs:
        pa, pb = (point_position(short, motion, b, short.body(b).points[p])[0]
                  for b, p in s.ends)
        assert np.linalg.norm(pb - pa) == pytest.approx(0.5, abs=1e-12)


def test_initial_state_is_a_rigid_rotation_at_two_pi(case):
    """Every body turns at 2 pi rad/s about z and no point moves along z or radially: the
    four initial rates of the file fix exactly the specification's rigid rotation. The rod's
    centre of mass moves at 2 pi (0.05 + d cos 30 deg) = 5.6015555 m/s, the value Exudyn's
    port prints (references/published.toml)."""
    init = initial_body_states(case)
    for name in ("shaft", "slider", "rodA", "rodB"):
        assert np.allclose(init[name].omega, [0, 0, OMEGA0], atol=1e-12), name
    pub = tomllib.loads((REFERENCES / "published.toml").read_text())["a05_flyball_governor"]
    for rod, sign in (("rodA", 1), ("rodB", -1)):
        b = case.body(rod)
        v = init[rod].velocity + np.cross(init[rod].omega, init[rod].rotation @ b.com)
        assert np.allclose(v, [0, sign * pub["rod_com_speed_t0"], 0], atol=1e-7), rod
    assert case.body("rodA").mass == pytest.approx(0.3 + 5.0)
    assert case.body("shaft").mass + case.body("slider").mass == pytest.approx(3.3)


def _spring_rates(short, motion):
    """Elongation rate dl/dt (T,) of each spring, m/s, from the end-point velocities."""
    out = {}
    for s in short.springs:
        (ba, pa), (bb, pb) = s.ends
        xa = point_position(short, motion, ba, short.body(ba).points[pa])
        xb = point_position(short, motion, bb, short.body(bb).points[pb])
        va = point_velocity(short, motion, ba, short.body(ba).points[pa])
        vb = point_velocity(short, motion, bb, short.body(bb).points[pb])
        e = (xb - xa) / np.linalg.norm(xb - xa, axis=1)[:, None]
        out[s.name] = np.sum(e * (vb - va), axis=1)
    return out


def _angular_momentum_z(short, motion) -> np.ndarray:
    """L_z about the origin (T,), kg m^2/s: sum of m (r x v)_z + (R I R^T omega)_z."""
    L = np.zeros(len(motion.t))
    for b in short.bodies:
        r = point_position(short, motion, b.name, b.com)
        v = point_velocity(short, motion, b.name, b.com)
        R = motion.R(b.name)
        Iw = np.einsum("tij,jk,tlk,tl->ti", R, b.inertia, R, motion.omega[b.name])
        L += b.mass * np.cross(r, v)[:, 2] + Iw[:, 2]
    return L


def test_energy_balance_and_angular_momentum(case):
    """Over the first 0.3 s (the dampers' start-up transient, sampled every 1e-4 s):
    kinetic + gravitational + spring energy + the work the dampers dissipated (the integral
    of c (dl/dt)^2) stays at its initial value, the mechanical energy never rises, and the
    angular momentum about the shaft axis is constant (gravity and the bearing exert no
    moment about z)."""
    short, motion = _run(case, {"method": "dop853", "rtol": 1e-11, "atol": 1e-13}, 0.3, 1e-4)
    E = evaluate_channels(short, motion)["energy"].to_numpy()
    rates = _spring_rates(short, motion)
    power = sum(s.damping * rates[s.name] ** 2 for s in short.springs)  # W, >= 0
    dt = short.output_dt
    W = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1]) * dt)])
    assert W[-1] > 1e-3  # the dampers do dissipate (about 2.4e-3 J): the check has content
    assert np.max(np.abs(E + W - E[0])) < 1e-3 * W[-1]  # measured 1.2e-4 W (trapezoid)
    assert np.all(np.diff(E) < 1e-9)  # monotone up to the integration error
    L = _angular_momentum_z(short, motion)
    assert L[0] > 1.0
    assert np.max(np.abs(L - L[0])) < 1e-11 * L[0]  # measured 1.8e-14 relative


def test_s_converges_as_the_tolerance_tightens(case):
    """natcoord's s(t) over 0.5 s (the slider's first rise to 0.743 m) against its run at
    rtol 1e-11: the error falls by at least 100x per two decades of rtol and is below 1e-9 m
    at rtol 1e-8 (measured: 2.2e-8 m at 1e-6, 2.3e-12 m at 1e-8)."""
    runs = {r: evaluate_channels(*_run(case, {"method": "dop853", "rtol": r,
                                              "atol": r * 1e-2}, 0.5))["s"].to_numpy()
            for r in (1e-6, 1e-8, 1e-11)}
    e6, e8 = (np.max(np.abs(runs[r] - runs[1e-11])) for r in (1e-6, 1e-8))
    assert runs[1e-11].max() == pytest.approx(0.7433, abs=1e-3)
    assert e8 < 1e-9
    assert e8 < e6 / 100


def test_mujoco_agrees_with_the_reference(case):
    """MuJoCo (RK4, dt 1e-4 s, the case's settings) follows natcoord's stored reference of
    s(t), the shaft angle and the energy over the whole 10 s, within the case's tolerance
    (a few times the measured difference, itself above the reference's own error
    estimate)."""
    ref = load_reference(case.name, REFERENCES)
    assert ref is not None, "no stored reference: run natcoord reference update"
    spec = case.engine("mujoco")
    run = adapter("mujoco").run(case, initial_body_states(case), spec.settings)
    out = evaluate_channels(case, run.motion)
    for name in ("s", "psi", "zA", "energy"):
        err = np.max(np.abs(out[name].to_numpy() - ref[name].to_numpy()))
        assert err <= spec.tolerance_for(case.channel(name)), (name, err)
    assert ref["s"].max() > 0.74 and ref["s"].min() == pytest.approx(0.5, abs=1e-3)
