"""DART adapter: reaction sign on a hanging rod, parity with natcoord on the closed loops,
first-order convergence, conversions (joint orientation, initial velocities, particles,
slides on a turning body, free bodies) and refusals/failures.

DART integrates with semi-implicit Euler only, so every error here is first-order model error
of the integrator (deterministic, not noise). Bounds are the errors measured at the adapter
defaults (dt 1e-4 s, BallJointConstraint, error-reduction parameter 1.0; dartpy 6.20) times
about 1.5.
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

pytest.importorskip("dartpy")

pytestmark = pytest.mark.engines

ROOT = Path(__file__).resolve().parents[1]
G = ec.G


def _run(case, settings=None):
    return ec.run("dart", case, settings)


@pytest.fixture(scope="module")
def reference():
    """natcoord's solution of the two closed loops (computed once)."""
    return {name: ec.natcoord(ec.case(name)) for name in ("slider_crank", "four_bar")}


# ------------------------------------------------------------------------------ reaction sign

def test_hanging_rod_pivot_pushes_up_with_mg():
    case = ec.hanging_rod()
    run = _run(case)
    table = evaluate_channels(case, run.motion)
    np.testing.assert_allclose(table["O_y"], 2.0 * G, rtol=0, atol=1e-10)  # measured 0
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)  # measured 7e-17
    np.testing.assert_allclose(table["theta"], -np.pi / 2, rtol=0, atol=1e-12)
    assert run.n_steps == round(case.duration / 1e-4) + 1  # + the step read for t = end
    assert run.build_time_s > 0 and run.wall_time_s > 0


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    """bodies = [rod, ground]: the reaction is then the force on the ground, -m g."""
    case = ec.hanging_rod()
    case = dataclasses.replace(case, joints=(ec.reversed_joint(case.joint("O")),))
    table = evaluate_channels(case, _run(case).motion)
    np.testing.assert_allclose(table["O_y"], -2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------ closed loops

# measured max |dart - natcoord| over 2 s at the defaults (dt 1e-4):
#   slider_crank: theta 7.54e-4 rad, xB 1.90e-4 m, reactions 8.8e-3 (A_y) .. 3.16e-2 N (O_x),
#   energy 3.08e-3 J;
#   four_bar: theta 1.13e-3 rad, positions 4.4e-4 .. 1.0e-3 m, reactions 4.9e-2 (D_x) ..
#   9.9e-2 N (D_y), energy 1.48e-2 J. Loop gap 1.7e-7 / 2.2e-7 m (~20 dt^2).
BOUNDS = {
    "slider_crank": {"angle": 1.2e-3, "position": 3e-4, "reaction": 5e-2, "energy": 5e-3},
    "four_bar": {"angle": 1.7e-3, "position": 1.5e-3, "reaction": 0.15, "energy": 2.2e-2},
}


@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_closed_loop_matches_natcoord(name, reference):
    case = ec.case(name)
    run = _run(case)
    err = ec.channel_errors(case, run, reference[name])
    bad = {c.name: err[c.name] for c in case.channels if not err[c.name] <= BOUNDS[name][c.kind]}
    assert not bad, f"{name}: channels beyond their bound: {bad}"
    assert run.n_steps == 20001
    assert run.counters["loop_drift_max_m"] < 5e-7
    notes = " | ".join(run.notes)
    assert "BallJointConstraint, error-reduction parameter 1.0" in notes
    assert "Newton-Euler" in notes


@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_first_order_in_dt(name, reference):
    """Semi-implicit Euler: halving dt halves the angle and the reaction errors."""
    case = ec.case(name)
    coarse = ec.channel_errors(case, _run(case, {"dt": 2e-4}), reference[name])
    fine = ec.channel_errors(case, _run(case, {"dt": 1e-4}), reference[name])
    ratio = coarse["theta"] / fine["theta"]
    assert 1.8 < ratio < 2.2, ratio  # measured 2.00 / 2.00 (order 1.00)
    reactions = [c.name for c in case.channels if c.kind == "reaction"]
    r = [coarse[c] / fine[c] for c in reactions]
    assert 1.7 < min(r) and max(r) < 2.3, dict(zip(reactions, r, strict=True))


def test_slider_crank_cuts_the_loop_at_a_revolute_and_says_so():
    case = dataclasses.replace(ec.case("slider_crank"), duration=0.01)
    notes = " | ".join(_run(case).notes)
    assert "loops cut at B" in notes
    assert "particle 'slider'" in notes and "angle is reported as 0" in notes


def test_four_bar_spinning_with_every_joint_reversed():
    """Initial velocity conversion and both reaction signs (tree, loop via Newton-Euler)."""
    case = dataclasses.replace(ec.case("four_bar"), duration=0.3, velocity={"theta": 3.0})
    flipped = dataclasses.replace(case, joints=tuple(ec.reversed_joint(j) for j in case.joints))
    runs = {}
    for c in (case, flipped):
        runs[c is flipped] = run = _run(c)
        err = ec.motion_errors(c, run.motion, ec.natcoord(c).motion)
        # measured: poses 1.1e-4, velocities 5.7e-4, forces 8.5e-3 N (D; peak ~300 N)
        assert max(v for k, v in err.items() if k.endswith((".origin", ".angle"))) < 2e-4, err
        assert max(v for k, v in err.items() if k.endswith((".velocity", ".omega"))) < 1e-3
        assert max(v for k, v in err.items() if k.endswith(".force")) < 1.5e-2, err
    for j in ("O", "A", "C", "D"):
        np.testing.assert_allclose(runs[True].motion.joint_force[j],
                                   -runs[False].motion.joint_force[j], rtol=0, atol=1e-6)


def test_moving_start_reactions_at_t0():
    """A loop constraint's first two steps are transients (about 10 N on D_y here); the t = 0
    reactions are extrapolated from steps 2 and 3."""
    case = dataclasses.replace(ec.case("four_bar"), duration=0.1, velocity={"theta": 3.0})
    a = evaluate_channels(case, ec.natcoord(case).motion)
    b = evaluate_channels(case, _run(case).motion)
    for ch in ("O_x", "O_y", "D_x", "D_y"):
        assert abs(a[ch][0] - b[ch][0]) < 0.02, ch  # measured <= 8.1e-3 N (D_y)


# ------------------------------------------------------------------------------ open chains

def _open_chain():
    """slider_crank without its slide: crank, rod and the particle hanging at B, moving."""
    case = ec.case("slider_crank")
    return dataclasses.replace(
        case, duration=0.3, joints=case.joints[:3],
        channels=(Channel("theta", "angle", body="crank"), Channel("phi", "angle", body="rod")),
        fix={"theta": 0.785398, "phi": -0.3}, velocity={"theta": 1.0, "phi": 2.0})


def test_open_chain_with_a_particle():
    case = _open_chain()
    err = ec.motion_errors(case, _run(case).motion, ec.natcoord(case).motion)
    # measured: poses 2.0e-4, velocities 6.5e-4, forces 5.0e-3 N
    assert max(v for k, v in err.items() if k.endswith((".origin", ".angle"))) < 3e-4, err
    assert max(v for k, v in err.items() if k.endswith((".velocity", ".omega"))) < 1e-3, err
    assert max(v for k, v in err.items() if k.endswith(".force")) < 8e-3, err


def test_free_bodies_fly_in_the_plane():
    """Only joint O: the rod and the particle fly free (DART planar joints)."""
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
    # measured: poses 1.8e-4 (free flight: semi-implicit Euler is off by g t dt / 2, exact in
    # velocity), velocities 1.8e-4, force at O 1.2e-3 N
    assert max(v for k, v in err.items() if not k.endswith(".force")) < 3e-4, err
    assert err["O.force"] < 2e-3, err
    assert any("body 'rod' is not joined to the ground" in n for n in run.notes)




@pytest.mark.parametrize("flip", [False, True])
def test_slide_on_a_turning_body(tmp_path, flip):
    """Prismatic tree joint with its axis in a turning body's frame (either orientation)."""
    case = load_case(DATA / "slot.toml")
    if flip:
        case = dataclasses.replace(case, joints=(case.joints[0], ec.reversed_joint(case.joints[1])))
    err = ec.motion_errors(case, _run(case).motion, ec.natcoord(case).motion)
    # measured: poses 2.2e-4, velocities 4.9e-4, forces 8.6e-4 N
    assert max(v for k, v in err.items() if k.endswith((".origin", ".angle"))) < 3.5e-4, err
    assert max(v for k, v in err.items() if k.endswith((".velocity", ".omega"))) < 8e-4, err
    assert max(v for k, v in err.items() if k.endswith(".force")) < 1.5e-3, err


# ------------------------------------------------------------------------------ refusals, failures

def test_three_dimensional_case_is_unsupported():
    case = dataclasses.replace(ec.hanging_rod(), dimension=3)
    with pytest.raises(Unsupported, match="2-D"):
        adapter("dart").run(case, {}, {})


def test_loop_of_prismatic_joints_is_unsupported():
    case = ec.case("slider_crank")
    slide = case.joint("slide")
    case = dataclasses.replace(case, joints=case.joints + (
        dataclasses.replace(slide, name="slide2"),))
    with pytest.raises(Unsupported, match="slide2"):
        adapter("dart").run(case, {}, {})  # refused before the state is used


def test_divergence_raises():
    """DART's RevoluteJointConstraint blows up at a high error-reduction parameter; DART
    itself only warns and substitutes identities, the adapter must fail."""
    case = dataclasses.replace(ec.case("four_bar"), duration=0.1)
    with pytest.raises(RuntimeError, match="DART diverged"):
        _run(case, {"loop_constraint": "revolute", "erp": 1.0})


def test_error_reduction_parameter_is_restored():
    import dartpy

    jc = dartpy.constraint.DynamicJointConstraint
    before = jc.getErrorReductionParameter()
    _run(dataclasses.replace(ec.case("four_bar"), duration=0.01), {"erp": 0.5})
    assert jc.getErrorReductionParameter() == before


def test_step_must_divide_the_output_interval():
    with pytest.raises(ValueError, match="divide"):
        _run(ec.hanging_rod(), {"dt": 3e-3})


def test_version_and_lazy_import():
    import dartpy

    assert adapter("dart").version() == dartpy.__version__
    code = ("import sys, natcoord.engines.dart_engine as m; "
            "assert 'dartpy' not in sys.modules; print(m.NAME, m.PACKAGE)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == ["dart", "dartpy"]
