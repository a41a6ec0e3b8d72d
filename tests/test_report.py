"""The HTML report: rendering of a results directory (not physics)."""

from __future__ import annotations

import gzip
import json
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from natcoord.report import write_report
from natcoord.report.html import MAX_POINTS, cell_for, fmt_num, fmt_time
from natcoord.report.lazy import decoded, from_text, page_figures

ENGINES = ["natcoord", "mujoco", "pinocchio", "exudyn", "dart"]
CHROMIUM = Path("/usr/bin/chromium")
EVIL = "<script>alert('x')</script> & \"quotes\""


# ---------------------------------------------------------------- a results directory


def _pendulum(t: np.ndarray) -> pd.DataFrame:
    """Rigid pendulum-like motion: an analytic angle, mass position, link tension."""
    w = 2 * np.pi / 2.3678419
    th = -np.pi / 2 + (np.pi / 2) * np.cos(w * t)
    thd = -(np.pi / 2) * w * np.sin(w * t)
    x, y = np.cos(th), np.sin(th)
    tension = -9.81 * y + thd**2
    return pd.DataFrame({"t": t, "x": x, "y": y, "tension": tension})


def _five_bar(t: np.ndarray, share: float = 0.5) -> pd.DataFrame:
    """An angle and two redundant axial forces whose split (``share``) is arbitrary."""
    phi = np.pi / 2 + t - 4.0 * t**2
    m = 200.0 + 50.0 * np.sin(3 * t)  # determined combination N34 + 2 N56
    n56 = share * m / 2
    n34 = m - 2 * n56
    return pd.DataFrame({"t": t, "phi": phi, "N34": n34, "N56": n56, "N34_2N56": n34 + 2 * n56})


CHANNELS = {
    "pendulum": {"x": ("position", "m"), "y": ("position", "m"), "tension": ("reaction", "N")},
    "five_bar": {"phi": ("angle", "rad"), "N34": ("reaction", "N"), "N56": ("reaction", "N"),
                 "N34_2N56": ("reaction", "N")},
}
UNDETERMINED = {"N34", "N56"}
TOL = {"angle": 1e-6, "position": 1e-6, "reaction": 1e-3, "energy": 1e-6}

# (status, verdict, reason, how the engine's series differ from the reference)
PLAN = {
    "pendulum": {
        "natcoord": ("ok", "pass", "", 1e-9),
        "mujoco": ("ok", "fail", "", 2e-3),
        "pinocchio": ("ok", "pass", "", 3e-7),
        "exudyn": ("failed", "n/a", "diverged at t = 4.2 s (NaN state)", None),
        "dart": ("unsupported", "n/a", f"no massless link {EVIL}", None),
    },
    "five_bar": {
        "natcoord": ("ok", "pass", "", 0.0),
        "mujoco": ("unsupported", "n/a", "singular mass matrix cannot be modelled", None),
        "pinocchio": ("skipped", "n/a", "package pin not installed", None),
        "exudyn": ("ok", "pass", "", 1e-8),
        "dart": ("ok", "fail", "", 5e-2),
    },
}


def _record(case, engine, status, verdict, reason, offset, run, ref):
    channels = {}
    for name, (kind, unit) in CHANNELS[case].items():
        det = name not in UNDETERMINED
        if status == "ok":
            err = np.abs(run[name].to_numpy() - ref[name].to_numpy())
            max_abs = float(np.max(err))
            rng = float(np.ptp(ref[name].to_numpy())) or 1.0
            tol = TOL[kind]
            channels[name] = {"kind": kind, "unit": unit, "max_abs": max_abs,
                              "max_rel": max_abs / rng, "tolerance": tol if det else None,
                              "pass": (max_abs <= tol) if det else None, "determined": det}
        else:
            channels[name] = {"kind": kind, "unit": unit, "max_abs": None, "max_rel": float("nan"),
                              "tolerance": TOL[kind], "pass": None, "determined": det}
    n_steps = 10000 if status == "ok" else 0
    return {
        "case": case, "description": f"{case} test case: description with <b>markup</b>",
        "engine": engine, "engine_version": f"{engine}-1.2.3", "status": status,
        "reason": reason, "verdict": verdict, "channels": channels,
        "tolerance_reason": f"{engine} tolerance: step 1e-4 s, RK4" if status == "ok" else "",
        "wall_time_s": 0.0123 * (1 + ENGINES.index(engine)) if status == "ok" else float("nan"),
        "build_time_s": 0.5 if status == "ok" else None,
        "n_steps": n_steps,
        "us_per_step": 1.23 * (1 + ENGINES.index(engine)) if status == "ok" else None,
        "sim_time_s": float(ref["t"].iloc[-1]),
        "settings": {"integrator": "RK4", "dt": 1e-4},
        "counters": {"rhs_evals": 4 * n_steps, "max_drift": 1.5e-12},
        "notes": [f"{engine}: link modelled as a stiff capsule"] if engine == "mujoco" else [],
    }


def make_results(root: Path, with_bench: bool = True) -> tuple[Path, Path]:
    """A results directory (2 cases x 5 engines) and a references directory under root."""
    out, refs = root / "run", root / "references"
    refs.mkdir(parents=True)
    records = []
    for case, plan in PLAN.items():
        t = np.linspace(0.0, 10.0 if case == "pendulum" else 1.8, 10001)
        ref = _pendulum(t) if case == "pendulum" else _five_bar(t)
        ref.to_csv(refs / f"{case}.csv", index=False)
        (refs / f"{case}.json").write_text(json.dumps({
            "case": case, "method": "natcoord index-3 augmented Lagrangian, dt 1e-5",
            "settings": {"dt": 1e-5, "tol": 1e-12}, "tolerances": {"angle": 1e-9},
            "versions": {"natcoord": "0.1.0", "numpy": "2.4"},
            "created": "2025-11-20T10:00:00+00:00", "max_phi": 3.1e-14}))
        for engine, (status, verdict, reason, offset) in plan.items():
            run = None
            if status == "ok":
                run = _pendulum(t) if case == "pendulum" else _five_bar(t, share=0.3 + 0.1 *
                                                                        ENGINES.index(engine))
                for name in CHANNELS[case]:
                    if name not in UNDETERMINED:
                        run[name] = run[name] + offset * np.sin(7 * t) ** 2
                d = out / "results" / case
                d.mkdir(parents=True, exist_ok=True)
                run.to_csv(d / f"{engine}.csv", index=False)
            elif status == "failed":  # a partial run ending in NaN
                part = ref.iloc[:4200].copy()
                part.iloc[-50:, 1:] = np.nan
                d = out / "results" / case
                d.mkdir(parents=True, exist_ok=True)
                part.to_csv(d / f"{engine}.csv", index=False)
            records.append(_record(case, engine, status, verdict, reason, offset,
                                   run if run is not None else ref, ref))
    summary = {
        "generated": "2025-11-21T23:40:00+00:00", "natcoord_version": "0.1.0",
        "machine": {"python": "3.11.9", "platform": "Linux-6.1-x86_64", "cpu": "Test CPU @ 3 GHz",
                    "blas_threads": 1},
        "records": records,
    }
    (out / "summary.json").write_text(json.dumps(summary))  # NaN written as NaN
    if with_bench:
        bench = {"machine": {"cpu": "Test CPU @ 3 GHz"}, "records": [
            {"case": c, "engine": e, "us_per_step": 0.7 * (i + 1), "wall_per_sim_s": 1e-3 * (i + 1),
             "build_time_s": 0.1, "repeats": 5}
            for c in PLAN for i, e in enumerate(ENGINES)]}
        (out / "bench.json").write_text(json.dumps(bench))
    return out, refs


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> tuple[Path, str]:
    out, refs = make_results(tmp_path_factory.mktemp("report"))
    path = write_report(out, references=refs)
    return path, path.read_text(encoding="utf-8")


# ---------------------------------------------------------------- page content


def test_writes_index_html(report):
    path, html = report
    assert path.name == "index.html" and path.is_file()
    assert html.startswith("<!DOCTYPE html>")


def test_every_case_and_engine_shown(report):
    _, html = report
    for case in PLAN:
        assert f'id="case-{case}"' in html
        assert case in html
    for engine in ENGINES:
        assert engine in html
        assert f"{engine}-1.2.3" in html  # engine versions


def test_verdict_cells(report):
    _, html = report
    cells = re.findall(r'<td class="cell (\w+)[ "]', html)
    assert len(cells) == len(PLAN) * len(ENGINES)
    assert sorted(set(cells)) == ["fail", "failed", "pass", "skipped", "unsupported"]
    # reasons on hover and in text
    assert 'title="exudyn · failed: diverged at t = 4.2 s (NaN state)"' in html
    assert "singular mass matrix cannot be modelled" in html
    assert html.count("package pin not installed") >= 2  # hover + footnote
    assert 'class="verdict v-fail"' in html  # overall verdict: two runs outside tolerance


def test_failing_channels_named(report):
    _, html = report
    # the mujoco pendulum offset (2e-3 m) is named with its tolerance
    assert re.search(r"x: 2(\.00)?e−3\u00a0m &gt; 1(\.00)?e−6\u00a0m", html)


def test_self_contained(report):
    _, html = report
    assert '<script src="http' not in html
    assert not re.search(r"""<(script|link|img|iframe)[^>]+(src|href)\s*=\s*["']?(https?:)?//""",
                         html)
    # plotly.js embedded once, inline (gzip, base85)
    blob = re.findall(r'<script type="application/octet-stream" id="nc-plotly"[^>]*>([^<]+)<', html)
    assert len(blob) == 1
    assert gzip.decompress(from_text(blob[0])).startswith(b"/**\n* plotly.js")
    assert "cdn.plot.ly" not in html


def test_text_is_escaped(report):
    _, html = report
    assert EVIL not in html
    assert "&lt;script&gt;alert(" in html
    assert "<b>markup</b>" not in html and "&lt;b&gt;markup&lt;/b&gt;" in html


def test_figures_per_channel(report):
    _, html = report
    n_channels = sum(len(c) for c in CHANNELS.values())
    assert html.count('class="plotly-graph-div"') == n_channels
    # packed in one blob, drawn by one loader when the section opens (not at load)
    figs = page_figures(html)
    assert len(figs) == n_channels and html.count('id="nc-figures"') == 1
    assert html.count("Plotly.newPlot(") == 1
    # 16-bit arrays over their own span (time axes as grids), downsampled
    ys = [t["y"] for f in figs.values() for t in f["data"]]
    assert any("q" in y and "lo" in y for y in ys) and all("q" in y or "grid" in y for y in ys)
    assert "undetermined: not gated" in html
    assert "dash" in html and "log" in html


def test_downsampled_and_reasonably_small(report):
    path, html = report
    size = path.stat().st_size
    plotly_js = len(re.search(r'id="nc-plotly"[^>]*>([^<]*)<', html)[1])
    assert size - plotly_js < 1_500_000, f"figures and tables take {size - plotly_js} bytes"
    arrays = [decoded(t[k]) for f in page_figures(html).values() for t in f["data"]
              for k in ("x", "y") if isinstance(t.get(k), dict)]
    assert arrays and max(len(a) for a in arrays) <= MAX_POINTS


def test_speed_and_bench_sections(report):
    _, html = report
    assert 'id="speed"' in html and 'id="bench"' in html
    assert "µs" in html and "× natcoord" in html


def test_tolerance_reasons_notes_and_provenance(report):
    _, html = report
    assert "tolerance: step 1e-4 s, RK4" in html
    assert "link modelled as a stiff capsule" in html
    assert "natcoord index-3 augmented Lagrangian" in html
    assert "Test CPU @ 3 GHz" in html


def test_missing_reference_and_bench(tmp_path):
    out, refs = make_results(tmp_path, with_bench=False)
    (refs / "five_bar.csv").unlink()
    (refs / "five_bar.json").unlink()
    html = write_report(out, references=refs).read_text(encoding="utf-8")
    assert "No reference for this case yet" in html
    assert 'id="bench"' not in html
    assert html.count('class="plotly-graph-div"') == sum(len(c) for c in CHANNELS.values())


def test_sparse_records(tmp_path):
    """Records with only the essentials (a crashed runner, NaN numbers) still render."""
    (tmp_path / "summary.json").write_text(
        '{"records": [{"case": "c1", "engine": "natcoord", "status": "failed", '
        '"wall_time_s": NaN, "channels": {"q": {"max_abs": NaN}}}, '
        '{"case": "c1", "engine": "newengine", "status": "ok", "verdict": "pass"}]}'
    )
    (tmp_path / "results" / "c1").mkdir(parents=True)
    (tmp_path / "results" / "c1" / "newengine.csv").write_text("t,q\n0,1\n1,2\n")
    (tmp_path / "results" / "c1" / "natcoord.csv").write_text("")
    html = write_report(tmp_path, references=tmp_path / "none").read_text(encoding="utf-8")
    assert "newengine" in html and 'class="cell failed' in html
    assert "No reference for this case yet" in html


def test_missing_summary(tmp_path):
    with pytest.raises(FileNotFoundError):
        write_report(tmp_path, references=tmp_path)


def test_formatting():
    assert fmt_num(0.000123456, "rad") == "1.23e−4\u00a0rad"
    assert fmt_num(12.3456) == "12.3"
    assert fmt_num(float("nan")) == "—" and fmt_num(None) == "—"
    assert fmt_time(0.0123) == "12.3\u00a0ms"
    assert fmt_time(2.5e-6) == "2.5\u00a0µs"
    assert cell_for({"status": "ok", "verdict": "pass"})["css"] == "pass"
    assert cell_for({"status": "skipped", "reason": "r"})["reason"] == "r"
    assert cell_for(None)["key"] == "missing"
    assert math.isfinite(1.0)


# ---------------------------------------------------------------- in a browser


def _chromium(args: list[str], profile: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    cmd = [
        str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
        "--no-first-run", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--disable-dev-shm-usage", f"--user-data-dir={profile}",
        # any network access would fail (and show up as an error): the page must not need it
        "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _dom(path: Path, profile: Path, fragment: str = "") -> str:
    """The page's DOM after load (and after opening what ``#fragment`` asks), with no
    console message and no network access."""
    proc = _chromium(
        ["--enable-logging=stderr", "--v=0", "--virtual-time-budget=20000",
         "--window-size=1400,1000", "--dump-dom", path.resolve().as_uri() + fragment],
        profile,
    )
    dom, log = proc.stdout, proc.stderr
    assert proc.returncode == 0, log[-3000:]
    console = [ln for ln in log.splitlines()
               if "CONSOLE" in ln or "Uncaught" in ln or "ERR_NAME_NOT_RESOLVED" in ln]
    assert not console, "\n".join(console)
    return dom


DRAWN = r'<div id="[^"]+" class="plotly-graph-div js-plotly-plot"'


@pytest.mark.browser
@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (/usr/bin/chromium) absent")
def test_renders_in_chromium(report, tmp_path):
    path, _ = report
    n_channels = sum(len(c) for c in CHANNELS.values())
    # at load every case is collapsed and no figure is drawn
    dom = _dom(path, tmp_path / "profile")
    assert not re.findall(DRAWN, dom)
    assert dom.count("data-lazy=") == n_channels
    # a link to a case opens it: its figures, and only those, are drawn
    dom = _dom(path, tmp_path / "profile", "#case-five_bar")
    assert len(re.findall(DRAWN, dom)) == len(CHANNELS["five_bar"])
    assert re.search(r'<details class="sec" open[^>]*>\s*<summary><h2>five_bar', dom)
    # every section open: every figure drawn
    dom = _dom(path, tmp_path / "profile", "#open-all")
    # plotly drew every figure (each has its own main-svg layers)
    drawn = re.findall(r'<div id="[^"]+" class="plotly-graph-div js-plotly-plot"', dom)
    assert len(drawn) == n_channels, f"{len(drawn)} of {n_channels} figures drawn"
    assert dom.count('class="main-svg"') >= n_channels
    for case in PLAN:
        assert f'id="case-{case}"' in dom
    for engine in ENGINES:  # matrix header and a drawn plot legend entry for each engine
        assert f"{engine}</th>" in dom
        assert re.search(rf'class="legendtext"[^>]*>{engine}<', dom), engine


def _screenshot(path: Path, png: Path, profile: Path, height: int = 5000) -> None:
    """Full-page screenshot for a human look (not run by default)."""
    _chromium(["--hide-scrollbars", f"--window-size=1400,{height}", "--virtual-time-budget=20000",
               f"--screenshot={png}", path.resolve().as_uri()], profile)


if __name__ == "__main__":  # python tests/test_report.py DIR: build a sample page + screenshot
    import sys
    import tempfile

    root = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp())
    shutil.rmtree(root, ignore_errors=True)
    out, refs = make_results(root)
    page = write_report(out, references=refs)
    print(page, page.stat().st_size)
    if CHROMIUM.exists():
        _screenshot(page, root / "screenshot.png", root / "profile")
        print(root / "screenshot.png")


def test_redundant_case_section_from_a_real_run(tmp_path):
    """five_bar run in natcoord and Exudyn (real engines): the report explains the redundant
    constraint (rank, DOF, N), marks determined / undetermined force channels, puts
    natcoord's reaction methods beside each engine, and shows the published angles."""
    from natcoord.case.casefile import load_case
    from natcoord.suite.runner import run_suite

    from .conftest import CASES, REFERENCES

    case = load_case(CASES / "five_bar.toml")
    run_suite([case], ["natcoord", "exudyn"], tmp_path, references=REFERENCES)
    html = write_report(tmp_path, REFERENCES).read_text()
    assert "Redundant constraints: what is determined" in html
    assert "rank Φ<sub>q</sub> = 7 · 1 DOF · 1 redundant" in html
    assert "Self-equilibrating set 1" in html and "<code>N56</code>" in html
    for method in ("min_norm", "unit_invariant", "weighted_KL1_KT1000", "weighted_KL1000_KT1"):
        assert f"natcoord<br>{method}" in html
    assert html.count("determined: gated") == 3  # N34_2N56, R1_y, R2_y
    assert html.count("undetermined: shown only") == 4  # N34, N56, R1_x, R2_x
    assert "Published values" in html and "García de Jalón" in html and "-330.97" in html


# ---------------------------------------------------------------- history, benchmark, speed


def _bench(scale: dict[tuple[str, str], float] | None = None, work_precision: bool = True
           ) -> dict:
    """A bench.json with every repeat's wall time and, optionally, a work-precision sweep
    of natcoord (two variants) and mujoco on the pendulum."""
    scale = scale or {}
    records = []
    for case in PLAN:
        for i, e in enumerate(ENGINES):
            w = 1e-2 * (i + 1) * scale.get((case, e), 1.0)
            ss = [w, 1.1 * w, 1.3 * w]
            records.append({"case": case, "engine": e, "status": "ok", "samples_s": ss,
                            "wall_time_s": min(ss), "wall_median_s": 1.1 * w, "repeats": 3,
                            "wall_per_sim_s": w / 10, "us_per_step": 1e6 * w / 1e4,
                            "n_steps": 10000, "build_time_s": 0.1})
    out = {"generated": "2025-11-21T23:50:00+00:00", "machine": {"cpu": "Test CPU @ 3 GHz"},
           "repeats": 3, "records": records}
    if work_precision:
        pts = []
        for eng, var, dts, c in (("natcoord", "index1 dop853", (1e-6, 1e-8, 1e-10), 1e4),
                                 ("natcoord", "index3 trapezoidal", (2e-3, 1e-3, 5e-4), 1.0),
                                 ("mujoco", "", (1e-3, 5e-4, 2e-4), 3.0)):
            for k, d in enumerate(dts):
                pts.append({"case": "pendulum", "engine": eng, "variant": var,
                            "channel": "x", "setting": {"dt": d}, "status": "ok",
                            "error": c * d ** 2 if eng != "natcoord" or k else 1e-4,
                            "wall_time_s": 0.01 * (k + 1) * (2 if eng == "mujoco" else 1)})
        out["work_precision"] = pts
        from natcoord.suite.bench import time_to_accuracy
        out["time_to_accuracy"] = time_to_accuracy(pts)
    return out


def _summary(out: Path) -> dict:
    with open(out / "summary.json") as f:
        return json.load(f)


@pytest.fixture(scope="module")
def history_report(tmp_path_factory) -> tuple[Path, str]:
    """A results folder with a work-precision bench.json, reported with a history of two
    earlier runs (the pendulum in natcoord three times slower in this one)."""
    from natcoord.suite.history import record

    root = tmp_path_factory.mktemp("history")
    out, refs = make_results(root)
    db = root / "history.db"
    summary = _summary(out)
    for k in range(2):
        summary["generated"] = f"2025-11-{19 + k}T23:40:00+00:00"
        record(db, kind="suite", summary=summary, bench=_bench(work_precision=False),
               results_dir=str(root / f"earlier{k}"))
    (out / "bench.json").write_text(json.dumps(_bench({("pendulum", "natcoord"): 3.0})))
    path = write_report(out, references=refs, history=db)
    return path, path.read_text(encoding="utf-8")


def test_change_point():
    from natcoord.report.trends import change_point

    assert change_point([1.0, 1.02, 0.98, 1.01, 1.6, 1.62, 1.58], 1.25)["index"] == 4
    cp = change_point([1.0, 1.02, 0.98, 1.01, 1.6, 1.62, 1.58], 1.25)
    assert cp["factor"] == pytest.approx(1.6 / 1.0, rel=0.02)
    assert change_point([1.0, 1.1, 0.95, 1.05, 1.12, 0.9], 1.25) is None  # noise only
    assert change_point([1e-9, 2e-9, 5e-9], 10.0) is None  # accuracy: below a decade
    assert change_point([1e-9, 1e-9, 1e-6], 10.0)["index"] == 2
    assert change_point([1.0], 1.25) is None


def test_trends_section_from_history(history_report):
    _, html = history_report
    assert 'id="trends"' in html and "last 3 runs" in html
    assert "the last point is this run, not yet recorded" in html
    for case in PLAN:
        assert f'id="trend-{case}"' in html
    steps = html.split('<table class="speed steps">', 1)[1].split("</table>", 1)[0]
    assert "pendulum" in steps and "median wall time" in steps and "3× (worse)" in steps
    assert "five_bar" not in steps  # unchanged cells show no step


def test_trends_need_two_runs(report, tmp_path):
    _, html = report
    assert "No history (no history database)" in html
    from natcoord.suite.history import record

    out, refs = make_results(tmp_path)
    db = tmp_path / "history.db"
    record(db, kind="suite", summary=_summary(out), results_dir=str(out.resolve()))
    html = write_report(out, references=refs, history=db).read_text(encoding="utf-8")
    assert "Fewer than two runs in the history" in html  # this folder is the one run


def test_work_precision_and_time_to_accuracy(history_report):
    _, html = history_report
    assert "Speed at equal accuracy" in html
    assert 'id="wp-pendulum"' in html and "Work-precision diagrams (1 case)" in html
    tta = html.split('<table class="speed tta">', 1)[1].split("</table>", 1)[0]
    assert "time to error ≤ 1e-6" in tta and "time to error ≤ 1e-9" in tta
    assert "natcoord (index1 dop853)" in tta and "natcoord (index3 trapezoidal)" in tta
    assert "not reached" in tta  # mujoco's sweep never reaches 1e-9
    # interpolated on each curve (log-log, between the points around 1e-6): index1 dop853
    # 10 ms x 2^(1/4) (1e-4 at 10 ms, 1e-12 at 20 ms), mujoco 20 ms x 2^(ln 3 / ln 4)
    # (3e-6 at 20 ms, 7.5e-7 at 40 ms): 11.9 and 34.6 ms, 2.91x
    assert "interpolated" in tta
    mujoco = re.search(r"<td>mujoco</td>(.*?)</tr>", tta, re.S).group(1)
    dop853 = re.search(r"<td>natcoord \(index1 dop853\)</td>(.*?)</tr>", tta, re.S).group(1)
    assert "34.6\u00a0ms" in mujoco and "2.91" in mujoco
    assert "11.9\u00a0ms" in dop853
    fig_id = re.search(r'id="([^"]+)" class="plotly-graph-div"',
                       html.split('id="wp-pendulum"', 1)[1])[1]
    spec = page_figures(html)[fig_id]
    assert spec["layout"]["xaxis"]["type"] == spec["layout"]["yaxis"]["type"] == "log"
    assert {t["name"] for t in spec["data"] if t.get("mode") == "lines+markers"} == {
        "natcoord (index1 dop853)", "natcoord (index3 trapezoidal)", "mujoco"}


def test_speed_from_bench_with_spread(history_report):
    _, html = history_report
    own = html.split('<h3 id="bench">', 1)[1].split("</table>", 1)[0]
    assert "at each engine&#39;s own settings" in own or "at each engine's own settings" in own
    assert "samples_s" in own and "median" in own
    # natcoord pendulum: samples 30, 33, 39 ms: best, median and spread from the samples
    row = re.search(r"<td>natcoord</td>(.*?)</tr>", own, re.S).group(1)
    assert "30\u00a0ms" in row and "33\u00a0ms" in row
    assert "30\u00a0ms–39\u00a0ms" in row and "+30 %" in row  # range on hover
    assert "wall (1 run)" not in html  # the run's one-repeat timings are not shown beside it


def test_constraint_rows_in_words():
    from natcoord.report.redundant import describe_row

    assert describe_row("135.5 in 135: x") == "135.5 fixed in body 135, x component"
    assert describe_row("O: axis.1").startswith("joint O: rotation axis kept aligned")
    assert describe_row("A: x") == "joint A: its two points coincide along x"
    assert "rigid body plate" in describe_row("plate: |plate.1plate.2|")
    assert describe_row("N34", {"N34"}).startswith("rod N34")
    assert describe_row("something") == ""


@pytest.mark.browser
@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (/usr/bin/chromium) absent")
def test_trends_and_work_precision_draw_in_chromium(history_report, tmp_path):
    path, _ = history_report
    dom = _dom(path, tmp_path / "profile")
    assert not re.findall(DRAWN, dom)
    for fragment, figure in (("#trend-pendulum", 'id="trend-pendulum"'),
                             ("#wp-pendulum", 'id="wp-pendulum"')):
        dom = _dom(path, tmp_path / "profile", fragment)
        section = dom.split(figure, 1)[1].split("</figure>", 1)[0]
        assert re.search(DRAWN, section), fragment
        assert 'class="main-svg"' in section
        assert len(re.findall(DRAWN, dom)) == 1  # only the opened section's figure


def test_unreadable_history_is_one_line(tmp_path):
    out, refs = make_results(tmp_path)
    db = tmp_path / "history.db"
    db.write_bytes(b"not a database" * 100)
    html = write_report(out, references=refs, history=db).read_text(encoding="utf-8")
    assert "History unreadable" in html


# ---------------------------------------------------------------- energy balance


def _figure_series(html: str, anchor: str) -> dict[str, np.ndarray]:
    """Trace name -> y values (decoded as the page does) of the lazily stored figure inside
    the element with id ``anchor``."""
    start = html.index(f'id="{anchor}"')
    fig_id = re.search(r'id="([^"]+)" class="plotly-graph-div"', html[start:])[1]
    return {t["name"]: decoded(t["y"]) for t in page_figures(html)[fig_id]["data"]}


@pytest.fixture(scope="module")
def balance_report(tmp_path_factory) -> tuple[Path, str]:
    """a03_andrews (motor torque, spring) and a02_four_bar_n2 (conservative) run in natcoord
    (real runs, ~20 s), and their report."""
    from natcoord.case.casefile import load_case
    from natcoord.suite.runner import run_suite

    from .conftest import CASES, REFERENCES

    out = tmp_path_factory.mktemp("balance")
    cases = [load_case(CASES / f"{n}.toml") for n in ("a03_andrews", "a02_four_bar_n2")]
    run_suite(cases, ["natcoord"], out, references=REFERENCES)
    path = write_report(out, REFERENCES)
    return path, path.read_text(encoding="utf-8")


def test_energy_balance_drift_from_a_real_run(balance_report):
    """Each case gets an energy-balance figure of its conserved channel (a03: the
    ``balance`` channel, not ``energy``, which the motor changes by 0.52 J; a02: ``energy``)
    with natcoord's and the reference's drift relative to the energy scale, below 1e-9
    (measured: a03 7.3e-11 J of its 1.44 J scale, 5.1e-11; a02 3.2e-8 J of 110 J, 3.0e-10)."""
    path, html = balance_report
    assert 'id="case-a03_andrews-energy-balance"' in html
    assert 'id="case-a03_andrews-balance-energy"' not in html  # not conserved: not drawn
    for anchor in ("case-a03_andrews-balance-balance", "case-a02_four_bar_n2-balance-energy"):
        series = _figure_series(html, anchor)
        assert set(series) == {"natcoord", "reference"}, anchor
        for who, y in series.items():
            assert len(y) > 100 and np.nanmax(y) < 1e-9, (anchor, who, np.nanmax(y))
    summary = json.loads((path.parent / "summary.json").read_text())
    entries = {r["case"]: r["channels"] for r in summary["records"]}
    assert entries["a03_andrews"]["balance"]["balance"] is True
    assert entries["a03_andrews"]["energy"]["balance"] is False
    assert entries["a02_four_bar_n2"]["energy"]["scale"] > 10.0


@pytest.mark.browser
@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (/usr/bin/chromium) absent")
def test_energy_balance_figure_draws_in_chromium(balance_report, tmp_path):
    """A link to the balance section opens its case and draws the drift figure (log axis)."""
    path, _ = balance_report
    dom = _dom(path, tmp_path / "profile", "#case-a03_andrews-energy-balance")
    start = dom.index('id="case-a03_andrews-balance-balance"')
    fig = dom[start:dom.index("</figure>", start)]
    assert re.search(DRAWN, fig) and 'class="main-svg"' in fig
    assert "|drift| / energy scale" in fig


def test_no_energy_balance_section_without_energy_channels(report):
    _, html = report
    assert "Energy balance" not in html


def test_a_note_several_engines_carry_is_listed_once_with_all_of_them():
    """The case's assembly note is in every cell's notes: the report lists it once."""
    from natcoord.report.html import _grouped_notes
    same = "assembly turned body 'rocker' 36.1 deg from its pose in the case file"
    recs = [{"engine": "natcoord", "notes": [same, "compiled path: generated"]},
            {"engine": "mujoco", "notes": [same]}, {"engine": "dart"}]
    assert _grouped_notes(recs) == [("natcoord, mujoco", [same]),
                                    ("natcoord", ["compiled path: generated"])]
