"""MuJoCo adapter: reaction sign on a hanging rod, parity with natcoord on the closed loops,
conversions (initial velocities, joint orientation, particles, slides, floating bodies) and
failure detection.

Bounds on the closed loops are the errors measured at the adapter defaults (RK4, dt 1e-4 s,
connect solref 1e-3 s 1, solimp 0.9999; mujoco 4.0.0) times about 3. They are deterministic
model error of MuJoCo's soft loop constraint, not noise: the angle error scales with the square
of the solref time constant, the reaction error has a floor set by solimp (0.9999 is MuJoCo's
cap), largest at t = 0 before the constraint stabilisation settles. Open chains carry no soft
constraint and match natcoord to round-off.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from natcoord.casefile import load_case
from natcoord.engines import adapter
from natcoord.errors import Unsupported
from natcoord.mechanism import Channel
from natcoord.result import evaluate_channels

from . import engine_checks as ec
from .conftest import DATA

pytest.importorskip("mujoco")

pytestmark = pytest.mark.engines

ROOT = Path(__file__).resolve().parents[1]
G = ec.G


def _run(case, settings=None):
    return ec.run("mujoco", case, settings)


# ------------------------------------------------------------------------------ reaction sign

def test_hanging_rod_pivot_pushes_up_with_mg():
    case = ec.hanging_rod()
    run = _run(case)
    table = evaluate_channels(case, run.motion)
    np.testing.assert_allclose(table["O_y"], 2.0 * G, rtol=0, atol=1e-10)  # measured 0
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)  # measured 3e-15
    np.testing.assert_allclose(table["theta"], -np.pi / 2, rtol=0, atol=1e-12)
    assert run.n_steps == round(case.duration / 1e-4)
    assert run.build_time_s > 0 and run.wall_time_s > 0


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    """bodies = [rod, ground]: the reaction is then the force on the ground, -m g."""
    case = ec.hanging_rod()
    case = dataclasses.replace(case, joints=(ec.reversed_joint(case.joint("O")),))
    table = evaluate_channels(case, _run(case).motion)
    np.testing.assert_allclose(table["O_y"], -2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------ closed loops

# measured max |mujoco - natcoord| over 2 s at the defaults:
#   slider_crank: theta 1.09e-8 rad, xB 6.5e-9 m, reactions 1.5e-4..5.0e-4 N (t = 0), energy
#   9.7e-8 J; four_bar: theta 2.07e-8, positions 8.5e-9..1.92e-8, O 2.3e-4, D_y 1.59e-3 (t = 0),
#   energy 3.7e-7.
BOUNDS = {
    "slider_crank": {"angle": 3e-8, "position": 2e-8, "reaction": 1.5e-3, "energy": 3e-7},
    "four_bar": {"angle": 6e-8, "position": 6e-8, "reaction": 5e-3, "energy": 1.2e-6},
}


@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_closed_loop_matches_natcoord(name):
    case = load_case(ROOT / "cases" / f"{name}.toml")
    ref = evaluate_channels(case, ec.natcoord(case).motion)
    run = _run(case)
    table = evaluate_channels(case, run.motion)
    assert list(table.columns) == list(ref.columns)
    np.testing.assert_array_equal(table["t"], ref["t"])
    bad = {}
    for ch in case.channels:
        err = float(np.max(np.abs(table[ch.name] - ref[ch.name])))
        if not err <= BOUNDS[name][ch.kind]:
            bad[ch.name] = err
    assert not bad, f"{name}: channels beyond their bound: {bad}"
    assert run.n_steps == 20000
    assert run.counters["loop_drift_m"] < 2e-8  # measured 4.5e-9 / 5.1e-9 m
    assert any("connect equality" in n for n in run.notes)


def test_slider_crank_cuts_the_loop_at_a_revolute_and_says_so():
    case = load_case(ROOT / "cases" / "slider_crank.toml")
    notes = " | ".join(_run(dataclasses.replace(case, duration=0.01)).notes)
    assert "loop cut at revolute B instead of prismatic slide" in notes
    assert "particle slider given inertia" in notes


def test_four_bar_spinning_with_every_joint_reversed():
    """Initial velocity conversion and both reaction signs (tree and connect), body by body."""
    case = load_case(ROOT / "cases" / "four_bar.toml")
    case = dataclasses.replace(case, duration=0.3, velocity={"theta": 2.0})
    flipped = dataclasses.replace(case, joints=tuple(ec.reversed_joint(j) for j in case.joints))
    for c in (case, flipped):
        err = ec.motion_errors(c, _run(c).motion, ec.natcoord(c).motion)
        # measured: poses 7.4e-10, velocities 3.5e-9, forces 1.4e-3 (D at t = 0)
        assert max(v for k, v in err.items() if not k.endswith(".force")) < 2e-8, err
        assert max(v for k, v in err.items() if k.endswith(".force")) < 5e-3, err
    f0 = _run(case).motion.joint_force
    f1 = _run(flipped).motion.joint_force
    for j in ("O", "A", "C", "D"):
        np.testing.assert_allclose(f1[j], -f0[j], rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ open chains

def _open_chain():
    """slider_crank without its slide: crank, rod and the particle hanging at B, moving."""
    case = load_case(ROOT / "cases" / "slider_crank.toml")
    return dataclasses.replace(
        case, duration=0.3, joints=case.joints[:3],
        channels=(Channel("theta", "angle", body="crank"), Channel("phi", "angle", body="rod")),
        fix={"theta": 0.785398, "phi": -0.3}, velocity={"theta": 1.0, "phi": 2.0})


def test_particle_welded_at_its_revolute_is_exact():
    case = _open_chain()
    run = _run(case)
    err = ec.motion_errors(case, run.motion, ec.natcoord(case).motion)
    assert max(err.values()) < 1e-11, err  # measured 1.3e-13
    assert any("particle slider welded" in n for n in run.notes)


def test_floating_bodies_slide_and_turn_in_the_plane():
    """Only joint O: the rod (slide x, y, hinge z) and the particle (slide x, y) fly free."""
    base = _open_chain()
    case = dataclasses.replace(
        base, joints=base.joints[:1],
        channels=(Channel("theta", "angle", body="crank"), Channel("phi", "angle", body="rod"),
                  Channel("xA", "position", body="rod", point="A", axis="x"),
                  Channel("yA", "position", body="rod", point="A", axis="y"),
                  Channel("xB", "position", body="slider", point="B", axis="x"),
                  Channel("yB", "position", body="slider", point="B", axis="y")),
        fix={"theta": 0.785398, "phi": 0.3, "xA": 0.7, "yA": 0.7, "xB": 1.0, "yB": 2.0},
        velocity={"theta": 1.0, "phi": -2.0, "xA": 0.5, "yA": 1.0, "xB": -1.0, "yB": 3.0})
    run = _run(case)
    err = ec.motion_errors(case, run.motion, ec.natcoord(case).motion)
    assert max(err.values()) < 1e-11, err  # measured 2.9e-13
    assert any("body rod is not joined to the ground" in n for n in run.notes)




def test_slide_on_a_rotating_body_is_exact(tmp_path):
    case = load_case(DATA / "slot.toml")
    err = ec.motion_errors(case, _run(case).motion, ec.natcoord(case).motion)
    assert max(err.values()) < 1e-11, err  # measured 5.9e-15


# ------------------------------------------------------------------------------ refusals, failures

def test_drivers_are_unsupported():
    case = load_case(ROOT / "cases" / "slider_crank.toml")
    if "drivers" not in {f.name for f in dataclasses.fields(case)}:
        pytest.skip("this natcoord has no drivers")
    driven = ROOT / "cases" / "slider_crank_driven.toml"
    if not driven.exists():
        pytest.skip("no driven case")
    with pytest.raises(Unsupported, match="drivers"):
        adapter("mujoco").run(load_case(driven), {}, {})


def test_loop_of_prismatic_joints_is_unsupported():
    case = load_case(ROOT / "cases" / "slider_crank.toml")
    slide = case.joint("slide")
    case = dataclasses.replace(case, joints=case.joints + (
        dataclasses.replace(slide, name="slide2"),))
    with pytest.raises(Unsupported, match="slide2"):
        adapter("mujoco").run(case, {}, {})  # refused before the state is used


def test_instability_raises_instead_of_resetting(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT to the working directory
    case = load_case(ROOT / "cases" / "four_bar.toml")
    case = dataclasses.replace(case, duration=0.1, velocity={"theta": 1e6})
    with pytest.raises(RuntimeError, match="MuJoCo warned .*unstable"):
        _run(case, {"dt": 0.01})


def test_open_loop_is_a_failure_not_a_result():
    case = load_case(ROOT / "cases" / "four_bar.toml")
    case = dataclasses.replace(case, duration=0.1, velocity={"theta": 50.0})
    with pytest.raises(RuntimeError, match="loop opened"):
        _run(case, {"dt": 0.01, "solref_steps": 2})


def test_step_must_divide_the_output_interval():
    with pytest.raises(ValueError, match="divide"):
        _run(ec.hanging_rod(), {"dt": 3e-3})


def test_version_and_lazy_import():
    import mujoco

    assert adapter("mujoco").version() == mujoco.__version__
    code = ("import sys, natcoord.engines.mujoco_engine as m; "
            "assert 'mujoco' not in sys.modules; print(m.NAME, m.PACKAGE)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == ["mujoco", "mujoco"]
