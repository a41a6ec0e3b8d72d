"""The 3-D references against a derivation that shares nothing with natcoord's: body
coordinates (centre of mass, Euler parameters), Newton-Euler, joint constraints from their
definitions (natcoord.derivations.spatial). The full runs are stored by `natcoord reference
update` under `independent`; here each case's first SPAN seconds are recomputed, and a 1 mm
length or 1 % mass change on either side is shown to break the agreement."""

from __future__ import annotations

import ast
import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from natcoord import load_case
from natcoord.case.mechanism import Channel
from natcoord.derivations import spatial
from natcoord.derivations.spatial import SpatialModel, compare, stiff, supported
from natcoord.engines.base import initial_body_states
from natcoord.engines.natcoord_engine import run as natcoord_run
from natcoord.outputs.result import evaluate_channels

from .conftest import CASES, REFERENCES

SPATIAL = ("four_bar_3d", "parallelogram_3d", "parallelogram_3d_flexible", "a04_bricard",
           "a05_flyball_governor", "slider_crank_3d", "mjcf_rssr")
STIFF = ("parallelogram_3d_flexible", "a05_flyball_governor")  # integrated by Radau
MOTION = 1e-8  # m, rad, J: what the derivation must agree to (issue 28)
FORCE = 1e-6  # relative to the channel's largest value: the determined reactions
SPAN = 0.2  # s recomputed in the tests


def _short(case, span=SPAN):
    return dataclasses.replace(case, duration=span)


def _mine(case, work="samples"):
    model = SpatialModel(case)
    return model.channels(case.times, model.integrate(case.times), work=work)


def _undetermined(name):
    return set(json.loads((REFERENCES / f"{name}.json").read_text())["undetermined"])


def _worst(case, diff):
    """(worst motion difference, worst relative force difference) of a compare() result."""
    force = {c.name for c in case.channels if c.kind in spatial.FORCE_KINDS}
    motion = [v for k, v in diff["max_abs_diff"].items() if k not in force]
    return max(motion, default=0.0), max(diff["max_rel_diff"].values(), default=0.0)


def test_every_3d_case_is_covered():
    threes = sorted(p.stem for p in CASES.glob("*.toml")
                    if load_case(p).dimension == 3)
    assert threes == sorted(SPATIAL)
    assert all(supported(load_case(CASES / f"{n}.toml")) == "" for n in SPATIAL)
    assert sorted(n for n in SPATIAL if stiff(load_case(CASES / f"{n}.toml"))) == sorted(STIFF)
    for name in SPATIAL:  # every one stored by `natcoord reference update`
        assert "independent" in json.loads((REFERENCES / f"{name}.json").read_text()), name


@pytest.mark.parametrize("name", STIFF)
def test_stiff_cases_implicit_agrees_with_explicit(name):
    """The stiff cases are integrated by Radau (its compiled Jacobian); over their first
    0.02 s the explicit DOP853 at rtol 1e-12 (steps held by stability, affordable only
    that short) gives the same states."""
    case = _short(load_case(CASES / f"{name}.toml"), 0.02)
    model = SpatialModel(case)
    assert "stiff" in stiff(case) and model.settings()[0] == spatial.STIFF_SETTINGS
    implicit = model.integrate(case.times)
    explicit = model.integrate(case.times, spatial.SETTINGS)
    assert np.max(np.abs(implicit - explicit)) < 1e-9  # r, p, v, w, work: m, 1, m/s, J


def test_spring_dampers_keep_the_energy_balance():
    """The spring-damper path (tension, its potential, the damper's power) and the applied
    force's work: parallelogram_3d_flexible with soft springs (1e3 N/m, 10 N s/m: not
    stiff), whose energy minus the work of the damper and the force stays at its t = 0
    value, while the energy alone changes by 0.28 J."""
    case = load_case(CASES / "parallelogram_3d_flexible.toml")
    soft = tuple(dataclasses.replace(sp, stiffness=1e3, damping=10.0) for sp in case.springs)
    channels = (Channel("E", "energy"), Channel("balance", "energy", work=True),
                Channel("A1", "axial", rod="A1"))
    case = dataclasses.replace(_short(case, 0.5), springs=soft, channels=channels)
    assert not stiff(case)
    mine, _ = _mine(case, work="exact")
    assert np.ptp(mine["E"]) > 0.1  # J (0.28 measured): the force and damper do work
    np.testing.assert_allclose(mine["balance"], mine["balance"][0], atol=1e-9)
    assert mine["A1"].abs().max() > 1.0  # N: the springs carry it


def test_energy_balance_with_dampers_is_compared_as_defined_and_exact_apart():
    """a05_flyball_governor's balance: exact in the derivation (the dampers' work a state),
    constant; as the channel is defined (the dampers' power integrated over the 0.01 s
    samples) it agrees with the reference; the two differ in the start-up transient by
    what the samples cannot resolve, stored apart as ``exact_work``."""
    case = _short(load_case(CASES / "a05_flyball_governor.toml"))
    ref = pd.read_csv(REFERENCES / "a05_flyball_governor.csv").iloc[:len(case.times)]
    model = SpatialModel(case)
    ys = model.integrate(case.times)
    exact = model.channels(case.times, ys, work="exact")[0]["balance"]
    sampled = model.channels(case.times, ys)[0]["balance"]
    assert np.ptp(exact) < 1e-8  # J
    assert np.max(np.abs(sampled - ref["balance"])) < MOTION
    assert np.max(np.abs(exact - sampled)) > 1e-5  # J (3.4e-4 measured)
    stored = json.loads((REFERENCES / "a05_flyball_governor.json").read_text())
    assert stored["independent"]["exact_work"]["balance"] > 1e-5


@pytest.mark.parametrize("name", SPATIAL)
def test_stored_independent_field_meets_the_bounds(name):
    """`natcoord reference update` stored the full-length agreement."""
    case = load_case(CASES / f"{name}.toml")
    ind = json.loads((REFERENCES / f"{name}.json").read_text())["independent"]
    assert ind["method"].startswith("body coordinates")
    diff = {"max_abs_diff": ind["max_abs_diff"], "max_rel_diff": ind["max_rel_diff"]}
    compared = set(ind["max_abs_diff"])
    assert compared == {c.name for c in case.channels} - _undetermined(name) - set(
        ind["undetermined"])
    motion, force = _worst(case, diff)
    assert motion <= MOTION and force <= FORCE, (motion, force)


@pytest.mark.parametrize("name", SPATIAL)
def test_reference_agrees_over_the_first_span(name):
    case = _short(load_case(CASES / f"{name}.toml"))
    ref = pd.read_csv(REFERENCES / f"{name}.csv").iloc[:len(case.times)]
    mine, free = _mine(case)
    np.testing.assert_allclose(mine["t"], ref["t"], atol=1e-12)
    assert free <= _undetermined(name)  # what one calls undetermined, the other does too
    motion, force = _worst(case, compare(case, mine, ref, _undetermined(name)))
    assert motion <= MOTION and force <= FORCE, (motion, force)


# ---- a 1 mm length or 1 % mass change, on either side, is seen -------------------------------
def _heavier(case, body="coupler"):
    return dataclasses.replace(case, bodies=tuple(
        dataclasses.replace(b, mass=1.01 * b.mass) if b.name == body else b
        for b in case.bodies))


def _rocker_1mm_shorter(case):
    """mjcf_rssr's rocker pivot D moved 1 mm towards C along x, on the ground and the rocker
    alike: the mechanism stays closed at t = 0, its rocker and ground link 1 mm shorter."""
    shift = np.array([-1e-3, 0.0, 0.0])
    ground = {**case.ground, "D": case.ground["D"] + shift}
    bodies = tuple(dataclasses.replace(b, points={**b.points, "D": b.points["D"] + shift})
                   if b.name == "rocker" else b for b in case.bodies)
    return dataclasses.replace(case, ground=ground, bodies=bodies)


@pytest.fixture(scope="module")
def rssr():
    """mjcf_rssr over SPAN: the case, the stored reference and the derivation's channels."""
    case = _short(load_case(CASES / "mjcf_rssr.toml"))
    ref = pd.read_csv(REFERENCES / "mjcf_rssr.csv").iloc[:len(case.times)]
    return case, ref, _mine(case)[0]


def _natcoord(case):
    own = {k: v for k, v in case.engine("natcoord").settings.items() if k == "coordinates"}
    run = natcoord_run(case, initial_body_states(case),
                       own | {"method": "DOP853", "rtol": 1e-12, "atol": 1e-14})
    return evaluate_channels(case, run.motion)


@pytest.mark.parametrize("change", [_heavier, _rocker_1mm_shorter], ids=["mass", "length"])
def test_a_change_in_the_derivation_is_seen(rssr, change):
    case, ref, mine = rssr
    assert max(_worst(case, compare(case, mine, ref, set()))) <= MOTION  # unperturbed
    changed, _ = _mine(change(case))
    motion, force = _worst(case, compare(case, changed, ref, set()))
    assert motion > 100 * MOTION and force > 100 * FORCE, (motion, force)


@pytest.mark.parametrize("change", [_heavier, _rocker_1mm_shorter], ids=["mass", "length"])
def test_a_change_in_natcoord_is_seen(rssr, change):
    case, _, mine = rssr
    assert max(_worst(case, compare(case, _natcoord(case), mine, set()))) <= MOTION
    motion, force = _worst(case, compare(case, _natcoord(change(case)), mine, set()))
    assert motion > 100 * MOTION and force > 100 * FORCE, (motion, force)


def test_a_change_in_a_stiff_derivation_is_seen():
    """The implicit path too: a05_flyball_governor's slider 1 % heavier in the derivation
    moves it off the reference over SPAN."""
    case = _short(load_case(CASES / "a05_flyball_governor.toml"))
    ref = pd.read_csv(REFERENCES / "a05_flyball_governor.csv").iloc[:len(case.times)]
    changed, _ = _mine(_heavier(case, "slider"))
    motion, force = _worst(case, compare(case, changed, ref, set()))
    assert motion > 100 * MOTION and force > 100 * FORCE, (motion, force)


def test_hanging_rod_pin_reaction_is_its_weight():
    """Closed form: four_bar_3d's crank alone, hanging at rest from its revolute (the other
    bodies and joints removed): pin force +m g on the crank, no motion."""
    case = load_case(CASES / "four_bar_3d.toml")
    crank = case.body("crank")
    down = {**crank.points, "A": np.array([0.0, 0.0, -1.0])}
    case = dataclasses.replace(
        _short(case, 0.05), bodies=(dataclasses.replace(crank, points=down,
                                                        com=np.array([0.0, 0.0, -0.5])),),
        joints=(case.joint("O"),), velocity={},
        channels=tuple(c for c in case.channels if c.name in ("zA", "O_y", "O_z")))
    mine, free = _mine(case)
    assert not free
    np.testing.assert_allclose(mine["zA"], -1.0, atol=1e-12)
    np.testing.assert_allclose(mine["O_z"], crank.mass * 9.81, rtol=1e-12)
    np.testing.assert_allclose(mine["O_y"], 0.0, atol=1e-12)


def test_derivation_uses_no_natcoord_model():
    """Independent means independent: the module takes the case data and nothing else, its
    compiled kernel numpy and numba only."""
    here = CASES.parent / "natcoord" / "derivations"
    tree = ast.parse((here / "spatial.py").read_text())
    local = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level}
    assert local <= {"errors", "case.mechanism", "estimates", None}  # None: `from . import`
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level
             and n.module is None for a in n.names}
    assert names == {"spatial_kernel"}
    kernel = ast.parse((here / "spatial_kernel.py").read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(kernel) if isinstance(n, ast.Import)
                for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(kernel)
                 if isinstance(n, ast.ImportFrom) and not n.level}
    assert imported == {"__future__", "numpy", "numba"}
    assert not any(isinstance(n, ast.ImportFrom) and n.level for n in ast.walk(kernel))


def test_report_shows_the_3d_agreement_as_for_planar_cases():
    from natcoord.report.html import _independent_line
    meta = json.loads((REFERENCES / "four_bar_3d.json").read_text())
    line = _independent_line(meta, {"theta": "rad", "O_y": "N"})
    assert line.startswith("independent check: body coordinates")
    theta = meta["independent"]["max_abs_diff"]["theta"]
    assert f"theta {theta:.2g} rad" in line and "O_y" in line
    assert "O_x" not in line  # undetermined: never compared
    meta = json.loads((REFERENCES / "a05_flyball_governor.json").read_text())
    line = _independent_line(meta, {"balance": "J"})
    exact = meta["independent"]["exact_work"]["balance"]
    assert line.endswith(f"; against the exact dampers' work balance {exact:.2g} J")
