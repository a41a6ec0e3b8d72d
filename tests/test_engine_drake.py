"""Drake adapter: reaction sign on a hanging rod, agreement with the stored references on
the closed loops (discrete SAP plant, ball-constraint loops) and on an open pendulum (the
continuous plant), first-order convergence of the soft loops under dt, and a missing
pydrake becoming ``skipped`` with its pip command.

Bounds are the errors measured (drake 1.51.1) times about 2; the loop errors are the SAP
time-stepping's (first order: the constraints are soft, with a compliance set by the time
step), deterministic, not noise.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pydrake", reason="pydrake (pip install drake) is not installed")

from natcoord.outputs.result import evaluate_channels  # noqa: E402
from natcoord.suite.references import load_reference  # noqa: E402

from . import engine_checks as ec  # noqa: E402
from .conftest import REFERENCES, ROOT  # noqa: E402

pytestmark = pytest.mark.engines


def _errors(case, settings: dict | None = None):
    """Drake's run of ``case`` (a shipped case, maybe shortened) and its max error per
    channel against the stored reference."""
    run = ec.run("drake", case, settings)
    ref, got = load_reference(case.name, REFERENCES), evaluate_channels(case, run.motion)
    n = len(got)
    np.testing.assert_allclose(got["t"], ref["t"].iloc[:n], rtol=0, atol=1e-12)
    return run, {ch.name: float(np.max(np.abs(got[ch.name] - ref[ch.name].iloc[:n])))
                 for ch in case.channels}


@pytest.mark.parametrize("plant", ["discrete", "continuous"])
def test_hanging_rod_pivot_pushes_up_with_mg(plant):
    """Drake's reaction (parent on child at the joint) is natcoord's: + m g up."""
    c = ec.hanging_rod()
    table = evaluate_channels(c, ec.run("drake", c, {"plant": plant}).motion)
    np.testing.assert_allclose(table["O_y"], 2.0 * ec.G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["theta"], -np.pi / 2, rtol=0, atol=1e-12)


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    ec.assert_reversed_joint_flips_the_reaction("drake")


def test_version_and_lazy_import():
    from importlib.metadata import version

    assert ec.adapter("drake").version() == version("drake")
    code = ("import sys, natcoord.engines.drake_engine as m; "
            "assert 'pydrake' not in sys.modules; print(m.NAME, m.PACKAGE)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == ["drake", "drake"]


# measured at dt 1e-4 over 2 s against the references (peaks: four_bar 176 N, slider_crank
# 74 N): four_bar theta 6.7e-4 rad, positions <= 5.9e-4 m, reactions <= 0.19 N, energy
# 9.9e-3 J; slider_crank theta 7.5e-4 rad, xB 1.9e-4 m, reactions <= 3.2e-2 N, energy 3.1e-3 J
BOUNDS = {
    "four_bar": {"angle": 1.5e-3, "position": 1.2e-3, "reaction": 0.4, "energy": 2e-2},
    "slider_crank": {"angle": 1.5e-3, "position": 4e-4, "reaction": 7e-2, "energy": 7e-3},
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_closed_loop_matches_the_reference(name):
    c = ec.case(name)
    run, err = _errors(c, {"dt": 1e-4})
    bad = {k: v for k, v in err.items() if not v <= BOUNDS[name][c.channel(k).kind]}
    assert not bad, bad
    assert run.n_steps == 20000
    assert run.counters["loop_gap_m"] < 1e-6  # measured 4.4e-7 / 3.4e-7 m
    assert any("AddBallConstraint" in n for n in run.notes)


def test_loops_converge_at_first_order_in_dt():
    """four_bar over 0.5 s: SAP holds the ball constraint softly (compliance ~ dt), so the
    crank angle error and the loop gap shrink ~10x and ~100x per 10x dt."""
    c = dataclasses.replace(ec.case("four_bar"), duration=0.5)
    coarse, e1 = _errors(c, {"dt": 1e-3})
    fine, e2 = _errors(c, {"dt": 1e-4})
    ratio = e1["theta"] / e2["theta"]
    assert 7.0 < ratio < 13.0, (e1["theta"], e2["theta"])
    gap = coarse.counters["loop_gap_m"] / fine.counters["loop_gap_m"]
    assert 50.0 < gap < 200.0, (coarse.counters, fine.counters)


def test_open_pendulum_on_the_continuous_plant_matches_the_reference():
    """No constraint: the continuous plant's error-controlled RK5 is as accurate as asked."""
    c = dataclasses.replace(ec.case("pendulum"), duration=2.0)
    run, err = _errors(c, {"plant": "continuous", "accuracy": 1e-10})
    assert err["theta"] < 1e-8, err  # measured 1.1e-9 rad over 10 s
    assert max(err["O_x"], err["O_y"]) < 1e-6, err  # measured 2.8e-8 N
    assert "continuous" in " ".join(run.notes)


def test_constraints_need_the_discrete_plant():
    with pytest.raises(ec.Unsupported, match="continuous MultibodyPlant refuses constraints"):
        ec.run("drake", ec.case("four_bar"), {"plant": "continuous"})


def test_drivers_and_rods_are_unsupported_with_the_reason():
    with pytest.raises(ec.Unsupported, match="prescribed motions"):
        ec.run("drake", ec.case("slider_crank_driven"))
    with pytest.raises(ec.Unsupported, match="massless rods"):
        ec.run("drake", ec.case("five_bar"))


def test_loop_of_prismatic_joints_is_unsupported():
    ec.assert_loop_of_prismatic_joints_is_unsupported("drake")


def test_step_must_divide_the_output_interval():
    ec.assert_step_must_divide_the_output_interval("drake", 3e-3, "must divide")


def test_missing_pydrake_is_skipped_with_its_pip_command():
    """pydrake blocked in a fresh process: the worker records ``skipped`` and says how to
    install it, without running anything."""
    code = (
        "import sys; sys.modules['pydrake'] = None\n"
        "from natcoord.case.casefile import load_case\n"
        "from natcoord.engines.base import initial_body_states\n"
        "from natcoord.suite.worker import Job, run_one\n"
        f"c = load_case({str(ROOT / 'cases' / 'four_bar.toml')!r})\n"
        "r = run_one(Job(c, initial_body_states(c), 'drake'))\n"
        "print(r.status.value if hasattr(r.status, 'value') else r.status); print(r.reason)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    status, reason = out.stdout.strip().split("\n", 1)
    assert status == "skipped", out.stdout
    assert "pip install drake" in reason
