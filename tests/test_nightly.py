"""The nightly service: history in SQLite, speed regressions told from noise, compare,
CI summary."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from natcoord import load_case
from natcoord.suite import bench, diff, history, propose, speed
from natcoord.suite.io import read_json, write_json
from natcoord.suite.runner import run_suite

from .conftest import CASES, REFERENCES


def _cli(*args, env=None, timeout=600):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def test_speed_rule_needs_factor_significance_and_power():
    rng = np.random.default_rng(0)
    base = list(1.0 + 0.05 * rng.random(7))
    assert not speed.judge("c", "e", base, list(1.0 + 0.05 * rng.random(7))).slower  # noise
    assert speed.judge("c", "e", base, [2 * x for x in base]).slower  # 2x, 7 vs 7 samples
    assert not speed.judge("c", "e", base, [1.4 * x for x in base]).slower  # under 1.5x
    three = speed.judge("c", "e", base[:3], [2 * x for x in base[:3]])
    assert three.judged and three.slower  # calibrated samples: 3 vs 3 have the power
    two = speed.judge("c", "e", base[:2], [3 * x for x in base[:2]])
    assert not two.judged and not two.slower  # no power: said so, never a silent pass
    assert "cannot judge speed: 2 -> 2 samples" in two.line()
    assert two.p == pytest.approx(1 / 6)  # the exact test's own p (was shown as 1.0)
    assert speed.judge("c", "e", base, [3 * base[0]]).judged is False  # 1 vs 7
    c = speed.judge("c", "e", base, base, {"steps": 70}, {"steps": 71})
    assert c.counters == {"steps": (70, 71)}  # a behaviour change, reported apart


def test_speed_rule_judges_cpu_time_where_both_sides_have_it():
    """Waiting for the core inflates wall time, not CPU time: with CPU samples on both
    sides they are judged (a doubled wall time from a busy core is no slowdown); a real
    slowdown doubles both."""
    base, cpu = [1.0, 1.01, 1.02, 0.99, 1.0], [0.9, 0.91, 0.92, 0.89, 0.9]
    busy = speed.judge("c", "e", base, [2 * x for x in base], base_cpu=cpu, new_cpu=cpu)
    assert busy.clock == "cpu" and not busy.slower and busy.ratio == 1.0
    real = speed.judge("c", "e", base, [2 * x for x in base], base_cpu=cpu,
                       new_cpu=[2 * x for x in cpu])
    assert real.clock == "cpu" and real.slower
    assert speed.judge("c", "e", base, [2 * x for x in base], base_cpu=cpu).clock == "wall"


def _folder(tmp_path: Path, name: str, cases, engines=("natcoord",), repeats=7) -> Path:
    out = tmp_path / name
    summary = run_suite(cases, list(engines), out, references=REFERENCES)
    result = bench.bench(cases, list(engines), repeats=repeats)
    bench.store(result, out)
    return out, summary, result


def _doctored(src: Path, dst: Path, edit) -> Path:
    """A copy of results folder ``src`` whose bench records are changed by ``edit``: speed
    figures made from stored data, never timed on the fly, so a verdict on them does not
    depend on the machine's load."""
    shutil.copytree(src, dst)
    data = read_json(dst / "bench.json")
    for r in data["records"]:
        edit(r)
    write_json(dst / "bench.json", data)
    return dst


def _scaled(k):
    def edit(r):
        for key in ("samples_s", "cpu_samples_s"):
            r[key] = [k * s for s in r[key]]
    return edit


@pytest.fixture(scope="module")
def pendulum_folder(tmp_path_factory):
    """One real run + bench of pendulum in natcoord (7 calibrated samples)."""
    tmp = tmp_path_factory.mktemp("nightly")
    return _folder(tmp, "a", [load_case(CASES / "pendulum.toml")])


def test_compare_unchanged_runs_exit_0_and_doctored_samples_exit_4(tmp_path, pendulum_folder):
    """Deterministic: the unchanged run is a copy of the timed one (same samples), the slow
    one the same samples tripled (the judged CPU times as well as the wall times)."""
    a, *_ = pendulum_folder
    rec = read_json(a / "bench.json")["records"][0]
    assert len(rec["samples_s"]) == len(rec["cpu_samples_s"]) == 7, rec
    same = _doctored(a, tmp_path / "same", lambda r: None)
    p = _cli("compare", a, same)
    assert p.returncode == 0 and "cannot judge" not in p.stderr, p.stderr
    slow = _doctored(a, tmp_path / "slow", _scaled(3))
    p = _cli("compare", a, slow)
    assert p.returncode == 4 and "pendulum/natcoord: SLOWER" in p.stderr, p.stderr
    assert "cpu time" in p.stderr
    j = _cli("compare", a, slow, "--json")
    assert j.returncode == 4 and json.loads(j.stdout)["slower"][0]["case"] == "pendulum"


def test_compare_says_it_cannot_judge_speed_on_too_few_samples(tmp_path, pendulum_folder):
    """Two samples a side cannot reach p <= 0.05: even tripled, compare says "cannot judge
    speed" (text and JSON) instead of passing silently; folders without bench.json say why
    speed is absent."""
    a, *_ = pendulum_folder

    def cut(k):
        def edit(r):
            for key in ("samples_s", "cpu_samples_s"):
                r[key] = [k * s for s in r[key][:2]]
        return edit

    few = _doctored(a, tmp_path / "few", cut(1))
    slow = _doctored(a, tmp_path / "slow", cut(3))
    p = _cli("compare", few, slow)
    assert p.returncode == 0, p.stderr
    assert "pendulum/natcoord: cannot judge speed: 2 -> 2 samples" in p.stderr, p.stderr
    j = json.loads(_cli("compare", few, slow, "--json").stdout)
    (un,) = j["cannot_judge_speed"]
    assert (un["case"], un["n_base"], un["n_new"], un["judged"]) == ("pendulum", 2, 2, False)
    assert j["rows"][0]["speed_judged"] is False
    bare = tmp_path / "run-only"
    shutil.copytree(a, bare)
    (bare / "bench.json").unlink()
    p = _cli("compare", a, bare)
    assert p.returncode == 0 and "speed not compared: no bench.json in" in p.stderr, p.stderr


def test_compare_a_heavier_mass_is_an_accuracy_regression(tmp_path):
    case = load_case(CASES / "pendulum.toml")
    heavier = tmp_path / "cases"
    heavier.mkdir()
    text = (CASES / "pendulum.toml").read_text().replace("mass = 1.0", "mass = 1.01")
    (heavier / "pendulum.toml").write_text(text)
    a = tmp_path / "a"
    run_suite([case], ["natcoord"], a, references=REFERENCES)
    b = tmp_path / "b"
    run_suite([load_case(heavier / "pendulum.toml")], ["natcoord"], b, references=REFERENCES)
    p = _cli("compare", a, b)
    assert p.returncode == 1 and "O_y" in p.stderr, p.stderr


def test_compare_refuses_bad_input(tmp_path):
    (tmp_path / "a").mkdir()
    p = _cli("compare", tmp_path / "a", tmp_path / "a")
    assert p.returncode == 2 and "no summary" in p.stderr


def test_history_records_runs_and_two_writers_lose_nothing(tmp_path):
    db = tmp_path / "history.db"
    summary = {"generated": "now", "natcoord_version": "x", "machine": {"fingerprint": "m"},
               "records": [{"case": "c", "engine": "e", "status": "ok", "verdict": "pass",
                            "channels": {"x": {"max_abs": 1e-9, "max_rel": 1e-9,
                                               "tolerance": 1e-8, "kind": "position"}}}]}
    result = {"machine": {"fingerprint": "m"}, "records": [
        {"case": "c", "engine": "e", "case_hash": "h", "samples_s": [1.0, 1.1]}]}
    errors = []

    def writer():
        try:
            for _ in range(20):
                history.record(db, kind="suite", summary=summary, bench=result, gate=0)
        except Exception as e:  # pragma: no cover - the failure this test looks for
            errors.append(e)

    threads = [threading.Thread(target=writer) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    with history.connect(db) as con:
        assert con.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 40
        assert con.execute("SELECT COUNT(*) FROM results").fetchone()[0] == 40
        assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    samples, _ = history.past_samples(db, "c", "e", "h", "m", last=3)
    assert samples == [1.0, 1.1] * 3
    assert history.past_samples(db, "c", "e", "other case file", "m")[0] == []
    assert history.trends(db)["c/e"]["worst_rel"][-1] == 1e-9


def test_history_jsonl_is_imported_once(tmp_path):
    jl = tmp_path / "history.jsonl"
    jl.write_text(json.dumps({"generated": "g", "natcoord_version": "0", "gate": 0,
                              "runs": {"pendulum/natcoord": {"status": "ok",
                                                             "verdict": "pass",
                                                             "worst_rel": 1e-9}}}) + "\n{torn")
    db = tmp_path / "history.db"
    assert history.import_jsonl(db, jl) == 1
    assert history.import_jsonl(db, jl) == 0
    assert history.trends(db)["pendulum/natcoord"]["worst_rel"] == [1e-9]


def test_gate_judges_speed_against_history(tmp_path, pendulum_folder):
    """A copy of a recorded run passes the speed gate against the history of the same case
    file on this machine, its samples tripled give exit 4, and too few samples are said to
    be unjudged (deterministic: no sample is timed for the verdicts)."""
    a, summary, result = pendulum_folder
    db = tmp_path / "history.db"
    empty = _cli("gate", "--results", a, "--history", db)
    assert empty.returncode == 0, empty.stderr
    assert "speed not judged for 1 cell(s): no earlier benchmark" in empty.stderr
    history.record(db, kind="suite", summary=summary, bench=result, gate=0,
                   results_dir=str(a.resolve()))
    b = _doctored(a, tmp_path / "b", lambda r: None)
    p = _cli("gate", "--results", b, "--history", db)
    assert p.returncode == 0 and "cannot judge" not in p.stderr, p.stderr
    slow = _doctored(a, tmp_path / "slow", _scaled(3))
    p = _cli("gate", "--results", slow, "--history", db)
    assert p.returncode == 4 and "SLOWER" in p.stderr, p.stderr

    def one(r):
        for key in ("samples_s", "cpu_samples_s"):
            r[key] = r[key][:1]
    lone = _doctored(a, tmp_path / "lone", one)
    p = _cli("gate", "--results", lone, "--history", db)
    assert p.returncode == 0 and "cannot judge speed: 7 -> 1 samples" in p.stderr, p.stderr



def test_compare_two_benchmark_folders_compares_speed_and_says_accuracy_was_not(
        tmp_path, pendulum_folder):
    """`compare` on two folders that hold only bench.json (what `natcoord bench --out`
    writes) used to exit 2 for want of a summary: the speed is compared (a tripled copy
    exits 4) and the output says why there is no accuracy."""
    a, *_ = pendulum_folder
    def bench_only(dst: Path, edit) -> Path:
        _doctored(a, dst, edit)
        for p in list(dst.iterdir()):
            if p.name != "bench.json":
                shutil.rmtree(p) if p.is_dir() else p.unlink()
        return dst
    same = bench_only(tmp_path / "same", lambda r: None)
    slow = bench_only(tmp_path / "slow", _scaled(3))
    base = bench_only(tmp_path / "base", lambda r: None)
    p = _cli("compare", base, same)
    assert p.returncode == 0 and "accuracy not compared" in p.stderr, p.stderr
    p = _cli("compare", base, slow)
    assert p.returncode == 4 and "SLOWER" in p.stderr, p.stderr

def test_ci_summary_is_markdown_with_verdicts():
    summary = {"records": [{"case": "c", "engine": "e", "status": "ok", "verdict": "fail",
                            "verdict_reason": "1 of 2 gated channels over tolerance"}]}
    text = diff.markdown(summary, 1, [], "reports/latest/index.html")
    assert text.startswith("## natcoord suite: accuracy regression (exit 1)")
    assert "`c/e`: 1 of 2 gated channels over tolerance" in text


def test_ci_summary_of_a_skipped_required_engine_is_not_nothing_ran():
    """82 cells passed and one required engine was skipped: the heading says a required
    cell did not run (not "not run"), and the gate's line says which."""
    records = [{"case": f"c{i}", "engine": "e", "status": "ok", "verdict": "pass"}
               for i in range(82)]
    records.append({"case": "c0", "engine": "dart", "status": "skipped",
                    "reason": "dartpy is not installed"})
    line = "c0/dart: required engine skipped: dartpy is not installed"
    text = diff.markdown({"records": records}, 3, [], "index.html", [line])
    assert text.startswith("## natcoord suite: incomplete: a required cell did not run "
                           "(exit 3)")
    assert "| pass | 82 |" in text and f"- {line}" in text
    none = diff.markdown({"records": records[-1:]}, 3, [], "index.html", [])
    assert none.startswith("## natcoord suite: nothing ran (exit 3)")


def test_platform_floors_scale_a_zero_channel_by_its_unit():
    """A channel that is zero throughout (a point held in a plane) takes the size of the
    case's largest channel of the same unit; the floor grows as sqrt(steps)."""
    case = load_case(CASES / "four_bar.toml")
    ref = pd.read_csv(REFERENCES / "four_bar.csv")
    metres = [c.name for c in case.channels if c.unit == "m"]
    zero = ref.copy()
    zero[metres[0]] = 0.0
    f1, f100 = (propose.platform_floors(case, zero, n) for n in (1, 100))
    biggest = max(np.abs(zero[m]).max() for m in metres)
    assert f1[metres[0]] == pytest.approx(100 * 8 * np.finfo(float).eps * biggest)
    assert f100[metres[0]] == pytest.approx(10 * f1[metres[0]])


def _tables(out: Path) -> dict:
    return {p.relative_to(out).as_posix(): pd.read_csv(p)
            for p in sorted((out / "results").rglob("*.csv"))}


def test_parallel_and_dask_runs_give_the_local_results(tmp_path):
    """The same cells run one at a time, two at a time, and on a Dask LocalCluster: the
    same statuses and the same numbers (each run is the same engine process)."""
    from distributed import LocalCluster

    cases = [load_case(CASES / "pendulum.toml"), load_case(CASES / "slider_crank.toml")]
    engines = ["natcoord", "exudyn"]
    serial = run_suite(cases, engines, tmp_path / "serial", references=REFERENCES)
    two = run_suite(cases, engines, tmp_path / "two", references=REFERENCES, jobs=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        dask = run_suite(cases, engines, tmp_path / "dask", references=REFERENCES,
                         scheduler=cluster.scheduler_address)
    key = [(r["case"], r["engine"], r["status"], r["verdict"]) for r in serial["records"]]
    for other in (two, dask):
        assert [(r["case"], r["engine"], r["status"], r["verdict"])
                for r in other["records"]] == key
    a = _tables(tmp_path / "serial")
    for folder in ("two", "dask"):
        b = _tables(tmp_path / folder)
        assert a.keys() == b.keys()
        for k in a:
            assert np.array_equal(a[k].to_numpy(), b[k].to_numpy()), (folder, k)


def test_an_unreachable_scheduler_is_a_clear_error(tmp_path):
    p = _cli("run", "pendulum", "--engines", "natcoord", "--scheduler", "tcp://127.0.0.1:9",
             "--out", tmp_path / "r", timeout=300)
    assert p.returncode == 2 and "cannot reach the Dask scheduler" in p.stderr, p.stderr


def test_a_scheduler_without_a_worker_is_a_clear_error(tmp_path):
    """A scheduler no worker serves: refused once no worker came within the connection
    wait, not after every run's deadline (130 s for one 10 s run); nothing written."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=True, dashboard_address=None) as cluster:
        p = _cli("run", "pendulum", "--engines", "natcoord", "--timeout", "10", "--scheduler",
                 cluster.scheduler_address, "--out", tmp_path / "r", timeout=300)
    assert p.returncode == 2 and "the Dask scheduler has no worker (waited 30 s)" in \
        p.stderr, p.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("command", [["run"], ["suite", "--quick", "--history", "h.db"]],
                         ids=lambda c: c[0])
def test_a_scheduler_that_is_no_address_is_bad_input(tmp_path, command):
    """Dask's parser refused the address with a ValueError: exit 1 and a traceback."""
    command = [tmp_path / a if a == "h.db" else a for a in command]
    p = _cli(*command, "pendulum", "--engines", "natcoord", "--scheduler", "notaurl",
             "--out", tmp_path / "r", timeout=300)
    assert p.returncode == 2, p.stderr[-1500:]
    assert "--scheduler 'notaurl': not a Dask scheduler address" in p.stderr, p.stderr
    assert "Traceback" not in p.stdout + p.stderr and not (tmp_path / "r").exists()


def test_a_lost_dask_task_fails_its_cell(tmp_path, monkeypatch):
    """A task whose Dask worker dies with it: the cell is failed with the reason; the
    command does not hang."""
    from distributed import LocalCluster

    (tmp_path / "tmp").mkdir()  # what the killed worker cannot remove is left here
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))

    from natcoord.suite import parallel, runner

    slow = (CASES / "pendulum.toml").read_text().replace(
        "duration = 10.0", "duration = 999.0").replace("output_dt = 0.01", "output_dt = 1.0")
    slow = slow.replace("[engines.natcoord]\n", '[engines.natcoord]\nsettings = { method = '
                        '"rk4", h = 1e-4, formulation = "index1", compiled = false }\n', 1)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "pendulum.toml").write_text(slow)
    job = runner.prepare(load_case(tmp_path / "c" / "pendulum.toml"))  # Python loop: minutes
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        gen = parallel.distributed([job], ["natcoord"], tmp_path, 10.0,
                                   cluster.scheduler_address, runner._failed, margin_s=20.0)
        import time
        t0 = time.time()
        pids = [w.process.process.pid for w in cluster.workers.values()]
        killer = threading.Thread(target=lambda: (time.sleep(3.0), [
            os.kill(pid, 9) for pid in pids]))
        killer.start()
        out = list(gen)
        killer.join()
    assert time.time() - t0 < 120
    (i, rec), = out
    assert rec["status"] == "failed" and rec["reason"], rec  # lost, retried, timed out


def test_propose_calls_a_sweep_converged_only_when_its_error_falls():
    """A last error a hair below the first (a flat sweep) was called converged, and its
    proposal went out without the note that the error does not fall."""
    sweep = lambda *errs: [{"setting": {}, "error": e} for e in errs]  # noqa: E731
    assert propose.converged(sweep(1e-3, 2e-4, 4e-5))
    assert not propose.converged(sweep(1e-3, 1e-3, 0.999e-3))  # flat
    assert not propose.converged(sweep(1e-3, 2e-3))  # grows
    assert propose.converged(sweep(3e-14, 4e-14, 3e-14))  # at round-off: nothing to fall
    assert not propose.converged(sweep(1e-3, float("nan")))
    assert not propose.converged(sweep(1e-3, None))  # one error is no sweep


def test_propose_measures_and_writes_tolerances_that_then_pass(tmp_path):
    """A new case without engine blocks: reference update, propose, paste, run, gate."""
    import tomllib

    text = (CASES / "four_bar.toml").read_text()
    text = text.replace('name = "four_bar"', 'name = "new_bar"')
    text = text[:text.index("[engines.")]
    cases, refs = tmp_path / "cases", tmp_path / "refs"
    cases.mkdir()
    (cases / "new_bar.toml").write_text(text)
    args = ("--cases-dir", cases, "--references", refs)
    assert _cli("reference", "update", "new_bar", *args).returncode == 0
    p = _cli("propose", "new_bar", "--engines", "natcoord,exudyn", "--out",
             tmp_path / "p.toml", *args)
    assert p.returncode == 0, p.stderr
    blocks = tomllib.loads((tmp_path / "p.toml").read_text())["engines"]
    assert set(blocks) == {"natcoord", "exudyn"}
    assert "first angle over its sweep" in blocks["exudyn"]["reason"]
    assert blocks["exudyn"]["tolerance"]["theta"] > 1e-6  # a second-order engine
    ref = pd.read_csv(refs / "new_bar.csv")  # never below the platform margin
    case = load_case(cases / "new_bar.toml")
    least = propose.platform_floors(case, ref, 1)
    for k, tol in blocks["natcoord"]["tolerance"].items():
        assert tol >= least[k] >= 100 * 8 * np.finfo(float).eps * np.abs(ref[k]).max(), k
    assert "x the run's round-off for" in blocks["natcoord"]["reason"]
    (cases / "new_bar.toml").write_text(text + "\n" + (tmp_path / "p.toml").read_text())
    run = _cli("run", "new_bar", "--engines", "natcoord,exudyn", "--out", tmp_path / "r", *args)
    assert run.returncode == 0 and "2 within tolerance" in run.stdout, run.stdout
    g = _cli("gate", "--results", tmp_path / "r", "--baseline", tmp_path / "b.json",
             "--update-baseline", *args)
    assert g.returncode == 0 and "baseline updated" in g.stdout
    assert set(json.loads((tmp_path / "b.json").read_text())["errors"]) == {
        "new_bar/natcoord", "new_bar/exudyn"}


def test_a_suite_stopped_once_published_is_recorded_and_says_so(tmp_path, monkeypatch):
    """A Ctrl-C once the night is published (here: as the history is written) used to end
    the command with "no results of this command published" while they were, and the
    history missed the night. Now the published night is finished whole: recorded, the
    gate's exit code, and a line saying when it was interrupted."""
    import signal

    from typer.testing import CliRunner

    from natcoord.cli import app

    real = history.record

    def interrupted(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # delivered to this (main) thread at once
        return real(*args, **kwargs)

    monkeypatch.setattr(history, "record", interrupted)
    db, out = tmp_path / "h.db", tmp_path / "night"
    before = signal.getsignal(signal.SIGINT)
    res = CliRunner().invoke(app, ["suite", "pendulum", "--engines", "natcoord", "--jobs",
                                   "1", "--repeats", "3", "--cases-dir", str(CASES),
                                   "--references", str(REFERENCES), "--history", str(db),
                                   "--out", str(out)])
    assert res.exit_code == 0, (res.output, res.exception)
    said = " ".join((res.output + res.stderr).split())
    assert "interrupted after the results were published: finished recording them" in said
    assert (out / "summary.json").is_file()
    with history.reading(db) as con:  # the night is in the history
        assert con.execute("SELECT COUNT(*) FROM runs").fetchone() == (1,)
    assert signal.getsignal(signal.SIGINT) is before  # the handlers given back
