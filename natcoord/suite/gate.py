"""The regression gate: judge a results folder from its evidence, print what regressed,
return an exit code.

Every cell that ran is judged again from its result files (:mod:`natcoord.suite.evidence`):
each file checked against the sha256 the run stored, the errors recomputed against the
stored reference with the tolerances of the case file as it is now. The summary only says
which cells there are; the numbers it holds are never trusted.

Exit codes: 0 all hold; 1 an accuracy regression (a gated channel over its tolerance or
non-finite, an error grown past the stored baseline, a result file missing, altered since
the run or unreadable, a result file whose cell has no record in the summary, a file the
folder's marker lists gone); 2 bad input (no or malformed summary or baseline, a damaged
marker, a case file or reference missing or damaged, a case without tolerances for an
engine that ran); 3 nothing
ran, or a required engine failed or was skipped, or a cell the baseline holds did not run
(a record that says ``unsupported`` or ``skipped`` cannot hide a cell that passed before).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..case.casefile import NAME_PATTERN, load_case
from ..case.mechanism import Case
from ..engines import engine_names
from ..errors import CaseError, StoredFileError
from . import evidence
from .io import locked, read_json, write_json
from .stored import check_summary

OK, REGRESSION, BAD_INPUT, NOT_RUN = 0, 1, 2, 3
CANNOT_WRITE = 5  # the baseline could not be written (a read-only folder, a full disk)


@dataclass
class Verdict:
    """Exit code and what caused it; ``notes`` are worth knowing but fail nothing.
    ``channels``: per cell judged from its files, its channels as
    :func:`natcoord.suite.compare.channel_errors` gives them; ``outcome``: per cell that
    ran, ``pass`` (judged from its files, within every rule), ``fail``, ``bad evidence``
    or ``cannot judge``; ``faults``: the lines about files that could not be trusted;
    ``said``: per cell, what the gate said of it (its lines without the cell's name) but
    for what its channels show (a channel over its tolerance)."""

    code: int
    lines: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    channels: dict[str, dict] = field(default_factory=dict)
    outcome: dict[str, str] = field(default_factory=dict)
    faults: list[str] = field(default_factory=list)
    said: dict[str, list[str]] = field(default_factory=dict)

    def worse(self, code: int, line: str, fault: bool = False, cell: str | None = None,
              shown: bool = False) -> None:
        """Raise the exit code to ``code`` for ``line``, about ``cell`` ("case/engine";
        None: the folder as a whole); ``shown``: the cell's channels say it already."""
        self.code = max(self.code, code)
        if cell is not None and not shown:
            self.said.setdefault(cell, []).append(line)
        line = line if cell is None else f"{cell}: {line}"
        self.lines.append(line)
        if fault:
            self.faults.append(line)

    @property
    def folder_faults(self) -> list[str]:
        """The faults about the folder as a whole (a result file without its record, a
        file natcoord wrote that is gone ...), not about one cell that ran."""
        mine = {f"{k}: {line}" for k, lines in self.said.items() for line in lines}
        return [line for line in self.faults if line not in mine]

    @property
    def passed(self) -> list[str]:
        """The cells judged from their files and within every rule: the only ones a
        baseline update stores."""
        return [k for k, o in self.outcome.items() if o == "pass"]

    @property
    def errors(self) -> dict[str, dict[str, float]]:
        """Per cell judged from its files, each channel's max error (a baseline)."""
        return {k: {n: c["max_abs"] for n, c in ch.items() if c["max_abs"] is not None}
                for k, ch in self.channels.items()}


class CaseBook:
    """The case files a gate judges with, by case name: ``directory/<name>.toml`` (or one
    of the cases given already loaded), each read once."""

    def __init__(self, directory: Path, loaded: Mapping[str, Case] | None = None):
        self.directory = Path(directory)
        self.cases: dict[str, Case] = dict(loaded or {})

    def get(self, name: str) -> Case:
        if name not in self.cases:
            path = self.directory / f"{name}.toml"
            if not NAME_PATTERN.fullmatch(name):
                raise CaseError(self.directory, "", f"{name[:64]!r} is not a case name")
            if not path.is_file():
                raise CaseError(path, "", f"no case file for case {name!r} (give the "
                                "folder of case files with --cases-dir)")
            self.cases[name] = load_case(path)
        return self.cases[name]


def _fmt(x: float | None, unit: str = "") -> str:
    return "n/a" if x is None else f"{x:.3g}{' ' + unit if unit else ''}"


def load_summary(results: Path) -> dict:
    """Read and check ``results/summary.json`` (every field a reader uses, with its type:
    :func:`natcoord.suite.stored.check_summary`); raises ValueError (StoredFileError)
    naming the file, the field and the problem."""
    path = Path(results) / "summary.json"
    if not path.exists() and not path.is_symlink():
        raise StoredFileError(f"{path}: no summary (run `natcoord run` first; an interrupted "
                              "run leaves none on purpose)")
    return check_summary(path, read_json(path))


def judge(summary: dict, results: Path, *, cases: CaseBook, references: Path,
          required: set[str] | None = None, baseline: dict | None = None,
          baseline_factor: float = 10.0, floor: float = 1e-12, staged: bool = False) -> Verdict:
    """Apply the gate's rules to the cells a summary lists, each judged from its result
    files in ``results`` (see :func:`natcoord.suite.evidence.judge_cell`) with the case
    files of ``cases`` and the references in ``references``; the worst outcome wins
    (3 > 2 > 1 > 0). ``staged``: ``results`` is the caller's own staging folder (the
    suite judging what it is about to publish), else a folder marked staging is refused."""
    v = Verdict(OK)
    records = summary["records"]
    try:  # every result file in the folder has its record, every file natcoord wrote is there
        for line in evidence.unrecorded(Path(results), records, staged):
            v.worse(REGRESSION, line, fault=True)
    except StoredFileError as e:
        v.worse(BAD_INPUT, str(e), fault=True)
    if not any(r["status"] == "ok" for r in records):
        v.worse(NOT_RUN, "nothing ran: no case x engine finished with status ok")
        return v
    have = {(r["case"], r["engine"]) for r in records}
    engines = set(summary.get("engines", ())) | (required or set())
    for case in summary.get("cases", ()):  # every cell asked for must have its record
        for engine in sorted(engines):
            if (case, engine) not in have:
                v.worse(NOT_RUN, "no record (required, not run)", cell=f"{case}/{engine}")
    for r in records:
        key = f"{r['case']}/{r['engine']}"
        if r["status"] in ("failed", "skipped") and (required is None or r["engine"] in required):
            v.worse(NOT_RUN, f"required engine {r['status']}: {r.get('reason') or ''}",
                    cell=key)
        elif r["status"] == "ok":
            _judge_cell(v, r, key, Path(results), cases, Path(references),
                        (baseline or {}).get(key) or {}, baseline_factor, floor)
        elif (baseline or {}).get(key):
            v.worse(NOT_RUN, f"{r['status']} ({(r.get('reason') or '')[:200]}), but the "
                    "baseline holds its errors from a judged run: a cell that passed "
                    "before must run and be judged again", cell=key)
    return v


def _judge_cell(v: Verdict, r: dict, key: str, results: Path, cases: CaseBook,
                references: Path, base: dict, baseline_factor: float, floor: float) -> None:
    """One cell that ran, judged from its files, against its tolerances and its baseline."""
    v.outcome[key] = "cannot judge"
    if r["engine"] not in engine_names():
        v.worse(BAD_INPUT, f"{r['engine'][:40]!r} is not an engine", fault=True, cell=key)
        return
    try:
        case = cases.get(r["case"])
        judged = evidence.judge_cell(case, r["engine"], results, references,
                                     r.get("files"))
    except evidence.BadEvidence as e:
        v.outcome[key] = "bad evidence"
        v.worse(REGRESSION, str(e), fault=True, cell=key)
        return
    except (evidence.BadReference, CaseError) as e:
        v.worse(BAD_INPUT, f"cannot judge: {e}", fault=True, cell=key)
        return
    if r.get("case_hash") and r["case_hash"] != case.digest:
        v.notes.append(f"{key}: {case.file} changed since the run; judged with its "
                       "tolerances as they are now")
    channels = v.channels[key] = judged["channels"]
    if judged["verdict"] == "not-gated":
        v.worse(BAD_INPUT, f"cannot judge: {judged['verdict_reason']} ({case.file})",
                cell=key)
        return
    held = judged["verdict"] == "pass"
    for name, c in channels.items():
        unit = c.get("unit", "")
        if c["pass"] is False:
            held = False
            if c["max_abs"] is None or c["max_abs"] == float("inf"):
                v.worse(REGRESSION, f"{name}: {c['note'] or 'no value'}", cell=key, shown=True)
                continue
            ratio = c["max_abs"] / c["tolerance"] if c["tolerance"] else float("inf")
            v.worse(REGRESSION, f"{name} max error {_fmt(c['max_abs'], unit)} > "
                    f"tolerance {_fmt(c['tolerance'], unit)} ({ratio:.3g}x)", cell=key,
                    shown=True)
        err, tol, was = c["max_abs"], c["tolerance"], base.get(name)
        # growth below a tenth of the tolerance is platform noise, not a regression
        if c["pass"] is not None and was is not None and err is not None and \
                err > max(baseline_factor * was, floor, 0.1 * tol):
            held = False
            v.worse(REGRESSION, f"{name} error {_fmt(err, unit)} grew "
                    f"{err / max(was, floor):.3g}x over the baseline {_fmt(was, unit)} "
                    f"(limit {baseline_factor:g}x)", cell=key)
    v.outcome[key] = "pass" if held else "fail"


def check_bench_file(v: Verdict, results: Path, summary: dict) -> bool:
    """Whether ``results/bench.json`` may be read for the verdict ``v``: checked against
    the sha256 the suite stored (:func:`natcoord.suite.evidence.bench_checked`); a fault
    (exit 1) when it cannot be trusted, a note when the summary does not list it."""
    try:
        note = evidence.bench_checked(results, summary)
    except evidence.BadEvidence as e:
        v.worse(REGRESSION, str(e), fault=True)
        return False
    v.notes += [note] if note else []
    return True


def update_baseline(verdict: Verdict, path: Path, generated: str | None = None) -> list[str]:
    """Store the errors of the cells this gate judged from their files and passed over the
    stored baseline, under a lock (two updates at once lose no cell); every other cell
    keeps its entry (a subset run never shrinks the baseline). Returns the cells stored."""
    cells = {k: verdict.errors[k] for k in sorted(verdict.passed)}
    with locked(path):
        errors = (load_baseline(path) or {}) | cells
        write_json(path, {"generated": generated, "errors": errors})
    return list(cells)


def load_baseline(path: Path) -> dict | None:
    """The stored baseline's errors ({cell: {channel: error}}), None when there is none;
    StoredFileError (a ValueError) naming the baseline file and what is wrong in it."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return None
    data = read_json(path)  # StoredFileError: unreadable, not JSON
    errors = data.get("errors") if isinstance(data, dict) else None
    if not isinstance(errors, dict):
        raise StoredFileError(f"{path}: malformed baseline: errors: missing or not a table")
    for cell, channels in errors.items():
        if not isinstance(channels, dict):
            raise StoredFileError(f"{path}: malformed baseline: errors.{cell[:80]}: not a "
                                  "table of channel errors")
        for name, x in channels.items():
            if x is not None and (isinstance(x, bool) or not isinstance(x, (int, float))
                                  or not math.isfinite(x) or x < 0):
                raise StoredFileError(f"{path}: malformed baseline: errors.{cell[:80]}."
                                      f"{name[:40]}: not an error (a number >= 0)")
    return errors
