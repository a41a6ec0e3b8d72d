"""The report's trends: per case x engine, accuracy (worst relative error over the determined
channels) and speed (median wall time of the benchmark repeats) over the last runs of the
history database, with change points marked.

Change points (a simple form of airspeed velocity's step detection): the series is split
once, at the split that minimises the sum of absolute deviations of log10 values from each
side's median (each side at least two runs when the series has four or more, else one). The
split is reported as a step when the two medians differ by more than a factor (speed 1.25,
accuracy 10), so run-to-run noise below that factor never shows as a step.
"""

from __future__ import annotations

import math
import sqlite3
import statistics
from pathlib import Path

import plotly.graph_objects as go
from plotly.subplots import make_subplots

from ..suite import history as hist
from .speed import samples, worst_rel

SPEED_FACTOR = 1.25
ACCURACY_FACTOR = 10.0
LAST_RUNS = 30


def change_point(values: list[float], factor: float) -> dict | None:
    """The best single split of a positive series, or None when there is no step larger
    than ``factor``: ``{"index": first index after the step, "before": median,
    "after": median, "factor": after / before}``."""
    xs = [math.log10(v) for v in values]
    n = len(xs)
    if n < 2:
        return None
    least = 2 if n >= 4 else 1
    best = None
    for k in range(least, n - least + 1):
        a, b = xs[:k], xs[k:]
        ma, mb = statistics.median(a), statistics.median(b)
        cost = sum(abs(x - ma) for x in a) + sum(abs(x - mb) for x in b)
        if best is None or cost < best[0]:
            best = (cost, k, ma, mb)
    if best is None:
        return None
    _, k, ma, mb = best
    ratio = 10 ** (mb - ma)
    if max(ratio, 1 / ratio) <= factor:
        return None
    return {"index": k, "before": 10 ** ma, "after": 10 ** mb, "factor": ratio}


def _in_history(path: Path, results_dir: Path) -> bool:
    with hist.reading(path) as db:
        return db is not None and db.execute("SELECT 1 FROM runs WHERE results_dir = ? LIMIT 1",
                          (str(Path(results_dir).resolve()),)).fetchone() is not None


def series(history: Path | None, results_dir: Path, summary: dict,
           bench: dict | None) -> tuple[dict, int, bool]:
    """Per cell ``{"acc": [(when, value)], "speed": [(when, value)]}``, the number of runs
    and whether this results folder was appended (it is not yet in the history while the
    suite writes its report)."""
    cells: dict[str, dict] = {}
    n_runs = 0
    if history is not None and (Path(history).exists() or Path(history).is_symlink()):
        raw = hist.trends(history, last=LAST_RUNS)
        with hist.reading(history) as db:
            n_runs = 0 if db is None else min(
                LAST_RUNS, db.execute("SELECT COUNT(*) FROM runs").fetchone()[0])
        for cell, t in raw.items():
            cells[cell] = {
                "acc": [(g, v) for g, v in zip(t["generated"], t["worst_rel"], strict=False)
                        if isinstance(v, int | float) and v > 0],
                "speed": [(g, v) for g, v in zip(t["bench_generated"], t["median_s"],
                                                 strict=False)
                          if isinstance(v, int | float) and v > 0]}
        appended = not _in_history(history, results_dir)
    else:
        appended = True
    if appended:
        n_runs += 1
        when = summary.get("generated") or "this run"
        for r in summary.get("records") or []:
            v = worst_rel(r)
            if v:
                cells.setdefault(f"{r.get('case')}/{r.get('engine')}",
                                 {"acc": [], "speed": []})["acc"].append((when, v))
        for r in (bench or {}).get("records") or []:
            ss = samples(r)
            v = statistics.median(ss) if ss else r.get("wall_median_s") or r.get("wall_time_s")
            if isinstance(v, int | float) and v > 0:
                cells.setdefault(f"{r.get('case')}/{r.get('engine')}",
                                 {"acc": [], "speed": []})["speed"].append(
                                     ((bench or {}).get("generated") or when, v))
    return cells, n_runs, appended


def section(history: Path | None, results_dir: Path, summary: dict, bench: dict | None,
            cases_order: list[str], engine_order, colors: dict[str, str], layout, anchor,
            fmt_num, fmt_time, fmt_when) -> dict:
    """Template context: ``{"message", "steps": [...], "groups": [(case, anchor, fig)]}``;
    figures are plotly Figures (made lazy by the caller)."""
    where = str(history) if history is not None else "no history database"
    try:
        cells, n_runs, appended = series(history, results_dir, summary, bench)
    except (sqlite3.Error, ValueError, KeyError, TypeError) as exc:
        return {"message": f"History unreadable ({where}): {exc}", "steps": [], "groups": [],
                "n_runs": 0}
    if history is None or not Path(history).is_file():
        return {"message": f"No history ({where}): trends appear once the suite has recorded "
                           "two runs.", "steps": [], "groups": [], "n_runs": n_runs}
    if n_runs < 2:
        return {"message": f"Fewer than two runs in the history ({where}): no trend yet.",
                "steps": [], "groups": [], "n_runs": n_runs}
    by_case: dict[str, dict[str, dict]] = {}
    for cell, s in cells.items():
        case, _, eng = cell.partition("/")
        by_case.setdefault(case, {})[eng] = s
    order = [c for c in cases_order if c in by_case] + sorted(
        c for c in by_case if c not in cases_order)
    steps, groups = [], []
    for case in order:
        fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.08)
        for eng in engine_order(by_case[case]):
            s = by_case[case][eng]
            for row, key, factor, fmt in ((1, "acc", ACCURACY_FACTOR, fmt_num),
                                          (2, "speed", SPEED_FACTOR, fmt_time)):
                pts = s[key]
                if not pts:
                    continue
                x, y = [p[0] for p in pts], [p[1] for p in pts]
                fig.add_trace(go.Scatter(
                    x=x, y=y, name=eng, legendgroup=eng, showlegend=row == 1 or not s["acc"],
                    mode="lines+markers", line={"color": colors.get(eng, "#444"), "width": 1.4},
                    marker={"size": 5},
                    hovertemplate=f"{eng}<br>%{{x}}<br>%{{y:.3g}}<extra></extra>"),
                    row=row, col=1)
                cp = change_point(y, factor)
                if cp:
                    k = cp["index"]
                    what = "worst relative error" if key == "acc" else "median wall time"
                    worse = cp["factor"] > 1
                    steps.append({"case": case, "engine": eng, "what": what,
                                  "when": fmt_when(x[k]), "before": fmt(cp["before"]),
                                  "after": fmt(cp["after"]), "factor": f"{cp['factor']:.3g}×",
                                  "worse": worse, "anchor": anchor("trend", case)})
                    fig.add_trace(go.Scatter(
                        x=[x[k]], y=[y[k]], mode="markers", legendgroup=eng, showlegend=False,
                        marker={"symbol": "star", "size": 15, "color": colors.get(eng, "#444"),
                                "line": {"color": "#000", "width": 1}},
                        hovertemplate=(f"{eng}: step in {what}<br>median {fmt(cp['before'])}"
                                       f" → {fmt(cp['after'])} ({cp['factor']:.3g}×)"
                                       "<extra></extra>")), row=row, col=1)
        fig.update_yaxes(type="log", title_text="worst rel. error", row=1, col=1)
        fig.update_yaxes(type="log", title_text="median wall [s]", row=2, col=1)
        layout(fig, 460)
        groups.append({"case": case, "anchor": anchor("trend", case), "fig": fig})
    note = " (the last point is this run, not yet recorded)" if appended else ""
    return {"message": "", "steps": steps, "groups": groups, "n_runs": n_runs,
            "source": f"{where}, last {n_runs} runs{note}"}
