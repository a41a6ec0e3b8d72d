"""natcoord's compiled code made ready before a suite's natcoord runs, only what they use.

On a machine where numba has not cached them yet, each compiled loop takes 10-50 s of
process time to compile (:mod:`natcoord.compiled.cache`); runs started together would each
compile the same loop. Instead, the loops that two or more of the suite's natcoord runs take
(read from each case's settings and model: :func:`needs`) are compiled (or, once cached,
loaded in about a second) one after another, one process each, by one worker at the start
(:func:`natcoord.suite.parallel.local`), while the other cores run the other engines and the
natcoord runs that need no compiled loop. A natcoord run starts once the loops it takes are
ready; a loop only one run takes is compiled in that run (after the warmed ones, whose
shared callees it then loads from the cache).
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Sequence

ENGINE = "natcoord"
# the order of the warm-up chain: the loop most runs take first; later loops load the
# callees the earlier ones compiled
ORDER = ("generated", "outputs", "sparse", "general", "maggi", "index3")


def needs(job) -> frozenset[str]:
    """The compiled code (keys of :data:`natcoord.compiled.cache.WARM_UP`) that natcoord's
    run of ``job`` (a prepared Job) takes, decided from the case's settings and model as the
    run decides, nothing compiled; empty when it runs no compiled loop (``compiled =
    false``, an integrator or model the loops do not serve, natcoord unsupported) or the
    model cannot be built (the run reports that itself)."""
    from ..dynamics.common import Counters
    from ..dynamics.formulations import FORMULATIONS
    from ..dynamics.solver import case_solver
    from ..model import casemodel

    case = job.case
    spec = case.engine(ENGINE)
    if spec.unsupported or job.init is None:
        return frozenset()
    settings = {**spec.settings, **getattr(job, "settings", {})}
    try:
        solver = case_solver(settings)
        coordinates = settings.get("coordinates", "joints")
        cm = casemodel.build(case, coordinates)
        q0 = (job.init.q if job.init.coordinates == coordinates
              else casemodel.initial_state(cm).q)
        form = FORMULATIONS[solver.formulation.name].loop(
            cm.model, solver.formulation.options(), Counters())
        if not form.compiled_candidate(solver.method, solver.h):
            return frozenset()
        return frozenset(form.compiled_needs(q0))
    except Exception:  # noqa: BLE001 - the run itself reports what is wrong with the case
        return frozenset()


def command(item: str) -> list[str]:
    """A process that compiles (or loads) one key of ``WARM_UP``."""
    return [sys.executable, "-P", "-c", "from natcoord.compiled.cache import ensure_compiled; "
            f"ensure_compiled({item!r})"]


def plan(jobs: Sequence, engines: Sequence[str]) -> tuple[list[tuple[str, list[str]]],
                                                          dict[int, frozenset[str]]]:
    """The warm-up of a suite of ``jobs`` x ``engines``: the chain ``[(item, command),
    ...]`` (in :data:`ORDER`, the items two or more natcoord runs take) and, by cell index
    (:func:`natcoord.suite.parallel.cells`), what each natcoord run waits for: its own items,
    or every warmed one when it compiles an item of its own."""
    if ENGINE not in engines:
        return [], {}
    from .parallel import cells

    need = {id(job): needs(job) for job in jobs}
    count = Counter(item for items in need.values() for item in items)
    chain = [p for p in ORDER if count[p] >= 2]
    waits = {}
    for i, (job, engine) in enumerate(cells(jobs, engines)):
        items = need[id(job)] if engine == ENGINE else frozenset()
        if items and chain:
            waits[i] = frozenset(chain) if items - set(chain) else items
    return [(p, command(p)) for p in chain], waits
