"""Singular positions are passed at the case settings and across a neighbourhood of them.

A02's N-four-bar crosses the horizontal position, where Phi_q loses rank N and the
constraint manifold is two branches crossing. A state a rounding error off the manifold
sees a hyperbola there instead of the crossing and turns onto the other branch; how near
it comes depends on the last bits of Phi, which the BLAS kernel and the CPU change (the
former pivoted-QR settings of N = 2 stopped with a step-size underflow under 4 of 6
OpenBLAS kernels). The shared points with Phi summed in two doubles and projected to
round-off pass at every rtol from 1e-10 to 1e-12; tests/platform_matrix.py runs the case
settings under every kernel.
"""

from __future__ import annotations

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.derivations import exact
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.model.kinematics import singular_hint
from natcoord.outputs.result import evaluate_channels
from tests.conftest import CASES, REFERENCES


def _run(case, **over):
    settings = {k: v for k, v in case.engine("natcoord").settings.items()
                if k not in ("reference", "reference_check")} | over
    run = adapter("natcoord").run(case, initial_body_states(case), settings)
    return evaluate_channels(case, run.motion)


@pytest.mark.parametrize("rtol", [1e-10, 3e-11, 1e-11, 5e-12, 2e-12, 1e-12])
def test_a02_n2_passes_at_every_rtol_near_the_case_settings(rtol):
    """Measured against the exact reduction under the Haswell kernel and SkylakeX (an
    AVX-512 machine's default, whose initial velocities differ in the last bit): 1.6e-8 m
    at rtol 1e-10, 1.1e-9 m at 1e-11, 3.6-10.2e-9 m from 5e-12 to 1e-12; the passes amplify
    round-off (2.2e-7 m at 2e-11 under Haswell). Leaving the parallelogram branch costs
    metres."""
    case = load_case(CASES / "a02_four_bar_n2.toml")
    df = _run(case, rtol=rtol)
    ex = exact.n_four_bar(2, case.times)
    err = max(np.max(np.abs(df["x_B0"].to_numpy() - ex["x"])),
              np.max(np.abs(df["y_B0"].to_numpy() - ex["y"])))
    assert err < 1e-6  # on the parallelogram branch through all 10 passes
    if rtol <= 5e-12:
        assert err < case.engine("natcoord").tolerance["position"]  # the case's tolerance


@pytest.mark.slow
@pytest.mark.parametrize("rtol", [1e-10, 1e-11, 1e-12])
def test_a02_n40_passes_at_every_rtol_near_the_case_settings(rtol):
    """20 passes over 20 s, each on the parallelogram branch (leaving it costs metres):
    measured 7.7e-8 m at rtol 1e-10, within the case's 1e-8 m from 1e-11 down."""
    case = load_case(CASES / "a02_four_bar_n40.toml")
    df = _run(case, rtol=rtol)
    ex = exact.n_four_bar(40, case.times)
    err = np.max(np.abs(df["x_B0"].to_numpy() - ex["x"]))
    assert err < 1e-6
    if rtol <= 1e-11:
        assert err < 1e-8  # the case's tolerance


@pytest.mark.parametrize("rtol", [1e-10, 3e-11, 1e-11, 3e-12, 1e-12])
def test_five_bar_passes_at_every_rtol_near_the_case_settings(rtol):
    import pandas as pd
    case = load_case(CASES / "five_bar.toml")
    df = _run(case, rtol=rtol, atol=rtol * 1e-2)
    ref = pd.read_csv(REFERENCES / "five_bar.csv")
    assert np.max(np.abs(df["phi"].to_numpy() - ref["phi"].to_numpy())) < 1e-8


def test_a_failure_near_a_singular_position_names_the_rank_drop_and_what_to_change():
    """The message a step-size underflow gets there (both loops use it): how far from a
    rank drop Phi_q is, how many rows are about to drop out, and what to change."""
    rng = np.random.default_rng(1)
    U, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    V, _ = np.linalg.qr(rng.standard_normal((9, 9)))
    s = np.array([3.0, 2.0, 1.5, 1.0, 1e-7, 2e-7])
    J = U @ np.diag(s) @ V[:6]  # rank 6, two singular values 1e-7 of the largest
    msg = singular_hint(J, 1e-9)
    assert "singular position" in msg and "2 of its 6" in msg and "shared" in msg
    assert "3.3e-08" in msg  # 1e-7 / 3
    s[4:] = 0.5  # well conditioned: the failure has another cause, nothing is said
    assert singular_hint(U @ np.diag(s) @ V[:6], 1e-9) == ""
