"""Speed benchmark: per case x engine, the wall time of repeated whole runs, measured in one
session.

Each cell runs in one engine process (single-threaded BLAS, pinned to one core; build time
kept apart from the stepping time): a warm-up run, then ``repeats`` timing samples, each a
**calibrated batch** (the stepping repeated until the batch lasts at least ``MIN_BATCH_S``;
its time per run is the sample), as many as fit in ``BUDGET_S`` (a run longer than that is
measured once). A preemption then costs a sample a few per cent, not 10x
(:mod:`natcoord.suite.batches`). Every sample's time per run is kept as ``samples_s`` (wall
clock) and, where the engine measures it (natcoord), ``cpu_samples_s`` (CPU time, which
waiting for the core does not inflate), with the runs of each batch in ``batch_runs`` and
the time of the reference work measured after each sample (``ref_samples_s``,
``ref_cpu_samples_s``: how fast the machine ran just then), beside the best and the
median, and the deterministic cost counters (steps, right-hand sides, factorizations),
so that a speed judgement can tell noise from a regression (:mod:`natcoord.suite.speed`).
Ratios to natcoord are computed within the same benchmark run, so machine load drifts
cancel as far as they can.

Cost explained (:func:`cost_fit`): every cell also times the same case over its first
``FIT_FRACTION`` of samples in the same process (its batches interleaved with the full
run's, or for natcoord right after them), and the best time per run at each duration
gives ``wall = fixed + per_step * steps`` (and the same line in right-hand-side
evaluations where the engine counts them). natcoord's cold start (a fresh
Python process importing natcoord, loading its compiled kernels from the numba cache and
running a tiny case) is measured apart (:func:`cold_start`): build time, never step time.

IFToMM-style scoring (:func:`scoring`): for a case with a ``[benchmark]`` table, the error
of its benchmark output against the reference at the case's settings, and the least wall
time of a run's stepping on one pinned core (over the case's settings and the
work-precision sweep) whose error is within the benchmark's precision.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..case.mechanism import Case, bench_key
from .io import write_json
from .references import usable_reference
from .runner import as_job, machine_info, run_subprocess
from .worker import truncated

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
    "pybullet": [{"dt": d} for d in (1e-3, 5e-4, 2e-4, 1e-4, 5e-5)],
}
TARGETS = (1e-6, 1e-9)
MIN_BATCH_S = 0.1  # a timing sample: the stepping repeated for at least this long
BUDGET_S = 10.0  # process time the timing samples of one cell may take
CORE = max(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None  # timing
# runs are pinned to one core (the last this process may use), one at a time
COUNTERS = ("steps", "rejected", "rhs", "factorizations", "newton", "projections")
FIT_FRACTION = 0.25  # the cost fit's second duration: this fraction of the case's samples
COLD_SAMPLES = 10  # output intervals of the cold-start run
COLD_REPEATS = 3


def now() -> str:
    """The time now (UTC), as the records store it."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def _line(points: Sequence[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray, float,
                                                          float] | None:
    """(x, w, slope, intercept) of the free least-squares line through the usable points
    (finite, positive), or None with fewer than two distinct x."""
    x = np.array([p[0] for p in points], dtype=float)
    w = np.array([p[1] for p in points], dtype=float)
    ok = np.isfinite(x) & np.isfinite(w) & (x > 0) & (w > 0)
    x, w = x[ok], w[ok]
    if len(np.unique(x)) < 2:
        return None
    slope, fixed = np.polyfit(x, w, 1)
    return x, w, float(slope), float(fixed)


def cost_fit(points: Sequence[tuple[float, float]]) -> tuple[float, float] | None:
    """The line ``wall = fixed + slope * x`` through ``(x, wall)`` points (x: steps or
    right-hand sides of a run, wall: its best wall time in s), least squares with ``fixed
    >= 0``: when the free intercept comes out negative (noise), the line through the origin.
    Returns ``(fixed_s, slope_s)``, or None when the points do not determine a positive
    slope (one distinct x, or the shorter run not cheaper: noise larger than the work)."""
    line = _line(points)
    if line is None:
        return None
    x, w, slope, fixed = line
    if fixed < 0:
        fixed, slope = 0.0, float(x @ w / (x @ x))
    if not slope > 0:
        return None
    return float(fixed), float(slope)


def explain_cost(full: dict, short: dict | None) -> dict:
    """The cost-fit keys of a bench record from its full runs (``samples_s``, ``n_steps``,
    ``counters``) and its truncated runs (the worker's ``short`` record)."""
    out: dict = {"fixed_s": None, "per_step_us": None, "per_rhs_us": None}
    full_s, short_s = full.get("samples_s") or [], (short or {}).get("samples_s") or []
    if not full_s or not short_s:
        return out
    rows = [{"duration_s": full["duration_s"], "n_steps": full["n_steps"],
             "rhs": (full.get("counters") or {}).get("rhs"), "wall_s": min(full_s),
             "repeats": len(full_s)},
            {"duration_s": short["duration_s"], "n_steps": short["n_steps"],
             "rhs": (short.get("counters") or {}).get("rhs"), "wall_s": min(short_s),
             "repeats": len(short_s)}]
    for r in rows:
        r["us_per_step"] = 1e6 * r["wall_s"] / r["n_steps"] if r["n_steps"] else None
    by_step = [(r["n_steps"], r["wall_s"]) for r in rows]
    step, free = cost_fit(by_step), _line(by_step)
    if step:
        out["fixed_s"], out["per_step_us"] = step[0], 1e6 * step[1]
    if all(isinstance(r["rhs"], (int, float)) for r in rows):
        rhs = cost_fit([(r["rhs"], r["wall_s"]) for r in rows])
        out["per_rhs_us"] = 1e6 * rhs[1] if rhs else None
    out["cost_fit"] = {
        "method": f"best wall time of the whole case and of its first {FIT_FRACTION:g} of "
                  "samples (both timed in the same process), line through them "
                  "in steps (and in right-hand sides), intercept >= 0",
        "points": rows, "determined": step is not None,
        # the free line's intercept: negative when the shorter run cost less per step (noise,
        # or a cost per step that grows with the run's length); the fit then uses 0
        "free_fixed_s": None if free is None else free[3]}
    return out


def timed_runs(job, engine: str, tmp: Path, timeout_s: float, repeats: int,
               settings: dict | None = None, budget_s: float = BUDGET_S) -> list[dict]:
    """The run record of one timed cell (a list of one), pinned to the bench's core: one
    engine process that takes ``repeats`` calibrated samples within ``budget_s``; their
    times per run are in the record's ``samples_s`` (and ``cpu_samples_s``)."""
    job = dataclasses.replace(as_job(job), batch_s=MIN_BATCH_S, budget_s=budget_s)
    return [run_subprocess(job, engine, tmp, timeout_s, settings, repeat=repeats, cpu=CORE)]


def measure(job, engine: str, repeats: int, timeout_s: float, tmp: Path,
            references: Path | None = None, budget_s: float = BUDGET_S) -> dict:
    """One cell's benchmark record: every sample's time per run (``samples_s``, wall;
    ``cpu_samples_s``, CPU, where measured; ``batch_runs``, runs per batch), best, median,
    spread, build time, steps and cost counters; the cost fit (``fixed_s``,
    ``per_step_us``, ``per_rhs_us``, ``cost_fit``); with ``references`` and a case
    ``[benchmark]``, the benchmark error of the run (``benchmark_error``)."""
    case = job.case
    job = dataclasses.replace(as_job(job), truncate=FIT_FRACTION)
    (run,) = timed_runs(job, engine, tmp, timeout_s, repeats, budget_s=budget_s)
    from ..engines.registry import adapter_digest

    rec = {"case": case.name, "engine": engine, "case_hash": case.digest,
           "bench_key": bench_key(case, engine),
           "status": run["status"], "reason": run.get("reason", ""),
           "engine_version": run.get("engine_version", ""), "measured": now(),
           "adapter_hash": adapter_digest(engine), "requested_repeats": repeats,
           "process_time_s": run.get("process_time_s")}
    if run["status"] == "ok" and run.get("wall_time_s"):
        samples = run.get("samples_s") or [run["wall_time_s"]]
        best = min(samples)
        n_steps = run["n_steps"]
        counters = run.get("counters") or {}
        rec |= {"repeats": len(samples), "samples_s": samples,
                "cpu_samples_s": run.get("cpu_samples_s") or [],
                "batch_runs": run.get("batch_runs") or [1] * len(samples),
                "ref_samples_s": run.get("ref_samples_s") or [],
                "ref_cpu_samples_s": run.get("ref_cpu_samples_s") or [],
                "min_batch_s": MIN_BATCH_S, "wall_time_s": best,
                "wall_spread": (max(samples) - best) / best,
                "wall_median_s": statistics.median(samples),
                "build_time_s": run["build_time_s"] or 0.0,
                "n_steps": n_steps, "us_per_step": 1e6 * best / n_steps if n_steps else None,
                "wall_per_sim_s": best / case.duration, "settings": run["settings"],
                "counters": {k: counters[k] for k in COUNTERS
                             if isinstance(counters.get(k), (int, float))}}
        if isinstance(counters.get("path"), str):  # natcoord's compiled path that ran
            rec["path"] = counters["path"]  # ('sparse' where 'generated' could not load)
        rec |= explain_cost({"samples_s": samples, "n_steps": n_steps, "counters": counters,
                             "duration_s": case.duration}, run.get("short"))
        if references is not None and case.benchmark:
            csv = tmp / "results" / case.name / f"{engine}.csv"
            rec["benchmark_error"] = benchmark_error(case, csv, references)
    return rec


def benchmark_error(case: Case, csv: Path, references: Path) -> float | None:
    """The error of a run (its results CSV) as the case's ``[benchmark]`` defines it:
    max |run - reference| over the benchmark's channels, over every output sample
    (``error = "max_abs"``) or at the last one (``"final_abs"``). None without a
    reference or a readable run."""
    spec = case.benchmark
    ref = usable_reference(case, references)
    if not spec or ref is None or not Path(csv).exists():
        return None
    run = pd.read_csv(csv)
    cols = list(spec["channels"])
    if len(run) != len(ref) or any(c not in run or c not in ref for c in cols):
        return None
    diff = np.abs(run[cols].to_numpy(dtype=float) - ref[cols].to_numpy(dtype=float))
    if spec["error"] == "final_abs":
        diff = diff[-1:]
    return float(np.max(diff)) if np.all(np.isfinite(diff)) else float("inf")


COLD_CHILD = """\
import json, pickle, sys, time
t0 = time.perf_counter()
from natcoord.engines import natcoord_engine
t1 = time.perf_counter()
with open(sys.argv[1], "rb") as f:
    case, init, settings = pickle.load(f)
run = natcoord_engine.run(case, init, settings)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "run_total_s": t2 - t1, "build_time_s": run.build_time_s,
                  "kernel_load_s": run.counters.get("compile_time_s", 0.0)
                  + run.counters.get("plan_time_s", 0.0), "path": run.counters.get("path"),
                  "wall_time_s": run.wall_time_s, "n_steps": run.n_steps}))
"""


def cold_start(job, tmp: Path, repeats: int = COLD_REPEATS, timeout_s: float = 600.0) -> dict:
    """natcoord's cold start: a fresh Python process that imports natcoord, loads its
    compiled kernels (from the numba cache when it is warm) and runs ``job``'s case over its
    first ``COLD_SAMPLES`` output intervals; ``repeats`` processes, one after the other, on
    the bench's core. Wall time of the whole process (interpreter start to exit) and its
    parts, all build time: none of it is step time."""
    job = as_job(job)
    case = job.case
    n = max(1, int(round(case.duration / case.output_dt)))
    tiny = truncated(case, min(1.0, COLD_SAMPLES / n))
    rec = {"case": case.name, "duration_s": tiny.duration, "samples_s": [], "parts": [],
           "status": "ok", "reason": ""}
    if job.init is None or case.engine("natcoord").unsupported:
        return rec | {"status": "skipped", "reason": "natcoord does not run this case"}
    path = tmp / "cold-start.pkl"
    with open(path, "wb") as f:
        pickle.dump((tiny, job.init, dict(case.engine("natcoord").settings)), f)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    pin = (lambda: os.sched_setaffinity(0, {CORE})) if CORE is not None else None
    for _ in range(repeats):
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, "-c", COLD_CHILD, str(path)], env=env,
                               capture_output=True, text=True, timeout=timeout_s,
                               preexec_fn=pin)
        except subprocess.TimeoutExpired:
            return rec | {"status": "failed", "reason": f"timed out after {timeout_s:g} s"}
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            tail = " ".join((p.stderr or "").strip().splitlines()[-2:])
            return rec | {"status": "failed", "reason": f"exit {p.returncode}: {tail}"}
        rec["samples_s"].append(wall)
        rec["parts"].append(json.loads(p.stdout.strip().splitlines()[-1]))
    best = int(np.argmin(rec["samples_s"]))
    rec |= {"build_time_s": rec["samples_s"][best], **{
        k: rec["parts"][best].get(k) for k in ("import_s", "kernel_load_s", "wall_time_s",
                                               "path")}}
    return rec


def bench(cases: Sequence[Case], engines: Sequence[str], *, repeats: int = 7,
          timeout_s: float = 600.0, progress: Callable[[str, dict], None] | None = None,
          references: Path | None = None, reuse: dict | None = None,
          cold: bool = True, spare: dict | None = None, budget=None,
          cell_budget_s: float = BUDGET_S) -> dict:
    """Benchmark and return ``{"records": [...], "machine": ..., "generated": ...}`` (and
    ``cold_start`` when natcoord is benchmarked and ``cold``). ``reuse``: ``{(case, engine):
    record}`` taken as they are instead of measured; ``spare``: ``{(case, engine): record}``
    measured after the others, in this order, while ``budget`` (a
    :class:`natcoord.suite.policy.Budget`) lasts, else taken as they are
    (:mod:`natcoord.suite.policy`); ``cell_budget_s``: process time a cell's samples may
    take."""
    jobs = [as_job(c) for c in cases]
    if "natcoord" in engines:  # an unusable kernel cache makes natcoord's cells slow: say so
        from ..compiled import codegen
        codegen.warn_uncached()
    reuse, spare = reuse or {}, spare or {}
    todo = [(job, engine) for job in jobs for engine in engines]
    found: dict[tuple, dict] = {}
    first = [(j, e) for j, e in todo if (j.case.name, e) not in spare]
    later = sorted((x for x in todo if (x[0].case.name, x[1]) in spare),
                   key=lambda x: list(spare).index((x[0].case.name, x[1])))
    cold_rec = None
    with tempfile.TemporaryDirectory(prefix="natcoord-bench-") as tmp:
        for job, engine in first + later:
            key = (job.case.name, engine)
            if key in reuse:
                rec = reuse[key]
            elif key in spare and budget is not None and not budget.left():
                rec = spare[key]
            else:
                rec = measure(job, engine, repeats, timeout_s, Path(tmp), references,
                              cell_budget_s)
                if key in spare and budget is not None:
                    budget.charge(rec)
            found[key] = rec
            if progress:
                progress(f"{job.case.name}/{engine}", rec)
        records = [found[(j.case.name, e)] for j, e in todo]
        if cold and "natcoord" in engines and jobs:  # after the runs above: kernels cached
            ran = [j for j in jobs if any(r["case"] == j.case.name and r["engine"] ==
                                          "natcoord" and r["status"] == "ok" for r in records)]
            cold_rec = cold_start((ran or jobs)[0], Path(tmp), timeout_s=timeout_s)
    by_key = {(r["case"], r["engine"]): r for r in records}
    for r in records:
        ref = by_key.get((r["case"], "natcoord"), {})
        if r.get("wall_time_s") and ref.get("wall_time_s"):
            r["wall_ratio_to_natcoord"] = r["wall_time_s"] / ref["wall_time_s"]
    out = {"generated": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
           "natcoord_version": __version__, "machine": machine_info(), "repeats": repeats,
           "records": records}
    if cold_rec is not None:
        out["cold_start"] = cold_rec
    return out


def store(result: dict, out: Path, history_dir: Path | None = None) -> Path:
    """Write ``out/bench.json`` and, when asked, a dated copy under ``history_dir``."""
    write_json(Path(out) / "bench.json", result)
    if history_dir is not None:
        stamp = result["generated"].replace(":", "").replace("+0000", "Z")
        write_json(Path(history_dir) / f"bench-{stamp}.json", result)
    return Path(out) / "bench.json"


def work_precision(cases: Sequence[Case], engines: Sequence[str], *,
                   references: Path = Path("references"), repeats: int = 5,
                   timeout_s: float = 600.0,
                   progress: Callable[[str, dict], None] | None = None,
                   sweeps: dict[str, list[dict]] | None = None,
                   skip: set | frozenset = frozenset(), budget=None,
                   free: Sequence[str] = (), cell_budget_s: float = BUDGET_S) -> list[dict]:
    """Error of the first angle channel (``error``) and, for a case with a ``[benchmark]``,
    the benchmark's error (``benchmark_error``) against CPU time over each engine's sweep:
    every sweep point timed as a bench cell (:func:`timed_runs`: ``repeats`` calibrated
    samples in one process), its best time per run.

    Returns one record per case x engine x setting, and per case x engine the time to
    reach each error in TARGETS (the cheapest point at or below it; None if none does).
    ``sweeps``: the settings per engine (default :data:`SWEEPS`); ``skip``: (case, engine)
    pairs not swept; ``budget`` (a :class:`natcoord.suite.policy.Budget`): an engine not in
    ``free`` starts a case's sweep only while it lasts, and its points are charged to it;
    ``cell_budget_s``: process time a point's samples may take.
    """

    sweeps = SWEEPS if sweeps is None else sweeps
    points = []
    with tempfile.TemporaryDirectory(prefix="natcoord-wp-") as tmp:
        for job in map(as_job, cases):
            case = job.case
            ref = usable_reference(case, references)  # None when stale or damaged
            angle = next((c.name for c in case.channels if c.kind == "angle"), None)
            if ref is None or (angle is None and not case.benchmark):
                continue
            for engine in engines:
                if (case.name, engine) in skip:
                    continue
                charged = budget is not None and engine not in free
                if charged and not budget.left():
                    continue
                for setting in sweeps.get(engine, []):
                    runs = timed_runs(job, engine, Path(tmp), timeout_s, repeats, setting,
                                      cell_budget_s)
                    if charged:
                        budget.charge(runs[-1])
                    ok = [r for r in runs if r["status"] == "ok"]
                    rec = {"case": case.name, "engine": engine, "setting": setting,
                           "variant": variant(setting), "channel": angle,
                           "status": runs[-1]["status"], "measured": now(),
                           "process_time_s": runs[-1].get("process_time_s")}
                    if ok:
                        csv = Path(tmp) / "results" / case.name / f"{engine}.csv"
                        run = pd.read_csv(csv)
                        err = (float(np.max(np.abs(run[angle].to_numpy() -
                                                   ref[angle].to_numpy())))
                               if angle else None)
                        rec |= {"error": err, "repeats": sum(len(r.get("samples_s") or [1])
                                                             for r in ok),
                                "wall_time_s": min(min(r.get("samples_s") or
                                                       [r["wall_time_s"]]) for r in ok),
                                "n_steps": ok[0]["n_steps"]}
                        if case.benchmark:
                            rec["benchmark_error"] = benchmark_error(case, csv, references)
                    points.append(rec)
                    if progress:
                        label = " ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                                         for k, v in setting.items() if v is not None)
                        progress(f"{case.name}/{engine} {label}", rec)
    return points


def scoring(cases: Sequence[Case], records: list[dict], points: list[dict]) -> list[dict]:
    """IFToMM-style scoring, per case with a ``[benchmark]`` x engine: the benchmark error at
    the case's settings (``error``, from the bench record), and the least wall time of a run
    within the benchmark's precision (``time_to_precision``: over the case's settings, best
    of the bench's repeats or, for a cell the bench did not time, the stepping time of its
    accuracy run; and every work-precision sweep point, each timed once; None: not reached)
    with the setting that reached it (``reached_by``)."""
    out = []
    for case in (c.case if hasattr(c, "case") else c for c in cases):
        spec = case.benchmark
        if not spec:
            continue
        prec = spec["precision"]
        for r in records:
            if r.get("case") != case.name:
                continue
            engine = r.get("engine")
            err = r.get("benchmark_error")
            cand = []
            if r.get("status") == "ok" and err is not None and err <= prec and r.get(
                    "wall_time_s"):
                cand.append((r["wall_time_s"], "case settings" + (
                    f" ({r['timed_by'].get('run', 'accuracy run')})" if r.get("timed_by")
                    else "")))
            for p in points:
                e = p.get("benchmark_error")
                if (p.get("case"), p.get("engine")) == (case.name, engine) and (
                        e is not None and e <= prec and p.get("wall_time_s")):
                    label = " ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                                     for k, v in (p.get("setting") or {}).items()
                                     if v is not None)
                    cand.append((p["wall_time_s"], label))
            best = min(cand, default=(None, ""))
            swept = [p for p in points
                     if (p.get("case"), p.get("engine")) == (case.name, engine)
                     and p.get("benchmark_error") is not None]
            out.append({"case": case.name, "engine": engine, "status": r.get("status"),
                        "channels": list(spec["channels"]), "precision": prec,
                        "error_kind": spec["error"], "source": spec["source"],
                        "error": err, "wall_time_s": r.get("wall_time_s"),
                        "time_to_precision": best[0], "reached_by": best[1],
                        "best_swept_error": min((p["benchmark_error"] for p in swept),
                                                default=None)})
    return out


def variant(setting: dict) -> str:
    """Label of a sweep's formulation and integrator, e.g. ``index1 dop853`` ('' when the
    sweep varies only a step size)."""
    return " ".join(str(setting[k]) for k in ("formulation", "method") if k in setting)


def time_to_accuracy(points: list[dict], targets=TARGETS) -> list[dict]:
    """Per case x engine x variant, the least wall time of a sweep point with error <=
    target (None: not reached) and that time interpolated on the sweep's curve
    (:func:`interpolated_time`), keyed by :func:`time_to_key`."""
    out = []
    points = [p for p in points if p.get("channel", "") is not None]  # a case without an
    # angle channel is swept for its benchmark output only
    keys = sorted({(p["case"], p["engine"], p.get("variant", "")) for p in points})
    for case, engine, var in keys:
        mine = [p for p in points if (p["case"], p["engine"], p.get("variant", ""))
                == (case, engine, var) and p.get("error") is not None]
        row = {"case": case, "engine": engine if not var else f"{engine} ({var})"}
        for target in targets:
            good = [p for p in mine if p["error"] <= target]
            row[time_to_key(target)] = min((p["wall_time_s"] for p in good), default=None)
            row[time_to_key(target, True)] = interpolated_time(
                [(p["wall_time_s"], p["error"]) for p in mine], target)
        out.append(row)
    return out


def time_to_key(target: float, interpolated: bool = False) -> str:
    """The key of a ``time_to_accuracy`` row's time to ``target``, e.g. ``time_to_1e-06``
    (``interpolated_time_to_1e-06``: :func:`interpolated_time`)."""
    return f"{'interpolated_' if interpolated else ''}time_to_{target:g}"


def interpolated_time(curve: list[tuple[float, float]], target: float) -> float | None:
    """The wall time (s) at which a sweep's curve of (wall time s, error) points reaches
    ``target``, interpolated linearly in log time against log error between the cheapest
    point at or under the target and the costliest point cheaper than it (over it, then).
    The cheapest point alone flatters a sweep whose grid jumps far past the target; None
    when no cheaper point brackets the target (or none reaches it)."""
    pts = [(w, e) for w, e in curve if w > 0 and e > 0 and math.isfinite(w) and
           math.isfinite(e)]
    good = [p for p in pts if p[1] <= target]
    if not good:
        return None
    wb, eb = min(good)
    over = [p for p in pts if p[0] < wb]
    if not over:
        return None
    wa, ea = max(over)
    frac = (math.log(ea) - math.log(target)) / (math.log(ea) - math.log(eb))
    return math.exp(math.log(wa) + frac * (math.log(wb) - math.log(wa)))
