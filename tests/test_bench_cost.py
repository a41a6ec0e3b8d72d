"""The bench's cost explained (fixed cost, per step, per right-hand side; natcoord's cold
start) and the IFToMM-style scoring (a case's [benchmark]: error and time to precision).
Figures are checked for their structure and signs, never against a timing."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from natcoord.case.casefile import load_case
from natcoord.errors import CaseError
from natcoord.suite import bench
from natcoord.suite.worker import truncated

from .conftest import CASES, REFERENCES, ROOT

BLOCK = '\n[benchmark]\nchannels = ["x", "y"]\nprecision = "1 mm"\nsource = "test"\n'


# ---------------------------------------------------------------- the cost fit


def test_cost_fit_recovers_a_line():
    fixed, slope = bench.cost_fit([(250, 0.5 + 250 * 2e-3), (1000, 0.5 + 1000 * 2e-3)])
    assert fixed == pytest.approx(0.5) and slope == pytest.approx(2e-3)
    # three points, least squares
    xs = np.array([100.0, 400.0, 1600.0])
    fixed, slope = bench.cost_fit(list(zip(xs, 0.1 + 1e-3 * xs + [1e-3, -2e-3, 1e-3],
                                           strict=True)))
    assert fixed == pytest.approx(0.1, abs=3e-3) and slope == pytest.approx(1e-3, rel=3e-3)


def test_cost_fit_never_returns_a_negative_fixed_cost():
    # the shorter run measured relatively slow: a free line would cross below zero
    fixed, slope = bench.cost_fit([(250, 0.2), (1000, 1.0)])
    x, w = np.array([250.0, 1000.0]), np.array([0.2, 1.0])
    assert fixed == 0.0 and slope == pytest.approx(x @ w / (x @ x))


def test_cost_fit_undetermined_is_none():
    assert bench.cost_fit([(1000, 1.0), (1000, 0.9)]) is None  # one distinct x
    assert bench.cost_fit([(250, 1.1), (1000, 1.0)]) is None  # shorter run not cheaper
    assert bench.cost_fit([(250, float("nan")), (1000, 1.0)]) is None


def test_explain_cost_from_full_and_truncated_runs():
    full = {"samples_s": [1.1, 1.0, 1.2], "n_steps": 1000, "duration_s": 10.0,
            "counters": {"steps": 1000, "rhs": 4001}}
    short = {"samples_s": [0.4, 0.3], "n_steps": 250, "duration_s": 2.5,
             "counters": {"steps": 250, "rhs": 1001}}
    c = bench.explain_cost(full, short)
    slope = (1.0 - 0.3) / 750  # best of each duration
    assert c["per_step_us"] == pytest.approx(1e6 * slope)
    assert c["fixed_s"] == pytest.approx(1.0 - 1000 * slope)
    assert c["per_rhs_us"] == pytest.approx(1e6 * 0.7 / 3000)
    pts = c["cost_fit"]["points"]
    assert [p["duration_s"] for p in pts] == [10.0, 2.5]
    assert [p["repeats"] for p in pts] == [3, 2] and c["cost_fit"]["determined"]
    # an engine that does not count right-hand sides: no per-rhs figure
    no_rhs = bench.explain_cost({**full, "counters": {}}, {**short, "counters": {}})
    assert no_rhs["per_rhs_us"] is None and no_rhs["per_step_us"] == c["per_step_us"]
    # no truncated runs: nothing fitted
    assert bench.explain_cost(full, None) == {"fixed_s": None, "per_step_us": None,
                                              "per_rhs_us": None}


def test_truncated_case_keeps_everything_but_the_duration():
    case = load_case(CASES / "pendulum.toml")
    q = truncated(case, 0.25)
    assert q.duration == pytest.approx(2.5) and len(q.times) == 251
    assert np.allclose(q.times, case.times[:251])
    assert q.bodies == case.bodies and q.engines == case.engines
    assert truncated(case, 1e-9).duration == pytest.approx(case.output_dt)  # one interval


# ---------------------------------------------------------------- [benchmark] in a case file


def test_benchmark_tables_of_the_catalogue_load():
    expect = {"a01_pendulum": (("x", "y"), "max_abs"),
              "a02_four_bar_n2": (("x_B0", "y_B0"), "max_abs"),
              "a03_andrews": (("beta", "theta", "gamma", "phi", "delta", "omega", "epsilon"),
                              "final_abs"),
              "a04_bricard": (("xP3", "yP3", "zP3"), "max_abs"),
              "a05_flyball_governor": (("s",), "max_abs"),
              "slider_crank_3d": (("xC",), "max_abs")}
    for name, (channels, error) in expect.items():
        b = load_case(CASES / f"{name}.toml").benchmark
        assert b["channels"] == channels and b["error"] == error, name
        assert b["precision"] == 1e-3 and "IFToMM" in b["source"], name
    assert load_case(CASES / "pendulum.toml").benchmark == {}


@pytest.mark.parametrize("block, field, words", [
    (BLOCK.replace('["x", "y"]', '["x", "nope"]'), "benchmark.channels[1]", "unknown channel"),
    (BLOCK.replace('["x", "y"]', '["x", "x"]'), "benchmark.channels[1]", "listed twice"),
    (BLOCK.replace('["x", "y"]', '["x", "O_y"]'), "benchmark.channels", "one unit"),
    (BLOCK.replace('["x", "y"]', "[]"), "benchmark.channels", "non-empty list"),
    (BLOCK.replace('"1 mm"', "-1e-3"), "benchmark.precision", "positive"),
    (BLOCK.replace('"1 mm"', '"1 rad"'), "benchmark.precision", "expected a length"),
    (BLOCK.replace('"1 mm"', '"fine"'), "benchmark.precision", "cannot read"),
    (BLOCK + 'error = "rms"\n', "benchmark.error", "unknown value"),
    (BLOCK + 'tolerance = 1\n', "benchmark.tolerance", "unknown field"),
    (BLOCK.replace('source = "test"\n', ""), "benchmark.source", "missing"),
])
def test_bad_benchmark_table_is_refused_with_its_field(tmp_path, block, field, words):
    path = tmp_path / "pendulum.toml"
    path.write_text((CASES / "pendulum.toml").read_text() + block)
    with pytest.raises(CaseError) as e:
        load_case(path)
    assert f": {field}:" in str(e.value) and words in str(e.value), str(e.value)


def test_benchmark_table_reads_units(tmp_path):
    path = tmp_path / "pendulum.toml"
    path.write_text((CASES / "pendulum.toml").read_text() + BLOCK)
    b = load_case(path).benchmark
    assert b == {"channels": ("x", "y"), "precision": pytest.approx(1e-3), "error": "max_abs",
                 "source": "test"}


# ---------------------------------------------------------------- the benchmark's error


def _case_with_benchmark(error: str):
    case = load_case(CASES / "pendulum.toml")
    return dataclasses.replace(case, benchmark={"channels": ("x", "y"), "precision": 1e-3,
                                                "error": error, "source": "test"})


def test_benchmark_error_max_over_samples_or_at_the_end(tmp_path):
    ref = pd.read_csv(REFERENCES / "pendulum.csv")
    run = ref.copy()
    run.loc[100, "y"] += 3e-4  # the largest deviation, mid-run
    run.loc[len(run) - 1, "x"] -= 1e-4  # a smaller one at the end
    csv = tmp_path / "run.csv"
    run.to_csv(csv, index=False)
    assert bench.benchmark_error(_case_with_benchmark("max_abs"), csv, REFERENCES) == (
        pytest.approx(3e-4, rel=1e-6))
    assert bench.benchmark_error(_case_with_benchmark("final_abs"), csv, REFERENCES) == (
        pytest.approx(1e-4, rel=1e-6))
    run.loc[5, "x"] = np.nan  # a diverged run is infinitely wrong, not unscored
    run.to_csv(csv, index=False)
    assert bench.benchmark_error(_case_with_benchmark("max_abs"), csv, REFERENCES) == np.inf
    assert bench.benchmark_error(_case_with_benchmark("max_abs"), tmp_path / "none.csv",
                                 REFERENCES) is None


def test_scoring_least_time_within_the_precision():
    case = _case_with_benchmark("max_abs")
    records = [
        {"case": "pendulum", "engine": "natcoord", "status": "ok", "benchmark_error": 2e-9,
         "wall_time_s": 0.02},
        {"case": "pendulum", "engine": "mujoco", "status": "ok", "benchmark_error": 5e-3,
         "wall_time_s": 0.5},
        {"case": "pendulum", "engine": "dart", "status": "ok", "benchmark_error": 2e-2,
         "wall_time_s": 0.1},
        {"case": "pendulum", "engine": "simbody", "status": "unsupported"},
    ]
    points = [  # natcoord: a cheaper sweep point within 1e-3 beats its case settings
        {"case": "pendulum", "engine": "natcoord", "setting": {"rtol": 1e-5},
         "benchmark_error": 4e-4, "wall_time_s": 0.005},
        {"case": "pendulum", "engine": "natcoord", "setting": {"rtol": 1e-3},
         "benchmark_error": 3e-3, "wall_time_s": 0.001},  # cheaper, not precise enough
        {"case": "pendulum", "engine": "mujoco", "setting": {"dt": 1e-4},
         "benchmark_error": 9e-4, "wall_time_s": 2.0},
        {"case": "pendulum", "engine": "mujoco", "setting": {"dt": 5e-5},
         "benchmark_error": 1e-4, "wall_time_s": 4.0},
        {"case": "pendulum", "engine": "dart", "setting": {"dt": 1e-4},
         "benchmark_error": 2e-3, "wall_time_s": 1.0},
    ]
    rows = {r["engine"]: r for r in bench.scoring([case], records, points)}
    assert rows["natcoord"]["time_to_precision"] == 0.005
    assert rows["natcoord"]["reached_by"] == "rtol=1e-05"
    assert rows["mujoco"]["time_to_precision"] == 2.0 and rows["mujoco"]["error"] == 5e-3
    assert rows["dart"]["time_to_precision"] is None  # not reached
    assert rows["dart"]["best_swept_error"] == 2e-3
    assert rows["simbody"]["time_to_precision"] is None and rows["simbody"]["error"] is None
    records[0]["benchmark_error"] = 1e-3  # at the precision counts as reached
    points[0]["benchmark_error"] = 2e-3
    rows = {r["engine"]: r for r in bench.scoring([case], records, points)}
    assert rows["natcoord"]["time_to_precision"] == 0.02
    assert rows["natcoord"]["reached_by"] == "case settings"
    assert bench.scoring([load_case(CASES / "pendulum.toml")], records, points) == []


# ---------------------------------------------------------------- a real bench


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory):
    """`natcoord bench pendulum --engines natcoord,pinocchio --json`: bench.json on stdout."""
    tmp = tmp_path_factory.mktemp("bench")
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bench", "pendulum", "--engines",
                        "natcoord,pinocchio", "--repeats", "3", "--json", "--out",
                        str(tmp / "out"), "--history", str(tmp / "hist")],
                       capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert p.returncode == 0, p.stderr
    result = json.loads(p.stdout)
    assert json.loads((tmp / "out" / "bench.json").read_text()) == result
    return result


def test_real_bench_explains_the_cost(tiny_bench):
    recs = {r["engine"]: r for r in tiny_bench["records"]}
    assert set(recs) == {"natcoord", "pinocchio"}
    for engine, r in recs.items():
        assert r["status"] == "ok", r
        assert r["fixed_s"] >= 0 and r["per_step_us"] > 0, (engine, r["cost_fit"])
        assert r["per_rhs_us"] > 0  # both count right-hand sides
        assert r["per_rhs_us"] < r["per_step_us"]  # several evaluations per step
        full, short = r["cost_fit"]["points"]
        assert full["duration_s"] == 10.0 and short["duration_s"] == pytest.approx(2.5)
        assert full["n_steps"] == r["n_steps"] == r["counters"]["steps"]
        assert short["n_steps"] < full["n_steps"] and short["rhs"] < full["rhs"]
        # 3 asked; fewer when a loaded machine makes them outgrow the cell's budget
        assert 1 <= full["repeats"] == short["repeats"] == len(r["samples_s"]) <= 3
        assert r["requested_repeats"] == 3
        assert full["wall_s"] == r["wall_time_s"] == min(r["samples_s"])
    # pinocchio's RK4 at dt 1e-3 over 10 s: 4 evaluations a step, exactly
    assert recs["pinocchio"]["n_steps"] == 10000
    assert recs["pinocchio"]["counters"]["rhs"] == 4 * 10000 + 1


def test_real_bench_cold_start_is_build_time(tiny_bench):
    c = tiny_bench["cold_start"]
    assert c["status"] == "ok" and c["case"] == "pendulum", c
    assert len(c["samples_s"]) == bench.COLD_REPEATS == len(c["parts"])
    assert c["build_time_s"] == min(c["samples_s"])
    # the whole process contains its import and its run
    assert c["build_time_s"] > c["import_s"] > 0 and c["kernel_load_s"] >= 0
    assert c["duration_s"] == pytest.approx(bench.COLD_SAMPLES * 0.01)
    best = c["parts"][int(np.argmin(c["samples_s"]))]
    assert best["n_steps"] > 0 and c["wall_time_s"] == best["wall_time_s"]


def test_an_unusable_kernel_cache_is_said_and_the_path_recorded(tmp_path, monkeypatch):
    """NATCOORD_CACHE_DIR a file: the generated kernels cannot be cached and natcoord runs
    its generic ('sparse') kernels, many times slower. That was silent, and the cold start
    said "kernels from cache": now a warning names the variable and the problem, once,
    and the natcoord record (and the cold start) carry the compiled path that ran."""
    from natcoord.compiled import codegen

    afile = tmp_path / "afile"
    afile.write_text("x")
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bench", "pendulum", "--engines",
                        "natcoord", "--repeats", "1", "--out", str(tmp_path / "out"),
                        "--history", str(tmp_path / "hist")], capture_output=True, text=True,
                       cwd=ROOT, timeout=900, env={**os.environ,
                                                   "NATCOORD_CACHE_DIR": str(afile)})
    assert p.returncode == 0, p.stderr
    said = (f"warning: NATCOORD_CACHE_DIR={afile}: not a writable folder ({afile} is a "
            "file): the generated kernels cannot be cached; natcoord runs its generic "
            "kernels (slower)")
    assert " ".join(p.stderr.split()).count(said) == 1, p.stderr
    assert "from cache" not in p.stdout and "(sparse path" in p.stdout, p.stdout
    result = json.loads((tmp_path / "out" / "bench.json").read_text())
    assert result["records"][0]["path"] == "sparse" == result["cold_start"]["path"]
    monkeypatch.setenv("NATCOORD_CACHE_DIR", str(tmp_path / "new" / "cache"))
    assert codegen.cache_problem() is None  # a folder that can be made is fine
    monkeypatch.setattr(os, "access", lambda *a, **k: False)  # read-only (root writes any)
    assert codegen.cache_problem().startswith("not a writable folder")


# ---------------------------------------------------------------- the report


def test_report_shows_cost_cold_start_and_scoring(tmp_path):
    from natcoord.report import write_report

    from .test_report import make_results

    out, refs = make_results(tmp_path)
    data = json.loads((out / "bench.json").read_text())
    for r in data["records"]:
        r |= bench.explain_cost(
            {"samples_s": [1.0], "n_steps": 1000, "duration_s": 10.0,
             "counters": {"rhs": 4000}},
            {"samples_s": [0.4], "n_steps": 250, "duration_s": 2.5, "counters": {"rhs": 1000}})
        r["status"] = "ok"
    data["cold_start"] = {"case": "pendulum", "status": "ok", "duration_s": 0.1,
                          "samples_s": [1.6, 2.0], "build_time_s": 1.6, "import_s": 0.9,
                          "kernel_load_s": 0.2, "wall_time_s": 5e-4}
    data["scoring"] = bench.scoring(
        [_case_with_benchmark("max_abs")],
        [{"case": "pendulum", "engine": "natcoord", "status": "ok", "benchmark_error": 2e-9,
          "wall_time_s": 0.02},
         {"case": "pendulum", "engine": "dart", "status": "ok", "benchmark_error": 2e-2,
          "wall_time_s": 0.1}], [])
    (out / "bench.json").write_text(json.dumps(data))
    html = write_report(out, references=refs).read_text(encoding="utf-8")
    cost = html.split('<h3 id="cost">', 1)[1].split("</table>", 1)[0]
    # fit through (250, 0.4 s) and (1000, 1.0 s): 800 us per step, 0.2 s fixed, 200 us/rhs
    row = cost.split("<td>natcoord</td>", 1)[1].split("</tr>", 1)[0]
    assert "200\u00a0ms" in row and "800\u00a0µs" in row and "200\u00a0µs" in row
    assert "first quarter" in cost
    cold = html.split('id="cold-start"', 1)[1].split("</p>", 1)[0]
    assert "1.6\u00a0s" in cold and "import 900\u00a0ms" in cold and "build time" in cold
    score = html.split('<h3 id="scoring">', 1)[1].split("</table>", 1)[0]
    assert "x, y, over every output sample (≤ 1.00e−3)" in score
    assert "not reached" in score and "case settings" in score


def test_time_to_accuracy_leaves_out_cases_swept_for_their_benchmark_only():
    pts = [{"case": "a04", "engine": "mujoco", "variant": "", "channel": None, "error": None,
            "benchmark_error": 1e-4, "wall_time_s": 1.0},
           {"case": "c", "engine": "mujoco", "variant": "", "channel": "theta", "error": 1e-7,
            "wall_time_s": 2.0}]
    rows = bench.time_to_accuracy(pts)
    assert [(r["case"], r["time_to_1e-06"]) for r in rows] == [("c", 2.0)]


def test_a_piped_bench_prints_its_figures_whole(tmp_path):
    """Piped (a CI log), rich drew the cost table 80 columns wide and cut every figure to
    '0.00…'; the table is as wide as its figures need unless COLUMNS says otherwise."""
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bench", "pendulum", "--engines",
                        "natcoord", "--repeats", "1", "--out", tmp_path / "b", "--history",
                        tmp_path / "h"], capture_output=True, text=True, timeout=600, env=env)
    assert p.returncode == 0, p.stderr[-2000:]
    (row,) = [line for line in p.stdout.splitlines() if "│ pendulum" in line]
    assert "…" not in row and len(row) > 80, row
    assert re.search(r"│ +\d+\.\d+e-\d+ │|│ +0\.\d{4,} │", row), row
