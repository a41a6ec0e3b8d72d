"""A faulty engine plug-in fails its own cells, with a reason, and nothing else: what its
run returns is checked before anything is kept of it, a fault in its declarations or
capability rules fails the cell (never passes for ``unsupported``), its rules run in its
engine process (under the time limit), and what it prints never reaches a command's JSON.

Plug-ins are written here as a module and its distribution's metadata (an entry point in a
``.dist-info`` folder), no install: in this process they are registered by patching the
registry's entry points (as tests/test_registry.py does); in a child process (an engine
process, a command) by putting their folder on PYTHONPATH."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import natcoord.engines.registry as reg
from natcoord.case.casefile import load_case
from natcoord.suite import worker
from natcoord.suite.runner import prepare

from .conftest import CASES, ROOT, project_copy

HEAD = '''
from natcoord.engines.capabilities import Capabilities
from natcoord.engines.schema import Setting

NAME = "{name}"
PACKAGE = "p-{name}"
CAPABILITIES = Capabilities(dimensions={{2}})
SETTINGS = ()


def version():
    return "0.1"


def run(case, init, settings):
    from natcoord.engines import natcoord_engine
    return natcoord_engine.run(case, init, {{"method": "rk4", "h": 1e-3}})
'''


def write_plugin(folder: Path, name: str, body: str = "", *, head: bool = True) -> Path:
    """Plug-in ``name`` in ``folder``: module ``p_<name>`` (a valid adapter, ``body`` appended
    to override part of it; without ``head`` the module is ``body`` alone) and its
    entry point. Returns ``folder``."""
    info = folder / f"p_{name}-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: p-{name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[natcoord.engines]\n{name} = p_{name}\n")
    (folder / f"p_{name}.py").write_text((HEAD.format(name=name) if head else "") + body)
    return folder


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """``plugin(name, body)``: write a plug-in and register it (alone) in this process."""
    folder = tmp_path / "site"
    names = []

    def make(name: str, body: str = "", head: bool = True):
        write_plugin(folder, name, body, head=head)
        names.append(name)
        monkeypatch.syspath_prepend(str(folder))
        monkeypatch.setattr(reg, "_entries", lambda: [(n, f"p_{n}") for n in names])
        sys.modules.pop(f"p_{name}", None)
        reg.discover.cache_clear()
        return reg.discover()

    yield make
    reg.discover.cache_clear()
    for n in names:
        sys.modules.pop(f"p_{n}", None)


@pytest.fixture(scope="module")
def pendulum():
    """The pendulum over 0.1 s, assembled: a Job template."""
    case = load_case(CASES / "pendulum.toml")
    return prepare(dataclasses.replace(case, duration=0.1))


def run_in_process(job, engine: str) -> dict:
    res, _ = worker.run_job(dataclasses.replace(job, engine=engine))
    return worker.record_of(res, job.case.duration)


# --------------------------------------------------------------- what a run returns
@pytest.mark.parametrize("change, why", [
    ("r.settings = [1]", "settings [1] (list), not a dict"),
    ("r.counters = 'many'", "counters 'many' (str), not a dict"),
    ("r.counters = {'f': print}", "counters that JSON cannot hold"),
    ("r.settings = {1: 2}", "settings with the key 1, not a string"),
    ("r.notes = 'a note'", "notes 'a note', not a list of strings"),
    ("r.n_steps = 2.5", "n_steps = 2.5, not a whole number"),
    ("r.wall_time_s = float('nan')", "wall_time_s = nan, not a finite number"),
    ("r.build_time_s = None", "build_time_s = None, not a finite number"),
    ("r.methods = {'x': 1}", "method 'x''s motion 1 (int), not a natcoord Motion"),
    ("r.motion = None", "a motion None (NoneType), not a natcoord Motion"),
    ("r = {'motion': r.motion}", "not a natcoord EngineRun"),
    ("r.motion = dataclasses.replace(r.motion, t=r.motion.t * 1.01)",
     "a motion with 11 samples at other times than the case's 11"),
    ("r.motion = dataclasses.replace(r.motion, t=r.motion.t[:5])",
     "a motion with 5 samples at other times than the case's 11"),
    ("r.motion = dataclasses.replace(r.motion, origin={})",
     "the engine's motion does not give the case's channels: KeyError"),
])
def test_what_a_run_returns_is_checked_and_fails_its_cell(plugin, pendulum, change, why):
    """A run whose record later code would trust but cannot read (settings a list: the
    report crashed on it) fails its cell with the reason; nothing of it is kept."""
    plugin("ev", f'''
import dataclasses
_run = run
def run(case, init, settings):
    r = _run(case, init, settings)
    {change}
    return r
''')
    res, extra = worker.run_job(dataclasses.replace(pendulum, engine="ev"))
    assert res.status == "failed" and why in res.reason, res.reason
    assert res.table is None and extra == {} and res.samples_s == []
    rec = worker.record_of(res, 0.1)
    assert isinstance(rec["settings"], dict) and isinstance(rec["counters"], dict)
    json.dumps(rec)


def test_a_valid_run_is_kept_as_it_was(plugin, pendulum):
    plugin("ok")
    rec = run_in_process(pendulum, "ok")
    assert rec["status"] == "ok" and rec["n_steps"] == 100, rec
    assert rec["settings"]["method"] == "rk4" and rec["counters"]["steps"] == 100


@pytest.mark.parametrize("body, why", [
    ("def version():\n    raise RuntimeError('broke')\n",
     "the engine's version() raised RuntimeError: broke"),
    ("def version():\n    return 1\n", "the engine's version() returned 1, not a string"),
])
def test_a_broken_version_fails_the_cell(plugin, pendulum, body, why):
    plugin("vr", body)
    rec = run_in_process(pendulum, "vr")
    assert rec["status"] == "failed" and rec["reason"] == why


# ------------------------------------------------------------ the capability rules
@pytest.mark.parametrize("rules, status, why", [
    ("raise RuntimeError('bug')", "failed",
     "the engine's capability rules raised RuntimeError: bug"),
    ("raise SystemExit(0)", "failed", "the engine's capability rules raised SystemExit: 0"),
    ("return 'no'", "failed", "the engine's capability rules returned 'no', not a list of "
     "reasons (strings)"),
    ("return None", "failed", "the engine's capability rules returned None, not a list"),
    ("return [1]", "failed", "the engine's capability rules returned [1], not a list"),
    ("return ['no pendulums here']", "unsupported", "no pendulums here"),
    ("print('chatter'); return []", "ok", ""),
])
def test_a_fault_in_the_rules_fails_the_cell(plugin, pendulum, capsys, rules, status, why):
    """A bug in a plug-in's rules was recorded as ``unsupported`` (the reason: the
    exception) and passed a gate that required the engine; now the cell fails."""
    plugin("rr", f'''
def rules(case, settings):
    {rules}
CAPABILITIES = Capabilities(dimensions={{2}}, rules=rules)
''')
    rec = run_in_process(pendulum, "rr")
    assert rec["status"] == status and rec["reason"].startswith(why), rec["reason"]
    assert "chatter" not in capsys.readouterr().out  # printed to stderr


def test_a_plugins_rules_never_run_in_the_commands_process(plugin, pendulum, tmp_path):
    """Only its engine process asks a plug-in's rules (an exit or a hang there is the
    run's, under its time limit); a built-in engine's are asked before any process."""
    marker = tmp_path / "asked"
    plugin("rm", f'''
def rules(case, settings):
    open({str(marker)!r}, "a").write("x")
    return ["never here"]
CAPABILITIES = Capabilities(dimensions={{2}}, rules=rules)
''')
    assert worker.cannot_run(pendulum.case, "rm") == ""
    assert not marker.exists()
    three_d = dataclasses.replace(pendulum.case, dimension=3)  # the declared fields still say
    assert worker.cannot_run(three_d, "rm") == "3-D cases are not modelled"
    assert worker.assess(pendulum.case, "rm") == ("unsupported", "never here")
    assert marker.exists()


def natcoord(args, home: Path, site: Path, timeout: float = 600):
    """A natcoord command in project ``home`` with the plug-ins of ``site`` installed."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join((str(site), str(ROOT))),
           "NATCOORD_HOME": str(home), "COLUMNS": "300"}  # this natcoord, not an installed one
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *args], cwd=home, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
@pytest.mark.parametrize("rules, why", [
    ("import os; os._exit(0)", "engine process exited with status 0 without writing its "
     "record"),
    ("import time; time.sleep(300)", "timed out after 5 s (killed)"),
])
def test_rules_that_exit_or_hang_end_their_own_run(tmp_path, rules, why):
    """os._exit in a plug-in's rules ended `run` in the command's process (exit 0, nothing
    published: a later gate judged the folder's old results) and a sleep there blocked it
    past --timeout: they run in the engine process now, whose end fails the cell."""
    import time

    home = project_copy(tmp_path, "pendulum")
    site = write_plugin(tmp_path / "site", "rx", f'''
def rules(case, settings):
    {rules}
CAPABILITIES = Capabilities(dimensions={{2}}, rules=rules)
''')
    out = tmp_path / "out"
    t0 = time.perf_counter()
    r = natcoord(["run", "pendulum", "--engines", "rx", "--out", str(out), "--timeout", "5"],
                 home, site)
    assert time.perf_counter() - t0 < 120
    assert r.returncode == 3, r.stdout + r.stderr
    [rec] = json.loads((out / "summary.json").read_text())["records"]
    assert rec["status"] == "failed" and rec["reason"] == why, rec
    r = natcoord(["gate", "--results", str(out), "--require", "rx"], home, site)
    assert r.returncode == 3, r.stdout + r.stderr


def test_what_an_engine_writes_in_its_current_folder_stays_out_of_the_users(tmp_path):
    """A plug-in whose run writes a log into the current folder (as MuJoCo's warnings
    did): the engine process runs in a scratch folder of its own, removed afterwards; the
    folder the command started from holds only what it held, and the run passes."""
    home = project_copy(tmp_path, "pendulum")
    site = write_plugin(tmp_path / "site", "rlog", '''
def run(case, init, settings):
    from pathlib import Path

    from natcoord.engines import natcoord_engine
    Path("rlog.log").write_text("a plug-in's log")
    Path("dump").mkdir()
    return natcoord_engine.run(case, init, {"method": "rk4", "h": 1e-3})
''')
    before = sorted(p.name for p in home.iterdir())
    r = natcoord(["run", "pendulum", "--engines", "rlog", "--out", str(tmp_path / "out")],
                 home, site)
    [rec] = json.loads((tmp_path / "out" / "summary.json").read_text())["records"]
    assert rec["status"] == "ok", (rec, r.stderr)
    assert sorted(p.name for p in home.iterdir()) == before, r.stderr


@pytest.mark.slow
def test_cases_lists_faulty_plugins_and_stays_json(tmp_path):
    """Plug-ins that exit on import, declare a dict for CAPABILITIES, print on import or in
    their rules, or whose rules raise or exit: `cases --json` stays JSON, lists the ones
    that do not load with their problem, gives a rule's fault as the reason (evaluated in
    an engine process: the exit ends that process, not the listing) and lists the rest."""
    home = project_copy(tmp_path, "pendulum")
    site = tmp_path / "site"
    write_plugin(site, "se", "raise SystemExit('no')\n", head=False)
    write_plugin(site, "cd", "CAPABILITIES = {'dimensions': [2]}\n")
    write_plugin(site, "pr", "print('hello'); raise ImportError('x')\n", head=False)
    write_plugin(site, "rp", '''
def rules(case, settings):
    print("hello from rules")
    return []
CAPABILITIES = Capabilities(dimensions={2}, rules=rules)
''')
    write_plugin(site, "rr", '''
def rules(case, settings):
    raise RuntimeError("bug in rules")
CAPABILITIES = Capabilities(dimensions={2}, rules=rules)
''')
    write_plugin(site, "rx", '''
def rules(case, settings):
    import os
    os._exit(0)
CAPABILITIES = Capabilities(dimensions={2}, rules=rules)
''')
    r = natcoord(["cases", "--json"], home, site)
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    assert list(data["engines"])[-3:] == ["rp", "rr", "rx"] and "natcoord" in data["engines"]
    problems = {p["name"]: p["error"] for p in data["engine_problems"]}
    assert problems == {
        "se": "import failed: SystemExit: no", "pr": "import failed: ImportError: x",
        "cd": "its CAPABILITIES is {'dimensions': [2]} (dict), not a "
              "natcoord.engines.capabilities.Capabilities"}
    [case] = data["cases"]
    assert case["engines"]["natcoord"] is None and case["engines"]["rp"] is None
    assert case["engines"]["rr"] == ("failed: the engine's capability rules raised "
                                     "RuntimeError: bug in rules")
    assert case["engines"]["rx"].startswith("failed: the engine process evaluating its "
                                            "capability rules exited with status 0")
    assert "hello" in r.stderr and "Traceback" not in r.stderr

    r = natcoord(["check-engine", "cd", "--json"], home, site)  # listed, not a crash
    assert r.returncode == 2 and r.stdout == "", r.stdout + r.stderr
    assert "unknown engine 'cd'" in r.stderr and "not a natcoord.engines.capabilities" in r.stderr
    assert "Traceback" not in r.stderr


# ------------------------------------------------------------------- check-engine
@pytest.mark.slow
def test_check_engine_fails_a_check_on_runs_at_other_times(tmp_path):
    """An engine sampling at other times than the case's ended the scorecard with exit 2
    ("bad input", naming a deleted temporary folder): now those checks fail, with why."""
    home = project_copy(tmp_path, "pendulum")
    site = write_plugin(tmp_path / "site", "tm", '''
import dataclasses
_run = run
def run(case, init, settings):
    r = _run(case, init, settings)
    r.motion = dataclasses.replace(r.motion, t=r.motion.t * 1.01)
    return r
''')
    r = natcoord(["check-engine", "tm", "--json"], home, site)
    assert r.returncode == 1, r.stdout + r.stderr
    card = json.loads(r.stdout)
    rows = {x["check"]: x for x in card["rows"]}
    assert card["version"] == "0.1"
    for check in ("reaction sign", "energy", "momentum", "reference pendulum"):
        assert rows[check]["result"] == "fail", rows[check]
        assert rows[check]["detail"].startswith("the engine's run returned a motion with "), \
            rows[check]
        assert "samples at other times than the case's" in rows[check]["detail"]


@pytest.mark.slow
@pytest.mark.parametrize("version, why", [
    ("raise RuntimeError('version broke')",
     "vr: the engine's version() raised RuntimeError: version broke"),
    ("print('chatter'); return 2", "vr: the engine's version() returned 2, not a string"),
    ("import os; os._exit(0)",  # in the command's process it ended it: exit 0, no output
     "vr: the engine's version() ended the process (exit status 0)"),
])
def test_check_engine_says_a_broken_version(tmp_path, version, why):
    """A version() that raised gave a traceback: now a one-line error, exit 3."""
    home = project_copy(tmp_path, "pendulum")
    site = write_plugin(tmp_path / "site", "vr", f'''
def version():
    {version}
''')
    r = natcoord(["check-engine", "vr", "--json"], home, site)
    assert r.returncode == 3 and r.stdout == "", r.stdout + r.stderr
    assert why in " ".join(r.stderr.split()) and "Traceback" not in r.stderr


def test_check_engine_fails_a_run_whose_results_cannot_be_read(tmp_path, monkeypatch):
    """A run's unreadable results are that check's failure, not bad input (exit 2)."""
    from natcoord.suite import conformance

    def run_subprocess(job, engine, out, timeout_s, settings=None):
        folder = out / "results" / job.case.name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"{engine}.csv").write_text("t,theta\n0,x\n")
        return {"status": "ok", "reason": ""}

    monkeypatch.setattr(conformance, "run_subprocess", run_subprocess)
    b = conformance.Battery("natcoord", tmp_path, tmp_path)
    try:
        rec, table = b.run(conformance.rod(b.tmp))
        b.not_run("reaction sign", rec, "reactions")
    finally:
        import shutil
        shutil.rmtree(b.tmp, ignore_errors=True)
    assert table is None and rec["status"] == "failed", rec
    assert rec["reason"].startswith("its results cannot be read: unreadable (ValueError")
    assert b.rows[0].result == "fail"


def test_a_builtin_engines_rule_fault_is_listed_as_failed(pendulum, monkeypatch):
    """natcoord's own rules are asked in the command's process; a fault there is listed by
    `cases` as "failed: ...", and left to the engine process to fail the run."""
    from natcoord.engines import natcoord_engine
    from natcoord.suite.runner import assessed

    def rules(case, settings):
        raise ValueError("oops")

    monkeypatch.setattr(natcoord_engine, "CAPABILITIES",
                        dataclasses.replace(natcoord_engine.CAPABILITIES, rules=rules))
    assert assessed([pendulum.case], ["natcoord"]) == {
        ("pendulum", "natcoord"): "failed: the engine's capability rules raised ValueError: "
                                  "oops"}
    assert worker.cannot_run(pendulum.case, "natcoord") == ""
    rec = run_in_process(pendulum, "natcoord")
    assert rec["status"] == "failed" and "rules raised ValueError: oops" in rec["reason"]


def test_check_engine_fails_an_engine_that_declines_every_check(tmp_path):
    """Every check skipped (rules decline every case): the card passed, exit 0, with
    nothing shown to conform."""
    home = project_copy(tmp_path, "pendulum")
    site = write_plugin(tmp_path / "site", "nope", '''
CAPABILITIES = Capabilities(dimensions={2, 3}, rules=lambda case, settings: ["never"])
''')
    r = natcoord(["check-engine", "nope"], home, site)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "no check passed or failed" in " ".join(r.stderr.split()), r.stderr
    assert "Traceback" not in r.stdout + r.stderr
