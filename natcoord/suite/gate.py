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
    """Read and check ``results/summary.json``; raises ValueError naming the problem."""
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
                ratio = c["max_abs"] / c["tolerance"] if c["tolerance"] else float("inf")
                v.lines.append(f"{key}: {name} max error {_fmt(c['max_abs'], c['unit'])} > "
                               f"tolerance {_fmt(c['tolerance'], c['unit'])} ({ratio:.3g}x)")
            base = (baseline or {}).get(key, {}).get(name)
            err = c.get("max_abs")
            tol = c.get("tolerance")
            # growth below a tenth of the tolerance is platform noise, not a regression
            if c.get("determined", True) and base is not None and err is not None and \
                    tol is not None and err > max(baseline_factor * base, floor, 0.1 * tol):
                v.code = max(v.code, REGRESSION)
                v.lines.append(f"{key}: {name} error {_fmt(err, c['unit'])} grew "
                               f"{err / max(base, floor):.3g}x over the baseline "
                               f"{_fmt(base, c['unit'])} (limit {baseline_factor:g}x)")
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
    if not Path(path).exists():
        return None
    try:
        return read_json(path)["errors"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: malformed baseline ({e})") from None
