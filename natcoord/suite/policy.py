"""The nightly's bench policy: which bench cells a suite measures tonight and which it takes
from earlier suites' ``bench.json``.

* natcoord's cells are measured every night (calibrated samples), with a short
  work-precision sweep (:data:`NIGHTLY_SWEEPS`).
* An external engine's cell (its bench record and its work-precision points) is measured
  again only when its engine version (tonight's accuracy run says which), the case file
  (sha256), its adapter's code (sha256 of the adapter's files), the machine (fingerprint)
  or the samples asked for changed, when it is older than :data:`MAX_AGE`, or when no
  earlier suite (:func:`earlier`) has a record of it. Otherwise it is reused, marked
  ``reused`` with the time it was measured and the folder it comes from.
* A reused cell is not a new measurement: the history does not record its samples again and
  the speed gate does not judge it.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from ..engines.registry import adapter_digest
from ..errors import NatcoordError
from . import bench, history
from .io import read_json
from .stored import check_bench

MAX_AGE = dt.timedelta(days=7)
ALWAYS = ("natcoord",)  # engines measured every night
# The suite's work-precision sweeps, on the cases with a [benchmark] table (the catalogue):
# natcoord index-1 DOP853 at four tolerances; another engine every other setting of its
# full sweep (coarse to fine). `natcoord bench --work-precision` keeps the full sweeps.
NIGHTLY_SWEEPS = {"natcoord": [{"formulation": "index1", "method": "dop853", "h": None,
                                "rtol": r, "atol": r * 1e-2}
                               for r in (1e-5, 1e-7, 1e-9, 1e-11)]}
NIGHTLY_SWEEPS |= {e: s[::2] for e, s in bench.SWEEPS.items() if e not in NIGHTLY_SWEEPS}
QUICK_ENGINES = ("natcoord", "mujoco", "pinocchio")  # `suite --quick`: the fastest to start


def earlier(db: Path, machine: str, last: int = 20) -> tuple[dict | None, dict | None]:
    """The newest measurement of every cell over the last ``last`` recorded suites on this
    machine whose folders still hold a readable ``bench.json`` (a one-case suite does not
    hide the nights before it): a bench-like ``{"machine", "records", "work_precision",
    "origins": {"case/engine": folder}}`` and a summary-like ``{"records"}`` (for the
    durations), or (None, None). A damaged or vanished file is skipped (measured again)."""
    with history.reading(db) as con:
        if con is None:
            return None, None
        rows = con.execute("SELECT results_dir FROM runs WHERE kind = 'suite' AND machine = ? "
                           "AND IFNULL(results_dir, '') != '' ORDER BY id DESC LIMIT ?",
                           (machine, last)).fetchall()
    bench_, runs, origins, machine_info = [], {}, {}, None
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
        for r in data.get("records", []):
            key = f"{r['case']}/{r['engine']}"
            if key not in origins:
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
             "origins": origins}, {"records": list(runs.values())})


def stale(old: dict | None, *, engine_version: str, case_hash: str, adapter: str,
          machine: str, old_machine: str, repeats: int, when: dt.datetime) -> str:
    """Why a previous bench record cannot stand for tonight's ('' when it can)."""
    if not old or old.get("status") != "ok" or not old.get("samples_s"):
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


def plan(summary: dict, previous: dict | None, engines, *,
         repeats: int, machine: str, when: dt.datetime | None = None
         ) -> tuple[dict, list, dict]:
    """Per case x engine of tonight's accuracy run (``summary``) that ran: the bench records
    to reuse ``{(case, engine): record marked reused}``, the work-precision points that go
    with them (marked too), and why each other cell is measured ``{(case, engine):
    reason}``. ``previous``: the earlier measurements (:func:`earlier`, or None)."""
    when = when or dt.datetime.now(dt.UTC)
    old = {(r["case"], r["engine"]): r for r in (previous or {}).get("records", [])}
    old_machine = ((previous or {}).get("machine") or {}).get("fingerprint", "")
    points: dict[tuple, list] = {}
    for p in (previous or {}).get("work_precision", []):
        points.setdefault((p.get("case"), p.get("engine")), []).append(p)
    digests = {e: adapter_digest(e) for e in engines if e not in ALWAYS}
    reuse, kept, measure = {}, [], {}
    for r in summary.get("records", []):
        key = (r["case"], r["engine"])
        if r["engine"] in ALWAYS:
            measure[key] = "measured every night"
            continue
        if r.get("status") != "ok":
            continue  # the bench finds out again (unsupported or failed: no timing)
        why = stale(old.get(key), engine_version=r.get("engine_version", ""),
                    case_hash=r.get("case_hash", ""), adapter=digests.get(r["engine"], ""),
                    machine=machine, old_machine=old_machine, repeats=repeats, when=when)
        if why:
            measure[key] = why
            continue
        mark = {"measured": old[key]["measured"],
                "from": previous.get("origins", {}).get("/".join(key), "")}
        reuse[key] = {**old[key], "reused": mark}
        kept += [{**p, "reused": mark} for p in points.get(key, [])]
    return reuse, kept, measure


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
    return {**result, "records": [r for r in result.get("records", []) if "reused" not in r]}
