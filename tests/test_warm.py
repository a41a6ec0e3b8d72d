"""natcoord's compiled code is made ready once, before its runs, while other engines run.

The board of :func:`natcoord.suite.parallel.local` hands out the preparing chain first, the
other runs while it goes on, and each natcoord run once the code it takes is ready;
:mod:`natcoord.suite.warm` decides that code from each case's settings and model, as the
run's own set-up does.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest

from natcoord.case.casefile import load_case
from natcoord.dynamics.common import Counters
from natcoord.dynamics.formulations import FORMULATIONS
from natcoord.dynamics.solver import case_solver
from natcoord.model import casemodel
from natcoord.suite import parallel, warm
from natcoord.suite.runner import prepare, run_suite

ROOT = Path(__file__).resolve().parents[1]
CASES = ROOT / "cases"
REFERENCES = ROOT / "references"


def test_a_run_waits_for_the_items_it_needs_others_do_not():
    chain = [("generated", ["a"]), ("outputs", ["b"])]
    board = parallel._Board([0, 1, 2, 3, 4], chain, {0: {"generated"}, 2: {"generated",
                                                                           "outputs"}})
    assert board.take() == ("before", chain)  # one worker prepares, in order
    # preparing: the runs that need nothing prepared go first, in order
    assert board.take() == ("cell", 1)
    assert board.take() == ("cell", 3)
    assert board.take() == ("cell", 4)
    board.ready("generated")
    assert board.take() == ("cell", 0)
    got = []
    t = threading.Thread(target=lambda: got.append(board.take()))
    t.start()
    t.join(1.0)
    assert t.is_alive() and not got  # "outputs" still preparing: run 2 waits
    board.ready("outputs")
    t.join(30.0)
    assert got == [("cell", 2)]
    assert board.take() is None


def test_without_preparing_processes_the_order_is_kept_and_stop_ends_the_wait():
    board = parallel._Board([2, 0, 1], [], {1: {"generated"}})  # nothing warmed: no wait
    assert [board.take() for _ in range(3)] == [("cell", 2), ("cell", 0), ("cell", 1)]
    assert board.take() is None
    waiting = parallel._Board([0], [("generated", ["a"])], {0: {"generated"}})
    assert waiting.take() == ("before", [("generated", ["a"])])
    got = []
    t = threading.Thread(target=lambda: got.append(waiting.take()))
    t.start()
    waiting.stop()  # an interruption: a waiting thread gets no more work
    t.join(30.0)
    assert got == [None]
    failed = parallel._Board([0], [("generated", ["a"])], {0: {"generated"}})
    chain = failed.take()[1]
    failed.finished("before", chain)  # a chain that failed still lets its runs go
    assert failed.take() == ("cell", 0)


def _variant(name: str, **settings):
    case = load_case(CASES / f"{name}.toml")
    spec = case.engine("natcoord")
    return prepare(dataclasses.replace(case, engines={
        **case.engines, "natcoord": dataclasses.replace(
            spec, settings={**spec.settings, **settings})}))


def _taken(job) -> set[str]:
    """What a real set-up of natcoord's compiled run of ``job`` takes: its path and the
    sparse outputs when it has the outputs' plan."""
    settings = job.case.engine("natcoord").settings
    solver = case_solver(settings)
    cm = casemodel.build(job.case, settings.get("coordinates", "joints"))
    form = FORMULATIONS[solver.formulation.name].loop(cm.model, solver.formulation.options(),
                                                      Counters())
    if not form.compiled_candidate(solver.method, solver.h):
        return set()
    prep = form.prepare_compiled(casemodel.initial_state(cm).q)
    return {prep.path} | ({"outputs"} if prep.plan is not None else set())


@pytest.mark.parametrize("job, want", [
    ("pendulum", {"generated"}),                        # singular M: dense generated route
    ("slider_crank", {"generated", "outputs"}),         # regular M: outputs on the plan
    ("four_bar_3d", {"general"}),                       # M_r singular after elimination
    ("a02_four_bar_n40", {"sparse", "outputs"}),        # too large for generated kernels
    ("parallelogram_3d_flexible", set()),               # Radau (scipy): no compiled loop
    ("slider_crank_driven", set()),                     # rheonomic: the Python loop
    (("slider_crank", {"linsolve": "qr"}), {"general"}),
    (("slider_crank", {"generated": False}), {"sparse", "outputs"}),
    (("slider_crank", {"compiled": False}), set()),
    (("pendulum", {"formulation": "maggi"}), {"maggi"}),
    (("pendulum", {"formulation": "index3", "h": 1e-3}), {"index3"}),
], ids=str)
def test_the_code_a_run_needs_is_what_its_set_up_takes(job, want):
    job = prepare(load_case(CASES / f"{job}.toml")) if isinstance(job, str) else _variant(
        job[0], **job[1])
    assert warm.needs(job) == want
    assert _taken(job) == want  # the real set-up (generated kernels compiled) agrees


def test_only_what_two_runs_take_is_warmed_and_each_run_waits_for_its_own():
    names = ["pendulum", "slider_crank", "four_bar", "four_bar_3d",
             "parallelogram_3d_flexible"]
    jobs = [prepare(load_case(CASES / f"{n}.toml")) for n in names]
    engines = ["mujoco", "natcoord"]
    chain, waits = warm.plan(jobs, engines)
    assert [item for item, _ in chain] == ["generated", "outputs"]
    nat = {names[i // 2]: w for i, w in waits.items()}
    assert all(i % 2 == 1 for i in waits)  # natcoord's cells only
    assert nat == {"pendulum": {"generated"}, "slider_crank": {"generated", "outputs"},
                   "four_bar": {"generated", "outputs"},
                   # compiles "general" in its own run, after the shared callees
                   "four_bar_3d": {"generated", "outputs"}}
    # one case: nothing warmed (its run compiles what it takes); no natcoord: nothing
    assert warm.plan(jobs[:1], engines) == ([], {})
    assert warm.plan(jobs, ["mujoco"]) == ([], {})
    for item, cmd in chain:  # each loads (or compiles) its code and exits cleanly
        assert cmd[0] == sys.executable
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT)
        assert p.returncode == 0, (item, p.stderr)


def test_two_at_a_time_with_preparation_gives_the_serial_results(tmp_path):
    cases = [load_case(CASES / "pendulum.toml"), load_case(CASES / "slider_crank.toml")]
    engines = ["natcoord", "mujoco"]
    # slider_crank's outputs are needed by one run only: not warmed, compiled in that run
    chain, _ = warm.plan([prepare(c) for c in cases], engines)
    assert [item for item, _ in chain] == ["generated"]
    serial = run_suite(cases, engines, tmp_path / "one", references=REFERENCES)
    two = run_suite(cases, engines, tmp_path / "two", references=REFERENCES,
                    jobs=2)
    key = [(r["case"], r["engine"], r["status"], r["verdict"]) for r in serial["records"]]
    assert [(r["case"], r["engine"], r["status"], r["verdict"])
            for r in two["records"]] == key
    assert all(r["status"] == "ok" for r in two["records"])


def test_the_longest_expected_start_first_and_among_unknowns_the_largest_case():
    jobs = [SimpleNamespace(case=load_case(CASES / f"{n}.toml"))
            for n in ("four_bar", "a01_pendulum", "a02_four_bar_n40")]
    todo = parallel.cells(jobs, ["natcoord", "mujoco"])
    names = lambda order: [(todo[i][0].case.name, todo[i][1]) for i in order]  # noqa: E731
    assert names(parallel._order(todo, {}))[:4] == [  # 2000 s x 2 bodies, 20 s x 82
        ("a01_pendulum", "natcoord"), ("a01_pendulum", "mujoco"),
        ("a02_four_bar_n40", "natcoord"), ("a02_four_bar_n40", "mujoco")]
    assert names(parallel._order(todo, {("four_bar", "mujoco"): 9.0}))[0] == (
        "four_bar", "mujoco")
