"""Every engine's settings are a declared schema, checked when a case is loaded; no string of
a case file reaches an engine's model text unescaped; a mechanism natcoord cannot carry (no
degree of freedom, a body whose points cannot define its frame) is refused at load."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from natcoord import CaseError, load_case
from natcoord.case.casefile import load_cases
from natcoord.engines import adapter, engine_names
from natcoord.engines.schema import Setting, check, defaults, problems

from .conftest import CASES, PLATE, ROOT

ENGINES = engine_names()  # the built-ins and any plug-in installed here

ENGINE_DIRS = {"mujoco": "mujoco_engine", "pinocchio": "pinocchio_engine",
               "exudyn": "exudyn_engine", "dart": "dart_engine", "simbody": "simbody_engine",
               "pybullet": "pybullet_engine"}


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *args], capture_output=True,
                          text=True, timeout=600, cwd=cwd)


# ---- the declarations ---------------------------------------------------------------------
@pytest.mark.parametrize("engine", ENGINES)
def test_every_adapter_declares_its_settings(engine):
    mod = adapter(engine)
    names = [s.name for s in mod.SETTINGS]
    assert names and len(names) == len(set(names))
    for s in mod.SETTINGS:
        assert isinstance(s, Setting) and s.meaning
        assert not check({s.name: s.default}, mod.SETTINGS) or s.default is None, s
    if hasattr(mod, "DEFAULTS"):  # one source: the run's defaults are the declared ones
        assert mod.DEFAULTS == defaults(mod.SETTINGS)


@pytest.mark.parametrize("engine", sorted(ENGINE_DIRS))
def test_every_setting_an_adapter_reads_is_declared(engine):
    """The keys its code reads from the merged settings (s["key"], s.get("key"),
    settings.get("key")) are all in its schema."""
    read = set()
    for f in (ROOT / "natcoord" / "engines" / ENGINE_DIRS[engine]).glob("*.py"):
        text = f.read_text()
        read |= set(re.findall(r"\b(?:s|settings)(?:\.get\(|\[)[\"']([a-z_]+)[\"']", text))
    # results and counters read in the same files under the name s (not settings)
    read -= {"origin", "velocity", "omega", "acceleration", "alpha", "steps",
             "readout_time_s"}
    declared = {s.name for s in adapter(engine).SETTINGS}
    assert read and read <= declared, read - declared


def test_natcoord_schema_covers_the_solver():
    from dataclasses import fields

    from natcoord.dynamics.solver import FORMULATIONS

    declared = {s.name for s in adapter("natcoord").SETTINGS}
    options = {f.name for c in FORMULATIONS.values() for f in fields(c)}
    assert options | {"formulation", "method", "h", "rtol", "atol", "coordinates",
                      "reference", "reference_check"} == declared


def test_every_setting_of_a_stock_case_is_declared():
    seen = 0
    for case in load_cases(CASES).values():
        for engine, spec in case.engines.items():
            assert problems(adapter(engine), spec.settings) == [], (case.name, engine)
            seen += len(spec.settings)
    assert seen > 20


def test_loading_cases_does_not_import_any_engine():
    code = ("import sys\nfrom natcoord.case.casefile import load_cases\nload_cases('cases')\n"
            "from natcoord.engines import adapter\n"
            f"[adapter(e).SETTINGS for e in {list(ENGINES)!r}]\n"
            "print([m for m in ('mujoco', 'pinocchio', 'exudyn', 'dartpy', 'opensim', 'numba')"
            " if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    assert out.strip() == "[]"


# ---- the check ----------------------------------------------------------------------------
SCHEMA = (Setting("dt", "number", 1e-3, "step", "s", exclusive_minimum=0.0),
          Setting("n", "integer", 10, "count", minimum=1),
          Setting("on", "boolean", False, "flag"),
          Setting("kind", "choice", "a", "which", choices=("a", "b")),
          Setting("gains", "numbers", (1.0, 2.0), "pair", length=2, minimum=0.0),
          Setting("sub", "table", None, "nested", fields=(
              Setting("x", "number", 0.5, "x", minimum=0.0, maximum=1.0),)))


@pytest.mark.parametrize("settings, field, words", [
    ({"dt": 1}, None, None),
    ({"dt": 0.0}, "dt", "must be > 0 (s)"),
    ({"dt": True}, "dt", "must be a number"),
    ({"dt": "1e-3"}, "dt", "must be a number"),
    ({"dt": float("nan")}, "dt", "finite"),
    ({"dt": float("inf")}, "dt", "finite"),
    ({"n": 2.0}, "n", "must be an integer"),
    ({"n": 0}, "n", "must be >= 1"),
    ({"on": 1}, "on", "true or false"),
    ({"kind": "c"}, "kind", "must be one of a, b"),
    ({"kind": 1}, "kind", "must be one of a, b"),
    ({"gains": [1.0]}, "gains", "list of 2 numbers"),
    ({"gains": [1.0, -1.0]}, "gains[1]", "must be >= 0"),
    ({"sub": {"x": 2}}, "sub.x", "must be in [0, 1]"),
    ({"sub": {"y": 0}}, "sub.y", "unknown setting; known: x"),
    ({"sub": 3}, "sub", "must be a table"),
    ({"dtt": 1e-3}, "dtt", "unknown setting; known: dt, n, on, kind, gains, sub"),
    (3, "", "must be a table of settings"),
])
def test_check_names_the_field_and_the_reason(settings, field, words):
    found = check(settings, SCHEMA)
    if field is None:
        assert found == []
    else:
        assert found and found[0][0] == field and words in found[0][1], found


BAD = [
    # (engine, settings as TOML, field under engines.<engine>.settings, words)
    ("mujoco", "{ dt = 1e-4, solref_step = 5 }", "solref_step",
     "unknown setting; known: dt, integrator, solver"),
    ("mujoco", "{ integrator = 'RK4\" gravity=\"0 0 0' }", "integrator", "must be one of"),
    ("mujoco", "{ solver = 'Newton\"/><include file=\"/etc/hostname\"/><x a=\"' }", "solver",
     "must be one of PGS, CG, Newton"),
    ("mujoco", "{ dt = '1e-4' }", "dt", "must be a number (s)"),
    ("mujoco", "{ iterations = 1.5 }", "iterations", "must be an integer"),
    ("mujoco", "{ solref_steps = 1 }", "solref_steps", "must be >= 2"),
    ("mujoco", "{ solimp = [0.9, 0.95, 0.001, 0.5] }", "solimp", "list of 5 numbers"),
    ("mujoco", "{ solimp = [0.9, 1.5, 0.001, 0.5, 2] }", "solimp[1]", "below 1"),
    ("pinocchio", "{ dt = 'fast' }", "dt", "must be a number"),
    ("pinocchio", "{ method = 'euler' }", "method", "must be one of rk4, radau"),
    ("exudyn", "{ newton_tolerance = 1e-6 }", "newton_tolerance", "unknown setting"),
    ("exudyn", "{ modified_newton = 'yes' }", "modified_newton", "true or false"),
    ("dart", "{ erp = 2.0 }", "erp", "must be in [0, 1]"),
    ("dart", "{ loop_constraint = 'weld' }", "loop_constraint", "must be one of ball, revolute"),
    ("simbody", "{ integrator = 'rk_mersen' }", "integrator", "must be one of rk_merson"),
    ("simbody", "{ step_limit = -1 }", "step_limit", "must be in [1, 2147483647]"),
    ("mujoco", "{ iterations = 9223372036854775807 }", "iterations",  # MuJoCo's XML: a C int
     "must be in [1, 2147483647]"),
    ("natcoord", "{ methd = 'dop853' }", "methd", "unknown setting"),
    ("natcoord", "{ method = 'rk4' }", "", "fixed-step method"),
    ("natcoord", "{ reference = { method = 'rk4' } }", "reference", "fixed-step method"),
    ("natcoord", "{ reference = { rtol = -1 } }", "reference.rtol", "must be in (0, 1]"),
    ("natcoord", "{ rtol = 1e300 }", "rtol", "must be in (0, 1]"),  # failed at run time
    ("natcoord", "{ rank_tol = 1e10 }", "rank_tol", "must be in (0, 1)"),
    ("natcoord", "{ coordinates = 'shard' }", "coordinates", "must be one of joints, shared"),
]


@pytest.mark.parametrize("engine, settings, field, words", BAD,
                         ids=[f"{b[0]}-{b[2] or 'combination'}" for b in BAD])
def test_bad_engine_settings_are_refused_at_load(tmp_path, engine, settings, field, words):
    text = (CASES / "pendulum.toml").read_text()
    bad = re.sub(rf"^\[engines\.{engine}\]\n(settings = .*\n)?",
                 f"[engines.{engine}]\nsettings = {settings}\n", text, count=1, flags=re.M)
    assert bad != text
    p = tmp_path / "pendulum.toml"
    p.write_text(bad)
    with pytest.raises(CaseError) as info:
        load_case(p)
    e = info.value
    assert e.file == str(p)
    assert e.field == f"engines.{engine}.settings" + (f".{field}" if field else ""), str(e)
    assert words in e.reason, str(e)


def test_a_typo_in_an_engine_table_is_refused(case_variant):
    p = case_variant("pendulum", [(r"^settings = \{ dt = 1e-4 \}", "setings = { dt = 1e-4 }")])
    with pytest.raises(CaseError, match=r"engines.mujoco.setings: unknown field; expected "
                                        "some of reason, settings, tolerance, unsupported"):
        load_case(p)


def test_an_injected_mujoco_setting_is_refused_by_the_command_line(case_variant, tmp_path):
    p = case_variant("pendulum", [(r"^settings = \{ dt = 1e-4 \}",
                                   "settings = { dt = 1e-4, integrator = 'RK4\" gravity=\"0 0 "
                                   "0\"><include file=\"/etc/hostname\"/><x a=\"' }")])
    out = tmp_path / "out"
    r = _cli("run", str(p), "--engines", "mujoco", "--out", str(out))
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert f"{p}: engines.mujoco.settings.integrator: must be one of" in r.stderr
    assert not (out / "summary.json").exists()


def test_cases_json_shows_each_engines_schema(tmp_path):
    r = _cli("cases", "--json", cwd=ROOT)
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    assert {c["name"] for c in data["cases"]} >= {"pendulum", "a04_bricard"}
    for engine in ENGINES:
        shown = data["engines"][engine]
        assert shown["package"] == adapter(engine).PACKAGE
        assert [s["name"] for s in shown["settings"]] == [s.name for s in
                                                          adapter(engine).SETTINGS]
    dt = next(s for s in data["engines"]["mujoco"]["settings"] if s["name"] == "dt")
    assert dt == {"name": "dt", "type": "number", "exclusive_minimum": 0.0, "range": "> 0",
                  "unit": "s", "default": 1e-4,
                  "meaning": "time step; must divide the case's output interval"}
    integ = next(s for s in data["engines"]["mujoco"]["settings"] if s["name"] == "integrator")
    assert integ["choices"] == ["Euler", "RK4", "implicit", "implicitfast"]


# ---- MJCF text ----------------------------------------------------------------------------
HOSTILE = '1" gravity="0 0 0"><include file="/etc/hostname"/><x a="&<>\''


def test_the_mjcf_writer_escapes_every_string():
    """A value that bypasses the loader (an adapter called directly) cannot add attributes or
    elements: the option keeps its gravity and the hostile text stays one attribute value."""
    from natcoord.engines import mujoco_engine
    from natcoord.engines.mujoco_engine import mjcf
    from natcoord.engines.planar import lift_case

    case = lift_case(load_case(CASES / "pendulum.toml"))
    s = mujoco_engine.DEFAULTS | {"integrator": HOSTILE, "solver": HOSTILE}
    xml = mjcf.document(case, s, {}, [], [], [])
    root = ET.fromstring(xml)
    option = root.find("option")
    assert option.get("integrator") == HOSTILE and option.get("solver") == HOSTILE
    assert option.get("gravity") == "0.0 -9.81 0.0"
    assert root.find(".//include") is None and root.find(".//x") is None


def test_names_in_the_mjcf_are_escaped():
    """Joint and case names (the loader allows only identifiers; the writer escapes anyway)
    stay attribute values in every element that carries them."""
    import dataclasses

    pytest.importorskip("mujoco")
    from natcoord.engines import mujoco_engine
    from natcoord.engines.base import initial_body_states
    from natcoord.engines.mujoco_engine import mjcf
    from natcoord.engines.planar import lift_case, lift_init

    case = load_case(CASES / "four_bar.toml")
    init = initial_body_states(case)
    names = {j.name: f"{j.name}{HOSTILE}" for j in case.joints}
    hostile = dataclasses.replace(
        case, name=HOSTILE, joints=tuple(dataclasses.replace(j, name=names[j.name])
                                         for j in case.joints))
    space = lift_case(hostile)
    built = mjcf.build(space, lift_init(hostile, init), mujoco_engine.DEFAULTS, True)
    root = ET.fromstring(built.xml)
    assert root.get("model") == HOSTILE
    assert root.find(".//include") is None and root.find(".//x") is None
    joint_names = {e.get("name") for e in root.iter("joint")}
    connects = list(root.iter("connect"))
    assert joint_names | {c.get("name") for c in connects} == set(names.values())
    assert all(c.get("site1").endswith("_0") and HOSTILE in c.get("site1") for c in connects)
    assert root.find("option").get("gravity") == "0.0 -9.81 0.0"


def test_mujoco_refuses_an_escaped_bad_keyword():
    """What still reaches MuJoCo escaped is one bad keyword it refuses: an error, never a
    silently changed model."""
    mujoco = pytest.importorskip("mujoco")
    from natcoord.engines import mujoco_engine
    from natcoord.engines.mujoco_engine import mjcf
    from natcoord.engines.planar import lift_case

    case = lift_case(load_case(CASES / "pendulum.toml"))
    xml = mjcf.document(case, mujoco_engine.DEFAULTS | {"integrator": 'RK4" gravity="0 0 0'},
                        {}, [], [], [])
    with pytest.raises(ValueError, match="invalid keyword"):
        mujoco.MjModel.from_xml_string(xml)


# ---- mechanisms natcoord cannot carry -----------------------------------------------------
TRIANGLE = """name = "triangle"
description = "two rods pinned to the ground and to each other: a locked triangle"
dimension = 2
gravity = [0.0, -9.81]
duration = 0.1
output_dt = 0.01
[ground]
points = { O = [0.0, 0.0], D = [2.0, 0.0] }
[[bodies]]
name = "a"
kind = "uniform_rod"
mass = 1.0
points = { O = [0.0, 0.0], A = [1.0, 1.0] }
[[bodies]]
name = "b"
kind = "uniform_rod"
mass = 1.0
points = { A = [1.0, 1.0], D = [2.0, 0.0] }
[[joints]]
name = "O"
type = "revolute"
bodies = ["ground", "a"]
points = ["O", "O"]
[[joints]]
name = "A"
type = "revolute"
bodies = ["a", "b"]
points = ["A", "A"]
[[joints]]
name = "D"
type = "revolute"
bodies = ["ground", "b"]
points = ["D", "D"]
[channels]
x = { kind = "position", body = "a", point = "A", axis = "x" }
"""

def _drivers(*pairs) -> str:
    """Coordinate drivers holding z of (body, point, value0) in four_bar_3d."""
    return "".join(f'[[drivers]]\nname = "m{k}"\ntype = "coordinate"\nbody = "{b}"\n'
                   f'point = "{p}"\naxis = "z"\nvalue0 = {v!r}\nrate = 0.1\n\n'
                   for k, (b, p, v) in enumerate(pairs))


CRANK_Z = ("crank", "A", 0.8660254037844386)
ROCKER_Z = ("rocker", "C", 1.441312021736259)


def _four_bar_3d(tmp_path, drivers: str, stem: str = "four_bar_3d") -> Path:
    text = (CASES / "four_bar_3d.toml").read_text().replace(
        "[initial]\nvelocity = { theta = 0.0 }\n", drivers)
    text = text.replace('name = "four_bar_3d"', f'name = "{stem}"')
    p = tmp_path / f"{stem}.toml"
    p.write_text(text)
    return p


def test_a_locked_mechanism_is_refused_with_the_counts(tmp_path):
    p = tmp_path / "triangle.toml"
    p.write_text(TRIANGLE)
    with pytest.raises(CaseError) as info:
        load_case(p)
    assert info.value.field == "joints"
    assert info.value.reason == ("the mechanism has no degree of freedom: 8 coordinates, "
                                 "rank Phi_q = 8, drivers 0")


def test_a_four_bar_with_a_driver_on_each_crank_is_refused(tmp_path):
    p = _four_bar_3d(tmp_path, _drivers(CRANK_Z, ROCKER_Z))
    with pytest.raises(CaseError) as info:
        load_case(p)
    assert info.value.field == "joints"
    assert info.value.reason.startswith("the mechanism has no degree of freedom for its "
                                        "drivers: 36 coordinates, rank Phi_q = 36 with the "
                                        "drivers (35 without: 1 degree(s) of freedom), "
                                        "drivers 2"), str(info.value)


def test_driven_and_redundant_mechanisms_still_load(tmp_path):
    """One driver on the four-bar takes its one degree of freedom (0 left: the driver is
    the motion); Bricard is Grübler 0 with one redundant constraint (mobility 1);
    slider_crank_driven is driven."""
    from natcoord.model.casemodel import build, initial_positions, mobility

    one = load_case(_four_bar_3d(tmp_path, _drivers(CRANK_Z)))
    for case in (one, load_case(CASES / "a04_bricard.toml"),
                 load_case(CASES / "slider_crank_driven.toml")):
        cm = build(case)
        n, r0, r, d = mobility(cm, initial_positions(cm))
        assert n - r0 == 1 and r - r0 == d, (case.name, n, r0, r, d)
    bricard = build(load_case(CASES / "a04_bricard.toml")).model
    assert bricard.m - bricard.n == 0  # as many rows as coordinates: Grübler's count is 0


@pytest.mark.parametrize("text, stem, field, words", [
    (TRIANGLE, "triangle", "joints", "no degree of freedom"),
    (PLATE, "plate", "bodies[0] (plate).points", "cannot define its frame"),
])
def test_the_command_line_refuses_them_without_a_traceback(tmp_path, text, stem, field,
                                                           words):
    p = tmp_path / f"{stem}.toml"
    p.write_text(text)
    r = _cli("run", str(p), "--engines", "natcoord,mujoco", "--out", str(tmp_path / "out"))
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr
    assert f"{p}: {field}: " in r.stderr and words in r.stderr, r.stderr


def test_a_plate_with_an_axis_or_a_planar_mass_loads(tmp_path):
    """What natcoord can carry still loads: the same plate on a revolute (its axis completes
    the frame), or with its mass in the plane of its points (a lamina)."""
    revolute = PLATE.replace('type = "spherical"', 'type = "revolute"\naxis = [0.0, 0.0, 1.0]')
    lamina = PLATE.replace("[0, 0, 0.1]]", "[0, 0, 0.2]]")  # Izz = Ixx + Iyy: all in z = 0
    for k, text in enumerate((revolute, lamina)):
        p = tmp_path / f"plate{k}.toml"
        p.write_text(text.replace('name = "plate"\ndescription', f'name = "plate{k}"\n'
                                  "description"))
        assert load_case(p).name == f"plate{k}"


@pytest.mark.parametrize("h, k", [(0.004, 3), (0.005, 2), (0.01, 1), (0.02, 1)])
def test_natcoord_says_the_fixed_step_it_took(h, k):
    """A fixed step h is the longest step: each output interval (0.01 s) is taken in k
    equal steps, which the run's notes state and its step count confirms."""
    from natcoord.engines import natcoord_engine

    case = load_case(CASES / "pendulum.toml")
    run = natcoord_engine.run(case, None, {"formulation": "index1", "method": "rk4", "h": h})
    intervals = len(case.times) - 1
    assert run.n_steps == k * intervals, (run.n_steps, intervals)
    assert f"fixed steps of {0.01 / k:.6g} s: {k} per output interval of 0.01 s (h = {h:g} s" \
        in " ".join(run.notes), run.notes
