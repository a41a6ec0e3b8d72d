"""The report's front page (accuracy map, speed at equal accuracy, engine profiles, changes
since the last green night) and its lightness, on a real run; the page in headless Chromium
(Playwright driving Debian's /usr/bin/chromium): no horizontal overflow at 1,400 px, no
console error, no clipped tick label, no table cell wrapped past two lines; screenshots of
the front page in the test's tmp folder (and in $NATCOORD_SCREENSHOTS when set)."""

from __future__ import annotations

import base64
import gzip
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from natcoord.report import write_report
from natcoord.report.front import colour, equal_accuracy, worst_motion
from natcoord.report.lazy import (
    LEVELS,
    decoded,
    encode,
    from_text,
    pack,
    page_figures,
    to_text,
    unpack,
)
from natcoord.suite.history import record

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
CASES = ["a01_pendulum", "a02_four_bar_n2"]
ENGINES = "natcoord,mujoco"


# ---------------------------------------------------------------- stored arrays


def test_arrays_kept_to_their_span():
    """16-bit storage: a value within 1/65534 of its array's span (an energy drifting by
    2e-6 J at 10 J keeps its shape: float32 made it a staircase of 1e-6 J steps); on a log
    span within 0.04 %; NaN stays NaN; an even grid is exact."""
    t = np.linspace(0.0, 2.0, 601)
    energy = 10.0 + 2e-6 * np.sin(3 * t)
    back = decoded(encode(energy))
    assert np.max(np.abs(back - energy)) <= 0.51 * 4e-6 / LEVELS
    assert np.max(np.abs(energy.astype(np.float32) - energy)) > 1e-7  # float32 cannot
    err = 10.0 ** np.linspace(-15, -3, 601)
    err[100] = np.nan
    back = decoded(encode(err))
    assert np.isnan(back[100])
    ok = ~np.isnan(err)
    assert np.max(np.abs(back[ok] / err[ok] - 1)) < 4.3e-4
    assert encode(t) == {"grid": [0.0, 2.0 / 600, 601]}
    assert np.array_equal(decoded(encode(t)), 0.0 + 2.0 / 600 * np.arange(601))


def test_figures_blob_round_trip():
    """The page's blob gives back every figure as stored: 16-bit codes through the delta
    coding (a jump of 65535 wraps), NaN codes, grids and other attributes; identical arrays
    stored once."""
    wave = np.sin(np.linspace(0.0, 9.0, 600))
    jumpy = np.array([0.0, 1.0, 0.0, np.nan, 1.0, 0.5])  # codes 0, 65534, 0, 65535, ...
    specs = {f"fig-{i}": {"data": [{"x": encode(np.linspace(0, 1, 600)), "y": encode(y),
                                    "name": f"trace {i}"}],
                          "layout": {"title": {"text": "</script><!-- é"}}, "config": {}}
             for i, y in enumerate((wave, jumpy, wave))}
    blob = pack(specs)
    assert unpack(blob) == specs
    raw = gzip.decompress(blob)
    head = json.loads(raw[4:4 + int.from_bytes(raw[:4], "little")])
    assert head["n"] == 606  # the sine once, the jumpy array once, the grid inline
    assert np.array_equal(decoded(unpack(blob)["fig-1"]["data"][0]["y"]),
                          decoded(encode(jumpy)), equal_nan=True)


def test_page_text_form():
    """Binary in the page: base85 without "<" (cannot end its script element), 1.25 chars a
    byte, any length back exactly."""
    rng = np.random.default_rng(1)
    for n in (0, 1, 2, 3, 4, 5, 4001):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        text = to_text(data)
        assert from_text(text) == data and "<" not in text
        assert len(text) <= 1.25 * n + 1
    assert "<" in base64.b85encode(bytes(range(256)) * 4).decode()  # what "." replaces


def test_colour_scale_is_monotone_in_darkness():
    """Smaller errors are lighter: the map reads without colour names (viridis)."""
    def luminance(hex_: str) -> float:
        r, g, b = (int(hex_[i:i + 2], 16) / 255 for i in (1, 3, 5))
        return 0.2126 * r + 0.7152 * g + 0.0722 * b
    lum = [luminance(colour(10.0 ** e)[0]) for e in range(-16, 1)]
    assert all(a >= b for a, b in zip(lum, lum[1:], strict=False)) and lum[0] > lum[-1]


def test_worst_motion_takes_gated_motion_channels_only():
    rec = {"channels": {
        "theta": {"kind": "angle", "max_rel": 1e-9, "tolerance": 1e-6},
        "x": {"kind": "position", "max_rel": 3e-8, "tolerance": 1e-6},
        "N": {"kind": "reaction", "max_rel": 1e-2, "tolerance": 1.0},
        "E": {"kind": "energy", "max_rel": 1e-3, "tolerance": 1.0},
        "y": {"kind": "position", "max_rel": 5e-1},  # no tolerance: not gated
        "l1": {"kind": "position", "max_rel": 9e-1, "tolerance": 1.0, "determined": False}}}
    assert worst_motion(rec) == (3e-8, "x")
    assert worst_motion({"channels": {}}) == (None, "")


def test_equal_accuracy_takes_each_engines_best_variant():
    """From sweep points as ``natcoord bench --work-precision`` writes them: per case and
    engine the least time to each target over its variants, the ratio to the fastest, and
    'not reached' / 'not swept' where so; without a sweep the reason."""
    from natcoord.suite.bench import time_to_accuracy

    pts = [{"case": "c", "engine": e, "variant": v, "channel": "theta", "error": err,
            "wall_time_s": w}
           for e, v, err, w in (("natcoord", "index1 dop853", 1e-7, 0.010),
                                ("natcoord", "index1 dop853", 1e-10, 0.020),
                                ("natcoord", "index3 trapezoidal", 1e-7, 0.004),
                                ("mujoco", "", 5e-7, 0.012),
                                ("mujoco", "", 1e-5, 0.001))]
    bench = {"records": [], "time_to_accuracy": time_to_accuracy(pts)}
    fmt_t = lambda v: f"{v * 1e3:.3g} ms"  # noqa: E731
    fmt_r = lambda v: f"{v:.3g}×"  # noqa: E731
    out = equal_accuracy(bench, ["c"], ["natcoord", "mujoco", "dart"], lambda *a: "-".join(a),
                         fmt_t, fmt_r)
    assert out["targets"] == ["1e-6", "1e-9"] and not out["missing"]
    nat, muj, dart = out["rows"][0]["cells"]
    assert [ln["text"] for ln in nat["lines"]] == ["4 ms (1×)", "20 ms (1×)"]
    assert nat["lines"][0]["best"] and nat["lines"][1]["best"]
    assert [ln["text"] for ln in muj["lines"]] == ["12 ms (3×)", "not reached"]
    assert dart["lines"] == []  # not swept
    assert "no work-precision sweep" in equal_accuracy({"records": []}, ["c"], ["natcoord"],
                                                       str, fmt_t, fmt_r)["missing"]
    assert "no benchmark" in equal_accuracy(None, ["c"], ["natcoord"], str, fmt_t,
                                            fmt_r)["missing"]


# ---------------------------------------------------------------- a real run


def _natcoord(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=1800)


@pytest.fixture(scope="module")
def real_run(tmp_path_factory) -> tuple[Path, Path]:
    """a01_pendulum and a02_four_bar_n2 run in natcoord and MuJoCo (real engines, a few
    minutes on a loaded machine), with a bench.json of the run's own wall times (three equal
    samples a cell), and a history holding an earlier green suite that is this run scaled:
    MuJoCo's four-bar 100x more accurate (its worst error / tolerance was 0.33 here), its
    pendulum 3x faster, its version another; the changes section must name all three."""
    pytest.importorskip("mujoco")
    root = tmp_path_factory.mktemp("front")
    out = root / "run"
    proc = _natcoord("run", *CASES, "--engines", ENGINES, "--out", str(out))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    green = json.loads(json.dumps(summary))
    for r in green["records"]:
        if (r["case"], r["engine"]) == ("a02_four_bar_n2", "mujoco"):
            for ch in r["channels"].values():
                if ch.get("max_abs") is not None:
                    ch["max_abs"] = ch["max_abs"] * 1e-2
                    ch["max_rel"] = (ch.get("max_rel") or 0.0) * 1e-2
        r["engine_version"] = r["engine_version"] + "-old" if r["engine"] == "mujoco" else \
            r["engine_version"]
    bench = {"generated": summary["generated"], "machine": summary.get("machine", {}),
             "records": [{"case": r["case"], "engine": r["engine"], "status": "ok",
                          "samples_s": [r["wall_time_s"]] * 3, "wall_time_s": r["wall_time_s"],
                          "repeats": 3} for r in summary["records"]]}
    old = json.loads(json.dumps(bench))
    for r in old["records"]:
        if (r["case"], r["engine"]) == ("a01_pendulum", "mujoco"):
            r["samples_s"] = [s / 3 for s in r["samples_s"]]
    db = root / "history.db"
    record(db, kind="suite", summary=green, bench=old, gate=0, results_dir=str(root / "old"))
    (out / "bench.json").write_text(json.dumps(bench))
    return out, db


@pytest.fixture(scope="module")
def front_page(real_run) -> tuple[Path, str]:
    out, db = real_run
    path = write_report(out, references=ROOT / "references", history=db)
    return path, path.read_text(encoding="utf-8")


@pytest.mark.engines
@pytest.mark.slow
def test_front_page_answers(front_page, real_run):
    path, html = front_page
    summary = json.loads((real_run[0] / "summary.json").read_text())
    # the accuracy map: each cell the worst relative motion error, its mark and colour
    for r in summary["records"]:
        v, _ = worst_motion(r)
        assert v is not None and r["verdict"] == "pass"
        cell = re.search(rf'<td class="cell pass acc map" style="background:{colour(v)[0]};'
                         rf'[^"]*" title="{r["engine"]} · pass: worst relative error ', html)
        assert cell, (r["case"], r["engine"])
    assert html.count('<span class="mark">✓</span>') == len(summary["records"])
    # speed: this folder's bench has no sweep, and the page says so
    assert "No speed at equal accuracy: bench.json has no work-precision sweep" in html
    # profiles: each engine ran both cases, MuJoCo's speed relative to natcoord's
    assert re.search(r"<b>natcoord</b>: ran 2 of 2 cases \(2 within tolerance\)", html)
    assert re.search(r"<b>mujoco</b>: ran 2 of 2 cases .* median bench time [0-9.e+]+× "
                     r"natcoord's over 2 cases", html)
    # changes since the green night: MuJoCo's four-bar 100x worse, its pendulum 3x slower,
    # its version changed
    changes = html[html.index('id="changes"'):html.index('id="speed"')]
    assert re.search(r"a02_four_bar_n2/mujoco</th><td>worst error / tolerance", changes)
    assert re.search(r"a01_pendulum/mujoco</th><td>median bench time \(3.00×\)", changes)
    assert re.search(r"<b>mujoco</b>: \S+-old → ", changes)
    assert "Worse (2)" in changes and "Better" not in changes


@pytest.mark.engines
@pytest.mark.slow
def test_light(front_page):
    """A two-case, two-engine report was 4.9 MB (4.8 MB of it plotly.js), then 690 KB with
    the basic bundle and figures as inline JSON; 593 KB with figures in one gzip blob and
    binary in base85 (a full suite's: 3.57 -> 1.93 MB)."""
    path, html = front_page
    assert path.stat().st_size < 640_000, path.stat().st_size
    blob = re.search(r'id="nc-plotly"[^>]*>([^<]+)<', html)[1]
    assert gzip.decompress(from_text(blob)).startswith(b"/**\n* plotly.js (basic")


# ---------------------------------------------------------------- in a browser

PROBE = """() => {
  const out = {scrollWidth: document.documentElement.scrollWidth,
               width: window.innerWidth, wide: [], wrapped: [], clipped: [], drawn: 0};
  for (const t of document.querySelectorAll("main table")) {
    if (!t.offsetParent) continue;
    const box = t.parentElement.classList.contains("table-wrap") ? t.parentElement : t;
    if (t.getBoundingClientRect().width > box.clientWidth + 1 ||
        t.getBoundingClientRect().width > document.querySelector("main").clientWidth)
      out.wide.push(t.className + ": " + Math.round(t.getBoundingClientRect().width) + " px");
    for (const cell of t.querySelectorAll("td, th")) {
      const walker = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
      for (let n = walker.nextNode(); n; n = walker.nextNode()) {
        if (!n.textContent.trim()) continue;
        const r = document.createRange(); r.selectNodeContents(n);
        const tops = new Set([...r.getClientRects()].map(q => Math.round(q.top)));
        if (tops.size > 2) out.wrapped.push(n.textContent.trim().slice(0, 60) + ": " + tops.size);
      }
    }
  }
  for (const div of document.querySelectorAll(".js-plotly-plot")) {
    out.drawn += 1;
    const box = div.getBoundingClientRect();
    for (const tx of div.querySelectorAll(".xtick text, .ytick text, .g-ytitle text")) {
      const b = tx.getBoundingClientRect();
      if (b.width && (b.left < box.left - 0.5 || b.right > box.right + 0.5))
        out.clipped.push(div.id + ": " + tx.textContent);
    }
  }
  return out;
}"""


def _shots_dir(tmp_path: Path) -> Path:
    d = Path(os.environ.get("NATCOORD_SCREENSHOTS") or tmp_path)
    d.mkdir(parents=True, exist_ok=True)
    return d


@pytest.mark.engines
@pytest.mark.slow
@pytest.mark.browser
@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (/usr/bin/chromium) absent")
def test_front_page_in_chromium(front_page, tmp_path):
    playwright = pytest.importorskip("playwright.sync_api")
    path, html = front_page
    shots = _shots_dir(tmp_path)
    problems: list[str] = []
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM),
                                    args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.on("console", lambda m: m.type in ("error", "warning")
                    and problems.append(f"{m.type}: {m.text}"))
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            page.on("request", lambda r: not r.url.startswith(("file:", "data:", "blob:"))
                    and problems.append(f"network: {r.url}"))
            t0 = time.perf_counter()
            page.goto(path.resolve().as_uri(), wait_until="load")
            load_s = time.perf_counter() - t0
            page.screenshot(path=str(shots / "front-page.png"))
            page.screenshot(path=str(shots / "front-page-full.png"), full_page=True)
            closed = page.evaluate(PROBE)
            page.goto(path.resolve().as_uri() + "#open-all", wait_until="load")
            page.reload(wait_until="load")
            page.wait_for_function("document.querySelectorAll('div[data-lazy]').length === 0",
                                   timeout=120_000)
            opened = page.evaluate(PROBE)
            drawn = dict(page.evaluate(
                "() => Array.from(document.querySelectorAll('.plotly-graph-div'), d => "
                "[d.id, (d.data || []).map(t => t.y ? Array.from(t.y) : null)])"))
            page.screenshot(path=str(shots / "open-all.png"))
        finally:
            browser.close()
    print(f"load {load_s:.2f} s; screenshots in {shots}")
    (shots / "load-time.txt").write_text(f"{load_s:.3f} s to the load event\n")
    assert not problems, problems
    assert closed["drawn"] == 0  # figures wait for their section
    assert opened["drawn"] > 0
    for state in (closed, opened):
        assert state["scrollWidth"] <= state["width"], state["scrollWidth"]
        assert not state["wide"], state["wide"]
        assert not state["wrapped"], state["wrapped"]
    assert not opened["clipped"], opened["clipped"][:10]
    # the page's decoding of the figure blob is Python's, value for value to the last bits
    # (a log axis's 10^v: the browser's Math.pow and numpy's power, which on an AVX-512
    # machine is its own vectorised one, may round differently: measured 2.2e-16 relative)
    figs = page_figures(html)
    assert figs and set(drawn) == set(figs)
    for fid, spec in figs.items():
        for trace, y in zip(spec["data"], drawn[fid], strict=True):
            if isinstance(trace.get("y"), dict):
                got = np.array([np.nan if v is None else v for v in y], dtype=float)
                want = decoded(trace["y"])
                assert np.array_equal(np.isnan(got), np.isnan(want)), fid
                np.testing.assert_allclose(got, want, rtol=1e-15, atol=0, equal_nan=True,
                                           err_msg=fid)

