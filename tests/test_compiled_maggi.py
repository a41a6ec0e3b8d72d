"""The compiled Maggi loop (natcoord.compiled.maggi) against the Python one, and its physics.

Both loops take the same steps with the same stages, Newton, step control and
re-partitioning, so they agree to round-off (adaptive runs on the compiled loop's generic
kernels; its generated path, index-1's kernels for Phi and qdd, against them): fixed-step
RK4 on every case the compiled core runs, adaptive dop853/dopri5 on a few, runs that
re-partition, a mechanism without degrees of freedom. The compiled Gaussian elimination
with full pivoting picks the pivots of :func:`natcoord.dynamics.common.full_pivot_partition`.
Physics: the pendulum of IFToMM A01 against its elliptic solution, the four-bar against the
compiled index-1 loop.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from natcoord.compiled import maggi as kernels_maggi
from natcoord.derivations import exact
from natcoord.dynamics.common import full_pivot_partition
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.solver import Adaptive, Fixed, Index1, Maggi, Solver
from natcoord.model.constraints import QuadraticConstraints
from natcoord.model.drivers import ConstraintSystem

from .test_compiled_core import COMPILED, _model, rk4_window

SAME = ("steps", "rejected", "rhs", "repartitions")  # counters both loops must share


def _pair(model, st, times, method, step, **opt):
    """(compiled, Python) solutions of the same Maggi run."""
    out = []
    for compiled in (True, False):
        sol = integrate(model, st, times, Solver(Maggi(compiled=compiled, **opt), method, step))
        assert sol.counters["compiled"] is compiled
        assert sol.counters["path"] == ("maggi" if compiled else "python")
        out.append(sol)
    return out


def _agree(a, b, tol_q=1e-10, tol_qdd=1e-9):
    """The same step sequence and samples equal to round-off; or, where round-off moved one
    step or one rejection (an adaptive run at rtol 1e-10 under OpenBLAS's SkylakeX kernel,
    whose LAPACK the Python loop uses: slider_crank 12 / 13 rejections, four_bar 47 / 46
    steps), the same repartitions and samples equal to the truncation error that step
    moves (measured 1.3e-10 in q, 1.0e-9 in qd, 2.0e-9 in qdd, relative; bounds 1e-9,
    1e-8, 1e-8)."""
    moved = any(a.counters[k] != b.counters[k] for k in ("steps", "rejected"))
    if moved:
        assert abs(a.counters["steps"] - b.counters["steps"]) <= 1
        assert abs(a.counters["rejected"] - b.counters["rejected"]) <= 1
        assert a.counters["repartitions"] == b.counters["repartitions"]
        tol_q, tol_qd, tol_qdd = 1e-9, 1e-8, 1e-8
    else:
        for key in SAME:
            assert a.counters[key] == b.counters[key], key
        tol_qd = tol_q
    for x, y, tol in ((a.q, b.q, tol_q), (a.qd, b.qd, tol_qd), (a.qdd, b.qdd, tol_qdd)):
        assert np.max(np.abs(x - y)) < tol * max(1.0, float(np.max(np.abs(y))))


@pytest.mark.parametrize("name", [n for n in COMPILED if n != "a03_andrews"])
def test_compiled_rk4_matches_the_python_loop(name):
    """Fixed-step RK4, the same steps: the compiled loop (on the coordinates an
    elimination keeps, where index-1's generated kernels serve it) and the Python loop
    (the model's coordinates) agree to round-off (measured <= 1.5e-14 in q, 1.5e-12 in qd,
    3e-10 in qdd relative; 1e-10 asserted)."""
    case, model, st = _model(name)
    h, times = rk4_window(case, name)
    a, b = _pair(model, st, times, "rk4", Fixed(h))
    assert a.counters["steps"] >= 50
    _agree(a, b)


def test_compiled_rk4_on_kept_coordinates_follows_the_python_loop_to_the_newton_stop():
    """Andrews' squeezer: the compiled loop's Newton solves the rows left over the kept
    coordinates, the Python loop's all of the model's, each stopping at |Phi| < newton_tol;
    the mechanism (its stiff spring) carries that difference to the velocities: measured
    1.8e-10 in q, 3.1e-8 in qd, 3.5e-8 in qdd (relative) over 0.03 s at newton_tol 1e-13,
    2.2e-10 in qd at 1e-15 (the same steps, counters and re-partitions both times).
    Asserted: within 1e-9 / 1e-7 at the default, and at least 30x closer in qd with a 100x
    tighter stop, so the gap is the Newton's stop, not a difference in the dynamics."""
    case, model, st = _model("a03_andrews")
    h, times = rk4_window(case, "a03_andrews")
    gaps = []
    for newton_tol in (1e-13, 1e-15):
        a, b = _pair(model, st, times, "rk4", Fixed(h), newton_tol=newton_tol)
        for key in SAME:
            assert a.counters[key] == b.counters[key], key
        assert a.counters["repartitions"] > 0
        gaps.append([np.max(np.abs(x - y)) / max(1.0, float(np.max(np.abs(y))))
                     for x, y in ((a.q, b.q), (a.qd, b.qd), (a.qdd, b.qdd))])
    assert gaps[0][0] < 1e-9 and gaps[0][1] < 1e-7 and gaps[0][2] < 1e-7
    assert gaps[1][1] < gaps[0][1] / 30


@pytest.mark.parametrize("name, method, window, rtol", [
    ("slider_crank", "dop853", 1.0, 1e-10), ("four_bar", "dop853", 1.0, 1e-10),
    # a03_andrews at 1e-9: at 1e-10 its error estimate's round-off parts the loops since
    # steps may grow tenfold (natcoord.compiled.stepcontrol.MAX_FACTOR): 140 and 118 steps, 7e-10 m
    ("five_bar", "dop853", 1.0, 1e-10), ("a03_andrews", "dop853", 0.03, 1e-9),
    ("four_bar", "dopri5", 0.5, 1e-10), ("slider_crank", "dopri5", 0.5, 1e-10),
    # loose: some steps too long for the Newton of the dependent positions (rejected, h / 4)
    ("four_bar", "dop853", 1.0, 1e-3), ("slider_crank", "dop853", 1.0, 1e-2)])
def test_compiled_adaptive_matches_the_python_loop(name, method, window, rtol):
    """The same steps (Hairer's initial step, the same error norm and factors) and samples
    from the same continuous extension; only round-off differs. The compiled loop's generic
    kernels: the generated path's round-off differs more (Schur complement of M against
    R^T M R, simplified Newton), enough to move one rejection of 14 on slider_crank at rtol
    1e-10 (test_generated_path_matches_eq23 compares it with them). (At much tighter
    tolerances, e.g. rtol 1e-12 with atol 1e-14 on a start from rest, the error estimate of
    the first steps is the stages' round-off, which differs between the loops, and so may
    the step sequence, by a step or two in a hundred.)"""
    _, model, st = _model(name)
    times = np.linspace(0.0, window, 201)
    a, b = _pair(model, st, times, method, Adaptive(rtol=rtol, atol=rtol * 1e-2),
                 generated=False)
    assert 5 < a.counters["steps"] < len(times)  # most samples from the dense output
    _agree(a, b)


@pytest.mark.parametrize("name, method, step, t_end", [
    ("four_bar", "rk4", Fixed(0.5), 1.0), ("a03_andrews", "rk4", Fixed(0.003), 0.03)])
def test_both_loops_refuse_a_failing_run(name, method, step, t_end):
    """Fixed steps too long for the dependent positions' Newton: both loops raise. (Andrews'
    squeezer at rtol = atol = 1e-4 failed so until both loops grew steps by up to 10
    (natcoord.compiled.stepcontrol.MAX_FACTOR): now both carry it, 34 steps, 19 rejected.)"""
    _, model, st = _model(name)
    for compiled in (True, False):
        with pytest.raises(RuntimeError, match="maggi"):
            integrate(model, st, np.array([0.0, t_end]),
                      Solver(Maggi(compiled=compiled), method, step))


@pytest.mark.parametrize("name, method, step, growth", [
    ("four_bar", "dop853", Adaptive(rtol=1e-10, atol=1e-12), 1.5),
    ("slider_crank", "dop853", Adaptive(rtol=1e-10, atol=1e-12), 1.01),
    ("a03_andrews", "rk4", Fixed(1e-3), 1.5),
    ("slider_crank", "dopri5", Fixed(2e-3), 1.01)])
def test_repartitions_match(name, method, step, growth):
    case, model, st = _model(name)
    times = case.times[case.times <= 1.0 + 1e-12]
    a, b = _pair(model, st, times, method, step, repartition_growth=growth, generated=False)
    assert a.counters["repartitions"] > 0
    _agree(a, b)
    cs = ConstraintSystem(model)  # the rebuilt dependent coordinates close the loops
    assert max(np.max(np.abs(cs.phi(q))) for q in a.q) < 1e-11


def test_partition_picks_the_pivots_of_full_pivoting():
    """rows, dep, indep and the rank of the compiled elimination equal the Python one's on
    the cases' Jacobians (redundant rows included) and on random rank-deficient matrices."""
    rng = np.random.default_rng(11)
    mats = []
    for name in ("five_bar", "a04_bricard", "parallelogram_3d", "slider_crank_3d"):
        _, model, st = _model(name)
        mats.append(ConstraintSystem(model).jacobian(np.asarray(st.q, float)))
    for m, n, r in ((5, 8, 3), (8, 8, 6), (9, 4, 4), (3, 7, 0)):
        mats.append(rng.standard_normal((m, r)) @ rng.standard_normal((r, n)))
    for J in mats:
        m, n = J.shape
        A, rows, cols = np.zeros((m, n)), np.zeros(m, np.int64), np.zeros(n, np.int64)
        r = kernels_maggi.partition(J, 1e-9, A, rows, cols)
        ref = full_pivot_partition(J, 1e-9)
        assert r == len(ref[0])
        for x, y in zip((rows[:r], cols[:r], cols[r:]), ref[:3], strict=True):
            assert np.array_equal(x, y)


def test_no_degrees_of_freedom():
    """A01's pendulum with its mass held on y = 0 (f = 0): both loops give the kinematics
    at every sample, at rest."""
    _, model, st = _model("a01_pendulum")
    con, n = model.constraints, model.n
    row = QuadraticConstraints(  # Phi_m = q[3] (point P's y)
        n, con.m + 1, np.append(con.k, [con.m, con.m]), np.append(con.i, [3, n]),
        np.append(con.j, [n, 3]), np.append(con.v, [1.0, 1.0]), (*con.labels, "P.y"),
        np.append(con.length_dim, 1))
    fixed = dataclasses.replace(model, constraints=row)
    times = np.linspace(0.0, 0.1, 5)
    for method, step in (("dop853", Adaptive()), ("rk4", Fixed(0.01))):
        a, b = _pair(fixed, st, times, method, step)
        _agree(a, b)
        assert a.counters["steps"] == 0
        assert np.max(np.abs(a.q - st.q)) < 1e-14 and np.max(np.abs(a.qdd)) < 1e-12


def test_a01_pendulum_follows_the_elliptic_solution():
    """The point mass on a massless link (singular M) over 20 s (about 8 periods, many
    re-partitions as the link turns) within 1e-9 m of the Jacobi elliptic solution."""
    case, model, st = _model("a01_pendulum")
    times = case.times[case.times <= 20.0 + 1e-9]
    sol = integrate(model, st, times, Solver(Maggi(), "dop853", Adaptive(1e-12, 1e-14)))
    assert sol.counters["path"] == "maggi" and sol.counters["repartitions"] > 10
    ex = exact.a01_pendulum(times)
    assert np.max(np.abs(sol.q[:, 2] - ex["x"])) < 1e-9
    assert np.max(np.abs(sol.q[:, 3] - ex["y"])) < 1e-9


@pytest.mark.parametrize("name", ["four_bar", "slider_crank"])
def test_agrees_with_the_compiled_index1_loop(name):
    """Two formulations, two compiled loops, the same motion and reactions over 2 s."""
    case, model, st = _model(name)
    times = case.times[case.times <= 2.0 + 1e-9]
    step = Adaptive(rtol=1e-12, atol=1e-14)
    a = integrate(model, st, times, Solver(Maggi(), "dop853", step))
    b = integrate(model, st, times, Solver(Index1(), "dop853", step))
    assert a.counters["path"] == "maggi" and b.counters["compiled"]
    for x, y, tol in ((a.q, b.q, 1e-9), (a.qd, b.qd, 1e-8), (a.qdd, b.qdd, 1e-8),
                      (a.lam, b.lam, 1e-9)):
        assert np.max(np.abs(x - y)) < tol * max(1.0, float(np.max(np.abs(y))))


def _generic_and_generated(name, times, method, steps):
    """(generic, generated) (Q, QD, QDD) and counters of the same compiled Maggi run: the
    generic kernels with Eq. (23), and index-1's generated kernels (Phi, accelerations)."""
    from natcoord.dynamics.common import Counters
    from natcoord.dynamics.index1 import Index1Loop
    from natcoord.dynamics.maggi import MaggiLoop
    _, model, st = _model(name)
    q0, qd0 = Index1Loop(model, {"linsolve": "qr"}, Counters()).project(
        0.0, np.asarray(st.q, float), np.asarray(st.qd, float))
    out = []
    for generated in (False, True):
        cnt = Counters()
        loop = MaggiLoop(model, {}, cnt)
        loop.prepare_compiled(q0)
        assert loop._gen is not None  # the generated kernels serve these models
        y, q, part = loop.compiled_start(0.0, q0, qd0)
        frc = loop._frc if loop._red is None else loop._red.frc
        sol = kernels_maggi.run(loop._packed, frc, times, y, q, part, method, steps, cnt,
                                loop._gen if generated else None)
        out.append((sol, cnt))
    return out


@pytest.mark.parametrize("name", ["four_bar", "slider_crank", "five_bar"])
def test_generated_path_matches_eq23(name):
    """The generated path (Phi and qdd by index-1's kernels, simplified Newton) against the
    generic one (Eq. (23) with R^T M R): fixed-step RK4 over 1 s, the same steps, the same
    motion to round-off (measured, relative to the largest value: q, qd, qdd <= 3.5e-14;
    slider_crank 7.3e-14 m, 1.3e-13 m/s, 1.2e-12 m/s^2)."""
    times = np.linspace(0.0, 1.0, 101)
    (a, ca), (b, cb) = _generic_and_generated(name, times, "rk4",
                                              kernels_maggi.Steps(h=1e-3))
    assert ca.steps == cb.steps == 1000 and ca.rhs == cb.rhs
    assert cb.newton > 0
    for x, y in zip(a, b, strict=True):
        assert np.max(np.abs(x - y)) < 3e-13 * float(np.max(np.abs(x)))


def test_generated_path_repartitions_through_the_dead_points():
    """The slider-crank turns through its dead points over 2 s, where max|R^d| grows
    without bound: re-partitioning at growth 1.01, the generated path re-partitions where
    the generic one does and agrees with it to round-off (fixed-step RK4: the same steps)."""
    times = np.linspace(0.0, 2.0, 201)
    (a, ca), (b, cb) = _generic_and_generated(
        "slider_crank", times, "rk4", kernels_maggi.Steps(h=1e-3, repartition_growth=1.01))
    assert cb.repartitions > 0 and cb.repartitions == ca.repartitions
    for x, y in zip(a, b, strict=True):
        assert np.max(np.abs(x - y)) < 3e-13 * float(np.max(np.abs(x)))


@pytest.mark.parametrize("name", ["four_bar", "five_bar"])
def test_generated_newton_keeps_the_assembly_branch(name):
    """Loose adaptive steps (dop853 rtol 1e-8, long stage increments): the generated path's
    Newton (the M-weighted step with q^i held, R rebuilt from the last R; five_bar's
    independent coordinate is a massless point's) stays with the generic path on the
    assembly branch over 2 s. A simplified Newton with the last evaluation's LU jumped to
    the other branch here (errors of 7.6 and 4 rad)."""
    times = np.linspace(0.0, 2.0, 201)
    (a, _), (b, cb) = _generic_and_generated(name, times, "dop853",
                                             kernels_maggi.Steps(rtol=1e-8, atol=1e-10))
    assert cb.newton > 0
    for x, y in zip(a, b, strict=True):
        assert np.max(np.abs(x - y)) < 1e-5 * float(np.max(np.abs(x)))
