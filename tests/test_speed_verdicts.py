"""Speed verdicts with power: calibrated timing batches, the slowdown test hook, and the
speed rule under load. Figures are never asserted by absolute time; the one benchmark-level
test compares an unchanged cell and a deliberately slowed one with wide margins."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from natcoord import load_case, timing
from natcoord.engines import natcoord_engine
from natcoord.errors import StoredFileError
from natcoord.outputs.result import evaluate_channels
from natcoord.suite import batches, bench, diff, history, speed
from natcoord.suite.runner import as_job, machine_info

from .conftest import CASES

# ---------------------------------------------------------------- natcoord's own batches


@pytest.mark.parametrize("extra", [
    {}, {"formulation": "maggi"}, {"method": "rk4", "h": 1e-3},
    {"formulation": "index3", "method": "trapezoidal", "h": 1e-3},
    {"compiled": False, "rtol": 1e-6, "atol": 1e-8}], ids=["index1", "maggi", "rk4",
                                                         "index3", "python"])
def test_a_batched_run_gives_the_single_runs_results_and_counters(extra):
    """The stepping repeated inside one run (a benchmark's calibrated batch) starts over
    each time: the samples and every deterministic counter are those of one run."""
    job = as_job(load_case(CASES / "slider_crank.toml"))
    settings = {**job.case.engine("natcoord").settings, **extra}
    one = natcoord_engine.run(job.case, job.init, settings)
    try:
        timing.configure(samples=2, min_batch_s=0.01)
        many = natcoord_engine.run(job.case, job.init, settings)
    finally:
        timing.configure()
    a, b = (evaluate_channels(job.case, r.motion) for r in (one, many))
    assert np.array_equal(a.to_numpy(), b.to_numpy())
    timed = ("batch_wall_s", "batch_cpu_s", "batch_runs", "batch_ref_wall_s",
             "batch_ref_cpu_s")
    assert not set(timed) & set(one.counters)
    wall, cpu, runs, ref_wall, ref_cpu = (many.counters.pop(k) for k in timed)
    assert len(wall) == len(cpu) == len(runs) == len(ref_wall) == len(ref_cpu) == 2
    assert min(runs) >= 1 and min(ref_wall) > 0 and min(ref_cpu) > 0
    assert all(w * n >= 0.01 for w, n in zip(wall, runs, strict=True))  # a batch >= 0.01 s
    assert many.wall_time_s == min(wall)
    drop = ("compile_time_s", "plan_time_s")
    assert ({k: v for k, v in one.counters.items() if k not in drop}
            == {k: v for k, v in many.counters.items() if k not in drop})


def test_timing_policy_is_checked():
    with pytest.raises(ValueError, match="timing policy"):
        timing.configure(samples=0)
    with pytest.raises(ValueError, match="timing policy"):
        timing.configure(slowdown=0)
    assert timing.policy() == timing.Policy()


# ---------------------------------------------------------------- whole-run batches


class _Clock:
    """A fake clock that only the fake engine advances: batch sizes and budgets become
    deterministic."""

    def __init__(self):
        self.t = 0.0

    def perf_counter(self):
        return self.t


def _engine(clock, step_s: float, overhead_s: float):
    """An engine that times one run (no batches of its own): stepping ``step_s`` (its
    reported wall time) inside a run that costs ``overhead_s`` more (build, outputs)."""
    calls = []

    def run(case, init, settings):
        calls.append(case)
        k = 0.25 if case == "short" else 1.0
        clock.t += k * (step_s + overhead_s)
        return SimpleNamespace(wall_time_s=k * step_s, counters={}, n_steps=10)

    return run, calls


def test_whole_run_batches_are_calibrated_and_the_slowdown_hook_multiplies(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(batches, "time", clock)
    monkeypatch.delenv(batches.SLOWDOWN_ENV, raising=False)
    run, calls = _engine(clock, step_s=0.004, overhead_s=0.001)
    _, _, full, short = batches.measure(run, "full", "short", None, {}, engine="e", samples=5,
                                        min_batch_s=0.02, budget_s=100.0)
    assert full.runs == [5] * 5 and full.wall_s == pytest.approx([0.004] * 5)
    assert short.runs == [20] * 5 and short.wall_s == pytest.approx([0.001] * 5)
    assert full.cpu_s == [] and len(calls) == 2 + 5 * (5 + 20)  # warm-up, then batches
    assert len(full.ref_wall_s) == len(full.ref_cpu_s) == 5  # the reference after each
    assert min(full.ref_wall_s) > 0 and short.ref_wall_s == []
    monkeypatch.setenv(batches.SLOWDOWN_ENV, "other=5,e=3")
    _, _, slow, _ = batches.measure(run, "full", None, None, {}, engine="e", samples=5,
                                    min_batch_s=0.02, budget_s=100.0)
    assert slow.wall_s == pytest.approx([3 * 0.004] * 5)  # every timed run executed 3x


def test_whole_run_batches_stay_within_the_budget(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(batches, "time", clock)
    monkeypatch.delenv(batches.SLOWDOWN_ENV, raising=False)
    run, _ = _engine(clock, step_s=0.004, overhead_s=0.096)  # a run costs 0.1 s
    _, _, full, _ = batches.measure(run, "full", None, None, {}, engine="e", samples=7,
                                    min_batch_s=0.02, budget_s=1.4)
    assert full.runs == [2] * 7  # fewer runs per batch first (5 would cost 3.5 s)
    _, _, full, _ = batches.measure(run, "full", None, None, {}, engine="e", samples=7,
                                    min_batch_s=0.02, budget_s=0.35)
    assert full.runs == [1, 1, 1]  # then fewer samples
    _, _, full, _ = batches.measure(run, "full", None, None, {}, engine="e", samples=7,
                                    min_batch_s=0.02, budget_s=0.05)
    assert full.runs == [1] and full.wall_s == [0.004]  # a long run: the warm-up only


def test_in_run_batches_stay_within_the_budget_and_a_long_warm_up_is_the_sample(monkeypatch):
    """natcoord's own timing (natcoord.timing): samples stop before they would overrun the
    budget; a warm-up that alone took the budget is the one sample, not the first of two."""
    clock = _Clock()
    clock.process_time = clock.perf_counter
    monkeypatch.setattr(timing, "time", clock)

    def step():
        clock.t += run_s
        return "run"

    try:
        run_s = 0.5
        timing.configure(samples=7, min_batch_s=0.1, budget_s=2.0)
        out, wall, got = timing.timed(step)
        assert (out, wall) == ("run", 0.5) and got.runs == [1, 1, 1, 1]  # a 5th: 2.5 s
        assert clock.t == pytest.approx(0.5 * (1 + 4))  # the warm-up, then 4 samples
        clock.t, run_s = 0.0, 2.5
        out, wall, got = timing.timed(step)
        assert wall == 2.5 and got.runs == [1] and got.wall_s == got.cpu_s == [2.5]
        assert clock.t == 2.5  # one run: the warm-up is the sample
    finally:
        timing.configure()


def test_slowdown_hook_is_read_per_engine_and_checked():
    assert batches.slowdown("natcoord", "natcoord=3, mujoco=2") == 3
    assert batches.slowdown("pinocchio", "natcoord=3") == 1
    assert batches.slowdown("natcoord", "") == 1
    for bad in ("natcoord", "natcoord=0", "natcoord=2x"):
        with pytest.raises(ValueError, match=batches.SLOWDOWN_ENV):
            batches.slowdown("natcoord", bad)


# ---------------------------------------------------------------- history, notes


def test_a_tolerance_edit_keeps_the_speed_baseline_and_a_mechanism_edit_does_not(
        tmp_path):
    """A benchmark is stored under its bench key (mechanism and the engine's settings):
    after a tolerance-only edit of the case file (another sha256) the next night is judged
    against the nights before it; after a change of mass it starts a new baseline. A night
    stored before bench keys (keyed by the case file's sha256) still counts while the file is
    the same."""
    from natcoord.case.mechanism import bench_key

    def variant(folder, old="", new=""):
        text = (CASES / "pendulum.toml").read_text()
        assert old in text
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "pendulum.toml").write_text(text.replace(old, new, 1))
        return load_case(tmp_path / folder / "pendulum.toml")

    base = variant("a")
    looser = variant("b", "\nangle = 1e-8", "\nangle = 1e-7")
    heavier = variant("c", "mass = 1.0", "mass = 2.0")
    assert base.digest != looser.digest and bench_key(base, "natcoord") == bench_key(
        looser, "natcoord") != bench_key(heavier, "natcoord")
    assert bench_key(base, "natcoord") != bench_key(base, "mujoco")
    db = tmp_path / "history.db"
    machine = {"fingerprint": "m"}

    def night(case, samples, keyed=True):
        rec = {"case": "pendulum", "engine": "natcoord", "case_hash": case.digest,
               "samples_s": samples, **({"bench_key": bench_key(case, "natcoord")}
                                        if keyed else {})}
        return {"machine": machine, "records": [rec]}

    history.record(db, kind="bench", bench=night(base, [1.0, 1.1], keyed=False))  # older
    history.record(db, kind="bench", bench=night(base, [1.2, 1.3]))
    (judged,) = diff.against_history(night(base, [1.0] * 3), db)
    assert judged.n_base == 4
    (judged,) = diff.against_history(night(looser, [1.0] * 3), db)
    assert judged.n_base == 2  # the night with a key; the older one was of the other file
    (judged,) = diff.against_history(night(heavier, [1.0] * 3), db)
    assert judged.n_base == 0 and not judged.judged


def test_the_speed_gate_reads_the_history_once_for_every_cell(tmp_path, monkeypatch):
    """Each reading runs the integrity check over the whole history: read three times per
    cell, a 200-night history took 32 s to judge 136 cells (one reading: 1.2 s)."""
    db = tmp_path / "history.db"
    recs = [{"case": f"c{i}", "engine": "natcoord", "case_hash": "h", "bench_key": "k",
             "samples_s": [1.0, 1.1, 1.2], "cpu_samples_s": [1.0, 1.0, 1.1],
             "ref_samples_s": [0.01] * 3, "ref_cpu_samples_s": [0.01] * 3} for i in range(4)]
    bench_night = {"machine": {"fingerprint": "m"}, "records": recs}
    history.record(db, kind="bench", bench=bench_night)
    opened = []
    real = history.reading

    def counted(*a, **k):
        opened.append(a)
        return real(*a, **k)

    monkeypatch.setattr(history, "reading", counted)
    judged = diff.against_history(bench_night, db)
    assert len(opened) == 1 and len(judged) == 4
    assert all(s.n_base == 3 and s.clock == "cpu" and s.relative for s in judged)


def test_history_keeps_cpu_samples_beside_wall_samples(tmp_path):
    db = tmp_path / "history.db"
    rec = {"case": "c", "engine": "natcoord", "case_hash": "h", "samples_s": [2.0, 2.1],
           "cpu_samples_s": [1.0, 1.1]}
    other = {"case": "c", "engine": "e", "case_hash": "h", "samples_s": [3.0]}
    history.record(db, kind="bench", bench={"machine": {"fingerprint": "m"},
                                            "records": [rec, other]})
    assert history.past_samples(db, "c", "natcoord", "h", "m")[0] == [2.0, 2.1]
    assert history.past_cpu_samples(db, "c", "natcoord", "h", "m") == [1.0, 1.1]
    assert history.past_cpu_samples(db, "c", "e", "h", "m") == []
    new = {"machine": {"fingerprint": "m"}, "records": [
        {**rec, "samples_s": [4.0] * 3, "cpu_samples_s": [1.05] * 3},  # a busy core
        {**other, "case": "unseen"}]}
    judged, unseen = diff.against_history(new, db)
    assert judged.clock == "cpu" and not judged.slower and not judged.judged  # 3 vs 2
    assert unseen.n_base == 0 and not unseen.judged
    notes = diff.speed_notes([judged, unseen], db)
    assert notes[0].startswith("c/natcoord: cannot judge speed: 2 -> 3 samples")
    assert notes[1].startswith("speed not judged for 1 cell(s): no earlier benchmark")


def test_a_slow_spell_of_the_whole_machine_is_no_slowdown_but_a_slower_code_is():
    """Samples judged relative to the reference work measured after each: a spell that
    slows the machine 1.6x (samples and references alike) reads as ~1x where the CPU
    times alone read as a slowdown; code 2x slower (samples only) is caught either way.
    Without references on one side the judgement falls back to the CPU times."""
    base = {"case": "c", "engine": "natcoord", "samples_s": [1.0, 1.02, 0.99, 1.01, 1.0],
            "ref_samples_s": [0.010, 0.0101, 0.0099, 0.0100, 0.0102]}
    base |= {"cpu_samples_s": base["samples_s"], "ref_cpu_samples_s": base["ref_samples_s"]}
    spell = {k: [1.6 * x for x in v] if isinstance(v, list) else v for k, v in base.items()}
    code = base | {"samples_s": [2 * x for x in base["samples_s"]],
                   "cpu_samples_s": [2 * x for x in base["samples_s"]]}

    def judged(b, n):
        return speed.judge("c", "natcoord", b["samples_s"], n["samples_s"],
                           base_cpu=b["cpu_samples_s"], new_cpu=n["cpu_samples_s"],
                           base_relative=speed.relative(b), new_relative=speed.relative(n))

    raw = speed.judge("c", "natcoord", [], [], base_cpu=base["cpu_samples_s"],
                      new_cpu=spell["cpu_samples_s"])
    assert raw.slower and raw.ratio == pytest.approx(1.6)  # a false alarm without them
    calm = judged(base, spell)
    assert calm.relative and calm.clock == "cpu" and not calm.slower, calm.line()
    assert calm.ratio == pytest.approx(1.0) and "cpu time / reference work" in calm.line()
    slow = judged(base, code)
    assert slow.relative and slow.slower and slow.ratio == pytest.approx(2.0), slow.line()
    old = {k: v for k, v in base.items() if not k.startswith("ref_")}
    fallback = judged(old, spell)
    assert not fallback.relative and fallback.slower  # no reference: CPU times as before
    assert speed.relative(base | {"ref_samples_s": [0.01] * 4}) == {
        "cpu": pytest.approx([x / r for x, r in zip(base["samples_s"], base["ref_samples_s"],
                                                    strict=True)])}  # lengths differ: none
    (compared,) = speed.compare_bench({"records": [base]}, {"records": [spell]})
    assert compared.relative and not compared.slower


def test_history_keeps_relative_samples_and_reads_an_older_history(tmp_path):
    """bench_relative holds each sample over its reference, per clock; a history from
    before it (no such table) gives none and gets the table on its next write."""
    import sqlite3

    db = tmp_path / "history.db"
    rec = {"case": "c", "engine": "natcoord", "case_hash": "h", "samples_s": [2.0, 3.0],
           "cpu_samples_s": [1.0, 1.5], "ref_samples_s": [0.5, 0.5],
           "ref_cpu_samples_s": [0.25, 0.5]}
    history.record(db, kind="bench", bench={"machine": {"fingerprint": "m"},
                                            "records": [rec]})
    assert history.past_relative(db, "c", "natcoord", "h", "m") == {
        "wall": [4.0, 6.0], "cpu": [4.0, 3.0]}
    assert history.past_relative(db, "c", "natcoord", "other", "m") == {}
    with sqlite3.connect(db) as con:
        con.execute("DROP TABLE bench_relative")
    assert history.past_relative(db, "c", "natcoord", "h", "m") == {}
    history.record(db, kind="bench", bench={"machine": {"fingerprint": "m"},
                                            "records": [rec]})
    assert history.past_relative(db, "c", "natcoord", "h", "m", last=1)["cpu"] == [4.0, 3.0]
    assert history.past_relative(db, "c", "natcoord", "h", "m") == {}  # one run lacks them
    with sqlite3.connect(db) as con:  # a damaged row is named, as in the other tables
        con.execute("UPDATE bench_relative SET samples = '[-1]'")
    with pytest.raises(history.HistoryError, match="table bench_relative, row 1, column "
                       "samples"):
        history.past_relative(db, "c", "natcoord", "h", "m")


def test_the_relative_baseline_is_of_the_same_nights_as_the_raw_one(tmp_path):
    """A slow night with references, then five fast ones without (written by a natcoord
    from before them): the baseline of past_relative was that slow night, six nights old,
    and a 3x slowdown passed as 1.0x. The window is the raw one's now: it lacks references,
    so the judgement is on CPU times, and the slowdown is caught; with references in every
    night of the window it is judged relative to them."""
    db = tmp_path / "history.db"

    def rec(x: float, refs: bool) -> dict:
        r = {"case": "c", "engine": "natcoord", "case_hash": "h", "samples_s": [x] * 5,
             "cpu_samples_s": [x] * 5}
        return r | ({"ref_samples_s": [0.01] * 5, "ref_cpu_samples_s": [0.01] * 5}
                    if refs else {})

    def night(x: float, refs: bool) -> None:
        history.record(db, kind="bench", bench={"machine": {"fingerprint": "m"},
                                                "records": [rec(x, refs)]})

    night(3.0, True)
    for _ in range(5):
        night(1.0, False)
    new = {"machine": {"fingerprint": "m"}, "records": [rec(3.0, True)]}
    (v,) = diff.against_history(new, db)
    assert v.slower and not v.relative and v.ratio == pytest.approx(3.0), v.line()
    for _ in range(5):
        night(1.0, True)
    (v,) = diff.against_history(new, db)
    assert v.slower and v.relative and v.ratio == pytest.approx(3.0), v.line()


def test_a_history_with_a_foreign_added_table_is_refused_before_anything_runs(tmp_path):
    """A bench_relative table of other columns was found only when the night was written
    (its results thrown away); it is refused on the first check now, as bench is."""
    import sqlite3

    db = tmp_path / "history.db"
    history.record(db, kind="bench", bench={"machine": {"fingerprint": "m"}, "records": []})
    with sqlite3.connect(db) as con:
        con.execute("DROP TABLE bench_relative")
        con.execute("CREATE TABLE bench_relative (run_id INTEGER, case_name TEXT)")
    with pytest.raises(history.HistoryError, match="table 'bench_relative' lacks columns"):
        history.check(db, write=True)


@pytest.mark.parametrize("field, value", [("cpu_samples_s", 5), ("cpu_samples_s", ["x"]),
                                          ("samples_s", [float("nan")]),
                                          ("ref_cpu_samples_s", [0.0]),
                                          ("ref_samples_s", [1e300]),  # no such machine
                                          ("ref_cpu_samples_s", [1e-12]),
                                          ("samples_s", []),  # was NaN in --json
                                          ("batch_runs", {})])
def test_two_benchmarks_with_a_malformed_sample_list_are_bad_input(tmp_path, field, value):
    """Two benchmark folders (speed only) whose bench.json holds a sample list of another
    shape: compare used to crash judging them; the file is named with the field, exit 2."""
    rec = {"case": "pendulum", "engine": "natcoord", "samples_s": [0.1] * 3,
           "cpu_samples_s": [0.1] * 3}
    for name in ("b1", "b2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "bench.json").write_text(json.dumps({"records": [rec | {field: value}]}))
    with pytest.raises(StoredFileError, match=re.escape(
            f"{tmp_path / 'b1' / 'bench.json'}: records[0].{field}: not a list")):
        diff.compare_runs(tmp_path / "b1", tmp_path / "b2", cases=None, references=tmp_path)
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "compare", tmp_path / "b1",
                        tmp_path / "b2"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert f"records[0].{field}: not a list" in p.stderr, p.stderr


def test_a_slowdown_the_gate_caught_is_no_baseline_until_accepted(tmp_path):
    """A lasting 3x slowdown passed the speed gate from its third night on: the nights it
    failed entered the pooled baseline. Now a run records the cells its gate found slower
    and their samples are left out of later baselines (the slowdown keeps failing), until
    a night is accepted (suite --accept-speed records none). A history from before the
    table reads as before."""
    import sqlite3

    db = tmp_path / "history.db"

    def night(x: float, slower=()):
        rec = {"case": "c", "engine": "natcoord", "case_hash": "h", "samples_s": [x] * 3,
               "cpu_samples_s": [x] * 3}
        history.record(db, kind="suite", gate=4 if slower else 0, slower=slower,
                       bench={"machine": {"fingerprint": "m"}, "records": [rec]})

    for _ in range(3):
        night(1.0)
    night(3.0, slower=[("c", "natcoord")])  # caught: exit 4
    assert history.past_cpu_samples(db, "c", "natcoord", "h", "m") == [1.0] * 9
    assert history.past_samples(db, "c", "natcoord", "h", "m")[0] == [1.0] * 9
    night(3.0)  # accepted: tonight's speed is the baseline from now on
    assert history.past_cpu_samples(db, "c", "natcoord", "h", "m")[:3] == [3.0] * 3
    with sqlite3.connect(db) as con:  # as a history written before the table was
        con.execute("DROP TABLE slower")
    assert history.past_cpu_samples(db, "c", "natcoord", "h", "m")[:6] == [3.0] * 6
    night(1.0)  # writing to it adds the table again
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT COUNT(*) FROM slower").fetchone() == (0,)


# ---------------------------------------------------------------- the real timing path


@pytest.mark.slow
def test_under_load_unchanged_cells_pass_and_an_injected_slowdown_is_caught(
        tmp_path, monkeypatch):
    """A process busy on the other core throughout; slider_crank's natcoord cell measured
    by the real bench path (worker process, calibrated batches, 5 samples) three times for
    the history (as three nights leave it: a shared machine drifts between fast and slow
    spells, up to 1.6x on CPU time over a minute, so one measurement is no baseline), five
    times unchanged and once with its stepping executed three times per run
    (the test hook). Judged as the suite judges (against the history, a suspect measured
    again, each sample relative to the reference work measured after it: a slow spell of
    the whole machine once read 1.53x on CPU time alone): the five unchanged cells raise
    no alarm (ratio ~1 against 1.5x), the 3x cell is caught by the suite's and by
    compare's rule."""
    job = as_job(load_case(CASES / "slider_crank.toml"))
    others = sorted(set(os.sched_getaffinity(0)) - {bench.CORE}) if bench.CORE is not None \
        else []
    pin = (lambda: os.sched_setaffinity(0, set(others))) if others else None
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=pin)
    db = tmp_path / "history.db"

    def cell(slowdown: int = 1) -> dict:
        if slowdown > 1:
            monkeypatch.setenv(batches.SLOWDOWN_ENV, f"natcoord={slowdown}")
        else:
            monkeypatch.delenv(batches.SLOWDOWN_ENV, raising=False)
        rec = bench.measure(job, "natcoord", 5, 600.0, tmp_path)
        assert rec["status"] == "ok", rec
        return {"machine": machine_info(), "records": [rec]}

    def gate(result: dict) -> speed.SpeedChange:
        (v,) = diff.slower_rechecked(result, [job], 5, 600.0, db)
        assert v.judged and v.clock == "cpu" and v.relative, v.line()
        return v

    try:
        for _ in range(3):
            base = cell()
            history.record(db, kind="bench", bench=base)
        unchanged = [gate(cell()) for _ in range(5)]
        slow = cell(3)
        caught = gate(slow)
    finally:
        busy.kill()
        busy.wait()
    assert not any(v.slower for v in unchanged), [v.line() for v in unchanged]
    assert caught.slower, caught.line()
    (compared,) = speed.compare_bench(base, slow)
    assert compared.slower, compared.line()
