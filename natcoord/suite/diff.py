"""What changed between two runs, and speed judged against the history.

:func:`compare_runs` reads two results folders (``summary.json``, and ``bench.json`` when
there is one) and judges the new one against the old: accuracy with the gate's rules, both
folders judged from their result files (a gated channel over tolerance, or an error grown
past 10x the old one and a tenth of the tolerance; a result file missing or altered in the
new folder is a regression, in the old one bad input), speed with
:mod:`natcoord.suite.speed` on the raw samples. Changes of engine version, case file and
engine settings between the runs are listed (``changes``); they fail nothing. A cell with too
few samples to be judged is said so; folders without ``bench.json`` say why speed is absent.
:func:`against_history` judges a benchmark against the history database instead (same case
file, same machine).

Exit codes (``natcoord compare``): 0 nothing significant, 1 an accuracy regression (it
takes precedence), 2 bad input, 4 a significant slowdown.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import EnvironmentFault
from . import bench, gate, history, speed
from .io import read_json, write_atomic
from .stored import carried, check_bench

SLOWER = 4


@dataclass
class Comparison:
    """Exit code, accuracy lines, speed judgements, and the rows of the table."""

    code: int = 0
    accuracy: list[str] = field(default_factory=list)
    speed: list[speed.SpeedChange] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)
    changes: list[str] = field(default_factory=list)
    speed_note: str = ""  # why speed was not compared at all ('' when it was)

    @property
    def slower(self) -> list[speed.SpeedChange]:
        return [s for s in self.speed if s.slower]

    @property
    def unjudged(self) -> list[speed.SpeedChange]:
        return [s for s in self.speed if not s.judged]

    def as_json(self) -> dict:
        return {"code": self.code, "accuracy": self.accuracy, "rows": self.rows,
                "changes": self.changes,
                "slower": [s.__dict__ for s in self.slower],
                "cannot_judge_speed": [s.__dict__ | {"line": s.line()}
                                       for s in self.unjudged],
                "speed": [s.__dict__ for s in self.speed], "speed_note": self.speed_note,
                "behaviour_changes": [s.__dict__ for s in self.speed if s.counters]}


def read_bench(folder: Path) -> dict | None:
    path = Path(folder) / "bench.json"
    if not path.exists():
        return None
    return check_bench(path, read_json(path))


def _worst(channels: dict | None) -> float | None:
    vals = [c["max_abs"] / c["tolerance"] for c in (channels or {}).values()
            if c.get("pass") is not None and c.get("tolerance") and c.get("max_abs")
            is not None]
    return max(vals) if vals else None


def changes(old: dict, new: dict) -> list[str]:
    """What differs between two runs of a cell beyond their results: the engine's version,
    the case file (its sha256) and the settings the engine ran with."""
    out = []
    if old.get("engine_version") != new.get("engine_version"):
        out.append(f"engine version {old.get('engine_version') or '?'} -> "
                   f"{new.get('engine_version') or '?'}")
    if old.get("case_hash") != new.get("case_hash"):
        out.append(f"case file changed (sha256 {str(old.get('case_hash'))[:12]} -> "
                   f"{str(new.get('case_hash'))[:12]})")
    a, b = old.get("settings") or {}, new.get("settings") or {}
    if isinstance(a, dict) and isinstance(b, dict):
        out += [f"setting {k}: {a.get(k, 'unset')!r} -> {b.get(k, 'unset')!r}"
                for k in sorted(set(a) | set(b), key=str) if a.get(k) != b.get(k)]
    return out


def compare_runs(base: Path, new: Path, *, cases: gate.CaseBook,
                 references: Path) -> Comparison:
    """Judge results folder ``new`` against ``base``, both from their result files with the
    case files of ``cases`` and the references in ``references``; raises ValueError on
    bad input. Two benchmark folders (``bench.json``, no summary) are compared for speed
    only, and say so."""
    if not any((Path(f) / "summary.json").exists() for f in (base, new)):
        bb, nb = read_bench(base), read_bench(new)
        if bb and nb:
            return _speed_only(bb, nb)
    b, n = gate.load_summary(base), gate.load_summary(new)
    out = Comparison()
    before = gate.judge(b, base, cases=cases, references=references)
    verdict = gate.judge(n, new, cases=cases, references=references, baseline=before.errors)
    if verdict.code in (gate.REGRESSION, gate.NOT_RUN):
        out.code = gate.REGRESSION
    elif verdict.code == gate.BAD_INPUT:
        out.code = gate.BAD_INPUT
    out.accuracy = verdict.lines + [f"{base} (base): {line}" for line in before.faults]
    if before.faults and out.code == 0:
        out.code = gate.BAD_INPUT
    old = {(r["case"], r["engine"]): r for r in b["records"]}
    changed = {}
    bb, nb = read_bench(base), read_bench(new)
    if bb and nb:
        out.speed = speed.compare_bench(bb, nb)
        changed = {(s.case, s.engine): s for s in out.speed}
    else:
        lack = " and ".join(str(f) for f, x in ((base, bb), (new, nb)) if not x)
        out.speed_note = (f"speed not compared: no bench.json in {lack} (`natcoord bench` "
                          "and `natcoord suite` write one, `natcoord run` does not)")
    for r in n["records"]:
        key = (r["case"], r["engine"])
        s = changed.get(key)
        if key in old:
            out.changes += [f"{r['case']}/{r['engine']}: {c}" for c in changes(old[key], r)]
        out.rows.append({"case": r["case"], "engine": r["engine"], "status": r["status"],
                         "verdict": verdict.outcome.get("/".join(key), r["status"]),
                         "worst_of_tolerance_base": _worst(before.channels.get(
                             "/".join(key))),
                         "worst_of_tolerance_new": _worst(verdict.channels.get(
                             "/".join(key))),
                         "speed_ratio": None if s is None else s.ratio,
                         "speed_p": None if s is None else s.p,
                         "speed_judged": None if s is None else s.judged,
                         "slower": bool(s and s.slower)})
    gone = sorted(set(old) - {(r["case"], r["engine"]) for r in n["records"]})
    for key in gone:  # listed, not judged: a run of fewer cases is a fair thing to compare
        out.rows.append({"case": key[0], "engine": key[1], "status": "absent",
                         "verdict": f"not in {new}",
                         "worst_of_tolerance_base": _worst(before.channels.get("/".join(key))),
                         "worst_of_tolerance_new": None, "speed_ratio": None,
                         "speed_p": None, "speed_judged": None, "slower": False})
    if out.code == 0 and out.slower:
        out.code = SLOWER
    return out


def _speed_only(bb: dict, nb: dict) -> Comparison:
    """Two benchmark folders: their cells' speed compared, accuracy not (a benchmark keeps
    timings, not result files)."""
    out = Comparison(speed=speed.compare_bench(bb, nb))
    out.accuracy = ["accuracy not compared: benchmark folders hold timings, not result "
                    "files (compare two `run` or `suite` folders for accuracy)"]
    judged = {(s.case, s.engine): s for s in out.speed}
    old = {(r.get("case"), r.get("engine")): r for r in bb.get("records", [])}
    for r in nb.get("records", []):
        key = (r.get("case"), r.get("engine"))
        s = judged.get(key)
        if key in old:
            out.changes += [f"{key[0]}/{key[1]}: {c}" for c in changes(old[key], r)]
        out.rows.append({"case": key[0], "engine": key[1], "status": r.get("status", "ok"),
                         "verdict": "", "worst_of_tolerance_base": None,
                         "worst_of_tolerance_new": None,
                         "speed_ratio": None if s is None else s.ratio,
                         "speed_p": None if s is None else s.p,
                         "speed_judged": None if s is None else s.judged,
                         "slower": bool(s and s.slower)})
    out.code = SLOWER if out.slower else 0
    return out


def against_history(bench: dict, db: Path, *, exclude_dir: str = "") -> list[speed.SpeedChange]:
    """Judge every cell of a benchmark that has samples against the history's samples of
    the same mechanism and engine settings (or case file) on the same machine (CPU times
    where both have them, relative to the reference work where both measured it); a cell
    without history is unjudged with ``n_base`` 0."""
    machine = bench.get("machine", {}).get("fingerprint", "")
    records = [r for r in bench.get("records", [])  # reused or run-timed: nothing to judge
               if r.get("samples_s") and not carried(r)]
    # a history from before bench keys stored the case file's sha256
    past = history.baselines(db, [(r["case"], r["engine"], tuple(
        k for k in (r.get("bench_key"), r.get("case_hash")) if k) or ("",)) for r in records],
        machine, exclude_dir=exclude_dir)
    out = []
    for r in records:
        b = past[r["case"], r["engine"]]
        out.append(speed.judge(r["case"], r["engine"], b.samples, r["samples_s"], b.counters,
                               r.get("counters"), base_cpu=b.cpu,
                               new_cpu=r.get("cpu_samples_s"), base_relative=b.relative,
                               new_relative=speed.relative(r)))
    return out


def speed_notes(changes: list[speed.SpeedChange], history_db: Path | None = None) -> list[str]:
    """What a verdict says about speed beyond slowdowns: each cell that has too few samples
    to be judged, (against a history) how many cells have none to be judged against, and
    how many were judged."""
    none = [s for s in changes if not s.judged and s.n_base == 0] if history_db else []
    lines = [s.line() for s in changes if not s.judged and s not in none]
    if none:
        lines.append(f"speed not judged for {len(none)} cell(s): no earlier benchmark of the "
                     f"same mechanism and settings on this machine in {history_db}")
    judged = [s for s in changes if s.judged]
    if judged:
        cpu = sum(s.clock == "cpu" for s in judged)
        rel = sum(s.relative for s in judged)
        lines.append(f"speed judged for {len(judged)} cell(s) ({cpu} on CPU time, {rel} "
                     f"relative to the reference work), {sum(s.slower for s in judged)} "
                     "significantly slower")
    return lines


def slower_rechecked(result: dict, jobs, repeats: int, timeout_s: float, db: Path,
                     say: Callable[[int], None] = lambda n: None) -> list[speed.SpeedChange]:
    """Every cell of a benchmark judged against its history (:func:`against_history`);
    each cell significantly slower is measured once more, with twice the samples (so they
    span twice the time: a shared machine drifts between fast and slow spells lasting
    seconds), its new samples replacing the first ones in ``result``, and judged again
    before it is reported. ``say(n)`` is told how many are re-measured."""
    first = against_history(result, db)
    suspects = [s for s in first if s.slower]
    if not suspects:
        return first
    say(len(suspects))
    by_name = {j.case.name: j for j in jobs}
    records = {(r["case"], r["engine"]): r for r in result["records"]}
    with tempfile.TemporaryDirectory(prefix="natcoord-recheck-") as tmp:
        for s in suspects:
            records[(s.case, s.engine)].update(
                bench.measure(by_name[s.case], s.engine, 2 * repeats, timeout_s, Path(tmp)))
    return against_history(result, db)


def write_ci_summary(folder: Path, summary: dict, code: int, slower: list,
                     report: Path, found: list[str] | None = None) -> str:
    """summary.md in the results folder; returns its text (for
    :func:`append_step_summary`, once the results are published)."""
    text = markdown(summary, code, slower, str(report), found)
    write_atomic(Path(folder) / "summary.md", text)
    return text


def append_step_summary(text: str) -> None:
    """Append ``text`` to $GITHUB_STEP_SUMMARY when it is set; a path that cannot be
    written raises EnvironmentFault naming it."""
    path = os.environ.get("GITHUB_STEP_SUMMARY")
    if not path:
        return
    try:
        with open(path, "a", encoding="utf-8") as f:
            f.write(text)
    except OSError as e:
        raise EnvironmentFault(f"GITHUB_STEP_SUMMARY={path}: cannot be written "
                               f"({e.strerror or e})") from None


HEADINGS = {0: "passed", 1: "accuracy regression", 2: "bad input",
            3: "incomplete: a required cell did not run", 4: "significant slowdown"}


def markdown(summary: dict, code: int, slower: list[speed.SpeedChange], report: str,
             found: list[str] | None = None) -> str:
    """A short CI summary: the gate's verdict, outcome counts, failing cells, what the gate
    found (``found``, its lines), slowdowns, where the report is."""
    counts: dict[str, int] = {}
    for r in summary["records"]:
        key = r["verdict"] if r["status"] == "ok" else r["status"]
        counts[key] = counts.get(key, 0) + 1
    if code == 3 and not any(r["status"] == "ok" for r in summary["records"]):
        word = "nothing ran"
    else:
        word = HEADINGS.get(code, str(code))
    quick = summary.get("mode") == "quick"  # `suite --quick`: a first look, no nightly
    lines = [f"## natcoord suite{' --quick' if quick else ''}: {word} (exit {code})", ""]
    if quick:
        lines += ["Quick: a first look, not a nightly (a few engines, no sweeps, no speed "
                  "gate, not in the history).", ""]
    lines += ["| outcome | cells |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in sorted(counts.items())]
    bad = [r for r in summary["records"] if r.get("verdict") == "fail"
           or r["status"] == "failed"]
    if bad:
        lines += ["", "### Failing cells", ""]
        lines += [f"- `{r['case']}/{r['engine']}`: {r.get('reason') or r.get('verdict_reason')}"
                  for r in bad]
    shown = set(lines)
    found = [f"- {x}" for x in found or [] if f"- {x}" not in shown]
    if found:
        lines += ["", "### What the gate found", ""] + found[:50]
        if len(found) > 50:
            lines.append(f"- ... and {len(found) - 50} more (see the report)")
    if slower:
        lines += ["", "### Significant slowdowns", ""] + [f"- {s.line()}" for s in slower]
    lines += ["", f"Report: `{report}`", ""]
    return "\n".join(lines)
