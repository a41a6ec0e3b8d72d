"""Run cases in engines, each run in its own process with a time limit, and summarise.

A crash, hang or NaN in one engine becomes status ``failed`` with a reason; the rest of the
suite completes. ``summary.json`` is written last and atomically, and removed when a run
starts, so a gate never trusts a summary from an interrupted run. An interruption of this
process (Ctrl-C, SIGTERM, an error) kills the engine process it waits for, and an engine
process dies with this one (it is asked to on Linux), so no worker outlives the command.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import hashlib
import os
import pickle
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from .. import __version__
from ..case.mechanism import Case
from ..errors import NatcoordError
from ..outputs.channels import assembly_note, initial_body_states
from . import evidence, zygote
from .io import read_json, write_json
from .worker import Assessment, Job, cannot_run

DEFAULT_TIMEOUT_S = 600.0
ASSESS_TIMEOUT_S = 60.0  # a plug-in's capability rules on every case (natcoord cases)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """What the machine is; ``fingerprint`` names machines whose timings compare (CPU model
    and core count: speed history is only compared within one fingerprint)."""
    cpu, cores = _cpu_model(), os.cpu_count()
    return {"python": platform.python_version(), "platform": platform.platform(),
            "cpu": cpu, "cores": cores, "blas_threads": 1,
            "fingerprint": hashlib.sha256(f"{cpu}|{cores}".encode()).hexdigest()[:16]}


def prepare(case: Case) -> Job:
    """Assemble a case once: a Job template (engine left empty) that every run of the case
    starts from. A case that does not assemble keeps the reason instead of a state."""
    try:
        init = initial_body_states(case)
        return Job(case, init, "", assembly_note=assembly_note(case, init))
    except NatcoordError as e:
        return Job(case, None, "", assembly_error=str(e))


def as_job(case: Case | Job) -> Job:
    """A prepared Job as it is, or a loaded case assembled now."""
    return case if isinstance(case, Job) else prepare(case)


def time_limit(case: Case, timeout_s: float) -> float:
    """Seconds one run of ``case`` may take: the stricter of the command's limit and the
    case file's own ``timeout``."""
    return min(timeout_s, case.timeout) if case.timeout else timeout_s


WORKER = [sys.executable, "-P", "-m", "natcoord.suite.worker"]  # + the worker's arguments


def worker_command(job_file: Path, out: Path, scratch: str) -> tuple[list[str], dict]:
    """The engine process's command line and environment; it runs in the folder
    ``scratch``. ``-P`` keeps the current directory off the import path and PYTHONPATH
    starts with the folder of the natcoord this command runs, so the worker imports that
    natcoord (never a ``natcoord/`` folder where the command happens to be started)."""
    return [*WORKER, "--cwd", scratch, str(job_file), str(out)], worker_env()


def worker_env() -> dict:
    """An engine process's environment: this natcoord first on the import path, BLAS on
    one thread."""
    package_root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(filter(None, (package_root, os.environ.get("PYTHONPATH"))))
    return {**os.environ, "PYTHONPATH": path, "OPENBLAS_NUM_THREADS": "1",
            "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def run_subprocess(case: Case | Job, engine: str, out: Path, timeout_s: float,
                   settings: dict | None = None, repeat: int = 1,
                   cpu: int | None = None) -> dict:
    """Run one case x engine in a child process; return its record (status failed on a
    crash, a non-zero exit or the time limit). ``case`` may be a prepared Job (assembled
    once for all its engines). ``cpu``: pin the engine process to that core (timing)."""
    job = as_job(case)
    case = job.case
    why = cannot_run(case, engine, settings)
    if why:  # from the case file or the engine's capabilities: no engine process
        return {**_failed(case, engine, why), "status": "unsupported"}
    folder = out / "results" / case.name
    for suffix in (".csv", ".json"):
        (folder / f"{engine}{suffix}").unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    job_file = folder / f".{engine}.job.pkl"
    with open(job_file, "wb") as f:
        pickle.dump(dataclasses.replace(job, engine=engine, settings=dict(settings or {}),
                                        repeat=repeat), f)
    timeout_s = time_limit(case, timeout_s) * max(1, repeat)
    t0 = time.perf_counter()
    try:
        returncode, err = run_worker(job_file, out, timeout_s, cpu)
    except subprocess.TimeoutExpired:
        return _failed(case, engine, f"timed out after {timeout_s:g} s (killed)")
    except _Stopping:
        return _failed(case, engine, "not started: the command is stopping")
    finally:
        job_file.unlink(missing_ok=True)
    record_file = folder / f"{engine}.json"
    if returncode != 0 or not record_file.exists():
        if returncode and returncode < 0:
            why = f"engine process killed by signal {signal.Signals(-returncode).name}"
        else:
            why = f"engine process exited with status {returncode}" + (
                " without writing its record" if returncode == 0 else "")
        tail = "\n".join((err or "").strip().splitlines()[-3:])
        return _failed(case, engine, f"{why}{': ' + tail if tail else ''}")
    record = read_json(record_file)
    record["process_time_s"] = time.perf_counter() - t0
    return record


def assessed(cases: Sequence[Case], engines: Sequence[str],
             timeout_s: float = ASSESS_TIMEOUT_S) -> dict[tuple[str, str], str]:
    """(case name, engine) -> why the engine cannot run the case ("" when it can), as
    listed by ``natcoord cases``: a built-in engine's :func:`~natcoord.suite.worker.assess`
    here, a plug-in's :func:`cannot_run` here and its capability rules in an engine process
    of its own (one per plug-in, every case, within ``timeout_s``: a rule that raises,
    hangs, exits or prints does so there). A fault of the rules is given as the reason,
    prefixed "failed: " (a run of that cell fails)."""
    from ..engines import adapter, discover
    from .worker import assess

    def listed(status: str, why: str) -> str:
        return f"failed: {why}" if status == "failed" else why

    reg = discover()
    out = {(c.name, e): (listed(*assess(c, e)) if reg.builtin(e) else cannot_run(c, e))
           for c in cases for e in engines}
    for e in engines:
        todo = [c for c in cases if not out[c.name, e]]
        if reg.builtin(e) or not todo or adapter(e).CAPABILITIES.rules is None:
            continue
        for name, answer in _assess(todo, e, timeout_s).items():
            out[name, e] = listed(*answer)
    return out


def _assess(cases: list[Case], engine: str, timeout_s: float) -> dict[str, tuple[str, str]]:
    """case name -> (status, reason) of :func:`natcoord.suite.worker.assess` of ``engine``,
    evaluated in an engine process; every case failed with the reason when that process
    does not finish, or finishes without its answer."""
    with tempfile.TemporaryDirectory(prefix="natcoord-assess-") as tmp:
        job_file = Path(tmp) / "assess.pkl"
        with open(job_file, "wb") as f:
            pickle.dump(Assessment(tuple(cases), engine), f)
        answer = Path(tmp) / f"{engine}.assessed.json"
        got = None
        try:
            returncode, err = run_worker(job_file, Path(tmp), timeout_s)
        except subprocess.TimeoutExpired:
            why = f"the engine's capability rules did not finish within {timeout_s:g} s"
        except _Stopping:
            why = "not evaluated: the command is stopping"
        else:
            tail = "\n".join((err or "").strip().splitlines()[-3:])
            why = ("the engine process evaluating its capability rules "
                   + (f"was killed by signal {signal.Signals(-returncode).name}"
                      if returncode < 0 else f"exited with status {returncode}"
                      + (" without its answer" if returncode == 0 else ""))
                   + (f": {tail}" if tail else ""))
            if returncode == 0 and answer.is_file():
                with contextlib.suppress(NatcoordError):
                    got = read_json(answer)
    if not isinstance(got, dict):
        return {c.name: ("failed", why) for c in cases}
    return {c.name: (tuple(a) if isinstance(a := got.get(c.name), list) and len(a) == 2
                     and all(isinstance(x, str) for x in a)
                     else ("failed", "no answer from the engine process"))
            for c in cases}


def run_worker(job_file: Path, out: Path, timeout_s: float,
               cpu: int | None = None) -> tuple[int, str]:
    """Run the engine process of ``job_file`` (:func:`worker_command`), forked from the
    fork server (:mod:`natcoord.suite.zygote`) where it serves, else a fresh interpreter;
    as :func:`run_command`: (exit status, standard error), subprocess.TimeoutExpired after
    ``timeout_s``, killed with the command."""
    if _STOPPING.is_set():
        raise _Stopping
    # its current directory, and its standard error's file when forked: removed here
    # however it ends (killed at the time limit)
    with tempfile.TemporaryDirectory(prefix="natcoord-engine-",
                                     ignore_cleanup_errors=True) as scratch:
        cmd, env = worker_command(job_file, out, scratch)
        if not zygote.usable(env):
            return run_command(cmd, timeout_s, cpu, env)
        err_path = os.path.join(scratch, ".natcoord-worker.err")
        open(err_path, "x").close()  # the fork writes to it only while it exists
        proc = zygote.Forked(cmd[len(WORKER):], err_path, cpu)
        _supervised(proc, lambda: proc.wait(timeout_s))
        with open(err_path, errors="replace") as f:
            return proc.returncode, f.read()


class _Stopping(Exception):
    """The command is stopping (:func:`kill_all`): no new process starts."""


def _supervised(proc, wait: Callable):
    """``wait()`` for the engine process ``proc`` (a Popen or a fork), listed among the
    command's live processes meanwhile (:func:`kill_all`) and SIGKILLed on anything that
    ends the wait early: the time limit, Ctrl-C, SIGTERM (see natcoord.cli), an error."""
    _LIVE.add(proc)
    if _STOPPING.is_set():  # stopped while it started
        _kill(proc)
    try:
        return wait()
    except BaseException:  # no orphan worker
        _kill(proc)
        raise
    finally:
        _LIVE.discard(proc)


def run_command(cmd: list[str], timeout_s: float, cpu: int | None = None,
                env: dict | None = None) -> tuple[int, str]:
    """Run a child process of this command (killed with it, by :func:`kill_all`, or after
    ``timeout_s``: subprocess.TimeoutExpired); ``cpu``: pin it to that core. Returns its
    exit status and standard error. The environment defaults to an engine process's."""
    if env is None:
        env = worker_env()
    if _STOPPING.is_set():
        raise _Stopping
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, start_new_session=True,
                            preexec_fn=lambda: _die_with_parent(cpu))

    def wait():
        try:
            return proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill(proc)
            proc.communicate()  # its pipes drained and closed
            raise

    _, err = _supervised(proc, wait)
    return proc.returncode, err or ""


def _die_with_parent(cpu: int | None = None) -> None:  # pragma: no cover - in the child
    """Ask Linux to SIGKILL this child when its parent dies (even by SIGKILL); pin it to
    core ``cpu`` when given."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {cpu})
        except OSError:
            pass


_LIVE: set[subprocess.Popen] = set()  # engine processes running now (any thread)
_STOPPING = threading.Event()  # set by kill_all: no new engine process starts


def kill_all() -> None:
    """SIGKILL every engine process this command runs, and start no more (parallel runs
    wait in threads that an interruption of the main thread does not reach)."""
    _STOPPING.set()
    for proc in list(_LIVE):
        _kill(proc)


def _kill(proc: subprocess.Popen) -> None:
    """SIGKILL the worker's process group; it may already be gone."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):  # gone, or a fork not yet in its group
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(proc.pid, signal.SIGKILL)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:  # pragma: no cover - the kernel reaps it
        pass


def _failed(case: Case, engine: str, reason: str) -> dict:
    return {"case": case.name, "engine": engine, "engine_version": "", "status": "failed",
            "reason": reason, "wall_time_s": None, "build_time_s": None, "n_steps": 0,
            "us_per_step": None, "sim_time_s": case.duration, "settings": {},
            "counters": {}, "notes": []}


def compare_record(case: Case, record: dict, out: Path, references: Path) -> dict:
    """Add the comparison with the reference to a run record, and the evidence a gate
    checks it by: the sha256 of each result file (``files``), the case file's sha256
    (``case_hash``). The errors come from :func:`natcoord.suite.evidence.judge_cell`, the
    function ``gate`` and ``compare`` judge the files with."""
    record = {**record, "description": case.description, "case_hash": case.digest,
              "tolerance_reason": case.engine(record["engine"]).reason}
    if record["status"] != "ok":
        return {**record, "channels": {}, "verdict": "n/a"}
    try:
        files = evidence.hashes(out, case.name, record["engine"])
        judged = evidence.judge_cell(case, record["engine"], out, references, files)
    except evidence.BadReference as e:  # the run is fine; its reference cannot judge it
        return {**record, "files": files, "channels": {}, "verdict": "no-reference",
                "verdict_reason": str(e)}
    except (OSError, evidence.BadEvidence) as e:
        # one unreadable result fails its own cell, never the whole run
        return {**record, "status": "failed", "channels": {}, "verdict": "n/a",
                "reason": f"results of this run could not be compared: {e}"}
    if case.benchmark:  # the IFToMM-style score's error (natcoord.suite.bench.scoring)
        from .bench import benchmark_error
        record["benchmark_error"] = benchmark_error(
            case, out / "results" / case.name / f"{record['engine']}.csv", references)
    return {**record, "files": files, **judged}


def run_suite(cases: Sequence[Case | Job], engines: Sequence[str], out: Path, *,
              references: Path = Path("references"), timeout_s: float = DEFAULT_TIMEOUT_S,
              progress: Callable[[str, dict], None] | None = None, jobs: int = 1,
              scheduler: str | None = None, first: dict | None = None,
              started: Callable[[str], None] | None = None) -> dict:
    """Run every case in every engine and write ``out/summary.json``; returns the summary.
    ``cases`` may be loaded cases or prepared Jobs (assembled once by the caller); ``jobs``
    engine processes run at once here, or every run goes to the Dask cluster at
    ``scheduler`` (see :mod:`natcoord.suite.parallel`; ``first``: expected seconds per
    (case, engine), the longest started first here; ``started("case/engine")`` as a run
    starts here). Records keep the order of the cells whatever order they finish in."""
    from . import parallel, warm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").unlink(missing_ok=True)
    prepared = [as_job(c) for c in cases]
    todo = parallel.cells(prepared, engines)
    found: dict[int, dict] = {}
    warmup = warm.plan(prepared, engines) if jobs > 1 and not scheduler else None
    runs = (parallel.distributed(prepared, engines, out, timeout_s, scheduler, _failed)
            if scheduler else parallel.local(
                prepared, engines, out, timeout_s, jobs, first, warmup,
                started and (lambda i: started(f"{todo[i][0].case.name}/{todo[i][1]}"))))
    for i, raw in runs:
        case, engine = todo[i][0].case, todo[i][1]
        found[i] = compare_record(case, raw, out, references)
        if progress:
            progress(f"{case.name}/{engine}", found[i])
    records = [found[i] for i in range(len(todo))]
    summary = {"generated": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
               "natcoord_version": __version__, "machine": machine_info(),
               "cases": [j.case.name for j in prepared], "engines": list(engines),
               "records": records}
    write_json(out / "summary.json", summary)
    return summary
