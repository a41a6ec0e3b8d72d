"""What changed since the last green night: this results folder against the newest suite in
the history database whose gate passed (exit 0), in accuracy, speed and engine versions.

The rules are ``natcoord history --since-green``'s (:mod:`natcoord.suite.history_views`):
a verdict that turned fail or failed, a worst error/tolerance grown past 10x (and past 0.1),
a median bench time grown past 1.5x; the same factors the other way are listed as better.
"""

from __future__ import annotations

import sqlite3
import statistics
from pathlib import Path

from ..suite import history as hist
from ..suite.history_views import GROWTH, SLOWER, _median_s, _worst
from .speed import _num, samples


def _worst_now(records: list[dict]) -> dict[tuple[str, str], dict]:
    """This run's cells as the history stores them: status, verdict and the worst
    max |error| / tolerance over determined channels."""
    out = {}
    for r in records:
        w = None
        for ch in (r.get("channels") or {}).values():
            a, tol = _num(ch.get("max_abs")), _num(ch.get("tolerance"))
            if ch.get("determined", True) is not False and a is not None and tol:
                w = max(w or 0.0, a / tol)
        out[(str(r.get("case")), str(r.get("engine")))] = {
            "status": r.get("status"), "verdict": r.get("verdict"), "worst": w}
    return out


def _median_now(bench: dict | None) -> dict[tuple[str, str], float]:
    out = {}
    for r in (bench or {}).get("records") or []:
        ss = samples(r) if isinstance(r, dict) else []
        if ss:
            out[(str(r.get("case")), str(r.get("engine")))] = statistics.median(ss)
    return out


def _green(history: Path, results_dir: Path) -> tuple:
    """(run row, worst per cell, median time per cell, engine versions) of the newest
    suite in ``history`` whose gate passed, this results folder's own record aside;
    (None, ...) when there is none."""
    this = str(results_dir.resolve())
    with hist.reading(history) as db:
        if db is None:
            return None, {}, {}, {}
        green = db.execute(
            "SELECT id, generated, git_commit FROM runs WHERE kind = 'suite' AND gate = 0 "
            "AND results_dir IS NOT ? ORDER BY id DESC LIMIT 1", (this,)).fetchone()
        if green is None:
            return None, {}, {}, {}
        versions = {e: v for e, v in db.execute(
            "SELECT DISTINCT engine, engine_version FROM results WHERE run_id = ?",
            (green[0],)) if v}
        return green, _worst(db, green[0]), _median_s(db, green[0]), versions


def section(history: Path | None, results_dir: Path, summary: dict,
            bench: dict | None, fmt_when, fmt_num, fmt_time) -> dict:
    """``{"message"}`` when there is nothing to compare with, else ``{"green": {when,
    commit}, "worse": [...], "better": [...], "versions": [...], "n_cells"}``, each item
    ``{"cell", "what", "before", "after"}``."""
    if history is None or not Path(history).exists():
        return {"message": "No history database: nothing to compare with."}
    try:
        green, then, t_then, v_then = _green(Path(history), Path(results_dir))
    except (sqlite3.Error, ValueError, KeyError, TypeError) as exc:
        return {"message": f"History unreadable ({history}): {exc}"}
    if green is None:
        return {"message": "No earlier suite in the history passed its gate: nothing "
                           "to compare with yet."}
    records = [r for r in summary.get("records") or [] if isinstance(r, dict)]
    now, t_now = _worst_now(records), _median_now(bench)
    worse, better = [], []
    for key in sorted(set(now) | set(t_now)):
        cell = "/".join(key)
        c, was = now.get(key, {}), then.get(key)
        if was is not None and c:
            bad = c.get("verdict") == "fail" or c.get("status") == "failed"
            bad0 = was.get("verdict") == "fail" or was.get("status") == "failed"
            if bad != bad0:
                (worse if bad else better).append({
                    "cell": cell, "what": "verdict",
                    "before": f"{was.get('status')} / {was.get('verdict')}",
                    "after": f"{c.get('status')} / {c.get('verdict')}"})
            w, w0 = c.get("worst"), was.get("worst")
            if w is not None and w0 is not None:
                if w > max(GROWTH * w0, 0.1):
                    worse.append({"cell": cell, "what": "worst error / tolerance",
                                  "before": fmt_num(w0), "after": fmt_num(w)})
                elif w0 > max(GROWTH * w, 0.1):
                    better.append({"cell": cell, "what": "worst error / tolerance",
                                   "before": fmt_num(w0), "after": fmt_num(w)})
        s, s0 = t_now.get(key), t_then.get(key)
        if s and s0 and (s > SLOWER * s0 or s0 > SLOWER * s):
            (worse if s > s0 else better).append({
                "cell": cell, "what": f"median bench time ({s / s0:.2f}×)",
                "before": fmt_time(s0), "after": fmt_time(s)})
    v_now: dict[str, str] = {}
    for r in records:
        if r.get("engine_version"):
            v_now[str(r.get("engine"))] = str(r.get("engine_version"))
    versions = [{"engine": e, "before": v_then[e], "after": v}
                for e, v in sorted(v_now.items()) if e in v_then and v_then[e] != v]
    return {"message": "", "green": {"when": fmt_when(green[1]), "commit": green[2] or "—"},
            "worse": worse, "better": better, "versions": versions,
            "rules": f"a verdict turned fail or failed; worst error / tolerance grown past "
                     f"{GROWTH:g}× (and 0.1); median bench time past {SLOWER:g}×"}
