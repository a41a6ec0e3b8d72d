"""Run one case in one engine, in its own process, and write its result files.

    python -m natcoord.suite.worker [--cwd DIR] JOB_FILE OUT_DIR

``JOB_FILE`` is a pickled :class:`Job` written by the runner: the case as loaded and
assembled once by the command (the worker neither reads the case file nor assembles it
again), the engine and its setting overrides. Writes
``OUT_DIR/results/<case>/<engine>.csv`` (when the run produced data) and
``OUT_DIR/results/<case>/<engine>.json`` (the run record), both atomically. The parent
process owns time limits and crashes: whatever this process does not write is reported by
the parent as ``failed``. The engine's capability rules are evaluated here first (a
plug-in's rules are its own code: an exception, a hang or an exit there fails this cell
alone); a fault in them fails the cell, a reason from them makes it ``unsupported``.
``JOB_FILE`` may instead hold an :class:`Assessment`: the rules of one engine on many
cases, for listing (``natcoord cases``), no run.

A bench job (``Job.batch_s`` > 0) takes ``repeat`` timing samples, each a calibrated batch
of at least ``batch_s`` of stepping, within ``budget_s`` (:mod:`natcoord.suite.batches`:
per-run wall times in the record's ``samples_s``, CPU times in ``cpu_samples_s`` where the
engine measures them, runs per batch in ``batch_runs``). It may ask for a cost fit
(``Job.truncate``): every sample then also times the same case over its first ``truncate``
fraction of samples, interleaved in this process, so that both durations see the same
machine load (their samples go to the record's ``short``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import pickle
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # single-threaded BLAS: timings comparable across engines

import numpy as np  # noqa: E402

from ..case.mechanism import FORCE_KINDS, Case  # noqa: E402
from ..engines import adapter  # noqa: E402
from ..engines.base import EngineRun, InitialState  # noqa: E402
from ..engines.capabilities import RulesError, why_not  # noqa: E402
from ..engines.schema import short  # noqa: E402
from ..errors import Unsupported  # noqa: E402
from ..outputs.result import Motion, Result, Status, evaluate_channels, methods_table  # noqa: E402
from . import batches  # noqa: E402
from .io import write_csv, write_json  # noqa: E402


def record_of(result: Result, sim_time_s: float) -> dict:
    """The JSON record of a run (comparison fields are added by the runner)."""
    return {
        "case": result.case, "engine": result.engine, "engine_version": result.engine_version,
        "status": str(result.status), "reason": result.reason,
        "wall_time_s": result.wall_time_s, "build_time_s": result.build_time_s,
        "n_steps": result.n_steps, "us_per_step": result.us_per_step,
        "sim_time_s": sim_time_s, "settings": result.settings, "counters": result.counters,
        "notes": result.notes, "samples_s": list(result.samples_s),
    }


@dataclass(frozen=True)
class Job:
    """One case x engine run: the loaded case, its assembled state at t = 0 (None with
    ``assembly_error`` when it does not assemble), the engine and setting overrides.
    ``repeat``: how many times to run it in this process (timing samples; the results are
    the last run's); with ``batch_s`` > 0 (a bench job) each sample is a calibrated batch
    of at least that many seconds, all of them within ``budget_s``. ``truncate``: a
    fraction in (0, 1) makes every sample also time the case cut to that fraction of its
    samples (the bench's cost fit); 0 does not."""

    case: Case
    init: InitialState | None
    engine: str
    settings: dict = field(default_factory=dict)
    assembly_error: str = ""
    assembly_note: str = ""  # what assembly changed of the file's poses (or "")
    repeat: int = 1
    truncate: float = 0.0
    batch_s: float = 0.0
    budget_s: float = math.inf


@dataclass(frozen=True)
class Assessment:
    """A job of an engine process that runs nothing: :func:`assess` ``engine`` on every
    case (its capability rules evaluated in this process, under the caller's time limit);
    ``main`` writes ``OUT_DIR/<engine>.assessed.json``, case name -> [status, reason]."""

    cases: tuple[Case, ...]
    engine: str


def truncated(case: Case, fraction: float) -> Case:
    """The same case over its first ``fraction`` of output intervals (at least one): same
    mechanism, start state, settings and output step, a shorter duration."""
    n = int(round(case.duration / case.output_dt))
    k = max(1, min(n, math.ceil(fraction * n)))
    return dataclasses.replace(case, duration=k * case.output_dt)


class BadReturn(Exception):
    """An engine's ``run`` returned something other than the :class:`EngineRun` its
    contract promises (the message says what): its cell fails, nothing of it is kept."""


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"{type(x).__name__} is not JSON")


def _table_problem(what: str, x) -> str:
    """Why ``x`` cannot be a record's table ``what`` (settings, counters): a dict with
    string keys whose values JSON can hold; "" when it can."""
    if not isinstance(x, dict):
        return f"{what} {short(x)} ({type(x).__name__}), not a dict"
    bad = [k for k in x if not isinstance(k, str)]
    if bad:
        return f"{what} with the key {short(bad[0])}, not a string"
    try:
        json.dumps(x, default=_json_default)
    except (TypeError, ValueError, RecursionError, OverflowError) as e:
        return f"{what} that JSON cannot hold ({e})"
    return ""


def _number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(
        x, (bool, np.bool_))


def _motion_problem(what: str, m, case: Case) -> str:
    """Why ``m`` is not a Motion at ``case``'s sample times; "" when it is."""
    if not isinstance(m, Motion):
        return f"{what} {short(m)} ({type(m).__name__}), not a natcoord Motion"
    try:
        t = np.asarray(m.t, dtype=float)
    except (TypeError, ValueError):
        return f"{what} with sample times {short(m.t)}, not numbers"
    want = case.times
    if t.shape != want.shape or not np.allclose(t, want, atol=1e-9):  # as the gate reads
        return (f"{what} with {t.size} samples at other times than the case's "
                f"{want.size} (t = {short(t.tolist(), 60)}; the case's start at "
                f"{want[0]:g} s, every {case.output_dt:g} s to {want[-1]:g} s)")
    return ""


def run_problem(run, case: Case) -> str:
    """Why ``run`` is not a valid :class:`EngineRun` of ``case``: what every later reader
    (the record, its CSV, the report, the gate) trusts of it; "" when it is valid."""
    if not isinstance(run, EngineRun):
        return f"{short(run)} ({type(run).__name__}), not a natcoord EngineRun"
    why = _motion_problem("a motion", run.motion, case)
    if why:
        return why
    for name in ("build_time_s", "wall_time_s"):
        x = getattr(run, name)
        if not _number(x) or not math.isfinite(x) or x < 0:
            return f"{name} = {short(x)}, not a finite number of seconds >= 0"
    if not isinstance(run.n_steps, (int, np.integer)) or isinstance(run.n_steps, bool) \
            or run.n_steps < 0:
        return f"n_steps = {short(run.n_steps)}, not a whole number >= 0"
    for name in ("settings", "counters"):
        why = _table_problem(name, getattr(run, name))
        if why:
            return why
    if not isinstance(run.notes, list) or not all(isinstance(n, str) for n in run.notes):
        return f"notes {short(run.notes)}, not a list of strings"
    if not isinstance(run.methods, dict):
        return f"methods {short(run.methods)}, not a dict"
    for k, m in run.methods.items():
        why = ((f"methods with the key {short(k)}, not a string" if not isinstance(k, str)
                else "") or _motion_problem(f"method {k!r}'s motion", m, case))
        if why:
            return why
    return ""


def check_run(out, case: Case) -> None:
    """BadReturn saying what is wrong when ``out`` is not a valid run of ``case``
    (:func:`run_problem`), instead of a run later code would trust; its step count made an
    int."""
    why = run_problem(out, case)
    if why:
        raise BadReturn(f"the engine's run returned {why}")
    if not isinstance(out.n_steps, int):
        out.n_steps = int(out.n_steps)


def cannot_run(case: Case, engine: str, settings: dict | None = None) -> str:
    """Why ``engine`` does not run ``case``, known in the command's own process before an
    engine process starts: the case file's ``unsupported``, else the engine's declared
    capabilities (:mod:`natcoord.engines.capabilities`), with the capability rules of a
    built-in engine. A plug-in's rules are its own code: they run in its engine process
    (:func:`assess`, under the run's time limit), never here. "" when it may run; "" too
    when the capabilities cannot be read here (the engine process then fails the cell
    with the reason)."""
    from ..engines import discover

    try:
        return why_not(case, engine, settings, rules=discover().builtin(engine))
    except Exception:  # a fault, not a reason: the engine process finds and reports it
        return ""


def assess(case: Case, engine: str, settings: dict | None = None) -> tuple[str, str]:
    """(status, reason) of ``engine`` on ``case`` before it runs, its capability rules
    included (in an engine process: a plug-in's rules are its code): ("", "") when it may
    run, ("unsupported", why) when it cannot, ("failed", what went wrong) when its
    declarations or rules fail (raise, return something other than a list of reasons).
    What the rules print goes to standard error."""
    try:
        with contextlib.redirect_stdout(sys.stderr):
            why = why_not(case, engine, settings)
    except RulesError as e:
        return str(Status.FAILED), str(e)
    except Exception as e:  # a declaration that cannot be read: the engine's fault
        return str(Status.FAILED), (f"the engine's capabilities could not be read: "
                                    f"{type(e).__name__}: {e}")
    return (str(Status.UNSUPPORTED), why) if why else ("", "")


def run_one(job: Job) -> Result:
    """Run a job in this process and return its Result (never raises for engine trouble:
    that becomes the status)."""
    return run_job(job)[0]


def run_job(job: Job) -> tuple[Result, dict]:
    """Run a job in this process: its Result (never raises for engine trouble: that becomes
    the status) and what a bench job adds to its record (else {}): ``cpu_samples_s``,
    ``batch_runs``, the reference work's ``ref_samples_s`` and ``ref_cpu_samples_s`` and,
    with ``truncate``, the truncated runs' ``short`` record
    ``{duration_s, samples_s, cpu_samples_s, batch_runs, n_steps, counters}``."""
    case, engine = job.case, job.engine
    spec = case.engine(engine)
    res = Result(case.name, engine)
    mod = adapter(engine)
    status, why = assess(case, engine, job.settings)
    if status:
        res.status, res.reason = Status(status), why
        return res, {}
    try:
        version = mod.version()
    except ImportError as e:
        res.status = Status.SKIPPED
        res.reason = f"package {mod.PACKAGE!r} is not installed ({e}); pip install {mod.PACKAGE}"
        return res, {}
    except Exception as e:  # the adapter's own bug: this cell fails, the suite goes on
        res.status = Status.FAILED
        res.reason = f"the engine's version() raised {type(e).__name__}: {e}"
        return res, {}
    if not isinstance(version, str):
        res.status = Status.FAILED
        res.reason = f"the engine's version() returned {short(version)}, not a string"
        return res, {}
    res.engine_version = version
    if job.init is None:
        res.status, res.reason = Status.FAILED, f"the case does not assemble: {job.assembly_error}"
        return res, {}
    settings = {**spec.settings, **job.settings}
    short_case = truncated(case, job.truncate) if 0 < job.truncate < 1 else None
    extra: dict = {}
    try:
        if job.batch_s > 0:  # the runs checked outside the timed batches (~50 us each)
            run, cut, full, part = batches.measure(
                mod.run, case, short_case, job.init, settings, engine=engine,
                samples=max(1, job.repeat), min_batch_s=job.batch_s, budget_s=job.budget_s,
                check=check_run)
            res.samples_s = full.wall_s
            extra = {k: v for k, v in full.record().items() if k != "samples_s"}
            if cut is not None:
                extra["short"] = {"duration_s": short_case.duration, "n_steps": cut.n_steps,
                                  "counters": cut.counters} | part.record()
        else:
            for _ in range(max(1, job.repeat)):  # every repeat a whole run
                run = mod.run(case, job.init, settings)
                check_run(run, case)
                res.samples_s.append(run.wall_time_s)
    except Unsupported as e:
        res.status, res.reason = Status.UNSUPPORTED, str(e)
        return res, {}
    except BadReturn as e:
        res.status, res.reason = Status.FAILED, str(e)
        res.samples_s = []
        return res, {}
    except Exception as e:  # an engine's failure must not take the suite down
        res.status = Status.FAILED
        res.reason = f"{type(e).__name__}: {e}"
        res.notes.append(traceback.format_exc(limit=4))
        return res, {}
    try:
        table = evaluate_channels(case, run.motion)
        methods = methods_table(case, run) if run.methods else None
    except Exception as e:  # a motion missing a body, arrays of the wrong shape, ...
        res.status = Status.FAILED
        res.reason = (f"the engine's motion does not give the case's channels: "
                      f"{type(e).__name__}: {e}")
        res.samples_s = []
        res.notes.append(traceback.format_exc(limit=4))
        return res, {}
    res.table, res.methods = table, methods
    res.build_time_s, res.n_steps = run.build_time_s, run.n_steps
    res.wall_time_s = min(res.samples_s) if res.samples_s else run.wall_time_s
    res.settings, res.counters = run.settings, run.counters
    res.notes = ([job.assembly_note] if job.assembly_note else []) + list(run.notes)
    motion = [c for c in case.channels if c.kind not in FORCE_KINDS]
    absent = [c.name for c in motion if c.kind in MAYBE_ABSENT
              and np.all(np.isnan(res.table[c.name]))]
    if absent:
        res.notes.append(f"not computed by {engine}: {', '.join(absent)}")
    bad = [c.name for c in motion
           if c.name not in absent and not np.all(np.isfinite(res.table[c.name]))]
    if bad:
        res.status = Status.FAILED
        first = int(np.argmax(~np.isfinite(res.table[bad[0]].to_numpy())))
        res.reason = (f"non-finite values in {', '.join(bad)} from t = "
                      f"{res.table['t'].iloc[first]:.4g} s (the engine diverged)")
    return res, extra


# kinds an engine may not compute: NaN throughout is "not reported" (judged so by the gate
# when gated), not a divergence that fails the run
MAYBE_ABSENT = ("acceleration", "angular_acceleration")


@contextlib.contextmanager
def scratch_cwd(folder: str | None = None):
    """Run an engine in a scratch folder as the current directory: what an engine or a
    plug-in writes there (a log, a dump) never lands in the folder the command was started
    from. ``folder``: one the caller made and removes however this process ends (the
    runner's, so that a process killed at its time limit leaves nothing behind); None: a
    temporary folder of its own, removed afterwards. A relative ``NATCOORD_CACHE_DIR``
    keeps meaning the command's folder."""
    import tempfile

    cache = os.environ.get("NATCOORD_CACHE_DIR")
    if cache:
        os.environ["NATCOORD_CACHE_DIR"] = os.path.abspath(cache)
    with (contextlib.nullcontext(folder) if folder else
          tempfile.TemporaryDirectory(prefix="natcoord-engine-")) as tmp, \
            contextlib.chdir(tmp):
        yield Path(tmp)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="natcoord.suite.worker")
    p.add_argument("job_file", help="pickled Job written by the runner")
    p.add_argument("out_dir")
    p.add_argument("--cwd", help="scratch folder to run in, made and removed by the caller "
                   "(default: a temporary folder of this process's own)")
    a = p.parse_args(argv)
    out_dir = Path(a.out_dir).resolve()
    with open(a.job_file, "rb") as f:
        job: Job | Assessment = pickle.load(f)
    with scratch_cwd(a.cwd):
        if isinstance(job, Assessment):
            write_json(out_dir / f"{job.engine}.assessed.json",
                       {c.name: list(assess(c, job.engine)) for c in job.cases})
            return 0
        res, extra = run_job(job)
    folder = out_dir / "results" / res.case
    if res.table is not None:
        write_csv(folder / f"{res.engine}.csv", res.table)
    if res.methods is not None:
        write_csv(folder / f"{res.engine}.methods.csv", res.methods)
    record = record_of(res, job.case.duration)
    if res.status == Status.OK:
        record |= extra
    write_json(folder / f"{res.engine}.json", record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
