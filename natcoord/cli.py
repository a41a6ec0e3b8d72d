"""The ``natcoord`` command line: cases, run, report, gate, bench, suite, reference update."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from .casefile import load_case
from .engines import ENGINES
from .errors import CaseError, NatcoordError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Natural-coordinate multibody solver and cross-engine validation suite.")
reference_app = typer.Typer(no_args_is_help=True, help="Stored reference solutions.")
app.add_typer(reference_app, name="reference")
out = Console(soft_wrap=True)
err = Console(stderr=True, soft_wrap=True)

DEFAULT_OUT = Path("reports/latest")
CasesDir = Annotated[Path, typer.Option("--cases-dir", help="Folder of case files.")]
RefDir = Annotated[Path, typer.Option("--references", help="Folder of reference solutions.")]
CaseArgs = Annotated[list[str] | None, typer.Argument(
    help="Case names (or paths to case files); default: every case.", show_default=False)]


def _fail(message: str, code: int = 2):
    err.print(f"[bold red]error:[/] {message}", highlight=False)
    raise typer.Exit(code)


def _cases(names: list[str] | None, cases_dir: Path):
    """Load the named cases (all when none); bad input exits 2 with file, field, reason."""
    try:
        if not names:
            files = sorted(Path(cases_dir).glob("*.toml"))
            if not files:
                _fail(f"{cases_dir}: no case files (*.toml)")
        else:
            files = []
            for n in names:
                p = Path(n) if n.endswith(".toml") else Path(cases_dir) / f"{n}.toml"
                if not p.exists():
                    known = ", ".join(sorted(f.stem for f in Path(cases_dir).glob("*.toml")))
                    _fail(f"unknown case {n!r}; cases are: {known}")
                files.append(p)
        cases = [load_case(f) for f in files]
    except CaseError as e:
        _fail(str(e))
    return [_prepared(case) for case in cases]


def _prepared(case):
    """Assemble a case once (the Job every run of it starts from). A mechanism that does
    not assemble is bad input too (exit 2), caught before running."""
    from .suite.runner import prepare

    job = prepare(case)
    if job.init is None:
        _fail(str(CaseError(case.file, "initial", job.assembly_error)))
    return job


def _engines(spec: str | None) -> list[str]:
    if not spec:
        return list(ENGINES)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    bad = [n for n in names if n not in ENGINES]
    if bad:
        _fail(f"--engines: unknown engine {bad[0]!r}; engines are {', '.join(ENGINES)}")
    return names


def _progress_printer(total: int):
    done = [0]
    style = {"ok": "green", "failed": "red", "unsupported": "yellow", "skipped": "dim"}
    verdict_style = {"pass": "green", "fail": "bold red"}

    def show(key: str, rec: dict):
        done[0] += 1
        status, verdict = rec.get("status", "?"), rec.get("verdict", "")
        cost = rec.get("us_per_step")
        cost = f"{cost:9.2f} us/step " if isinstance(cost, (int, float)) else " " * 17
        reason = rec.get("reason") or rec.get("verdict_reason") or ""
        out.print(Text.assemble(f"[{done[0]:>3}/{total}] {key:<30} ",
                                (f"{status:<12}", style.get(status, "")),
                                (f"{verdict:<10}", verdict_style.get(verdict, "")),
                                cost, (reason[:100], "dim")))
    return show


@app.command("cases")
def cases_cmd(cases_dir: CasesDir = Path("cases")):
    """List the cases with a one-line description and the engines that support each."""
    table = Table(title=f"cases in {cases_dir}")
    table.add_column("case")
    table.add_column("description")
    table.add_column("engines")
    for c in (job.case for job in _cases(None, cases_dir)):
        eng = [e if not c.engine(e).unsupported else f"[dim strike]{e}[/]" for e in ENGINES]
        table.add_row(c.name, c.description, " ".join(eng))
    out.print(table)


@app.command("run")
def run_cmd(cases: CaseArgs = None,
            engines: Annotated[str | None, typer.Option(help="Comma-separated engines.")] = None,
            out_dir: Annotated[Path, typer.Option("--out", help="Results folder.")] = DEFAULT_OUT,
            timeout: Annotated[float, typer.Option(help="Seconds per engine run.")] = 600.0,
            cases_dir: CasesDir = Path("cases"), references: RefDir = Path("references")):
    """Run cases in engines; write results/<case>/<engine>.csv and summary.json."""
    from .suite.runner import run_suite

    selected, names = _cases(cases, cases_dir), _engines(engines)
    total = len(selected) * len(names)
    out.print(f"running {len(selected)} case(s) x {len(names)} engine(s) -> {out_dir}")
    summary = run_suite(selected, names, out_dir, references=references, timeout_s=timeout,
                        progress=_progress_printer(total))
    n_ok = sum(r["status"] == "ok" for r in summary["records"])
    out.print(f"{n_ok}/{total} runs ok; summary: {out_dir / 'summary.json'}")


@app.command("report")
def report_cmd(results: Annotated[Path, typer.Option(help="Results folder.")] = DEFAULT_OUT,
               references: RefDir = Path("references")):
    """Write RESULTS/index.html from a results folder."""
    from .report.html import write_report

    if not (results / "summary.json").exists():
        _fail(f"{results}: no summary.json; run `natcoord run` first")
    path = write_report(results, references)
    out.print(f"report: {path.resolve()}")


@app.command("gate")
def gate_cmd(results: Annotated[Path, typer.Option(help="Results folder.")] = DEFAULT_OUT,
             require: Annotated[str | None, typer.Option(
                 help="Engines that must run (default: all that were asked for).")] = None,
             baseline: Annotated[Path, typer.Option(help="Stored baseline errors.")] = Path(
                 "references/baseline.json"),
             update_baseline: Annotated[bool, typer.Option(
                 help="Store this run's errors as the new baseline (after it passes).")] = False):
    """Compare results with tolerances and the stored baseline.

    Exit 0 when all hold, 1 on a regression, 2 on bad input, 3 when nothing ran or a
    required engine failed.
    """
    from .suite import gate

    try:
        summary = gate.load_summary(results)
        base = gate.load_baseline(baseline)
    except ValueError as e:
        _fail(str(e))
    required = set(_engines(require)) if require else None
    verdict = gate.judge(summary, required=required, baseline=base)
    for line in verdict.lines:
        err.print(f"[red]REGRESSION[/] {line}" if verdict.code == 1 else line, highlight=False)
    n = len(summary["records"])
    if verdict.code == 0:
        gated = sum(r["verdict"] == "pass" for r in summary["records"])
        out.print(f"[green]gate passed[/]: {gated} of {n} case x engine runs gated and within "
                  "tolerance" + ("" if base else " (no baseline stored)"))
        if update_baseline:
            gate.update_baseline(summary, baseline)
            out.print(f"baseline written: {baseline}")
    else:
        err.print(f"[bold red]gate failed[/] (exit {verdict.code})")
    raise typer.Exit(verdict.code)


@app.command("bench")
def bench_cmd(cases: CaseArgs = None,
              engines: Annotated[str | None, typer.Option(help="Comma-separated engines.")] = None,
              repeats: Annotated[int, typer.Option(min=1, help="Repeats (best is kept).")] = 3,
              out_dir: Annotated[Path, typer.Option("--out", help="Results folder.")] = DEFAULT_OUT,
              history: Annotated[Path, typer.Option(help="Where dated copies go.")] = Path(
                  "reports/bench"),
              work_precision: Annotated[bool, typer.Option(
                  help="Also sweep step sizes / tolerances: angle error against CPU time, "
                       "and the time each engine needs to reach 1e-6 and 1e-9 rad.")] = False,
              cases_dir: CasesDir = Path("cases"), references: RefDir = Path("references")):
    """Measure step cost per case x engine (best of repeats, single-threaded BLAS)."""
    from .suite import bench

    selected, names = _cases(cases, cases_dir), _engines(engines)
    total = len(selected) * len(names)
    out.print(f"benchmarking {total} case x engine pairs, best of {repeats}")
    result = bench.bench(selected, names, repeats=repeats, progress=_progress_printer(total))
    if work_precision:
        n = sum(len(bench.SWEEPS.get(e, [])) for e in names) * len(selected)
        out.print(f"work-precision: {n} runs")
        points = bench.work_precision(selected, names, references=references,
                                      progress=_progress_printer(n))
        result["work_precision"] = points
        result["time_to_accuracy"] = bench.time_to_accuracy(points)
        table = Table(title="CPU time (s) to reach an angle error")
        for col in ("case", "engine", *(f"<= {t:g} rad" for t in bench.TARGETS)):
            table.add_column(col)
        for row in result["time_to_accuracy"]:
            cells = [row[f"time_to_{t:g}"] for t in bench.TARGETS]
            table.add_row(row["case"], row["engine"],
                          *("not reached" if c is None else f"{c:.3g}" for c in cells))
        out.print(table)
    path = bench.store(result, out_dir, history)
    out.print(f"benchmark: {path}")


@app.command("suite")
def suite_cmd(engines: Annotated[str | None, typer.Option(help="Comma-separated engines.")] = None,
              out_dir: Annotated[Path, typer.Option("--out", help="Results folder.")] = DEFAULT_OUT,
              repeats: Annotated[int, typer.Option(min=0, help="Bench repeats (0: no bench).")] = 3,
              cases_dir: CasesDir = Path("cases"), references: RefDir = Path("references"),
              history: Annotated[Path, typer.Option(help="History file.")] = Path(
                  "reports/history.jsonl")):
    """The nightly job: run all, bench, report, gate, record history. Exits with the gate's
    code."""
    from .report.html import write_report
    from .suite import bench, gate
    from .suite import history as hist
    from .suite.runner import run_suite

    selected, names = _cases(None, cases_dir), _engines(engines)
    total = len(selected) * len(names)
    out.print(f"[bold]natcoord suite[/]: {len(selected)} cases x {len(names)} engines")
    summary = run_suite(selected, names, out_dir, references=references,
                        progress=_progress_printer(total))
    bench_result = None
    if repeats:
        out.print(f"[bold]bench[/]: best of {repeats}")
        bench_result = bench.bench(selected, names, repeats=repeats,
                                   progress=_progress_printer(total))
        bench.store(bench_result, out_dir, Path(history).parent / "bench")
    report = write_report(out_dir, references)
    try:
        base = gate.load_baseline(references / "baseline.json")
    except ValueError as e:
        _fail(str(e))
    verdict = gate.judge(summary, baseline=base)
    for line in verdict.lines:
        err.print(line, highlight=False)
    hist.append(history, hist.entry(summary, verdict.code, bench_result))
    out.print(f"report: {report.resolve()}")
    out.print("[green]gate passed[/]" if verdict.code == 0
              else f"[bold red]gate failed[/] (exit {verdict.code})")
    raise typer.Exit(verdict.code)


@reference_app.command("update")
def reference_update(cases: CaseArgs = None, cases_dir: CasesDir = Path("cases"),
                     references: RefDir = Path("references")):
    """Regenerate stored references (natcoord at tight tolerance), with provenance."""
    from .suite.references import update_reference

    for job in _cases(cases, cases_dir):
        case = job.case
        prov = update_reference(case, references, job.init)
        worst = max(prov["estimated_error"].values())
        out.print(f"{case.name}: reference written (estimated error <= {worst:.2g}, "
                  f"{prov['counters'].get('steps', '?')} steps)")


def main():  # pragma: no cover - console entry
    try:
        app()
    except NatcoordError as e:
        err.print(f"[bold red]error:[/] {e}", highlight=False)
        sys.exit(2)


if __name__ == "__main__":  # pragma: no cover
    main()
