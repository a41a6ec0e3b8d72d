"""The runner, the comparison and the gate, end to end on natcoord runs (real solver runs,
no stand-ins): the gate must fire on injected regressions, and a killed engine must not
take the suite down."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

from natcoord import load_case
from natcoord.suite import gate
from natcoord.suite.io import read_json, write_csv
from natcoord.suite.runner import compare_record, run_suite

from .conftest import CASES, REFERENCES


def _gate(out: Path, summary: dict | None = None, cases: Path = CASES, **kw) -> gate.Verdict:
    """The gate's verdict on a results folder, judged from its files."""
    return gate.judge(summary or gate.load_summary(out), out, cases=gate.CaseBook(cases),
                      references=REFERENCES, **kw)


@pytest.fixture(scope="module")
def baseline_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    cases = [load_case(CASES / "slider_crank.toml"), load_case(CASES / "four_bar.toml")]
    summary = run_suite(cases, ["natcoord"], out, references=REFERENCES)
    return out, summary


def test_clean_run_passes(baseline_run):
    out, summary = baseline_run
    assert [r["verdict"] for r in summary["records"]] == ["pass", "pass"]
    assert _gate(out).code == gate.OK
    assert (out / "results" / "slider_crank" / "natcoord.csv").exists()
    df = pd.read_csv(out / "results" / "slider_crank" / "natcoord.csv")
    assert list(df.columns)[:3] == ["t", "theta", "xB"]


def test_gate_fires_on_a_one_percent_mass_change(case_variant, tmp_path):
    """A copy of slider_crank with the slider 1% heavier must fail against the reference."""
    path = case_variant("slider_crank", [(r'mass = 1.0\npoints = \{ B = ', 'mass = 1.01\n'
                                          'points = { B = ')])
    out = tmp_path / "out"
    run_suite([load_case(path)], ["natcoord"], out, references=REFERENCES)
    v = _gate(out)
    assert v.code == gate.REGRESSION
    assert any("slider_crank/natcoord: theta max error" in line for line in v.lines), v.lines


def test_gate_fires_on_a_flipped_sign(baseline_run, tmp_path):
    """Flip the sign of one reaction channel in a result file: exit 1, naming the channel."""
    out, summary = baseline_run
    case = load_case(CASES / "four_bar.toml")
    csv = out / "results" / "four_bar" / "natcoord.csv"
    df = pd.read_csv(csv)
    df["D_y"] = -df["D_y"]
    flipped = tmp_path / "results" / "four_bar" / "natcoord.csv"
    write_csv(flipped, df)
    record = next(r for r in summary["records"] if r["case"] == "four_bar")
    rec = compare_record(case, record, tmp_path, REFERENCES)  # as a run would record it
    v = _gate(tmp_path, {"records": [rec]})
    assert v.code == gate.REGRESSION
    assert any("D_y" in line for line in v.lines)
    assert v.channels["four_bar/natcoord"]["D_x"]["pass"] is True  # only D_y fails


def test_gate_exit_codes_for_bad_input_and_nothing_run(tmp_path, baseline_run):
    with pytest.raises(ValueError, match="no summary"):
        gate.load_summary(tmp_path)
    (tmp_path / "summary.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        gate.load_summary(tmp_path)
    out, summary = baseline_run
    dead = {"records": [{**r, "status": "failed", "channels": {}, "verdict": "n/a"}
                        for r in summary["records"]]}
    assert _gate(out, dead).code == gate.NOT_RUN


def test_gate_cli_exit_codes(tmp_path, baseline_run):
    out, _ = baseline_run
    run = [sys.executable, "-m", "natcoord.cli", "gate", "--baseline",
           str(tmp_path / "none.json")]
    assert subprocess.run(run + ["--results", str(out)], capture_output=True).returncode == 0
    r = subprocess.run(run + ["--results", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "no summary" in r.stderr and "Traceback" not in r.stderr


def test_baseline_growth_is_a_regression(baseline_run, tmp_path):
    out, _ = baseline_run
    base = _gate(out).errors
    shrunk = {k: {n: e / 1e6 for n, e in v.items()} for k, v in base.items()}
    # errors far below a tenth of the tolerance never count as growth (platform noise)
    assert _gate(out, baseline=shrunk).code == gate.OK
    # the case file's tolerances tightened to twice the errors: growth now counts
    tight = tmp_path / "cases"
    tight.mkdir()
    for name in ("slider_crank", "four_bar"):
        text = (CASES / f"{name}.toml").read_text()
        block = text.index("[engines.natcoord.tolerance]")
        end = text.index("\n\n", block)
        worst = {}
        for c in _gate(out).channels[f"{name}/natcoord"].values():
            if c["pass"] is not None:
                worst[c["kind"]] = max(worst.get(c["kind"], 0.0), c["max_abs"])
        text = (text[:block] + "[engines.natcoord.tolerance]\n"
                + "".join(f"{k} = {2 * e:.3e}\n" for k, e in worst.items()) + text[end:])
        (tight / f"{name}.toml").write_text(text)
    v = _gate(out, cases=tight, baseline=shrunk)
    assert v.code == gate.REGRESSION and any("over the baseline" in line for line in v.lines)


def _kill_worker_when_started(engine: str, stop: threading.Event):
    """Find the worker process of ``engine`` in /proc and SIGKILL it once it runs."""
    while not stop.is_set():
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            line = b" ".join(cmd)  # the job file is results/<case>/.<engine>.job.pkl
            if b"natcoord.suite.worker" in cmd and f".{engine}.job".encode() in line \
                    and b"four_bar" in line:
                time.sleep(0.3)  # mid-run: after imports, while it integrates
                os.kill(int(pid), signal.SIGKILL)
                return
        time.sleep(0.01)


def test_killed_engine_is_failed_and_the_suite_completes(tmp_path):
    cases = [load_case(CASES / "four_bar.toml"), load_case(CASES / "slider_crank.toml")]
    stop = threading.Event()
    killer = threading.Thread(target=_kill_worker_when_started, args=("natcoord", stop))
    killer.start()
    try:
        summary = run_suite(cases, ["natcoord"], tmp_path, references=REFERENCES)
    finally:
        stop.set()
        killer.join()
    by_case = {r["case"]: r for r in summary["records"]}
    assert by_case["four_bar"]["status"] == "failed"
    assert "SIGKILL" in by_case["four_bar"]["reason"]
    assert by_case["slider_crank"]["status"] == "ok"
    assert not (tmp_path / "results" / "four_bar" / "natcoord.csv").exists()
    assert read_json(tmp_path / "summary.json")["records"][1]["verdict"] == "pass"


def test_time_limit_kills_a_slow_engine(tmp_path):
    case = load_case(CASES / "four_bar.toml")
    summary = run_suite([case], ["natcoord"], tmp_path, references=REFERENCES,
                        timeout_s=0.5)
    rec = summary["records"][0]
    assert rec["status"] == "failed" and "timed out after 0.5 s" in rec["reason"]


def test_work_precision_reports_each_natcoord_formulation_apart():
    """time_to_accuracy keeps one row per formulation (the cheapest point at or below each
    target), and the natcoord sweep covers index1 (adaptive and fixed step), maggi, index3."""
    from natcoord.suite import bench

    assert {bench.variant(s) for s in bench.SWEEPS["natcoord"]} == {
        "index1 dop853", "index1 rk4", "maggi dop853", "index3 trapezoidal"}
    pts = [
        {"case": "c", "engine": "natcoord", "variant": "index1 dop853", "error": 5e-7,
         "wall_time_s": 2.0},
        {"case": "c", "engine": "natcoord", "variant": "index1 dop853", "error": 5e-10,
         "wall_time_s": 3.0},
        {"case": "c", "engine": "natcoord", "variant": "index3 trapezoidal", "error": 2e-6,
         "wall_time_s": 1.0},
        {"case": "c", "engine": "mujoco", "variant": "", "error": 9e-7, "wall_time_s": 40.0},
    ]
    rows = {r["engine"]: r for r in bench.time_to_accuracy(pts)}
    assert rows["natcoord (index1 dop853)"]["time_to_1e-06"] == 2.0
    assert rows["natcoord (index1 dop853)"]["time_to_1e-09"] == 3.0
    assert rows["natcoord (index3 trapezoidal)"]["time_to_1e-06"] is None
    assert rows["mujoco"]["time_to_1e-06"] == 40.0 and rows["mujoco"]["time_to_1e-09"] is None


def test_time_to_accuracy_is_also_interpolated_on_the_sweeps_curve():
    """Between the cheapest point under the target and the costliest point over it, log
    time is linear in log error; a curve that starts under the target, or never reaches
    it, has no interpolated time."""
    import math

    from natcoord.suite import bench

    def row(points, target=1e-6):
        pts = [{"case": "c", "engine": "e", "error": e, "wall_time_s": w} for w, e in points]
        (r,) = bench.time_to_accuracy(pts, targets=(target,))
        return r[f"time_to_{target:g}"], r[f"interpolated_time_to_{target:g}"]

    # half way down in log error (1e-5 -> 1e-7): half way up in log time (1 -> 2 s)
    assert row([(1.0, 1e-5), (2.0, 1e-7), (4.0, 1e-9)]) == (2.0, pytest.approx(math.sqrt(2.0)))
    # an erratic curve: the bracket is the costliest point over the target
    w, wi = row([(1.0, 1e-5), (1.5, 3e-5), (2.0, 1e-7), (0.5, 1e-3)])
    f = math.log(30.0) / math.log(300.0)
    assert w == 2.0 and wi == pytest.approx(1.5 * (2.0 / 1.5) ** f, rel=1e-12)
    assert 1.5 < wi < 2.0
    assert row([(1.0, 1e-7), (2.0, 1e-9)]) == (1.0, None)  # nothing swept over 1e-6
    assert row([(1.0, 1e-5), (2.0, 1e-5)]) == (None, None)  # never reached
    assert row([(1.0, 1e-5), (2.0, 1e-6)]) == (2.0, pytest.approx(2.0))  # on a point: its time


def test_work_precision_times_each_point_like_a_bench_cell(monkeypatch):
    """A sweep point runs once in a fresh process and then repeats in a second one (real
    natcoord runs); its wall time is the best of every repeat, and its error is measured
    against the stored reference."""
    from natcoord.suite import bench

    monkeypatch.setattr(bench, "SWEEPS", {"natcoord": [
        {"formulation": "index1", "method": "dop853", "h": None, "rtol": 1e-8, "atol": 1e-10}]})
    case = load_case(CASES / "slider_crank.toml")
    (pt,) = bench.work_precision([case], ["natcoord"], references=REFERENCES, repeats=3)
    assert pt["status"] == "ok" and pt["repeats"] == 3
    assert 0 < pt["error"] < 1e-6  # rtol 1e-8 on the crank angle, against the reference
    assert 0 < pt["wall_time_s"] < 1.0
