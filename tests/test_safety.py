"""Nothing a command is given is destroyed, stored state is read safely, and the faults a
tester found end in the right exit code with the file and the problem named: real
commands through the command line, on temporary folders (issue 30, items 2, 4 and 6)."""

from __future__ import annotations

import atexit
import errno
import functools
import json
import os
import resource
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
import types
from pathlib import Path

import pytest

from natcoord import CaseError, load_case
from natcoord.suite import history, outdir
from natcoord.suite.io import read_json, write_json

from .conftest import CASES, REFERENCES, ROOT, project_copy, worker_pids

PENDULUM = (CASES / "pendulum.toml").read_text()
NATCOORD = Path(sys.executable).parent / "natcoord"  # the console script, as a user runs it


def _cli(*args, cwd=None, env=None, timeout=300, preexec_fn=None):
    e = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *map(str, args)], cwd=cwd,
                          env=e, capture_output=True, text=True, timeout=timeout,
                          preexec_fn=preexec_fn)


def _clean(p, code):
    """Exit ``code``, one error line, no traceback."""
    assert p.returncode == code, (p.returncode, p.stdout[-1500:], p.stderr[-1500:])
    assert "Traceback" not in p.stdout + p.stderr, p.stderr[-1500:]


_project = project_copy


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


def _run(out, home, *extra, cwd=None):
    return _cli("run", "pendulum", "--engines", "natcoord", "--out", out, *extra, cwd=cwd,
                env={"NATCOORD_HOME": str(home)})


# ---- nothing a command is given is destroyed -------------------------------------------------
def test_a_users_folder_given_as_out_survives_two_runs(tmp_path):
    home = _project(tmp_path, "pendulum")
    mine = tmp_path / "mine"
    (mine / "sub").mkdir(parents=True)
    (mine / "notes.txt").write_text("my notes")
    (mine / "sub" / "data.csv").write_text("1,2\n")
    (mine / ".git").mkdir()
    before = _snapshot(mine)
    for _ in range(2):
        p = _run(mine, home)
        _clean(p, 2)
        assert "natcoord did not write" in p.stderr and str(mine) in p.stderr
        assert _snapshot(mine) == before
    assert sorted(q.name for q in tmp_path.iterdir()) == ["mine", "project"]  # nothing aside


def test_an_empty_folder_of_the_users_in_a_results_folder_is_kept(tmp_path):
    """A results folder natcoord wrote, with the user's empty folders added (at the top
    and in a case's folder): the next run into it is refused, naming them, and they stay
    (the replaced folder's clean-up removed every empty folder before)."""
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "out"
    _clean(_run(out, home), 0)
    (out / "my_notes").mkdir()
    (out / "results" / "pendulum" / "keep").mkdir()
    before = _snapshot(out)
    p = _run(out, home)
    _clean(p, 2)
    assert "natcoord did not write" in p.stderr and "my_notes" in p.stderr \
        and "results/pendulum/keep" in p.stderr, p.stderr
    assert _snapshot(out) == before
    (out / "my_notes").rmdir()
    (out / "results" / "pendulum" / "keep").rmdir()
    _clean(_run(out, home), 0)  # natcoord's own folders alone: replaced as before


def test_an_existing_file_given_as_out_is_refused_not_unlinked(tmp_path):
    home = _project(tmp_path, "pendulum")
    f = tmp_path / "results.txt"
    f.write_text("keep me")
    p = _run(f, home)
    _clean(p, 2)
    assert "not a folder" in p.stderr and f.read_text() == "keep me"
    link = tmp_path / "link"
    link.symlink_to(f)
    _clean(_run(link, home), 2)
    assert link.is_symlink() and f.read_text() == "keep me"


def test_a_results_folder_is_replaced_only_by_a_complete_run(tmp_path):
    """The previous results stay in place while the new run writes, and after a failed one;
    a complete run replaces them and leaves nothing beside."""
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "res"
    _clean(_run(out, home), 0)
    marker = read_json(out / outdir.MARKER)
    assert marker["command"] == "run" and "summary.json" in marker["files"]
    before = _snapshot(out)
    with pytest.raises(RuntimeError), outdir.publishing(out) as staging:
        assert _snapshot(out) == before  # kept while the new one is written
        (staging / "summary.json").write_text("{}")
        raise RuntimeError("the run fails")
    assert _snapshot(out) == before
    old_stamp = read_json(out / outdir.MARKER)["created"]
    time.sleep(1.1)
    _clean(_run(out, home), 0)
    assert read_json(out / outdir.MARKER)["created"] > old_stamp  # the new run's folder
    assert sorted(q.name for q in tmp_path.iterdir()) == ["project", "res"]


def test_a_results_folder_with_a_users_file_in_it_is_not_replaced(tmp_path):
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "res"
    _clean(_run(out, home), 0)
    (out / "my-analysis.ipynb").write_text("{}")
    before = _snapshot(out)
    p = _run(out, home)
    _clean(p, 2)
    assert "my-analysis.ipynb" in p.stderr and _snapshot(out) == before


def test_a_reported_results_folder_may_be_the_out_of_the_next_run(tmp_path):
    """`report` lists index.html in the folder's marker (it used to leave it unlisted, and
    the next run into the folder was refused for holding a file natcoord did not write);
    the next run replaces the folder, index.html with it, and leaves nothing beside."""
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "res"
    _clean(_run(out, home), 0)
    _clean(_cli("report", "--results", out, env={"NATCOORD_HOME": str(home)}), 0)
    files = read_json(out / outdir.MARKER)["files"]
    assert "index.html" in files and (out / "index.html").is_file()
    assert "index.html.tmp" not in files and not (out / "index.html.tmp").exists()
    _clean(_run(out, home), 0)
    assert not (out / "index.html").exists() and (out / "summary.json").is_file()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["project", "res"]
    # what a block adding files leaves, listed before it writes: a killed one's half file
    # is natcoord's; after it, only those that exist
    before = read_json(out / outdir.MARKER)["files"]
    with pytest.raises(RuntimeError), outdir.recording(out, ["page.html", "page.tmp"]):
        assert read_json(out / outdir.MARKER)["files"] == before + ["page.html", "page.tmp"]
        (out / "page.tmp").write_text("half")
        raise RuntimeError("the writer fails")
    assert read_json(out / outdir.MARKER)["files"] == before + ["page.tmp"]
    with outdir._locked(out), pytest.raises(outdir.FolderBusy, match="run this again"), \
            outdir.recording(out, ["page.html"]):
        pass  # another command writes the folder: refused, nothing listed
    assert read_json(out / outdir.MARKER)["files"] == before + ["page.tmp"]
    _clean(_run(out, home), 0)  # page.tmp is natcoord's: removed with the folder
    assert not (out / "page.tmp").exists()


def test_report_gives_no_marker_to_a_folder_natcoord_did_not_write(tmp_path):
    """A folder with a summary and results but no marker (not written by a natcoord
    command) gets index.html and no marker: with one, --out would take the folder for
    natcoord's and remove the user's files it listed."""
    home = _project(tmp_path, "pendulum")
    mine = tmp_path / "mine"
    shutil.copytree(_real_run(), mine)
    (mine / outdir.MARKER).unlink()
    before = _snapshot(mine)
    _clean(_cli("report", "--results", mine, env={"NATCOORD_HOME": str(home)}), 0)
    after = _snapshot(mine)
    assert set(after) == set(before) | {"index.html"} and outdir.MARKER not in after
    p = _run(mine, home)
    _clean(p, 2)
    assert "natcoord did not write" in p.stderr and _snapshot(mine) == after


def test_an_empty_folder_may_be_the_target(tmp_path):
    home = _project(tmp_path, "pendulum")
    out = tmp_path / "empty"
    out.mkdir()
    _clean(_run(out, home), 0)
    assert (out / "summary.json").is_file()


_workers = worker_pids


def test_a_killed_run_leaves_no_staging_folder_for_ever(tmp_path):
    """SIGKILL (no clean-up possible) leaves a staging folder; the next command in the same
    parent folder removes it (its pid is gone)."""
    home = _project(tmp_path, "pendulum")
    slow = PENDULUM.replace("duration = 10.0", "duration = 999.0").replace(
        "output_dt = 0.01", "output_dt = 1.0").replace(
        "[engines.natcoord]\n", '[engines.natcoord]\nsettings = { method = "rk4", h = 1e-4, '
        'formulation = "index1" }\n', 1)
    (home / "cases" / "slow.toml").write_text(slow.replace('name = "pendulum"',
                                                           'name = "slow"'))
    runs = tmp_path / "runs"
    scratch = tmp_path / "tmp"  # what the killed command cannot remove of its own is left here
    scratch.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "natcoord.cli", "run", "slow", "--engines",
                             "natcoord", "--out", str(runs / "a")],
                            env={**os.environ, "NATCOORD_HOME": str(home),
                                 "TMPDIR": str(scratch)},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not _workers(runs) and time.time() < deadline:
        time.sleep(0.05)
    assert _workers(runs), "the worker never started"
    proc.kill()
    proc.wait()
    left = [q.name for q in runs.iterdir()]
    assert any(".staging-" in n for n in left), left  # what a killed command leaves
    _clean(_run(runs / "b", home), 0)
    assert sorted(q.name for q in runs.iterdir()) == ["b"]


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _results_folder(folder: Path, pid: int, text: str) -> Path:
    """A results folder as natcoord writes it (summary.json and its marker) by ``pid``."""
    (folder / "results").mkdir(parents=True)
    (folder / "summary.json").write_text(text)
    (folder / "results" / "a.csv").write_text(text)
    (folder / outdir.MARKER).write_text(json.dumps({
        "natcoord": "0.1.0", "command": "run", "state": "complete", "pid": pid,
        "created": "2026-01-01T00:00:00+00:00", "files": ["results/a.csv", "summary.json"]}))
    return folder


@pytest.mark.parametrize("next_target", ["beside", "the same"])
def test_a_command_killed_between_the_two_renames_loses_no_results(tmp_path, next_target):
    """SIGKILL after the previous folder was set aside and before the new one took its
    place: the next command writing beside it (or to it) puts the previous folder back
    and removes the killed command's staging folder; nothing is deleted but that."""
    pid = _dead_pid()
    old = _snapshot(_results_folder(tmp_path / "keep", 1, "previous"))
    shutil.copytree(tmp_path / "keep", tmp_path / f".res.replaced-{pid}")
    _results_folder(tmp_path / f".res.staging-{pid}", pid, "new, never published")
    (tmp_path / ".res.lock").write_text(str(pid))
    target = tmp_path / ("other" if next_target == "beside" else "res")
    with outdir.publishing(target) as staging:
        assert _snapshot(tmp_path / "res") == old  # put back before anything is written
        (staging / "summary.json").write_text("next")
    names = sorted(q.name for q in tmp_path.iterdir())
    if next_target == "beside":
        assert names == ["keep", "other", "res"] and _snapshot(tmp_path / "res") == old
    else:  # replaced by the complete command, as any previous results folder is
        assert names == ["keep", "res"] and (tmp_path / "res" / "summary.json").read_text() \
            == "next" and not (tmp_path / "res" / "results").exists()


def test_a_command_killed_after_the_swap_leaves_only_its_new_results(tmp_path):
    """Killed while removing the previous files it had set aside: the next command removes
    what is left of them; a set-aside folder whose target holds other files is kept."""
    pid = _dead_pid()
    _results_folder(tmp_path / "res", pid, "new")
    _results_folder(tmp_path / f".res.replaced-{pid}", 1, "previous")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    _results_folder(tmp_path / f".mine.replaced-{pid}", 1, "previous")
    kept = _snapshot(tmp_path / f".mine.replaced-{pid}")
    assert outdir.clean_stale(tmp_path) == [tmp_path / f".res.replaced-{pid}"]
    assert sorted(q.name for q in tmp_path.iterdir()) == [f".mine.replaced-{pid}", "mine",
                                                          "res"]
    assert _snapshot(tmp_path / f".mine.replaced-{pid}") == kept
    assert (tmp_path / "res" / "summary.json").read_text() == "new"


def test_two_commands_stamped_in_the_same_second_get_two_folders(tmp_path, monkeypatch):
    """The default folder's name is reserved when it is chosen: a second command started in
    the same second gets the next name and is not refused as a writer of the first's."""
    import datetime as dt

    class Frozen(dt.datetime):
        @classmethod
        def now(cls, tz=None):
            return cls(2026, 1, 2, 3, 4, 5, tzinfo=tz)

    monkeypatch.setattr(outdir, "dt", types.SimpleNamespace(datetime=Frozen, UTC=dt.UTC))
    runs = tmp_path / "runs"
    first = outdir.stamped(runs, "run")
    second = outdir.stamped(runs, "run")
    assert (first.name, second.name) == ("20260102T030405Z-run", "20260102T030405Z-run-2")
    with outdir.publishing(first) as a, outdir.publishing(second) as b:
        (a / "summary.json").write_text("first")
        (b / "summary.json").write_text("second")
    assert (first / "summary.json").read_text() == "first"
    assert (second / "summary.json").read_text() == "second"
    assert sorted(q.name for q in runs.iterdir()) == [first.name, second.name]
    third = outdir.stamped(runs, "run")  # the published folders' names are taken
    assert third.name == "20260102T030405Z-run-3"
    # a command that ended before publishing leaves its reservation; once its pid is gone
    # the next command beside it removes it (a live one's, or a lock not natcoord's, stays)
    (runs / f".{third.name}.lock").write_text(str(_dead_pid()))
    (runs / ".20260102T030405Z-run-4.lock").write_text(str(os.getppid()))
    (runs / ".tool.lock").write_text(str(_dead_pid()))
    with outdir.publishing(runs / "x"):
        pass
    assert sorted(q.name for q in runs.iterdir()) == [
        ".20260102T030405Z-run-4.lock", ".tool.lock", first.name, second.name, "x"]


def test_point_latest_never_moves_a_users_folder(tmp_path):
    latest = tmp_path / "latest"
    latest.mkdir()
    (latest / "mine.txt").write_text("x")
    target = tmp_path / "runs" / "r1"
    target.mkdir(parents=True)
    assert outdir.point_latest(latest, target) is False
    assert (latest / "mine.txt").read_text() == "x" and not latest.is_symlink()
    assert sorted(q.name for q in (tmp_path / "runs").iterdir()) == ["r1"]
    link = tmp_path / "link"
    assert outdir.point_latest(link, target) and link.resolve() == target.resolve()


def test_suite_writes_no_bench_folder_beside_out(tmp_path):
    home = _project(tmp_path, "pendulum")
    where = tmp_path / "ci"
    where.mkdir()
    p = _cli("suite", "pendulum", "--engines", "natcoord", "--repeats", "1", "--out",
             where / "out", "--history", where / "history.db",
             env={"NATCOORD_HOME": str(home)}, timeout=600)
    _clean(p, 0)
    assert sorted(q.name for q in where.iterdir()) == ["history.db", "out"]
    assert (where / "out" / "bench.json").is_file()
    assert not (home / "reports" / "bench").exists()  # a subset is not the nightly


# ---- stored state is read safely -------------------------------------------------------------
@functools.cache
def _real_run() -> Path:
    """One real pendulum run in natcoord (its result files are the gate's evidence), in a
    temporary folder removed when the tests end."""
    base = tempfile.mkdtemp(prefix="natcoord-safety-")
    atexit.register(shutil.rmtree, base, True)
    out = Path(base) / "run"
    p = _cli("run", "pendulum", "--engines", "natcoord", "--out", out, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-1500:]
    return out


def _gate_folder(tmp_path: Path) -> Path:
    """A copy of a real passing results folder with a bench.json, so that the gate reads
    the history (speed against the past)."""
    d = tmp_path / "g"
    shutil.copytree(_real_run(), d)
    write_json(d / "bench.json", {"generated": "now", "machine": {"fingerprint": "m"},
                                  "records": [{"case": "pendulum", "engine": "natcoord",
                                               "case_hash": "h", "samples_s": [0.1] * 7}]})
    return d


def _read_history(command: str, results: Path, db: Path, timeout: float):
    """``gate`` or ``report`` of the results folder with ``db`` as the history."""
    args = ["--results", results, "--history", db]
    if command == "report":
        args += ["--references", REFERENCES]
    return _cli(command, *args, timeout=timeout)


def _natcoord_history(path: Path) -> Path:
    history.record(path, kind="suite", summary={"generated": "then", "records": []},
                   bench={"machine": {"fingerprint": "m"}, "records": [
                       {"case": "pendulum", "engine": "natcoord", "case_hash": "h",
                        "samples_s": [0.1] * 7}]}, gate=0)
    return path


def _damaged(kind: str, tmp_path: Path) -> Path:
    db = tmp_path / "history.db"
    if kind == "foreign schema":
        with sqlite3.connect(db) as con:
            con.execute("CREATE TABLE runs (x TEXT)")
            con.execute("INSERT INTO runs VALUES ('theirs')")
        con.close()
    elif kind == "random bytes":
        db.write_bytes(os.urandom(8192))
    elif kind == "truncated":
        _natcoord_history(db)
        with sqlite3.connect(db) as con:  # one file (no WAL) so that it can be cut
            con.execute("PRAGMA journal_mode=DELETE")
        con.close()
        raw = db.read_bytes()
        db.write_bytes(raw[:len(raw) // 2])
    elif kind == "a folder":
        db.mkdir()
    elif kind == "text":
        db.write_text("SQLite format 3 but not really\n")
    elif kind in ROW_DAMAGE:  # natcoord's history, one row damaged
        _natcoord_history(db)
        with sqlite3.connect(db) as con:  # one file (no WAL): unmodified means the same
            con.execute("PRAGMA journal_mode=DELETE")
            con.execute("UPDATE runs SET machine = 'm'")  # the gate folder's: it reads them
            con.execute(ROW_DAMAGE[kind])
        con.close()
    return db


ROW_DAMAGE = {"samples not json": "UPDATE bench SET samples = 'fast'",
              "samples null": "UPDATE bench SET samples = NULL",
              "samples of text": """UPDATE bench SET samples = '["0.1", "0.1"]'""",
              "a number as text": "UPDATE bench SET wall_time_s = 'abc'",
              "a deleted run": "DELETE FROM runs"}


@pytest.mark.parametrize("kind", ["foreign schema", "random bytes", "truncated", "a folder",
                                  "text", *ROW_DAMAGE])
@pytest.mark.parametrize("command", ["gate", "report"])
def test_a_damaged_or_foreign_history_exits_2_and_is_not_modified(tmp_path, kind, command):
    db = _damaged(kind, tmp_path)
    before = _snapshot(tmp_path)
    p = _read_history(command, _gate_folder(tmp_path), db, timeout=60)
    _clean(p, 2)
    assert str(db) in p.stderr and "bench.json" not in p.stderr, p.stderr
    if kind in ROW_DAMAGE:  # the row and column named
        assert "damaged row: table bench, row 1, column " in p.stderr, p.stderr
    after = _snapshot(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith("g")} == before  # no -wal


def test_suite_refuses_a_foreign_history_before_running(tmp_path):
    home = _project(tmp_path, "pendulum")
    db = _damaged("foreign schema", tmp_path)
    before = db.read_bytes()
    p = _cli("suite", "pendulum", "--engines", "natcoord", "--repeats", "0", "--out",
             tmp_path / "out", "--history", db, env={"NATCOORD_HOME": str(home)})
    _clean(p, 2)
    assert str(db) in p.stderr and "not a natcoord history" in p.stderr
    assert db.read_bytes() == before and not (tmp_path / "out").exists()
    assert not Path(f"{db}-wal").exists()


def test_the_gate_reads_a_locked_history_without_waiting_long_or_writing(tmp_path):
    """A history another process holds an exclusive lock on: the gate waits a few seconds
    (not a minute), says so, exits 2; it never takes a write lock itself."""
    db = _natcoord_history(tmp_path / "history.db")
    con = sqlite3.connect(db, isolation_level=None)
    con.execute("PRAGMA journal_mode=DELETE")
    con.execute("BEGIN EXCLUSIVE")
    try:
        t0 = time.monotonic()
        p = _cli("gate", "--results", _gate_folder(tmp_path), "--history", db, timeout=40)
        assert time.monotonic() - t0 < 30
        _clean(p, 2)
        assert "locked" in p.stderr and str(db) in p.stderr
    finally:
        con.execute("ROLLBACK")
        con.close()
    # unlocked, read-only: the gate reads it and changes nothing
    db.chmod(0o444)
    before = _snapshot(tmp_path)
    p = _cli("gate", "--results", tmp_path / "g", "--history", db, timeout=60)
    _clean(p, 0)
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", ["gate", "report"])
def test_reading_a_wal_history_creates_nothing_beside_it(tmp_path, command):
    """The history natcoord writes is in WAL mode; a plain read-only SQLite open of it
    leaves -wal and -shm files beside it. The commands that only read it leave the folder
    as it was (and a file recorded into while read is refused, not half-read)."""
    hist = tmp_path / "h"
    hist.mkdir()
    db = _natcoord_history(hist / "history.db")
    assert db.read_bytes()[18:20] == b"\x02\x02"  # WAL mode
    d = _gate_folder(tmp_path)
    before = _snapshot(hist)
    p = _read_history(command, d, db, timeout=120)
    _clean(p, 0)
    assert _snapshot(hist) == before
    with pytest.raises(history.HistoryError, match="recorded into it while it was read"):
        with history.reading(db) as con:
            con.execute("SELECT COUNT(*) FROM runs").fetchone()
            _natcoord_history(db)
    with history.reading(db) as con:
        assert con.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 2


@pytest.mark.parametrize("text, problem", [
    ("not json", "not valid JSON"), ('{"records": 3}', "records"),
    ('{"records": [{"case": "pendulum", "engine": "natcoord", "samples_s": "fast"}]}',
     "samples_s"),
    ('{"records": [{"case": "pendulum", "engine": "natcoord", "samples_s": [0.1, 0.1, 0.1],'
     ' "cpu_samples_s": 5}]}', "records[0].cpu_samples_s: not a list of timing samples"),
    ('{"records": [{"case": "pendulum", "engine": "natcoord", "samples_s": [0.0, 0.0, 0.0]}]}',
     "records[0].samples_s: not a list of timing samples (s, each at least 1e-12)"),
    ('{"records": [{"case": "pendulum", "engine": "natcoord", "samples_s": [1e-320, 1e-3]}]}',
     "records[0].samples_s: not a list of timing samples")])
def test_a_malformed_bench_json_exits_2_naming_it(tmp_path, text, problem):
    d = _gate_folder(tmp_path)
    (d / "bench.json").write_text(text)
    for args in (["report", "--results", d, "--references", REFERENCES,
                  "--history", tmp_path / "none.db"], ["compare", d, d],
                 ["gate", "--results", d, "--history", tmp_path / "none.db"]):
        p = _cli(*args)
        _clean(p, 2)
        assert str(d / "bench.json") in p.stderr and problem in p.stderr, (args, p.stderr)


@pytest.mark.parametrize("make", ["not json", "a folder", "a list"])
def test_a_malformed_summary_exits_2_in_report_and_compare(tmp_path, make):
    d = _gate_folder(tmp_path)
    (d / "summary.json").unlink()
    if make == "a folder":
        (d / "summary.json").mkdir()
    else:
        (d / "summary.json").write_text("not json" if make == "not json" else "[1, 2]")
    for args in (["report", "--results", d, "--references", REFERENCES], ["compare", d, d]):
        p = _cli(*args)
        _clean(p, 2)
        assert str(d / "summary.json") in p.stderr, (args, p.stderr)


@pytest.mark.parametrize("text", ['{"errors": 3}', '{"errors": {"a/b": {"x": "big"}}}',
                                  "{not json", '["errors"]'])
def test_a_malformed_baseline_is_named_as_the_baseline(tmp_path, text):
    base = tmp_path / "baseline.json"
    base.write_text(text)
    p = _cli("gate", "--results", _gate_folder(tmp_path), "--baseline", base,
             "--history", tmp_path / "none.db")
    _clean(p, 2)
    assert str(base) in p.stderr and "summary.json" not in p.stderr, p.stderr


@pytest.mark.parametrize("damage", ["garbage", "a folder", "bad json"])
def test_a_damaged_reference_exits_2_naming_it_before_running(tmp_path, damage):
    home = _project(tmp_path, "pendulum")
    csv, meta = home / "references" / "pendulum.csv", home / "references" / "pendulum.json"
    if damage == "garbage":
        csv.write_bytes(b'"\x00\xff unterminated\n' * 3)
        bad = csv
    elif damage == "a folder":
        csv.unlink()
        csv.mkdir()
        bad = csv
    else:
        meta.write_text("{oops")
        bad = meta
    p = _run(tmp_path / "out", home)
    _clean(p, 2)
    assert str(bad) in p.stderr and not (tmp_path / "out").exists(), p.stderr
    p = _cli("report", "--results", _gate_folder(tmp_path), "--references",
             home / "references", "--history", tmp_path / "none.db")
    _clean(p, 2)
    assert str(bad) in p.stderr, p.stderr


# ---- the environment -------------------------------------------------------------------------
def _cli_with_fault(code: int, *args, env=None):
    """The command line with every atomic write failing with OSError(code) (a full disk,
    a read-only folder) at the file it writes."""
    prog = textwrap.dedent(f"""
        import os, sys
        import natcoord.suite.io as io
        def write_atomic(path, text, **kw):
            raise OSError({code}, os.strerror({code}), str(path))
        io.write_atomic = write_atomic
        sys.argv = ["natcoord", *sys.argv[1:]]
        from natcoord.cli import main
        main()
    """)
    return subprocess.run([sys.executable, "-c", prog, *map(str, args)], capture_output=True,
                          text=True, timeout=300, env={**os.environ, **(env or {})})


def test_a_passing_gate_that_updates_the_baseline_exits_0(tmp_path):
    base = tmp_path / "baseline.json"
    shutil.copy(REFERENCES / "baseline.json", base)
    p = _cli("gate", "--results", _gate_folder(tmp_path), "--baseline", base,
             "--history", tmp_path / "none.db", "--update-baseline")
    _clean(p, 0)
    stored = read_json(base)["errors"]["pendulum/natcoord"]  # the errors this gate judged
    case = load_case(CASES / "pendulum.toml")
    assert set(stored) == {c.name for c in case.channels}
    own = case.engine("natcoord")
    assert all(0 <= stored[c.name] <= own.tolerance_for(c) for c in case.channels)


def test_updating_a_baseline_given_as_a_link_writes_its_target(tmp_path):
    """A baseline kept elsewhere and linked: the update writes the file the link leads to,
    atomically, and the link stays a link."""
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(REFERENCES / "baseline.json", mine / "baseline.json")
    link = tmp_path / "baseline.json"
    link.symlink_to(Path("mine") / "baseline.json")
    p = _cli("gate", "--results", _gate_folder(tmp_path), "--baseline", link,
             "--history", tmp_path / "none.db", "--update-baseline")
    _clean(p, 0)
    assert link.is_symlink() and os.readlink(link) == str(Path("mine") / "baseline.json")
    assert "pendulum/natcoord" in read_json(mine / "baseline.json")["errors"]
    assert sorted(q.name for q in mine.iterdir()) == ["baseline.json"]  # no temporary left
    loop = tmp_path / "loop"
    loop.symlink_to("loop")
    with pytest.raises(OSError):
        write_json(loop, {})
    assert loop.is_symlink() and os.readlink(loop) == "loop"


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS])
def test_a_full_disk_or_read_only_folder_exits_5_never_1(tmp_path, code):
    base = tmp_path / "baseline.json"
    shutil.copy(REFERENCES / "baseline.json", base)
    before = base.read_bytes()
    p = _cli_with_fault(code, "gate", "--results", _gate_folder(tmp_path), "--baseline",
                        base, "--history", tmp_path / "none.db", "--update-baseline")
    _clean(p, 5)
    assert os.strerror(code) in p.stderr and str(base) in p.stderr
    assert base.read_bytes() == before


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS, errno.ENOSPC])
def test_generate_and_import_into_a_folder_that_cannot_be_written_exit_5(tmp_path, code):
    """generate and import wrote the case file's OSError as bad input (exit 2): a
    read-only folder or a full disk is the machine's (exit 5), the file named."""
    for args in (["generate", "n_four_bar", "--n", "2"],
                 ["import", CASES / "mjcf_four_bar.xml"]):
        out = tmp_path / "rel.toml"
        p = _cli_with_fault(code, *args, "--out", out)
        _clean(p, 5)
        assert f"{out}: cannot be written ({os.strerror(code)}" in " ".join(
            p.stderr.split()), (args, p.stderr)
        assert not out.exists()


def test_a_path_that_cannot_name_a_folder_is_bad_input_not_the_machine(tmp_path):
    """A file where --out needs a folder, a name longer than the file system allows: exit
    2 naming the path (they were called a fault of the environment, exit 5)."""
    home = _project(tmp_path, "pendulum")
    afile = tmp_path / "afile"
    afile.write_text("mine")
    long = tmp_path / ("x" * 300)
    for args, said in (
            (["run", "pendulum", "--engines", "natcoord", "--out", afile / "sub"],
             f"{afile}: File exists (a file where a folder is needed)"),
            (["bench", "pendulum", "--engines", "natcoord", "--out", afile / "sub" / "b"],
             f"{afile / 'sub'}: Not a directory (a part of the path is a file, not a folder)"),
            (["run", "pendulum", "--engines", "natcoord", "--out", long / "r"],
             f"{long}/r: File name too long (a name in the path is over the file system's "
             "limit"),
            (["report", "--results", long], f"{long}/summary.json: File name too long"),
            (["gate", "--results", long], f"{long}/summary.json: File name too long"),
            (["generate", "n_four_bar", "--n", "2", "--out", afile / "x.toml"],
             f"{afile / 'x.toml'}: cannot be written: {afile} is a file, not a folder")):
        p = _cli(*args, env={"NATCOORD_HOME": str(home)})
        _clean(p, 2)
        assert said in p.stderr and "fault of the environment" not in p.stderr, p.stderr
    assert afile.read_text() == "mine"


def test_bench_checks_its_history_folder_before_measuring(tmp_path, monkeypatch):
    """bench --history names the folder of its dated copies: one that cannot be a folder
    (a file in the path) was found only after the whole bench (its measurements lost);
    now it is refused first (exit 2, nothing measured), an unwritable one is exit 5."""
    from natcoord.errors import EnvironmentFault
    from natcoord.suite.io import check_folder

    home = _project(tmp_path, "pendulum")
    afile = tmp_path / "afile"
    afile.write_text("mine")
    p = _cli("bench", "pendulum", "--engines", "natcoord", "--repeats", "1", "--out",
             tmp_path / "b", "--history", afile / "sub", env={"NATCOORD_HOME": str(home)})
    _clean(p, 2)
    assert f"--history {afile / 'sub'}: cannot be a folder: {afile} is a file" in p.stderr
    assert "cold start" not in p.stdout and not (tmp_path / "b").exists(), p.stdout
    assert afile.read_text() == "mine"
    check_folder(tmp_path / "new" / "sub", "--history")  # creatable: fine, nothing made
    assert not (tmp_path / "new").exists()
    monkeypatch.setattr(os, "access", lambda *a, **k: False)  # a read-only folder (root
    with pytest.raises(EnvironmentFault, match="cannot be written"):  # writes any)
        check_folder(tmp_path / "new" / "sub", "--history")


def test_paths_that_are_not_utf8_are_read_written_or_refused_without_a_traceback(
        tmp_path, monkeypatch, capfd):
    """A name in Latin-1 (b'\\xe9', which Python carries as a surrogate escape): the
    history is read (its SQLite address was built from text, a traceback), a run writes
    its results under it (the worker's process title failed), a case name that cannot be
    is refused naming the file (exit 2), and any other such error at the command line's
    top level is exit 2 with the name, not a traceback."""
    from natcoord import cli

    home = _project(tmp_path, "pendulum")
    lat = Path(os.fsdecode(bytes(tmp_path) + b"/lat\xe9"))
    lat.mkdir()
    db = _natcoord_history(lat / "history.db")
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "history", "--json",
                        "--history", os.fsencode(db)], capture_output=True, timeout=120)
    assert p.returncode == 0, p.stderr[-1500:]
    assert len(json.loads(p.stdout)) == 1
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "run", "pendulum", "--engines",
                        "natcoord", "--out", os.fsencode(lat / "r")], capture_output=True,
                       timeout=300, env={**os.environ, "NATCOORD_HOME": str(home)})
    assert p.returncode == 0, p.stderr[-1500:]
    assert read_json(lat / "r" / "summary.json")["records"][0]["status"] == "ok"
    out = lat / "g\udce9.toml"
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "generate", "n_four_bar",
                        "--n", "2", "--out", os.fsencode(out)], capture_output=True,
                       timeout=120)
    assert p.returncode == 2 and b"Traceback" not in p.stderr, p.stderr[-1500:]
    assert b"its stem is the case name" in p.stderr and not out.exists()

    def app():
        str(lat).encode("utf-8")

    monkeypatch.setattr(cli, "app", app)
    monkeypatch.setattr(cli.signal, "signal", lambda *a: None)  # pytest's handlers kept
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 2
    assert "lat\\xe9: not valid UTF-8" in capfd.readouterr().err


def test_an_unwritable_step_summary_keeps_the_nightly_results(tmp_path):
    home = _project(tmp_path, "pendulum")
    step = tmp_path / "step-summary"
    step.mkdir()
    out = tmp_path / "out"
    p = _cli("suite", "pendulum", "--engines", "natcoord", "--repeats", "0", "--out", out,
             "--history", tmp_path / "history.db",
             env={"NATCOORD_HOME": str(home), "GITHUB_STEP_SUMMARY": str(step)})
    _clean(p, 5)
    assert "GITHUB_STEP_SUMMARY" in p.stderr and str(step) in p.stderr
    assert read_json(out / "summary.json")["records"][0]["status"] == "ok"
    assert (out / "summary.md").is_file() and (out / "index.html").is_file()
    with history.reading(tmp_path / "history.db") as db:  # recorded too
        assert db.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 1


# ---- other defects ---------------------------------------------------------------------------
def test_the_worker_runs_the_installed_package_whatever_the_current_folder(tmp_path):
    home = _project(tmp_path, "pendulum")
    here = tmp_path / "here"
    (here / "natcoord" / "suite").mkdir(parents=True)
    (here / "natcoord" / "__init__.py").write_text("raise ImportError('the wrong natcoord')\n")
    (here / "natcoord" / "suite" / "__init__.py").write_text("")
    p = subprocess.run([str(NATCOORD), "run", "pendulum", "--engines", "natcoord", "--out",
                        tmp_path / "out"], cwd=here, capture_output=True, text=True,
                       timeout=300, env={**os.environ, "NATCOORD_HOME": str(home)})
    _clean(p, 0)
    rec = read_json(tmp_path / "out" / "summary.json")["records"][0]
    assert rec["status"] == "ok" and rec["verdict"] == "pass", rec


def test_run_exits_3_when_a_cell_failed(tmp_path):
    home = _project(tmp_path)
    text = PENDULUM.replace('name = "pendulum"', 'name = "pendulum"\ntimeout = "10 ms"')
    (home / "cases" / "pendulum.toml").write_text(text)
    p = _run(tmp_path / "out", home)
    _clean(p, 3)
    rec = read_json(tmp_path / "out" / "summary.json")["records"][0]
    assert rec["status"] == "failed" and "0 within tolerance, 0 over tolerance, 1 failed" \
        in p.stdout


def test_the_stricter_time_limit_wins(tmp_path):
    """--timeout 0.05 beside a case file's own 600 s: the run is held to 0.05 s."""
    home = _project(tmp_path)
    (home / "cases" / "pendulum.toml").write_text(
        PENDULUM.replace('name = "pendulum"', 'name = "pendulum"\ntimeout = "600 s"'))
    p = _run(tmp_path / "out", home, "--timeout", "0.05")
    _clean(p, 3)
    rec = read_json(tmp_path / "out" / "summary.json")["records"][0]
    assert rec["status"] == "failed" and "timed out after 0.05 s" in rec["reason"]


def _limit_memory():  # pragma: no cover - in the child
    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))


def test_a_case_file_that_is_not_a_regular_file_is_refused(tmp_path):
    """A link to /dev/zero is not read without bound, a FIFO does not hang."""
    cases = tmp_path / "cases"
    cases.mkdir()
    (cases / "pendulum.toml").symlink_to("/dev/zero")
    p = _cli("run", cases / "pendulum.toml", "--out", tmp_path / "o", timeout=60,
             preexec_fn=_limit_memory)
    _clean(p, 2)
    assert str(cases / "pendulum.toml") in p.stderr
    with pytest.raises(CaseError, match="not a regular file"):
        load_case(cases / "pendulum.toml")
    (cases / "pendulum.toml").unlink()
    os.mkfifo(cases / "pendulum.toml")
    p = _cli("run", cases / "pendulum.toml", "--out", tmp_path / "o", timeout=60)
    _clean(p, 2)
    assert "not a regular file" in p.stderr and str(cases / "pendulum.toml") in p.stderr


@pytest.mark.parametrize("what", ["missing", "no cases"])
def test_an_invalid_natcoord_home_is_refused(tmp_path, what):
    home = tmp_path / "home"
    if what == "no cases":
        home.mkdir()
    p = _cli("cases", cwd=tmp_path, env={"NATCOORD_HOME": str(home)})
    _clean(p, 2)
    assert f"$NATCOORD_HOME={home}" in p.stderr


def test_generate_keeps_an_existing_case_file_unless_forced(tmp_path):
    f = tmp_path / "a02_four_bar_n3.toml"
    f.write_text("# mine\n")
    p = _cli("generate", "n_four_bar", "--n", "3", "--out", f)
    _clean(p, 2)
    assert "--force" in p.stderr and f.read_text() == "# mine\n"
    _clean(_cli("generate", "n_four_bar", "--n", "3", "--out", f, "--force"), 0)
    assert load_case(f).name == "a02_four_bar_n3"
    new = tmp_path / "a02_four_bar_n4.toml"
    _clean(_cli("generate", "n_four_bar", "--n", "4", "--out", new), 0)
    assert json.dumps(load_case(new).name) == '"a02_four_bar_n4"'


def test_gate_and_report_read_the_last_run_by_default(tmp_path):
    """After `run` (default folder), `gate` and `report` without --results read that run
    (they used to ask for a run that had just been made); a later run refused for bad
    input leaves reports/latest at the complete one."""
    home = project_copy(tmp_path, "pendulum")
    env = {"NATCOORD_HOME": str(home)}
    _clean(_cli("run", "pendulum", "--engines", "natcoord", env=env), 0)
    first = (home / "reports" / "latest").resolve()
    assert (first / "summary.json").is_file()
    p = _cli("gate", env=env)
    _clean(p, 0)
    assert f"-> {first}" in p.stderr and "name another with --results" in p.stderr
    _clean(_cli("report", env=env), 0)
    assert (first / "index.html").is_file()
    _clean(_cli("run", "no_such_case", "--engines", "natcoord", env=env), 2)
    assert (home / "reports" / "latest").resolve() == first


def test_json_for_machines_is_strict():
    """Every --json output and stored JSON goes through one writer: a non-finite number
    is null, never the NaN / Infinity tokens a strict JSON reader refuses (compare --json
    printed "speed_ratio": NaN and "worst_of_tolerance_new": Infinity)."""
    import json

    import numpy as np

    from natcoord.suite.io import json_text

    text = json_text({"a": float("inf"), "b": [np.float64("nan"), np.float32(1.5)], "c": 2})
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c)) == {
        "a": None, "b": [None, 1.5], "c": 2}


def test_report_keeps_a_page_it_did_not_write(tmp_path):
    """`report --results` of a folder holding the user's own index.html (no marker):
    exit 2 naming it, the page kept, where it was replaced silently. natcoord's own page
    there (a marker listing it, or its generator tag in a folder without a marker) is
    rewritten; a link in its place is kept."""
    d = tmp_path / "r"
    shutil.copytree(_real_run(), d)
    args = ("report", "--results", d, "--references", REFERENCES,
            "--history", tmp_path / "none.db")
    _clean(_cli(*args), 0)  # the marker lists the page natcoord wrote: rewritten
    (d / ".natcoord-results").unlink()
    _clean(_cli(*args), 0)  # no marker: its own page, by its generator tag
    mine = "<html><body>my page</body></html>"
    (d / "index.html").write_text(mine)
    p = _cli(*args)
    _clean(p, 2)
    said = " ".join(p.stderr.split())
    assert "index.html: not a report natcoord wrote" in said, said
    assert (d / "index.html").read_text() == mine
    (d / "index.html").unlink()
    (d / "index.html").symlink_to(tmp_path / "elsewhere.html")
    _clean(_cli(*args), 2)
    assert (d / "index.html").is_symlink() and not (tmp_path / "elsewhere.html").exists()


@pytest.mark.parametrize("link", ["csv", "case folder", "results folder"])
def test_a_result_file_or_folder_replaced_by_a_link_is_no_evidence(tmp_path, link):
    """The check of a result file followed links (stat): a CSV, a case's folder or the
    results folder moved out and linked back passed the gate. The run wrote none."""
    d = tmp_path / "r"
    shutil.copytree(_real_run(), d)
    target = {"csv": d / "results" / "pendulum" / "natcoord.csv",
              "case folder": d / "results" / "pendulum",
              "results folder": d / "results"}[link]
    aside = tmp_path / "aside"
    target.rename(aside)
    target.symlink_to(aside)
    p = _cli("gate", "--results", d)
    _clean(p, 1)
    assert "symbolic link" in p.stderr, p.stderr


def test_a_summary_with_a_record_twice_is_refused(tmp_path):
    """A copied record was judged twice and the gate passed ('6 of 7 runs judged')."""
    d = tmp_path / "r"
    shutil.copytree(_real_run(), d)
    data = json.loads((d / "summary.json").read_text())
    data["records"].append(dict(data["records"][0]))
    (d / "summary.json").write_text(json.dumps(data))
    p = _cli("gate", "--results", d)
    _clean(p, 2)
    assert "a second record of pendulum/natcoord" in p.stderr, p.stderr


def test_reference_update_replaces_only_natcoord_s_own_reference(tmp_path):
    """reference update replaced a hand-made table, followed a link out of the project
    into a user's file, and a case named 'baseline' would have replaced the gate's
    baseline.json: each is refused now before any work (exit 2, the file named and kept);
    natcoord's own reference of the case is still replaced."""
    home = _project(tmp_path, "pendulum")
    text = (home / "cases" / "pendulum.toml").read_text()
    for name in ("baseline", "linked"):
        (home / "cases" / f"{name}.toml").write_text(
            text.replace('name = "pendulum"', f'name = "{name}"'))
    env = {"NATCOORD_HOME": str(home)}
    base = (home / "references" / "baseline.json").read_bytes()
    p = _cli("reference", "update", "baseline", env=env)
    _clean(p, 2)
    assert "baseline.json: not a reference natcoord wrote" in p.stderr, p.stderr
    assert (home / "references" / "baseline.json").read_bytes() == base
    mine = tmp_path / "mine.txt"
    mine.write_text("a user's file")
    (home / "references" / "linked.csv").symlink_to(mine)
    p = _cli("reference", "update", "linked", env=env)
    _clean(p, 2)
    assert "linked.csv: not a regular file" in p.stderr and mine.read_text() == "a user's file"
    before = (home / "references" / "pendulum.json").read_text()
    p = _cli("reference", "update", "pendulum", env=env)
    _clean(p, 0)
    assert (home / "references" / "pendulum.json").read_text() != before  # a new 'created'


@pytest.mark.parametrize("command", [["bench", "--work-precision", "--repeats", "1"],
                                     ["propose"]])
def test_a_damaged_reference_stops_bench_and_propose_naming_it(tmp_path, command):
    """A reference cut to one row: numpy stretched it over the 201 samples (errors of
    4.7 rad at every setting, an empty proposed tolerance, exit 0); cut to ten, a
    traceback. It is read as the gate reads it now: exit 2 naming the file."""
    refs = tmp_path / "refs"
    refs.mkdir()
    for rows, name in ((2, "one"), (11, "ten")):
        d = refs / name
        d.mkdir()
        lines = (REFERENCES / "pendulum.csv").read_text().splitlines()[:rows]
        (d / "pendulum.csv").write_text("\n".join(lines) + "\n")
        shutil.copy(REFERENCES / "pendulum.json", d)
        p = _cli(command[0], "pendulum", "--engines", "natcoord", "--references", d,
                 *command[1:], *(["--out", tmp_path / f"b-{name}"] if command[0] == "bench"
                                 else []))
        _clean(p, 2)
        assert f"{d / 'pendulum.csv'}: reference sample times differ" in p.stderr, p.stderr
