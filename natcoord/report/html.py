"""Self-contained HTML report of a results directory.

Input (the runner's contract, README "Commands"):

- ``DIR/summary.json``: header fields and one record per case x engine;
- ``DIR/results/<case>/<engine>.csv``: column ``t`` then one column per channel;
- ``references/<case>.csv`` and ``references/<case>.json`` (data and provenance);
- optionally ``DIR/bench.json`` (speed benchmark, work-precision sweeps);
- optionally the history database (``reports/history.db``: trends over the last runs).

Output: ``DIR/index.html``, one file that works offline: plotly.js is embedded once,
inline, and every figure travels in one compressed blob (16-bit arrays) and is drawn when the
section holding it is opened (:mod:`natcoord.report.lazy`), so the page loads fast however
many cases it has.
"""

from __future__ import annotations

import gzip
import json
import math
import re
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

import jinja2
import numpy as np
import pandas as pd
import plotly.offline
from markupsafe import Markup, escape

from ..case.mechanism import FORCE_KINDS
from ..engines import engine_names
from ..errors import NatcoordError
from . import balance, changes, front, redundant, speed, trends
from .lazy import FigureStore, to_text
from .look import style
from .sampling import MAX_POINTS, envelope, minmax, series  # noqa: F401 (MAX_POINTS: tests)

# Okabe & Ito's colour-blind-safe palette (its black left to the reference, its yellow too
# pale for a line on white), then Tol's "muted" colours, in the registry's engine order
ENGINE_COLORS = {
    "natcoord": "#0072B2",   # blue
    "mujoco": "#E69F00",     # orange
    "pinocchio": "#009E73",  # bluish green
    "exudyn": "#D55E00",     # vermillion
    "dart": "#CC79A7",       # reddish purple
    "simbody": "#56B4E9",    # sky blue
    "drake": "#882255",      # wine (Tol)
    "pybullet": "#999933",   # olive (Tol)
}
_EXTRA_COLORS = ["#332288", "#44AA99", "#DDCC77", "#AA4499", "#7f7f7f"]
REFERENCE_COLOR = "#222222"
FIG_HEIGHT = 480  # px, every channel figure (grid rows line up)
ON_REFERENCE = 1e-3  # an engine within this fraction of the reference's range is drawn with
# the reference's samples (a pixel of a figure's height; its error panel shows the rest)
KIND_ORDER = {"angle": 0, "position": 1, "velocity": 2, "energy": 3, "reaction": 4}
PLOT_CONFIG = {
    "displaylogo": False,
    "responsive": True,
    "modeBarButtonsToRemove": ["lasso2d", "select2d", "autoScale2d"],
    "toImageButtonOptions": {"format": "svg"},
}

_TEMPLATES = Path(__file__).with_name("templates")


# ---------------------------------------------------------------- number formatting


def num(x: Any) -> float | None:
    """A finite float, or None for null / NaN / inf / non-numbers."""
    if x is None or isinstance(x, bool):
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def fmt_num(x: Any, unit: str = "") -> str:
    """3 significant digits; scientific outside [0.01, 1e4); an em dash for no value."""
    v = num(x)
    if v is None:
        return "—"
    if v == 0 or 1e-2 <= abs(v) < 1e4:
        s = f"{v:.3g}"
    else:
        m, e = f"{v:.2e}".split("e")
        s = f"{m}e{int(e)}"
    s = s.replace("-", "−")
    return f"{s}\u00a0{unit}" if unit else s


def fmt_time(x: Any) -> str:
    """A duration in seconds with an SI prefix and 3 significant digits."""
    v = num(x)
    if v is None:
        return "—"
    a = abs(v)
    for scale, unit in ((1.0, "s"), (1e-3, "ms"), (1e-6, "µs"), (1e-9, "ns")):
        if a >= scale or scale == 1e-9:
            if a >= 1e4 and scale == 1.0:
                return fmt_num(v, "s")
            return f"{v / scale:.3g}\u00a0{unit}"
    return fmt_num(v, "s")  # pragma: no cover


def fmt_int(x: Any) -> str:
    v = num(x)
    return "—" if v is None else f"{int(round(v)):,}".replace(",", "\u202f")


def fmt_ratio(x: Any) -> str:
    v = num(x)
    return "—" if v is None else f"{v:.3g}×"


def fmt_value(x: Any) -> str:
    """Provenance / settings values: dicts as ``k = v`` lists, floats with 3 digits."""
    if isinstance(x, dict):
        return ", ".join(f"{k} = {fmt_value(v)}" for k, v in x.items()) or "—"
    if isinstance(x, list | tuple):
        return ", ".join(fmt_value(v) for v in x) or "—"
    if isinstance(x, float):
        return fmt_num(x)
    if x is None:
        return "—"
    return str(x)


def fmt_when(iso: str | None) -> str:
    if not iso:
        return "unknown time"
    try:
        d = datetime.fromisoformat(str(iso).replace("Z", "+00:00"))
    except ValueError:
        return str(iso)
    tz = d.strftime("%Z") or ""
    return d.strftime("%Y-%m-%d %H:%M:%S") + (f" {tz}" if tz else "")


def anchor(*parts: str) -> str:
    return "-".join(re.sub(r"[^A-Za-z0-9_-]+", "_", p) for p in parts)


# ---------------------------------------------------------------- reading the inputs


def _read_json(path: Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)  # accepts NaN / Infinity as written by Python's json


def _read_csv(path: Path) -> pd.DataFrame | None:
    if not path.is_file():
        return None
    try:
        df = pd.read_csv(path)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, OSError):
        return None
    if "t" not in df.columns:
        return None
    return df.apply(pd.to_numeric, errors="coerce")


def _engine_order(names: Iterable[str]) -> list[str]:
    """The engines of a report in the registry's order (built-ins, then plug-ins by name),
    then any other name a results folder holds (an engine not installed here), sorted."""
    names = list(dict.fromkeys(names))
    known = [e for e in engine_names() if e in names]
    return known + sorted(n for n in names if n not in known)


def _engine_colors(engines: list[str]) -> dict[str, str]:
    """A colour per engine, the same in every report of this installation: fixed ones for
    the first engines, then the palette in registry order, then the names it lacks."""
    colors = dict(ENGINE_COLORS)
    extra = iter(_EXTRA_COLORS * 10)
    for e in [*engine_names(), *engines]:
        if e not in colors:
            colors[e] = next(extra)
    return colors


# ---------------------------------------------------------------- cells and verdicts

_CELL = {
    # key: (label, css class)
    "pass": ("pass", "pass"),
    "fail": ("fail", "fail"),
    "failed": ("failed", "failed"),
    "unsupported": ("unsupported", "unsupported"),
    "skipped": ("skipped", "skipped"),
    "no-reference": ("no reference", "noref"),
    "n/a": ("not judged", "na"),
    "missing": ("not run", "missing"),
}


def _failing_channels(rec: dict) -> list[str]:
    out = []
    for name, ch in (rec.get("channels") or {}).items():
        if ch.get("pass") is False and ch.get("determined", True):
            unit = ch.get("unit") or ""
            out.append(
                f"{name}: {fmt_num(ch.get('max_abs'), unit)} > {fmt_num(ch.get('tolerance'), unit)}"
            )
    return out


def cell_for(rec: dict | None) -> dict:
    """Matrix cell of one case x engine record: label, css class and reason text."""
    if rec is None:
        label, css = _CELL["missing"]
        return {"key": "missing", "label": label, "css": css, "reason": "no record", "note": None}
    status = str(rec.get("status") or "").lower()
    verdict = str(rec.get("verdict") or "").lower()
    reason = str(rec.get("reason") or "").strip()
    if status in ("failed", "unsupported", "skipped"):
        key = status
    elif status == "ok":
        key = verdict if verdict in ("pass", "fail", "no-reference", "n/a") else "n/a"
    else:
        key, reason = "failed", reason or f"unknown status {status!r}"
    if key == "fail":
        bad = _failing_channels(rec)
        reason = "; ".join(filter(None, ["; ".join(bad), reason]))
    elif key == "no-reference" and not reason:
        reason = "no stored reference for this case: errors not computed"
    label, css = _CELL[key]
    return {"key": key, "label": label, "css": css, "reason": reason, "note": None}


def as_judged(records: list[dict], verdict) -> tuple[list[dict], list[str]]:
    """The records as the gate judged them from the result files
    (:func:`natcoord.suite.gate.judge`'s ``verdict``; the summary's own verdicts and
    errors are never shown then): a cell judged gets the gate's verdict and recomputed
    channels, a cell whose files cannot be trusted fails with the gate's reason. Also
    returns the gate's lines that fail the page: about the folder as a whole (a result
    file without its record, a file natcoord wrote that is gone ...) and about a cell it
    cannot judge because a file it judges with cannot be trusted (a damaged reference)."""
    out, faults = [], list(verdict.folder_faults)
    for r in records:
        key = f"{r.get('case')}/{r.get('engine')}"
        said = "; ".join(verdict.said.get(key, ()))
        outcome = verdict.outcome.get(key) if r.get("status") == "ok" else None
        if outcome in ("pass", "fail"):  # what its channels do not show: growth over the
            r = {**r, "verdict": outcome, "channels": verdict.channels.get(key, {}),
                 "reason": said or r.get("reason")}  # baseline
        elif outcome == "bad evidence":
            r = {**r, "verdict": "fail", "channels": {}, "reason": said}
        elif outcome is not None:  # cannot judge (no reference, no tolerance ...)
            r = {**r, "verdict": "no-reference" if r.get("verdict") == "no-reference"
                 else "n/a", "channels": {}, "reason": said or r.get("reason")}
            faults += [f"{key}: {line}" for line in verdict.said.get(key, ())
                       if f"{key}: {line}" in verdict.faults]
        out.append(r)
    return out, faults


def overall_verdict(records: list[dict], faults: list[str] = ()) -> dict:
    """The page's verdict over the cells; ``faults``: lines about evidence that cannot be
    trusted (:func:`as_judged`), each of which fails it. PASS only when every cell that
    ran was judged and passed, as the gate's exit 0."""
    cells = [cell_for(r) for r in records]
    counts: dict[str, int] = {}
    for c in cells:
        counts[c["key"]] = counts.get(c["key"], 0) + 1
    n = len(cells)
    bad = [
        f"{r.get('case')} / {r.get('engine')}"
        for r, c in zip(records, cells, strict=True)
        if c["key"] in ("fail", "failed")
    ] + list(faults)
    if not n:
        state, word = "empty", "NO RESULTS"
    elif bad:
        state, word = "fail", "FAIL"
    elif counts.get("pass", 0) == 0:
        state, word = "incomplete", "NOT GATED"
    elif counts.get("no-reference", 0) + counts.get("n/a", 0):  # the gate fails (exit 2)
        state, word = "incomplete", "PARTLY GATED"  # while a cell that ran is not judged
    else:
        state, word = "pass", "PASS"
    parts = []
    for key in ("pass", "fail", "failed", "no-reference", "n/a", "unsupported", "skipped"):
        if counts.get(key):
            parts.append(f"{counts[key]} {_CELL[key][0]}")
    return {
        "state": state,
        "word": word,
        "n": n,
        "summary": ", ".join(parts),
        "bad": bad,
        "counts": counts,
    }


# ---------------------------------------------------------------- plotting


def _on_reference_times(ref_t: np.ndarray, t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Engine series at the reference's sample times (NaN outside the engine's span)."""
    if len(t) == len(ref_t) and np.allclose(t, ref_t, rtol=0, atol=1e-12):
        return y
    ok = np.isfinite(t) & np.isfinite(y)
    if ok.sum() < 2:
        return np.full_like(ref_t, np.nan, dtype=float)
    out = np.interp(ref_t, t[ok], y[ok])
    out[(ref_t < t[ok][0] - 1e-12) | (ref_t > t[ok][-1] + 1e-12)] = np.nan
    return out


def channel_figure(
    name: str,
    unit: str,
    ref: pd.DataFrame | None,
    runs: dict[str, pd.DataFrame],
    colors: dict[str, str],
    undetermined: bool = False,
) -> dict:
    """One figure per channel: values over the reference (dashed) and |error| (log), as a
    plotly spec ``{"data", "layout"}`` (written as data: plotly's figure objects validate
    every property, which cost most of a report's time)."""
    has_ref = ref is not None and name in ref.columns
    ref_t = ref_y = None
    if has_ref:
        ref_t = ref["t"].to_numpy(float)
        ref_y = ref[name].to_numpy(float)
    errors: dict[str, np.ndarray] = {}
    if has_ref and not undetermined:  # an undetermined multiplier has no "error"
        for eng, df in runs.items():
            if name in df.columns:
                y = _on_reference_times(ref_t, df["t"].to_numpy(float), df[name].to_numpy(float))
                e = np.abs(y - ref_y)
                e[e <= 0] = np.nan  # log axis: exact agreement is not drawable
                if np.any(np.isfinite(e)):
                    errors[eng] = e
    two = bool(errors)
    data: list[dict] = []

    def add(trace: dict, row: int) -> None:
        if two:
            trace |= {"xaxis": "x" if row == 1 else "x2", "yaxis": "y" if row == 1 else "y2"}
        data.append({"type": "scatter", "mode": "lines", **trace})

    for eng, df in runs.items():
        if name not in df.columns:
            continue
        t = df["t"].to_numpy(float)
        y = df[name].to_numpy(float)
        if not np.any(np.isfinite(y)):
            continue
        hover = f"{eng}<br>t=%{{x:.4g}} s<br>%{{y:.4g}}<extra></extra>"
        err = errors.get(eng)
        if err is not None and np.nanmax(err) <= ON_REFERENCE * np.ptp(ref_y[np.isfinite(ref_y)]):
            # closer to the reference than a line is wide: drawn with the reference's
            # samples (stored once), its error in the panel below
            t, y = ref_t, ref_y
            hover = (f"{eng}: within {fmt_num(np.nanmax(err), unit)} of the reference"
                     "<br>t=%{x:.4g} s<br>%{y:.4g}<extra></extra>")
        x, y = minmax(t, y)
        add({"x": x, "y": y, "name": eng, "legendgroup": eng,
             "line": {"color": colors[eng], "width": 1.5}, "hovertemplate": hover}, 1)
    if has_ref:  # drawn last: its dashes stay visible over engines that agree with it
        x, y = minmax(ref_t, ref_y)
        add({"x": x, "y": y, "name": "reference", "legendgroup": "reference",
             "line": {"color": REFERENCE_COLOR, "dash": "dash", "width": 1.8},
             "hovertemplate": "reference<br>t=%{x:.4g} s<br>%{y:.4g}<extra></extra>"}, 1)
    for eng, e in errors.items():
        te, ee = envelope(ref_t, e)
        add({"x": series(te), "y": series(ee), "name": eng, "legendgroup": eng,
             "showlegend": False, "line": {"color": colors[eng], "width": 1.2},
             "hovertemplate": f"{eng} |error|<br>t=%{{x:.4g}} s<br>%{{y:.3g}}<extra></extra>"},
            2)
    ulabel = f" [{unit}]" if unit else ""
    axis = {
        "showline": True, "linecolor": "#999", "ticks": "outside", "tickcolor": "#999",
        "gridcolor": "#e8e8e8", "zeroline": False, "mirror": True,
        "exponentformat": "power", "automargin": True,  # tick labels are never clipped
    }
    layout = {
        "template": {"data": {"scatter": [{"type": "scatter"}]}},  # plotly's "none"
        "height": FIG_HEIGHT,
        "margin": {"l": 64, "r": 14, "t": 30, "b": 70},
        "font": {"family": "system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif",
                 "size": 12},
        "legend": {"orientation": "h", "x": 0, "xanchor": "left",
                   "y": -50 / (FIG_HEIGHT - 100), "yanchor": "top", "font": {"size": 11}},
        "hovermode": "closest", "paper_bgcolor": "white", "plot_bgcolor": "white",
    }
    if two:  # two rows sharing the time axis, 60 % / 40 % of the height, 7 % apart
        layout |= {
            "xaxis": {"anchor": "y", "domain": [0.0, 1.0], "matches": "x2",
                      "showticklabels": False, **axis},
            "yaxis": {"anchor": "x", "domain": [0.442, 1.0], **axis,
                      "title": {"text": f"{name}{ulabel}"}},
            "xaxis2": {"anchor": "y2", "domain": [0.0, 1.0], **axis,
                       "title": {"text": "t [s]"}},
            "yaxis2": {"anchor": "x2", "domain": [0.0, 0.372], **axis, "type": "log",
                       "title": {"text": f"|error|{ulabel}"}}}
    else:
        layout |= {"xaxis": {**axis, "title": {"text": "t [s]"}},
                   "yaxis": {**axis, "title": {"text": f"{name}{ulabel}"}}}
    if not data:
        layout["annotations"] = [{"text": "no data", "showarrow": False, "xref": "paper",
                                  "yref": "paper", "x": 0.5, "y": 0.5}]
    return {"data": data, "layout": layout}


# ---------------------------------------------------------------- building the page


def _channel_meta(records: list[dict], names: list[str]) -> dict[str, dict]:
    meta: dict[str, dict] = {}
    for name in names:
        kind, unit, determined = None, None, True
        for r in records:
            ch = (r.get("channels") or {}).get(name)
            if not ch:
                continue
            kind = kind or ch.get("kind")
            unit = unit or ch.get("unit")
            if ch.get("determined") is False:
                determined = False
        meta[name] = {"kind": kind or "other", "unit": unit or "", "determined": determined}
    return meta


def _channel_cell(ch: dict | None, rec: dict) -> dict:
    status = str(rec.get("status") or "")
    if status != "ok":
        return {"css": "na", "text": "—", "sub": "", "title": f"{status}"}
    if not ch:
        return {"css": "na", "text": "—", "sub": "", "title": "channel not reported"}
    unit = ch.get("unit") or ""
    text = fmt_num(ch.get("max_abs"), unit)
    tol = num(ch.get("tolerance"))
    rel = num(ch.get("max_rel"))
    sub = []
    if tol is not None:
        sub.append(f"tol {fmt_num(tol, unit)}")
    rel_text = f"; {fmt_num(rel)} of its range" if rel is not None else ""
    if ch.get("determined") is False:
        css, title = "undet", "undetermined redundant reaction: shown, not gated"
        sub.append("not gated")
    elif ch.get("pass") is True:
        css, title = "pass", "within tolerance"
    elif ch.get("pass") is False:
        css, title = "fail", "outside tolerance"
    else:
        css, title = "na", "no tolerance or no reference: not gated"
    return {"css": css, "text": text, "sub": " · ".join(sub), "title": title + rel_text}


def _sim_time(rec: dict, run: pd.DataFrame | None) -> float | None:
    s = num(rec.get("sim_time_s"))
    if s is None and run is not None and len(run):
        t = run["t"].to_numpy(float)
        s = num(np.nanmax(t) - np.nanmin(t)) if np.any(np.isfinite(t)) else None
    return s if s else None


def _speed_row(rec: dict, run: pd.DataFrame | None, base: float | None) -> dict:
    sim = _sim_time(rec, run)
    wall = num(rec.get("wall_time_s"))
    wps = wall / sim if (wall is not None and sim) else None
    us = num(rec.get("us_per_step"))
    if us is None and wall is not None and num(rec.get("n_steps")):
        us = 1e6 * wall / float(rec["n_steps"])
    return {
        "engine": rec.get("engine", ""),
        "status": rec.get("status", ""),
        "build": fmt_time(rec.get("build_time_s")),
        "wall": fmt_time(wall),
        "wall_per_sim": fmt_time(wps),
        "us_per_step": fmt_time(us * 1e-6 if us is not None else None),
        "steps": fmt_int(rec.get("n_steps")) if num(rec.get("n_steps")) else "—",
        "sim": fmt_time(sim),
        "ratio": fmt_ratio(wps / base) if (wps is not None and base) else "—",
        "_wps": wps,
    }


def _reference_info(references: Path, case: str) -> tuple[pd.DataFrame | None, dict | None]:
    ref = _read_csv(references / f"{case}.csv")
    meta_path = references / f"{case}.json"
    meta = None
    if meta_path.is_file():
        try:
            meta = _read_json(meta_path)
        except (OSError, ValueError):
            meta = {"error": f"unreadable provenance file {meta_path.name}"}
    return ref, meta


def _provenance_items(meta: dict | None) -> list[tuple[str, str]]:
    if not meta:
        return []
    order = ["method", "created", "max_phi", "settings", "tolerances", "versions"]
    keys = [k for k in order if k in meta] + [
        k for k in meta if k not in order and k not in ("case", "independent")
    ]
    return [(k.replace("_", " "), fmt_value(meta[k])) for k in keys]


def _independent_line(meta: dict | None, units: dict[str, str]) -> str:
    """'independent check: <method>, max |diff| theta 4.1e-13 rad, ...' from the
    reference's ``independent`` field ('' when it has none; escaped by the template)."""
    ind = (meta or {}).get("independent")
    if not isinstance(ind, dict):
        return ""
    diffs = ind.get("max_abs_diff") if isinstance(ind.get("max_abs_diff"), dict) else {}
    parts = [f"{k} {num(v):.2g} {units.get(k, '')}".rstrip() for k, v in diffs.items()
             if num(v) is not None]
    exact = ind.get("exact_work") if isinstance(ind.get("exact_work"), dict) else {}
    extra = [f"{k} {num(v):.2g} J" for k, v in exact.items() if num(v) is not None]
    return "independent check: " + ", ".join(
        [str(ind.get("method", "?")), "max |diff| " + ", ".join(parts or ["—"])]) + (
        "; against the exact dampers' work " + ", ".join(extra) if extra else "")


def _read_bench(results_dir: Path) -> tuple[dict | None, str]:
    path = results_dir / "bench.json"
    if not path.is_file():
        return None, ""
    try:
        data = _read_json(path)
    except (OSError, ValueError) as exc:
        return None, f"unreadable bench.json: {exc}"
    return (data, "") if isinstance(data, dict) else (None, "bench.json is not an object")


def _speed_context(bench: dict | None, bench_error: str, by_key: dict, case_names: list[str],
                   speed_groups: list[dict], colors: dict[str, str],
                   figures: FigureStore) -> dict:
    """The speed section: time to accuracy (headline), work-precision diagrams and the
    benchmark at each engine's own settings, all from bench.json; the run's own timings
    only when there is no benchmark."""
    if bench is None:
        return {"source": "run", "error": bench_error, "tta": None, "wp": [], "own": [],
                "cost": [], "cold": None, "score": [],
                "run": speed_groups, "machine": [], "how": ""}
    tta = speed.time_to_accuracy(bench, case_names, anchor, fmt_time, fmt_ratio)
    wp = [{"case": c, "anchor": anchor("wp", c), "fig": figures.add(f, PLOT_CONFIG)}
          for c, f in speed.work_precision_figures(bench, case_names, colors, style)]
    own = speed.own_settings(bench, by_key, case_names, _engine_order, anchor, fmt_time,
                             fmt_num, fmt_ratio, fmt_int)
    reps = sorted({int(r["repeats"]) for r in bench.get("records") or []
                   if isinstance(r, dict) and num(r.get("repeats"))})
    has_samples = any(r.get("samples_s") for r in bench.get("records") or []
                      if isinstance(r, dict))
    runs = "–".join(str(r) for r in dict.fromkeys([reps[0], reps[-1]])) if reps else "?"
    when = f" of {escape(fmt_when(bench['generated']))}" if bench.get("generated") else ""
    batched = any(r.get("batch_runs") for r in bench.get("records") or []
                  if isinstance(r, dict))
    how = (f"<code>bench.json</code>{when}: " + (
        f"every cell timed in {runs} sample(s), each a calibrated batch (the stepping "
        "repeated for at least 0.1 s; the sample is its time per run) in one process "
        "pinned to one core; <i>best</i> and <i>median</i> over those samples; "
        if batched else
        f"every cell run {runs} time(s), each run a whole simulation in a fresh process "
        "pinned to one core; <i>best</i> and <i>median</i> over those repeats; ")
        + ("<i>spread</i>: fastest–slowest repeat (<code>samples_s</code>)" if has_samples
           else "<i>spread</i>: slowest over best (no per-repeat samples recorded)"))
    return {"source": "bench", "error": bench_error, "tta": tta, "wp": wp, "own": own,
            "cost": speed.cost_explained(bench, case_names, _engine_order, anchor, fmt_time,
                                         fmt_int),
            "cold": speed.cold_start(bench, fmt_time),
            "score": speed.scoring(bench, case_names, _engine_order, anchor, fmt_time, fmt_num),
            "run": [], "machine": [(k, fmt_value(v)) for k, v in
                                   (bench.get("machine") or {}).items()],
            "how": Markup(how)}


def build_context(results_dir: Path, references: Path = Path("references"),
                  history: Path | None = None, verdict=None) -> dict:
    """Everything the template needs, as plain values (no file access in the template);
    ``verdict``: the gate's on this folder (:func:`as_judged`), else the summary's
    records are shown as they are."""
    results_dir = Path(results_dir)
    references = Path(references)
    summary_path = results_dir / "summary.json"
    if not summary_path.is_file():
        raise FileNotFoundError(f"{summary_path} not found: run `natcoord run` first")
    summary = _read_json(summary_path)
    records = [r for r in summary.get("records") or [] if isinstance(r, dict)]
    records, faults = as_judged(records, verdict) if verdict is not None else (records, [])

    case_names = list(dict.fromkeys(str(r.get("case", "")) for r in records))
    engines = _engine_order(str(r.get("engine", "")) for r in records)
    colors = _engine_colors(engines)
    by_key = {(str(r.get("case")), str(r.get("engine"))): r for r in records}

    figures = FigureStore()
    footnotes: list[dict] = []
    matrix = []
    cases = []
    speed_groups = []
    for case in case_names:
        crecs = [by_key[(case, e)] for e in engines if (case, e) in by_key]
        case_anchor = anchor("case", case)
        # matrix row
        row = []
        for e in engines:
            cell = cell_for(by_key.get((case, e)))
            cell["engine"] = e
            cell["color"] = colors[e]
            if cell["reason"] and cell["key"] != "missing":
                footnotes.append({"n": len(footnotes) + 1, "case": case, "engine": e,
                                  "label": cell["label"], "css": cell["css"],
                                  "reason": cell["reason"]})
                cell["note"] = len(footnotes)
            row.append(cell)
        description = next((r.get("description") for r in crecs if r.get("description")), "")
        matrix.append({"case": case, "anchor": case_anchor, "cells": row,
                       "description": description})

        # data
        ref, ref_meta = _reference_info(references, case)
        runs: dict[str, pd.DataFrame] = {}
        for r in crecs:
            df = _read_csv(results_dir / "results" / case / f"{r.get('engine')}.csv")
            if df is not None:
                runs[str(r.get("engine"))] = df
        names: list[str] = []
        if ref is not None:
            names += [c for c in ref.columns if c != "t"]
        for df in runs.values():
            names += [c for c in df.columns if c != "t"]
        for r in crecs:
            names += list((r.get("channels") or {}).keys())
        names = list(dict.fromkeys(names))
        meta = _channel_meta(crecs, names)
        names.sort(key=lambda n: (KIND_ORDER.get(meta[n]["kind"], 5), not meta[n]["determined"]))

        ran = [r for r in crecs]
        table = []
        for n in names:
            m = meta[n]
            table.append({
                "name": n, "unit": m["unit"], "kind": m["kind"], "determined": m["determined"],
                "anchor": anchor("fig", case, n),
                "cells": [_channel_cell((r.get("channels") or {}).get(n), r) for r in ran],
            })
        plots_runs = {e: runs[e] for e in engines if e in runs}
        trajectories, reactions = [], []
        for n in names:
            m = meta[n]
            fig = {
                "name": n, "unit": m["unit"], "determined": m["determined"],
                "anchor": anchor("fig", case, n),
                "fig": figures.add(channel_figure(n, m["unit"], ref, plots_runs, colors,
                                                  not m["determined"]), PLOT_CONFIG,
                                   FIG_HEIGHT),
            }
            (reactions if m["kind"] in FORCE_KINDS else trajectories).append(fig)

        notes = _grouped_notes(crecs)
        tol_reasons = [(str(r.get("engine")), str(r.get("tolerance_reason")))
                       for r in crecs if r.get("tolerance_reason")]
        details = []
        for r in crecs:
            details.append({
                "engine": r.get("engine"),
                "version": r.get("engine_version") or "",
                "settings": [(k, fmt_value(v)) for k, v in (r.get("settings") or {}).items()],
                "counters": [(k, fmt_value(v)) for k, v in (r.get("counters") or {}).items()],
            })

        base = None
        nat = by_key.get((case, "natcoord"))
        if nat is not None:
            base = _speed_row(nat, runs.get("natcoord"), None)["_wps"]
        speed_rows = [_speed_row(r, runs.get(str(r.get("engine"))), base) for r in crecs]
        speed_groups.append({"case": case, "anchor": case_anchor, "rows": speed_rows})

        balances = balance.section(crecs, plots_runs, ref, colors, fmt_num,
                                   lambda f: figures.add(f, PLOT_CONFIG, balance.HEIGHT))
        redundancy = redundant.section(case, crecs, runs, ref, ref_meta, results_dir, references,
                                       colors, fmt_num, figures.add)
        cases.append({
            "redundancy": redundancy,
            "name": case,
            "anchor": case_anchor,
            "description": description,
            "cells": row,
            "columns": [{"engine": r.get("engine"), "color": colors[str(r.get("engine"))],
                         "cell": cell_for(r)} for r in ran],
            "table": table,
            "trajectories": trajectories,
            "reactions": reactions,
            "balances": balances,
            "any_undetermined": any(not f["determined"] for f in reactions + trajectories),
            "has_reference": ref is not None,
            "reference_file": f"{case}.csv",
            "provenance": _provenance_items(ref_meta),
            "independent": _independent_line(ref_meta, {n: meta[n]["unit"] for n in names}),
            "notes": notes,
            "tolerance_reasons": tol_reasons,
            "details": details,
            "n_samples": None if ref is None else len(ref),
        })

    versions: dict[str, list[str]] = {}
    for r in records:
        v = str(r.get("engine_version") or "")
        if v:
            versions.setdefault(str(r.get("engine")), [])
            if v not in versions[str(r.get("engine"))]:
                versions[str(r.get("engine"))].append(v)
    engine_versions = [(e, ", ".join(versions.get(e, [])) or "—") for e in engines]
    machine = summary.get("machine") or {}

    bench, bench_error = _read_bench(results_dir)
    speed_ctx = _speed_context(bench, bench_error, by_key, case_names, speed_groups, colors,
                               figures)
    amap = front.accuracy_map(by_key, case_names, engines, cell_for, anchor, fmt_num)
    for row, mrow in zip(amap, matrix, strict=True):
        for cell, mcell in zip(row["cells"], mrow["cells"], strict=True):
            cell["note"] = mcell["note"]
    front_ctx = {
        "map": amap, "legend": front.legend(),
        "equal": front.equal_accuracy(bench, case_names, engines, anchor, fmt_time, fmt_ratio),
        "profiles": front.profiles(records, bench, engines, fmt_num, fmt_ratio),
        "changes": changes.section(history, results_dir, summary, bench, fmt_when, fmt_num,
                                   fmt_time),
    }
    trend = trends.section(history, results_dir, summary, bench, case_names, _engine_order,
                           colors, style, anchor, fmt_num, fmt_time, fmt_when)
    for g in trend["groups"]:
        g["fig"] = figures.add(g["fig"], PLOT_CONFIG)

    return {
        "title": "natcoord validation report",
        "generated": fmt_when(summary.get("generated")),
        "generated_iso": str(summary.get("generated") or ""),
        "version": str(summary.get("natcoord_version") or "unknown"),
        "machine": [(k.replace("_", " "), fmt_value(v)) for k, v in machine.items()],
        "engine_versions": engine_versions,
        "engines": [{"name": e, "color": colors[e]} for e in engines],
        "overall": overall_verdict(records, faults),
        "gate_notes": list(verdict.notes) if verdict is not None else [],  # judged, but
        "matrix": matrix,  # with a caveat (a case file changed since the run)
        "footnotes": footnotes,
        "cases": cases,
        "speed": speed_ctx,
        "front": front_ctx,
        "bench": bench is not None or bool(bench_error),
        "trends": trend,
        "figures_gz": figures.blob(),
        "n_figures": len(figures),
        "references_dir": str(references),
        "results_dir": str(results_dir),
    }


def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(_TEMPLATES)),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = fmt_num
    env.filters["time"] = fmt_time
    return env


PLOTLY_BASIC = Path(__file__).with_name("vendor") / "plotly-basic.min.js"


def plotly_js() -> str:
    """plotly.js for the page: the basic bundle (scatter, bar, pie; 1.2 MB) shipped beside
    this module, at the version of the plotly package's own bundle (4.8 MB), which is the
    fallback when the versions differ or the file is missing."""
    try:
        basic = PLOTLY_BASIC.read_text(encoding="utf-8")
    except OSError:
        return plotly.offline.get_plotlyjs()
    m = re.search(r"plotly\.js \(basic - minified\) v(\S+)", basic[:300])
    if m is None or m.group(1) != plotly.offline.get_plotlyjs_version():
        return plotly.offline.get_plotlyjs()
    return basic


def render(context: dict) -> str:
    """The page; plotly.js travels gzip-compressed in base85 (1.2 MB -> 0.49 MB), unpacked
    by the browser's DecompressionStream when the page loads (report.js.j2)."""
    gz = gzip.compress(plotly_js().encode("utf-8"), compresslevel=9, mtime=0)
    template = _environment().get_template("report.html.j2")
    page = template.render(plotly_gz=Markup(to_text(gz)), **context)
    return re.sub(r"\n[ \t]+", "\n", page)  # indentation: the page has no <pre>


def _replaceable(out: Path) -> bool:
    """Whether the page ``out`` may be (re)written: absent, or natcoord's: a file its
    folder's marker lists, or whose head names natcoord as its generator (a report of a
    folder written without a marker). A user's own page, or a link, is kept."""
    from ..suite import outdir

    if not out.exists() and not out.is_symlink():
        return True
    if out.is_symlink() or not out.is_file():
        return False
    marker = outdir.read_marker(out.parent)
    if marker is not None and out.name in marker["files"]:
        return True
    try:
        with open(out, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return b'<meta name="generator" content="natcoord ' in head


def write_report(results_dir: Path, references: Path = Path("references"),
                 history: Path | None = None, verdict=None) -> Path:
    """Write ``results_dir/index.html`` from the run's results, the stored references and,
    when given, the history database (trends) and the gate's verdict on the folder (what
    the page shows as each cell's verdict and the whole's). In a natcoord results folder the page is
    listed in the folder's marker (:func:`natcoord.suite.outdir.recording`), so the folder
    stays one that ``--out`` may replace."""
    from ..suite import outdir

    results_dir = Path(results_dir)
    out = results_dir / "index.html"
    if not _replaceable(out):
        raise NatcoordError(f"{out}: not a report natcoord wrote (the folder's marker does "
                            "not list it, and it does not name natcoord as its generator); "
                            "natcoord replaces only its own: move it, then run the command "
                            "again")
    html = render(build_context(results_dir, references, history, verdict))
    tmp = out.with_suffix(".html.tmp")
    with outdir.recording(results_dir, [out.name, tmp.name]):
        tmp.write_text(html, encoding="utf-8")
        tmp.replace(out)
    return out


def _grouped_notes(records: list[dict]) -> list[tuple[str, list[str]]]:
    """Each cell's notes as (engines, [note]): a note several engines carry (the case's
    assembly, say) is listed once with all of them, in the records' order."""
    by_note: dict[str, list[str]] = {}
    for r in records:
        for x in r.get("notes") or []:
            by_note.setdefault(str(x), []).append(str(r.get("engine")))
    return [(", ".join(engines), [note]) for note, engines in by_note.items()]
