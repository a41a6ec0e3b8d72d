"""Output channels checked on closed forms: ``loop_gap`` (how far an engine lets the points a
joint holds together drift apart, from its own body poses)."""

from __future__ import annotations

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.errors import CaseError
from natcoord.outputs.result import evaluate_channels

from . import engine_checks as ec
from .conftest import PENDULUM_AY

GAP = r'^(energy = \{ kind = "energy" \})'


def _four_bar_with_gap(case_variant, line: str = 'gap = { kind = "loop_gap" }'):
    return load_case(case_variant("four_bar", [(GAP, r"\1\n" + line)]))


def test_loop_gap_convention_on_a_pose_that_opens_a_joint(case_variant):
    """The four-bar at its natcoord trajectory, then the rocker moved by (3, 4) mm: the gap
    at joints C and D (the rocker's) is exactly 5 mm, at O and A still ~0; ``joints``
    restricts it to the named joints."""
    import dataclasses

    case = _four_bar_with_gap(case_variant, 'gap = { kind = "loop_gap" }\n'
                              'gapOA = { kind = "loop_gap", joints = ["O", "A"] }')
    motion = ec.natcoord(case).motion
    shifted = dict(motion.origin)
    shifted["rocker"] = motion.origin["rocker"] + np.array([3e-3, 4e-3])
    table = evaluate_channels(case, dataclasses.replace(motion, origin=shifted))
    np.testing.assert_allclose(table["gap"], 5e-3, rtol=1e-9)
    assert np.max(table["gapOA"]) < 1e-9


def test_prismatic_gap_is_across_the_axis_only(case_variant):
    """slider_crank: the slider moved 1 cm along its prismatic axis (world x) opens nothing
    at the prismatic joint; 1 cm across it (y) opens 1 cm."""
    import dataclasses

    path = case_variant("slider_crank", [(r"^(\[channels\])", r"\1\n"
                                          'gap_slide = { kind = "loop_gap", joints = ["slide"] }')])
    case = load_case(path)
    jp = case.joint("slide")
    assert jp.type == "prismatic"
    slider = jp.bodies[1] if jp.bodies[0] == "ground" else jp.bodies[0]
    motion = ec.natcoord(case).motion
    for shift, gap in (([1e-2, 0.0], 0.0), ([0.0, 1e-2], 1e-2)):
        origin = dict(motion.origin)
        origin[slider] = motion.origin[slider] + np.array(shift)
        table = evaluate_channels(case, dataclasses.replace(motion, origin=origin))
        np.testing.assert_allclose(table["gap_slide"], gap, rtol=1e-9, atol=1e-12)


def test_loop_gap_joints_must_be_named_joints(case_variant):
    with pytest.raises(CaseError, match=r"channels\.gap\.joints"):
        _four_bar_with_gap(case_variant, 'gap = { kind = "loop_gap", joints = ["Q"] }')
    with pytest.raises(CaseError, match=r"channels\.gap\.joints"):
        _four_bar_with_gap(case_variant, 'gap = { kind = "loop_gap", joints = [] }')


@pytest.mark.engines
def test_loop_gap_natcoord_closed_mujoco_soft(case_variant):
    """four_bar over 2 s: natcoord holds its loop to round-off (measured 4.4e-16 m);
    MuJoCo's connect is soft, so its gap is positive but small (measured 4.8e-9 m at the
    adapter defaults: RK4 dt 1e-4, solref 1e-3 s)."""
    case = _four_bar_with_gap(case_variant)
    nat = evaluate_channels(case, ec.natcoord(case).motion)["gap"].to_numpy()
    muj = evaluate_channels(case, ec.run("mujoco", case).motion)["gap"].to_numpy()
    assert nat.max() < 1e-11
    assert 1e-10 < muj.max() < 1e-6


# ---- angular velocity, angular momentum, linear momentum -----------------------------------
SPIN = """name = "spin"
description = "a rigid body with a full inertia tensor on a hinge about z, no gravity"
dimension = 3
gravity = [0.0, 0.0, GRAVITY]
duration = 1.0
output_dt = 0.01
[ground]
points = { O = [0.0, 0.0, 0.0] }
[[bodies]]
name = "b"
kind = "rigid"
mass = 2.0
com = [0.3, 0.2, -0.5]
inertia = [[0.05, 0.01, 0.0], [0.01, 0.04, 0.005], [0.0, 0.005, 0.03]]
points = { O = [0.0, 0.0, 0.0], c = [0.3, 0.2, -0.5], e = [0.0, 0.0, -0.5], f = [0.1, -0.2, 0.0] }
[[joints]]
name = "O"
JOINT
bodies = ["ground", "b"]
points = ["O", "O"]
[initial]
velocity = VELOCITY
[channels]
theta = { kind = "angle", body = "b", points = ["e", "c"], plane = "xy" }
xc = { kind = "position", body = "b", point = "c", axis = "x" }
yc = { kind = "position", body = "b", point = "c", axis = "y" }
wx = { kind = "angular_velocity", body = "b", axis = "x" }
wy = { kind = "angular_velocity", body = "b", axis = "y" }
wz = { kind = "angular_velocity", body = "b", axis = "z" }
wbx = { kind = "angular_velocity", body = "b", axis = "x", frame = "body" }
wbz = { kind = "angular_velocity", body = "b", axis = "z", frame = "body" }
Hx = { kind = "angular_momentum", axis = "x" }
Hy = { kind = "angular_momentum", axis = "y" }
Hz = { kind = "angular_momentum", axis = "z" }
Hcz = { kind = "angular_momentum", body = "b", about = "com", axis = "z" }
px = { kind = "momentum", axis = "x" }
py = { kind = "momentum", axis = "y" }
pz = { kind = "momentum", body = "b", axis = "z" }
"""
M, C = 2.0, np.array([0.3, 0.2, -0.5])
I_G = np.array([[0.05, 0.01, 0.0], [0.01, 0.04, 0.005], [0.0, 0.005, 0.03]])
I_O = I_G + M * (C @ C * np.eye(3) - np.outer(C, C))  # about the pivot, parallel axes


def _spin(tmp_path, joint: str, w: float, g: float = 0.0):
    """The body on ``joint`` spinning about z at w rad/s (theta and the centre of mass's
    velocity w z x r_G: a spherical joint's three rates)."""
    rates = f"{{ theta = {w!r}, xc = {float(-w * C[1])!r}, yc = {float(w * C[0])!r} }}"
    rates = rates if "spherical" in joint else f"{{ theta = {w!r} }}"
    text = (SPIN.replace("JOINT", joint).replace("VELOCITY", rates)
            .replace("GRAVITY", repr(g)))
    return ec.case_from_text(tmp_path, text, "spin")


@pytest.mark.parametrize("engine", ["natcoord", "mujoco", "pinocchio"])
def test_body_spinning_about_a_fixed_axis(tmp_path, engine):
    """A body on a hinge about z, no gravity, spinning at w = 3 rad/s: omega = (0, 0, w) in
    world axes and, since the body's z axis is the hinge, in body axes; its angular momentum
    about the pivot is Rz(w t) I_O (0, 0, w) (I_O by parallel axes: H_z = 0.87 kg m^2/s, the
    x, y parts turning with the body), about its centre of mass H_z = I_G,zz w; its momentum
    m w z x r_G. Bounds: 1e-6 of the values (engines' own integration error)."""
    w = 3.0
    case = _spin(tmp_path, 'type = "revolute"\naxis = [0.0, 0.0, 1.0]', w)
    run = ec.run(engine, case, case.engine(engine).settings)
    tab = evaluate_channels(case, run.motion)
    t = tab["t"].to_numpy()
    phi = tab["theta"].to_numpy() - tab["theta"].iloc[0]
    np.testing.assert_allclose(phi, w * t, atol=1e-6)  # the spin itself
    c, s = np.cos(phi), np.sin(phi)
    H0 = I_O @ [0.0, 0.0, w]
    H = np.stack([c * H0[0] - s * H0[1], s * H0[0] + c * H0[1], np.full_like(t, H0[2])], 1)
    np.testing.assert_allclose(tab[["Hx", "Hy", "Hz"]].to_numpy(), H, atol=1e-6)
    np.testing.assert_allclose(tab["Hcz"], I_G[2, 2] * w, atol=1e-6)
    for name, value in (("wx", 0.0), ("wy", 0.0), ("wz", w), ("wbx", 0.0), ("wbz", w)):
        np.testing.assert_allclose(tab[name], value, atol=1e-6, err_msg=name)
    x, y = tab["xc"].to_numpy(), tab["yc"].to_numpy()
    np.testing.assert_allclose(tab["px"], -M * w * y, atol=1e-6)
    np.testing.assert_allclose(tab["py"], M * w * x, atol=1e-6)
    np.testing.assert_allclose(tab["pz"], 0.0, atol=1e-6)
    assert H0[2] == pytest.approx(0.87)


@pytest.mark.parametrize("engine", ["natcoord", "mujoco"])
def test_spherical_pendulum_keeps_its_vertical_angular_momentum(tmp_path, engine):
    """The same body on a spherical joint under gravity, set spinning about z: gravity's
    moment about the pivot, r_G x m g, has no z part, so H_z about the pivot stays at its
    value at t = 0 while H_x, H_y change at the rate r_G x m g (Euler's second law, checked
    by central differences of the samples: 1e-3 of m g |r_G|)."""
    g = -9.81
    case = _spin(tmp_path, 'type = "spherical"', 3.0, g)
    run = ec.run(engine, case, case.engine(engine).settings)
    tab = evaluate_channels(case, run.motion)
    H = tab[["Hx", "Hy", "Hz"]].to_numpy()
    assert np.ptp(H[:, 0]) > 0.1  # it does tumble
    np.testing.assert_allclose(H[:, 2], H[0, 2], atol=1e-6 * abs(H[0, 2]))
    rg = np.stack([run.motion.origin["b"][:, k] for k in range(3)], 1) + np.einsum(
        "tij,j->ti", run.motion.R("b"), C)
    torque = np.cross(rg, M * np.array([0.0, 0.0, g]))
    dt = case.output_dt
    dH = (H[2:] - H[:-2]) / (2 * dt)
    scale = M * abs(g) * np.linalg.norm(C)
    assert np.max(np.abs(dH - torque[1:-1])) < 1e-3 * scale


def test_compound_pendulum_2d(tmp_path):
    """A uniform rod (2 kg, 1 m) swinging on a pin in 2-D: H about the pin = m L^2 / 3
    omega, about its centre of mass m L^2 / 12 omega, momentum m (L / 2) omega (-sin, cos),
    and dH/dt = -m g (L / 2) cos theta (central differences over 1 ms samples, 1e-4)."""
    from natcoord.suite.conformance import ROD

    text = ROD.format(bodies='["ground", "rod"]', angle=-30.0, duration=0.5, rate=1.0,
                      gravity=-9.81).replace("output_dt = 0.01", "output_dt = 0.001")
    text += ('w = { kind = "angular_velocity", body = "rod", axis = "z" }\n'
             'H = { kind = "angular_momentum", axis = "z" }\n'
             'Hc = { kind = "angular_momentum", body = "rod", about = "com", axis = "z" }\n'
             'px = { kind = "momentum", axis = "x" }\n'
             'py = { kind = "momentum", body = "rod", axis = "y" }\n')
    case = ec.case_from_text(tmp_path, text, "check_rod")
    tab = evaluate_channels(case, ec.natcoord(case).motion)
    th, w, H = (tab[k].to_numpy() for k in ("theta", "w", "H"))
    m, L = 2.0, 1.0
    np.testing.assert_allclose(H, m * L**2 / 3 * w, rtol=1e-12)
    np.testing.assert_allclose(tab["Hc"], m * L**2 / 12 * w, rtol=1e-12)
    np.testing.assert_allclose(tab["px"], -m * L / 2 * w * np.sin(th), atol=1e-12)
    np.testing.assert_allclose(tab["py"], m * L / 2 * w * np.cos(th), atol=1e-12)
    dH = (H[2:] - H[:-2]) / 2e-3
    np.testing.assert_allclose(dH, -m * 9.81 * L / 2 * np.cos(th[1:-1]), atol=1e-4)
    assert w[0] == pytest.approx(1.0)


def test_angular_channels_are_refused_where_they_mean_nothing(tmp_path):
    from natcoord.suite.conformance import ROD

    base = ROD.format(bodies='["ground", "rod"]', angle=0.0, duration=0.1, rate=0.0,
                      gravity=-9.81)
    for line, field in (('w = { kind = "angular_velocity", body = "rod", axis = "x" }',
                         "channels.w.axis"),
                        ('w = { kind = "angular_velocity", axis = "z" }', "channels.w.body"),
                        ('w = { kind = "angular_momentum", axis = "z", about = [1.0] }',
                         r"channels.w.about"),
                        ('w = { kind = "momentum", body = "nobody", axis = "x" }',
                         "channels.w.body")):
        with pytest.raises(CaseError, match=field):
            ec.case_from_text(tmp_path, base + line + "\n", "check_rod")


# ---- accelerations in 3-D ------------------------------------------------------------------
ACCEL = ('acx = { kind = "acceleration", body = "b", point = "c", axis = "x" }\n'
         'acy = { kind = "acceleration", body = "b", point = "c", axis = "y" }\n'
         'acz = { kind = "acceleration", body = "b", point = "c", axis = "z" }\n')


@pytest.mark.parametrize("engine, settings, bound", [
    ("natcoord", {}, 1e-6), ("mujoco", {}, 1e-6), ("dart", {}, 1e-6), ("simbody", {}, 1e-6),
    ("exudyn", {"dt": 1e-4}, 3e-5)])
def test_3d_point_acceleration_of_a_body_driven_about_a_hinge(tmp_path, engine, settings,
                                                              bound):
    """The hinged body of the spin tests with a torque of 0.5 N m about the hinge (z): its
    angular acceleration is tau / I_O,zz = 1.72 rad/s^2 (I_O,zz = 0.29 kg m^2), so its
    centre of mass accelerates by alpha z x r - omega^2 r (omega = 3 + alpha t), nothing
    along z. Bound 1e-6 m/s^2 (measured: natcoord 4.4e-11, MuJoCo, classical accelerations
    from mj_objectAcceleration, 4.5e-12, DART 4.5e-12, Simbody 4.1e-14); Exudyn's are
    generalized-alpha's, 1.0e-2 at its default step 1e-3 s, 1.1e-5 at 1e-4 s (bound 3e-5).
    Pinocchio, Drake and PyBullet report none: NaN, "not computed"."""
    w0, tau = 3.0, 0.5
    text = (SPIN.replace("JOINT", 'type = "revolute"\naxis = [0.0, 0.0, 1.0]')
            .replace("VELOCITY", f"{{ theta = {w0!r} }}").replace("GRAVITY", "0.0")
            .replace("[channels]\n", "[channels]\n" + ACCEL)
            + f'[[forces]]\ntype = "torque"\nbody = "b"\nvalue = [0.0, 0.0, {tau!r}]\n')
    case = ec.case_from_text(tmp_path, text, "spin")
    tab = evaluate_channels(case, ec.run(engine, case, settings).motion)
    alpha = tau / I_O[2, 2]
    t, x, y = (tab[k].to_numpy() for k in ("t", "xc", "yc"))
    w = w0 + alpha * t
    err = {"acx": np.max(np.abs(tab["acx"] - (-alpha * y - w**2 * x))),
           "acy": np.max(np.abs(tab["acy"] - (alpha * x - w**2 * y))),
           "acz": np.max(np.abs(tab["acz"]))}
    assert max(err.values()) < bound, err


@pytest.mark.engines
def test_an_acceleration_channel_an_engine_does_not_report_leaves_the_run_ok(case_variant):
    """Pinocchio's adapter reports no accelerations: the column is NaN throughout, which is
    "not reported" for that channel (ungated, noted), never a discarded run."""
    from natcoord.engines.base import initial_body_states as init
    from natcoord.suite.worker import Job, run_job

    path = case_variant("pendulum", PENDULUM_AY)
    case = load_case(path)
    res, _ = run_job(Job(case, init(case), "pinocchio"))
    assert res.status.value == "ok", res.reason
    assert np.all(np.isnan(res.table["ay"])) and np.all(np.isfinite(res.table["theta"]))
    assert any("not computed by pinocchio: ay" in n for n in res.notes)


# ---- the angle between two body vectors ------------------------------------------------------
@pytest.mark.parametrize("engine", ["natcoord", "mujoco"])
def test_vector_angle_of_a_spinning_body_against_a_ground_axis(tmp_path, engine):
    """The hinged body spinning at 3 rad/s about z: its horizontal vector e -> c makes the
    angle arccos(cos(phi0 + w t)) with world x (phi0 = atan2(0.2, 0.3)), through pi;
    its vertical O -> e stays at pi / 2. Bound 1e-9 rad (measured round-off)."""
    w = 3.0
    text = (SPIN.replace("JOINT", 'type = "revolute"\naxis = [0.0, 0.0, 1.0]')
            .replace("VELOCITY", f"{{ theta = {w!r} }}").replace("GRAVITY", "0.0")
            .replace("{ O = [0.0, 0.0, 0.0] }", "{ O = [0.0, 0.0, 0.0], X = [1.0, 0.0, 0.0] }")
            .replace("[channels]\n", '[channels]\n'
                     'a = { kind = "vector_angle", vectors = [["b", "e", "c"], '
                     '["ground", "O", "X"]] }\n'
                     'v = { kind = "vector_angle", vectors = [["b", "O", "e"], '
                     '["ground", "O", "X"]] }\n'))
    case = ec.case_from_text(tmp_path, text, "spin")
    tab = evaluate_channels(case, ec.run(engine, case).motion)
    t = tab["t"].to_numpy()
    expected = np.arccos(np.cos(np.arctan2(0.2, 0.3) + w * t))
    np.testing.assert_allclose(tab["a"], expected, atol=1e-9)
    np.testing.assert_allclose(tab["v"], np.pi / 2, atol=1e-9)
    assert tab["a"].max() > 3.13  # it passes pi (phi0 + w t from 0.59 to 3.59 rad)


def test_vector_angle_needs_two_body_vectors(tmp_path):
    base = (SPIN.replace("JOINT", 'type = "revolute"\naxis = [0.0, 0.0, 1.0]')
            .replace("VELOCITY", "{ theta = 1.0 }").replace("GRAVITY", "0.0"))
    for vectors in ('[["b", "e", "c"]]', '[["b", "e", "c"], ["b", "e", "e"]]',
                    '[["b", "e", "c"], ["nobody", "O", "e"]]', '"e"'):
        text = base.replace("[channels]\n", f'[channels]\na = {{ kind = "vector_angle", '
                            f'vectors = {vectors} }}\n')
        with pytest.raises(CaseError, match=r"channels\.a\.vectors"):
            ec.case_from_text(tmp_path, text, "spin")


# ---- a 3-D joint's reaction along and across its axis --------------------------------------
@pytest.mark.parametrize("engine", ["natcoord", "mujoco"])
@pytest.mark.parametrize("joint", ["prismatic", "cylindrical"])
def test_reaction_along_and_across_an_inclined_slide(tmp_path, engine, joint):
    """incline_3d: a 2 kg block on a frictionless slide along (1, 1, 1) / sqrt(3) through
    its centre of mass (prismatic, or cylindrical: no moment about the axis either): the
    joint pushes across the axis with m |g - (g . u) u| = m g sqrt(2/3) = 16.02 N and not
    along it, and the block stays on the axis (loop_gap across it). Bounds 1e-9 N, 1e-9 m
    (measured round-off)."""
    case = ec.data_case(tmp_path, "incline_3d", {
        'type = "prismatic"': f'type = "{joint}"',
        "Rz = {": 'along = { kind = "reaction", joint = "slide", axis = "along" }\n'
                  'across = { kind = "reaction", joint = "slide", axis = "across" }\n'
                  'gap = { kind = "loop_gap" }\nRz = {'})
    tab = evaluate_channels(case, ec.run(engine, case).motion)
    z = tab["z"].to_numpy()
    assert z[0] - z[-1] > 0.3  # it slides down the axis: the gap counts only across it
    assert np.max(tab["gap"]) < 1e-9
    np.testing.assert_allclose(tab["along"], 0.0, atol=1e-9)
    np.testing.assert_allclose(tab["across"], 2.0 * 9.81 * np.sqrt(2 / 3), atol=1e-9)


def test_along_and_across_need_a_3d_joint_with_an_axis(case_variant):
    with pytest.raises(CaseError, match=r"channels\.O_x\.axis"):
        load_case(case_variant("four_bar", [(r'^O_x = \{ kind = "reaction", joint = "O", '
                                             r'axis = "x" \}',
                                             'O_x = { kind = "reaction", joint = "O", '
                                             'axis = "along" }')]))
