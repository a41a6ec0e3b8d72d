"""Where the accuracy runs of a suite execute: here one at a time, here on N cores, or on a
Dask distributed cluster.

Every run is still one engine process with its own time limit
(:func:`natcoord.suite.runner.run_subprocess`). On a cluster the task runs that process on
the Dask worker, in a temporary folder of its own, and returns the files it wrote; they are
written here, on the machine that runs the command. A task that raises, or a worker lost
with the task, gives ``failed`` with the reason for that cell, never a hang: every result
is awaited at most the run's time limit plus a margin. Timing runs (``natcoord bench``)
never come here: they stay serial, one core at a time.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import queue
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from ..errors import NatcoordError
from .io import write_atomic

MARGIN_S = 120.0  # scheduling and start-up allowance on top of a run's own time limit


def cells(jobs, engines) -> list[tuple]:
    return [(job, engine) for job in jobs for engine in engines]


class Cores:
    """The cores the parallel runs are pinned to, one run per core, when there are at least
    as many cores as runs at a time (then each run's stepping time is its own core's: the
    suite takes it as the timing of a cell the bench does not measure, see
    :mod:`natcoord.suite.policy`); else no pinning (``one()`` gives None)."""

    def __init__(self, workers: int):
        mine = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        self.free = queue.SimpleQueue()
        self.pinned = 0 < workers <= len(mine)
        for cpu in mine[-workers:] if self.pinned else ():
            self.free.put(cpu)

    @contextlib.contextmanager
    def one(self):
        cpu = self.free.get() if self.pinned else None
        try:
            yield cpu
        finally:
            if cpu is not None:
                self.free.put(cpu)


def local(jobs, engines, out: Path, timeout_s: float, workers: int,
          first: dict | None = None, warmup: tuple | None = None,
          started: Callable[[int], None] | None = None) -> Iterator[tuple]:
    """Yield ``(index, record)`` as runs finish, ``workers`` engine processes at a time
    (never more threads than there is work for: one per run, and one for the preparing
    chain);
    ``first``: ``{(case, engine): seconds}`` expected, the longest started first (so that
    no long run is left to the end while the other cores idle; among equals, the largest
    case). ``warmup``: ``(chain, waits)`` of :func:`natcoord.suite.warm.plan`, processes
    that prepare compiled code (``[(item, command), ...]``, run one after another by one
    worker from the start) and, by cell index, the items a run waits for; the other runs go
    on meanwhile (so that no two runs compile the same loop). ``started(index)`` is called
    as a run gets its core (from a worker thread)."""
    from .runner import kill_all, run_subprocess

    todo = cells(jobs, engines)
    chain, waits = warmup or ([], {})
    workers = min(workers, len(todo) + bool(chain))  # an idle thread takes nothing
    if workers <= 1:
        for i, (job, engine) in enumerate(todo):
            if started:
                started(i)
            yield i, run_subprocess(job, engine, out, timeout_s)
        return
    board = _Board(_order(todo, first), chain, waits)
    cores = Cores(workers)
    done: queue.SimpleQueue = queue.SimpleQueue()

    def work():
        while (task := board.take()) is not None:
            kind, x = task
            try:
                with cores.one() as cpu:
                    if kind == "before":
                        for item, command in x:  # in order: each loads what the last made
                            _prepare(command, cpu, timeout_s)
                            board.ready(item)
                    else:
                        if started:
                            started(x)
                        done.put((x, run_subprocess(todo[x][0], todo[x][1], out, timeout_s,
                                                    cpu=cpu)))
            except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
                done.put((x if kind == "cell" else None, e))
            finally:
                board.finished(kind, x)

    threads = [threading.Thread(target=work, daemon=True) for _ in range(workers)]
    for t in threads:
        t.start()
    try:
        for _ in range(len(todo)):
            i, rec = done.get()
            if isinstance(rec, BaseException):
                raise rec
            yield i, rec
    except BaseException:  # an interruption: stop what waits, then what runs
        board.stop()
        kill_all()
        raise
    finally:
        board.stop()
        for t in threads:
            t.join()


def _order(todo: list[tuple], first: dict | None) -> list[int]:
    """Indices of ``todo`` ((job, engine) cells), the longest expected first."""
    return sorted(range(len(todo)), key=lambda i: (-(first or {}).get(
        (todo[i][0].case.name, todo[i][1]), 0.0), -_size(todo[i][0].case)))


def _size(case) -> float:
    """A run's size before any was measured (simulated seconds x bodies): among runs
    expected to take equally long (none measured on this machine), the largest start
    first."""
    return float(case.duration) * (1 + len(case.bodies))


class _Board:
    """The work of :func:`local`: the preparing chain first (one task: one worker runs its
    processes in order), then the runs in ``order``; a run with ``waits`` (its index ->
    items of the chain) only once those items are ready."""

    def __init__(self, order: list[int], chain: list[tuple], waits: dict[int, frozenset]):
        self.cond = threading.Condition()
        self.chain = list(chain)
        self.done: set = set()
        self.waits = {i: set(w) & {item for item, _ in chain} for i, w in waits.items()}
        self.order, self.stopped = list(order), False

    def take(self):
        """The next task, ``("before", chain)`` or ``("cell", index)``; None: no more."""
        with self.cond:
            while not self.stopped:
                if self.chain:
                    chain, self.chain = self.chain, []
                    return "before", chain
                for k, i in enumerate(self.order):
                    if self.waits.get(i, set()) <= self.done:
                        return "cell", self.order.pop(k)
                if not self.order:
                    return None
                self.cond.wait()
            return None

    def ready(self, item) -> None:
        """An item of the chain is ready (or failed: the runs then compile it themselves)."""
        with self.cond:
            self.done.add(item)
            self.cond.notify_all()

    def finished(self, kind: str, x) -> None:
        if kind == "before":  # every item, whatever became of it
            for item, _ in x:
                self.ready(item)

    def stop(self) -> None:
        with self.cond:
            self.stopped = True
            self.cond.notify_all()


def _prepare(command: list[str], cpu: int | None, timeout_s: float) -> None:
    """Run one preparing process; its failure only costs the runs the time it would have
    saved (each run still prepares what it needs itself)."""
    from .runner import run_command

    try:
        run_command(command, timeout_s, cpu)
    except Exception:  # noqa: BLE001 - a time limit, a stopping command, an OS error
        pass


def remote_run(job_bytes: bytes, engine: str, timeout_s: float) -> dict:
    """Runs on a Dask worker: one engine process in a temporary folder; returns the record
    and the text of every file the run wrote (relative path -> text)."""
    from .runner import run_subprocess

    job = pickle.loads(job_bytes)
    with tempfile.TemporaryDirectory(prefix="natcoord-dask-") as tmp:
        record = run_subprocess(job, engine, Path(tmp), timeout_s)
        files = {str(p.relative_to(tmp)): p.read_text(encoding="utf-8")
                 for p in Path(tmp).rglob("*") if p.is_file() and not p.name.startswith(".")}
    return {"record": record, "files": files}


def distributed(jobs, engines, out: Path, timeout_s: float, scheduler: str,
                failed: Callable[[object, str, str], dict], *, connect_s: float = 30.0,
                margin_s: float = MARGIN_S) -> Iterator[tuple]:
    """Yield ``(index, record)`` from a Dask cluster at ``scheduler`` (tcp://host:port);
    files are written under ``out`` here. A scheduler not reached, or without a worker,
    within ``connect_s`` is a NatcoordError. ``failed(case, engine, reason)`` makes the record
    of a run that the cluster lost."""
    try:
        from distributed import Client
        from distributed import TimeoutError as DaskTimeout
        from distributed import as_completed as dask_done
    except ImportError as e:
        raise NatcoordError("--scheduler needs Dask: pip install 'natcoord[cluster]'") from e
    from .runner import time_limit

    todo = cells(jobs, engines)
    longest = max(time_limit(job.case, timeout_s) for job, _ in todo) if todo else timeout_s
    try:
        client = Client(scheduler, timeout=connect_s)
    except ValueError as e:  # dask's address parsing: no port, an unknown scheme, ...
        raise NatcoordError(f"--scheduler {scheduler!r}: not a Dask scheduler address "
                            f"({e}); expected tcp://HOST:PORT") from None
    except (OSError, TimeoutError) as e:
        raise NatcoordError(f"--scheduler {scheduler}: cannot reach the Dask scheduler "
                            f"({type(e).__name__}: {e})") from None
    with client:
        try:  # a cluster without a worker would hold every run until the last deadline
            client.wait_for_workers(1, timeout=connect_s)
        except (DaskTimeout, TimeoutError):
            raise NatcoordError(f"--scheduler {scheduler}: the Dask scheduler has no worker "
                                f"(waited {connect_s:g} s); start one with `dask worker "
                                f"{scheduler}`") from None
        futures = {client.submit(remote_run, pickle.dumps(job), engine, timeout_s,
                                 pure=False, retries=0): i
                   for i, (job, engine) in enumerate(todo)}
        done = set()
        try:
            for f in dask_done(list(futures), timeout=longest * len(todo) + margin_s):
                i = futures[f]
                done.add(i)
                job, engine = todo[i]
                try:
                    res = f.result()
                except Exception as e:  # the task raised or its worker was lost
                    yield i, failed(job.case, engine, f"Dask worker: {type(e).__name__}: {e}")
                    continue
                for rel, text in res["files"].items():
                    write_atomic(Path(out) / rel, text)
                yield i, res["record"]
        except (DaskTimeout, TimeoutError):
            pass
        finally:
            client.cancel([f for f, i in futures.items() if i not in done])
        for i, (job, engine) in enumerate(todo):
            if i not in done:
                yield i, failed(job.case, engine, "the Dask cluster did not return this run "
                                "in time (a lost worker or scheduler)")
