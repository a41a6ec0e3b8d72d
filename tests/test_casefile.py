"""Case files: the shipped ones load; every kind of mistake is named by file, field, reason."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from natcoord import CaseError, load_case
from natcoord.case.casefile import load_cases

from .conftest import CASES, PLATE, SPHERICAL_ROD


def test_shipped_cases_load():
    cases = load_cases(CASES)
    assert {"slider_crank", "four_bar"} <= set(cases)
    sc = cases["slider_crank"]
    assert sc.fix["theta"] == pytest.approx(np.pi / 4)
    assert sc.body("crank").inertia == pytest.approx(1 / 12)
    assert sc.times[-1] == pytest.approx(2.0) and len(sc.times) == 201


MALFORMED = [
    # (description, substitutions, expected field, expected words in the reason)
    ("missing field", [(r"^duration = 2.0\n", "")], "duration", "missing required field"),
    ("wrong type", [(r"^mass = 1.0", 'mass = "heavy"')], "bodies[0] (crank).mass",
     "cannot read"),
    ("wrong unit", [(r"^mass = 1.0", 'mass = "1 m"')], "bodies[0] (crank).mass",
     "expected a mass"),
    ("unknown unit", [(r"^duration = 2.0", 'duration = "2 fortnights"')], "duration",
     "unknown unit"),
    ("negative mass", [(r"^mass = 1.0", "mass = -1.0")], "bodies[0] (crank).mass",
     "must be positive"),
    ("unknown body in joint", [(r'bodies = \["crank", "rod"\]', 'bodies = ["crank", "rood"]')],
     "joints[1] (A).bodies", "unknown body 'rood'"),
    ("unknown point", [(r'points = \["A", "A"\]', 'points = ["A", "Z"]')],
     "joints[1] (A).points", "has no point 'Z'"),
    ("unknown joint type", [(r'type = "revolute"', 'type = "hinge"')], "joints[0] (O).type",
     "unknown value 'hinge'"),
    ("unknown channel kind", [(r'kind = "angle", body = "crank"', 'kind = "torque"')],
     "channels.theta.kind", "unknown value 'torque'"),
    ("channel on unknown joint", [(r'joint = "O", axis = "x"', 'joint = "Q", axis = "x"')],
     "channels.O_x.joint", "unknown joint 'Q'"),
    ("duplicate body", [(r'name = "rod"', 'name = "crank"')], "bodies[1].name",
     "duplicate body name"),
    ("output_dt not dividing", [(r"^output_dt = 0.01", "output_dt = 0.03")], "output_dt",
     "must divide"),
    ("unknown top-level field", [(r"^dimension = 2", "dimension = 2\ncolour = 'red'")],
     "colour", "unknown field"),
    ("name mismatch", [(r'^name = "slider_crank"', 'name = "other"')], "name",
     "must equal the file name"),
    ("tolerance on unknown channel", [(r"^angle = 1e-9", "thetta = 1e-9")],
     "engines.natcoord.tolerance.thetta", "neither a channel"),
    ("unknown engine", [(r"^\[engines.natcoord\]", "[engines.bullet]")], "engines.bullet",
     "unknown engine 'bullet' (did you mean pybullet?)"),
    ("no engine's name", [(r"^\[engines.natcoord\]", '["engines"."my-plug"]')],
     "engines.my-plug", "unknown engine 'my-plug'"),
    ("zero prismatic axis", [(r"^axis = \[1.0, 0.0\]", "axis = [0.0, 0.0]")],
     "joints[3] (slide).axis", "must not be zero"),
    ("engine step not dividing output_dt", [(r"^\[engines.mujoco.settings\]\ndt = 1e-4",
                                             "[engines.mujoco.settings]\ndt = 3e-3")],
     "engines.mujoco.settings.dt", "must divide the output interval"),
    ("initial value on unknown channel", [(r'^fix = \{ theta = "45 deg" \}',
                                           'fix = { phi = "45 deg" }')],
     "initial.fix.phi", "unknown channel"),
    ("timeout below --timeout's range", [(r"^duration = 2.0", "duration = 2.0\ntimeout = 1e-9")],
     "timeout", "must be between 0.001 s and 604800 s"),
]


@pytest.mark.parametrize("what, subs, field, words", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_case_is_rejected_with_file_field_reason(case_variant, what, subs, field,
                                                           words):
    path = case_variant("slider_crank", subs)
    with pytest.raises(CaseError) as info:
        load_case(path)
    e = info.value
    assert e.file == str(path)
    assert e.field == field, str(e)
    assert words in e.reason, str(e)


def test_not_toml(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("name = [unclosed\n")
    with pytest.raises(CaseError, match="not valid TOML"):
        load_case(p)


def test_mechanism_that_does_not_assemble(case_variant):
    # the connecting rod is too short to reach the slide line from the crank at 45 deg
    path = case_variant("slider_crank", [(r"B = \[2.0, 0.0\]", "B = [0.5, 0.0]")])
    r = subprocess.run([sys.executable, "-m", "natcoord.cli", "run", str(path), "--engines",
                        "natcoord", "--out", str(path.parent / "out")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr + r.stdout
    assert f"{path}: initial:" in r.stderr and "does not assemble" in r.stderr


def test_cli_reports_bad_case_without_traceback(case_variant):
    path = case_variant("slider_crank", [(r"^mass = 1.0", "mass = -1.0")])
    r = subprocess.run([sys.executable, "-m", "natcoord.cli", "run", str(path), "--engines",
                        "natcoord", "--out", str(path.parent / "out")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr + r.stdout
    assert "bodies[0] (crank).mass" in r.stderr and "must be positive" in r.stderr


def test_a_3d_acceleration_channel_loads(case_variant):
    """It used to be refused at load (the code behind it was planar); 3-D point
    accelerations are computed now (tests/test_channels.py checks them on a closed form)."""
    path = case_variant("four_bar_3d", [(r'^yA = \{ kind = "position"',
                                         'yA = { kind = "acceleration"')])
    assert load_case(path).channel("yA").kind == "acceleration"


MISSPELT = [
    # (case, substitution, table path, misspelt key, the key meant): every table the loader
    # reads refuses a key it does not know, naming the table and the key
    ("slider_crank", (r"^mass = 1.0", "mass = 1.0\nmas = 2.0"), "bodies[0] (crank)", "mas",
     "mass"),
    ("a03_andrews", (r'^body = "K1"', 'body = "K1"\nfram = "body"'), "forces[0]", "fram",
     "frame"),
    ("a03_andrews", (r'relative_to = "beta"', 'relative_too = "beta"'), "channels.theta",
     "relative_too", "relative_to"),
    ("a03_andrews", (r"work = true", "wrok = true"), "channels.balance", "wrok", "work"),
    ("slider_crank", (r"^velocity = \{ theta = 0.0 \}", "velocty = { theta = 1.0 }"),
     "initial", "velocty", "velocity"),
    ("four_bar", (r'angle = "110 deg"', 'angel = "110 deg"'), "initial.pose.rocker", "angel",
     "angle"),
    ("slider_crank", (r"^points = \{ O = \[0.0, 0.0\] \}", "points = { O = [0.0, 0.0] }\n"
                      "pionts = {}"), "ground", "pionts", "points"),
    ("five_bar", (r'within = "1 deg"', 'witin = "1 deg"'), "comparison.singular", "witin",
     "within"),
]


@pytest.mark.parametrize("name, sub, table, key, meant", MISSPELT,
                         ids=[f"{m[2]}.{m[3]}" for m in MISSPELT])
def test_a_misspelt_key_is_refused_in_every_table(case_variant, name, sub, table, key, meant):
    """A misspelt key used to be ignored in these tables: the four-bar's rocker pose without
    its angle assembled the other branch, a channel without relative_to measured another
    angle. Now it is refused, as at the top level and in [engines.*], joints, drivers and
    rods."""
    path = case_variant(name, [sub])
    with pytest.raises(CaseError) as info:
        load_case(path)
    e = info.value
    assert e.file == str(path)
    assert e.field == f"{table}.{key}", str(e)
    assert "unknown field" in e.reason and f"did you mean {meant}?" in e.reason, str(e)


def _run_refused(path) -> subprocess.CompletedProcess:
    """`natcoord run` of a bad case file: exit 2, no traceback, nothing run."""
    r = subprocess.run([sys.executable, "-m", "natcoord.cli", "run", str(path), "--engines",
                        "natcoord", "--out", str(path.parent / "out")],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr + r.stdout
    assert not (path.parent / "out").exists()
    return r


def test_a_misspelt_pose_key_exits_2_before_anything_runs(case_variant):
    path = case_variant("four_bar", [(r'angle = "110 deg"', 'angel = "110 deg"')])
    r = _run_refused(path)
    assert f"{path}: initial.pose.rocker.angel: unknown field" in r.stderr


@pytest.mark.parametrize("name, sub, field, got", [
    ("five_bar", (r"of = \{ N34 = 1.0", "of = { N34 = nan"), "channels.N34_2N56.of.N34", "nan"),
    ("five_bar", (r"N56 = 2.0 \}", "N56 = -inf }"), "channels.N34_2N56.of.N56", "-inf"),
    ("a04_bricard", (r"J3_x = -1.0", "J3_x = " + "9" * 400), "channels.J1mJ3_x.of.J3_x",
     "9999"),
])
def test_a_combination_coefficient_must_be_finite(case_variant, name, sub, field, got):
    """A nan or inf coefficient used to load and run "ok" with a NaN column (and an integer
    past a float raised OverflowError)."""
    path = case_variant(name, [sub])
    with pytest.raises(CaseError) as info:
        load_case(path)
    assert info.value.field == field, str(info.value)
    assert info.value.reason.startswith(f"must be finite, got {got}"), str(info.value)


def test_a_nan_combination_coefficient_exits_2(case_variant):
    path = case_variant("five_bar", [(r"of = \{ N34 = 1.0", "of = { N34 = nan")])
    r = _run_refused(path)
    assert f"{path}: channels.N34_2N56.of.N34: must be finite, got nan" in r.stderr


@pytest.mark.parametrize("sub, field, reason", [
    ((r"^\[reactions.unit_invariant\]", "[reactions.unit_invariantt]"),
     "reactions.unit_invariantt", "unknown method; expected min_norm, unit_invariant, weighted "
     "(did you mean unit_invariant?)"),
    ((r"^\[reactions.weighted\]", "[reactions.zzweighted]"), "reactions.zzweighted",
     "unknown method"),
    ((r"^\[reactions.weighted\]", r'[reactions."x,y\\nz"]'), "reactions.'x,y\\nz'",
     "unknown method"),
    ((r"^\[reactions.weighted\]", '[reactions."weighted_a,b"]'), "reactions.weighted_a,b",
     "is not a name"),
    ((r"^\[reactions.min_norm\]", '[reactions.min_norm]\nstiffness = { A1 = "1 N/m" }'),
     "reactions.min_norm.stiffness", "only a weighted method"),
])
def test_an_unknown_reaction_method_is_refused(case_variant, sub, field, reason):
    """Any [reactions.<name>] used to run: a typo as a weighted minimum norm under its own
    name, and a name with a comma or newline broke the CSV header."""
    path = case_variant("parallelogram_3d", [sub])
    with pytest.raises(CaseError) as info:
        load_case(path)
    assert info.value.field == field, str(info.value)
    assert reason in info.value.reason, str(info.value)


def test_labelled_weighted_methods_still_load():
    assert list(load_case(CASES / "five_bar.toml").reactions) == [
        "min_norm", "unit_invariant", "weighted_KL1_KT1000", "weighted_KL1000_KT1"]


def test_a_misspelt_reaction_method_exits_2(case_variant):
    path = case_variant("parallelogram_3d", [(r"^\[reactions.unit_invariant\]",
                                              "[reactions.unit_invariantt]")])
    r = _run_refused(path)
    assert (f"{path}: reactions.unit_invariantt: unknown method; expected min_norm, "
            "unit_invariant, weighted (did you mean unit_invariant?)") in r.stderr


def test_a_long_name_is_counted_without_its_quotes(case_variant):
    """A 65-character body name was said to be of 67 characters (the repr's quotes)."""
    path = case_variant("slider_crank", [(r'name = "rod"', f'name = "{"b" * 65}"')])
    with pytest.raises(CaseError) as info:
        load_case(path)
    assert "(65 characters) is not a name" in info.value.reason, str(info.value)


@pytest.mark.parametrize("sub, field, reason", [
    ((r"^mass = 1.0", "mass = 1e308"), "bodies[0] (crank).mass",
     "1e+308 is beyond 1e+150 in size (its square would overflow)"),
    ((r"^gravity = .*", "gravity = [0.0, -1e200]"), "gravity[1]", "-1e+200 is beyond 1e+150"),
    ((r"^mass = 1.0", "mass = " + "9" * 400), "bodies[0] (crank).mass",
     "(400 characters) is beyond 1e+150"),
    ((r"^mass = 1.0", 'mass = "1e400 kg"'), "bodies[0] (crank).mass",
     "must be finite, got '1e400 kg'"),
    ((r"^angle = 1e-9", "angle = 1e-320"), "engines.natcoord.tolerance.angle",
     "1e-320 is below 1e-150 (its square would underflow to zero)"),
    ((r"^mass = 1.0", "mass = 1e-200"), "bodies[0] (crank).mass", "1e-200 is below 1e-150"),
])
def test_a_quantity_whose_square_overflows_is_refused(case_variant, sub, field, reason):
    """mass 1e308 and gravity 1e200 loaded and then failed at run time with numpy's
    RuntimeWarnings; an integer past a float raised OverflowError. A positive quantity as
    small as 1e-320 (a tolerance) made an error over it inf, which reached JSON as
    Infinity."""
    path = case_variant("slider_crank", [sub])
    with pytest.raises(CaseError) as info:
        load_case(path)
    assert info.value.field == field, str(info.value)
    assert reason in info.value.reason, str(info.value)


@pytest.mark.parametrize("com, what", [("[0.5, 0.0, 0.0]", "its inertia (a moment about the "
                                        "plane) leaves that plane"),
                                       ("[0.5, 0.0, 0.2]", "its centre of mass leaves")])
def test_a_body_whose_mass_leaves_its_points_plane_names_what_does(tmp_path, com, what):
    """It said "its mass (centre of mass or inertia) leaves that plane" of a centre of
    mass in the plane."""
    (tmp_path / "plate.toml").write_text(PLATE.replace("com = [0.5, 0.0, 0.0]", f"com = {com}"))
    with pytest.raises(CaseError) as info:
        load_case(tmp_path / "plate.toml")
    assert info.value.field == "bodies[0] (plate).points", str(info.value)
    assert what in info.value.reason, str(info.value)


def test_initial_rates_that_depend_on_each_other_are_named_so(tmp_path):
    """Three rates for a spherical joint's three freedoms, one of them (xP's, along the
    rod) fixed by the constraints already: "sets 3" read as enough; now it says that two
    count and one direction is left open."""
    from natcoord.errors import AssemblyError
    from natcoord.model import casemodel

    text = SPHERICAL_ROD.replace("zQ = 0.0 }", "xP = 0.0 }").replace(
        "[channels]\n", '[channels]\nxP = { kind = "position", body = "rod", point = "P", '
        'axis = "x" }\n')
    (tmp_path / "spherical_rod.toml").write_text(text)
    case = load_case(tmp_path / "spherical_rod.toml")
    with pytest.raises(AssemblyError) as info:
        casemodel.initial_state(casemodel.build(case))
    assert "degree(s) of freedom left by its drivers, but initial.velocity sets 3, of which " \
        "2 fix a velocity the constraints leave free" in str(info.value), str(info.value)
    assert "1 velocity direction(s) left open" in str(info.value)


def test_a_plugins_block_loads_where_the_plugin_is_not_installed(case_variant, tmp_path):
    """A case file with tolerances for a plug-in engine (as its author's repository keeps
    it) loads on a machine without that plug-in: the block is checked as far as it can be
    (tolerances, reason) and not used; `natcoord cases` says so. It was refused (exit 2),
    which took every command of that machine down with it."""
    import subprocess
    import sys

    from .conftest import ROOT

    block = ('[engines.myplug]\nreason = "measured on my machine"\nsettings = { dt = 1e-3 }'
             '\n[engines.myplug.tolerance]\nangle = 1e-6\n\n[engines.natcoord]')
    path = case_variant("slider_crank", [(r"^\[engines.natcoord\]", block)])
    case = load_case(path)
    assert case.absent_engines == ("myplug",) and "myplug" not in case.engines
    assert set(case.engines) >= {"natcoord", "mujoco"}
    bad = case_variant("slider_crank", [(r"^\[engines.natcoord\]", block.replace(
        "angle = 1e-6", "angle = -1.0")), (r'^name = "slider_crank"', 'name = "bad"')],
        stem="bad")
    with pytest.raises(CaseError) as info:  # what can be checked still is
        load_case(bad)
    assert info.value.field == "engines.myplug.tolerance.angle", str(info.value)
    bad.unlink()
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "cases", "--cases-dir",
                        str(tmp_path)], capture_output=True, text=True, timeout=300,
                       cwd=ROOT, env={**__import__("os").environ, "COLUMNS": "200"})
    assert p.returncode == 0, p.stderr
    assert "[engines.myplug]: no engine 'myplug' is installed here; its block is not used" \
        in " ".join(p.stderr.split()), p.stderr
