"""Tolerances proposed from measurement, for a new case.

:func:`propose` runs a case in each engine at the case's settings (and, to show how the
error converges, at the engine's work-precision sweep), measures every channel's error
against the case's reference, and proposes each determined channel's tolerance as the
measured error times a margin, rounded up to one significant digit, and never below the
**platform margin**: ``PLATFORM_MARGIN`` times the round-off a run of that many steps
accumulates on the channel's values (:func:`natcoord.estimates.roundoff`; a channel that is
zero throughout takes the size of the reference's channels of its unit). An error measured at
round-off on this machine is no bound on another CPU or BLAS kernel: the stock cases leave
100-1000x for machine differences. The result is TOML to paste into the case file, with a
reason that says what was measured (and which tolerances the platform margin set); an
engine that cannot run the case gets ``unsupported`` with its reason instead.
"""

from __future__ import annotations

import datetime as dt
import math
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from ..estimates import roundoff
from .bench import SWEEPS
from .compare import channel_errors
from .references import load_provenance, load_reference
from .runner import as_job, run_subprocess

FLOOR = 1e-14  # no tolerance below round-off
PLATFORM_MARGIN = 100.0  # x the round-off of the run: room for other CPUs and BLAS kernels


def round_up(x: float) -> float:
    """x rounded up to one significant digit (at least FLOOR)."""
    x = max(float(x), FLOOR)
    e = math.floor(math.log10(x))
    return math.ceil(x / 10**e - 1e-9) * 10**e


def platform_floors(case, reference: pd.DataFrame, steps: int) -> dict[str, float]:
    """Per channel of ``case`` in ``reference``: the smallest tolerance a proposal may
    give, PLATFORM_MARGIN x the round-off of ``steps`` steps on the channel's values (a
    channel zero throughout: on the largest channel of its unit, else on 1)."""
    peak = {c.name: float(np.nanmax(np.abs(reference[c.name].to_numpy(float))))
            for c in case.channels if c.name in reference and len(reference)}
    by_unit: dict[str, float] = {}
    for c in case.channels:
        if np.isfinite(peak.get(c.name, np.nan)):
            by_unit[c.unit] = max(by_unit.get(c.unit, 0.0), peak[c.name])
    out = {}
    for c in case.channels:
        scale = peak.get(c.name, 0.0)
        if not (np.isfinite(scale) and scale > 0):
            scale = by_unit.get(c.unit) or 1.0
        out[c.name] = PLATFORM_MARGIN * roundoff(scale, steps)
    return out


def _errors(case, engine, folder: Path, reference, undetermined) -> dict[str, float]:
    table = pd.read_csv(folder / "results" / case.name / f"{engine}.csv")
    channels, _, _ = channel_errors(case, engine, table, reference, undetermined)
    return {n: c["max_abs"] for n, c in channels.items()
            if c.get("determined", True) and c.get("max_abs") is not None}


def propose(case, engines, references: Path, *, margin: float = 3.0,
            timeout_s: float = 600.0, sweep: int = 3) -> list[dict]:
    """Per engine: status, the errors at the case's settings, the first angle channel's
    error over up to ``sweep`` settings of its sweep, and the proposed tolerances."""
    job = as_job(case)
    case = job.case
    reference = load_reference(case.name, references)
    if reference is None:
        raise ValueError(f"{case.name}: no reference stored; run `natcoord reference update "
                         f"{case.name}` first")
    undetermined = (load_provenance(case.name, references) or {}).get("undetermined", ())
    angle = next((c.name for c in case.channels if c.kind == "angle"), None)
    out = []
    with tempfile.TemporaryDirectory(prefix="natcoord-propose-") as tmp:
        for engine in engines:
            rec = run_subprocess(job, engine, Path(tmp), timeout_s)
            row = {"engine": engine, "status": rec["status"], "reason": rec.get("reason", ""),
                   "settings": rec.get("settings", {}), "errors": {}, "sweep": [],
                   "tolerance": {}}
            if rec["status"] == "ok":
                row["errors"] = _errors(case, engine, Path(tmp), reference, undetermined)
                floors = platform_floors(case, reference,
                                         int(rec.get("n_steps") or len(reference)))
                row["tolerance"] = {k: round_up(max(margin * v, floors.get(k, 0.0)))
                                    for k, v in row["errors"].items()}
                row["floored"] = [k for k, v in row["errors"].items()
                                  if floors.get(k, 0.0) > margin * v]
                for setting in SWEEPS.get(engine, [])[:sweep] if angle else []:
                    r = run_subprocess(job, engine, Path(tmp), timeout_s, setting)
                    err = (_errors(case, engine, Path(tmp), reference, undetermined).get(angle)
                           if r["status"] == "ok" else None)
                    row["sweep"].append({"setting": setting, "error": err,
                                         "wall_time_s": r.get("wall_time_s")})
            out.append(row)
    return out


def as_toml(case, rows: list[dict], margin: float) -> str:
    """The engine blocks to paste into the case file."""
    today = dt.date.today().isoformat()
    units = {c.name: c.unit for c in case.channels}
    lines = [f"# proposed by `natcoord propose {case.name}` on {today}: measured errors at "
             f"each engine's settings x {margin:g}, rounded up", ""]
    for row in rows:
        e = row["engine"]
        lines.append(f"[engines.{e}]")
        if row["status"] == "unsupported":
            lines += [f"unsupported = {_q(row['reason'])}", ""]
            continue
        if row["status"] != "ok":
            lines += [f"# {e} {row['status']}: {row['reason']}", ""]
            continue
        measured = ", ".join(f"{k} {v:.2g} {units.get(k, '')}".rstrip()
                             for k, v in row["errors"].items())
        conv = "; ".join(f"{_setting(s['setting'])}: {s['error']:.2g}"
                         for s in row["sweep"] if s["error"] is not None)
        floored = row.get("floored") or []
        reason = (f"measured at {_setting(row['settings']) or 'its defaults'}: {measured}"
                  f"{'; first angle over its sweep: ' + conv if conv else ''}; bounds "
                  f"{margin:g}x the measured errors"
                  + (f", {PLATFORM_MARGIN:g}x the run's round-off for {', '.join(floored)} "
                     "(room for other machines)" if floored else ""))
        lines += [f"reason = {_q(reason)}", f"[engines.{e}.tolerance]"]
        lines += [f"{k} = {v:.0e}" for k, v in row["tolerance"].items()]
        lines.append("")
    return "\n".join(lines)


def _setting(s: dict) -> str:
    return " ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                    for k, v in (s or {}).items() if v is not None and not isinstance(v, dict))


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


FALL = 0.5  # the sweep's last error at most this fraction of its first: it falls
ROUND_OFF = 1e-12  # rad: errors all below this are at round-off, where none can fall


def converged(sweep: list[dict]) -> bool:
    """Whether the sweep's errors fall as the setting tightens: the last at most FALL times
    the first (a last error a hair below the first, a flat sweep, once passed), or every one
    at round-off (below ROUND_OFF)."""
    errs = [s["error"] for s in sweep if s["error"] is not None]
    if len(errs) < 2 or not np.isfinite(errs).all():
        return False
    return errs[-1] <= FALL * errs[0] or max(errs) < ROUND_OFF
