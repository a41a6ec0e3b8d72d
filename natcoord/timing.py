"""How an engine times its stepping: once, or in a benchmark as calibrated batches.

A sub-millisecond run timed once is at the mercy of the scheduler: one preemption makes it
10x slower. In a benchmark (a bench worker calls :func:`configure`) :func:`timed` instead
takes ``samples`` timing samples, each a **calibrated batch**: the stepping repeated until
the batch lasts at least ``min_batch_s`` (as pyperf and timeit's autorange do), recorded as
its time per run (batch time / runs), in wall-clock and in CPU time of this process (which
time spent waiting for the core does not inflate). One discarded run comes first (warm-up),
unless that run alone took the whole budget: then it is the one sample.

Each sample is followed by :func:`reference_work`, a fixed amount of arithmetic whose time
says how fast the machine ran just then. A shared machine drifts between fast and slow
spells (a busy neighbour, a lower clock, a host taking the core) that slow every program
alike; the speed gate judges a sample relative to the reference measured beside it, so
such a spell does not read as a slowdown of the code.

``slowdown`` is a **test hook**: every timed run executes the stepping that many times, so
a benchmark test can inject a known, deterministic slowdown through the real timing path.
Outside a benchmark (the default policy) :func:`timed` runs the stepping once.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

T = TypeVar("T")

_REF_N, _REF_LOOPS = 24, 1000  # ~10 ms on a 2020s core
_REF_A = np.eye(_REF_N) * _REF_N + np.random.default_rng(0).random((_REF_N, _REF_N))
_REF_B = np.random.default_rng(1).random(_REF_N)


def reference_work() -> tuple[float, float]:
    """Wall and CPU time (s) of a fixed workload: 1000 dense solves of a 24 x 24 system,
    each from Python (interpreter, numpy dispatch and LAPACK, as an engine's step is).
    Its time measures the machine's speed at the moment, not the code under test."""
    w0, c0 = time.perf_counter(), time.process_time()
    x = _REF_B
    for _ in range(_REF_LOOPS):
        x = np.linalg.solve(_REF_A, x)
        x = x / np.abs(x).max()
    return time.perf_counter() - w0, time.process_time() - c0


@dataclass(frozen=True)
class Policy:
    """``samples`` batches of at least ``min_batch_s`` each (0: time one run, no batch),
    fewer when they would take more than ``budget_s`` (at least one); ``slowdown``:
    executions of the stepping per timed run (1; more only in tests)."""

    samples: int = 1
    min_batch_s: float = 0.0
    slowdown: int = 1
    budget_s: float = math.inf


@dataclass
class Timing:
    """Per-run wall and CPU time (s) of each sample, the runs in each batch, and the wall
    and CPU time (s) of the :func:`reference_work` measured after each sample."""

    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    runs: list[int] = field(default_factory=list)
    ref_wall_s: list[float] = field(default_factory=list)
    ref_cpu_s: list[float] = field(default_factory=list)

    def reference(self) -> None:
        """Measure the reference work once more (after a sample)."""
        wall, cpu = reference_work()
        self.ref_wall_s.append(wall)
        self.ref_cpu_s.append(cpu)

    @property
    def batched(self) -> bool:
        return bool(self.runs)

    def record(self) -> dict:
        """The fields of a bench record these samples give."""
        return {"samples_s": self.wall_s, "cpu_samples_s": self.cpu_s,
                "batch_runs": self.runs, "ref_samples_s": self.ref_wall_s,
                "ref_cpu_samples_s": self.ref_cpu_s}

    def counters(self) -> dict:
        """The counters an engine run reports when it timed calibrated batches ({} else)."""
        if not self.batched:
            return {}
        return {"batch_wall_s": self.wall_s, "batch_cpu_s": self.cpu_s,
                "batch_runs": self.runs, "batch_ref_wall_s": self.ref_wall_s,
                "batch_ref_cpu_s": self.ref_cpu_s}


_POLICY = Policy()


def configure(samples: int = 1, min_batch_s: float = 0.0, slowdown: int = 1,
              budget_s: float = math.inf) -> None:
    """Set this process's timing policy (a bench worker does, before running an engine)."""
    global _POLICY
    if samples < 1 or min_batch_s < 0 or slowdown < 1 or not budget_s > 0:
        raise ValueError(f"timing policy: samples {samples} >= 1, min_batch_s {min_batch_s}"
                         f" >= 0, slowdown {slowdown} >= 1 and budget_s {budget_s} > 0 "
                         "expected")
    _POLICY = Policy(int(samples), float(min_batch_s), int(slowdown), float(budget_s))


def policy() -> Policy:
    return _POLICY


def timed(step: Callable[[], T]) -> tuple[T, float, Timing]:
    """Run ``step`` (a whole stepping from the same start, re-runnable) under the policy:
    (its last result, wall time of one run in s, the batches' :class:`Timing`). Without
    batches the wall time is the one run's and the Timing is empty; with them it is the
    best sample's time per run."""
    pol = _POLICY
    if pol.min_batch_s <= 0 and pol.slowdown == 1:
        t0 = time.perf_counter()
        out = step()
        return out, time.perf_counter() - t0, Timing()
    w0, c0 = time.perf_counter(), time.process_time()
    out = step()  # warm-up, not timed ...
    warm = time.perf_counter() - w0
    timing = Timing()
    if pol.slowdown == 1 and warm >= max(pol.budget_s, pol.min_batch_s):
        # ... unless it alone took the budget: then it is the one sample (as for an engine
        # timed by whole runs, natcoord.suite.batches), not the first of two such runs
        timing.wall_s, timing.cpu_s, timing.runs = [warm], [time.process_time() - c0], [1]
        timing.reference()
        return out, warm, timing
    begin = time.perf_counter()
    for _ in range(pol.samples):
        done = len(timing.runs)
        if done and (time.perf_counter() - begin) * (done + 1) / done > pol.budget_s:
            break  # one more sample would overrun the budget
        runs = 0
        w0, c0 = time.perf_counter(), time.process_time()
        while True:
            for _ in range(pol.slowdown):
                out = step()
            runs += 1
            wall = time.perf_counter() - w0
            if wall >= pol.min_batch_s:
                break
        cpu = time.process_time() - c0
        timing.wall_s.append(wall / runs)
        timing.cpu_s.append(cpu / runs)
        timing.runs.append(runs)
        timing.reference()
    return out, min(timing.wall_s), timing
