"""The regression gate: judge a results directory, print what regressed, return an exit code.

Exit codes: 0 all hold; 1 an accuracy regression (a gated channel over its tolerance, or an
error grown past the stored baseline); 2 bad input (no or malformed summary, a case without
a reference or without tolerances for an engine that ran); 3 nothing ran, or a required
engine failed or was skipped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import StoredFileError
from .io import read_json, write_json

OK, REGRESSION, BAD_INPUT, NOT_RUN = 0, 1, 2, 3
REQUIRED_FIELDS = ("case", "engine", "status", "verdict", "channels")


@dataclass
class Verdict:
    code: int
    lines: list[str] = field(default_factory=list)


def _fmt(x: float | None, unit: str = "") -> str:
    return "n/a" if x is None else f"{x:.3g}{' ' + unit if unit else ''}"


def load_summary(results: Path) -> dict:
    """Read and check ``results/summary.json`` (every field the gate reads, with its type);
    raises ValueError naming the problem."""
    path = Path(results) / "summary.json"
    if not path.exists():
        raise ValueError(f"{path}: no summary (run `natcoord run` first; an interrupted run "
                         "leaves none on purpose)")
    try:
        summary = read_json(path)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    records = summary.get("records") if isinstance(summary, dict) else None
    if not isinstance(records, list):
        raise ValueError(f"{path}: records: missing or not a list")
    for i, r in enumerate(records):
        missing = [k for k in REQUIRED_FIELDS if not isinstance(r, dict) or k not in r]
        if missing:
            raise ValueError(f"{path}: records[{i}]: missing field {missing[0]!r}")
        for k in ("case", "engine", "status", "verdict"):
            if not isinstance(r[k], str):
                raise ValueError(f"{path}: records[{i}].{k}: not a string")
        if not isinstance(r["channels"], dict) or not all(
                isinstance(c, dict) for c in r["channels"].values()):
            raise ValueError(f"{path}: records[{i}].channels: not a table of channels")
        for name, c in r["channels"].items():
            for k in ("max_abs", "tolerance"):
                if c.get(k) is not None and (isinstance(c[k], bool)
                                             or not isinstance(c[k], (int, float))):
                    raise ValueError(f"{path}: records[{i}].channels.{name}.{k}: not a number")
    for k in ("cases", "engines"):
        if k in summary and not (isinstance(summary[k], list)
                                 and all(isinstance(x, str) for x in summary[k])):
            raise ValueError(f"{path}: {k}: not a list of names")
    return summary


def judge(summary: dict, *, required: set[str] | None = None, baseline: dict | None = None,
          baseline_factor: float = 10.0, floor: float = 1e-12) -> Verdict:
    """Apply the gate's rules to a summary; the worst outcome wins (3 > 2 > 1 > 0)."""
    v = Verdict(OK)
    records = summary["records"]
    if not any(r["status"] == "ok" for r in records):
        v.code = NOT_RUN
        v.lines.append("nothing ran: no case x engine finished with status ok")
        return v
    have = {(r["case"], r["engine"]) for r in records}
    engines = set(summary.get("engines", ())) | (required or set())
    for case in summary.get("cases", ()):  # every cell asked for must have its record
        for engine in sorted(engines):
            if (case, engine) not in have:
                v.code = max(v.code, NOT_RUN)
                v.lines.append(f"{case}/{engine}: no record (required, not run)")
    for r in records:
        key = f"{r['case']}/{r['engine']}"
        if r["status"] in ("failed", "skipped") and (required is None or r["engine"] in required):
            v.code = max(v.code, NOT_RUN)
            v.lines.append(f"{key}: required engine {r['status']}: {r.get('reason', '')}")
            continue
        if r["status"] == "ok" and r["verdict"] in ("no-reference", "not-gated"):
            v.code = max(v.code, BAD_INPUT)
            v.lines.append(f"{key}: cannot judge: {r.get('verdict_reason', r['verdict'])}")
            continue
        for name, c in r["channels"].items():
            if c.get("pass") is False:
                v.code = max(v.code, REGRESSION)
                if c.get("max_abs") is None or c["max_abs"] == float("inf"):
                    v.lines.append(f"{key}: {name}: {c.get('note') or 'no value'}")
                    continue
                ratio = c["max_abs"] / c["tolerance"] if c["tolerance"] else float("inf")
                unit = c.get("unit", "")
                v.lines.append(f"{key}: {name} max error {_fmt(c['max_abs'], unit)} > "
                               f"tolerance {_fmt(c['tolerance'], unit)} ({ratio:.3g}x)")
            base = (baseline or {}).get(key, {}).get(name)
            err = c.get("max_abs")
            tol = c.get("tolerance")
            # growth below a tenth of the tolerance is platform noise, not a regression
            if c.get("determined", True) and base is not None and err is not None and \
                    tol is not None and err > max(baseline_factor * base, floor, 0.1 * tol):
                v.code = max(v.code, REGRESSION)
                v.lines.append(f"{key}: {name} error {_fmt(err, c.get('unit', ''))} grew "
                               f"{err / max(base, floor):.3g}x over the baseline "
                               f"{_fmt(base, c.get('unit', ''))} (limit {baseline_factor:g}x)")
    return v


def baseline_of(summary: dict) -> dict:
    """Per case/engine, per channel max error of a run: the stored baseline's content."""
    return {f"{r['case']}/{r['engine']}": {n: c["max_abs"] for n, c in r["channels"].items()
                                           if c.get("max_abs") is not None}
            for r in summary["records"] if r["status"] == "ok"}


def update_baseline(summary: dict, path: Path) -> None:
    """Store the errors of every cell this summary ran over the stored baseline: cells the
    run did not touch keep their entries (a subset run never shrinks the baseline)."""
    errors = (load_baseline(path) or {}) | baseline_of(summary)
    write_json(path, {"generated": summary.get("generated"), "errors": errors})


def load_baseline(path: Path) -> dict | None:
    """The stored baseline's errors ({cell: {channel: error}}), None when there is none;
    StoredFileError (a ValueError) naming the file and the problem when it is malformed."""
    if not Path(path).exists() and not Path(path).is_symlink():
        return None
    data = read_json(path)
    errors = data.get("errors") if isinstance(data, dict) else None
    if not isinstance(errors, dict):
        raise StoredFileError(f"{path}: errors: missing or not a table (malformed baseline)")
    for cell, channels in errors.items():
        if not isinstance(channels, dict) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool)
                for v in channels.values()):
            raise StoredFileError(f"{path}: errors.{cell}: not a table of channel errors "
                                  "(malformed baseline)")
    return errors
