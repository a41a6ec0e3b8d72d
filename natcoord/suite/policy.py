"""The nightly's bench policy: which bench cells a suite measures tonight, which it takes
from earlier suites' ``bench.json`` and which it times by tonight's accuracy run.

* natcoord's cells are measured every night (calibrated samples), with a short
  work-precision sweep (:data:`NIGHTLY_SWEEPS`).
* An external engine's cell (its bench record and its work-precision points) is measured
  again only when its engine version (tonight's accuracy run says which), the case file
  (sha256), its adapter's code (sha256 of the adapter's files), the machine (fingerprint)
  or the samples asked for changed, when it is older than :data:`MAX_AGE`, or when no
  earlier suite (:func:`earlier`) has a calibrated record of it. Otherwise it is reused,
  marked ``reused`` with the time it was measured and the folder it comes from.
* The external cells to measure share a night's budget (:class:`Budget`: engine process
  time, ``natcoord suite --bench-budget``): the never measured first, then the oldest,
  the cheapest first among equals; a cell is measured with its sweep points while the
  budget lasts. A cell left over, and any cell (natcoord's too) whose single run is longer
  than a bench cell's timing budget (the bench would time that one run too), is **timed by
  its accuracy run**:
  the stepping time of tonight's run (one sample, BLAS on one thread, each parallel run
  pinned to a core of its own), marked ``timed_by``; it is measured on a later night.
* A reused or run-timed cell is not a bench measurement (:func:`natcoord.suite.stored.carried`):
  the history does not record its samples and the speed gate does not judge it.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path

from ..engines.registry import adapter_digest
from ..errors import NatcoordError
from . import bench, eta, history
from .io import read_json
from .stored import carried, check_bench

MAX_AGE = dt.timedelta(days=7)
CELL_BUDGET_S = 4.0  # s of process time a nightly cell's (or sweep point's) samples may take
ALWAYS = ("natcoord",)  # engines measured every night
# The suite's work-precision sweeps, on the cases with a [benchmark] table (the catalogue):
# natcoord index-1 DOP853 at four tolerances; another engine every other setting of its
# full sweep (coarse to fine). `natcoord bench --work-precision` keeps the full sweeps.
NIGHTLY_SWEEPS = {"natcoord": [{"formulation": "index1", "method": "dop853", "h": None,
                                "rtol": r, "atol": r * 1e-2}
                               for r in (1e-5, 1e-8, 1e-11)]}
NIGHTLY_SWEEPS |= {e: s[::2] for e, s in bench.SWEEPS.items() if e not in NIGHTLY_SWEEPS}
QUICK_ENGINES = ("natcoord", "mujoco")  # `suite --quick`: a first look within 2 minutes


def earlier(db: Path, machine: str, last: int = 20) -> tuple[dict | None, dict | None]:
    """The newest measurement of every cell over the last ``last`` recorded suites on this
    machine whose folders still hold a readable ``bench.json`` (a one-case suite does not
    hide the nights before it): a bench-like ``{"machine", "records", "work_precision",
    "origins": {"case/engine": folder}}`` and a summary-like ``{"records"}`` (for the
    durations; with the newest successful ``cold_start``), or (None, None). A damaged or
    vanished file is skipped (measured again)."""
    with history.reading(db) as con:
        if con is None:
            return None, None
        rows = con.execute("SELECT results_dir FROM runs WHERE kind = 'suite' AND machine = ? "
                           "AND IFNULL(results_dir, '') != '' ORDER BY id DESC LIMIT ?",
                           (machine, last)).fetchall()
    bench_, runs, origins, machine_info, cold = [], {}, {}, None, None
    points: list = []
    for (folder,) in rows:
        path = Path(folder) / "bench.json"
        try:
            data = check_bench(path, read_json(path)) if path.is_file() else None
        except (NatcoordError, OSError):
            data = None
        if data is None:
            continue
        try:
            summary = read_json(Path(folder) / "summary.json")
        except (NatcoordError, OSError):
            summary = None
        machine_info = machine_info or data.get("machine")
        if cold is None and eta.cold_start_s(data) is not None:
            cold = data["cold_start"]  # the newest natcoord cold start
        for r in data.get("records", []):
            key = f"{r['case']}/{r['engine']}"
            if key not in origins and "timed_by" not in r:  # a calibrated measurement
                origins[key] = str(folder)
                bench_.append(r)
                points += [p for p in data.get("work_precision", [])
                           if isinstance(p, dict) and f"{p.get('case')}/{p.get('engine')}"
                           == key]
        for r in (summary or {}).get("records", []) if isinstance(summary, dict) else []:
            if isinstance(r, dict):
                runs.setdefault((r.get("case"), r.get("engine")), r)
    if not origins:
        return None, None
    return ({"machine": machine_info or {}, "records": bench_, "work_precision": points,
             "origins": origins} | ({"cold_start": cold} if cold else {}),
            {"records": list(runs.values())})


def stale(old: dict | None, *, engine_version: str, case_hash: str, adapter: str,
          machine: str, old_machine: str, repeats: int, when: dt.datetime) -> str:
    """Why a previous bench record cannot stand for tonight's ('' when it can)."""
    if not old or old.get("status") != "ok" or not old.get("samples_s") or "timed_by" in old:
        return "no earlier measurement"
    if old_machine != machine:
        return "another machine"
    if old.get("engine_version") != engine_version:
        return f"engine version {old.get('engine_version') or '?'} -> {engine_version or '?'}"
    if old.get("case_hash") != case_hash:
        return "case file changed"
    if old.get("adapter_hash") != adapter:
        return "adapter code changed"
    if old.get("requested_repeats", old.get("repeats")) != repeats:
        return "other sample count"
    try:
        measured = dt.datetime.fromisoformat(old["measured"])
    except (KeyError, TypeError, ValueError):
        return "measurement date unknown"
    if when - measured > MAX_AGE:
        return f"measured {measured:%Y-%m-%d}, over {MAX_AGE.days} days ago"
    return ""


@dataclass
class Plan:
    """What tonight's bench does per case x engine that ran: ``reuse`` (records marked
    reused) with ``kept`` (their work-precision points), ``measure`` (why each cell is
    measured), ``spare`` (for each external cell to measure, in the order the budget takes
    them, the record it falls back to: timed by its accuracy run) and ``timed`` (records
    timed by their accuracy run without asking the budget: one run longer than a bench
    cell's timing budget)."""

    reuse: dict = field(default_factory=dict)
    kept: list = field(default_factory=list)
    measure: dict = field(default_factory=dict)
    spare: dict = field(default_factory=dict)
    timed: dict = field(default_factory=dict)


@dataclass
class Budget:
    """Engine process time (s) tonight's bench may spend on external cells: their bench
    record and their sweep points. A piece starts while some budget is left."""

    total: float
    spent: float = 0.0

    def left(self) -> bool:
        return self.spent < self.total

    def charge(self, record: dict) -> None:
        t = record.get("process_time_s")
        self.spent += float(t) if isinstance(t, (int, float)) else 0.0


def from_run(run: dict, why: str) -> dict:
    """A cell's bench record from tonight's accuracy-run record ``run``: its stepping time
    (build time apart) as the one sample, marked ``timed_by`` with ``why``."""
    wall, steps = run.get("wall_time_s"), run.get("n_steps") or 0
    counters = run.get("counters") or {}
    return {"case": run["case"], "engine": run["engine"], "status": "ok",
            "reason": "", "case_hash": run.get("case_hash", ""),
            "engine_version": run.get("engine_version", ""), "measured": bench.now(),
            "adapter_hash": adapter_digest(run["engine"]), "repeats": 1,
            "samples_s": [wall], "cpu_samples_s": [], "batch_runs": [1],
            "wall_time_s": wall, "wall_spread": 0.0, "wall_median_s": wall,
            "build_time_s": run.get("build_time_s") or 0.0, "n_steps": steps,
            "us_per_step": 1e6 * wall / steps if steps else None,
            "settings": run.get("settings") or {},
            "counters": {k: counters[k] for k in bench.COUNTERS
                         if isinstance(counters.get(k), (int, float))},
            "timed_by": {"run": "accuracy run", "why": why}} | (
        {"benchmark_error": run["benchmark_error"]} if "benchmark_error" in run else {})


def _cost(run: dict, repeats: int) -> float:
    """Expected process time (s) of a cell's bench from its accuracy run: start-up and
    build, the warm-up runs (whole and cost-fit), the calibrated samples within the
    cell's timing budget."""
    wall = float(run.get("wall_time_s") or 0.0)
    total = float(run.get("process_time_s") or wall)
    one = (1 + bench.FIT_FRACTION) * wall
    return (total - wall) + one + min(CELL_BUDGET_S, repeats * max(one, bench.MIN_BATCH_S))


def plan(summary: dict, previous: dict | None, engines, *,
         repeats: int, machine: str, when: dt.datetime | None = None) -> Plan:
    """The bench plan (:class:`Plan`) for tonight's accuracy run ``summary``; ``previous``:
    the earlier measurements (:func:`earlier`, or None)."""
    when = when or dt.datetime.now(dt.UTC)
    old = {(r["case"], r["engine"]): r for r in (previous or {}).get("records", [])}
    old_machine = ((previous or {}).get("machine") or {}).get("fingerprint", "")
    points: dict[tuple, list] = {}
    for p in (previous or {}).get("work_precision", []):
        points.setdefault((p.get("case"), p.get("engine")), []).append(p)
    digests = {e: adapter_digest(e) for e in engines if e not in ALWAYS}
    out, queue = Plan(), []
    for r in summary.get("records", []):
        key = (r["case"], r["engine"])
        wall = r.get("wall_time_s")
        if r.get("status") == "ok" and isinstance(wall, (int, float)) and wall > CELL_BUDGET_S:
            out.timed[key] = from_run(r, f"one run takes {wall:.1f} s, more than a nightly "
                                      f"cell's timing budget ({CELL_BUDGET_S:g} s): its accuracy "
                                      "run is its timing")
            continue
        if r["engine"] in ALWAYS:
            out.measure[key] = "measured every night"
            continue
        if r.get("status") != "ok":
            continue  # the bench finds out again (unsupported or failed: no timing)
        why = stale(old.get(key), engine_version=r.get("engine_version", ""),
                    case_hash=r.get("case_hash", ""), adapter=digests.get(r["engine"], ""),
                    machine=machine, old_machine=old_machine, repeats=repeats, when=when)
        if not why:
            mark = {"measured": old[key]["measured"],
                    "from": previous.get("origins", {}).get("/".join(key), "")}
            out.reuse[key] = {**old[key], "reused": mark}
            out.kept += [{**p, "reused": mark} for p in points.get(key, [])]
            continue
        out.measure[key] = why
        never = why == "no earlier measurement"
        age = "" if never else (old.get(key) or {}).get("measured") or ""
        queue.append((not never, age, _cost(r, repeats), key, r))
    for *_, key, r in sorted(queue, key=lambda x: x[:3]):
        out.spare[key] = from_run(r, "over tonight's bench budget: timed by its accuracy "
                                  "run, measured on a later night")
    return out


def quick(summary: dict) -> Plan:
    """`suite --quick`'s plan: no bench process; every cell that ran is timed by its
    accuracy run, the others keep their status."""
    timed = {}
    for r in summary.get("records", []):
        key = (r["case"], r["engine"])
        timed[key] = (from_run(r, "quick suite: timed by its accuracy run")
                      if r.get("status") == "ok" and r.get("wall_time_s")
                      else {"case": key[0], "engine": key[1], "status": r.get("status"),
                            "reason": r.get("reason", ""), "timed_by": {
                                "run": "accuracy run", "why": "quick suite"}})
    return Plan(timed=timed)


def likely_reused(previous: dict | None, digests: dict[str, str],
                  when: dt.datetime | None = None) -> set[tuple]:
    """The (case, engine) cells of the earlier measurements that tonight will probably
    reuse (same case file, young enough; engine versions are known only after tonight's
    accuracy run): for the time estimate before it."""
    when = when or dt.datetime.now(dt.UTC)
    out = set()
    for r in (previous or {}).get("records", []):
        key = (r.get("case"), r.get("engine"))
        if key[1] in ALWAYS or digests.get(key[0]) != r.get("case_hash"):
            continue
        if not stale(r, engine_version=r.get("engine_version", ""),
                     case_hash=r.get("case_hash", ""), adapter=r.get("adapter_hash", ""),
                     machine="", old_machine="", repeats=r.get("requested_repeats"),
                     when=when):
            out.add(key)
    return out


def measured_only(result: dict) -> dict:
    """A bench result holding only tonight's measurements (the same record objects): what
    the speed gate judges and the history records."""
    return {**result, "records": [r for r in result.get("records", []) if not carried(r)]}
