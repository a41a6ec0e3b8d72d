"""natcoord's compiled loops made ready once before a suite's natcoord runs.

On a machine where numba has not cached them yet, each compiled loop takes 10-40 s to
compile (:mod:`natcoord.compiled.cache`); runs started together would each compile the
same loop. Instead, one process per group of loops compiles them (or, once cached, loads
them in about a second) at the start, while the other engines' runs go on
(:func:`natcoord.suite.parallel.local`), and natcoord's runs then load them from the cache.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

ENGINE = "natcoord"
# loops that share compiled callees are compiled in one process (a second process would
# compile those callees again); the groups run side by side
GROUPS = (("sparse", "generated"), ("general",), ("maggi",), ("index3",))
_OF_FORMULATION = {"index1": {"sparse", "generated", "general"}, "maggi": {"maggi"},
                   "index3": {"index3"}}


def paths(jobs: Sequence) -> set[str]:
    """The compiled loops that natcoord's runs of ``jobs`` (cases or prepared Jobs) may
    take, read from their settings (index1: its three paths, which one depends on the
    model; a case with ``compiled = false`` or natcoord unsupported: none)."""
    out: set[str] = set()
    for job in jobs:
        eng = getattr(job, "case", job).engine(ENGINE)
        settings = eng.settings
        if eng.unsupported or settings.get("compiled", True) is False:
            continue
        out |= _OF_FORMULATION.get(settings.get("formulation", "index1"), set())
    return out


def commands(jobs: Sequence) -> list[list[str]]:
    """One command per group of :data:`GROUPS` that ``jobs`` need: a process that compiles
    (or loads) those loops."""
    need = paths(jobs)
    out = []
    for group in GROUPS:
        mine = [p for p in group if p in need]
        if mine:
            out.append([sys.executable, "-P", "-c",
                        "from natcoord.compiled.cache import ensure_compiled; "
                        f"ensure_compiled(*{mine!r})"])
    return out
