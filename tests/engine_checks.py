"""Helpers shared by the engine adapter tests: run a case, compare with natcoord."""

from __future__ import annotations

import dataclasses
import importlib
import subprocess
import sys

import numpy as np
import pytest

from natcoord.case.casefile import load_case
from natcoord.case.mechanism import Case, Channel, Joint
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.errors import Unsupported
from natcoord.outputs.result import evaluate_channels

from .conftest import CASES, DATA, ROOT

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


def data_case(tmp_path, name: str, subs: dict[str, str] | None = None) -> Case:
    """``tests/data/<name>.toml``, loaded; with ``subs``, each placeholder (which must occur)
    replaced by its text first and the result loaded from ``tmp_path``."""
    if not subs:
        return load_case(DATA / f"{name}.toml")
    text = (DATA / f"{name}.toml").read_text(encoding="utf-8")
    for placeholder, repl in subs.items():
        assert placeholder in text, f"{placeholder!r} not found in {name}.toml"
        text = text.replace(placeholder, repl)
    return case_from_text(tmp_path, text, name)


def worst(err: dict[str, float], *suffixes: str) -> float:
    """The largest of the errors whose key ends with one of ``suffixes``."""
    return max(v for k, v in err.items() if k.endswith(suffixes))


def open_chain() -> Case:
    """slider_crank without its slide: crank, rod and the particle hanging at B, moving."""
    c = case("slider_crank")
    return dataclasses.replace(
        c, duration=0.3, joints=c.joints[:3],
        channels=(Channel("theta", "angle", body="crank"), Channel("phi", "angle", body="rod")),
        fix={"theta": 0.785398, "phi": -0.3}, velocity={"theta": 1.0, "phi": 2.0})


def free_bodies() -> Case:
    """The open chain with only joint O: the rod and the particle fly free in the plane."""
    base = open_chain()
    return dataclasses.replace(
        base, joints=base.joints[:1],
        channels=(Channel("theta", "angle", body="crank"), Channel("phi", "angle", body="rod"),
                  Channel("xA", "position", body="rod", point="A", axis="x"),
                  Channel("yA", "position", body="rod", point="A", axis="y"),
                  Channel("xB", "position", body="slider", point="B", axis="x"),
                  Channel("yB", "position", body="slider", point="B", axis="y")),
        fix={"theta": 0.785398, "phi": 0.3, "xA": 0.7, "yA": 0.7, "xB": 1.0, "yB": 2.0},
        velocity={"theta": 1.0, "phi": -2.0, "xA": 0.5, "yA": 1.0, "xB": -1.0, "yB": 3.0})


def channel_tables(engine: str, c: Case):
    """``engine``'s run of ``c`` with natcoord's channel table and its own, both from the same
    initial state: (run, natcoord table, engine table)."""
    init = initial_body_states(c)
    a = evaluate_channels(c, adapter("natcoord").run(c, init, {}).motion)
    run_ = adapter(engine).run(c, init, {})
    return run_, a, evaluate_channels(c, run_.motion)


def assert_hanging_rod_pushes_up(engine: str):
    """The hanging rod at rest: the pivot pushes up with m g, nothing sideways, the angle
    stays at -90 deg. Returns (case, run) for the engine's own checks."""
    c = hanging_rod()
    run_ = run(engine, c)
    table = evaluate_channels(c, run_.motion)
    np.testing.assert_allclose(table["O_y"], 2.0 * G, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["O_x"], 0.0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table["theta"], -np.pi / 2, rtol=0, atol=1e-12)
    return c, run_


def assert_version_and_lazy_import(engine: str, package: str, module: str, printed: str,
                                   expected: list[str]) -> None:
    """The adapter reports the package's version, and importing ``natcoord.engines.<module>``
    (as ``m``) does not import the package; ``printed`` is printed there, split into
    ``expected``."""
    assert adapter(engine).version() == importlib.import_module(package).__version__
    code = (f"import sys, natcoord.engines.{module} as m; "
            f"assert {package!r} not in sys.modules; print({printed})")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert out.stdout.split() == expected


def assert_step_must_divide_the_output_interval(engine: str, dt: float, match: str) -> None:
    """A time step that does not divide the hanging rod's output interval is refused."""
    with pytest.raises(ValueError, match=match):
        run(engine, hanging_rod(), {"dt": dt})


def assert_loop_of_prismatic_joints_is_unsupported(engine: str) -> None:
    """slider_crank with a second slide: refused before the (empty) state is used."""
    c = case("slider_crank")
    slide = c.joint("slide")
    c = dataclasses.replace(c, joints=c.joints + (dataclasses.replace(slide, name="slide2"),))
    with pytest.raises(Unsupported, match="slide2"):
        adapter(engine).run(c, {}, {})
