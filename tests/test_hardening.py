"""No bad input, interruption or mixed results can produce a wrong verdict: one test per
defect a tester found (input, interruption, stale and mixed results, gate, permissions,
working directory, time limits)."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from natcoord import CaseError, load_case
from natcoord.case.casefile import NAME_PATTERN
from natcoord.suite import gate
from natcoord.suite.io import read_json, write_json
from natcoord.suite.runner import run_suite

from .conftest import CASES, REFERENCES, ROOT, project_copy, worker_pids

PENDULUM = (CASES / "pendulum.toml").read_text()


def _cli(*args, cwd=None, env=None, timeout=300):
    e = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *map(str, args)], cwd=cwd,
                          env=e, capture_output=True, text=True, timeout=timeout)


def _no_traceback(p):
    assert "Traceback" not in p.stderr + p.stdout, (p.stdout[-800:], p.stderr[-800:])


def _case_file(folder: Path, text: str, name: str = "pendulum") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    f = folder / f"{name}.toml"
    f.write_text(text)
    return f


_project = project_copy


# ---- input --------------------------------------------------------------------------------
def test_a_name_that_is_not_a_safe_path_component_is_refused(tmp_path):
    f = _case_file(tmp_path, PENDULUM.replace('name = "pendulum"', 'name = ".."'), "..")
    with pytest.raises(CaseError, match="name: '..' is not a name"):
        load_case(f)


def test_long_names_with_control_characters_are_refused(tmp_path):
    """The body's name: 50 000 characters and a NUL."""
    text = PENDULUM.replace('name = "link"', 'name = "l\\u0000' + "i" * 50_000 + '"', 1)
    assert text != PENDULUM
    with pytest.raises(CaseError, match=r"bodies\[0\]\.name: (must be printable|.* is not a "
                       "name)") as e:
        load_case(_case_file(tmp_path, text))
    assert len(str(e.value)) < 500  # the name is not echoed whole


def test_channel_names_that_are_not_names_are_refused(tmp_path):
    text = PENDULUM.replace("\nx = {", '\n"x[/]" = {', 1)
    assert text != PENDULUM
    with pytest.raises(CaseError, match=r"channels: 'x\[/\]' is not a name"):
        load_case(_case_file(tmp_path, text))


def test_a_case_name_over_64_characters_is_refused_as_bad_input(tmp_path):
    """README: names are at most 64 characters. A longer case name used to reach the file
    system, which refused the file name (ENAMETOOLONG: exit 5, "a fault of the
    environment")."""
    long = "a" * 300
    assert NAME_PATTERN.fullmatch("a" * 64) and not NAME_PATTERN.fullmatch("a" * 65)
    with pytest.raises(CaseError, match="name is 65 characters long without .toml; a case "
                                        "name .* is at most 64"):
        load_case(tmp_path / f"{'a' * 65}.toml")
    for arg in (long, tmp_path / f"{long}.toml"):
        for command in (("run", arg, "--engines", "natcoord", "--out", tmp_path / "o"),
                        ("propose", arg)):
            p = _cli(*command)
            assert p.returncode == 2, (command[0], p.returncode, p.stderr)
            assert "is 300 characters long without .toml" in p.stderr, p.stderr
            assert "at most 64" in p.stderr and long not in p.stderr, p.stderr
            _no_traceback(p)
    assert not (tmp_path / "o").exists()
    d = _summary(tmp_path, [_record(case=long)])
    for command in ("gate", "report"):
        p = _cli(command, "--results", d)
        assert p.returncode == 2 and "is not a case name" in p.stderr, (command, p.stderr)
        _no_traceback(p)


def test_sample_counts_and_durations_beyond_the_budget_are_refused(tmp_path):
    with pytest.raises(CaseError, match="output_dt: .* beyond the budget"):
        load_case(_case_file(tmp_path, PENDULUM.replace("output_dt = 0.01", "output_dt = 1e-12")))
    with pytest.raises(CaseError, match="duration: .* beyond the budget"):
        load_case(_case_file(tmp_path, PENDULUM.replace("duration = 10.0", "duration = 1e9")))


@pytest.mark.parametrize("value", ["2.0", "2.5", "true", '"2"'])
def test_a_dimension_that_is_not_the_integer_2_or_3_is_refused(tmp_path, value):
    text = PENDULUM.replace("dimension = 2", f"dimension = {value}")
    with pytest.raises(CaseError, match="dimension: must be the integer 2 or 3"):
        load_case(_case_file(tmp_path, text))


def test_an_engine_list_that_names_no_engine_is_refused():
    p = _cli("run", "pendulum", "--engines", ",")
    assert p.returncode == 2 and "no engine named" in p.stderr
    _no_traceback(p)


def test_more_jobs_than_runs_start_one_thread_per_run(tmp_path, monkeypatch):
    """--jobs is runs at once: a value far past the number of runs starts no idle threads
    (one per job ran a suite out of memory), and an absurd one is refused."""
    from natcoord.suite import parallel, runner

    made = []

    class Counted(threading.Thread):
        def __init__(self, *a, **k):
            made.append(self)
            super().__init__(*a, **k)

    monkeypatch.setattr(parallel.threading, "Thread", Counted)
    monkeypatch.setattr(runner, "run_subprocess", lambda job, engine, *a, **k: {
        "case": job.case.name, "engine": engine, "status": "ok"})
    jobs = [SimpleNamespace(case=load_case(CASES / "pendulum.toml"))]
    got = dict(parallel.local(jobs, ["natcoord", "mujoco"], tmp_path, 1.0, workers=200))
    assert sorted(got) == [0, 1] and len(made) == 2
    p = _cli("run", "pendulum", "--engines", "natcoord", "--jobs", "100000", "--cases-dir",
             tmp_path)  # no case there: were --jobs taken, the run would stop at once
    assert p.returncode == 2 and "--jobs" in p.stderr and "1024" in p.stderr, p.stderr
    _no_traceback(p)


# ---- interruption -------------------------------------------------------------------------
def _slow_project(tmp_path) -> Path:
    """A project whose natcoord run takes long (pendulum for 999 s at rk4 h 1e-4: just
    within the step budget of 10^7 steps)."""
    home = _project(tmp_path)
    slow = PENDULUM.replace("duration = 10.0", "duration = 999.0").replace(
        "output_dt = 0.01", "output_dt = 1.0")
    slow = slow.replace("[engines.natcoord]\n", '[engines.natcoord]\nsettings = { method = '
                        '"rk4", h = 1e-4, formulation = "index1" }\n', 1)
    assert "rk4" in slow
    _case_file(home / "cases", slow)
    return home


_workers = worker_pids


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interruption_stops_every_worker_and_publishes_nothing(tmp_path, sig, code):
    home = _slow_project(tmp_path)
    out = home / "reports" / "nightly"
    proc = subprocess.Popen([sys.executable, "-m", "natcoord.cli", "run", "pendulum",
                             "--engines", "natcoord", "--out", str(out)], cwd=tmp_path,
                            env={**os.environ, "NATCOORD_HOME": str(home)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not _workers(home) and time.time() < deadline:
        time.sleep(0.05)
    assert _workers(home), "the worker never started"
    time.sleep(0.5)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1, stderr
    time.sleep(0.2)
    assert _workers(home) == []  # no worker left behind, reparented to init
    assert not out.exists()  # nothing half-written was published


def test_a_killed_command_takes_its_worker_with_it(tmp_path):
    """Even SIGKILL of the command (no clean-up possible) ends the worker (Linux)."""
    home = _slow_project(tmp_path)
    scratch = tmp_path / "tmp"  # what the command cannot remove, killed, is left here
    scratch.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "natcoord.cli", "run", "pendulum",
                             "--engines", "natcoord"], cwd=tmp_path,
                            env={**os.environ, "NATCOORD_HOME": str(home),
                                 "TMPDIR": str(scratch)},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not _workers(home) and time.time() < deadline:
        time.sleep(0.05)
    assert _workers(home)
    proc.kill()
    proc.wait()
    deadline = time.time() + 10
    while _workers(home) and time.time() < deadline:
        time.sleep(0.05)
    assert _workers(home) == []


# ---- stale and mixed results --------------------------------------------------------------
def test_a_refused_run_publishes_nothing_and_keeps_the_previous_results(tmp_path):
    """A refused run writes nothing: the previous results folder stays byte for byte (it
    is replaced only by a complete run), and its summary still names its own time."""
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "res"
    env = {"NATCOORD_HOME": str(home)}
    assert _cli("run", "pendulum", "--engines", "natcoord", "--out", out, env=env).returncode == 0
    assert _cli("gate", "--results", out, env=env).returncode == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    _case_file(home / "cases", PENDULUM.replace("dimension = 2", "dimension = 7"))
    p = _cli("run", "pendulum", "--engines", "natcoord", "--out", out, env=env)
    assert p.returncode == 2 and "dimension" in p.stderr
    _no_traceback(p)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".res")] == []


def test_two_case_files_of_one_name_are_refused_before_anything_runs(tmp_path):
    """Both would write results/<name>/: the second run's files were taken from under the
    first (exit 3 and a traceback). Now the command refuses them before running (exit 2,
    naming both files); the same file given twice runs once."""
    other = _case_file(tmp_path / "x", PENDULUM.replace("duration = 10.0", "duration = 1.0"))
    out = tmp_path / "o"
    for command in (("run", "--out", out), ("suite", "--out", out), ("bench",)):
        p = _cli(command[0], CASES / "pendulum.toml", other, "--engines", "natcoord",
                 *command[1:])
        assert p.returncode == 2, (command[0], p.returncode, p.stderr)
        assert f"two case files named pendulum: {CASES / 'pendulum.toml'}, {other}" in \
            " ".join(p.stderr.split()), p.stderr
        _no_traceback(p)
        assert not out.exists()
    home = _project(tmp_path, "pendulum")
    short = PENDULUM.replace("duration = 10.0", "duration = 0.5")
    _case_file(home / "cases", short)
    p = _cli("run", "pendulum", home / "cases" / "pendulum.toml", "--engines", "natcoord",
             "--out", out, env={"NATCOORD_HOME": str(home)})
    assert p.returncode == 0, p.stderr
    assert [r["case"] for r in read_json(out / "summary.json")["records"]] == ["pendulum"]


def test_no_stale_file_survives_a_new_run(tmp_path):
    cases = [load_case(CASES / "pendulum.toml")]
    out = tmp_path / "res"
    from natcoord.suite.outdir import publishing
    with publishing(out) as staging:
        run_suite(cases, ["natcoord", "exudyn"], staging, references=REFERENCES)
    assert (out / "results" / "pendulum" / "exudyn.csv").exists()
    with publishing(out) as staging:
        run_suite(cases, ["natcoord"], staging, references=REFERENCES)
    assert sorted(p.name for p in (out / "results" / "pendulum").iterdir()) == [
        "natcoord.csv", "natcoord.json"]


def test_a_second_run_into_a_busy_folder_is_refused(tmp_path):
    out = tmp_path / "res"
    lock = tmp_path / ".res.lock"
    with open(lock, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write("12345")
        f.flush()
        p = _cli("run", "pendulum", "--engines", "natcoord", "--out", out)
    assert p.returncode == 2 and "another natcoord run (pid 12345)" in p.stderr
    _no_traceback(p)
    assert not out.exists()


def test_subset_runs_and_benches_leave_the_nightly_folder_alone(tmp_path):
    home = _project(tmp_path, "pendulum")
    latest = home / "reports" / "latest"
    latest.mkdir(parents=True)
    (latest / "summary.json").write_text("{}")
    env = {"NATCOORD_HOME": str(home)}
    assert _cli("run", "pendulum", "--engines", "natcoord", env=env).returncode == 0
    assert _cli("bench", "pendulum", "--engines", "natcoord", "--repeats", "1",
                env=env).returncode == 0
    assert (latest / "summary.json").read_text() == "{}"  # untouched
    kinds = sorted(p.name.split("-")[-1] for p in (home / "reports" / "runs").iterdir()
                   if not p.name.startswith("."))
    assert kinds == ["bench", "run"]


# ---- gate ---------------------------------------------------------------------------------
def _summary(tmp_path, records, **extra) -> Path:
    d = tmp_path / "g"
    d.mkdir(exist_ok=True)
    write_json(d / "summary.json", {"records": records, "generated": "now", **extra})
    return d


def _record(case="pendulum", engine="natcoord", **channels):
    return {"case": case, "engine": engine, "status": "ok", "verdict": "pass",
            "channels": {k: {"kind": "position", "unit": "m", "max_abs": v, "tolerance": 1e-6,
                             "pass": v is not None and v <= 1e-6} for k, v in channels.items()}}


def test_an_unknown_engine_is_refused_naming_the_option_that_named_it(tmp_path):
    """`gate --require` and `check-engine NAME` said "--engines: unknown engine", an option
    neither command was given."""
    d = _summary(tmp_path, [_record(x=1e-9)], cases=["pendulum"], engines=["natcoord"])
    for args, given in ((["gate", "--results", d, "--require", "nosuch"], "--require"),
                        (["check-engine", "nosuch"], "check-engine NAME"),
                        (["run", "pendulum", "--engines", "nosuch"], "--engines")):
        p = _cli(*args)
        assert p.returncode == 2, p.stderr
        assert f"error: {given}: unknown engine 'nosuch'; engines are natcoord" in p.stderr, \
            p.stderr
        _no_traceback(p)
    p = _cli("gate", "--results", d, "--require", " ")  # passed, requiring nothing
    assert p.returncode == 2 and "--require: no engine named in ' '" in p.stderr, p.stderr
    p = _cli("history", "--flaky", "--since-green", "--history", tmp_path / "h.db")
    assert p.returncode == 2 and "--since-green and --flaky ask for different views: give " \
        "one" in p.stderr, p.stderr  # --flaky was dropped without a word
    p = _cli("check-engine", "natcoord,mujoco")  # was a KeyError with a traceback
    assert p.returncode == 2 and "check-engine NAME: one engine name expected, got " \
        "'natcoord,mujoco'" in p.stderr, p.stderr
    _no_traceback(p)


def test_a_required_engine_without_a_record_fails_the_gate(tmp_path):
    d = _summary(tmp_path, [_record(x=1e-9)], cases=["pendulum"], engines=["natcoord"])
    p = _cli("gate", "--results", d, "--require", "natcoord,mujoco")
    assert p.returncode == 3 and "pendulum/mujoco: no record" in p.stderr
    d = _summary(tmp_path, [_record(x=1e-9)], cases=["pendulum", "four_bar"],
                 engines=["natcoord"])
    p = _cli("gate", "--results", d)
    assert p.returncode == 3 and "four_bar/natcoord: no record" in p.stderr


def test_an_all_nan_or_missing_channel_fails_its_cell_not_the_run(tmp_path):
    """A force channel that an engine reports all-NaN, and a CSV that lacks a channel: each
    fails its own cell with the reason; the run completes with a summary."""
    from natcoord.suite import runner

    case = load_case(CASES / "pendulum.toml")
    out = tmp_path / "res"
    run_suite([case], ["natcoord"], out, references=REFERENCES)
    csv = out / "results" / "pendulum" / "natcoord.csv"
    table = pd.read_csv(csv)
    rec = read_json(out / "results" / "pendulum" / "natcoord.json")
    table["O_x"] = np.nan  # a reaction (force) channel, gated by the 'reaction' tolerance
    table.to_csv(csv, index=False)
    r = runner.compare_record(case, rec, out, REFERENCES)
    assert r["verdict"] == "fail" and r["channels"]["O_x"]["pass"] is False
    assert "all NaN" in r["channels"]["O_x"]["note"]
    table.drop(columns=["x"]).to_csv(csv, index=False)
    r = runner.compare_record(case, rec, out, REFERENCES)
    assert r["verdict"] == "fail" and "missing" in r["channels"]["x"]["note"]
    (csv).write_text("t,x\n0,not-a-number\n")  # unreadable: fails the cell
    r = runner.compare_record(case, rec, out, REFERENCES)
    assert r["status"] == "failed" or r["verdict"] == "fail"


def test_names_with_markup_are_printed_not_interpreted(tmp_path):
    d = _summary(tmp_path, [_record(case="[/]x"), _record(case="[bold]y")])
    p = _cli("gate", "--results", d)
    assert p.returncode == 2 and "'[/]x' is not a case name" in p.stderr, p.stderr
    assert "'[bold]y' is not a case name" in p.stderr
    _no_traceback(p)


def test_updating_the_baseline_after_a_subset_run_keeps_every_other_cell(tmp_path):
    base = tmp_path / "baseline.json"
    shutil.copy(REFERENCES / "baseline.json", base)
    before = gate.load_baseline(base)
    judged = gate.Verdict(gate.OK, channels={"pendulum/natcoord": {"x": {"max_abs": 1e-9}}},
                          outcome={"pendulum/natcoord": "pass"})
    gate.update_baseline(judged, base, "now")
    after = gate.load_baseline(base)
    assert set(after) == set(before) | {"pendulum/natcoord"}
    assert after["pendulum/natcoord"] == {"x": 1e-9}
    assert after["four_bar/mujoco"] == before["four_bar/mujoco"]


@pytest.mark.parametrize("text", [
    "not json", "[]", '{"records": 3}', '{"records": [1]}',
    '{"records": [{"case": "a", "engine": "b", "status": "ok", "verdict": "pass", '
    '"channels": []}]}',
    '{"records": [{"case": "a", "engine": "b", "status": "ok", "verdict": "pass", '
    '"channels": {"x": {"max_abs": "big", "tolerance": 1}}}]}',
    '{"records": [{"case": 1, "engine": "b", "status": "ok", "verdict": "pass", '
    '"channels": {}}]}'])
def test_malformed_summaries_exit_2_with_a_message(tmp_path, text):
    d = tmp_path / "g"
    d.mkdir()
    (d / "summary.json").write_text(text)
    p = _cli("gate", "--results", d)
    assert p.returncode == 2 and "error:" in p.stderr, (p.returncode, p.stderr)
    _no_traceback(p)


# ---- other --------------------------------------------------------------------------------
def test_results_are_written_with_ordinary_permissions(tmp_path):
    f = tmp_path / "x.json"
    write_json(f, {"a": 1})
    mode = stat.S_IMODE(f.stat().st_mode)
    mask = os.umask(0)
    os.umask(mask)
    assert mode == 0o666 & ~mask


def test_the_closing_line_counts_passes_and_failures_honestly(tmp_path):
    home = _project(tmp_path)
    _case_file(home / "cases", PENDULUM.replace("position = 1e-8", "position = 1e-30"))
    assert "position = 1e-30" in (home / "cases" / "pendulum.toml").read_text()
    p = _cli("run", "pendulum", "--engines", "natcoord", "--out", tmp_path / "r",
             env={"NATCOORD_HOME": str(home)})
    assert p.returncode == 0, p.stderr
    assert "1 run(s): 0 within tolerance, 1 over tolerance, 0 failed" in p.stdout


def test_the_command_line_works_from_any_directory(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "NATCOORD_HOME"}
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "cases"], cwd=elsewhere,
                       env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "pendulum" in p.stdout  # the installed checkout's cases
    home = _project(tmp_path, "four_bar")
    p = _cli("cases", cwd=elsewhere, env={"NATCOORD_HOME": str(home)})
    assert p.returncode == 0 and "four_bar" in p.stdout and "pendulum" not in p.stdout
    p = _cli("run", "nope", cwd=elsewhere, env={"NATCOORD_HOME": str(home)})
    assert p.returncode == 2 and f"looked in {home / 'cases'}" in p.stderr


def test_a_case_file_sets_its_own_time_limit(tmp_path):
    home = _project(tmp_path)
    _case_file(home / "cases", PENDULUM.replace('name = "pendulum"',
                                                'name = "pendulum"\ntimeout = "50 ms"'))
    p = _cli("run", "pendulum", "--engines", "natcoord", "--out", tmp_path / "r",
             env={"NATCOORD_HOME": str(home)})
    assert p.returncode == 3  # a failed cell: `run` says so in its exit status
    rec = read_json(tmp_path / "r" / "summary.json")["records"][0]
    assert rec["status"] == "failed" and "timed out after 0.05 s" in rec["reason"]


def test_suite_and_bench_take_a_time_limit():
    for cmd in ("suite", "bench"):
        p = _cli(cmd, "--help")
        assert "--timeout" in p.stdout


@pytest.mark.parametrize("args", [
    ["run", "pendulum", "--timeout", "inf"], ["run", "pendulum", "--timeout", "1e10"],
    ["run", "pendulum", "--timeout", "nan"], ["bench", "pendulum", "--timeout", "inf"],
    ["suite", "pendulum", "--timeout", "inf"], ["propose", "pendulum", "--timeout", "inf"],
    ["bisect", "HEAD", "HEAD", "--timeout", "inf"], ["propose", "pendulum", "--margin", "inf"],
    ["history", "--last", "99999999999999999999"], ["suite", "pendulum", "--bench-budget", "inf"],
    ["suite", "pendulum", "--repeats", "100000"], ["bench", "pendulum", "--repeats", "100000"],
    ["suite", "pendulum", "--jobs", "1000000000000"],
    ["generate", "n_four_bar", "--n", "2", "--duration", "inf"],
    ["generate", "n_four_bar", "--n", "2", "--duration", "nan"],
    ["import", "m.xml", "--duration", "1e300"],
    ["bench", "pendulum", "--scaling", "64,3000"]], ids=" ".join)
def test_infinite_or_huge_numbers_are_refused_naming_the_option(tmp_path, args):
    """Each numeric option has a finite range: an infinite or huge value overflowed a wait,
    an SQLite integer, a tolerance or the memory (exit 1 with a traceback)."""
    from typer.testing import CliRunner

    from natcoord.cli import app

    option = next(a for a in args if a.startswith("--") and a != "--n")
    # were the value taken, each command would stop at once: no case in --cases-dir, no
    # repository, an empty history
    where = {"run": ["--cases-dir", tmp_path, "--out", tmp_path / "o"],
             "bench": ["--cases-dir", tmp_path, "--out", tmp_path / "o"],
             "suite": ["--cases-dir", tmp_path, "--out", tmp_path / "o", "--history",
                       tmp_path / "h.db"],
             "propose": ["--cases-dir", tmp_path], "bisect": ["--repo", tmp_path],
             "history": ["--history", tmp_path / "h.db"],
             "generate": ["--out", tmp_path / "x.toml"],
             "import": ["--out", tmp_path / "x.toml"]}[args[0]]
    res = CliRunner().invoke(app, [*args, *map(str, where)])
    assert res.exit_code == 2, (res.exit_code, res.output, res.exception)
    said = res.output + res.stderr
    assert option in said, said
    value = args[args.index(option) + 1]
    if value in ("inf", "nan"):  # said as such, not as a value beyond the range's end
        assert f"'{value}' is not a finite number" in said, said
    elif option in ("--timeout", "--duration"):  # import's starts at its output step
        low = "0.01" if args[0] == "import" else "0.001"
        assert f"{value} is outside [{low}, " in said, said


def test_the_longest_time_limit_a_run_takes_does_not_overflow(tmp_path):
    p = _cli("run", "pendulum", "--engines", "natcoord", "--timeout", 7 * 24 * 3600,
             "--out", tmp_path / "r")
    assert p.returncode == 0, p.stderr[-1500:]
    _no_traceback(p)


def test_project_root_is_where_the_tests_run():
    assert (ROOT / "cases").is_dir()
    assert json.loads((ROOT / "references" / "baseline.json").read_text())["errors"]


def test_check_engine_with_a_cases_folder_that_is_not_there_is_refused(tmp_path):
    """check-engine --cases-dir /nonexistent passed its 5 built-in checks and exited 0: the
    agreement checks on the cases silently vanished."""
    p = _cli("check-engine", "natcoord", "--cases-dir", tmp_path / "nonexistent")
    assert p.returncode == 2 and "no such folder (--cases-dir)" in p.stderr, p.stderr
    (tmp_path / "empty").mkdir()
    p = _cli("check-engine", "natcoord", "--cases-dir", tmp_path / "empty")
    assert p.returncode == 2 and "no case files" in p.stderr, p.stderr


def test_bench_with_a_failed_cell_exits_3_naming_it_and_scaling_sizes_are_ordered(tmp_path):
    """bench exited 0 with every cell failed (the table said 'failed', the reason only in
    bench.json). --scaling 8,2 said 'grew 0.5x for 0.25x the couplers' and 4,2,4 ran N = 4
    twice: sizes are taken once each, smallest first; an empty --scaling is refused."""
    from natcoord.cli import _scaling_sizes

    p = _cli("bench", "pendulum", "--engines", "natcoord", "--repeats", "1", "--timeout",
             "0.01", "--out", tmp_path / "b")
    assert p.returncode == 3, (p.returncode, p.stderr[-1500:])
    assert "pendulum/natcoord: failed: timed out after 0.01 s" in p.stderr, p.stderr
    _no_traceback(p)
    assert _scaling_sizes("8,2,8") == [2, 8] and _scaling_sizes("4, 2,4") == [2, 4]
    p = _cli("bench", "pendulum", "--scaling", "", "--out", tmp_path / "c")
    assert p.returncode == 2 and "--scaling: expected positive integers" in p.stderr
