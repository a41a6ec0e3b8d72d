"""Helpers shared by the engine adapter tests: run a case, compare with natcoord."""

from __future__ import annotations

import dataclasses

import numpy as np

from natcoord.casefile import load_case
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.mechanism import Case, Joint
from natcoord.result import evaluate_channels

from .conftest import CASES, DATA

G = 9.81


def case(name: str) -> Case:
    """A shipped case by name."""
    return load_case(CASES / f"{name}.toml")


def hanging_rod() -> Case:
    return load_case(DATA / "hanging_rod.toml")


def run(engine: str, c: Case, settings: dict | None = None):
    """Run ``c`` in ``engine`` from natcoord's assembled state."""
    return adapter(engine).run(c, initial_body_states(c), settings or {})


def natcoord(c: Case):
    return run("natcoord", c)


def reversed_joint(j: Joint) -> Joint:
    """The same joint with its bodies (and points) listed the other way round."""
    return dataclasses.replace(j, bodies=j.bodies[::-1], points=j.points[::-1])


def channel_errors(c: Case, run_, ref_run) -> dict[str, float]:
    """Max |run - reference| of every channel, on identical sample times."""
    a, b = evaluate_channels(c, ref_run.motion), evaluate_channels(c, run_.motion)
    assert list(a.columns) == list(b.columns)
    np.testing.assert_array_equal(a["t"], b["t"])
    return {ch.name: float(np.max(np.abs(a[ch.name] - b[ch.name]))) for ch in c.channels}


def motion_errors(c: Case, a, b) -> dict[str, float]:
    """Max abs difference of every body's origin, angle, velocity, omega and joint force."""
    out = {}
    for body in c.bodies:
        n = body.name
        for kind in ("origin", "angle", "velocity", "omega"):
            out[f"{n}.{kind}"] = float(np.max(np.abs(getattr(a, kind)[n] - getattr(b, kind)[n])))
    for j in c.joints:
        out[f"{j.name}.force"] = float(np.max(np.abs(a.joint_force[j.name]
                                                     - b.joint_force[j.name])))
    return out


def case_from_text(tmp_path, text: str, name: str) -> Case:
    """A case file's ``text`` written to ``tmp_path/<name>.toml`` and loaded."""
    path = tmp_path / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    return load_case(path)


def channel_mismatches(c: Case, a, b, bound: dict[str, float], default: float) -> list[str]:
    """The channels of tables ``a`` and ``b`` whose max difference exceeds the bound of their
    kind (``default`` for kinds not in ``bound``), as "name: error"."""
    return [f"{ch.name}: {np.max(np.abs(a[ch.name] - b[ch.name])):.3g}" for ch in c.channels
            if not np.max(np.abs(a[ch.name] - b[ch.name])) <= bound.get(ch.kind, default)]


def assert_reversed_joint_flips_the_reaction(engine: str) -> None:
    """bodies = [rod, ground] on the hanging rod: the reaction is then the force on the
    ground, -m g (the case convention: force on the second body named)."""
    c = hanging_rod()
    c = dataclasses.replace(c, joints=(reversed_joint(c.joint("O")),))
    table = evaluate_channels(c, run(engine, c).motion)
    np.testing.assert_allclose(table["O_y"], -2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)
