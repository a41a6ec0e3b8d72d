"""What ``natcoord history`` asks of the history database (read-only; see
:mod:`natcoord.suite.history`): the recent runs, one cell's accuracy and speed series, what
regressed since the last passing (green) suite, and which cells flip between pass and fail.

A cell's **worst** figure is the largest ``max_abs / tolerance`` over its gated, determined
channels in a run (over 1 fails); its speed the median of its benchmark samples (s).
"""

from __future__ import annotations

import json
import sqlite3
import statistics
from pathlib import Path

from . import speed
from .history import reading

GROWTH = 10.0  # a worst figure grown this much (and past 0.1) counts as regressed
SLOWER = 1.5  # trends: a median time grown this much (since-green uses the gate's rule)


def _worst(db, run_id: int) -> dict[tuple[str, str], dict]:
    out: dict[tuple[str, str], dict] = {}
    for case, engine, status, verdict, max_abs, tol in db.execute(
            "SELECT case_name, engine, status, verdict, max_abs, tolerance FROM results "
            "WHERE run_id = ? AND determined IS NOT 0", (run_id,)):
        c = out.setdefault((case, engine), {"status": status, "verdict": verdict,
                                            "worst": None})
        if max_abs is not None and tol:
            c["worst"] = max(c["worst"] or 0.0, max_abs / tol)
    return out


def _median_s(db, run_id: int) -> dict[tuple[str, str], float]:
    return {(c, e): statistics.median(json.loads(raw)) for c, e, raw in db.execute(
        "SELECT case_name, engine, samples FROM bench WHERE run_id = ?", (run_id,))
        if json.loads(raw)}


def _timings(db, run_id: int) -> dict[tuple[str, str], tuple[list, list, dict]]:
    """Per cell of a run, its (wall, CPU, relative) timing samples: CPU [] where not
    measured, relative (per clock, samples / reference work) {} where not measured, both
    also in a history from before them."""
    out = {(c, e): (json.loads(raw), [], {}) for c, e, raw in db.execute(
        "SELECT case_name, engine, samples FROM bench WHERE run_id = ?", (run_id,))}
    for query, put in (
            ("SELECT case_name, engine, samples FROM bench_cpu WHERE run_id = ?",
             lambda old, raw: (old[0], json.loads(raw), old[2])),
            ("SELECT case_name, engine, samples, clock FROM bench_relative WHERE run_id = ?",
             lambda old, raw, clock: (old[0], old[1], old[2] | {clock: json.loads(raw)}))):
        try:
            for c, e, *rest in db.execute(query, (run_id,)):
                if (c, e) in out:
                    out[c, e] = put(out[c, e], *rest)
        except sqlite3.OperationalError as err:
            if "no such table" not in str(err):
                raise
    return out


def runs(path: Path, last: int = 20) -> list[dict]:
    """The last ``last`` runs, newest first: id, time, kind, commit, machine, gate exit
    code and the cells that passed and failed."""
    with reading(path) as db:
        if db is None:
            return []
        rows = db.execute("SELECT id, generated, kind, git_commit, machine, gate FROM runs "
                          "ORDER BY id DESC LIMIT ?", (last,)).fetchall()
        out = []
        for run_id, generated, kind, commit, machine, gate in rows:
            cells = _worst(db, run_id)
            out.append({"id": run_id, "generated": generated, "kind": kind,
                        "commit": commit or "", "machine": machine or "", "gate": gate,
                        "passed": sum(c["verdict"] == "pass" for c in cells.values()),
                        "failed": sum(c["verdict"] == "fail" or c["status"] == "failed"
                                      for c in cells.values())})
    return out


def cell(path: Path, case: str, engine: str, last: int = 30) -> list[dict]:
    """One cell over the last ``last`` runs that hold it, oldest first: run, time,
    commit, status, verdict, worst figure, median time (s, when benchmarked)."""
    with reading(path) as db:
        if db is None:
            return []
        ids = [r[0] for r in db.execute(
            "SELECT DISTINCT run_id FROM results WHERE case_name = ? AND engine = ? UNION "
            "SELECT DISTINCT run_id FROM bench WHERE case_name = ? AND engine = ? "
            "ORDER BY 1 DESC LIMIT ?", (case, engine, case, engine, last))][::-1]
        out = []
        for run_id in ids:
            generated, commit = db.execute("SELECT generated, git_commit FROM runs WHERE "
                                           "id = ?", (run_id,)).fetchone()
            c = _worst(db, run_id).get((case, engine), {})
            out.append({"id": run_id, "generated": generated, "commit": commit or "",
                        "status": c.get("status"), "verdict": c.get("verdict"),
                        "worst": c.get("worst"),
                        "median_s": _median_s(db, run_id).get((case, engine))})
    return out


def _info(r) -> dict | None:
    return None if not r else {"id": r[0], "generated": r[1], "commit": r[2] or "",
                               "gate": r[3]}


def since_green(path: Path) -> dict:
    """The newest suite against the last suite whose gate passed before it: ``{"green",
    "latest"}`` (run summaries, None when there is none) and ``regressed``: the cells that
    failed, whose worst figure grew past :data:`GROWTH` x (and 0.1), or that the speed
    gate's rule finds slower (:func:`natcoord.suite.speed.judge`: CPU time where both have
    it, 1.5x and the rank test; on the same machine: else ``speed`` says why not), each
    with what changed."""
    with reading(path) as db:
        if db is None:
            return {"green": None, "latest": None, "regressed": []}
        head = "SELECT id, generated, git_commit, gate, machine FROM runs WHERE kind = 'suite'"
        latest = db.execute(head + " ORDER BY id DESC LIMIT 1").fetchone()
        green = latest and db.execute(head + " AND gate = 0 AND id < ? ORDER BY id DESC "
                                      "LIMIT 1", (latest[0],)).fetchone()
        out = {"green": _info(green), "latest": _info(latest), "regressed": []}
        if not (latest and green):
            return out
        now, then = _worst(db, latest[0]), _worst(db, green[0])
        t_now, t_then = _timings(db, latest[0]), _timings(db, green[0])
    if latest[4] != green[4]:  # times of two machines say nothing of the code
        out["speed"] = (f"times not compared: the green suite ran on another machine "
                        f"({green[4] or '?'}, the newest on {latest[4] or '?'})")
        t_then = {}
    for key in sorted(set(now) | set(t_now)):
        c, was = now.get(key, {}), then.get(key, {})
        why = []
        if c.get("verdict") == "fail" or c.get("status") == "failed":
            why.append(f"{c.get('status')} / {c.get('verdict')} (was {was.get('status')} / "
                       f"{was.get('verdict')})")
        w, w0 = c.get("worst"), was.get("worst")
        if w is not None and w0 is not None and w > max(GROWTH * w0, 0.1):
            why.append(f"worst error/tolerance {w0:.3g} -> {w:.3g}")
        if key in t_now and key in t_then:
            (wall, cpu, rel), (wall0, cpu0, rel0) = t_now[key], t_then[key]
            judged = speed.judge(*key, wall0, wall, base_cpu=cpu0, new_cpu=cpu,
                                 base_relative=rel0, new_relative=rel)
            if judged.slower:
                why.append(f"slower: median {judged.ratio:.3g}x (p = {judged.p:.2g}, "
                           f"{judged.n_base} -> {judged.n_new} samples, {judged.measure})")
        if why:
            out["regressed"].append({"cell": "/".join(key), "why": why})
    return out


def flaky(path: Path, last: int = 20) -> list[dict]:
    """Cells whose verdict flipped between pass and fail over the last ``last`` runs that
    judged them: score = flips / (runs - 1), highest first."""
    with reading(path) as db:
        if db is None:
            return []
        ids = [r[0] for r in db.execute("SELECT id FROM runs ORDER BY id DESC LIMIT ?",
                                        (last,))][::-1]
        series: dict[str, list[str]] = {}
        for run_id in ids:
            for key, c in _worst(db, run_id).items():
                if c["verdict"] in ("pass", "fail"):
                    series.setdefault("/".join(key), []).append(c["verdict"])
    out = []
    for name, v in series.items():
        flips = sum(a != b for a, b in zip(v, v[1:], strict=False))
        if flips:
            out.append({"cell": name, "score": flips / (len(v) - 1), "runs": len(v),
                        "flips": flips})
    return sorted(out, key=lambda x: -x["score"])
