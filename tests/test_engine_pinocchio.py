"""Pinocchio adapter: reaction sign on a hanging rod, parity with natcoord on the closed loops.

Bounds are the errors measured at the adapter defaults (RK4, dt 1e-3 s; pin 4.1) times a
margin of about 5; they are RK4 truncation error (it falls 16x per halved dt), not noise.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from natcoord.casefile import load_case
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.result import evaluate_channels

from . import engine_checks as ec

pytest.importorskip("pinocchio")

pytestmark = pytest.mark.engines

ROOT = Path(__file__).resolve().parents[1]
G = ec.G


def _run(case, settings=None):
    return ec.run("pinocchio", case, settings)


def test_hanging_rod_pivot_pushes_up_with_mg():
    case = ec.hanging_rod()
    run = _run(case)
    table = evaluate_channels(case, run.motion)
    np.testing.assert_allclose(table["O_y"], 2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["theta"], -np.pi / 2, rtol=0, atol=1e-12)
    assert run.n_steps == round(case.duration / 1e-3)


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    """bodies = [rod, ground]: the reaction is then the force on the ground, -m g."""
    case = ec.hanging_rod()
    case = dataclasses.replace(case, joints=(ec.reversed_joint(case.joint("O")),))
    table = evaluate_channels(case, _run(case).motion)
    np.testing.assert_allclose(table["O_y"], -2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)


# measured max |pinocchio - natcoord| (dt 1e-3): slider_crank angle 6.1e-11 rad, position
# 8.8e-10 m, reaction 1.3e-8 N, energy 2.2e-9 J; four_bar 9.2e-10, 8.7e-10, 1.8e-7, 9.9e-9.
BOUNDS = {
    "slider_crank": {"angle": 5e-10, "position": 5e-9, "reaction": 1e-7, "energy": 1e-8},
    "four_bar": {"angle": 5e-9, "position": 5e-9, "reaction": 1e-6, "energy": 5e-8},
}
# neutral motion of every body (origin m, angle rad, velocity m/s, omega rad/s), measured
# at most 3.1e-9 / 2.4e-9 / 7.6e-9 / 4.2e-9
MOTION_BOUNDS = {"origin": 2e-8, "angle": 2e-8, "velocity": 5e-8, "omega": 5e-8}


@pytest.fixture(scope="module", params=sorted(BOUNDS))
def parity(request):
    case = load_case(ROOT / "cases" / f"{request.param}.toml")
    init = initial_body_states(case)
    ref = adapter("natcoord").run(case, init, {})
    run = adapter("pinocchio").run(case, init, {})
    return case, ref, run


def test_channels_match_natcoord(parity):
    case, ref, run = parity
    a, b = evaluate_channels(case, ref.motion), evaluate_channels(case, run.motion)
    bounds = BOUNDS[case.name]
    bad = []
    for ch in case.channels:
        err = float(np.max(np.abs(a[ch.name] - b[ch.name])))
        if not err <= bounds[ch.kind]:
            bad.append(f"{ch.name} ({ch.kind}): {err:.3g} > {bounds[ch.kind]:g}")
    assert not bad, f"{case.name}: " + "; ".join(bad)


def test_body_motion_and_every_joint_force_match_natcoord(parity):
    case, ref, run = parity
    bad = []
    for key, err in ec.motion_errors(case, ref.motion, run.motion).items():
        kind = key.rsplit(".", 1)[1]
        bound = BOUNDS[case.name]["reaction"] if kind == "force" else MOTION_BOUNDS[kind]
        if not err <= bound:
            bad.append(f"{key}: {err:.3g} > {bound:g}")
    assert not bad, f"{case.name}: " + "; ".join(bad)


def test_costs_and_drift_are_bounded(parity):
    case, _, run = parity
    assert run.n_steps == round(case.duration / 1e-3)
    assert run.counters["rhs"] == 4 * run.n_steps + 1
    assert run.counters["prox_iter_max"] <= 5  # measured 3
    assert run.counters["drift_max_m"] < 2e-8  # measured 3.2e-9 m
    assert run.build_time_s > 0 and run.wall_time_s > 0


# Open chains exercising what the two case files do not: a particle on a revolute joint
# listed child-first; an inclined prismatic joint with a rigid child (com off its axis), a
# joint listed child-first and an applied torque. Measured errors <= 1.5e-10 N, 1e-11 rad, m.
ROD_BOB = """\
name = "rod_bob"
description = "rod with a particle pinned at its tip, released horizontal"
dimension = 2
gravity = [0.0, -9.81]
duration = 1.0
output_dt = 0.01

[ground]
points = { O = [0.0, 0.0] }

[[bodies]]
name = "rod"
kind = "uniform_rod"
mass = 2.0
points = { O = [0.0, 0.0], P = [1.0, 0.0] }

[[bodies]]
name = "bob"
kind = "particle"
mass = 0.5
points = { P = [0.0, 0.0] }

[[joints]]
name = "O"
type = "revolute"
bodies = ["ground", "rod"]
points = ["O", "O"]

[[joints]]
name = "P"
type = "revolute"
bodies = ["bob", "rod"]
points = ["P", "P"]

[initial]
fix = { theta = "0 deg" }
velocity = { theta = 1.0 }

[initial.pose]
rod = { origin = [0.0, 0.0], angle = "0 deg" }
bob = { origin = [1.0, 0.0] }

[channels]
theta = { kind = "angle", body = "rod" }
xP = { kind = "position", body = "bob", point = "P", axis = "x" }
vyP = { kind = "velocity", body = "bob", point = "P", axis = "y" }
O_x = { kind = "reaction", joint = "O", axis = "x" }
O_y = { kind = "reaction", joint = "O", axis = "y" }
P_x = { kind = "reaction", joint = "P", axis = "x" }
P_y = { kind = "reaction", joint = "P", axis = "y" }
energy = { kind = "energy" }
"""

RAIL_PENDULUM = """\
name = "rail_pendulum"
description = "block on an inclined rail carrying a pendulum, torque on the pendulum"
dimension = 2
gravity = [0.0, -9.81]
duration = 1.0
output_dt = 0.01

[ground]
points = { O = [0.0, 0.0] }

[[bodies]]
name = "block"
kind = "rigid"
mass = 3.0
points = { A = [0.0, 0.0], E = [0.4, 0.0] }
com = [0.2, 0.1]
inertia = 0.05

[[bodies]]
name = "rod"
kind = "uniform_rod"
mass = 1.0
points = { H = [0.0, 0.0], T = [1.2, 0.0] }

[[joints]]
name = "rail"
type = "prismatic"
bodies = ["ground", "block"]
points = ["O", "A"]
axis = [0.8660254037844386, 0.5]

[[joints]]
name = "H"
type = "revolute"
bodies = ["rod", "block"]
points = ["H", "E"]

[[forces]]
type = "torque"
body = "rod"
value = 2.0

[initial]
fix = { s = 0.3, phi = "-60 deg" }
velocity = { s = 0.5, phi = 1.0 }

[initial.pose]
block = { origin = [0.26, 0.15], angle = "10 deg" }
rod = { origin = [0.65, 0.22], angle = "-60 deg" }

[channels]
s = { kind = "position", body = "block", point = "A", axis = "x" }
phi = { kind = "angle", body = "rod" }
beta = { kind = "angle", body = "block" }
vT = { kind = "velocity", body = "rod", point = "T", axis = "y" }
rail_x = { kind = "reaction", joint = "rail", axis = "x" }
rail_y = { kind = "reaction", joint = "rail", axis = "y" }
N = { kind = "reaction", joint = "rail", axis = "normal" }
H_x = { kind = "reaction", joint = "H", axis = "x" }
H_y = { kind = "reaction", joint = "H", axis = "y" }
energy = { kind = "energy" }
"""


@pytest.mark.parametrize("name, text", [("rod_bob", ROD_BOB), ("rail_pendulum", RAIL_PENDULUM)])
def test_open_chains_match_natcoord(tmp_path, name, text):
    path = tmp_path / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    case = load_case(path)
    init = initial_body_states(case)
    a = evaluate_channels(case, adapter("natcoord").run(case, init, {}).motion)
    run = adapter("pinocchio").run(case, init, {})
    b = evaluate_channels(case, run.motion)
    bound = {"reaction": 2e-9}
    bad = [f"{c.name}: {np.max(np.abs(a[c.name] - b[c.name])):.3g}" for c in case.channels
           if not np.max(np.abs(a[c.name] - b[c.name])) <= bound.get(c.kind, 1e-10)]
    assert not bad, f"{name}: " + "; ".join(bad)
    assert ("particle" in " ".join(run.notes)) == (name == "rod_bob")


def test_slider_crank_prismatic_loop_is_moved_into_the_tree():
    case = load_case(ROOT / "cases" / "slider_crank.toml")
    run = _run(case, {"dt": 0.01})
    assert any("prismatic" in n for n in run.notes)


def test_divergence_is_reported():
    case = load_case(ROOT / "cases" / "four_bar.toml")
    with pytest.raises(RuntimeError, match="loop opened"):
        _run(case, {"dt": 0.01, "max_drift": 1e-9})


def test_dt_must_divide_the_output_interval():
    with pytest.raises(ValueError, match="must divide"):
        _run(ec.hanging_rod(), {"dt": 0.003})
