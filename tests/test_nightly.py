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

from natcoord import load_case
from natcoord.suite import bench, diff, history, speed
from natcoord.suite.io import read_json, write_json
from natcoord.suite.runner import run_suite

from .conftest import CASES, REFERENCES


def _cli(*args, env=None, timeout=600):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def test_mann_whitney_rule_needs_factor_and_significance():
    rng = np.random.default_rng(0)
    base = list(1.0 + 0.05 * rng.random(7))
    assert not speed.judge("c", "e", base, list(1.0 + 0.05 * rng.random(7))).slower  # noise
    assert speed.judge("c", "e", base, [2 * x for x in base]).slower  # 2x, 7 vs 7 samples
    assert not speed.judge("c", "e", base, [1.2 * x for x in base]).slower  # under 1.25x
    assert not speed.judge("c", "e", base[:3], [3 * x for x in base[:3]]).slower  # no power
    c = speed.judge("c", "e", base, base, {"steps": 70}, {"steps": 71})
    assert c.counters == {"steps": (70, 71)}  # a behaviour change, reported apart


def _folder(tmp_path: Path, name: str, cases, engines=("natcoord",), repeats=7) -> Path:
    out = tmp_path / name
    summary = run_suite(cases, list(engines), out, references=REFERENCES)
    result = bench.bench(cases, list(engines), repeats=repeats)
    bench.store(result, out)
    return out, summary, result


def test_compare_unchanged_runs_exit_0_and_doctored_samples_exit_4(tmp_path):
    cases = [load_case(CASES / "pendulum.toml")]
    a, *_ = _folder(tmp_path, "a", cases)
    b, *_ = _folder(tmp_path, "b", cases)
    p = _cli("compare", a, b)
    assert p.returncode == 0, p.stderr
    slow = tmp_path / "slow"
    shutil.copytree(b, slow)
    data = read_json(slow / "bench.json")
    for r in data["records"]:
        r["samples_s"] = [3 * s for s in r["samples_s"]]
    write_json(slow / "bench.json", data)
    p = _cli("compare", a, slow)
    assert p.returncode == 4 and "pendulum/natcoord: SLOWER" in p.stderr, p.stderr
    j = _cli("compare", a, slow, "--json")
    assert j.returncode == 4 and json.loads(j.stdout)["slower"][0]["case"] == "pendulum"


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


def test_gate_judges_speed_against_history(tmp_path):
    """A doctored copy of a run whose natcoord samples are tripled gives exit 4 against the
    history of the same case file on this machine; the unchanged run passes."""
    cases = [load_case(CASES / "pendulum.toml")]
    a, summary, result = _folder(tmp_path, "a", cases)
    db = tmp_path / "history.db"
    history.record(db, kind="suite", summary=summary, bench=result, gate=0,
                   results_dir=str(a.resolve()))
    b, *_ = _folder(tmp_path, "b", cases)
    assert _cli("gate", "--results", b, "--history", db).returncode == 0
    data = read_json(b / "bench.json")
    for r in data["records"]:
        r["samples_s"] = [3 * s for s in r["samples_s"]]
    write_json(b / "bench.json", data)
    p = _cli("gate", "--results", b, "--history", db)
    assert p.returncode == 4 and "SLOWER" in p.stderr, p.stderr


def test_ci_summary_is_markdown_with_verdicts():
    summary = {"records": [{"case": "c", "engine": "e", "status": "ok", "verdict": "fail",
                            "verdict_reason": "1 of 2 gated channels over tolerance"}]}
    text = diff.markdown(summary, 1, [], "reports/latest/index.html")
    assert text.startswith("## natcoord suite: accuracy regression (exit 1)")
    assert "`c/e`: 1 of 2 gated channels over tolerance" in text


def _tables(out: Path) -> dict:
    import pandas as pd
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


def test_a_lost_dask_task_fails_its_cell(tmp_path):
    """A task whose Dask worker dies with it: the cell is failed with the reason; the
    command does not hang."""
    from distributed import LocalCluster

    from natcoord.suite import parallel, runner

    slow = (CASES / "pendulum.toml").read_text().replace(
        "duration = 10.0", "duration = 2000.0").replace("output_dt = 0.01", "output_dt = 1.0")
    slow = slow.replace("[engines.natcoord]\n", '[engines.natcoord]\nsettings = { method = '
                        '"rk4", h = 1e-4, formulation = "index1" }\n', 1)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "pendulum.toml").write_text(slow)
    job = runner.prepare(load_case(tmp_path / "c" / "pendulum.toml"))  # runs for minutes
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
    (cases / "new_bar.toml").write_text(text + "\n" + (tmp_path / "p.toml").read_text())
    run = _cli("run", "new_bar", "--engines", "natcoord,exudyn", "--out", tmp_path / "r", *args)
    assert run.returncode == 0 and "2 within tolerance" in run.stdout, run.stdout
    g = _cli("gate", "--results", tmp_path / "r", "--baseline", tmp_path / "b.json",
             "--update-baseline", *args)
    assert g.returncode == 0 and "baseline updated" in g.stdout
    assert set(json.loads((tmp_path / "b.json").read_text())["errors"]) == {
        "new_bar/natcoord", "new_bar/exudyn"}
