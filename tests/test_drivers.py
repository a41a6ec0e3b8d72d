"""Drivers: the driven slider-crank against closed-form kinematics and inverse dynamics."""

from __future__ import annotations

import numpy as np
import pytest

from natcoord import CaseError, load_case
from natcoord.engines import natcoord_engine
from natcoord.outputs.result import evaluate_channels

CASE = "cases/slider_crank_driven.toml"


def closed_form(t):
    """xB, vB, aB and the driving torque of the slider-crank (r = 1, l = 2, uniform rods of
    1 kg, slider 1 kg, no gravity) with the crank at theta = 2 pi t."""
    r, l, w = 1.0, 2.0, 2 * np.pi
    s, c = np.sin(w * t), np.cos(w * t)
    D = np.sqrt(l * l - r * r * s * s)
    xB = r * c + D
    vB = -r * s * w - r * r * s * c * w / D
    aB = -r * c * w * w - r * r * w * w * (c * c - s * s) / D - r**4 * s * s * c * c * w * w / D**3
    vA, aA = np.stack([-r * s * w, r * c * w], 1), np.stack([-r * c * w * w, -r * s * w * w], 1)
    vG = (vA + np.stack([vB, 0 * t], 1)) / 2
    aG = (aA + np.stack([aB, 0 * t], 1)) / 2
    phid = -r * c * w / D  # rod angular velocity and acceleration
    phidd = r * s * w * w / D - r**3 * s * c * c * w * w / D**3
    # power balance (the crank turns uniformly, so its kinetic energy is constant)
    tau = (np.sum(aG * vG, 1) + (l * l / 12) * phidd * phid + aB * vB) / w
    return {"xB": xB, "vB": vB, "aB": aB, "torque": tau}


@pytest.mark.parametrize("settings", [
    {}, {"formulation": "index1", "method": "rk4", "h": 0.01},
    {"formulation": "maggi", "method": "dopri5"}, {"formulation": "index3", "h": 1e-3}])
def test_driven_slider_crank_matches_closed_form(settings):
    case = load_case(CASE)
    run = natcoord_engine.run(case, None, settings)
    table = evaluate_channels(case, run.motion)
    exact = closed_form(case.times)
    for name, tol in (("xB", 1e-10), ("vB", 1e-10), ("aB", 1e-10), ("torque", 1e-9)):
        err = np.max(np.abs(table[name].to_numpy() - exact[name]))
        assert err < tol, f"{name}: {err:.3g}"
    np.testing.assert_allclose(table["theta"], 2 * np.pi * case.times, atol=1e-12)


def test_driver_table_is_validated(tmp_path):
    text = open(CASE).read()
    for bad, field in [('body = "crank"\nangle0', "body"), ('rate = "360 deg/s"', "rate")]:
        broken = text.replace(bad, bad.replace("crank", "nope").replace("deg/s", "m"), 1)
        p = tmp_path / "slider_crank_driven.toml"
        p.write_text(broken)
        with pytest.raises(CaseError, match=field):
            load_case(p)
    p.write_text(text.replace('driver = "motor"', 'driver = "nope"'))
    with pytest.raises(CaseError, match="unknown driver"):
        load_case(p)
