"""The ``natcoord`` command line: cases, run, report, gate, bench, suite, reference update.

Every command works from any directory: cases, references and reports are found in the
project folder (:mod:`natcoord.case.project`) unless an option names them. Results go to a fresh
folder per command (``reports/runs/<time>-<command>``) and are published whole when the
command completes; ``reports/latest`` points at the last complete ``run`` or ``suite``
written there (until one completes, at the one before), which ``report`` and ``gate`` read
by default. Ctrl-C ends every engine process and exits 130,
SIGTERM (a cancelled CI job) 143; bad input (a case file, a stored file) exits 2 with one
line naming the problem, a fault of the environment (a full disk, a read-only folder) 5.
"""

from __future__ import annotations

import errno
import math
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from .case.casefile import (
    MAX_DURATION_S,
    MAX_NAME,
    MAX_SAMPLES,
    MAX_TIMEOUT_S,
    MIN_TIMEOUT_S,
    NAME_PATTERN,
    check_file_name,
    load_case,
)
from .case.generate import OUTPUT_DT as IMPORT_DT
from .case.project import resolve
from .engines import discover
from .errors import CaseError, EnvironmentFault, NatcoordError, StoredFileError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None,  # help texts are plain: [default: ...] stays visible
                  help="Natural-coordinate multibody solver and cross-engine validation suite.")
reference_app = typer.Typer(no_args_is_help=True, rich_markup_mode=None,
                            help="Stored reference solutions.")
app.add_typer(reference_app, name="reference")
# piped (a CI log), rich draws tables 80 columns wide and cuts the figures to "0.00…":
# as wide as they need there, unless COLUMNS says otherwise
PIPED_WIDTH = None if sys.stdout.isatty() or os.environ.get("COLUMNS") else 240
out = Console(soft_wrap=True, width=PIPED_WIDTH)
err = Console(stderr=True, soft_wrap=True, width=PIPED_WIDTH)

DEFAULT_TIMEOUT_S = 600.0
NIGHT_BUDGET_S = 60.0  # `suite --bench-budget`: see natcoord.suite.policy
RUN_FAILED = 3  # `run`: a case x engine failed (crashed, timed out, diverged)
ENVIRONMENT = 5  # a full disk, a read-only folder, an unwritable step summary
# Upper bounds of the numeric options: past these no value means anything a user could want,
# and an infinite or huge one overflowed a wait, an SQLite integer or the memory of threads.
MAX_JOBS = 1024  # accuracy runs at once (never more than there are runs)
MAX_REPEATS = 1000  # timing samples per cell
MAX_BUDGET_S = 7 * 24 * 3600.0  # a night's bench budget: a week of engine process time
MAX_MARGIN = 1000.0  # proposed tolerance over the measured error
MAX_LAST = 100_000  # runs read from the history (a run a night for 270 years)
def _number(lo: float, hi: float) -> Callable[[str], float]:
    """A float option's parser: a finite number in [lo, hi], else the option's error
    naming the value (click's range check lets nan through, and calls inf out of range)."""
    def parse(text):
        if text is None or isinstance(text, float):
            return text  # the default, already a number
        try:
            value = float(text)
        except (TypeError, ValueError):
            raise typer.BadParameter(f"{text!r} is not a number") from None
        if not math.isfinite(value):
            raise typer.BadParameter(f"{text!r} is not a finite number")
        if not lo <= value <= hi:
            raise typer.BadParameter(f"{text} is outside [{lo:g}, {hi:g}]")
        return value
    return parse


CasesDir = Annotated[Path | None, typer.Option(
    "--cases-dir", help="Folder of case files [default: <project>/cases].", show_default=False)]
RefDir = Annotated[Path | None, typer.Option(
    "--references", help="Folder of reference solutions [default: <project>/references].",
    show_default=False)]
OutDir = Annotated[Path | None, typer.Option(
    "--out", help="Results folder [default: a fresh <project>/reports/runs/<time>-<command>].",
    show_default=False)]
ResultsDir = Annotated[Path | None, typer.Option(
    "--results", help="Results folder [default: <project>/reports/latest, the last complete "
    "run or suite].",
    show_default=False)]
Timeout = Annotated[float, typer.Option(
    parser=_number(MIN_TIMEOUT_S, MAX_TIMEOUT_S), metavar="SECONDS",
    help=f"Seconds per engine run, {MIN_TIMEOUT_S:g} to {MAX_TIMEOUT_S:g} (a case file's own "
    "`timeout`, when stricter, wins).")]
Engines = Annotated[str | None, typer.Option(help="Comma-separated engines [default: all].")]
Jobs = Annotated[int | None, typer.Option(
    "--jobs", min=1, max=MAX_JOBS,
    help="Accuracy runs at once [default: every core]; timing stays serial.",
    show_default=False)]
Scheduler = Annotated[str | None, typer.Option(
    help="Send the accuracy runs to a Dask cluster: tcp://HOST:PORT.")]
HistoryDb = Annotated[Path | None, typer.Option(
    "--history", help="History database [default: <project>/reports/history.db].",
    show_default=False)]
CaseArgs = Annotated[list[str] | None, typer.Argument(
    help="Case names (or paths to case files); default: every case.", show_default=False)]


class Stopped(BaseException):
    """Ctrl-C (SIGINT) or SIGTERM received: unwinds the command (every worker is killed on
    the way) to :func:`main`, which exits 128 + the signal number. Not a KeyboardInterrupt,
    which the command-line library would turn into exit 1."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _code(e: Exception) -> int:
    """The exit code of a refused command: 5 for a fault of the environment, else 2."""
    return ENVIRONMENT if isinstance(e, EnvironmentFault) else 2


def _print_json(data) -> None:
    """``data`` on standard output as strict JSON (NaN and inf as null)."""
    from .suite.io import json_text

    print(json_text(data))


def _fail(message: str, code: int = 2):
    err.print(f"[bold red]error:[/] {escape(message)}", highlight=False)
    raise typer.Exit(code)


def _cases(names: list[str] | None, cases_dir: Path | None):
    """Load (exit 2 naming file, field and reason) and assemble once the selected cases:
    a list of :class:`natcoord.suite.worker.Job`."""
    try:
        cases_dir = resolve(cases_dir, "cases")
        if not names:
            files = sorted(Path(cases_dir).glob("*.toml"))
            if not files:
                _fail(f"{cases_dir}: no case files (*.toml)")
        else:
            files = []
            for n in names:
                p = Path(n) if n.endswith(".toml") else Path(cases_dir) / f"{n}.toml"
                check_file_name(p)
                if not p.exists():
                    known = ", ".join(sorted(f.stem for f in Path(cases_dir).glob("*.toml")))
                    _fail(f"unknown case {n!r} (looked in {cases_dir}); cases are: "
                          f"{known or 'none'}")
                files.append(p)
            by_name = {}  # a case's results go to results/<its name>: one file per name
            for p in files:
                first = by_name.setdefault(p.stem, p)
                if first is not p and not first.samefile(p):
                    _fail(f"two case files named {p.stem}: {first}, {p}")
            files = list(by_name.values())  # a file given twice runs once
        cases = [load_case(f) for f in files]
    except NatcoordError as e:
        _fail(str(e))
    return [_prepared(case) for case in cases]


def _check_references(jobs, references: Path, full: bool = False) -> None:
    """Read the stored reference (CSV and provenance) of every case (prepared jobs or
    names) before using them: a damaged one is bad input (exit 2 naming the file), not a
    failed cell or a silent gap later. ``full`` (bench, propose: they compute errors
    against it): also as the gate reads it, every channel at the case's sample times, finite
    (a run goes ahead with a stale reference: the gate then says it cannot judge)."""
    from .suite.evidence import read_reference
    from .suite.references import load_provenance, load_reference

    try:
        for item in (getattr(j, "case", j) for j in jobs):
            name = getattr(item, "name", item)
            if not isinstance(name, str):
                continue  # a malformed record: the summary check's job
            if not NAME_PATTERN.fullmatch(name):  # its file would be past the system's limit
                _fail(f"{name[:MAX_NAME]!r}{'...' if len(name) > MAX_NAME else ''} is not a "
                      f"case name (at most {MAX_NAME} letters, digits and _ . + -)")
            table = load_reference(name, references)  # raises for an unreadable one
            if full and table is not None and not isinstance(item, str):
                read_reference(item, references)  # as the gate reads it: every channel, at
                # the case's times, finite (one row stretched over 201 made up errors)
            load_provenance(name, references)
    except NatcoordError as e:
        _fail(str(e))


def _prepared(case):
    """Assemble a case once (the Job every run of it starts from). A mechanism that does
    not assemble is bad input too (exit 2), caught before running."""
    from .suite.runner import prepare

    job = prepare(case)
    if job.init is None:
        _fail(str(CaseError(case.file, "initial", job.assembly_error)))
    return job


def _known_engines() -> tuple[str, ...]:
    """Every engine that loads, in the registry's order; a plug-in that does not load is
    named on stderr (once per command) and left out."""
    reg = discover()
    if not getattr(_known_engines, "warned", False):
        _known_engines.warned = True
        for p in reg.problems:
            err.print(f"[yellow]warning:[/] {escape(p.line())}", highlight=False)
    return reg.names


def _engines(spec: str | None, option: str = "--engines") -> list[str]:
    """The engines ``spec`` names (comma-separated; every engine when None); an empty or
    unknown name exits 2 naming ``option``, the option or argument it was given as."""
    known = _known_engines()
    if spec is None:
        return list(known)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        _fail(f"{option}: no engine named in {spec!r}; engines are {', '.join(known)}")
    bad = [n for n in names if n not in known]
    if bad:
        _fail(f"{option}: unknown engine {bad[0]!r}; engines are {', '.join(known)}")
    return list(dict.fromkeys(names))


def _results_dir(given: Path | None) -> Path:
    """The results folder a reading command uses; the default (reports/latest) is named on
    stderr with where it points and how to name another."""
    if given is not None:
        return given
    latest = resolve(None, "reports/latest")
    where = f" -> {latest.resolve()}" if latest.is_symlink() else ""
    err.print(f"reading {escape(str(latest))}{escape(where)} (the last complete run or suite; "
              "name another with --results)", highlight=False, style="dim")
    return latest


def _point_latest(target: Path) -> None:
    """Point reports/latest at ``target``, a results folder just published (until then it
    keeps pointing at the previous complete one, which gate and report read meanwhile)."""
    from .suite.outdir import point_latest

    latest = resolve(None, "reports/latest")
    if not point_latest(latest, target):
        err.print(f"warning: {escape(str(latest))} is not a link natcoord made; left as it "
                  "is (not pointed at these results)", highlight=False)


def _out_dir(given: Path | None, kind: str) -> Path:
    from .suite.outdir import stamped

    return given if given is not None else stamped(resolve(None, "reports/runs"), kind)


def _progress_printer(total: int, where: str = "here", left=None):
    """A line per finished run with the time left (from the runs so far, or ``left(key)``:
    the whole suite's, see :mod:`natcoord.suite.eta`); during a silent stretch of more than
    30 s a line says that runs are still going (a first numba compile of natcoord's kernels
    takes about 30 s on a new machine), with the suite's time left once a piece has
    finished (``left.peek()``, None before)."""
    import threading
    import time

    start, done, last = time.monotonic(), [0], [time.monotonic()]
    style = {"ok": "green", "failed": "red", "unsupported": "yellow", "skipped": "dim"}
    verdict_style = {"pass": "green", "fail": "bold red"}
    stop = threading.Event()

    def heartbeat():
        while not stop.wait(5.0):
            if time.monotonic() - last[0] > 30.0 and done[0] < total:
                peek = getattr(left, "peek", lambda: None)()
                out.print(Text(f"      ... {total - done[0]} run(s) still going ({where}), "
                               f"{time.monotonic() - start:.0f} s so far"
                               + ("" if peek is None else f", ~{peek:.0f} s left in the suite"),
                               style="dim"))
                last[0] = time.monotonic()

    threading.Thread(target=heartbeat, daemon=True).start()

    def show(key: str, rec: dict):
        done[0] += 1
        last[0] = time.monotonic()
        if done[0] >= total:
            stop.set()
        elapsed = last[0] - start
        if left is not None:
            when = f"~{left(key, rec):4.0f} s left in the suite"
        elif done[0] < total:
            when = f"~{elapsed / done[0] * (total - done[0]):4.0f} s left"
        else:
            when = f"{elapsed:5.0f} s total"
        status, verdict = rec.get("status", "?"), rec.get("verdict", "")
        cost = rec.get("us_per_step")
        cost = f"{cost:9.2f} us/step " if isinstance(cost, (int, float)) else " " * 17
        reason = rec.get("reason") or rec.get("verdict_reason") or ""
        out.print(Text.assemble(f"[{done[0]:>3}/{total}] {key:<30} ",
                                (f"{status:<12}", style.get(status, "")),
                                (f"{verdict:<10}", verdict_style.get(verdict, "")),
                                cost, (f"{when}  ", "dim"), (reason[:90], "dim")))
    return show


def _where(jobs: int | None, scheduler: str | None) -> tuple[int, str]:
    import os

    n = jobs or os.cpu_count() or 1
    return n, (f"on the Dask cluster {scheduler}" if scheduler else
               f"{n} at a time here" if n > 1 else "one at a time here")


def counts_line(records: list[dict]) -> str:
    """What a run's records say, counted honestly: passes, tolerance failures, engine
    failures, cells with nothing to judge."""
    n = len(records)
    c = {k: 0 for k in ("pass", "fail", "failed", "unsupported", "skipped", "not judged")}
    for r in records:
        if r["status"] != "ok":
            c[r["status"] if r["status"] in c else "failed"] += 1
        elif r.get("verdict") in ("pass", "fail"):
            c[r["verdict"]] += 1
        else:
            c["not judged"] += 1
    parts = [f"{c['pass']} within tolerance", f"{c['fail']} over tolerance",
             f"{c['failed']} failed"]
    parts += [f"{c[k]} {k}" for k in ("unsupported", "skipped", "not judged") if c[k]]
    return f"{n} run(s): " + ", ".join(parts)


@app.command("cases")
def cases_cmd(cases_dir: CasesDir = None,
              as_json: Annotated[bool, typer.Option(
                  "--json", help="Print JSON: cases (per case its name, description, file, "
                                 "per engine null (it can run it) or the reason it cannot, "
                                 "absent_engines: blocks of engines not installed here, "
                                 "and assembly: what assembly changed of the file's "
                                 "poses, or null), "
                                 "engines (per engine its package, adapter module, "
                                 "built-in or plug-in, capabilities and settings schema) and "
                                 "engine_problems (plug-ins that do not load).")] = False):
    """List the cases with a one-line description, the engines that can run each and, for
    the others, why not (the case file's reason, else the engine's declared capabilities)."""
    from .engines import adapter
    from .suite.runner import assessed

    jobs = _cases(None, cases_dir)
    names = _known_engines()
    why = assessed([j.case for j in jobs], names)  # a plug-in's rules in its own process
    if as_json:
        from .engines.schema import describe

        reg = discover()
        _print_json({
            "cases": [{"name": c.name, "description": c.description, "file": str(c.file),
                       "engines": {e: (why[c.name, e] or None) for e in names},
                       "absent_engines": list(c.absent_engines),
                       "assembly": job.assembly_note or None}
                      for job in jobs for c in [job.case]],
            "engines": {e: {"package": adapter(e).PACKAGE, "module": reg.modules[e],
                            "origin": "built-in" if reg.builtin(e) else "plug-in",
                            "capabilities": adapter(e).CAPABILITIES.summary(),
                            "settings": describe(adapter(e).SETTINGS)} for e in names},
            "engine_problems": [{"name": p.name, "entry_point": p.value, "error": p.error}
                                for p in reg.problems]})
        return
    table = Table(title=f"cases in {escape(str(resolve(cases_dir, 'cases')))}")
    table.add_column("case")
    table.add_column("description")
    table.add_column("engines")
    table.add_column("cannot run it")
    for c in (job.case for job in jobs):
        can = [e for e in names if not why[c.name, e]]
        cannot = [f"{e}: {_short(why[c.name, e])}" for e in names if why[c.name, e]]
        table.add_row(escape(c.name), escape(c.description), " ".join(can),
                      escape("\n".join(cannot)))
    out.print(table)
    for job in jobs:
        c = job.case
        if job.assembly_note:
            err.print(escape(f"note: {c.file}: {job.assembly_note}"), highlight=False)
        for e in c.absent_engines:
            err.print(escape(f"note: {c.file}: [engines.{e}]: no engine {e!r} is installed "
                             "here; its block is not used"), highlight=False)


def _short(reason: str, width: int = 100) -> str:
    """A reason cut to ``width`` characters (``cases --json`` has it whole)."""
    return reason if len(reason) <= width else reason[:width - 3].rstrip() + "..."


@app.command("run")
def run_cmd(cases: CaseArgs = None, engines: Engines = None, out_dir: OutDir = None,
            timeout: Timeout = DEFAULT_TIMEOUT_S, jobs: Jobs = None, scheduler: Scheduler = None,
            cases_dir: CasesDir = None, references: RefDir = None):
    """Run cases in engines; write results/<case>/<engine>.csv and summary.json."""
    from .suite.outdir import publishing
    from .suite.runner import run_suite

    names = _engines(engines)
    target = _out_dir(out_dir, "run")
    with publishing(target, "run") as staging:  # a refused input publishes nothing
        selected = _cases(cases, cases_dir)
        references = resolve(references, "references")
        _check_references(selected, references)
        total = len(selected) * len(names)
        n, where = _where(jobs, scheduler)
        out.print(f"running {len(selected)} case(s) x {len(names)} engine(s), {where} -> "
                  f"{target}")
        summary = run_suite(selected, names, staging, references=references,
                            timeout_s=timeout, progress=_progress_printer(total, where),
                            jobs=n, scheduler=scheduler)
    out.print(f"{counts_line(summary['records'])}; summary: {target / 'summary.json'}")
    if out_dir is None:
        _point_latest(target)
        out.print("judge it with: natcoord gate (it reads reports/latest, this run)")
    else:
        out.print(f"judge it with: natcoord gate --results {target}")
    if any(r["status"] == "failed" for r in summary["records"]):
        err.print(f"[bold red]some runs failed[/] (exit {RUN_FAILED}): see the reasons above")
        raise typer.Exit(RUN_FAILED)


@app.command("report")
def report_cmd(results: ResultsDir = None, references: RefDir = None,
               history: HistoryDb = None, cases_dir: CasesDir = None):
    """Write RESULTS/index.html from a results folder (trends from the history database),
    every cell's verdict judged from its result files as the gate judges them."""
    from .report.html import write_report
    from .suite import diff, gate

    results = _results_dir(results)
    if not (results / "summary.json").exists():
        _fail(f"{results}: no summary.json; run `natcoord run` or `natcoord suite` first")
    from .suite import history as hist

    history = resolve(history, "reports/history.db")
    references = resolve(references, "references")
    try:  # what the report reads, checked first: a damaged file is named, exit 2
        summary = gate.load_summary(results)
        diff.read_bench(results)
        hist.check(history)
    except ValueError as e:
        _fail(str(e))
    _check_references(sorted({r["case"] for r in summary["records"]}), references)
    verdict = gate.judge(summary, results, cases=gate.CaseBook(resolve(cases_dir, "cases")),
                         references=references)
    gate.check_bench_file(verdict, results, summary)  # the page's speed figures
    path = write_report(results, references, history, verdict)
    out.print(f"report: {path.resolve()}")


READ_TRIES = 3  # judgings of a folder that a command publishing into it replaced meanwhile


def _read_whole(folders, judge):
    """``judge()`` over results folders that a command may publish into meanwhile (a folder
    is replaced whole, by rename: files read before and after would mix two runs, and their
    hashes fail as altered): judged again, up to READ_TRIES times, while a folder changed
    under it (its device and inode, through any link such as reports/latest)."""
    def which():
        out = []
        for f in folders:
            try:
                st = os.stat(f)
                out.append((st.st_dev, st.st_ino))
            except OSError:
                out.append(None)
        return out
    for _ in range(READ_TRIES - 1):
        before = which()
        result = judge()
        if which() == before:
            return result
        err.print("note: a results folder was replaced while it was read (a command "
                  "published into it): judging it again", highlight=False)
    return judge()


@app.command("gate")
def gate_cmd(results: ResultsDir = None,
             require: Annotated[str | None, typer.Option(
                 help="Engines that must have run every case (default: those asked for).")
             ] = None,
             baseline: Annotated[Path | None, typer.Option(
                 help="Stored baseline errors [default: <project>/references/baseline.json].",
                 show_default=False)] = None,
             update_baseline: Annotated[bool, typer.Option(
                 help="Store this run's errors in the baseline, cell by cell (after it "
                      "passes).")] = False,
             history: HistoryDb = None, cases_dir: CasesDir = None,
             references: RefDir = None):
    """Judge a results folder from its result files (checked against the hashes the run
    stored) with the case files' tolerances, the stored references and baseline, and its
    benchmark (when the folder has one) with the history of the same cases on this machine.

    Exit 0 when all hold, 1 on an accuracy regression (or a result file missing, altered or
    unreadable), 2 on bad input, 3 when nothing ran, or a required engine or case has no
    record or failed, 4 on a significant slowdown (accuracy regressions take precedence),
    5 when the baseline cannot be written.
    """
    from .suite import diff, gate

    results = _results_dir(results)
    baseline = resolve(baseline, "references/baseline.json")
    required = set(_engines(require, "--require")) if require is not None else None

    def judge():
        try:
            summary = gate.load_summary(results)
            base = gate.load_baseline(baseline)
        except ValueError as e:
            _fail(str(e))
        return summary, base, gate.judge(summary, results, cases=gate.CaseBook(resolve(
            cases_dir, "cases")), references=resolve(references, "references"),
            required=required, baseline=base)
    summary, base, verdict = _read_whole([results], judge)
    history = resolve(history, "reports/history.db")
    bench_result = None
    if gate.check_bench_file(verdict, results, summary):  # the speed verdict rests on it
        try:
            bench_result = diff.read_bench(results)
        except StoredFileError as e:
            _fail(str(e))
    if bench_result is not None and not bench_result.get("records"):
        verdict.notes.append(f"{results / 'bench.json'}: no benchmark records: speed not "
                             "judged")
    try:
        speed = diff.against_history(bench_result, history, exclude_dir=str(
            results.resolve())) if bench_result else []
    except StoredFileError as e:  # bench.json or the history, named in the message
        _fail(str(e))
    except (ValueError, KeyError, TypeError) as e:
        _fail(f"{results / 'bench.json'}: malformed ({type(e).__name__}: {e})")
    slower = [s for s in speed if s.slower]
    if verdict.code == 0 and slower:
        verdict.code = diff.SLOWER
    verdict.lines += [s.line() for s in slower]
    for line in verdict.lines:
        err.print(("[red]REGRESSION[/] " if verdict.code == 1 else "") + escape(line),
                  highlight=False)
    for line in verdict.notes:
        err.print(f"note: {escape(line)}", highlight=False)
    for line in diff.speed_notes(speed, history):
        err.print(escape(line), highlight=False)
    n = len(summary["records"])
    if verdict.code == 0:
        out.print(f"[green]gate passed[/]: {len(verdict.passed)} of {n} case x engine runs "
                  "judged from their result files and within tolerance"
                  + ("" if base else " (no baseline stored)"))
        if update_baseline:
            try:
                cells = gate.update_baseline(verdict, baseline, summary.get("generated"))
            except OSError as e:
                _fail(f"{baseline}: cannot write the baseline ({e.strerror or e})",
                      gate.CANNOT_WRITE)
            out.print(f"baseline updated for the {len(cells)} cells judged in this gate: "
                      f"{escape(str(baseline))}")
    else:
        err.print(f"[bold red]gate failed[/] (exit {verdict.code})")
    raise typer.Exit(verdict.code)


def _bench(selected, names, repeats, work_precision, references, timeout, quiet=False):
    from .suite import bench

    _check_references(selected, references, full=True)  # the benchmark errors read them
    total = len(selected) * len(names)
    say = (lambda *a: None) if quiet else out.print
    say(f"benchmarking {total} case x engine pairs, best of up to {repeats} calibrated "
        f"samples each (fewer where they would take over {bench.BUDGET_S:g} s of process "
        "time; bench.json keeps every one)")
    result = bench.bench(selected, names, repeats=repeats, timeout_s=timeout,
                         progress=None if quiet else _progress_printer(total),
                         references=references)
    say(_cost_table(result))
    if result.get("cold_start"):
        c = result["cold_start"]
        say(f"natcoord cold start ({escape(c['case'])}, {c['duration_s']:g} s simulated, "
            f"fresh process, build time): " + (
                f"{c['build_time_s']:.2f} s (import {c['import_s']:.2f} s, plan and kernels "
                + ("from cache" if c.get("path") in ("generated", None) else
                   f"({c['path']} path, not the generated kernels)")
                + f" {c['kernel_load_s'] or 0:.2f} s, run {c['wall_time_s']:.3g} s), "
                f"best of {len(c['samples_s'])}" if c["status"] == "ok" else
                f"{c['status']}: {escape(c['reason'])}"))
    if work_precision:
        n = sum(len(bench.SWEEPS.get(e, [])) for e in names) * len(selected)
        say(f"work-precision: {n} runs")
        points = bench.work_precision(selected, names, references=references,
                                      repeats=repeats, timeout_s=timeout,
                                      progress=None if quiet else _progress_printer(n))
        result["work_precision"] = points
        result["time_to_accuracy"] = bench.time_to_accuracy(points)
        result["scoring"] = bench.scoring(selected, result["records"], points)
        table = Table(title="time (s, a run's stepping, best wall clock on one core) to "
                            "reach an angle error: the cheapest swept point, and (~) "
                            "interpolated on the sweep's curve")
        for col in ("case", "engine", *(f"{c}{t:g} rad" for t in bench.TARGETS
                                         for c in ("<= ", "~ "))):
            table.add_column(col)
        for row in result["time_to_accuracy"]:
            cells = [(row[bench.time_to_key(t, interp)], "-" if interp else "not reached")
                     for t in bench.TARGETS for interp in (False, True)]
            table.add_row(escape(row["case"]), row["engine"],
                          *(none if c is None else f"{c:.3g}" for c, none in cells))
        say(table)
        if result["scoring"]:
            say(_score_table(result["scoring"]))
    return result


def _scaling_sizes(sizes: str) -> list[int]:
    """The N of ``--scaling``, checked before anything runs: positive integers the
    N-four-bar family can generate."""
    from .case.generate import n_four_bar

    try:
        ns = [int(x) for x in sizes.split(",") if x.strip()]
    except ValueError:
        ns = []
    if not ns or min(ns) < 1:
        _fail(f"--scaling: expected positive integers N separated by commas, got {sizes!r}")
    for n in ns:
        try:
            n_four_bar(n)
        except ValueError as e:
            _fail(f"--scaling: {e}")
    return sorted(set(ns))  # the growth is said from the smallest N to the largest


def _scaling(ns: list[int], quiet: bool = False) -> dict:
    from .suite import scaling

    say = (lambda *a: None) if quiet else out.print
    say(f"scaling: natcoord on N-four-bars N = {', '.join(map(str, ns))}")
    result = scaling.scaling(ns)
    table = Table(title=f"natcoord cost per step by size ({result['method']})")
    for col in ("N", "coordinates", "rows", "build s", "plan s", "steps", "us/step",
                "us/rhs", "s per simulated s", "B0 error m"):
        table.add_column(col)
    for r in result["records"]:
        table.add_row(str(r["N"]), str(r["n"]), str(r["m"]), f"{r['build_time_s']:.2f}",
                      f"{r['plan_time_s']:.3f}", str(r["steps"]), f"{r['us_per_step']:.1f}",
                      f"{r['us_per_rhs']:.2f}", f"{r['s_per_simulated_s']:.3g}",
                      f"{r['error_m']:.2g}")
    say(table)
    if "step_cost_ratio" in result:
        say(f"cost per step grew {result['step_cost_ratio']:.1f}x for {result['size_ratio']:g}x "
            "the couplers")
    return result


def _g(x, fmt="{:.3g}", none="—"):
    return none if x is None else fmt.format(x)


def _cost_table(result: dict) -> Table:
    """Per case x engine: best wall time, steps, rhs, and the cost fit."""
    table = Table(title="Cost per case x engine (fit over the whole run and its first "
                        "quarter, best of the repeats)")
    for col in ("case", "engine", "status", "best wall (s)", "steps", "rhs", "fixed (s)",
                "us/step", "us/rhs", "build (s)"):
        table.add_column(col, justify="left" if col in ("case", "engine", "status")
                         else "right")
    for r in result["records"]:
        c = r.get("counters") or {}
        table.add_row(escape(r["case"]), r["engine"], r["status"], _g(r.get("wall_time_s")),
                      _g(r.get("n_steps"), "{:d}"), _g(c.get("rhs"), "{:d}"),
                      _g(r.get("fixed_s"), "{:.2g}"), _g(r.get("per_step_us")),
                      _g(r.get("per_rhs_us")), _g(r.get("build_time_s"), "{:.2g}"))
    return table


def _score_table(rows: list[dict]) -> Table:
    """The benchmark scoring: error at the case's settings, CPU time to the precision."""
    table = Table(title=escape("Benchmark scoring (error as each case's [benchmark] "
                               "defines it)"))
    for col in ("case", "output", "precision", "engine", "error at case settings",
                "time to precision (s)", "by"):
        table.add_column(col)
    for r in rows:
        table.add_row(escape(r["case"]), ", ".join(r["channels"]) + (
            " (end)" if r["error_kind"] == "final_abs" else ""), f"{r['precision']:g}",
            r["engine"], _g(r["error"], "{:.2g}", r["status"] or "—"),
            _g(r["time_to_precision"], "{:.3g}", "not reached"), escape(r["reached_by"]))
    return table


@app.command("bench")
def bench_cmd(cases: CaseArgs = None, engines: Engines = None,
              repeats: Annotated[int, typer.Option(
                  min=1, max=MAX_REPEATS,
                  help="Timing samples per cell, each a calibrated batch (the run "
                              "repeated for at least 0.1 s), every one kept.")] = 7,
              out_dir: OutDir = None,
              history: Annotated[Path | None, typer.Option(
                  help="Where dated copies go [default: <project>/reports/bench].",
                  show_default=False)] = None,
              work_precision: Annotated[bool, typer.Option(
                  help="Also sweep step sizes / tolerances: angle error against CPU time, "
                       "the time each engine needs to reach 1e-6 and 1e-9 rad, and the "
                       "benchmark scoring of cases with a [benchmark] table.")] = False,
              timeout: Timeout = DEFAULT_TIMEOUT_S,
              cases_dir: CasesDir = None, references: RefDir = None,
              as_json: Annotated[bool, typer.Option(
                  "--json", help="Print bench.json to stdout instead of the tables.")] = False,
              scaling: Annotated[str | None, typer.Option(
                  help="Also natcoord's cost per step on generated N-four-bars of these N "
                       "(comma-separated, e.g. 64,512).", show_default=False)] = None):
    """Measure the cost per case x engine: best of repeats (single-threaded BLAS), fixed
    cost, cost per step and per right-hand side, natcoord's cold start; with --scaling,
    how natcoord's cost per step grows with the size of a mechanism. Exit 3 when a cell
    failed (each named with its reason), 0 otherwise."""
    from .suite import bench
    from .suite.io import check_folder
    from .suite.outdir import publishing

    names = _engines(engines)
    sizes = _scaling_sizes(scaling) if scaling is not None else None
    target = _out_dir(out_dir, "bench")
    copies = resolve(history, "reports/bench")
    check_folder(copies, "--history")  # before measuring: the measurements are not lost
    with publishing(target, "bench") as staging:
        selected = _cases(cases, cases_dir)
        result = _bench(selected, names, repeats, work_precision,
                        resolve(references, "references"), timeout, quiet=as_json)
        if sizes:
            result["scaling"] = _scaling(sizes, quiet=as_json)
        bench.store(result, staging, copies)
    if as_json:
        _print_json(result)
    else:
        out.print(f"benchmark: {target / 'bench.json'}")
    failed = [r for r in result["records"] if r.get("status") == "failed"]
    for r in failed:  # the table shows 'failed' only: the reason is here and in bench.json
        err.print(escape(f"{r['case']}/{r['engine']}: failed: {_short(r.get('reason') or '')}"),
                  highlight=False)
    if failed:
        err.print(f"[bold red]{len(failed)} of {len(result['records'])} cell(s) failed[/] "
                  f"(exit {RUN_FAILED})")
        raise typer.Exit(RUN_FAILED)


@app.command("suite")
def suite_cmd(engines: Engines = None, out_dir: OutDir = None,
              repeats: Annotated[int, typer.Option(
                  min=0, max=MAX_REPEATS,
                  help="Bench timing samples per cell, each a calibrated batch "
                              "(0: no bench).")] = 7,
              timeout: Timeout = DEFAULT_TIMEOUT_S, jobs: Jobs = None,
              scheduler: Scheduler = None, cases: CaseArgs = None,
              cases_dir: CasesDir = None, references: RefDir = None,
              history: HistoryDb = None,
              bench_budget: Annotated[float, typer.Option(
                  parser=_number(0, MAX_BUDGET_S), metavar="SECONDS",
                  help=f"Engine process time (s, at most {MAX_BUDGET_S:g}) a night's bench may "
                  "spend on other engines' cells that need measuring (natcoord's are "
                  "outside it); a cell left over is timed by its accuracy run and measured "
                  "on a later night.")] = NIGHT_BUDGET_S,
              quick: Annotated[bool, typer.Option(
                  "--quick", help="A first look: natcoord and mujoco (or "
                  "--engines), every cell timed by its accuracy run (no bench process), no "
                  "sweeps, no speed gate; not recorded in the history, reports/latest not "
                  "moved.")] = False,
              accept_speed: Annotated[bool, typer.Option(
                  "--accept-speed", help="Take tonight's speed as the new baseline: a "
                  "significant slowdown is reported, not failed (exit 4), and its samples "
                  "are later nights' baseline. Without it a slowdown's samples never are: "
                  "a lasting one fails every night until accepted.")] = False):
    """The nightly job: run all, bench, report, gate (accuracy, and speed against the
    history), record history; reports/latest then points at it. Exits with the gate's code
    (4: a significant slowdown). Bench policy: natcoord measured every night, another
    engine's cell measured again only when its version, the case file, its adapter or the
    machine changed or its measurement is a week old (else reused from earlier suites,
    marked so)."""
    from .report.html import write_report
    from .suite import bench, diff, evidence, gate, policy
    from .suite import eta as eta_
    from .suite import history as hist
    from .suite.io import write_json
    from .suite.outdir import publishing
    from .suite.runner import machine_info, run_suite

    names = _engines(engines)
    if quick:
        names = [e for e in names if e in policy.QUICK_ENGINES] if engines is None else names
        repeats = min(repeats, 1)
    references = resolve(references, "references")
    history = resolve(history, "reports/history.db")
    hist.check(history, write=True)  # damaged, foreign or read-only: exit 2 before running
    hist.import_jsonl(history, history.with_suffix(".jsonl"))
    target = _out_dir(out_dir, "suite-quick" if quick else "suite")
    # a subset is not nightly
    nightly = out_dir is None and not cases and engines is None and not quick
    machine = machine_info()["fingerprint"]
    prev_bench, prev_summary = policy.earlier(history, machine)
    with publishing(target, "suite") as staging:
        selected = _cases(cases, cases_dir)
        _check_references(selected, references)
        try:
            base = gate.load_baseline(references / "baseline.json")
        except ValueError as e:
            _fail(str(e))
        total = len(selected) * len(names)
        n, where = _where(jobs, scheduler)
        bench_engines = names
        catalogue = [] if quick or not repeats else [j for j in selected if j.case.benchmark]
        known, source = eta_.known(prev_summary, prev_bench, references)
        clock = eta_.Eta(_expected(selected, names, bench_engines if repeats and not quick
                                   else [],
                                   catalogue, prev_bench, known, n, bench_budget))
        whence = {"earlier": "earlier suites' durations",
                  "reference": "a reference suite's durations: none on this machine yet"}
        out.print(f"[bold]natcoord suite{' --quick' if quick else ''}[/]: {len(selected)} "
                  f"cases x {len(names)} engines, {where} -> {escape(str(target))}"
                  + (f"; about {clock.left():.0f} s ({whence[source]})" if source else ""))
        if quick:
            out.print("[bold yellow]quick[/]: a first look, not a nightly: engines "
                      f"{', '.join(names)}, every cell timed by its accuracy run (no bench), "
                      "no sweeps, no speed gate; not recorded in the history, reports/latest "
                      "not moved")
        phases = {"start": clock.clock()}
        first = {(c, e): t for (k, c, e), t in clock.expected.items() if k == "run"}
        tick = _ticker(clock, "run", n)
        summary = run_suite(selected, names, staging, references=references,
                            timeout_s=timeout, jobs=n, scheduler=scheduler, first=first,
                            progress=_progress_printer(total, where, tick), started=tick.started)
        if quick:
            summary["mode"] = "quick"
            write_json(staging / "summary.json", summary)
        phases["accuracy runs"] = clock.clock()
        bench_result, speed = None, []
        if repeats:
            plan = policy.quick(summary) if quick else policy.plan(
                summary, prev_bench, names, repeats=repeats, machine=machine)
            budget = policy.Budget(bench_budget)
            clock.add({(k, c, e): 0.0 for (c, e) in (*plan.reuse, *plan.timed)
                       for k in ("bench", "sweep")})
            clock.budget({(c, e) for c, e in plan.spare}, bench_budget)
            out.print("[bold]bench[/]: every cell timed by its accuracy run (quick)" if quick
                      else f"[bold]bench[/]: {repeats} calibrated sample(s) per measured "
                      "cell; " + _policy_line(plan, bench_budget))
            bench_result = bench.bench(
                selected, bench_engines, repeats=repeats, timeout_s=timeout,
                references=references, reuse={**plan.reuse, **plan.timed}, cold=not quick,
                spare=plan.spare, budget=budget, cell_budget_s=policy.CELL_BUDGET_S,
                progress=_progress_printer(len(selected) * len(bench_engines),
                                           "serial, one core", _ticker(clock, "bench")))
            clock.done(eta_.COLD_START, eta_.cold_start_s(bench_result))  # a piece that
            # was not expected (natcoord not benched) adds nothing
            run_timed = {(r["case"], r["engine"]): r["timed_by"]["why"]
                         for r in bench_result["records"] if "timed_by" in r}
            bench_result["policy"] = {
                "mode": "quick" if quick else "nightly", "always": list(policy.ALWAYS),
                "max_age_days": policy.MAX_AGE.days, "budget_s": bench_budget,
                "reused": sorted("/".join(k) for k in plan.reuse),
                "timed_by_accuracy_run": {"/".join(k): v for k, v in sorted(run_timed.items())},
                "measured": {"/".join(k): v for k, v in sorted(plan.measure.items())
                             if k not in run_timed}}
            phases["bench"] = clock.clock()
            if catalogue:
                swept = {(p.get("case"), p.get("engine")) for p in plan.kept}  # a reused
                # cell without points (its night's budget ran out) is swept when it can be
                _nightly_sweeps(bench_result, catalogue, names, references, timeout,
                                (set(plan.reuse) & swept) | set(run_timed), plan.kept, clock,
                                budget)
                phases["work-precision"] = clock.clock()
            bench_result["policy"]["spent_s"] = round(budget.spent, 1)
            if not quick:
                speed = diff.slower_rechecked(
                    policy.measured_only(bench_result), selected, repeats, timeout, history,
                    say=lambda n: out.print(f"re-measuring {n} cell(s) that look slower "
                                            "than their history"))
            # the dated copy only for the nightly suite, under the project's reports/
            stored = bench.store(bench_result, staging,
                                 resolve(None, "reports/bench") if nightly else None)
            summary["bench_sha256"] = evidence.sha256_of(stored.read_bytes())  # the gate
            write_json(staging / "summary.json", summary)  # checks bench.json against it
        slower = [s for s in speed if s.slower]
        verdict = gate.judge(summary, staging, references=references, baseline=base, staged=True,
                             cases=gate.CaseBook(resolve(cases_dir, "cases"),
                                                 {j.case.name: j.case for j in selected}))
        accepted = [f"accepted (--accept-speed): {s.line()}" for s in slower
                    if accept_speed]  # reported; the new baseline from tonight on
        slower = [] if accept_speed else slower
        verdict.notes += accepted
        if verdict.code == 0 and slower:
            verdict.code = diff.SLOWER
        verdict.lines += ([s.line() for s in slower] + accepted
                          + diff.speed_notes(speed, history))
        if quick:
            verdict.lines.append("quick suite: speed not judged (one sample per cell, from "
                                 "its accuracy run); "
                                 "not recorded in the history")
        write_report(staging, references, history, verdict)
        phases["speed gate, report"] = clock.clock()
        ci_text = diff.write_ci_summary(staging, summary, verdict.code, slower,
                                        target / "index.html", verdict.lines)
        late = _Deferred()  # from here the night is published: finish it whole
    try:
        marks = list(phases.items())
        out.print(f"suite{' --quick' if quick else ''} took {marks[-1][1] - marks[0][1]:.0f} s: "
                  + ", ".join(f"{k} {t - marks[i][1]:.0f} s" for i, (k, t) in
                              enumerate(marks[1:])))
        if out_dir is None and not quick:
            _point_latest(target)
        for line in verdict.lines:
            err.print(escape(line), highlight=False)
        code, faults = verdict.code, []
        try:  # the results are published: a fault from here on is reported, not fatal
            if not quick:  # a first look is no nightly: no history, no speed baseline
                hist.record(history, kind="suite", summary=summary,
                            bench=bench_result and policy.measured_only(bench_result),
                            gate=verdict.code, results_dir=str(target.resolve()),
                            commit=hist.git_commit(resolve(None, ".")),
                            slower=[(s.case, s.engine) for s in slower])
        except NatcoordError as e:
            faults.append((e, ENVIRONMENT if isinstance(e, EnvironmentFault) else 2))
        try:
            diff.append_step_summary(ci_text)
        except NatcoordError as e:
            faults.append((e, ENVIRONMENT))
        out.print(counts_line(summary["records"]) + (" (quick)" if quick else ""))
        out.print(f"report: {(target / 'index.html').resolve()}")
        out.print("[green]gate passed[/]" if verdict.code == 0
                  else f"[bold red]gate failed[/] (exit {verdict.code})")
        for e, c in faults:
            err.print(f"[bold red]error:[/] {escape(str(e))} (the results are kept in "
                      f"{escape(str(target))})", highlight=False)
            code = code or c
        if late.got:
            err.print(f"{'interrupted' if late.got[0] == signal.SIGINT else 'terminated'} "
                      f"after the results were published: finished recording them "
                      f"({target})", highlight=False)
    finally:
        late.restore()
    raise typer.Exit(code)


def _expected(selected, names, bench_engines, catalogue, prev_bench, known: dict,
              jobs: int, budget_s: float) -> dict:
    """Each piece of a suite's work and its expected seconds (:mod:`natcoord.suite.eta`)
    from ``known`` durations (earlier suites', or the shipped reference suite's): the
    accuracy runs shared over ``jobs`` cores; a bench cell or sweep of an engine the
    policy would reuse (same case file, last measured within its age) 0 s; the other
    engines' bench cells and sweeps within the night's budget ``budget_s``; natcoord's
    cold start (fresh processes, after the bench cells) when natcoord is benchmarked."""
    from .suite import eta, policy
    from .suite.worker import cannot_run

    cells = [(j.case, e) for j in selected for e in names]
    out = {k: t / jobs for k, t in eta.expect(
        [("run", c.name, e) for c, e in cells], known).items()}
    fresh = policy.likely_reused(prev_bench, {c.name: c.digest for c, _ in cells})
    sweep = {(j.case.name, e) for j in catalogue for e in names}
    pieces = [("bench", c.name, e) for c, e in cells if e in bench_engines]
    pieces += [("sweep", c, e) for c, e in sweep]
    out |= {k: 0.0 if (k[1], k[2]) in fresh else t
            for k, t in eta.expect(pieces, known).items()}
    cannot = {(c.name, e) for c, e in cells if cannot_run(c, e)}  # no engine process
    out = {k: 0.0 if (k[1], k[2]) in cannot else t for k, t in out.items()}
    if "natcoord" in bench_engines and cells:  # the bench ends with natcoord's cold start
        out |= eta.expect([eta.COLD_START], known)
    budgeted = {(c.name, e) for c, e in cells if e not in policy.ALWAYS} - fresh
    return eta.cap(out, budgeted, budget_s)


def _ticker(clock, kind: str, shared: int = 1):
    """``left(key, rec)`` for a progress printer: marks the piece ``key`` ('case/engine')
    of ``kind`` done, with its record's process time over the ``shared`` cores it ran
    beside others on (none for a bench record carried from elsewhere), and returns the
    suite's time left; ``left.started(key)`` marks a piece started."""
    from .suite.stored import carried

    def piece(key: str) -> tuple:
        case, _, engine = key.partition("/")
        return kind, case, engine

    def left(key: str, rec: dict | None = None) -> float:
        t = None if rec is None or carried(rec) else rec.get("process_time_s")  # a cell
        clock.done(piece(key),  # reused or timed by its run spent nothing tonight
                   t / shared if isinstance(t, (int, float)) else None)
        return clock.left()
    left.peek = lambda: clock.left() if clock.finished or clock.begun else None  # heartbeat
    left.started = lambda key: clock.started(piece(key), shared)
    return left


def _policy_line(plan, budget_s: float) -> str:
    """What the bench policy chose: cells measured (and why, counted), cells in the night's
    budget, cells reused, cells timed by their accuracy run."""
    from collections import Counter

    counts = Counter(plan.measure.values())
    text = f"{len(plan.measure)} cell(s) to measure (" + "; ".join(
        f"{v}: {k}" for k, v in counts.most_common(4)) + ")"
    if plan.spare:
        text += (f", {len(plan.spare)} of them other engines' within tonight's budget of "
                 f"{budget_s:g} s (the rest timed by their accuracy run)")
    if plan.reuse:
        dates = sorted(r["measured"][:10] for r in plan.reuse.values())
        text += (f", {len(plan.reuse)} reused from earlier suites (measured "
                 f"{dates[0]}{' to ' + dates[-1] if dates[-1] != dates[0] else ''})")
    if plan.timed:
        text += (f", {len(plan.timed)} timed by their accuracy run (one run longer than a "
                 "nightly cell's timing budget)")
    return text


def _nightly_sweeps(result: dict, catalogue, names, references, timeout, skip: set, kept,
                    clock, budget) -> None:
    """The suite's work-precision points (policy.NIGHTLY_SWEEPS on the catalogue cases;
    ``skip``: cells not swept tonight (reused ones' points ``kept``); other engines' sweeps
    while the night's ``budget`` lasts), time to accuracy and the benchmark scoring, into
    ``result`` as `natcoord bench --work-precision` writes them."""
    from .suite import bench, policy

    skip = set(skip)
    per = {(j.case.name, e): len(policy.NIGHTLY_SWEEPS.get(e, [])) for j in catalogue
           for e in names if (j.case.name, e) not in skip}
    total = sum(per.values())
    names_in = {j.case.name for j in catalogue}
    mine = sum(n for (_, e), n in per.items() if e in policy.ALWAYS)
    out.print(f"[bold]work-precision[/]: up to {total} point(s) on {len(catalogue)} catalogue "
              f"case(s): {mine} of natcoord, the other engines' while tonight's budget "
              f"lasts; {sum(c in names_in for c, _ in skip)} cell(s) reused or timed by "
              "their accuracy run")
    seen: dict = {}

    took: dict = {}

    def left(key: str, rec: dict | None = None) -> float:
        cell = key.split(" ")[0]
        case, _, engine = cell.partition("/")
        seen[(case, engine)] = seen.get((case, engine), 0) + 1
        t = (rec or {}).get("process_time_s")
        took[(case, engine)] = took.get((case, engine), 0.0) + (
            t if isinstance(t, (int, float)) else 0.0)
        if seen[(case, engine)] >= per.get((case, engine), 0):
            clock.done(("sweep", case, engine), took[(case, engine)])
        return clock.left()

    points = bench.work_precision(catalogue, names, references=references, repeats=3,
                                  timeout_s=timeout, sweeps=policy.NIGHTLY_SWEEPS,
                                  skip=skip, budget=budget, free=policy.ALWAYS,
                                  cell_budget_s=policy.CELL_BUDGET_S,
                                  progress=_progress_printer(
                                      total, "serial, one core", left))
    points += [p for p in kept if p.get("case") in names_in]
    for j in catalogue:  # an engine that cannot run a case: its sweep is done at once
        for e in names:
            if (j.case.name, e) not in seen:
                clock.done(("sweep", j.case.name, e))
    result["work_precision"] = points
    result["time_to_accuracy"] = bench.time_to_accuracy(points)
    result["scoring"] = bench.scoring(catalogue, result["records"], points)


@app.command("history")
def history_cmd(cell: Annotated[str | None, typer.Option(
                    help="One cell's series, CASE/ENGINE: accuracy and speed per run.")] = None,
                since_green: Annotated[bool, typer.Option(
                    "--since-green", help="What regressed in the newest suite since the last "
                    "suite whose gate passed.")] = False,
                flaky_: Annotated[bool, typer.Option(
                    "--flaky", help="Cells whose verdict flips, with a score (flips per "
                    "run).")] = False,
                last: Annotated[int, typer.Option(
                    min=1, max=MAX_LAST, help="Runs to read.")] = 20,
                as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
                history: HistoryDb = None):
    """Ask the history database: the recent runs (commit, machine, gate verdict), one
    cell's accuracy and speed, what regressed since the last green suite, flaky cells.
    Read-only; exit 1 when --since-green finds a regression, else 0."""

    from .suite import history as hist
    from .suite import history_views as views

    asked = [name for name, given in (("--cell", cell is not None),
                                      ("--since-green", since_green), ("--flaky", flaky_))
             if given]
    if len(asked) > 1:
        _fail(f"{' and '.join(asked)} ask for different views: give one")
    db = resolve(history, "reports/history.db")
    try:
        hist.check(db)
        if cell is not None:
            case, sep, engine = cell.partition("/")
            if not sep or not case or not engine:
                _fail(f"--cell {cell!r}: CASE/ENGINE expected")
            data = views.cell(db, case, engine, last)
        elif since_green:
            data = views.since_green(db)
        elif flaky_:
            data = views.flaky(db, last)
        else:
            data = views.runs(db, last)
    except NatcoordError as e:
        _fail(str(e))
    code = 1 if since_green and data["regressed"] else 0
    if as_json:
        _print_json(data)
        raise typer.Exit(code)
    if since_green:
        g, n = data["green"], data["latest"]
        if n is None or g is None:
            out.print(f"no {'suite' if n is None else 'green suite before the newest'} in "
                      f"{escape(str(db))}: nothing to compare")
            raise typer.Exit(0)
        out.print(f"newest suite #{n['id']} ({n['generated']}, {n['commit'][:10] or '?'}, "
                  f"gate {n['gate']}) against the last green #{g['id']} ({g['generated']}, "
                  f"{g['commit'][:10] or '?'})")
        if data.get("speed"):
            out.print(f"  {escape(data['speed'])}")
        for r in data["regressed"]:
            out.print(f"  {escape(r['cell'])}: {escape('; '.join(r['why']))}")
        if not data["regressed"]:
            out.print("  nothing regressed")
        raise typer.Exit(code)
    rows = data if isinstance(data, list) else []
    if not rows:
        what = (f"no run of cell {cell!r} recorded" if cell is not None else
                "no cell's verdict flipped between pass and fail" if flaky_ else
                "nothing recorded")
        out.print(f"{escape(what)} in {escape(str(db))}" + (
            "" if db.is_file() else " (no such file)"))
        raise typer.Exit(0)
    table = Table()
    for col in rows[0]:
        table.add_column(col)
    for r in rows:
        table.add_row(*(escape(f"{v:.3g}" if isinstance(v, float) else str(v if v is not
                                                                             None else ""))
                        for v in r.values()))
    out.print(table)


@app.command("bisect")
def bisect_cmd(good: Annotated[str, typer.Argument(help="A commit where the gate passes.")],
               bad: Annotated[str, typer.Argument(help="A later commit where it fails.")],
               cases: CaseArgs = None, engines: Engines = None,
               repo: Annotated[Path | None, typer.Option(
                   help="The git repository [default: the project folder].",
                   show_default=False)] = None,
               timeout: Timeout = DEFAULT_TIMEOUT_S,
               as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False):
    """Find the first commit between GOOD and BAD at which the gate fails for these cases
    and engines (git bisect in a temporary worktree: each commit's own natcoord, case files
    and references; a crash or timeout counts as bad, a commit that cannot start is
    skipped). Exit 0 with the commit named, 3 when bisect could not name one."""

    from .suite.bisect import bisect

    try:
        found = bisect(resolve(repo, "."), good, bad, list(cases or []), list(_engines(engines)),
                       timeout_s=timeout)
    except NatcoordError as e:
        _fail(str(e))
    if as_json:
        _print_json({k: v for k, v in found.items() if k != "log"})
    elif found["first_bad"]:
        out.print(f"first bad commit: {found['first_bad']} {escape(found['subject'])}")
    else:
        err.print(escape(found["log"][-2000:]), highlight=False)
        err.print(f"bisect could not name a first bad commit: {escape(found['why'])}")
    raise typer.Exit(0 if found["first_bad"] else 3)


@app.command("compare")
def compare_cmd(base: Annotated[Path, typer.Argument(help="The earlier results folder.")],
                new: Annotated[Path, typer.Argument(help="The later results folder.")],
                as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
                cases_dir: CasesDir = None, references: RefDir = None):
    """What changed in accuracy and speed between two results folders (both judged from
    their result files), and in engine versions, case files and settings.

    Exit 0 nothing significant, 1 an accuracy regression, 2 bad input, 4 a significant
    slowdown (median past 1.5x and Mann-Whitney U at p <= 0.05 on the calibrated samples;
    a cell with too few samples for that test says "cannot judge speed").
    """

    from .suite import diff, gate

    def judge():
        try:
            return diff.compare_runs(base, new, cases=gate.CaseBook(resolve(cases_dir, "cases")),
                                     references=resolve(references, "references"))
        except ValueError as e:
            _fail(str(e))
    c = _read_whole([base, new], judge)
    if as_json:
        _print_json(c.as_json())
        raise typer.Exit(c.code)
    table = Table(title=f"{escape(str(base))} -> {escape(str(new))}")
    for col in ("case", "engine", "status", "verdict", "worst/tol before", "worst/tol now",
                "speed ratio", "p"):
        table.add_column(col)
    fmt = lambda x, f: "" if x is None or x != x else format(x, f)  # noqa: E731 (nan: none)
    for r in c.rows:
        table.add_row(escape(r["case"]), r["engine"], r["status"], r["verdict"],
                      fmt(r["worst_of_tolerance_base"], ".3g"),
                      fmt(r["worst_of_tolerance_new"], ".3g"),
                      fmt(r["speed_ratio"], ".3g") + (" SLOWER" if r["slower"] else
                                                      " (cannot judge)" if r["speed_judged"]
                                                      is False else ""),
                      fmt(r["speed_p"], ".2g"))
    out.print(table)
    for line in c.accuracy:
        err.print(escape(line), highlight=False)
    for line in c.changes:
        err.print(f"changed: {escape(line)}", highlight=False)
    for s in c.slower:
        err.print(escape(s.line()), highlight=False)
    for line in diff.speed_notes(c.speed):
        err.print(escape(line), highlight=False)
    if c.speed_note:
        err.print(escape(c.speed_note), highlight=False)
    for s in c.speed:
        if s.counters:
            err.print(escape(f"{s.case}/{s.engine}: behaviour change: counters {s.counters}"))
    raise typer.Exit(c.code)


@app.command("propose")
def propose_cmd(case: Annotated[str, typer.Argument(help="Case name or case file.")],
                engines: Engines = None,
                margin: Annotated[float, typer.Option(
                    parser=_number(1.0, MAX_MARGIN), metavar="FACTOR",
                    help=f"Tolerance = measured error x margin (1 to {MAX_MARGIN:g}).")] = 3.0,
                out_file: Annotated[Path | None, typer.Option(
                    "--out", help="Write the proposed blocks here too.")] = None,
                timeout: Timeout = DEFAULT_TIMEOUT_S, cases_dir: CasesDir = None,
                references: RefDir = None,
                force: Annotated[bool, typer.Option(
                    "--force", help="Replace an existing --out file.")] = False):
    """Propose tolerances for a new case: run it in every engine (at its settings and over
    the start of each engine's sweep), measure the errors against its reference and print
    the [engines.*] blocks to paste into the case file."""
    from .suite import propose

    (job,) = _cases([case], cases_dir)
    names = _engines(engines)
    refs = resolve(references, "references")
    _check_references([job], refs, full=True)
    if out_file is not None:  # refused before the long runs, not after
        from .suite.io import check_user_file

        try:
            check_user_file(out_file, force=force)
        except NatcoordError as e:
            _fail(str(e))
    try:
        rows = propose.propose(job, names, refs, margin=margin, timeout_s=timeout)
    except ValueError as e:
        _fail(str(e))
    text = propose.as_toml(job.case, rows, margin)
    print(text)
    for row in rows:
        if row["sweep"] and not propose.converged(row["sweep"]):
            err.print(f"note: {row['engine']}'s error does not fall over its sweep; check its "
                      "settings before trusting the proposal")
    if out_file is not None:
        from .suite.io import write_user_file

        try:
            write_user_file(out_file, text + "\n", force=force)
        except NatcoordError as e:
            _fail(str(e), _code(e))
        out.print(f"written: {escape(str(out_file))}")


@app.command("check-engine")
def check_engine_cmd(engine: Annotated[str, typer.Argument(help="Engine name (built-in or "
                                                                "plug-in).")],
                     as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")
                                        ] = False,
                     cases_dir: CasesDir = None, references: RefDir = None):
    """A conformance scorecard: reaction sign and frame (a hanging rod, and with the joint
    reversed), energy on a conservative pendulum, convergence order under the engine's step
    setting, agreement with the stored references on every case it can run (first 0.5 s),
    determined and undetermined reactions. Exit 0 all pass, 1 a check failed or none was
    judged (every one skipped), 2 an unknown
    engine, 3 the engine's package is not installed (or its version() fails)."""

    from .engines import adapter
    from .engines.registry import version_of
    from .suite.conformance import check_engine

    if _engines(engine, "check-engine NAME") != [engine]:  # unknown: exit 2, naming them
        _fail(f"check-engine NAME: one engine name expected, got {engine!r}")
    mod = adapter(engine)
    version, why, missing = version_of(engine)  # in a child process: the adapter's code
    if missing:                                  # cannot end this one
        _fail(f"{engine}: package {mod.PACKAGE!r} is not installed ({why}); pip install "
              f"{mod.PACKAGE}", RUN_FAILED)
    if version is None:  # the adapter's bug: no run could be recorded
        _fail(f"{engine}: the engine's version() {why}; every run needs it, so nothing was "
              "checked", RUN_FAILED)
    folder = resolve(cases_dir, "cases")
    if not Path(folder).is_dir() or not any(Path(folder).glob("*.toml")):
        _fail(f"{folder}: no case files (*.toml)" if Path(folder).is_dir() else
              f"{folder}: no such folder (--cases-dir)")  # the agreement checks need cases
    say = (lambda s: None) if as_json else (lambda s: out.print(Text(f"  running {s}",
                                                                     style="dim")))
    try:
        card = check_engine(engine, folder,
                            resolve(references, "references"), say)
    except NatcoordError as e:
        _fail(str(e))
    failed = [r for r in card["rows"] if r["result"] == "fail"]
    if as_json:
        _print_json(card)
    else:
        table = Table(title=f"check-engine {escape(engine)} {escape(card['version'])} "
                            f"({card['seconds']:g} s)")
        for col in ("check", "result", "figure", "capability touched", "detail"):
            table.add_column(col)
        style = {"pass": "green", "fail": "bold red", "skipped": "yellow", "info": "dim"}
        for r in card["rows"]:
            table.add_row(escape(r["check"]), Text(r["result"], style=style[r["result"]]),
                          escape(r["figure"]), escape(r["capability"]),
                          escape(_short(r["detail"], 160)))
        out.print(table)
        out.print(f"{len(card['rows'])} checks: "
                  + ", ".join(f"{sum(r['result'] == k for r in card['rows'])} {k}"
                              for k in ("pass", "fail", "info", "skipped")))
    judged = [r for r in card["rows"] if r["result"] in ("pass", "fail")]
    if not judged:  # every check skipped: nothing was shown to conform
        err.print(f"check-engine {escape(engine)}: no check passed or failed (the engine "
                  "declines every case of the battery): nothing conforms", highlight=False)
    raise typer.Exit(1 if failed or not judged else 0)


@reference_app.command("update")
def reference_update(cases: CaseArgs = None, cases_dir: CasesDir = None,
                     references: RefDir = None):
    """Regenerate stored references (natcoord at tight tolerance), with provenance."""
    from .suite.references import update_reference

    references = resolve(references, "references")
    for job in _cases(cases, cases_dir):
        case = job.case
        prov = update_reference(case, references, job.init)
        worst = max(prov["estimated_error"].values())
        out.print(f"{case.name}: reference written (estimated error <= {worst:.2g}, "
                  f"{prov['counters'].get('steps', '?')} steps)")


@app.command("generate")
def generate_cmd(family: Annotated[str, typer.Argument(help="Case family: n_four_bar.")],
                 n: Annotated[int, typer.Option("--n", help="The family's size parameter.")],
                 out_arg: Annotated[str, typer.Option("--out", help="Case file to write "
                                                      "(NAME.toml); its stem is the case name.")],
                 duration: Annotated[float | None, typer.Option(
                     parser=_number(1e-3, MAX_DURATION_S), metavar="SECONDS",
                     help=f"s, 0.001 to {MAX_DURATION_S:g} [default: the family's "
                     "specification].")] = None,
                 force: Annotated[bool, typer.Option(
                     "--force", help="Replace an existing case file.")] = False):
    """Write one member of a parametric case family as a case file (loaded back to check
    before it is written; an existing file is kept unless --force)."""
    from .case.generate import FAMILIES, case_file_path, check_duration, write_case

    if family not in FAMILIES:
        _fail(f"unknown family {family!r}; families are {', '.join(FAMILIES)}")
    try:
        out_file = case_file_path(out_arg)
        if duration is not None:
            check_duration(duration)
        text = FAMILIES[family](n, name=out_file.stem, duration=duration)
        write_case(out_file, text, force=force)
    except (ValueError, NatcoordError) as e:
        _fail(str(e), _code(e))
    out.print(f"{family} N = {n}: {out_file}")


@app.command("import")
def import_cmd(model: Annotated[Path, typer.Argument(help="MuJoCo model (MJCF .xml).")],
               out_arg: Annotated[str, typer.Option(
                   "--out", help="Case file to write (NAME.toml; its stem is the case "
                   "name), or an existing folder to write <name>.toml in.")],
               name: Annotated[str | None, typer.Option(
                   help="Case name [default: the file's stem, or the model's].")] = None,
               duration: Annotated[float, typer.Option(
                   parser=_number(IMPORT_DT, MAX_SAMPLES * IMPORT_DT), metavar="SECONDS",
                   help=f"s, a multiple of the output step {IMPORT_DT:g} s, up to "
                        f"{MAX_SAMPLES * IMPORT_DT:g}.")] = 2.0,
               force: Annotated[bool, typer.Option(
                   "--force", help="Replace an existing case file.")] = False):
    """Turn a MuJoCo model into a case file: bodies with MuJoCo's compiled inertias, hinge,
    slide and ball joints, connect (and weld) equalities closing loops, gravity and the
    initial state; what it does not carry is listed in the file and here."""
    from .case.generate import case_file_path, check_duration, write_case
    from .case.mjcf import import_mjcf

    if out_arg and Path(out_arg).is_dir():  # an existing folder: the case file in it
        out_arg = os.path.join(out_arg, f"{name or model.stem}.toml")
    try:  # else a case file, as for generate (a folder yet to be made is refused)
        out_file = case_file_path(out_arg)
        check_duration(duration)
    except NatcoordError as e:
        _fail(str(e))
    if name is not None and name != out_file.stem:
        _fail(f"--name {name!r} must equal the case file's stem {out_file.stem!r}")
    try:
        imported = import_mjcf(model, out_file.stem, duration=duration)
        write_case(out_file, imported.text, force=force, assemble=True)
    except NatcoordError as e:
        _fail(str(e), _code(e))
    for note in imported.notes:
        out.print(f"not carried: {escape(note)}", highlight=False)
    out.print(f"{model} -> {out_file} ({imported.dimension}-D, "
              f"{len(imported.loops)} loop(s))", highlight=False)


# OSErrors that a path the user gave causes, not the machine: bad input (exit 2)
BAD_PATH = {errno.ENOTDIR: "a part of the path is a file, not a folder",
            errno.ENAMETOOLONG: "a name in the path is over the file system's limit, "
                                "255 bytes on most",
            errno.ELOOP: "the path goes round a loop of symbolic links",
            errno.EISDIR: "a folder where a file is expected"}


def _bad_path(e: OSError) -> str | None:
    """What is wrong with the path the user gave, when ``e`` comes from it (None: a fault
    of the environment: a full disk, a read-only folder, permissions)."""
    if e.errno in BAD_PATH:
        return BAD_PATH[e.errno]
    if e.errno == errno.EEXIST and e.filename is not None and os.path.lexists(e.filename) \
            and not os.path.isdir(e.filename):  # a folder to make, a file in the way
        return "a file where a folder is needed"
    return None


def _not_utf8(e: UnicodeError) -> str:
    """What to say for a name or text that is not valid UTF-8 (a path in Latin-1, say,
    that Python carries with surrogate escapes) when nothing nearer said it."""
    if isinstance(e, UnicodeEncodeError) and isinstance(e.object, str):
        try:
            shown = e.object.encode("utf-8", "surrogateescape").decode("utf-8",
                                                                       "backslashreplace")
        except UnicodeError:
            shown = ascii(e.object)
        return (f"{shown[:300]}: not valid UTF-8 (a file name in another encoding?); "
                "rename it or give another path")
    return (f"text that is not valid UTF-8 ({e.reason}): a file name or a file in another "
            "encoding?")


class _Deferred:
    """From its making on, a Ctrl-C or SIGTERM is noted (``got``) instead of stopping the
    command, until :meth:`restore`: a suite whose results are published records them,
    moves reports/latest and exits with its gate's code (stopped there, it said nothing
    was published and the history missed the night). Main thread only."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.got: list[int] = []
        self.old = [signal.signal(s, lambda signum, frame: self.got.append(signum))
                    for s in self.SIGNALS]

    def restore(self) -> None:
        for s, handler in zip(self.SIGNALS, self.old, strict=True):
            signal.signal(s, handler)


def _stop(signum, frame):
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C does not cut the clean-up
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Stopped(signum)


def main():  # pragma: no cover - console entry
    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    try:
        app()
    except EnvironmentFault as e:
        err.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False)
        sys.exit(ENVIRONMENT)
    except NatcoordError as e:
        err.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False)
        sys.exit(2)
    except (UnicodeEncodeError, UnicodeDecodeError) as e:  # bad input, not a traceback
        err.print(f"[bold red]error:[/] {escape(_not_utf8(e))}", highlight=False)
        sys.exit(2)
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        bad = _bad_path(e)
        if bad:  # the input: a path that cannot name what it should
            err.print(f"[bold red]error:[/] {escape(where + (e.strerror or str(e)))} "
                      f"({escape(bad)})", highlight=False)
            sys.exit(2)
        # the machine, not the input: a full disk, a read-only folder
        err.print(f"[bold red]error:[/] {escape(where + (e.strerror or str(e)))} (a fault of "
                  "the environment: disk space, permissions or a read-only folder)",
                  highlight=False)
        sys.exit(ENVIRONMENT)
    except Stopped as e:
        what = "interrupted" if e.signum == signal.SIGINT else "terminated"
        err.print(f"{what}: every engine process stopped; no results of this command "
                  "published")
        sys.exit(128 + e.signum)


if __name__ == "__main__":  # pragma: no cover
    main()
