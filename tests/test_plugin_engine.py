"""An engine plug-in installed next to natcoord runs through the suite with no change to
natcoord: tests/data/plugin_engine (natcoord's fixed-step RK4 under the name ``rk4``, the
README's example) and tests/data/plugin_broken (a module that fails to import, and one that
takes the built-in name ``mujoco``) are built and installed into a temporary folder (pip
--target: the project's environment is not touched), then ``cases``, ``run``, ``gate`` and
``report`` run in processes with that folder on PYTHONPATH."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest
import setuptools

from .conftest import DATA, ROOT, project_copy

pytestmark = pytest.mark.slow

RK4_BLOCK = """
[engines.rk4]
settings = { dt = 1e-3 }
reason = '''natcoord's RK4 at dt 1e-3 s (the plug-in test): measured theta 1.2e-10 rad,
x 1.1e-10 m, O_x 3.2e-9 N, energy 3.1e-11 J over 10 s; bounds ~8x'''
[engines.rk4.tolerance]
angle = 1e-9
position = 1e-9
reaction = 3e-8
energy = 3e-10
"""


def _needs_wheel_builder():
    major, minor = (int(x) for x in setuptools.__version__.split(".")[:2])
    if (major, minor) < (70, 1) and importlib.util.find_spec("wheel") is None:
        pytest.skip(f"setuptools {setuptools.__version__} builds wheels only with the "
                    "'wheel' package: pip install wheel (in natcoord's test extra)")


@pytest.fixture(scope="module")
def plugins(tmp_path_factory):
    """The folder both plug-in packages are installed into."""
    _needs_wheel_builder()
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    p = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index",
                        "--no-build-isolation", "--target", str(target),
                        str(DATA / "plugin_engine"), str(DATA / "plugin_broken")],
                       capture_output=True, text=True, timeout=600,
                       env={**os.environ, "TMPDIR": str(build)})
    assert p.returncode == 0, p.stdout + p.stderr
    assert (target / "natcoord_rk4.py").is_file()
    return target


def _natcoord(args, cwd, site):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join((str(site), str(ROOT))),
           "NATCOORD_HOME": str(cwd),  # this checkout's natcoord, not an installed one
           "COLUMNS": "300"}  # the cases table unwrapped
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def test_a_plugin_runs_through_the_suite(tmp_path, plugins):
    home = project_copy(tmp_path, "pendulum", "slider_crank_driven")
    with open(home / "cases" / "pendulum.toml", "a", encoding="utf-8") as f:
        f.write(RK4_BLOCK)

    r = _natcoord(["cases", "--json"], home, plugins)
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    names = list(data["engines"])
    assert names[-1] == "rk4" and names[0] == "natcoord"  # built-ins first, then plug-ins
    assert data["engines"]["rk4"]["origin"] == "plug-in"
    assert data["engines"]["rk4"]["module"] == "natcoord_rk4"
    assert data["engines"]["rk4"]["capabilities"]["dimensions"] == [2]
    assert data["engines"]["mujoco"]["origin"] == "built-in"
    by_case = {c["name"]: c["engines"] for c in data["cases"]}
    assert by_case["pendulum"]["rk4"] is None
    assert "this example prescribes no motion" in by_case["slider_crank_driven"]["rk4"]
    problems = {(p["name"], p["entry_point"]): p["error"] for p in data["engine_problems"]}
    assert "ModuleNotFoundError" in problems["broken", "natcoord_broken"]
    assert "built-in engine's name" in problems["mujoco", "natcoord_broken"]
    assert "engine plug-in 'broken'" in r.stderr and "skipped" in r.stderr

    r = _natcoord(["cases"], home, plugins)  # the table says why, in words
    assert r.returncode == 0 and "rk4: drivers" not in r.stdout
    assert "this example prescribes no motion" in r.stdout

    out = tmp_path / "out"
    r = _natcoord(["run", "--engines", "natcoord,rk4", "--out", str(out)], home, plugins)
    assert r.returncode == 0, r.stdout + r.stderr
    records = {(x["case"], x["engine"]): x for x in
               json.loads((out / "summary.json").read_text())["records"]}
    rk4 = records["pendulum", "rk4"]
    assert rk4["status"] == "ok" and rk4["verdict"] == "pass", rk4
    assert rk4["engine_version"] == "0.1.0" and rk4["n_steps"] == 10000
    driven = records["slider_crank_driven", "rk4"]
    assert driven["status"] == "unsupported"
    assert "prescribed motions are not modelled" in driven["reason"]
    assert not (out / "results" / "slider_crank_driven" / "rk4.json").exists()  # no worker

    r = _natcoord(["gate", "--results", str(out)], home, plugins)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "3 of 4 case x engine runs judged" in " ".join(r.stdout.split())

    r = _natcoord(["report", "--results", str(out)], home, plugins)
    assert r.returncode == 0, r.stderr
    html = (out / "index.html").read_text(encoding="utf-8")
    assert '"rk4"' in html or ">rk4<" in html

    # judged, not waved through: a tolerance below the measured error fails the gate
    text = (home / "cases" / "pendulum.toml").read_text(encoding="utf-8")
    (home / "cases" / "pendulum.toml").write_text(
        text.replace("[engines.rk4.tolerance]\nangle = 1e-9", "[engines.rk4.tolerance]\n"
                     "angle = 1e-12"), encoding="utf-8")
    r = _natcoord(["gate", "--results", str(out)], home, plugins)
    assert r.returncode == 1 and "pendulum/rk4" in r.stderr, r.stdout + r.stderr


def test_without_the_plugin_the_engine_is_unknown(tmp_path):
    """Uninstalled, the plug-in's name is refused with the engines that are there."""
    home = project_copy(tmp_path, "pendulum")
    r = subprocess.run([sys.executable, "-m", "natcoord.cli", "run", "--engines", "rk4"],
                       cwd=home, env={**os.environ, "NATCOORD_HOME": str(home),
                                      "PYTHONPATH": str(ROOT)},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "unknown engine 'rk4'" in r.stderr
    assert "natcoord, mujoco, pinocchio, exudyn, dart, simbody" in r.stderr


def test_check_engine_scores_a_plugin(tmp_path, plugins):
    """The battery on the plug-in: conventions and energy pass, RK4's order is measured
    near 4, and a reference check over a tolerance below its error fails the command."""
    home = project_copy(tmp_path, "pendulum")
    with open(home / "cases" / "pendulum.toml", "a", encoding="utf-8") as f:
        f.write(RK4_BLOCK.replace("angle = 1e-9", "angle = 1e-13"))
    r = _natcoord(["check-engine", "rk4", "--json"], home, plugins)
    assert r.returncode == 1, r.stdout + r.stderr
    card = json.loads(r.stdout)
    rows = {x["check"]: x for x in card["rows"]}
    assert card["version"] == "0.1.0"
    for check in ("reaction sign", "reaction, joint reversed", "energy", "momentum"):
        assert rows[check]["result"] == "pass", rows[check]
    order = rows["convergence order"]
    assert order["result"] == "pass" and order["capability"] == "settings: dt"
    assert 3.5 < float(order["figure"].split()[0]) < 4.5, order  # RK4
    ref = rows["reference pendulum"]
    assert ref["result"] == "fail" and "theta" in ref["detail"], ref
