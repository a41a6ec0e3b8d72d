"""A bench cell's timing samples, each a calibrated batch (in the bench worker's process).

An engine that times its stepping through :mod:`natcoord.timing` (natcoord's own) repeats
the stepping inside one run: its run reports ``samples`` batches of at least
``min_batch_s`` each, in wall and CPU time per run. Any other engine is timed by whole
runs: the first run is the warm-up and calibrates how many runs make a batch of at least
``min_batch_s`` of stepping; each sample is then the engine's stepping time per run over
such a batch (wall time only). A cell's timed runs stay within ``budget_s`` of process time
(fewer runs per batch first, then fewer samples; at least one sample: the warm-up itself
when even one more run would exceed the budget). Build time never enters a sample.

Test hook: ``NATCOORD_BENCH_SLOWDOWN=ENGINE=K[,ENGINE=K]`` makes every timed run of that
engine's bench cells execute K times (natcoord repeats its stepping K times; another engine
its whole run, the stepping times summed): a deterministic K-fold slowdown through the real
timing path, read only here, for tests of the speed gate. Never set it for a real benchmark.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable

from .. import timing

SLOWDOWN_ENV = "NATCOORD_BENCH_SLOWDOWN"
BATCH_KEYS = ("batch_wall_s", "batch_cpu_s", "batch_runs", "batch_ref_wall_s",
              "batch_ref_cpu_s")


def slowdown(engine: str, env: str | None = None) -> int:
    """The injected slowdown factor of ``engine`` from ``$NATCOORD_BENCH_SLOWDOWN`` (1: none);
    ValueError on a malformed value."""
    text = os.environ.get(SLOWDOWN_ENV, "") if env is None else env
    out = 1
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, k = part.partition("=")
        if not sep or not k.strip().isdigit() or int(k) < 1:
            raise ValueError(f"{SLOWDOWN_ENV}: {part!r}: ENGINE=K with an integer K >= 1 "
                             "expected")
        if name.strip() == engine:
            out = int(k)
    return out


Samples = timing.Timing  # one duration's timing samples, in wall and CPU time, and the
# reference work after each: an engine that times itself and one timed here fill the same


def _of_run(run) -> Samples | None:
    """The batches an engine run timed itself (None when it timed one run); their keys are
    taken out of its counters."""
    got = [run.counters.pop(k, None) for k in BATCH_KEYS]
    return None if got[0] is None else Samples(*(g or [] for g in got))


def measure(run_fn: Callable, case, short_case, init, settings: dict, *, engine: str,
            samples: int, min_batch_s: float, budget_s: float,
            check: Callable = lambda run, case: None):
    """Run ``case`` (and ``short_case``, the cost fit's shorter run, when given) in this
    process and time them: (last run, last short run or None, full Samples, short Samples
    or None). ``check(run, case)`` sees the warm-up runs and the last ones (it may raise),
    never a timed one: its cost stays out of the samples."""
    k = slowdown(engine)
    timing.configure(samples=samples, min_batch_s=min_batch_s, slowdown=k,
                     budget_s=budget_s)
    try:
        t0 = time.perf_counter()
        run = run_fn(case, init, settings)
        t1 = time.perf_counter()
        cut = run_fn(short_case, init, settings) if short_case is not None else None
        costs = (t1 - t0, time.perf_counter() - t1)  # whole runs, build time included
    finally:
        timing.configure()
    check(run, case)
    if cut is not None:
        check(cut, short_case)
    full, short = _of_run(run), (_of_run(cut) if cut is not None else None)
    if full is not None:
        return run, cut, full, short
    # timed by whole runs: the runs above were the warm-up; runs per batch (full, short)
    m = [math.ceil(min_batch_s / max(r.wall_time_s, 1e-9)) if r is not None else 0
         for r in (run, cut)]

    def cost() -> float:  # process time of one sample
        return k * (m[0] * costs[0] + m[1] * costs[1])

    if samples * cost() > budget_s:  # fewer runs per batch first
        f = budget_s / (samples * cost())
        m = [max(1, math.floor(x * f + 1e-9)) if x else 0 for x in m]
    n = min(samples, math.floor(budget_s / cost() + 1e-9))
    full, short = Samples(), (Samples() if cut is not None else None)
    if n == 0:  # a long run: the warm-up is the one sample
        full.wall_s, full.runs = [run.wall_time_s], [1]
        full.reference()
        if cut is not None:
            short.wall_s, short.runs = [cut.wall_time_s], [1]
        return run, cut, full, short
    for _ in range(n):  # full and short batches interleaved: both under the same load
        run, wall = _batch(run_fn, case, init, settings, m[0], k)
        full.wall_s.append(wall)
        full.runs.append(m[0])
        full.reference()
        if cut is not None:
            cut, wall = _batch(run_fn, short_case, init, settings, m[1], k)
            short.wall_s.append(wall)
            short.runs.append(m[1])
    check(run, case)
    if cut is not None:
        check(cut, short_case)
    return run, cut, full, short


def _batch(run_fn, case, init, settings, m: int, k: int):
    """(last run, stepping time per run) of ``m`` runs, each executed ``k`` times."""
    total, run = 0.0, None
    for _ in range(m):
        for _ in range(k):
            run = run_fn(case, init, settings)
            total += run.wall_time_s
    return run, total / m
