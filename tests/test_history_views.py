"""`natcoord history` reads the history back: recent runs, one cell's series, what
regressed since the last green suite (exit 1), flaky cells. Histories written through the
same `history.record` the suite uses."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys

import pytest

from natcoord.suite import history


def _summary(err: float, verdict: str) -> dict:
    chan = {"theta": {"kind": "angle", "max_abs": err, "max_rel": err, "tolerance": 1e-6,
                      "determined": True}}
    return {"generated": "2026-11-26T00:00:00", "machine": {"fingerprint": "m"},
            "records": [{"case": "pendulum", "engine": "mujoco", "status": "ok",
                         "verdict": verdict, "channels": chan},
                        {"case": "pendulum", "engine": "natcoord", "status": "ok",
                         "verdict": "pass", "channels": {**chan, "theta": {
                             **chan["theta"], "max_abs": 1e-12}}}]}


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", "history", *map(str, args)],
                          capture_output=True, text=True, timeout=120, env=dict(os.environ))


def test_since_green_names_the_cell_and_the_commits(tmp_path):
    db = tmp_path / "h.db"
    history.record(db, kind="suite", summary=_summary(1e-8, "pass"), gate=0, commit="aaa111")
    history.record(db, kind="suite", summary=_summary(1e-8, "pass"), gate=0, commit="bbb222")
    history.record(db, kind="suite", summary=_summary(3e-6, "fail"), gate=1, commit="ccc333")
    p = _cli("--since-green", "--history", db)
    assert p.returncode == 1, p.stderr
    assert "ccc333" in p.stdout and "bbb222" in p.stdout
    assert "pendulum/mujoco: ok / fail (was ok / pass); worst error/tolerance 0.01 -> 3" \
        in " ".join(p.stdout.split()), p.stdout
    assert "pendulum/natcoord" not in p.stdout
    data = json.loads(_cli("--since-green", "--json", "--history", db).stdout)
    assert [r["cell"] for r in data["regressed"]] == ["pendulum/mujoco"]
    assert data["green"]["commit"] == "bbb222" and data["latest"]["commit"] == "ccc333"


def test_since_green_compares_times_on_one_machine_only(tmp_path):
    """Twice the time on another machine is not a slowdown of the code (exit 0, saying
    why the times were not compared); on the same machine it is (exit 1), by the speed
    gate's rule: CPU time where both suites have it (wall time doubled by a busy core,
    CPU time unchanged, is what the gate passed and this view listed: 1.5x of wall
    medians, no test)."""
    def suite(machine: str, s: float, gate: int = 0, cpu: float | None = None):
        summary = {**_summary(1e-8, "pass"), "machine": {"fingerprint": machine}}
        bench = {"machine": {"fingerprint": machine}, "records": [
            {"case": "pendulum", "engine": "mujoco", "samples_s": [s, 1.01 * s, 1.02 * s]}
            | ({"cpu_samples_s": [cpu, 1.01 * cpu, 1.02 * cpu]} if cpu else {})]}
        history.record(db, kind="suite", summary=summary, bench=bench, gate=gate)
    db = tmp_path / "h.db"
    suite("fast", 0.1)
    suite("slow", 0.2, cpu=0.1)
    p = _cli("--since-green", "--history", db)
    assert p.returncode == 0 and "times not compared: the green suite ran on another " \
        "machine" in " ".join(p.stdout.split()), p.stdout
    suite("slow", 0.4, cpu=0.1)  # a busy core: wall time doubled, CPU time the same
    p = _cli("--since-green", "--history", db)
    assert p.returncode == 0 and "nothing regressed" in " ".join(p.stdout.split()), p.stdout
    suite("slow", 0.8, cpu=0.2)
    p = _cli("--since-green", "--history", db)
    assert p.returncode == 1 and "pendulum/mujoco: slower: median 2x (p = 0.05, 3 -> 3 " \
        "samples, cpu time)" in " ".join(p.stdout.split()), p.stdout


def test_runs_cell_series_and_flaky(tmp_path):
    db = tmp_path / "h.db"
    for err, v, code in ((1e-8, "pass", 0), (3e-6, "fail", 1), (1e-8, "pass", 0)):
        history.record(db, kind="suite", summary=_summary(err, v), gate=code)
    runs = json.loads(_cli("--json", "--history", db).stdout)
    assert [r["gate"] for r in runs] == [0, 1, 0] and runs[1]["failed"] == 1
    series = json.loads(_cli("--cell", "pendulum/mujoco", "--json", "--history", db).stdout)
    assert [round(s["worst"], 6) for s in series] == [0.01, 3.0, 0.01]
    (f,) = json.loads(_cli("--flaky", "--json", "--history", db).stdout)
    assert f["cell"] == "pendulum/mujoco" and f["flips"] == 2 and f["score"] == 1.0
    p = _cli("--cell", "pendulum", "--history", db)
    assert p.returncode == 2 and "CASE/ENGINE expected" in p.stderr
    assert _cli("--since-green", "--history", tmp_path / "none.db").returncode == 0
    said = " ".join(_cli("--cell", "nosuch/x", "--history", db).stdout.split())
    assert f"no run of cell 'nosuch/x' recorded in {db}" in said, said  # not "nothing"
    said = " ".join(_cli("--history", tmp_path / "typo.db").stdout.split())
    assert f"nothing recorded in {tmp_path / 'typo.db'} (no such file)" in said, said


@pytest.mark.parametrize("damage, named", [
    ("UPDATE results SET max_abs = 'abc'", "table results, row 1, column max_abs holds 'abc'"),
    ("UPDATE results SET tolerance = X'00' WHERE rowid = 2",
     "table results, row 2, column tolerance holds X'00'"),
    ("UPDATE bench SET samples = 'fast'", "table bench, row 1, column samples holds 'fast'"),
    ("UPDATE bench SET samples = NULL", "table bench, row 1, column samples holds NULL"),
    ("""UPDATE bench SET samples = '["a", "b"]'""", "table bench, row 1, column samples"),
    ("DELETE FROM runs WHERE id = 1", "table results, row 1, column run_id holds 1"),
    ("UPDATE bench SET samples = '[-1, 1e309]'",
     "table bench, row 1, column samples holds '[-1, 1e309]', not a JSON list of times "
     "(finite and positive)"),
    ("UPDATE bench SET samples = '[0.1, -0.1]'", "table bench, row 1, column samples")],
    ids=["number as text", "number as bytes", "samples not json", "samples null",
         "samples of text", "deleted run", "samples infinite", "samples negative"])
def test_a_damaged_row_is_named_whichever_view_reads(tmp_path, damage, named):
    """Rows are checked where the history is opened: every view (and the gate, the report)
    names the database, the row and the column (exit 2), none crashes on the value."""
    db = tmp_path / "h.db"
    bench = {"machine": {"fingerprint": "m"}, "records": [
        {"case": "pendulum", "engine": "mujoco", "samples_s": [0.1, 0.2]}]}
    for err, v, code in ((1e-8, "pass", 0), (3e-6, "fail", 1)):
        history.record(db, kind="suite", summary=_summary(err, v), bench=bench, gate=code)
    with sqlite3.connect(db) as con:
        con.execute(damage)
    con.close()
    for view in ([], ["--flaky"], ["--json"], ["--cell", "pendulum/mujoco"],
                 ["--since-green"]):
        p = _cli(*view, "--history", db)
        assert p.returncode == 2, (view, p.returncode, p.stdout[-500:], p.stderr[-1500:])
        assert f"{db}: damaged row: {named}" in p.stderr, (view, p.stderr)
        assert "Traceback" not in p.stderr + p.stdout


def test_an_empty_wal_beside_the_history_is_read_as_none(tmp_path):
    """A stale empty -wal (no frames: a copy, a killed process) beside a WAL history: the
    readers still open it as an unchanging file, creating no -shm beside it (which a
    read-only folder would refuse), and a run recorded into it while read is refused."""
    folder = tmp_path / "w"
    folder.mkdir()
    db = folder / "history.db"
    for err, v, code in ((1e-8, "pass", 0), (3e-6, "fail", 1)):
        history.record(db, kind="suite", summary=_summary(err, v), gate=code)
    assert db.read_bytes()[18:20] == b"\x02\x02"  # WAL mode
    (folder / "history.db-wal").write_bytes(b"")
    p = _cli("--json", "--history", db)
    assert p.returncode == 0, p.stderr
    assert [r["gate"] for r in json.loads(p.stdout)] == [1, 0]  # newest first
    assert sorted(f.name for f in folder.iterdir()) == ["history.db", "history.db-wal"]
    with pytest.raises(history.HistoryError, match="recorded into it while it was read"):
        with history.reading(db) as con:
            con.execute("SELECT COUNT(*) FROM runs").fetchone()
            history.record(db, kind="suite", summary=_summary(1e-8, "pass"), gate=0)
