"""PyBullet adapter: reaction sign on a hanging rod, the closed loops against the stored
references, first-order convergence under dt, and each PyBullet default that changes the
physics shown to act and to be overridden (link damping, velocity motors, inertia from
shapes, constraint pivots relative to the centre of mass, the joint speed cap).

Bounds are the errors measured at the adapter defaults (semi-implicit Euler, dt 1e-4 s,
erp 0.5, 100 solver iterations, residual 1e-10; pybullet 3.2.7) times about 1.5: they are
the step's deterministic first-order error, not noise (a pendulum without any loop has the
same error per dt).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("pybullet")  # CI installs it (the engines extra)

from natcoord.case.mechanism import Channel, Force  # noqa: E402
from natcoord.engines import adapter  # noqa: E402
from natcoord.engines.base import initial_body_states  # noqa: E402
from natcoord.engines.pybullet_engine import simulate  # noqa: E402
from natcoord.errors import Unsupported  # noqa: E402
from natcoord.outputs.result import evaluate_channels  # noqa: E402

from . import engine_checks as ec  # noqa: E402
from .conftest import REFERENCES, ROOT  # noqa: E402

pytestmark = pytest.mark.engines

G = ec.G


def _run(case, settings=None, keep=()):
    return simulate(case, initial_body_states(case), settings or {}, keep)


def _table(case, settings=None, keep=()):
    return evaluate_channels(case, _run(case, settings, keep).motion)


def _errors(case, table) -> dict[str, float]:
    """Max |PyBullet - stored reference| of every channel over the case's samples."""
    ref = pd.read_csv(REFERENCES / f"{case.name}.csv").iloc[:len(table)]
    np.testing.assert_allclose(table["t"], ref["t"], rtol=0, atol=1e-12)
    return {ch.name: float(np.max(np.abs(table[ch.name].to_numpy()
                                         - ref[ch.name].to_numpy()))) for ch in case.channels}


def _rod(duration: float, velocity: float, gravity=True, energy=False):
    """The hanging rod (2 kg, 1 m, pivot at one end) started at ``velocity`` rad/s."""
    c = ec.hanging_rod()
    channels = c.channels + ((Channel("energy", "energy"),) if energy else ())
    return dataclasses.replace(c, duration=duration, velocity={"theta": velocity},
                               channels=channels,
                               gravity=c.gravity if gravity else np.zeros(2))


# ------------------------------------------------------------------------------ reaction sign

def test_hanging_rod_pivot_pushes_up_with_mg():
    case, run = ec.assert_hanging_rod_pushes_up("pybullet")
    assert run.n_steps == round(case.duration / 1e-4)
    assert run.build_time_s > 0 and run.wall_time_s > 0


def test_hanging_rod_joint_listed_child_first_flips_the_reaction():
    ec.assert_reversed_joint_flips_the_reaction("pybullet")


# ------------------------------------------------------------------------------ closed loops

# measured max |pybullet - reference| over 2 s at the defaults:
#   slider_crank: theta 7.5e-4 rad, xB 1.9e-4 m, reactions 5.3e-2 N (O_x; the loop joint B
#   1.7e-2 / 2.4e-2 N), energy 3.1e-3 J; four_bar: theta 1.13e-3, positions 1.0e-3,
#   reactions 0.21 N (O_x; peak 176 N), energy 1.5e-2 J
BOUNDS = {
    "slider_crank": {"angle": 1.1e-3, "position": 3e-4, "reaction": 8e-2, "energy": 5e-3},
    "four_bar": {"angle": 1.7e-3, "position": 1.5e-3, "reaction": 0.32, "energy": 2.2e-2},
}


@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_closed_loop_matches_the_reference(name):
    case = ec.case(name)
    run = _run(case)
    err = _errors(case, evaluate_channels(case, run.motion))
    bad = {k: v for k, v in err.items() if not v <= BOUNDS[name][case.channel(k).kind]}
    assert not bad, f"{name}: channels beyond their bound: {bad}"
    assert run.n_steps == 20000
    assert run.counters["loop_drift_m"] < 1e-6  # measured 4.4e-7 / 5.0e-7 m
    assert any("JOINT_POINT2POINT" in n for n in run.notes)


def test_crank_error_is_first_order_in_dt():
    """four_bar over 1 s: 2.05e-3 rad at dt 1e-3, 2.0e-4 at 1e-4 (ratio 10.2)."""
    case = dataclasses.replace(ec.case("four_bar"), duration=1.0)
    coarse, fine = (_errors(case, _table(case, {"dt": dt}))["theta"] for dt in (1e-3, 1e-4))
    assert 1.5e-3 < coarse < 2.6e-3
    assert 8.0 < coarse / fine < 12.5, (coarse, fine)


def test_four_bar_with_every_joint_reversed_flips_every_reaction():
    """Tree joints (subtree balance) and the loop joint (constraint force) both follow the
    joint's order."""
    case = dataclasses.replace(ec.case("four_bar"), duration=0.3, velocity={"theta": 2.0})
    flipped = dataclasses.replace(case, joints=tuple(ec.reversed_joint(j) for j in case.joints))
    f0, f1 = (_run(c).motion.joint_force for c in (case, flipped))
    for j in ("O", "A", "C", "D"):
        assert np.max(np.abs(f0[j])) > 1.0
        np.testing.assert_allclose(f1[j], -f0[j], rtol=0, atol=1e-6)  # measured 0 to 1e-9


def test_prismatic_loop_is_cut_at_a_revolute_and_the_slider_is_not_welded():
    case = dataclasses.replace(ec.case("slider_crank"), duration=0.01)
    notes = " | ".join(_run(case).notes)
    assert "loop cut at B instead of prismatic slide" in notes
    assert "welded" not in notes


def test_tree_of_depth_first_order_starts_at_the_assembled_state():
    """a02_four_bar_n2's breadth-first tree: PyBullet renumbers links depth first, so the
    adapter must list them that way (else the start check fails by 1 m)."""
    case = dataclasses.replace(ec.case("a02_four_bar_n2"), duration=0.05)
    err = _errors(case, _table(case))
    assert max(err.values()) < 1e-4, err  # measured 1.2e-6


def test_bricard_loop_revolute_needs_its_axis_held(monkeypatch):
    """One point-to-point constraint makes the loop-closing J6 a ball joint (a 2-DOF loop):
    the adapter refuses that (as its capabilities say); with the refusal lifted the motion
    is wrong (P3 8.1e-2 m off over 0.5 s), and a second constraint 1 m along the axis
    restores Bricard's motion (3.1e-5 m)."""
    import natcoord.engines.pybullet_engine as pyb

    case = dataclasses.replace(ec.case("a04_bricard"), duration=0.5)
    held = _errors(case, _table(case, {"loop_axis_offset": 1.0}))
    with pytest.raises(Unsupported, match="revolute 'J6'.*loop_axis_offset"):
        _table(case)
    monkeypatch.setattr(pyb, "CAPABILITIES", dataclasses.replace(pyb.CAPABILITIES, rules=None))
    ball = _errors(case, _table(case))
    pos = ("xP3", "yP3", "zP3")
    assert max(held[k] for k in pos) < 1e-4, held
    assert max(ball[k] for k in pos) > 2e-2, ball


def _sensor_force(case, seconds: float, joint: str) -> np.ndarray:
    """PyBullet's force-torque sensor at ``joint`` after ``seconds`` at dt 1e-4, turned into
    the force on the joint's child link in world axes (it reports that force in the child's
    link frame), (3,) N."""
    import pybullet as pb

    from natcoord.engines.planar import lift_case, lift_init
    from natcoord.engines.pybullet_engine import DEFAULTS, multibody

    space = lift_case(case)
    frames = lift_init(case, initial_body_states(case))
    cid = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(*space.gravity.tolist(), physicsClientId=cid)
        pb.setPhysicsEngineParameter(fixedTimeStep=1e-4, erp=0.5, physicsClientId=cid)
        built = multibody.build(pb, cid, space, frames, DEFAULTS, case.dimension == 2)
        multibody.set_velocities(pb, cid, built, space, frames)
        i = built.joint_index[joint]
        pb.enableJointForceTorqueSensor(built.uid, i, True, physicsClientId=cid)
        for _ in range(round(seconds / 1e-4)):
            pb.stepSimulation(physicsClientId=cid)
        f = np.asarray(pb.getJointState(built.uid, i, physicsClientId=cid)[2][:3])
        q = pb.getLinkState(built.uid, i, computeForwardKinematics=1, physicsClientId=cid)[5]
        return np.array(pb.getMatrixFromQuaternion(q)).reshape(3, 3) @ f
    finally:
        pb.disconnect(physicsClientId=cid)


def test_joint_sensor_is_right_on_a_tree_but_leaves_out_the_loop():
    """Why reactions come from the subtree balance: PyBullet's joint sensor agrees with it
    on the pendulum (no loop; at 0.5 s the sensor 6.9e-3 N and the balance 1.2e-2 N from
    the reference, of 25 N), but on four_bar it misses the loop: O at 0.5 s (-121.5, -5.5) N
    against the reference's (-80.4, -2.5) N, the balance 0.14 N off."""
    for name, t, bound in (("pendulum", 0.5, 0.02), ("four_bar", 0.5, None)):
        case = ec.case(name)
        sensed = _sensor_force(case, t, "O")
        k = round(t / case.output_dt)
        ref = pd.read_csv(REFERENCES / f"{name}.csv")[["O_x", "O_y"]].to_numpy()[k]
        ours = _run(dataclasses.replace(case, duration=t)).motion.joint_force["O"][k]
        assert np.max(np.abs(ours - ref)) < 0.3  # measured 1.2e-2 / 0.14 N
        if bound is not None:
            assert np.max(np.abs(sensed[:2] - ref)) < bound
        else:
            assert np.max(np.abs(sensed[:2] - ref)) > 20.0  # measured 41.1 N


# ------------------------------------------------------------------------------ the traps

def test_link_damping_is_removed_so_energy_is_kept():
    """PyBullet damps every link by 0.04 s^-1: the rod swinging at 3 rad/s loses 0.56 J in
    2 s with it, 4e-4 J (Euler's first-order error) without."""
    case = _rod(2.0, 3.0, energy=True)
    kept = _table(case)["energy"]
    damped = _table(case, keep=("damping",))["energy"]
    assert np.max(np.abs(kept - kept.iloc[0])) < 1e-3  # measured 5.5e-4 J
    assert damped.iloc[0] - damped.iloc[-1] > 0.4  # measured 0.56 J


def test_default_motors_are_disabled_so_a_joint_turns_freely():
    """PyBullet drives every joint with a velocity motor (target 0): the
    rod started at 2 rad/s is stopped dead under it; without it, it swings up."""
    case = _rod(0.1, 2.0)
    held = _table(case, keep=("motors",))["theta"] + np.pi / 2
    free = _table(case)["theta"] + np.pi / 2
    assert np.max(np.abs(held)) < 1e-3
    assert free.iloc[-1] > 0.15  # 2 rad/s for 0.1 s, slowed by gravity


def test_inertia_is_the_declared_one_compound_pendulum_period():
    """The rod's small-oscillation period 2 pi sqrt(2 L / 3 g) (1 + theta0^2 / 16): with the
    declared inertia within 1e-5 (measured 5e-7 relative); with PyBullet's own inertia of a
    shapeless link 13 % short."""
    case = _rod(4.0, 0.1)
    amplitude = 0.1 / np.sqrt(1.5 * G)  # theta0 = omega0 / omega_n
    exact = 2 * np.pi * np.sqrt(2.0 / (3 * G)) * (1 + amplitude**2 / 16)

    def period(keep):
        tab = _table(case, keep=keep)
        x, t = tab["theta"].to_numpy() + np.pi / 2, tab["t"].to_numpy()
        k = np.flatnonzero(np.sign(x[:-1]) != np.sign(x[1:]))
        crossings = t[k] - x[k] * (t[k + 1] - t[k]) / (x[k + 1] - x[k])
        assert len(crossings) >= 4
        return 2 * float(np.mean(np.diff(crossings)))

    assert period(()) == pytest.approx(exact, rel=1e-5)
    assert period(("inertia",)) < 0.9 * exact  # measured 1.4185 s against 1.6380 s


def test_loop_closes_at_the_declared_point():
    """Pivots given relative to the centre of mass: four_bar's loop stays closed at D (the
    gap is the single-precision rounding of PyBullet's link frames, 3.7e-7 m, at t = 0);
    given relative to the link frame, the constraint holds other points and tears the
    mechanism open."""
    case = dataclasses.replace(ec.case("four_bar"), duration=0.1)
    run = _run(case)
    assert run.counters["start_loop_gap_m"] < 1e-6
    assert run.counters["loop_drift_m"] < 1e-6
    with pytest.raises(RuntimeError, match="a loop opened by"):
        _run(case, keep=("pivots",))


def test_joint_speed_cap_is_raised():
    """PyBullet caps joint rates at 100 rad/s by default (a03_andrews' crank turns at
    1.4e3 rad/s): a rod spinning at 300 rad/s without gravity keeps its rate."""
    case = _rod(0.05, 300.0, gravity=False)
    assert _run(case).motion.omega["rod"][-1] == pytest.approx(300.0, rel=1e-12)
    assert _run(case, keep=("speed",)).motion.omega["rod"][-1] == pytest.approx(100.0)


# ------------------------------------------------------------------------------ loads

def test_constant_torque_spins_the_rod_as_its_closed_form():
    """No gravity, 1 N m on the rod: theta = theta0 + tau t^2 / (2 I_O), I_O = m L^2 / 3;
    semi-implicit Euler's error is tau t dt / (2 I_O) (7.5e-6 rad at 0.1 s)."""
    case = dataclasses.replace(_rod(0.1, 0.0, gravity=False),
                               forces=(Force("torque", "rod", 1.0),))
    tab = _table(case)
    t = tab["t"].to_numpy()
    exact = -np.pi / 2 + t**2 / (2 * 2.0 / 3.0)
    np.testing.assert_allclose(tab["theta"], exact, rtol=0, atol=1e-5)


def test_flyball_governor_springs_follow_the_reference():
    """Spring-dampers applied at their points before every step; 0.3 s of a05 (measured
    s 7.2e-5 m, tensions 7.8e-2 N of ~44 N: first order, like the step)."""
    case = dataclasses.replace(ec.case("a05_flyball_governor"), duration=0.3)
    err = _errors(case, _table(case))
    assert err["s"] < 1.1e-4 and err["kA"] < 0.12 and err["kB"] < 0.12, err


# ------------------------------------------------------------------------------ refusals

@pytest.mark.parametrize("name, match", [
    ("slider_crank_driven", "prescribed motions"),
    ("five_bar", "massless rods"),
    ("slider_crank_3d", "universal"),
    ("parallelogram_3d_flexible", "not joined to the ground"),
])
def test_unsupported_cases_say_why(name, match):
    with pytest.raises(Unsupported, match=match):
        _run(ec.case(name))


def test_loop_of_prismatic_joints_is_unsupported():
    ec.assert_loop_of_prismatic_joints_is_unsupported("pybullet")


def test_step_must_divide_the_output_interval():
    ec.assert_step_must_divide_the_output_interval("pybullet", 3e-3, "divide")


def test_version_and_lazy_import():
    """pybullet has no __version__: the adapter reports the installed distribution's."""
    assert adapter("pybullet").version() == importlib.metadata.version("pybullet")
    code = ("import sys, natcoord.engines.pybullet_engine as m; "
            "assert 'pybullet' not in sys.modules; print(m.NAME, m.PACKAGE)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == ["pybullet", "pybullet"]


def test_settings_are_declared():
    a = adapter("pybullet")
    names = {s.name for s in a.SETTINGS}
    assert {"dt", "erp", "solver_iterations", "residual", "max_loop_drift"} <= names
