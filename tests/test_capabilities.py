"""Declared capabilities predict what each engine does: for every built-in engine and every
case (the catalogue, the test cases and variants made to hit each capability), the
reasons :func:`natcoord.engines.capabilities.reasons` gives are empty exactly when the
engine's own run does not raise Unsupported. Real runs over one output interval, no mock.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from natcoord.case.casefile import load_case
from natcoord.case.mechanism import Case, Driver, EngineSpec
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.engines.capabilities import Capabilities, reasons, why_not
from natcoord.engines.registry import BUILTIN
from natcoord.errors import NatcoordError, Unsupported
from natcoord.suite.worker import Job, run_one

from .conftest import CASES, DATA


def _variants() -> dict[str, tuple[Case, dict]]:
    """Cases that each touch one capability: (case, engine setting overrides)."""
    sc = load_case(CASES / "slider_crank.toml")
    slide = sc.joint("slide")
    par = load_case(CASES / "parallelogram_3d.toml")
    plate = par.body("plate")
    corner = next(p for p, x in plate.points.items() if any(abs(x - plate.com) > 1e-6))
    incline = load_case(DATA / "incline_3d.toml")
    rod = load_case(DATA / "driven_rod.toml")
    bricard = load_case(CASES / "a04_bricard.toml")
    return {
        # a second slide: a prismatic joint must close the loop
        "slider_crank+slide2": (dataclasses.replace(sc, joints=sc.joints + (
            dataclasses.replace(slide, name="slide2"),)), {}),
        # a force off the plate's centre of mass
        "parallelogram_3d+offset_force": (dataclasses.replace(par, forces=tuple(
            dataclasses.replace(f, point=corner) for f in par.forces)), {}),
        # the rod's tip height driven instead of its angle: a point off the centre of mass,
        # on a body pinned (not slid) to the ground
        "driven_rod+tip_height": (dataclasses.replace(rod, drivers=(Driver(
            "motor", "coordinate", "rod", 0.0, rate=0.5, point="tip", axis="y"),)), {}),
        # the block's slide made cylindrical (released at rest)
        "incline_3d+cylindrical": (dataclasses.replace(incline, joints=tuple(
            dataclasses.replace(j, type="cylindrical") for j in incline.joints)), {}),
        # Bricard's loop revolute at the engines' default settings, the case's own reasons
        # set aside (their measured failures are not capabilities)
        "a04_bricard@defaults": (dataclasses.replace(
            bricard, engines={e: EngineSpec() for e in bricard.engines}), {}),
    }


def _cases() -> dict[str, tuple[Case, dict]]:
    out = {}
    for f in sorted(CASES.glob("*.toml")) + sorted(Path(DATA).glob("*.toml")):
        try:
            c = load_case(f)
        except NatcoordError:  # a template with placeholders (tests fill them in)
            continue
        out[f"{f.parent.name}/{c.name}"] = (c, {})
    return out | _variants()


CASESET = _cases()
# natcoord models every element a case file holds (its capabilities are the defaults): its
# kernels compile per model, minutes for the catalogue here, so it runs the small models
SMALL_ONLY = {"natcoord"}


def _actual(engine: str, case: Case, settings: dict) -> str:
    """"" when the engine runs one output interval of ``case``, else its Unsupported text
    (any other failure is not a refusal: it runs, and fails)."""
    short = dataclasses.replace(case, duration=case.output_dt)
    init = initial_body_states(case)
    try:
        adapter(engine).run(short, init, {**case.engine(engine).settings, **settings})
    except Unsupported as e:
        return str(e) or "unsupported"
    except Exception:  # a run that fails is not a refusal
        return ""
    return ""


@pytest.mark.engines
@pytest.mark.slow
@pytest.mark.parametrize("engine", list(BUILTIN))
def test_capabilities_predict_every_refusal(engine):
    mod = adapter(engine)
    try:
        mod.version()
    except ImportError:
        pytest.skip(f"{mod.PACKAGE} is not installed")
    disagree, refused = [], 0
    for key, (case, settings) in CASESET.items():
        if case.engine(engine).unsupported:
            continue  # measured in the case file, not predicted
        if engine in SMALL_ONLY and key.startswith("cases/"):
            continue
        predicted = reasons(mod.CAPABILITIES, case, {
            **{s.name: s.default for s in mod.SETTINGS}, **case.engine(engine).settings,
            **settings})
        actual = _actual(engine, case, settings)
        refused += bool(actual)
        if bool(predicted) != bool(actual):
            disagree.append(f"{key}: predicted {predicted or 'runs'}; the engine: "
                            f"{actual or 'ran'}")
    assert not disagree, "\n".join(disagree)
    if engine != "natcoord":  # every other engine refuses something in this set
        assert refused, f"{engine} refused nothing: the set does not test its capabilities"


def test_slider_crank_driven_is_unsupported_before_running(tmp_path):
    """The case MuJoCo and Pinocchio used to accept and then refuse at run time: now
    unsupported from their capabilities, with the reason, and no engine process (no job
    file, no result file)."""
    from natcoord.suite.runner import run_subprocess

    case = load_case(CASES / "slider_crank_driven.toml")
    for engine in ("mujoco", "pinocchio"):
        why = why_not(case, engine)
        assert "driver 'motor'" in why and "prescribed motions are not modelled" in why
        rec = run_subprocess(Job(case, None, ""), engine, tmp_path, 60.0)
        assert rec["status"] == "unsupported" and rec["reason"] == why
        assert not (tmp_path / "results").exists()  # no worker was started
        assert run_one(Job(case, None, engine)).reason == why  # in-process: the same
    assert why_not(case, "natcoord") == ""


def test_reasons_name_what_is_missing():
    case = load_case(CASES / "four_bar.toml")
    assert reasons(Capabilities(), case) == []
    assert reasons(Capabilities(dimensions={3}), case) == ["2-D cases are not modelled"]
    got = reasons(Capabilities(loops="none"), case)
    assert len(got) == 1 and got[0].startswith("closed loops are not modelled (joint")
    explained = Capabilities(dimensions={3}, why={"dimensions": "a spatial-only engine"})
    assert reasons(explained, case) == ["2-D cases are not modelled: a spatial-only engine"]
    with pytest.raises(ValueError, match="loops must be one of"):
        Capabilities(loops="sometimes")
