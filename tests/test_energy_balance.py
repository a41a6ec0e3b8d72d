"""The energy balance channel (``kind = "energy", work = true``, natcoord.outputs.result.work):
kinetic + gravitational + spring energy minus the work applied loads, dampers and drivers
did since t = 0 stays at its value at t = 0 along natcoord's trajectories; which energy
channels are balances; how a case file says so."""

import dataclasses

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.case.mechanism import Channel, Force
from natcoord.engines import adapter
from natcoord.errors import CaseError
from natcoord.outputs.result import Motion, energy, evaluate_channels, is_balance, work
from tests.conftest import CASES

BALANCE = Channel("balance", "energy", work=True)


def _natcoord(case, settings=None, **replace):
    case = dataclasses.replace(case, **replace) if replace else case
    run = adapter("natcoord").run(case, None, settings or case.engine("natcoord").settings)
    return case, run.motion


def _drift(b: np.ndarray) -> float:
    return float(np.max(np.abs(b - b[0])))


def test_which_energy_channels_are_balances():
    """Conservative catalogue cases: ``energy`` is the balance. A03 (motor torque) and A05
    (dampers): only their ``balance`` channel (work = true) is."""
    for name in ("a01_pendulum", "a02_four_bar_n2", "a04_bricard", "slider_crank_3d"):
        case = load_case(CASES / f"{name}.toml")
        assert is_balance(case, case.channel("energy")), name
    for name in ("a03_andrews", "a05_flyball_governor"):
        case = load_case(CASES / f"{name}.toml")
        assert not is_balance(case, case.channel("energy")), name
        assert case.channel("balance").work and is_balance(case, case.channel("balance"))
        assert not case.channel("energy").work


def test_work_must_be_a_boolean(case_variant):
    path = case_variant("a03_andrews", [(r"work = true", "work = 1")])
    with pytest.raises(CaseError, match="work"):
        load_case(path)


def test_andrews_motor_work_is_exact():
    """A03: the motor torque feeds 0.52 J into kinetic + spring energy in 0.03 s; the balance
    (energy - mom (beta - beta0), exact from the crank angle) holds to 1e-10 J (measured
    7.3e-11 J at the case's settings, dop853 rtol 1e-11)."""
    case, motion = _natcoord(load_case(CASES / "a03_andrews.toml"))
    table = evaluate_channels(case, motion)
    assert np.ptp(table["energy"]) > 0.5
    assert _drift(table["balance"].to_numpy()) < 1e-10
    mom = case.forces[0].value
    beta = table["beta"].to_numpy()
    np.testing.assert_allclose(work(case, motion), mom * (beta - beta[0]), rtol=0, atol=1e-14)


@pytest.fixture(scope="module")
def flyball():
    """A05 over its first 0.3 s, sampled every 1e-4 s (natcoord dop853 rtol 1e-11)."""
    case = load_case(CASES / "a05_flyball_governor.toml")
    return _natcoord(case, {"method": "dop853", "rtol": 1e-11, "atol": 1e-13},
                     duration=0.3, output_dt=1e-4)


def _every(case, motion: Motion, k: int):
    """The same trajectory sampled at every k-th output time."""
    def f(d):
        return {n: v[::k] for n, v in d.items()}
    short = dataclasses.replace(case, output_dt=case.output_dt * k)
    return short, Motion(motion.t[::k], f(motion.origin), f(motion.angle), f(motion.velocity),
                         f(motion.omega), rotation=f(motion.rotation))


def test_flyball_balance_with_the_damper_work(flyball):
    """A05 sampled every 1e-4 s: the dampers dissipate 2.4e-3 J in 0.3 s (c (dl/dt)^2
    integrated over the samples) and kinetic + gravitational + spring energy + that stays
    constant to 1e-6 J (measured 1.8e-7 J, all of it in the first steps: the dampers' fast
    mode, ~3e4 1/s, is not resolved by 1e-4 s samples; after 1 ms flat to 1e-10 J,
    measured 3.9e-12 J)."""
    case, motion = flyball
    table = evaluate_channels(case, motion)
    W = work(case, motion)
    assert W[-1] < -2e-3 and np.all(np.diff(W) <= 0)  # dampers only take energy out
    b = table["balance"].to_numpy()
    np.testing.assert_allclose(b, table["energy"].to_numpy() - W, rtol=0, atol=1e-12)
    assert _drift(b) < 1e-6
    assert _drift(b[10:]) < 1e-10  # after 1 ms
    assert _drift(table["energy"].to_numpy()) > 2e-3  # the check has content


def test_flyball_balance_at_the_case_sampling(flyball):
    """The same trajectory at the case's own sampling (every 0.01 s): the quadrature misses
    the dampers' start-up transient between the first samples (an offset of 3.4e-4 J of the
    2.4e-3 J dissipated, ringing for a few samples), then the balance is flat: within 1e-6 J
    from t = 0.05 s on (measured 1.5e-7 J). So a drift plot of A05 shows this offset for
    every engine, the reference included."""
    case, motion = _every(*flyball, 100)
    b = evaluate_channels(case, motion)["balance"].to_numpy()
    assert 1e-4 < _drift(b) < 1e-3
    assert _drift(b[5:]) < 1e-6


def test_driver_work():
    """slider_crank_driven (natcoord reports the driver's torque): the driver's work, its
    torque times the prescribed rate integrated over the 0.01 s samples (cubic spline),
    balances the energy to 5e-6 of the 40 J it moves in and out (measured 4.0e-5 J,
    1.0e-6; at 1e-4 s samples 4.9e-12 J: the quadrature's error)."""
    case = load_case(CASES / "slider_crank_driven.toml")
    case, motion = _natcoord(case, channels=case.channels + (BALANCE,))
    table = evaluate_channels(case, motion)
    W = work(case, motion)
    assert np.ptp(W) > 10.0
    assert _drift(table["balance"].to_numpy()) < 5e-6 * np.ptp(W)


def test_3d_torque_work():
    """slider_crank_3d with a constant 0.05 N m world torque about the crank's axis x, over
    1 s sampled every 2 ms: the torque's work, tau . omega integrated over the samples, is
    tau times the crank's turn (to 3e-7 J, measured 7.3e-8 J: the quadrature's error) and
    balances the energy to 1e-6 J of 0.84 J (measured 7.3e-8 J; 1.8e-4 J at 0.01 s
    samples: the crank's rate jumps from 5.8 to 38 rad/s at the slider's dead points, so the
    quadrature needs fine samples)."""
    case = load_case(CASES / "slider_crank_3d.toml")
    torque = Force("torque", "crank", np.array([0.05, 0.0, 0.0]))
    case, motion = _natcoord(case, {"method": "dop853", "rtol": 1e-12, "atol": 1e-14},
                             duration=1.0, output_dt=2e-3, forces=(torque,),
                             channels=case.channels + (BALANCE,))
    assert not is_balance(case, case.channel("energy"))
    table = evaluate_channels(case, motion)
    W = work(case, motion)
    theta = table["theta"].to_numpy()
    assert W[-1] > 0.8
    np.testing.assert_allclose(W, 0.05 * (theta - theta[0]), rtol=0, atol=3e-7)
    b = table["balance"].to_numpy()
    assert _drift(b) < 1e-6
    np.testing.assert_allclose(b, energy(case, motion) - W, rtol=0, atol=1e-12)


def test_3d_torque_work_is_exact_about_a_fixed_axis():
    """The same torque sampled every 5 ms: the crank turns about its fixed hinge, so the
    rotations at the samples give its turn exactly, and the work is tau times the crank's
    turn to round-off (measured 9.8e-13 J of 0.84 J; 7.3e-6 J when tau . omega was
    integrated over the samples)."""
    case = load_case(CASES / "slider_crank_3d.toml")
    torque = Force("torque", "crank", np.array([0.05, 0.0, 0.0]))
    case, motion = _natcoord(case, {"method": "dop853", "rtol": 1e-12, "atol": 1e-14},
                             duration=1.0, output_dt=5e-3, forces=(torque,),
                             channels=case.channels + (BALANCE,))
    table = evaluate_channels(case, motion)
    theta = table["theta"].to_numpy()
    np.testing.assert_allclose(work(case, motion), 0.05 * (theta - theta[0]), rtol=0,
                               atol=1e-10)
    assert _drift(table["balance"].to_numpy()) < 1e-10


def test_3d_torque_work_on_a_tumbling_body(tmp_path):
    """A body with a full inertia tensor on a spherical joint under gravity, spinning and
    tumbling, with a constant world torque (0.3, -0.2, 0.4) N m feeding 3.2 J in 1 s: its
    axis moves, so the turn across the rotation vector comes from the spline of omega; at
    10 ms samples the balance holds to 1e-8 J (measured 3.9e-9 J; 4.7e-9 J by tau . omega
    over the samples, 2.4e-8 J by the rotation vectors alone), fourth order (2.3e-10 J at
    5 ms)."""
    from tests.test_channels import _spin

    case = _spin(tmp_path, 'type = "spherical"', 3.0, -9.81)
    torque = Force("torque", "b", np.array([0.3, -0.2, 0.4]))
    case, motion = _natcoord(case, {"method": "dop853", "rtol": 1e-12, "atol": 1e-14},
                             forces=(torque,), channels=case.channels + (BALANCE,))
    table = evaluate_channels(case, motion)
    assert work(case, motion)[-1] > 3.0
    assert _drift(table["balance"].to_numpy()) < 1e-8
