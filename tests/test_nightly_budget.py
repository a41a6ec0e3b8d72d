"""The nightly within a night: the bench policy (natcoord measured every night, another
engine's cell reused until something changed), the suite's own work-precision points and
scoring, `suite --quick`, and the time-left estimate."""

from __future__ import annotations

import datetime as dt
import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from natcoord.suite import eta, policy

ROOT = Path(__file__).resolve().parents[1]
NOW = dt.datetime(2026, 11, 26, 12, tzinfo=dt.UTC)


def _rec(engine="mujoco", **kw) -> dict:
    r = {"case": "c", "engine": engine, "status": "ok", "samples_s": [1.0, 1.1, 1.0],
         "engine_version": "3.1", "case_hash": "h1", "adapter_hash": "a1",
         "requested_repeats": 7, "measured": (NOW - dt.timedelta(days=1)).isoformat()}
    return r | kw


def _plan(old: dict, tonight: dict | None = None, *, machine="m", repeats=7):
    """plan() with one external cell, its adapter digest pinned to 'a1'."""
    summary = {"records": [{"case": "c", "engine": "mujoco", "status": "ok",
                            "engine_version": "3.1", "case_hash": "h1"} | (tonight or {}),
                           {"case": "c", "engine": "natcoord", "status": "ok"}]}
    previous = {"machine": {"fingerprint": "m"}, "records": [old, _rec("natcoord")],
                "work_precision": [{"case": "c", "engine": "mujoco", "error": 1e-3}],
                "origins": {"c/mujoco": "prev", "c/natcoord": "prev"}}
    return policy.plan(summary, previous, ["natcoord", "mujoco"],
                       repeats=repeats, machine=machine, when=NOW)


def test_an_external_cell_is_reused_until_something_changes(monkeypatch):
    monkeypatch.setattr(policy, "adapter_digest", lambda e: "a1")
    plan = _plan(_rec())
    reuse, points, why = plan.reuse, plan.kept, plan.measure
    assert list(reuse) == [("c", "mujoco")] and why == {("c", "natcoord"):
                                                        "measured every night"}
    mark = reuse[("c", "mujoco")]["reused"]
    assert mark == {"measured": _rec()["measured"], "from": "prev"}
    assert points == [{"case": "c", "engine": "mujoco", "error": 1e-3, "reused": mark}]
    for old, tonight, machine, reason in [
            (_rec(), {"engine_version": "3.2"}, "m", "engine version 3.1 -> 3.2"),
            (_rec(), {"case_hash": "h2"}, "m", "case file changed"),
            (_rec(adapter_hash="a0"), {}, "m", "adapter code changed"),
            (_rec(), {}, "other", "another machine"),
            (_rec(measured=(NOW - dt.timedelta(days=8)).isoformat()), {}, "m",
             "over 7 days ago"),
            (_rec(requested_repeats=3), {}, "m", "other sample count"),
            (_rec(status="failed", samples_s=[]), {}, "m", "no earlier measurement")]:
        plan = _plan(old, tonight, machine=machine)
        assert not plan.reuse and not plan.kept, reason
        assert reason in plan.measure[("c", "mujoco")], (plan.measure, reason)
        assert list(plan.spare) == [("c", "mujoco")]  # measured while the budget lasts


def test_the_budget_takes_the_never_measured_first_and_long_runs_are_run_timed(
        monkeypatch):
    """Cells to measure are queued: never measured (a run-timed record counts as none)
    before stale ones, the oldest first, the cheapest first among equals; a cell whose one
    run is longer than a bench cell's timing budget is timed by its accuracy run, and its
    record says so."""
    monkeypatch.setattr(policy, "adapter_digest", lambda e: "a1")
    old = lambda case, days: _rec(case=case, measured=(  # noqa: E731
        NOW - dt.timedelta(days=days)).isoformat())
    previous = {"machine": {"fingerprint": "m"}, "origins": {},
                "records": [old("stale9", 9), old("stale8", 8), old("fresh", 1),
                            _rec(case="timed", timed_by={"why": "x"})]}
    run = lambda case, wall: {"case": case, "engine": "mujoco", "status": "ok",  # noqa: E731
                              "engine_version": "3.1", "case_hash": "h1", "wall_time_s": wall,
                              "process_time_s": wall + 1.0, "n_steps": 100,
                              "build_time_s": 0.1, "settings": {"dt": 1e-3}}
    summary = {"records": [run("stale8", 0.5), run("stale9", 0.5), run("fresh", 0.5),
                           run("new_dear", 2.0), run("new_cheap", 0.01), run("timed", 0.2),
                           run("long", 2 * policy.CELL_BUDGET_S),
                           run("long", 2 * policy.CELL_BUDGET_S) | {"engine": "natcoord"},
                           run("short", 0.1) | {"engine": "natcoord"}]}
    plan = policy.plan(summary, previous, ["mujoco", "natcoord"], repeats=7, machine="m",
                       when=NOW)
    assert set(plan.timed) == {("long", "mujoco"), ("long", "natcoord")}
    assert plan.measure[("short", "natcoord")] == "measured every night"
    assert list(plan.reuse) == [("fresh", "mujoco")]
    assert [c for c, _ in plan.spare] == ["new_cheap", "timed", "new_dear", "stale9",
                                          "stale8"]
    long = plan.timed[("long", "mujoco")]
    assert long["samples_s"] == [2 * policy.CELL_BUDGET_S] and long["repeats"] == 1
    assert "its accuracy run is its timing" in long["timed_by"]["why"]
    assert long["us_per_step"] == pytest.approx(1e6 * 2 * policy.CELL_BUDGET_S / 100)
    spare = plan.spare[("new_cheap", "mujoco")]
    assert "over tonight's bench budget" in spare["timed_by"]["why"]
    from natcoord.suite.stored import carried
    assert carried(long) and carried(spare) and not carried(_rec())
    assert policy.measured_only({"records": [long, _rec()]})["records"] == [_rec()]


def test_a_one_case_suite_does_not_hide_the_nights_before_it(tmp_path):
    """earlier(): each cell's newest record over the recorded suites on this machine, with
    the folder it comes from; a vanished folder and another machine's suites are skipped."""
    from natcoord.suite import history
    from natcoord.suite.io import write_json

    db = tmp_path / "history.db"

    def night(name, cases, machine="m"):
        folder = tmp_path / name
        bench = {"generated": name, "machine": {"fingerprint": machine},
                 "records": [_rec(case=c, measured=name) for c in cases],
                 "work_precision": [{"case": c, "engine": "mujoco", "error": 1.0}
                                    for c in cases]}
        summary = {"generated": name, "machine": {"fingerprint": machine},
                   "records": [{"case": c, "engine": "mujoco", "status": "ok",
                                "process_time_s": 2.0} for c in cases]}
        write_json(folder / "bench.json", bench)
        write_json(folder / "summary.json", summary)
        history.record(db, kind="suite", summary=summary, bench=bench,
                       results_dir=str(folder))
        return folder

    night("n1", ["a", "b"])
    night("n2", ["a"])
    gone = night("n3", ["b"])
    night("n4", ["a", "b"], machine="other")
    (gone / "bench.json").unlink()
    bench, summary = policy.earlier(db, "m")
    assert {(r["case"], r["measured"]) for r in bench["records"]} == {("a", "n2"),
                                                                     ("b", "n1")}
    assert bench["origins"] == {"a/mujoco": str(tmp_path / "n2"),
                                "b/mujoco": str(tmp_path / "n1")}
    assert len(bench["work_precision"]) == 2 and len(summary["records"]) == 2
    assert policy.earlier(tmp_path / "none.db", "m") == (None, None)


def test_the_adapter_digest_follows_the_adapter_files():
    a, b = policy.adapter_digest("mujoco"), policy.adapter_digest("pinocchio")
    assert len(a) == 16 and a != b and a == policy.adapter_digest("mujoco")
    assert policy.adapter_digest("no-such-engine") == ""


def test_time_left_comes_from_the_last_durations_and_tonights_pace():
    """Deterministic: a fake clock. Pieces known from the last suite take their time, an
    unknown piece the median of its engine's; tonight runs at twice the pace, which the
    estimate follows fully once a tenth of the work is done."""
    known = eta.durations({"records": [{"case": f"c{i}", "engine": "e",
                                        "process_time_s": 1.0 + i} for i in range(3)]},
                          {"records": [], "work_precision": [
                              {"case": "c0", "engine": "e", "process_time_s": 2.0},
                              {"case": "c0", "engine": "e", "process_time_s": 3.0},
                              {"case": "c0", "engine": "x", "process_time_s": 9.0,
                               "reused": {}}]})
    assert known[("sweep", "c0", "e")] == 5.0 and ("sweep", "c0", "x") not in known
    pieces = [("run", f"c{i}", "e") for i in range(4)] + [("bench", "c0", "e")]
    exp = eta.expect(pieces, known)
    assert exp[("run", "c3", "e")] == 2.0  # median of its engine's accuracy runs
    assert exp[("bench", "c0", "e")] == eta.UNKNOWN_S  # no bench piece ever measured
    now = [0.0]
    clock = eta.Eta({("run", f"c{i}", "e"): 1.0 for i in range(20)}, clock=lambda: now[0])
    assert clock.left() == 20.0
    for i in range(2):  # a tenth, at twice the expected pace
        now[0] += 2.0
        clock.done(("run", f"c{i}", "e"))
    assert clock.left() == pytest.approx(36.0)  # 18 pieces x 2 s
    clock.add({("bench", "c0", "e"): 0.0})  # a reused cell costs nothing
    assert clock.left() == pytest.approx(36.0)


def test_the_pace_blends_measured_times_with_the_wall_clock():
    """Two cores: a long piece finishes after 100 s of wall clock, while the other core's
    piece is still running. Its measured time (60 s of process time over 2 cores = 30 s,
    as expected 50 s: 0.6x) and the wall clock (100 s for 50 expected: 2x) set the pace as
    their geometric mean; with nothing measured, the wall clock alone."""
    now = [0.0]
    exp = {("run", "long", "e"): 50.0} | {("run", f"c{i}", "e"): 5.0 for i in range(90)}
    clock = eta.Eta(exp, clock=lambda: now[0])
    wall = eta.Eta(exp, clock=lambda: now[0])  # no measured time: the wall clock's pace
    now[0] = 100.0
    clock.done(("run", "long", "e"), 30.0)
    assert clock.left() == pytest.approx(450.0 * (0.6 * 2.0) ** 0.5)
    wall.done(("run", "long", "e"))
    assert wall.left() == pytest.approx(450.0 * 2.0)


def test_other_engines_sweeps_are_not_expected_once_the_bench_spent_the_budget():
    """The night's budget (60 s) covers two external cells' bench and sweep pieces
    (expected 40 s each): while nothing is spent they share the 60 s; once the bench
    pieces measured 60 s, the sweeps are expected to take nothing."""
    now = [0.0]
    cells = {("a", "x"), ("b", "x")}
    exp = {(k, c, e): 40.0 for c, e in cells for k in ("bench", "sweep")}
    exp[("sweep", "a", "natcoord")] = 10.0  # natcoord's: outside the budget
    clock = eta.Eta(exp, clock=lambda: now[0])
    clock.budget(cells, 60.0)
    assert clock.left() == pytest.approx(70.0)  # 60 s of budget + natcoord's 10 s
    now[0] = 60.0
    clock.done(("bench", "a", "x"), 30.0)
    clock.done(("bench", "b", "x"), 30.0)
    # tonight's pace: 60 s measured and 60 s of wall clock for 80 s expected
    assert clock.left() == pytest.approx(10.0 * 0.75)  # only natcoord's sweep is left


def _suite(*args, timeout=1200):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", "suite", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "NO_COLOR": "1"})


@pytest.fixture(scope="module")
def two_nights(tmp_path_factory):
    """Two real suites of the spatial slider-crank (a catalogue case) in natcoord and MuJoCo
    against one fresh history: the first measures both, the second only natcoord."""
    tmp = tmp_path_factory.mktemp("nights")
    db = tmp / "history.db"
    args = ("slider_crank_3d", "--engines", "natcoord,mujoco", "--history", db)
    first = _suite(*args, "--out", tmp / "a")
    second = _suite(*args, "--out", tmp / "b")
    return tmp, db, first, second


def test_the_second_night_reuses_the_external_cell_and_judges_only_natcoord(two_nights):
    tmp, db, first, second = two_nights
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "2 cell(s) to measure" in first.stdout and "s left in the suite" in second.stdout
    assert "1 reused from earlier suites" in second.stdout, second.stdout
    a = json.loads((tmp / "a" / "bench.json").read_text())
    b = json.loads((tmp / "b" / "bench.json").read_text())
    old = {r["engine"]: r for r in a["records"]}
    new = {r["engine"]: r for r in b["records"]}
    assert "reused" not in old["mujoco"] and "reused" not in new["natcoord"]
    assert new["mujoco"]["reused"]["measured"] == old["mujoco"]["measured"]
    assert new["mujoco"]["samples_s"] == old["mujoco"]["samples_s"]
    assert new["natcoord"]["measured"] > old["natcoord"]["measured"]
    assert b["policy"]["reused"] == ["slider_crank_3d/mujoco"]
    # the speed gate judged natcoord's new samples only; the history holds each
    # measurement once (mujoco's samples are not recorded a second time)
    assert "speed judged for 1 cell(s) (1 on CPU time, 1 relative to the reference work)" \
        in second.stderr, second.stderr  # against the first night's references
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT engine, COUNT(*) FROM bench GROUP BY engine").fetchall()
    assert dict(rows) == {"natcoord": 2, "mujoco": 1}


def test_the_suite_writes_work_precision_and_scoring_like_bench(two_nights):
    tmp, *_ = two_nights
    for night in ("a", "b"):
        b = json.loads((tmp / night / "bench.json").read_text())
        pts = b["work_precision"]
        by = {e: [p for p in pts if p["engine"] == e] for e in ("natcoord", "mujoco")}
        assert len(by["natcoord"]) == len(policy.NIGHTLY_SWEEPS["natcoord"])
        assert len(by["mujoco"]) == len(policy.NIGHTLY_SWEEPS["mujoco"])
        assert all(p["status"] == "ok" and p["benchmark_error"] >= 0 for p in pts)
        assert all(("reused" in p) == (night == "b" and p["engine"] == "mujoco")
                   for p in pts)
        scores = {s["engine"]: s for s in b["scoring"]}
        assert set(scores) == {"natcoord", "mujoco"}
        for s in scores.values():  # every score within the benchmark's precision, 1 mm
            assert s["precision"] == 1e-3 and s["error"] <= 1e-3
            assert s["time_to_precision"] > 0 and s["reached_by"]
        assert {r["engine"] for r in b["time_to_accuracy"]} >= {"natcoord (index1 dop853)",
                                                                 "mujoco"}


def test_with_no_budget_left_the_external_cell_is_timed_by_its_accuracy_run(tmp_path):
    """`--bench-budget 0`: natcoord is measured as every night; MuJoCo's cell (never
    measured) is timed by tonight's accuracy run (one sample: that run's stepping time) and
    not swept; the history does not record it as a measurement."""
    db = tmp_path / "history.db"
    p = _suite("slider_crank_3d", "--engines", "natcoord,mujoco", "--history", db,
               "--bench-budget", "0", "--out", tmp_path / "n")
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    b = json.loads((tmp_path / "n" / "bench.json").read_text())
    s = json.loads((tmp_path / "n" / "summary.json").read_text())
    rec = {r["engine"]: r for r in b["records"]}
    run = {r["engine"]: r for r in s["records"]}
    assert "timed_by" not in rec["natcoord"] and len(rec["natcoord"]["samples_s"]) >= 2
    assert rec["mujoco"]["samples_s"] == [run["mujoco"]["wall_time_s"]]
    assert "over tonight's bench budget" in rec["mujoco"]["timed_by"]["why"]
    assert b["policy"]["budget_s"] == 0 and b["policy"]["spent_s"] == 0
    assert list(b["policy"]["timed_by_accuracy_run"]) == ["slider_crank_3d/mujoco"]
    assert {p["engine"] for p in b["work_precision"]} == {"natcoord"}
    # scored all the same, from the accuracy run: its benchmark error and stepping time
    from natcoord.case.casefile import load_case
    from natcoord.suite.bench import benchmark_error
    score = {x["engine"]: x for x in b["scoring"]}["mujoco"]
    err = benchmark_error(load_case(ROOT / "cases" / "slider_crank_3d.toml"),
                          tmp_path / "n" / "results" / "slider_crank_3d" / "mujoco.csv",
                          ROOT / "references")
    assert score["error"] == run["mujoco"]["benchmark_error"] == err
    assert 0 < err <= score["precision"]
    assert score["time_to_precision"] == run["mujoco"]["wall_time_s"]
    assert score["reached_by"] == "case settings (accuracy run)"
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT engine, COUNT(*) FROM bench GROUP BY engine").fetchall()
    assert dict(rows) == {"natcoord": 1}


def test_quick_is_marked_and_leaves_the_history_alone(two_nights):
    tmp, db, *_ = two_nights
    with sqlite3.connect(db) as con:
        before = con.execute("SELECT COUNT(*) FROM runs").fetchone()
    p = _suite("slider_crank_3d", "--quick", "--history", db, "--out", tmp / "q")
    assert p.returncode == 0, p.stderr
    assert "natcoord suite --quick" in p.stdout and "(quick)" in p.stdout
    assert "not recorded in the history" in p.stderr
    assert (tmp / "q" / "summary.md").read_text().startswith("## natcoord suite --quick:")
    assert json.loads((tmp / "q" / "summary.json").read_text())["mode"] == "quick"
    b = json.loads((tmp / "q" / "bench.json").read_text())
    assert b["policy"]["mode"] == "quick" and "work_precision" not in b
    s = json.loads((tmp / "q" / "summary.json").read_text())
    assert [r["engine"] for r in b["records"]] == ["natcoord", "mujoco"]
    runs = {r["engine"]: r for r in s["records"]}  # no bench process: the runs' own times
    assert all(r["samples_s"] == [runs[r["engine"]]["wall_time_s"]] and "quick" in
               r["timed_by"]["why"] for r in b["records"])
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT COUNT(*) FROM runs").fetchone() == before


def test_a_reused_cell_is_not_judged_as_a_new_measurement(tmp_path):
    from natcoord.suite import diff, speed

    fresh, reused = _rec(case="a"), _rec(case="b") | {"reused": {"measured": "x"}}
    bench = {"machine": {"fingerprint": "m"}, "records": [fresh, reused]}
    judged = diff.against_history(bench, tmp_path / "history.db")
    assert [(s.case, s.n_base) for s in judged] == [("a", 0)]
    slow = {"records": [r | {"samples_s": [3 * s for s in r["samples_s"]]}
                        for r in (fresh, reused)]}
    assert [s.case for s in speed.compare_bench({"records": [fresh, reused]}, slow)] == ["a"]


def test_the_heartbeat_shows_the_time_left_once_a_piece_has_started():
    """The 'still going' line of a long silent stretch carries the suite's time left once
    a piece has started: before anything finished, the expectation less what the running
    pieces have done (tonight's pace is not known yet)."""
    from natcoord.cli import _ticker

    now = [0.0]
    clock = eta.Eta({("run", f"c{i}", "e"): 10.0 for i in range(4)}, clock=lambda: now[0])
    tick = _ticker(clock, "run")
    assert tick.peek() is None
    tick.started("c0/e")
    now[0] = 4.0
    assert tick.peek() == pytest.approx(36.0)
    now[0] = 10.0
    assert tick("c0/e", {"process_time_s": 10.0}) == pytest.approx(30.0)
    assert tick.peek() == pytest.approx(30.0)


def test_a_running_piece_counts_as_done_for_the_time_it_has_run():
    """Two cores: a long run (100 s of process time, 50 s expected over 2 cores) and a
    short one start together; at 10 s the short one finishes on time. Counting the long
    run's 10 s (5 expected seconds) as done, the wall clock is on pace (10 s for 10) and
    so is the estimate; counting only what finished, the wall clock said 2x (10 s for 5)
    and the first estimates of a real first night came out 1.5x the truth."""
    now = [0.0]
    exp = ({("run", "long", "e"): 50.0, ("run", "short", "e"): 5.0}
           | {("run", f"c{i}", "e"): 5.0 for i in range(90)})
    clock = eta.Eta(exp, clock=lambda: now[0])
    for name in ("long", "short"):
        clock.started(("run", name, "e"), 2)
    now[0] = 4.0
    assert clock.left() == pytest.approx(505.0 - 4.0)  # nothing finished: no pace yet
    now[0] = 10.0
    clock.done(("run", "short", "e"), 5.0)
    assert clock.left() == pytest.approx(505.0 - 10.0)
    now[0] = 200.0  # a piece counts at most its expectation, however long it runs
    assert clock._running(exp) == 50.0


def test_a_machine_with_no_suite_yet_expects_the_shipped_reference_durations(tmp_path):
    """The shipped references/durations.json covers every catalogue cell's accuracy run;
    the suite's expectation takes it only when this machine has no suite of its own, and
    a missing or malformed file is no prior (an estimate never stops a suite)."""
    from natcoord.case.casefile import load_cases
    from natcoord.cli import _expected
    from natcoord.suite.runner import prepare

    shipped = eta.prior(ROOT / "references")
    cases = list(load_cases(ROOT / "cases").values())
    assert {("run", c.name, "natcoord") for c in cases} <= set(shipped)
    assert all(t >= 0 for t in shipped.values())
    jobs = [prepare(c) for c in cases if c.name in ("four_bar", "four_bar_3d")]
    durations, source = eta.known(None, None, ROOT / "references")
    assert source == "reference"
    with_prior = _expected(jobs, ["natcoord"], [], [], None, durations, 1, 60.0)
    assert with_prior[("run", "four_bar_3d", "natcoord")] == shipped[
        ("run", "four_bar_3d", "natcoord")]  # its compile: far more than an unknown 5 s
    assert shipped[("run", "four_bar_3d", "natcoord")] > 4 * shipped[
        ("run", "four_bar", "natcoord")]
    history = {"records": [{"case": "four_bar", "engine": "natcoord", "process_time_s": 1.5}]}
    durations, source = eta.known(history, None, ROOT / "references")
    assert source == "earlier"
    mine = _expected(jobs, ["natcoord"], [], [], None, durations, 1, 60.0)
    assert mine[("run", "four_bar_3d", "natcoord")] == 1.5  # this machine's own, not shipped
    for bad in ("{", '{"durations": [{"kind": "run"}]}', "[]"):
        (tmp_path / eta.PRIOR).write_text(bad)
        assert eta.prior(tmp_path) == {}
    assert eta.prior(tmp_path / "nowhere") == {}


def test_natcoords_cold_start_is_a_piece_of_the_time_left():
    """The bench ends with natcoord's cold start (fresh processes of about a second each):
    expected from the last suite's bench.json when natcoord is benchmarked, not otherwise;
    a failed one is no duration (a tiny suite's estimate was half the truth without it)."""
    from natcoord.case.casefile import load_cases
    from natcoord.cli import _expected
    from natcoord.suite.runner import prepare

    cold = {"status": "ok", "case": "pendulum", "samples_s": [1.25, 1.0, 1.5]}
    known = eta.durations(None, {"records": [], "cold_start": cold})
    assert known == {eta.COLD_START: 3.75}
    assert eta.durations(None, {"records": [], "cold_start": cold | {"status": "failed"}}
                         ) == {}
    jobs = [prepare(load_cases(ROOT / "cases")["pendulum"])]
    benched = _expected(jobs, ["natcoord"], ["natcoord"], [], None, known, 2, 60.0)
    assert benched[eta.COLD_START] == 3.75  # whole: the processes run one after another
    assert eta.COLD_START not in _expected(jobs, ["natcoord"], [], [], None, known, 2, 60.0)
    assert eta.COLD_START not in _expected(jobs, ["mujoco"], ["mujoco"], [], None, known, 2,
                                           60.0)
    unknown = _expected(jobs, ["natcoord"], ["natcoord"], [], None, {}, 2, 60.0)
    assert unknown[eta.COLD_START] == eta.UNKNOWN_S


def test_the_next_suite_expects_the_cold_start_its_history_measured(tmp_path):
    """policy.earlier() carries the newest successful cold start of the recorded suites, so
    that the next suite expects what it took (not UNKNOWN_S)."""
    from natcoord.suite import history
    from natcoord.suite.io import write_json

    db = tmp_path / "history.db"
    for name, cold in (("n1", {"status": "ok", "samples_s": [0.5, 0.5]}),
                       ("n2", {"status": "failed", "samples_s": []})):
        folder = tmp_path / name
        bench = {"generated": name, "machine": {"fingerprint": "m"},
                 "records": [_rec(case="a", measured=name)], "cold_start": cold}
        summary = {"generated": name, "machine": {"fingerprint": "m"},
                   "records": [{"case": "a", "engine": "mujoco", "status": "ok",
                                "process_time_s": 2.0}]}
        write_json(folder / "bench.json", bench)
        write_json(folder / "summary.json", summary)
        history.record(db, kind="suite", summary=summary, bench=bench, results_dir=str(folder))
    bench, summary = policy.earlier(db, "m")
    known, source = eta.known(summary, bench, ROOT / "references")
    assert source == "earlier" and known[eta.COLD_START] == 1.0  # n1's: n2's failed


def test_the_prior_is_written_from_a_suite_folder(tmp_path):
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "summary.json").write_text(json.dumps({
        "generated": "2026-11-27T00:00:00+00:00", "machine": {"cores": 2},
        "records": [{"case": "c", "engine": "e", "process_time_s": 2.5},
                    {"case": "d", "engine": "e", "process_time_s": 1.0, "reused": {}}]}))
    path = eta.write_prior(suite, tmp_path)
    assert eta.prior(tmp_path) == {("run", "c", "e"): 2.5}  # a carried record is no time
    assert json.loads(path.read_text())["measured"]["machine"] == {"cores": 2}


def test_the_reference_durations_are_written_from_a_full_suite_into_the_project(tmp_path):
    """`python -m natcoord.suite.eta RESULTS_DIR` wrote the installed checkout's
    references/durations.json whatever NATCOORD_HOME said, took a one-case quick suite as
    the whole suite's durations, and answered --help with a traceback."""
    import subprocess
    import sys

    from .conftest import ROOT

    home = tmp_path / "project"
    (home / "cases").mkdir(parents=True)
    (home / "references").mkdir()
    folder = tmp_path / "suite"
    folder.mkdir()
    (folder / "summary.json").write_text('{"records": [], "generated": "2026-11-28"}')
    (folder / "bench.json").write_text('{"records": [], "policy": {"mode": "quick"}}')
    shipped = (ROOT / "references" / "durations.json").read_bytes()

    def eta(*args):
        return subprocess.run([sys.executable, "-m", "natcoord.suite.eta", *map(str, args)],
                              capture_output=True, text=True, timeout=300, cwd=tmp_path,
                              env={**os.environ, "NATCOORD_HOME": str(home)})

    p = eta("--help")
    assert p.returncode == 0 and "usage: python -m natcoord.suite.eta" in p.stdout, p.stderr
    p = eta(folder)
    assert p.returncode == 2 and "not a full suite's folder" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and not (home / "references" / "durations.json").exists()
    (folder / "bench.json").write_text('{"records": [], "policy": {"mode": "nightly"}}')
    p = eta(folder)
    assert p.returncode == 0 and (home / "references" / "durations.json").is_file(), p.stderr
    assert (ROOT / "references" / "durations.json").read_bytes() == shipped


def _gate(results: Path, db: Path):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", "gate", "--results",
                           str(results), "--history", str(db)], capture_output=True,
                          text=True, timeout=600, env={**os.environ, "NO_COLOR": "1"})


def test_a_suite_folder_s_bench_json_is_evidence_checked_by_the_gate(two_nights, tmp_path):
    """bench.json was tied to nothing: divided by 3 (a 3x slowdown hidden), swapped for
    another night's, emptied, or deleted with the marker, the gate passed. The suite now
    stores its sha256 in summary.json and the gate checks it (exit 1, naming the file),
    as it checks the result CSVs; the copy as it was still passes."""
    import shutil

    tmp, db, *_ = two_nights
    src = tmp / "b"
    assert len(json.loads((src / "summary.json").read_text())["bench_sha256"]) == 64

    def copy(name: str, edit) -> Path:
        d = tmp_path / name
        shutil.copytree(src, d, symlinks=True)
        edit(d)
        return d

    def scaled(d: Path) -> None:
        data = json.loads((d / "bench.json").read_text())
        for r in data["records"]:
            r["samples_s"] = [x / 3 for x in r["samples_s"]]
        (d / "bench.json").write_text(json.dumps(data))

    def gone(d: Path) -> None:
        (d / "bench.json").unlink()
        (d / ".natcoord-results").unlink()

    def linked(d: Path) -> None:
        (d / "bench.json").rename(tmp_path / f"{d.name}-bench.json")
        (d / "bench.json").symlink_to(tmp_path / f"{d.name}-bench.json")

    intact = _gate(copy("intact", lambda d: None), db)  # trusted: its speed is judged (0,
    assert intact.returncode in (0, 4), intact.stderr  # or 4 should the two nights' timings
    assert "bench.json:" not in intact.stderr and "speed judged for" in intact.stderr  # differ)
    for name, edit, said in (("scaled", scaled, "altered since the run"),
                             ("swapped", lambda d: shutil.copy(tmp / "a" / "bench.json",
                                                               d / "bench.json"),
                              "altered since the run"),
                             ("gone", gone, "missing"),
                             ("linked", linked, "not a regular file (a symbolic link)")):
        p = _gate(copy(name, edit), db)
        assert p.returncode == 1 and f"bench.json: {said}" in p.stderr, (name, p.stderr)
        assert "Traceback" not in p.stderr


def test_the_folder_of_a_suite_that_did_not_finish_is_no_evidence(two_nights, tmp_path):
    """A suite killed before publishing leaves its staging folder, marked 'staging': the
    gate passed it (exit 0); it is refused now, naming the marker."""
    import shutil

    tmp, db, *_ = two_nights
    d = tmp_path / "staging"
    shutil.copytree(tmp / "b", d)
    marker = json.loads((d / ".natcoord-results").read_text())
    (d / ".natcoord-results").write_text(json.dumps(marker | {"state": "staging"}))
    p = _gate(d, db)
    assert p.returncode == 2 and "did not finish" in p.stderr, p.stderr
