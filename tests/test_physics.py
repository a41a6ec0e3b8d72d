"""natcoord's solution of the shipped cases against physics that cannot be argued with."""

from __future__ import annotations

import numpy as np
import pytest

from natcoord import evaluate_channels, load_case
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states

from .conftest import CASES, DATA


def _solve(path):
    case = load_case(path)
    run = adapter("natcoord").run(case, initial_body_states(case), {})
    return case, evaluate_channels(case, run.motion), run


@pytest.fixture(scope="module")
def slider_crank():
    return _solve(CASES / "slider_crank.toml")


@pytest.fixture(scope="module")
def four_bar():
    return _solve(CASES / "four_bar.toml")


def test_slider_crank_closed_form_position(slider_crank):
    """xB = L1 cos(theta) + sqrt(L2^2 - (L1 sin(theta))^2) at every sample."""
    _, df, _ = slider_crank
    th = df["theta"].to_numpy()
    closed = np.cos(th) + np.sqrt(4.0 - np.sin(th) ** 2)
    assert np.max(np.abs(df["xB"] - closed)) < 1e-10


def test_slider_vertical_balance(slider_crank):
    """The slider never accelerates vertically: rail normal force + rod force at B (both on
    the slider) balance its 1 kg weight at every sample. Checks the reaction signs too."""
    _, df, _ = slider_crank
    assert np.max(np.abs(df["N_slider"] + df["B_y"] - 9.81)) < 1e-9


@pytest.mark.parametrize("which", ["slider_crank", "four_bar"])
def test_energy_is_conserved(which, request):
    _, df, _ = request.getfixturevalue(which)
    e = df["energy"].to_numpy()
    assert np.ptp(e) < 1e-9 * max(1.0, abs(e[0]))


def test_four_bar_loop_closes(four_bar):
    """C reached through the crank-coupler chain equals C on the rocker (|D C| = 1.5)."""
    _, df, run = four_bar
    dc = np.hypot(df["xC"] - 2.0, df["yC"])
    ac = np.hypot(df["xC"] - df["xA"], df["yC"] - df["yA"])
    assert np.max(np.abs(dc - 1.5)) < 1e-10 and np.max(np.abs(ac - 2.0)) < 1e-10
    assert run.counters["max_phi"] < 1e-10


def test_hanging_rod_reaction_sign():
    """The pivot holds a hanging 2 kg rod up: force on the rod is +m g along y."""
    _, df, _ = _solve(DATA / "hanging_rod.toml")
    assert np.allclose(df["O_y"], 2.0 * 9.81, atol=1e-10)
    assert np.allclose(df["O_x"], 0.0, atol=1e-10)


def test_pendulum_reference_is_the_elliptic_solution():
    """IFToMM A01: the stored reference equals the exact solution (Jacobi elliptic functions):
    angle, position and the pivot force T (g cos(phi) + L phi'^2) along the link."""
    from scipy.special import ellipj, ellipk

    from natcoord.suite.references import load_reference

    from .conftest import REFERENCES

    ref = load_reference("pendulum", REFERENCES)
    g, L, m = 9.81, 1.0, 1.0
    k = np.sin(np.pi / 4)  # released from horizontal: amplitude 90 deg from the vertical
    K, w = ellipk(k**2), np.sqrt(g / L)
    t = ref["t"].to_numpy()
    sn, cn, dn, _ = ellipj(K - w * t, k**2)
    phi = 2 * np.arcsin(k * sn)  # from the downward vertical, counter-clockwise
    phi_dot = -2 * k * w * cn  # d/dt of 2 asin(k sn(K - w t)) = -2 k w cn
    assert 4 * K / w == pytest.approx(2.3678419, abs=1e-7)  # the published period
    assert np.max(np.abs(ref["theta"] - (phi - np.pi / 2))) < 1e-10
    assert np.max(np.abs(ref["x"] - L * np.sin(phi))) < 1e-10
    assert np.max(np.abs(ref["y"] + L * np.cos(phi))) < 1e-10
    T = m * (g * np.cos(phi) + L * phi_dot**2)
    assert np.max(np.abs(ref["O_x"] + T * np.sin(phi))) < 1e-8
    assert np.max(np.abs(ref["O_y"] - T * np.cos(phi))) < 1e-8
