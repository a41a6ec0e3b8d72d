"""Speed benchmark: per case x engine, the wall time of repeated whole runs, measured in one
session.

Each cell runs once in a fresh engine process (single-threaded BLAS; build time kept apart
from the stepping time), then ``repeats - 1`` more times in a second process, as many as fit
in ``BATCH_S`` (a run longer than that is measured once per process). Every repeat's wall
time is kept as ``samples_s`` beside the best and the median, and the deterministic cost
counters (steps, right-hand sides, factorizations) beside them, so that a speed judgement
can tell noise from a regression (:mod:`natcoord.suite.speed`). Ratios to natcoord are
computed within the same benchmark run, so machine load drifts cancel as far as they can.
"""

from __future__ import annotations

import datetime as dt
import os
import statistics
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..mechanism import Case
from .io import write_json
from .references import load_reference
from .runner import as_job, machine_info, run_subprocess

# Work-precision sweeps: settings that trade accuracy for time, coarse to fine (data, not
# code: a user tunes them here). MuJoCo's loop stiffness follows its step (solref_steps).
# natcoord sweeps each formulation; fixed-step variants also cross singular positions
# (five_bar), where adaptive step control stalls. ``h: None`` undoes a case's fixed step.
SWEEPS: dict[str, list[dict]] = {
    "natcoord": [{"formulation": "index1", "method": "dop853", "h": None, "rtol": r,
                  "atol": r * 1e-2} for r in (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)]
    + [{"formulation": "index1", "method": "rk4", "h": h} for h in (4e-3, 2e-3, 1e-3, 5e-4)]
    + [{"formulation": "maggi", "method": "dop853", "h": None, "rtol": r, "atol": r * 1e-2}
       for r in (1e-6, 1e-8, 1e-10, 1e-11)]
    + [{"formulation": "index3", "method": "trapezoidal", "h": h}
       for h in (2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4)],
    "mujoco": [{"dt": d, "solref_steps": 10} for d in (1e-3, 5e-4, 2e-4, 1e-4, 5e-5)],
    "pinocchio": [{"dt": d} for d in (1e-2, 5e-3, 2e-3, 1e-3, 5e-4)],
    "exudyn": [{"dt": d} for d in (5e-3, 2e-3, 1e-3, 5e-4, 2e-4)],
    "dart": [{"dt": d} for d in (1e-3, 5e-4, 2e-4, 1e-4, 5e-5)],
    "simbody": [{"accuracy": a} for a in (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)],
}
TARGETS = (1e-6, 1e-9)
BATCH_S = 10.0  # wall time the repeats of one cell may take in their process
CORE = max(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None  # timing
# runs are pinned to one core (the last this process may use), one at a time
COUNTERS = ("steps", "rejected", "rhs", "factorizations", "newton", "projections")


def measure(job, engine: str, repeats: int, timeout_s: float, tmp: Path) -> dict:
    """One cell's benchmark record: every repeat's wall time (``samples_s``), best, median,
    spread, build time, steps and cost counters."""
    case = job.case
    runs = [run_subprocess(job, engine, tmp, timeout_s, cpu=CORE)]
    first = runs[0].get("wall_time_s") or 0.0
    more = repeats - 1 if first <= 0 else min(repeats - 1, int(BATCH_S / first))
    if runs[0]["status"] == "ok" and more > 0:
        runs.append(run_subprocess(job, engine, tmp, timeout_s, repeat=more, cpu=CORE))
    ok = [r for r in runs if r["status"] == "ok" and r.get("wall_time_s")]
    rec = {"case": case.name, "engine": engine, "case_hash": case.digest,
           "status": runs[-1]["status"],
           "reason": runs[-1].get("reason", ""),
           "engine_version": runs[-1].get("engine_version", "")}
    if ok:
        samples = [s for r in ok for s in (r.get("samples_s") or [r["wall_time_s"]])]
        best = min(samples)
        n_steps = ok[0]["n_steps"]
        rec |= {"repeats": len(samples), "samples_s": samples, "wall_time_s": best,
                "wall_spread": (max(samples) - best) / best,
                "wall_median_s": statistics.median(samples),
                "build_time_s": min(r["build_time_s"] or 0.0 for r in ok),
                "n_steps": n_steps, "us_per_step": 1e6 * best / n_steps if n_steps else None,
                "wall_per_sim_s": best / case.duration, "settings": ok[0]["settings"],
                "counters": {k: ok[0]["counters"][k] for k in COUNTERS
                             if isinstance(ok[0].get("counters", {}).get(k), (int, float))}}
    return rec


def bench(cases: Sequence[Case], engines: Sequence[str], *, repeats: int = 7,
          timeout_s: float = 600.0, progress: Callable[[str, dict], None] | None = None) -> dict:
    """Benchmark and return ``{"records": [...], "machine": ..., "generated": ...}``."""
    records = []
    with tempfile.TemporaryDirectory(prefix="natcoord-bench-") as tmp:
        for job in map(as_job, cases):
            for engine in engines:
                rec = measure(job, engine, repeats, timeout_s, Path(tmp))
                records.append(rec)
                if progress:
                    progress(f"{job.case.name}/{engine}", rec)
    by_key = {(r["case"], r["engine"]): r for r in records}
    for r in records:
        ref = by_key.get((r["case"], "natcoord"), {})
        if r.get("wall_time_s") and ref.get("wall_time_s"):
            r["wall_ratio_to_natcoord"] = r["wall_time_s"] / ref["wall_time_s"]
    return {"generated": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "natcoord_version": __version__, "machine": machine_info(), "repeats": repeats,
            "records": records}


def store(result: dict, out: Path, history_dir: Path | None = None) -> Path:
    """Write ``out/bench.json`` and, when asked, a dated copy under ``history_dir``."""
    write_json(Path(out) / "bench.json", result)
    if history_dir is not None:
        stamp = result["generated"].replace(":", "").replace("+0000", "Z")
        write_json(Path(history_dir) / f"bench-{stamp}.json", result)
    return Path(out) / "bench.json"


def work_precision(cases: Sequence[Case], engines: Sequence[str], *,
                   references: Path = Path("references"), repeats: int = 1,
                   timeout_s: float = 600.0,
                   progress: Callable[[str, dict], None] | None = None) -> list[dict]:
    """Error of the first angle channel against CPU time over each engine's sweep.

    Returns one record per case x engine x setting, and per case x engine the time to
    reach each error in TARGETS (the cheapest point at or below it; None if none does).
    """
    points = []
    with tempfile.TemporaryDirectory(prefix="natcoord-wp-") as tmp:
        for job in map(as_job, cases):
            case = job.case
            ref = load_reference(case.name, references)
            angle = next((c.name for c in case.channels if c.kind == "angle"), None)
            if ref is None or angle is None:
                continue
            for engine in engines:
                for setting in SWEEPS.get(engine, []):
                    runs = [run_subprocess(job, engine, Path(tmp), timeout_s, setting)
                            for _ in range(repeats)]
                    ok = [r for r in runs if r["status"] == "ok"]
                    rec = {"case": case.name, "engine": engine, "setting": setting,
                           "variant": variant(setting), "channel": angle,
                           "status": runs[-1]["status"]}
                    if ok:
                        csv = Path(tmp) / "results" / case.name / f"{engine}.csv"
                        err = np.abs(pd.read_csv(csv)[angle].to_numpy() - ref[angle].to_numpy())
                        rec |= {"error": float(np.max(err)),
                                "wall_time_s": min(r["wall_time_s"] for r in ok),
                                "n_steps": ok[0]["n_steps"]}
                    points.append(rec)
                    if progress:
                        label = " ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                                         for k, v in setting.items() if v is not None)
                        progress(f"{case.name}/{engine} {label}", rec)
    return points


def variant(setting: dict) -> str:
    """Label of a sweep's formulation and integrator, e.g. ``index1 dop853`` ('' when the
    sweep varies only a step size)."""
    return " ".join(str(setting[k]) for k in ("formulation", "method") if k in setting)


def time_to_accuracy(points: list[dict], targets=TARGETS) -> list[dict]:
    """Per case x engine x variant, the least wall time of a sweep point with error <=
    target."""
    out = []
    keys = sorted({(p["case"], p["engine"], p.get("variant", "")) for p in points})
    for case, engine, var in keys:
        mine = [p for p in points if (p["case"], p["engine"], p.get("variant", ""))
                == (case, engine, var) and p.get("error") is not None]
        row = {"case": case, "engine": engine if not var else f"{engine} ({var})"}
        for target in targets:
            good = [p for p in mine if p["error"] <= target]
            row[f"time_to_{target:g}"] = min((p["wall_time_s"] for p in good), default=None)
        out.append(row)
    return out
