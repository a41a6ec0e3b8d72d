"""Pinocchio adapter: reaction sign on a hanging rod, parity with natcoord on the closed loops.

Bounds are the errors measured at the adapter defaults (RK4, dt 1e-3 s; pin 4.1) times a
margin of about 5; they are RK4 truncation error (it falls 16x per halved dt), not noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio  # noqa: E402,F401 - an engine is a real dependency: missing fails, never skips
import pytest

from natcoord.case.mechanism import Channel, Joint
from natcoord.engines import adapter
from natcoord.engines.base import BodyState, InitialState, initial_body_states
from natcoord.errors import Unsupported
from natcoord.outputs.result import evaluate_channels
from natcoord.suite.references import load_reference

from . import engine_checks as ec
from .conftest import REFERENCES, SPHERICAL_ROD

pytestmark = pytest.mark.engines



def _run(case, settings=None):
    return ec.run("pinocchio", case, settings)


def test_hanging_rod_pivot_pushes_up_with_mg():
    case, run = ec.assert_hanging_rod_pushes_up("pinocchio")
    assert run.n_steps == round(case.duration / 1e-3)


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    ec.assert_reversed_joint_flips_the_reaction("pinocchio")


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
    case = ec.case(request.param)
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
@pytest.mark.parametrize("name", ["rod_bob", "rail_pendulum"])
def test_open_chains_match_natcoord(tmp_path, name):
    case = ec.data_case(tmp_path, name)
    run, a, b = ec.channel_tables("pinocchio", case)
    bad = ec.channel_mismatches(case, a, b, {"reaction": 2e-9}, 1e-10)
    assert not bad, f"{name}: " + "; ".join(bad)
    assert ("particle" in " ".join(run.notes)) == (name == "rod_bob")


def test_slider_crank_prismatic_loop_is_moved_into_the_tree():
    case = ec.case("slider_crank")
    run = _run(case, {"dt": 0.01})
    assert any("prismatic" in n for n in run.notes)


def test_divergence_is_reported():
    case = ec.case("four_bar")
    with pytest.raises(RuntimeError, match="loop opened"):
        _run(case, {"dt": 0.01, "max_drift": 1e-9})


def test_dt_must_divide_the_output_interval():
    ec.assert_step_must_divide_the_output_interval("pinocchio", 0.003, "must divide")


# ---- reference-frame cases: 3-D, massless rods, spring-dampers ------------------------------
# Max |pinocchio - reference| measured with each case's [engines.pinocchio] settings (pin
# 4.1), bounds about 5x. Determined reactions only: the undetermined ones (five_bar N34,
# N56, R1_x, R2_x; four_bar_3d O_x, D_x; parallelogram A1, C2, E3, G4) are the proximal
# solver's own split and are only checked to be reported.
#   five_bar       phi 1.15e-8 rad, N34_2N56 9.1e-3 N (at the -180 deg peak of 1.03e4 N),
#                  R1_y 8.7e-6 N, R2_y 8.8e-6 N, energy 4.3e-6 J (light rods of 1e-8 kg)
#   four_bar_3d    9.2e-10 rad, 8.7e-10 m, O/D y,z 1.8e-7 N, 9.9e-9 J (RK4 truncation)
#   parallelogram  1.2e-7 m, K5 7.7e-6 N, M6 9.1e-6 N, energy 1.5e-6 J (light rods, 1e-6 kg)
REF_BOUNDS = {
    "five_bar": {"phi": 6e-8, "N34_2N56": 0.05, "R1_y": 5e-5, "R2_y": 5e-5, "energy": 2e-5},
    "four_bar_3d": {"theta": 5e-9, "yA": 5e-9, "zA": 5e-9, "yC": 5e-9, "zC": 5e-9,
                    "O_y": 1e-6, "O_z": 1e-6, "D_y": 1e-6, "D_z": 1e-6, "energy": 5e-8},
    "parallelogram_3d": {"xc": 6e-7, "yc": 6e-7, "zc": 6e-7, "K5": 5e-5, "M6": 5e-5,
                         "energy": 8e-6},
}
UNDETERMINED = {"five_bar": ("N34", "N56", "R1_x", "R2_x"), "four_bar_3d": ("O_x", "D_x"),
                "parallelogram_3d": ("A1", "C2", "E3", "G4")}


def _settings(case, **over):
    return {**case.engine("pinocchio").settings, **over}


@pytest.fixture(scope="module", params=sorted(REF_BOUNDS))
def reference_case(request):
    case = ec.case(request.param)
    run = _run(case, _settings(case))
    return case, run, evaluate_channels(case, run.motion), load_reference(case.name, REFERENCES)


def test_reference_frame_cases_match_the_natcoord_reference(reference_case):
    case, _, table, ref = reference_case
    assert ref is not None, f"references/{case.name}.csv missing"
    np.testing.assert_allclose(table["t"], ref["t"], rtol=0, atol=1e-12)
    bounds = REF_BOUNDS[case.name]
    assert set(bounds) | set(UNDETERMINED[case.name]) == {c.name for c in case.channels}
    errors = {n: float(np.max(np.abs(table[n] - ref[n]))) for n in bounds}
    bad = [f"{n}: {e:.3g} > {bounds[n]:g}" for n, e in errors.items() if not e <= bounds[n]]
    assert not bad, f"{case.name}: " + "; ".join(bad)
    for n in UNDETERMINED[case.name]:  # reported (a split of pinocchio's own), never gated
        assert np.isfinite(table[n]).all(), n


def test_reference_frame_cases_keep_their_loops_closed(reference_case):
    case, run, _, _ = reference_case
    assert run.counters["drift_max_m"] < 5e-8  # measured 3.6e-15 / 3.2e-9 / 8e-9 m
    assert run.n_steps == round(case.duration / 1e-3)
    assert run.counters["prox_iter_max"] <= int(_settings(case).get("max_iter", 20))


def test_five_bar_crosses_both_singular_positions():
    """phi passes 0 and -180 deg; the angle stays within 1e-3 rad of the reference at half
    the step too (measured 7.8e-5 rad: the -180 deg crossing costs most of it)."""
    case = ec.case("five_bar")
    ref = load_reference("five_bar", REFERENCES)
    table = evaluate_channels(case, _run(case, _settings(case, dt=5e-4)).motion)
    assert table["phi"].min() < -np.pi and table["phi"].max() > np.radians(96.7)
    assert np.max(np.abs(table["phi"] - ref["phi"])) < 1e-3
    assert np.degrees(table["phi"].iloc[-1]) == pytest.approx(-330.97, abs=0.05)


# Cost of the light-body substitute: halving the rod mass changes the results by about
# half the measured error. five_bar (1e-8 kg -> 5e-9 kg, 1.8 s): measured 5.5e-9 rad,
# N34_2N56 4.5e-3 N (singular peak), R1_y 4.2e-6 N, R2_y 4.7e-6 N; parallelogram (1e-6 ->
# 5e-7 kg, 1 s): 2.4e-8 m, K5 3.0e-6 N, M6 2.8e-6 N. Bounds about 5x.
SUBSTITUTE = {
    "five_bar": (1.8, {"phi": 3e-8, "N34_2N56": 0.03, "R1_y": 2e-5, "R2_y": 2e-5}),
    "parallelogram_3d": (1.0, {"xc": 1.5e-7, "yc": 1.5e-7, "zc": 1.5e-7, "K5": 1.5e-5,
                               "M6": 1.5e-5}),
}


@pytest.mark.parametrize("name", sorted(SUBSTITUTE))
def test_light_rod_mass_costs_little(name):
    duration, bounds = SUBSTITUTE[name]
    case = dataclasses.replace(ec.case(name), duration=duration)
    m = _settings(case)["rod_mass"]
    a = evaluate_channels(case, _run(case, _settings(case)).motion)
    run = _run(case, _settings(case, rod_mass=m / 2))
    b = evaluate_channels(case, run.motion)
    assert any("light bodies" in n and f"{m / 2:g} kg" in n for n in run.notes)
    changes = {n: float(np.max(np.abs(a[n] - b[n]))) for n in bounds}
    bad = [f"{n}: {e:.3g} > {bounds[n]:g}" for n, e in changes.items() if not e <= bounds[n]]
    assert not bad, f"{name}: " + "; ".join(bad)


def test_four_bar_3d_keeps_the_exact_slender_rod_inertia():
    case = dataclasses.replace(ec.case("four_bar_3d"), duration=0.5)
    run = _run(case, _settings(case))
    assert any("exact singular rotational inertia" in n for n in run.notes)
    assert not any("light bodies" in n for n in run.notes)
    assert run.motion.rotation["crank"].shape == (len(case.times), 3, 3)
    assert run.motion.omega["crank"].shape == (len(case.times), 3)
    # every body turns about X only: its rotation keeps e_x
    for body in ("crank", "coupler", "rocker"):
        np.testing.assert_allclose(run.motion.rotation[body][:, :, 0], [[1, 0, 0]] * len(
            case.times), atol=1e-12)
        np.testing.assert_allclose(run.motion.omega[body][:, 1:], 0.0, atol=1e-12)


def test_3d_revolute_loop_with_unaligned_tree_is_unsupported():
    """Cutting a revolute whose alignment the tree does not hold would need CONTACT_6D
    minus one rotation, which constraintDynamics lacks."""
    case = ec.case("four_bar_3d")
    joints = tuple(dataclasses.replace(j, axis=np.array([0.0, 0.6, 0.8])) if j.name == "A"
                   else j for j in case.joints)
    case = dataclasses.replace(case, joints=joints)
    with pytest.raises(Unsupported, match="alignment"):
        _run(case, {"dt": 0.01})


def test_flexible_parallelogram_springs_as_external_forces():
    """Six spring-dampers (17e6 N/m, 1e5 N s/m) as fext in aba, explicit RK4 at dt 1e-5 s
    (2e-5 s diverges at 0.24 s). First 0.02 s, the stiffest transient, against natcoord
    (or its stored reference): measured 3e-15 m, 3.4e-7 N (at 0.03 s)."""
    case = ec.case("parallelogram_3d_flexible")
    case = dataclasses.replace(case, duration=0.02)
    ref = load_reference(case.name, REFERENCES)
    if ref is None:  # not stored yet: natcoord itself (about 7 s)
        ref = evaluate_channels(case, ec.natcoord(case).motion)
    run = _run(case, _settings(case))
    table = evaluate_channels(case, run.motion)
    n = len(table)
    assert set(run.motion.rod_force) == {"A1", "C2", "E3", "G4", "K5", "M6"}
    assert any("spring-dampers" in x for x in run.notes)
    for c in case.channels:
        bound = {"position": 1e-12, "axial": 2e-6, "energy": 1e-10}[c.kind]
        err = float(np.max(np.abs(table[c.name] - ref[c.name][:n])))
        assert err <= bound, f"{c.name}: {err:.3g} > {bound:g}"
    assert run.n_steps == 2000


def test_external_forces_are_the_same_through_views_or_copies(monkeypatch):
    """aba's external forces and the joint placements are read and written through views of
    Pinocchio's storage; where the bindings copy instead, the adapter writes and reads them
    at every call: the same motion, bit for bit (parallelogram_3d_flexible, 20 ms)."""
    from natcoord.engines.pinocchio_engine import applied, dynamics

    case = dataclasses.replace(ec.case("parallelogram_3d_flexible"), duration=0.02)
    a = evaluate_channels(case, _run(case, _settings(case)).motion)
    for mod in (applied, dynamics):
        monkeypatch.setattr(mod, "is_view", lambda read: False)
    b = evaluate_channels(case, _run(case, _settings(case)).motion)
    assert len(a) == 3 and np.isfinite(a.to_numpy()).all()
    np.testing.assert_array_equal(a.to_numpy(), b.to_numpy())


def test_radau_option_agrees_with_rk4_on_the_springs():
    """method = "radau" (scipy Radau IIA on aba, finite-difference Jacobian): slower than
    RK4 at dt 1e-5 over the full run here, kept as an option. 0.01 s: measured 2e-16 m,
    5.4e-8 N."""
    case = dataclasses.replace(ec.case("parallelogram_3d_flexible"), duration=0.01)
    a = evaluate_channels(case, _run(case, {"dt": 1e-5}).motion)
    run = _run(case, {"method": "radau", "rtol": 1e-8, "atol": 1e-10})
    b = evaluate_channels(case, run.motion)
    assert any("Radau" in n for n in run.notes) and run.counters["jacobians"] > 0
    for c in case.channels:
        bound = {"position": 1e-12, "axial": 5e-7, "energy": 1e-10}[c.kind]
        assert np.max(np.abs(a[c.name] - b[c.name])) <= bound, c.name
    with pytest.raises(Unsupported, match="radau"):
        _run(ec.case("five_bar"), {"method": "radau"})


def test_compiled_spring_and_load_forces_obey_the_spring_law_and_newtons_third_law(
        monkeypatch):
    """The packed kernel (applied.py) on two free bodies with random poses and rates: the
    tension is k (l - l0) + c dl/dt (dl/dt by central differences of the integrated poses,
    agreeing to 1e-6 relative), a stretched spring pulls its ends together, and the world
    wrench on both bodies is the load's alone (the springs' pairs cancel, to round-off)."""
    import pinocchio as pin

    from natcoord.engines.pinocchio_engine.applied import Applied

    rng = np.random.default_rng(7)
    model = pin.Model()
    for name in ("a", "b"):
        model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), name)
    data = model.createData()
    q = pin.integrate(model, pin.neutral(model), rng.normal(size=12))
    v = rng.normal(size=12)
    P = rng.normal(size=(4, 3))
    springs = [("s1", (1, P[0]), (2, P[1]), 2e3, 0.0, 0.5),
               ("s2", (2, P[2]), (1, P[3]), 5e2, 30.0, 1.5)]
    f, m, p = np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.0, -1.0]), rng.normal(size=3)
    applied = Applied([(1, p, f, m)], springs, data)

    def lengths(qq):
        pin.forwardKinematics(model, data, qq)
        return [np.linalg.norm(data.oMi[jb].act(pb) - data.oMi[ja].act(pa))
                for _, (ja, pa), (jb, pb), *_ in springs]

    eps = 1e-6
    rate = (np.array(lengths(pin.integrate(model, q, eps * v)))
            - lengths(pin.integrate(model, q, -eps * v))) / (2 * eps)
    ln = np.array(lengths(q))
    pin.forwardKinematics(model, data, q, v)
    F = applied().copy()
    law = [k * (x - l0) + c * r for (_, _, _, k, c, l0), x, r in zip(springs, ln, rate,
                                                                     strict=True)]
    np.testing.assert_allclose(applied.T, law, rtol=1e-6)
    wrench = np.zeros(6)
    for s, jid in enumerate(applied.joints, 1):
        M = data.oMi[jid]
        fw = M.rotation @ F[s, :3]
        wrench += np.r_[fw, np.cross(M.translation, fw) + M.rotation @ F[s, 3:]]
    load = np.r_[f, np.cross(data.oMi[1].act(p), f) + m]
    np.testing.assert_allclose(wrench, load, atol=1e-9 * np.abs(applied.T).max())
    # s1 alone (stretched, no damping): body b is pulled towards a's end
    alone = Applied([], springs[:1], data)
    pin.forwardKinematics(model, data, q, v)
    Fb = data.oMi[2].rotation @ alone()[2, :3]
    towards_a = data.oMi[1].act(P[0]) - data.oMi[2].act(P[1])
    assert alone.T[0] > 0 and np.dot(Fb, towards_a) > 0
    np.testing.assert_allclose(np.linalg.norm(Fb), alone.T[0], rtol=1e-12)
    # a body-fixed load (f, m in the joint frame): applied as given, whatever the pose
    fixed = Applied([(2, p, f, m, True)], [], data)
    np.testing.assert_allclose(fixed()[1], np.r_[f, np.cross(p, f) + m], rtol=0, atol=1e-15)
    # the placements are read once as views of data's storage; bindings that copy are
    # read at every call, with the same forces
    from natcoord.engines.pinocchio_engine import applied as mod

    assert applied.live and mod.is_view(lambda: data.oMi[1].rotation)
    assert not mod.is_view(lambda: np.array(data.oMi[1].rotation))
    monkeypatch.setattr(mod, "is_view", lambda read: False)
    copied = Applied([(1, p, f, m)], springs, data)
    pin.forwardKinematics(model, data, q, v)
    assert not copied.live
    np.testing.assert_array_equal(copied(), applied())
    np.testing.assert_array_equal(copied.T, applied.T)


# Two pendulums from the ground, the first one double; joints in breadth-first file order
# (O, P, then Q below O), which Pinocchio needs depth-first. Measured <= 2.7e-10 (N);
# added in file order the angles were 1.2 rad off, with no error raised.
def test_branched_tree_is_built_depth_first(tmp_path):
    case = ec.data_case(tmp_path, "branched")
    _, a, b = ec.channel_tables("pinocchio", case)
    bad = ec.channel_mismatches(case, a, b, {}, 1e-8)
    assert not bad, "; ".join(bad)


# ---- joint types and features added with the single builder --------------------------------
def _reference_init(case, omega=None) -> InitialState:
    """Every body frame at the world frame at t = 0 (a reference-frame case), at rest or
    turning at ``omega`` (body -> rad/s, or (3,) world): a spinning start that the case
    file does not give."""
    d = case.dimension
    rest = 0.0 if d == 2 else np.zeros(3)
    return InitialState(np.zeros(0), np.zeros(0), {
        b.name: BodyState(np.zeros(d), 0.0, np.zeros(d), (omega or {}).get(b.name, rest),
                          np.eye(d)) for b in case.bodies})


def _incline_closed_form(table):
    """incline_3d's closed form (see the file): positions (T, 3) of c, m; reaction (3,), N."""
    g, u, m = np.array([0.0, 0.0, -9.81]), np.ones(3) / np.sqrt(3.0), 2.0
    t = table["t"].to_numpy()
    return np.array([0.3, 0.2, 0.1]) + ((g @ u) * t**2 / 2)[:, None] * u, -m * (g - (g @ u) * u)


# A constant acceleration is integrated exactly by RK4, so what remains is rounding:
# measured 1.6e-15 m and 1.8e-15 N over 0.5 s (dt 1e-3; 5.3e-15 N as a cylindrical joint);
# bounds 1e-13 leave ~20x for platform differences, while a modelling error (axis,
# placement, sign) would show at the 1e-2 level.
INCLINE_BOUND = {"position": 1e-13, "reaction": 1e-13}


@pytest.mark.parametrize("joint", ["prismatic", "cylindrical"])
def test_incline_3d_slides_along_its_axis_with_the_closed_form_reaction(tmp_path, joint):
    """A 3-D prismatic joint along (1, 1, 1)/sqrt(3); as a cylindrical joint it also spins
    freely about that axis (2 rad/s, the centre of mass on the axis), which changes neither
    the slide nor the force: measured 1.6e-15 m, 5.3e-15 N, the spin 1e-15 rad."""
    subs = {} if joint == "prismatic" else {'type = "prismatic"': 'type = "cylindrical"'}
    case = ec.data_case(tmp_path, "incline_3d", subs)
    u = np.ones(3) / np.sqrt(3.0)
    spin = 0.0 if joint == "prismatic" else 2.0
    init = initial_body_states(case) if not spin else _reference_init(case, {"block": spin * u})
    run = _run_from(case, init)
    table = evaluate_channels(case, run.motion)
    pos, force = _incline_closed_form(table)
    for k, axis in enumerate("xyz"):
        assert np.max(np.abs(table[axis] - pos[:, k])) <= INCLINE_BOUND["position"], axis
        assert np.max(np.abs(table[f"R{axis}"] - force[k])) <= INCLINE_BOUND["reaction"], axis
    R = run.motion.rotation["block"]
    np.testing.assert_allclose(R @ u, np.broadcast_to(u, (len(R), 3)), rtol=0, atol=1e-13)
    e = np.cross(u, [1.0, 0.0, 0.0])
    e /= np.linalg.norm(e)
    turned = np.arctan2(np.einsum("i,tij,j->t", np.cross(u, e), R, e),
                        np.einsum("i,tij,j->t", e, R, e))
    np.testing.assert_allclose(np.unwrap(turned), spin * table["t"], rtol=0, atol=1e-12)


def _run_from(case, init, settings=None):
    return adapter("pinocchio").run(case, init, settings or {})


def test_driven_rod_is_unsupported_with_its_reason():
    """Drivers are not modelled: constraintDynamics has only contact constraints. The
    driven crank angle would be a tree joint coordinate here, but prescribing it needs a
    partitioned solve this adapter does not implement."""
    case = ec.data_case(None, "driven_rod")
    init = initial_body_states(case)
    with pytest.raises(Unsupported, match=r"driver\(s\) motor \(angle of rod\).*rheonomic"):
        _run_from(case, init)


def test_planar_body_joined_by_a_rod_only_floats_in_the_plane():
    """hang_2d: the body no joint reaches floats on JointModelPlanar, the rod is a light
    body; against natcoord: measured 1.4e-14 N, 0 m."""
    case = ec.data_case(None, "hang_2d")
    run, a, b = ec.channel_tables("pinocchio", case)
    assert not ec.channel_mismatches(case, a, b, {"axial": 1e-9}, 1e-12)
    assert any("JointModelPlanar" in n for n in run.notes)


def test_universal_joint_swinging_about_one_axis_is_a_revolute(tmp_path):
    """hang_3d's body on a universal joint (x on the ground, y on the body) instead of its
    rod, released swinging about x: the y rotation is never excited, so it must follow the
    same body on a revolute about x. Measured identical (0 m, 0 N)."""
    case = ec.data_case(None, "hang_3d")
    ground_joint = Joint("U", "universal", ("ground", "plate"), ("O", "O"),
                         np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    bodies = (dataclasses.replace(case.bodies[0], points={**case.bodies[0].points,
                                                          "O": np.zeros(3)}),)
    channels = (Channel("yc", "position", body="plate", point="c", axis="y"),
                Channel("zc", "position", body="plate", point="c", axis="z"),
                Channel("U_y", "reaction", joint="U", axis="y"),
                Channel("U_z", "reaction", joint="U", axis="z"))
    uni = dataclasses.replace(case, bodies=bodies, joints=(ground_joint,), rods=(),
                              channels=channels, duration=0.5)
    rev = dataclasses.replace(uni, joints=(dataclasses.replace(
        ground_joint, type="revolute", axis2=None),))
    init = _reference_init(uni, {"plate": np.array([1.5, 0.0, 0.0])})
    a = evaluate_channels(uni, _run_from(uni, init).motion)
    b = evaluate_channels(rev, _run_from(rev, init).motion)
    assert not ec.channel_mismatches(uni, a, b, {"reaction": 1e-10}, 1e-12)
    assert np.ptp(a["yc"]) > 0.5  # it does swing


def test_rk4_is_fourth_order_on_a_spherical_joint(tmp_path):
    """A spherical joint's quaternion: RK4's stages composed on the group without the
    inverse of the exponential's Jacobian were second order (zQ off by 1.1e-6 m at dt 1e-3,
    4x less at half the step; MuJoCo's RK4 7e-15). Runge-Kutta-Munthe-Kaas: 16x less."""
    from natcoord import load_case

    (tmp_path / "spherical_rod.toml").write_text(SPHERICAL_ROD)
    case = load_case(tmp_path / "spherical_rod.toml")
    ref = ec.natcoord(case)
    err = {dt: ec.channel_errors(case, _run(case, {"dt": dt}), ref)["zQ"]
           for dt in (2e-3, 1e-3)}
    assert err[1e-3] < 1e-11 and err[2e-3] / err[1e-3] > 12, err
