"""natcoord's compiled loops are made ready once, before its runs, while other engines run.

The board of :func:`natcoord.suite.parallel.local` hands out the preparing processes first,
the other engines' runs while they go on, and natcoord's runs only once all have finished;
:mod:`natcoord.suite.warm` names the loops from the cases' settings.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

from natcoord.case.casefile import load_case
from natcoord.suite import parallel, warm
from natcoord.suite.runner import run_suite

ROOT = Path(__file__).resolve().parents[1]
CASES = ROOT / "cases"
REFERENCES = ROOT / "references"


def _board(order, engines, before):
    return parallel._Board(order, before, lambda i: engines[i])


def test_natcoord_runs_wait_for_every_preparing_process_others_do_not():
    engines = ["natcoord", "mujoco", "natcoord", "pinocchio"]
    board = _board([0, 1, 2, 3], engines, {"natcoord": [["a"], ["b"]]})
    assert board.take() == ("before", ["a"])
    assert board.take() == ("before", ["b"])
    # both preparing: the other engines' runs go first, in order
    assert board.take() == ("cell", 1)
    assert board.take() == ("cell", 3)
    board.finished("before", ["a"])
    got = []
    t = threading.Thread(target=lambda: got.append(board.take()))
    t.start()
    t.join(1.0)
    assert t.is_alive() and not got  # one still preparing: natcoord's runs wait
    board.finished("before", ["b"])
    t.join(30.0)
    assert got == [("cell", 0)]
    assert board.take() == ("cell", 2)
    assert board.take() is None


def test_without_preparing_processes_the_order_is_kept_and_stop_ends_the_wait():
    board = _board([2, 0, 1], ["natcoord"] * 3, {})
    assert [board.take() for _ in range(3)] == [("cell", 2), ("cell", 0), ("cell", 1)]
    assert board.take() is None
    waiting = _board([0], ["natcoord"], {"natcoord": [["a"]]})
    assert waiting.take() == ("before", ["a"])
    got = []
    t = threading.Thread(target=lambda: got.append(waiting.take()))
    t.start()
    waiting.stop()  # an interruption: a waiting thread gets no more work
    t.join(30.0)
    assert got == [None]


def test_the_loops_named_by_the_catalogue_and_by_settings():
    cases = [load_case(p) for p in sorted(CASES.glob("*.toml"))]
    assert warm.paths(cases) >= {"sparse", "generated", "general"}
    pendulum = load_case(CASES / "pendulum.toml")
    spec = pendulum.engine("natcoord")
    for settings, want in (({"compiled": False}, set()),
                           ({"formulation": "maggi"}, {"maggi"}),
                           ({"formulation": "index3", "h": 1e-3}, {"index3"})):
        case = dataclasses.replace(pendulum, engines={
            **pendulum.engines, "natcoord": dataclasses.replace(spec, settings=settings)})
        assert warm.paths([case]) == want, settings
    cmds = warm.commands([pendulum])
    assert len(cmds) == 2  # sparse + generated share a process, general its own
    for cmd in cmds:  # each loads (or compiles) its loops and exits cleanly
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=900,
                           cwd=ROOT)
        assert p.returncode == 0, p.stderr
    assert cmds[0][0] == sys.executable


def test_two_at_a_time_with_preparation_gives_the_serial_results(tmp_path):
    cases = [load_case(CASES / "pendulum.toml"), load_case(CASES / "slider_crank.toml")]
    engines = ["natcoord", "mujoco"]
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
