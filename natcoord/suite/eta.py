"""The suite's time-left estimate, from the durations of earlier suites on this machine.

Every piece of work (an accuracy run, a bench cell, a work-precision point, natcoord's cold
start) is expected to take what the same piece took last time (its engine process's time,
s; the accuracy runs shared over ``jobs`` cores; the cold start's fresh processes' wall
time), a piece never seen as long as the median of the same engine's pieces of that kind
(else of every piece of that kind, else :data:`UNKNOWN_S`). The time
left is the expected time of what is left, scaled by tonight's pace, fully so once a tenth
of the work is done. A piece that is running counts as done for the time it has run (up to
its expectation; its core's share of it in the parallel phase). The pace is the geometric
mean of two ratios to the expectation: the finished pieces' measured process times (blind
to waiting: start-up, a core shared with other work) and the wall clock since the start
against the work done, running pieces' part included (without it, a long run in progress
made the first estimates 1.5x the truth).
Replayed on two recorded nights of the full suite on a 2-core machine, the mean kept the
estimate within 0.8-1.2x of the truth from a tenth of the suite to nine tenths, where the
measured times alone fell to 0.69x. Bench and sweep pieces within the night's budget share
what is left of it (:meth:`Eta.budget`): once the bench has spent it, other engines' sweeps
are no longer expected.

A machine with no suite of its own yet expects the durations of a reference suite
shipped with the cases (:func:`prior`: ``references/durations.json``, measured on a fresh
clone of a 2-core machine, first night: numba compiling included), scaled by tonight's pace
like any other expectation; ``python -m natcoord.suite.eta RESULTS_DIR`` writes that file
from a full suite's folder (:func:`main`).
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Iterable
from pathlib import Path

from .io import read_json, write_json
from .stored import carried

UNKNOWN_S = 5.0  # a piece of a kind never measured on this machine
RUN, BENCH, SWEEP, COLD = "run", "bench", "sweep", "cold"
COLD_START = (COLD, "", "natcoord")  # the bench's cold start of natcoord: its fresh
# processes, one piece (wall seconds of all of them)


def durations(summary: dict | None, bench: dict | None) -> dict[tuple, float]:
    """``{(kind, case, engine): seconds}`` from a suite's summary.json and bench.json (a
    sweep: the sum of its points; the cold start, :data:`COLD_START`: the sum of its
    processes' wall times)."""
    out: dict[tuple, float] = {}
    for kind, records in ((RUN, (summary or {}).get("records", [])),
                          (BENCH, (bench or {}).get("records", []))):
        for r in records:
            t = r.get("process_time_s")
            if isinstance(t, (int, float)) and not carried(r):
                out[(kind, r.get("case"), r.get("engine"))] = float(t)
    for p in (bench or {}).get("work_precision", []):
        t = p.get("process_time_s")
        if isinstance(t, (int, float)) and not carried(p):
            key = (SWEEP, p.get("case"), p.get("engine"))
            out[key] = out.get(key, 0.0) + float(t)
    if (cold := cold_start_s(bench)) is not None:
        out[COLD_START] = cold
    return out


def cold_start_s(bench: dict | None) -> float | None:
    """Seconds natcoord's cold start took in a bench result (its processes' wall times
    summed: they run one after another), or None when it did not run or failed."""
    cold = (bench or {}).get("cold_start") or {}
    if cold.get("status") == "ok" and cold.get("samples_s"):
        return float(sum(cold["samples_s"]))
    return None


PRIOR = "durations.json"  # in the references folder: a reference suite's durations


def prior(references: Path) -> dict[tuple, float]:
    """``{(kind, case, engine): seconds}`` of the reference suite shipped in
    ``references`` (:data:`PRIOR`); {} when there is none or it is unreadable (an estimate
    is no reason to stop a suite)."""
    try:
        data = read_json(Path(references) / PRIOR)
        return {(d["kind"], d["case"], d["engine"]): float(d["process_time_s"])
                for d in data["durations"]
                if isinstance(d.get("process_time_s"), (int, float))
                and d["process_time_s"] >= 0}
    except Exception:  # noqa: BLE001 - missing, malformed, unreadable: no prior
        return {}


def known(summary: dict | None, bench: dict | None, references: Path) -> tuple[dict, str]:
    """The durations a suite expects its pieces to take and where they come from: this
    machine's last suite (:func:`durations`, "earlier"), else the reference suite shipped
    in ``references`` (:func:`prior`, "reference"), else none ("")."""
    if mine := durations(summary, bench):
        return mine, "earlier"
    shipped = prior(references)
    return shipped, "reference" if shipped else ""


def write_prior(results: Path, references: Path) -> Path:
    """Write :data:`PRIOR` in ``references`` from the suite folder ``results``
    (summary.json, bench.json), with where and when it was measured; returns its path."""
    results = Path(results)
    summary = read_json(results / "summary.json")
    bench = read_json(results / "bench.json") if (results / "bench.json").is_file() else None
    known = durations(summary, bench)
    out = Path(references) / PRIOR
    write_json(out, {
        "about": "process seconds of each piece of one suite, the time-left estimate's and "
                 "the scheduler's expectation on a machine with no suite of its own yet",
        "measured": {"suite": results.name, "generated": summary.get("generated"),
                     "natcoord": summary.get("natcoord_version"),
                     "machine": summary.get("machine")},
        "durations": [{"kind": k, "case": c, "engine": e, "process_time_s": round(t, 3)}
                      for (k, c, e), t in sorted(known.items())]})
    return out


def expect(pieces: Iterable[tuple], known: dict[tuple, float]) -> dict[tuple, float]:
    """Each piece ``(kind, case, engine)``'s expected seconds (see the module's rule)."""
    by_engine: dict[tuple, list] = {}
    by_kind: dict[str, list] = {}
    for (kind, _, engine), t in known.items():
        by_engine.setdefault((kind, engine), []).append(t)
        by_kind.setdefault(kind, []).append(t)
    out = {}
    for p in pieces:
        kind, _, engine = p
        similar = by_engine.get((kind, engine)) or by_kind.get(kind)
        out[p] = known.get(p, statistics.median(similar) if similar else UNKNOWN_S)
    return out


def cap(expected: dict[tuple, float], cells: set[tuple], seconds: float
        ) -> dict[tuple, float]:
    """``expected`` with the bench and sweep pieces of ``cells`` ((case, engine)) scaled
    to take ``seconds`` together at most (the night's bench budget)."""
    mine = [k for k in expected if k[0] in (BENCH, SWEEP) and (k[1], k[2]) in cells]
    total = sum(expected[k] for k in mine)
    f = min(1.0, seconds / total) if total > 0 else 1.0
    return {k: t * f if k in mine else t for k, t in expected.items()}


class Eta:
    """Time left of a suite: ``expected`` seconds per piece (wall time: a parallel piece
    already divided by the cores it shares); :meth:`done` as pieces finish, with the
    seconds each took where measured (on the same footing as its expectation)."""

    def __init__(self, expected: dict[tuple, float], clock=time.monotonic):
        self.expected, self.clock = dict(expected), clock
        self.start, self.finished = clock(), set()
        self.took: dict[tuple, float] = {}  # finished pieces' measured seconds
        self.begun: dict[tuple, tuple[float, int]] = {}  # running: (start, cores shared)
        self.budgeted: set[tuple] = set()  # (case, engine) of the night's budget
        self.budget_s = math.inf

    def add(self, expected: dict[tuple, float]) -> None:
        """More pieces (a later phase whose pieces are known only now)."""
        self.expected.update(expected)

    def budget(self, cells: set[tuple], seconds: float) -> None:
        """The bench and sweep pieces of ``cells`` ((case, engine)) share a budget of
        ``seconds`` of measured time: what is left of them is expected to take what is left
        of it (their own expectations scaled down to fit)."""
        self.budgeted, self.budget_s = set(cells), float(seconds)

    def started(self, piece: tuple, shared: int = 1) -> None:
        """``piece`` started now, on one of the ``shared`` cores its expectation is divided
        over (an accuracy run: the suite's jobs; a bench piece: 1)."""
        self.begun[piece] = (self.clock(), max(1, int(shared)))

    def _running(self, expected: dict[tuple, float]) -> float:
        """Expected seconds done by the pieces still running: each its time so far over the
        cores it shares, at most its expectation."""
        now = self.clock()
        return sum(min((now - t0) / k, expected.get(p, 0.0))
                   for p, (t0, k) in dict(self.begun).items() if p not in self.finished)

    def done(self, piece: tuple, took: float | None = None) -> None:
        """``piece`` finished; ``took``: its measured seconds (a run's engine-process time
        over the cores it shared), on the same footing as its expectation."""
        self.finished.add(piece)
        if took is not None and took >= 0:
            self.took[piece] = self.took.get(piece, 0.0) + float(took)

    def pace(self, done: float) -> float:
        """Tonight's seconds per expected second (``done``: expected seconds done, running
        pieces' part included): the geometric mean of the measured pieces' times against
        their expectations and the wall clock since the start against ``done`` (the wall
        clock's alone where nothing finished was measured; 1 before anything finished)."""
        if not self.finished:  # nothing measured, and the wall clock also holds work no
            return 1.0         # piece stands for (the compiled loops' warm-up)
        wall = (self.clock() - self.start) / done
        timed = [p for p in self.took if self.expected.get(p, 0.0) > 0]
        want = sum(self.expected[p] for p in timed)
        if want <= 0:
            return wall
        return math.sqrt(sum(self.took[p] for p in timed) / want * wall)

    def _expected_now(self) -> dict[tuple, float]:
        """The expectations with the budgeted pieces not yet finished fitted into what is
        left of their budget (their finished ones' measured times spent from it)."""
        if not self.budgeted:
            return self.expected
        spent = sum(t for k, t in self.took.items() if k[0] in (BENCH, SWEEP)
                    and (k[1], k[2]) in self.budgeted)
        rest = {k: t for k, t in self.expected.items() if k not in self.finished}
        return self.expected | cap(rest, self.budgeted, max(0.0, self.budget_s - spent))

    def left(self) -> float:
        expected = self._expected_now()
        total = sum(expected.values())
        done = sum(t for p, t in expected.items() if p in self.finished)
        done += self._running(expected)
        rest = max(0.0, total - done)
        if total <= 0 or done <= 0:
            return rest
        w = min(1.0, done / total / 0.1)  # trust tonight's pace once a tenth is done
        return rest * ((1 - w) + w * self.pace(done))


def main(argv=None) -> int:
    """``python -m natcoord.suite.eta RESULTS_DIR [--references DIR]``: write the reference
    suite's durations from a full (nightly) suite's folder into the project's references
    (``$NATCOORD_HOME`` or the project folder), or the folder given."""
    import argparse

    from ..case.project import resolve
    from ..errors import NatcoordError

    p = argparse.ArgumentParser(prog="python -m natcoord.suite.eta", description=(
        "Write the reference suite's durations (references/durations.json) from a full "
        "nightly suite's folder, into the project's references ($NATCOORD_HOME or the "
        "project folder) or the folder given."))
    p.add_argument("results", type=Path, help="a suite's results folder")
    p.add_argument("--references", type=Path, default=None,
                   help="folder to write durations.json in [default: <project>/references]")
    a = p.parse_args(argv)
    try:
        summary = read_json(a.results / "summary.json")
        bench = (read_json(a.results / "bench.json") if (a.results / "bench.json").is_file()
                 else {})
        if summary.get("mode") == "quick" or (bench.get("policy") or {}).get(
                "mode") != "nightly":
            raise NatcoordError(f"{a.results}: not a full suite's folder (a nightly "
                                "`natcoord suite` writes its bench.json with the nightly "
                                "policy): its durations would stand for the whole suite")
        print(write_prior(a.results, resolve(a.references, "references")))
    except NatcoordError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
