"""One model for every case style: drivers and 3-D prismatic joints in reference-frame cases
(against their closed forms), and the posed and reference-frame writings of one mechanism
giving the same model."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from natcoord import load_case
from natcoord.case.mechanism import Pose
from natcoord.engines import natcoord_engine
from natcoord.engines.base import initial_body_states
from natcoord.errors import AssemblyError
from natcoord.model import casemodel
from natcoord.outputs.result import evaluate_channels

DATA = Path(__file__).parent / "data"


def _run(name: str, settings: dict | None = None):
    case = load_case(DATA / f"{name}.toml")
    run = natcoord_engine.run(case, initial_body_states(case), settings or {})
    return case, evaluate_channels(case, run.motion)


@pytest.mark.parametrize("settings", [{}, {"formulation": "maggi", "method": "dop853"},
                                      {"formulation": "index3", "h": 1e-3}])
def test_reference_frame_case_follows_its_angle_driver(settings):
    """driven_rod: theta = pi/2 t; driver torque m g L/2 cos(theta); pin force m a_G - m g."""
    case, table = _run("driven_rod", settings)
    t, m, g, L, w = case.times, 2.0, 9.81, 1.0, np.pi / 2
    th = w * t
    exact = {"theta": th, "torque": m * g * L / 2 * np.cos(th),
             "Rx": -m * w * w * L / 2 * np.cos(th), "Ry": -m * w * w * L / 2 * np.sin(th) + m * g}
    tol = 1e-6 if settings.get("formulation") == "index3" else 1e-9
    for name, x in exact.items():
        err = np.max(np.abs(table[name].to_numpy() - x))
        assert err < tol * max(1.0, np.max(np.abs(x))), f"{name}: {err:.3g}"


def test_reference_frame_3d_prismatic_joint_matches_the_closed_form():
    """incline_3d: s = (g . u) t^2 / 2 along u; the joint's force on the block is
    -m (g - (g . u) u), constant."""
    case, table = _run("incline_3d")
    u = np.ones(3) / np.sqrt(3)
    g, m = np.array([0.0, 0.0, -9.81]), 2.0
    s = 0.5 * (g @ u) * case.times**2
    start = np.array([0.3, 0.2, 0.1])
    R = -m * (g - (g @ u) * u)
    for k, ax in enumerate("xyz"):
        assert np.max(np.abs(table[ax] - (start[k] + s * u[k]))) < 1e-12
        assert np.max(np.abs(table[f"R{ax}"] - R[k])) < 1e-9


def test_3d_prismatic_joint_rows_and_mobility():
    """A prismatic joint in 3-D: 2 point-on-line rows, 2 alignment rows, 1 no-spin row;
    the block keeps one degree of freedom."""
    cm = casemodel.build(load_case(DATA / "incline_3d.toml"))
    labels = [lab for lab in cm.model.constraints.labels if lab.startswith("slide:")]
    assert sorted(lab.split(": ")[1] for lab in labels) == [
        "axis.0", "axis.1", "line.0", "line.1", "no spin"]
    q = casemodel.initial_state(cm).q
    assert np.linalg.matrix_rank(cm.model.constraints.jacobian(q)) == cm.model.n - 1


def test_posed_and_reference_frame_writings_give_one_motion():
    """slider_crank written with approximate poses (its file) and the same mechanism
    written in the reference frame (every body frame the world frame at t = 0, points at
    their assembled positions): the same trajectory and reactions."""
    posed = load_case("cases/slider_crank.toml")
    init = initial_body_states(posed)
    bodies = []
    for b in posed.bodies:  # body points moved to their world positions at t = 0
        R, o = init[b.name].rotation, init[b.name].origin
        pts = {k: o + R @ x for k, x in b.points.items()}
        bodies.append(dataclasses.replace(b, points=pts, com=o + R @ b.com))
    joints = tuple(dataclasses.replace(j, axis=None if j.axis is None else (
        j.axis if j.bodies[0] == "ground" else init[j.bodies[0]].rotation @ j.axis))
        for j in posed.joints)
    flat = dataclasses.replace(posed, bodies=tuple(bodies), joints=joints, fix={},
                               guess={b.name: Pose(np.zeros(2)) for b in bodies},
                               pose_tolerance=1e-6)
    a = evaluate_channels(posed, natcoord_engine.run(posed, init, {}).motion)
    b = evaluate_channels(flat, natcoord_engine.run(flat, initial_body_states(flat),
                                                    {}).motion)
    for ch in posed.channels:
        if ch.kind == "angle":  # a body angle is measured from its own frame
            continue
        assert np.max(np.abs(a[ch.name] - b[ch.name])) < 1e-9, ch.name


def test_points_that_do_not_close_the_joints_are_refused():
    """In a reference-frame case the points are exact: assembly may not move them."""
    case = load_case(DATA / "incline_3d.toml")
    block = case.bodies[0]
    moved = dataclasses.replace(block, points={**block.points,
                                               "c": block.points["c"] + [0.0, 0.0, 0.01]})
    with pytest.raises(AssemblyError, match="slide: line"):
        casemodel.initial_state(casemodel.build(dataclasses.replace(case, bodies=(moved,))))
