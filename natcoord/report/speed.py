"""The report's speed section, from one source of truth: ``bench.json``.

- time to a stated accuracy (``time_to_accuracy``, from a ``--work-precision`` sweep): the
  headline, because engines run at their own settings reach different accuracies;
- work-precision diagrams (``work_precision`` points): error against wall time, log-log,
  one trace per engine and natcoord formulation / integrator;
- the benchmark at each engine's own settings: best, median and spread of every repeat
  (``samples_s``), beside the accuracy those settings reached in the run;
- the benchmark scoring of cases with a ``[benchmark]`` (``scoring``): the benchmark's error
  at the case's settings and the least time within its precision;
- the cost explained (``fixed_s``, ``per_step_us``, ``per_rhs_us`` and their ``cost_fit``)
  and natcoord's cold start (``cold_start``, build time).

Without ``bench.json`` the run's own timings (one repeat each) are shown, labelled so.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Iterable

import numpy as np
import plotly.graph_objects as go

from ..suite.speed import positive_finite

TARGET_KEY = "time_to_"
INTERPOLATED = "interpolated_"  # its key's prefix for the time interpolated on the curve
WP_DASHES = ("solid", "dash", "dot", "dashdot", "longdash")
WP_SYMBOLS = ("circle", "square", "diamond", "triangle-up", "x")


def worst_rel(rec: dict | None) -> float | None:
    """Worst relative error over a run's determined channels (the history's measure)."""
    vals = []
    for ch in ((rec or {}).get("channels") or {}).values():
        if ch.get("determined", True) is False:
            continue
        try:
            v = float(ch.get("max_rel"))
        except (TypeError, ValueError):
            continue
        if np.isfinite(v):
            vals.append(v)
    return max(vals) if vals else None


def angle_error(rec: dict | None) -> tuple[str, float | None, str]:
    """(channel, max |error|, unit) of a run's first angle channel (else its first position
    channel): the quantity the work-precision sweep measures, so that speeds at each
    engine's own settings can be set beside the accuracy they bought."""
    chans = ((rec or {}).get("channels") or {}).items()
    for kind in ("angle", "position"):
        for name, ch in chans:
            if ch.get("kind") == kind and ch.get("determined", True) is not False:
                return name, _num(ch.get("max_abs")), str(ch.get("unit") or "")
    return "", None, ""


def samples(rec: dict) -> list[float]:
    """Every repeat's wall time (s) of a bench record ([] when not recorded)."""
    return positive_finite(rec.get("samples_s"))


def _spread_text(rec: dict, ss: list[float], fmt_time: Callable) -> tuple[str, str]:
    """('min–max (+x %)', hover title) of a record's repeats."""
    if ss:
        lo, hi = min(ss), max(ss)
        title = "every repeat: " + ", ".join(fmt_time(s) for s in sorted(ss))
        return f"+{100 * (hi - lo) / lo:.0f} %", f"{fmt_time(lo)}–{fmt_time(hi)}; {title}"
    sp = rec.get("wall_spread")
    if isinstance(sp, int | float) and np.isfinite(sp):
        return f"+{100 * sp:.0f} % (max over best)", "bench.json without samples_s"
    return "—", "no spread recorded"


def _source(r: dict) -> dict:
    """Where a bench record's samples come from, when not tonight's bench: ``source`` (a
    word) and ``source_title`` (the why, for a hover)."""
    if isinstance(r.get("timed_by"), dict):
        return {"source": "run", "source_title": str(r["timed_by"].get("why", ""))}
    if isinstance(r.get("reused"), dict):
        return {"source": "reused", "source_title": "measured "
                f"{r['reused'].get('measured', '?')} (reused: nothing it depends on changed)"}
    return {"source": "", "source_title": ""}


def own_settings(bench: dict, summary_by_key: dict, cases_order: list[str],
                 engine_order: Callable[[Iterable[str]], list[str]], anchor: Callable,
                 fmt_time: Callable, fmt_num: Callable, fmt_ratio: Callable,
                 fmt_int: Callable) -> list[dict]:
    """Benchmark rows per case, each engine at its own settings."""
    by_case: dict[str, list[dict]] = {}
    for r in bench.get("records") or []:
        if isinstance(r, dict):
            by_case.setdefault(str(r.get("case", "")), []).append(r)
    order = [c for c in cases_order if c in by_case] + sorted(
        c for c in by_case if c not in cases_order)
    groups = []
    for case in order:
        rs = by_case[case]
        engs = engine_order(str(r.get("engine", "")) for r in rs)
        rs = sorted(rs, key=lambda r: engs.index(str(r.get("engine", ""))))
        base = next((_num(r.get("wall_per_sim_s")) for r in rs
                     if r.get("engine") == "natcoord"), None)
        rows = []
        for r in rs:
            ss = samples(r)
            w = _num(r.get("wall_per_sim_s"))
            median = statistics.median(ss) if ss else _num(r.get("wall_median_s"))
            spread, spread_title = _spread_text(r, ss, fmt_time)
            us = _num(r.get("us_per_step"))
            status = str(r.get("status") or ("ok" if w is not None else ""))
            chan, err, unit = angle_error(summary_by_key.get((case, str(r.get("engine", "")))))
            rows.append({
                "engine": r.get("engine", ""), "status": status,
                "reason": str(r.get("reason") or ""),
                "accuracy": fmt_num(err, unit), "accuracy_channel": chan,
                "best": fmt_time(r.get("wall_time_s")),
                "median": fmt_time(median),
                "spread": spread, "spread_title": spread_title,
                "repeats": fmt_int(r.get("repeats") or (len(ss) or None)),
                **_source(r),
                "wall_per_sim": fmt_time(w),
                "ratio": fmt_ratio(w / base) if (w is not None and base) else "—",
                "us_per_step": fmt_time(us * 1e-6 if us else None),
                "steps": fmt_int(r.get("n_steps")) if _num(r.get("n_steps")) else "—",
                "build": fmt_time(r.get("build_time_s")),
            })
        groups.append({"case": case, "anchor": anchor("case", case), "rows": rows})
    return groups


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def targets_of(rows: list[dict]) -> list[str]:
    """The accuracy targets named by ``time_to_<target>`` keys, e.g. ['1e-06', '1e-09']."""
    keys = dict.fromkeys(k[len(TARGET_KEY):] for r in rows for k in r
                         if k.startswith(TARGET_KEY))
    return sorted(keys, key=lambda t: -float(t))


def time_to_accuracy(bench: dict, cases_order: list[str], anchor: Callable,
                     fmt_time: Callable, fmt_ratio: Callable) -> dict | None:
    """The headline table: per case, each engine (variant)'s least wall time to reach each
    target, and its ratio to the fastest at that target."""
    rows = [r for r in bench.get("time_to_accuracy") or [] if isinstance(r, dict)]
    if not rows:
        return None
    targets = targets_of(rows)
    by_case: dict[str, list[dict]] = {}
    for r in rows:
        by_case.setdefault(str(r.get("case", "")), []).append(r)
    order = [c for c in cases_order if c in by_case] + sorted(
        c for c in by_case if c not in cases_order)
    channel = next((p.get("channel") for p in bench.get("work_precision") or []
                    if isinstance(p, dict) and p.get("channel")), None)
    groups = []
    for case in order:
        rs = by_case[case]
        best = {(k, t): min((v for r in rs if (v := _num(r.get(k + TARGET_KEY + t)))),
                            default=None) for t in targets for k in ("", INTERPOLATED)}
        out = []
        for r in rs:
            cells = []
            for t in targets:
                v = _num(r.get(TARGET_KEY + t))
                vi = _num(r.get(INTERPOLATED + TARGET_KEY + t))
                bi = best[INTERPOLATED, t]
                cells.append({"time": fmt_time(v) if v is not None else "not reached",
                              "ratio": fmt_ratio(v / best["", t]) if (v and best["", t])
                              else "", "best": v is not None and v == best["", t],
                              "interpolated": fmt_time(vi) if vi is not None else "",
                              "interpolated_ratio": fmt_ratio(vi / bi) if (vi and bi)
                              else ""})
            out.append({"engine": str(r.get("engine", "")), "cells": cells})
        groups.append({"case": case, "anchor": anchor("case", case), "rows": out})
    return {"targets": [f"{float(t):.0e}".replace("e-0", "e-") for t in targets],
            "channel": channel, "groups": groups}


def work_precision_figures(bench: dict, cases_order: list[str], colors: dict[str, str],
                           layout: Callable[[go.Figure, int], None]) -> list[tuple[str, go.Figure]]:
    """One log-log figure per case: error of the swept channel against wall time, a trace
    per engine and natcoord variant, points ordered by wall time."""
    pts = [p for p in bench.get("work_precision") or [] if isinstance(p, dict)]
    by_case: dict[str, list[dict]] = {}
    for p in pts:
        if _num(p.get("error")) and _num(p.get("wall_time_s")):
            by_case.setdefault(str(p.get("case", "")), []).append(p)
    order = [c for c in cases_order if c in by_case] + sorted(
        c for c in by_case if c not in cases_order)
    targets = [float(t) for t in targets_of(bench.get("time_to_accuracy") or [])]
    out = []
    for case in order:
        fig = go.Figure()
        traces: dict[tuple[str, str], list[dict]] = {}
        for p in by_case[case]:
            traces.setdefault((str(p.get("engine", "")), str(p.get("variant") or "")),
                              []).append(p)
        per_engine: dict[str, int] = {}  # an engine's k-th variant: its dash and symbol
        for (eng, var), ps in traces.items():
            ps = sorted(ps, key=lambda p: p["wall_time_s"])
            k = per_engine[eng] = per_engine.get(eng, -1) + 1
            name = f"{eng} ({var})" if var else eng
            text = [", ".join(f"{a}={b:g}" if isinstance(b, float) else f"{a}={b}"
                              for a, b in (p.get("setting") or {}).items() if b is not None)
                    for p in ps]
            fig.add_trace(go.Scatter(
                x=[p["wall_time_s"] for p in ps], y=[p["error"] for p in ps], text=text,
                name=name, mode="lines+markers",
                line={"color": colors.get(eng, "#444"), "dash": WP_DASHES[k % 5], "width": 1.5},
                marker={"symbol": WP_SYMBOLS[k % 5], "size": 7},
                hovertemplate=f"{name}<br>%{{text}}<br>wall %{{x:.3g}} s<br>"
                              "error %{y:.3g}<extra></extra>"))
        for t in targets:
            fig.add_hline(y=t, line={"color": "#999", "dash": "dot", "width": 1})
        channel = by_case[case][0].get("channel") or "error"
        fig.update_xaxes(type="log", title_text="wall time of the whole run [s], one core")
        fig.update_yaxes(type="log", title_text=f"max |{channel} − reference|")
        layout(fig, 500)
        fig.update_layout(legend={"orientation": "h", "x": 0, "y": -0.2, "yanchor": "top"},
                          margin={"b": 110})
        out.append((case, fig))
    return out


def _by_case(rows: Iterable[dict], cases_order: list[str]) -> list[tuple[str, list[dict]]]:
    by: dict[str, list[dict]] = {}
    for r in rows:
        if isinstance(r, dict):
            by.setdefault(str(r.get("case", "")), []).append(r)
    order = [c for c in cases_order if c in by] + sorted(c for c in by if c not in cases_order)
    return [(c, by[c]) for c in order]


def cost_explained(bench: dict, cases_order: list[str],
                   engine_order: Callable[[Iterable[str]], list[str]], anchor: Callable,
                   fmt_time: Callable, fmt_int: Callable) -> list[dict]:
    """Per case, each engine's fixed cost per run, cost per step and per right-hand side
    (the cost fit of bench.json), beside the counters and the two runs the fit used."""
    groups = []
    for case, rs in _by_case(bench.get("records") or [], cases_order):
        if not any("cost_fit" in r or "fixed_s" in r for r in rs):
            continue
        engs = engine_order(str(r.get("engine", "")) for r in rs)
        rows = []
        for r in sorted(rs, key=lambda r: engs.index(str(r.get("engine", "")))):
            fit = r.get("cost_fit") or {}
            pts = [p for p in fit.get("points") or [] if isinstance(p, dict)]
            c = r.get("counters") or {}
            per_step, per_rhs = _num(r.get("per_step_us")), _num(r.get("per_rhs_us"))
            rows.append({
                "engine": str(r.get("engine", "")), "status": str(r.get("status") or ""),
                "reason": str(r.get("reason") or ""),
                "fixed": "0" if _num(r.get("fixed_s")) == 0 else fmt_time(r.get("fixed_s")),
                "per_step": fmt_time(per_step * 1e-6 if per_step else None),
                "per_rhs": fmt_time(per_rhs * 1e-6 if per_rhs else None),
                "steps": fmt_int(r.get("n_steps")) if _num(r.get("n_steps")) else "—",
                "rhs": fmt_int(c.get("rhs")) if _num(c.get("rhs")) else "—",
                "counters": ", ".join(f"{k} {v:g}" for k, v in c.items()
                                      if k not in ("steps", "rhs") and _num(v) is not None),
                "build": fmt_time(r.get("build_time_s")),
                "points": "; ".join(
                    f"{_num(p.get('duration_s')) or 0:g} s: {fmt_int(p.get('n_steps'))} steps, "
                    f"{fmt_time(p.get('wall_s'))}"
                    + (f" ({fmt_time(us * 1e-6)}/step)" if (us := _num(p.get("us_per_step")))
                       else "") for p in pts) or "—",
                "points_short": " · ".join(
                    f"{_num(p.get('duration_s')) or 0:g} s {fmt_time(p.get('wall_s'))}"
                    for p in pts) or "—",
                "superlinear": (_num(fit.get("free_fixed_s")) or 0.0) < 0,
                "undetermined": bool(pts) and fit.get("determined") is False,
            })
        groups.append({"case": case, "anchor": anchor("case", case), "rows": rows})
    return groups


def cold_start(bench: dict, fmt_time: Callable) -> dict | None:
    """natcoord's cold start (a fresh process: import, kernels from the numba cache, a tiny
    run) as the report states it; None when the benchmark did not measure it."""
    c = bench.get("cold_start")
    if not isinstance(c, dict):
        return None
    ss = [v for v in (_num(x) for x in c.get("samples_s") or []) if v]
    return {"case": str(c.get("case", "")), "status": str(c.get("status") or ""),
            "reason": str(c.get("reason") or ""),
            "duration": f"{_num(c.get('duration_s')) or 0:g} s",
            "total": fmt_time(c.get("build_time_s")), "import": fmt_time(c.get("import_s")),
            "kernels": fmt_time(c.get("kernel_load_s")), "run": fmt_time(c.get("wall_time_s")),
            "samples": ", ".join(fmt_time(x) for x in ss), "n": len(ss)}


def scoring(bench: dict, cases_order: list[str],
            engine_order: Callable[[Iterable[str]], list[str]], anchor: Callable,
            fmt_time: Callable, fmt_num: Callable) -> list[dict]:
    """Per case with a benchmark definition: its output, error measure, precision and source,
    and per engine the error at the case's settings and the least time within the
    precision ("not reached" when neither the case's settings nor any sweep point is)."""
    groups = []
    for case, rs in _by_case(bench.get("scoring") or [], cases_order):
        first = rs[0]
        engs = engine_order(str(r.get("engine", "")) for r in rs)
        times = [t for r in rs if (t := _num(r.get("time_to_precision")))]
        rows = []
        for r in sorted(rs, key=lambda r: engs.index(str(r.get("engine", "")))):
            t, err = _num(r.get("time_to_precision")), _num(r.get("error"))
            prec = _num(r.get("precision"))
            status = str(r.get("status") or "")
            rows.append({
                "engine": str(r.get("engine", "")), "status": status,
                "error": fmt_num(err) if err is not None else (status or "—"),
                "within": err is not None and prec is not None and err <= prec,
                "time": fmt_time(t) if t is not None else "not reached",
                "by": str(r.get("reached_by") or ""),
                "best_swept": fmt_num(_num(r.get("best_swept_error"))),
                "fastest": t is not None and t == min(times)})
        kind = ("at the last sample" if first.get("error_kind") == "final_abs"
                else "over every output sample")
        groups.append({"case": case, "anchor": anchor("case", case), "rows": rows,
                       "output": ", ".join(str(c) for c in first.get("channels") or []),
                       "precision": fmt_num(_num(first.get("precision"))), "kind": kind,
                       "source": str(first.get("source") or "")})
    return groups
