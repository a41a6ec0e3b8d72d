"""Nightly history: one JSON line per suite run, appended to ``reports/history.jsonl``."""

from __future__ import annotations

import json
from pathlib import Path

from .io import _clean


def entry(summary: dict, gate_code: int, bench: dict | None = None) -> dict:
    """A compact line: verdict counts, gate code, per case/engine worst relative error and
    step cost."""
    per = {}
    for r in summary["records"]:
        rel = [c["max_rel"] for c in r.get("channels", {}).values()
               if c.get("max_rel") is not None and c.get("determined", True)]
        per[f"{r['case']}/{r['engine']}"] = {"status": r["status"], "verdict": r["verdict"],
                                             "worst_rel": max(rel) if rel else None,
                                             "us_per_step": r.get("us_per_step")}
    counts: dict[str, int] = {}
    for r in summary["records"]:
        counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
    out = {"generated": summary["generated"], "natcoord_version": summary["natcoord_version"],
           "gate": gate_code, "verdicts": counts, "runs": per}
    if bench:
        out["bench_us_per_step"] = {f"{r['case']}/{r['engine']}": r.get("us_per_step")
                                    for r in bench["records"]}
    return out


def append(path: Path, line: dict) -> None:
    """Append one line; a line is written whole (one write call of a complete line)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(json.dumps(_clean(line), sort_keys=True) + "\n")


def read(path: Path) -> list[dict]:
    path = Path(path)
    if not path.exists():
        return []
    lines = []
    for raw in path.read_text(encoding="utf-8").splitlines():
        try:
            lines.append(json.loads(raw))
        except json.JSONDecodeError:
            continue  # a torn last line from a killed run is skipped, not trusted
    return lines
