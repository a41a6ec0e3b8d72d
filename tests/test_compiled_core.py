"""The compiled core against the Python path, case by case, and its sparsity plan.

Every case natcoord can run compiled (scleronomic, known forces) is integrated by fixed-step
RK4 twice, once in the compiled loop (sparse Schur path for a regular M, the QR null-space
form for a singular one) and once in the Python loop: the same method with the same steps,
so the two agree to round-off and the projection tolerance, and must agree to 1e-10. The
plan itself is checked against dense algebra: J, W = J M^-1 J^T and its Cholesky factor,
and a redundant row (five_bar's regular-M variant) left out by the semi-definite factor.
"""

from __future__ import annotations

import numpy as np
import pytest

from natcoord.case import casefile
from natcoord.compiled import codegen, sparsity
from natcoord.compiled import index1 as kernels
from natcoord.compiled import sparse as ks
from natcoord.dynamics.common import Counters, compiled_forces
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.index1 import Index1Loop
from natcoord.dynamics.solver import Adaptive, Fixed, Index1, Index3, Maggi, Solver
from natcoord.model import casemodel
from natcoord.model.drivers import ConstraintSystem

from .conftest import CASES

H = 1e-3  # RK4 step (s)
WINDOW = 0.05  # s of each case
STIFF = {"a05_flyball_governor": (1e-4, 0.01),  # dampers' mode ~1e4 1/s
         "parallelogram_3d_flexible": (2e-5, 0.002)}  # its springs: ~35 steps per ms
COMPILED = [p.stem for p in sorted(CASES.glob("*.toml"))
            if p.stem not in ("slider_crank_driven",)]  # drivers are rheonomic: Python only


def _model(name):
    case = casefile.load_case(CASES / f"{name}.toml")
    engine = case.engines.get("natcoord")
    coords = (getattr(engine, "settings", None) or {}).get("coordinates", "joints")
    cm = casemodel.build(case, coords)
    return case, cm.model, casemodel.initial_state(cm)


def rk4_window(case, name) -> tuple[float, np.ndarray]:
    """(h, times): the RK4 step and the case's samples in the window the loops compare."""
    h, window = STIFF.get(name, (H, WINDOW))
    times = case.times[case.times <= window + 1e-12]
    return h, times if len(times) >= 2 else np.array([0.0, window])


@pytest.mark.parametrize("name", COMPILED)
def test_compiled_rk4_matches_the_python_loop(name):
    case, model, st = _model(name)
    h, times = rk4_window(case, name)
    runs = {}
    for compiled in (True, False):
        sol = integrate(model, st, times, Solver(Index1(compiled=compiled), "rk4", Fixed(h)))
        assert sol.counters["compiled"] is compiled
        runs[compiled] = sol
    a, b = runs[True], runs[False]
    assert a.counters["steps"] == b.counters["steps"]
    scale = max(1.0, float(np.max(np.abs(b.q))))
    assert np.max(np.abs(a.q - b.q)) < 1e-10 * scale
    vscale = max(1.0, float(np.max(np.abs(b.qd))))
    assert np.max(np.abs(a.qd - b.qd)) < 1e-10 * vscale
    ascale = max(1.0, float(np.max(np.abs(b.qdd))))
    assert np.max(np.abs(a.qdd - b.qdd)) < 1e-9 * ascale


@pytest.mark.parametrize("name", ["slider_crank", "four_bar", "a02_four_bar_n2",
                                  "slider_crank_3d", "a04_bricard"])
def test_plan_reproduces_dense_algebra(name):
    _, model, st = _model(name)
    cs = ConstraintSystem(model)
    M = np.asarray(model.M, float)
    plan = sparsity.schur_plan(cs.con, M)
    I, F, O = plan.kernel_args
    ws = ks.workspace(plan.kernel_args)
    J = cs.con.jacobian(np.asarray(st.q, float))[plan.perm]  # plan rows: RCM order
    cnt = np.zeros(kernels.N_COUNTERS)
    ks.refactor((I, F, O), ks.NO_GK, np.asarray(st.q, float), ws, cnt)
    nJ, nY = len(plan.jac_ptr) - 1, len(plan.y_ptr) - 1
    Jv = ws[:nJ]
    Jp = np.zeros_like(J)
    Jp[plan.J_row, plan.J_col] = Jv
    assert np.allclose(Jp, J, rtol=0, atol=1e-14)
    Lv = ws[nJ + nY:nJ + nY + plan.envelope]
    L = np.zeros((plan.m, plan.m))
    for r in range(plan.m):
        for c in range(plan.env_first[r], r + 1):
            L[r, c] = Lv[plan.env_ptr[r] + c - plan.env_first[r]]
    W = J @ np.linalg.solve(M, J.T)
    rank = np.linalg.matrix_rank(J, 1e-9)
    assert np.count_nonzero(np.diag(L)) == rank
    assert np.allclose(L @ L.T, W, rtol=0, atol=1e-10 * np.max(np.abs(W)))


def test_semidefinite_factor_solves_a_redundant_system():
    """A four_bar with its last joint row repeated: W is singular, the factor marks the
    copy dependent, and qdd equals the one without the copy."""
    _, model, st = _model("four_bar")
    cs = ConstraintSystem(model)
    con = cs.con
    last = con.k == con.m - 1

    class Con:
        m = con.m + 1
        k = np.concatenate([con.k, np.full(int(last.sum()), con.m)])
        i = np.concatenate([con.i, con.i[last]])
        j = np.concatenate([con.j, con.j[last]])
        v = np.concatenate([con.v, 2.0 * con.v[last]])  # a multiple: still redundant

    frc = compiled_forces(model)
    M = np.asarray(model.M, float)
    q, qd = np.asarray(st.q, float), np.asarray(st.qd, float)
    out = []
    for c in (con, Con):  # generic and generated kernels, without and with the copy
        plan = sparsity.schur_plan(c, M)
        gk = codegen.load(plan, frc)
        for P, g, f in ((plan.kernel_args, ks.NO_GK, frc), (None, gk, None)):
            ws = ks.workspace(plan.kernel_args)
            qdd = np.zeros(model.n)
            ks.accelerations(P, g, f, q, qd, qdd, ws, np.zeros(kernels.N_COUNTERS), True)
            out.append(qdd)
    assert len(out) == 4
    for other in out[1:]:
        assert np.max(np.abs(out[0] - other)) < 1e-12 * max(1.0, np.max(np.abs(out[0])))
    ref = Index1Loop(model, {"linsolve": "qr"}, Counters()).accelerations(0.0, q, qd)
    assert np.max(np.abs(out[0] - ref)) < 1e-10 * max(1.0, np.max(np.abs(ref)))


def test_envelope_of_a_chain_stays_narrow(tmp_path):
    """Reverse Cuthill-McKee keeps W's envelope linear in the size of a chain: the
    N-four-bar's envelope per row does not grow with N."""
    from natcoord.case.generate import n_four_bar

    per_row = []
    for n_cranks in (4, 16):
        path = tmp_path / f"a02_four_bar_n{n_cranks}.toml"
        path.write_text(n_four_bar(n_cranks))
        case = casefile.load_case(path)
        cm = casemodel.build(case, "joints")
        cs = ConstraintSystem(cm.model)
        plan = sparsity.schur_plan(cs.con, np.asarray(cm.model.M, float))
        per_row.append(plan.envelope / plan.m)
    assert per_row[1] < 1.3 * per_row[0]


def test_phi_carries_no_round_off_far_from_the_origin():
    """Phi of A02 N = 40 (points up to 41 m from the origin) at a perturbed pose, against
    exact rational arithmetic: the compiled sum (two doubles per product and sum) is exact to
    a few 1e-16 m^2; the plain sum of the same products loses ~1e-13 m^2 to cancellation,
    which is what misplaced the cranks near the singular position."""
    from fractions import Fraction

    _, model, st = _model("a02_four_bar_n40")
    cs = ConstraintSystem(model)
    con = cs.con
    plan = sparsity.schur_plan(con, np.asarray(model.M, float))
    I, F, O = plan.kernel_args
    q = np.asarray(st.q, float) + 1e-3 * np.random.default_rng(7).standard_normal(model.n)
    qh = [Fraction(x) for x in q] + [Fraction(1)]
    exact = [Fraction(0)] * con.m
    for k, i, j, v in zip(con.k, con.i, con.j, con.v, strict=True):
        exact[k] += Fraction(v) * qh[i] * qh[j] / 2
    exact = np.array([float(x) for x in exact])  # case row order
    out = np.zeros(con.m)
    ks.phi(I, F, O, q, out)
    assert np.max(np.abs(out[np.argsort(plan.perm)] - exact)) < 4e-16  # plan row order
    assert np.max(np.abs(con.phi(q) - exact)) > 1e-14  # what the two-double sum is for


REGULAR = ["slider_crank", "four_bar", "a02_four_bar_n2", "slider_crank_3d", "a04_bricard"]


@pytest.mark.parametrize("name", REGULAR)
def test_generated_kernels_equal_the_generic_ones(name):
    """The straight-line kernels written for the model (natcoord.compiled.codegen) against the
    generic sparse kernels on the same plan: Phi at a perturbed pose; the accelerations
    (factor and solve), a Newton correction and J x at the initial pose (where a redundant
    system such as Bricard's is consistent) with random velocities; then a whole adaptive
    dop853 run each way, at a tolerance tight enough that A02's samples near its singular
    position (where projecting a sample amplifies round-off a thousandfold) agree too."""
    case, model, st = _model(name)
    M = np.asarray(model.M, float)
    con = ConstraintSystem(model).con
    frc = compiled_forces(model)
    plan = sparsity.schur_plan(con, M)
    I, F, O = plan.kernel_args
    gk = codegen.load(plan, frc)
    assert gk is not None
    rng = np.random.default_rng(3)
    q = np.asarray(st.q, float)
    qp = q + 1e-4 * rng.standard_normal(model.n)
    qd = np.asarray(st.qd, float) + rng.standard_normal(model.n)
    res = []
    for P, g, f in (((I, F, O), ks.NO_GK, frc), (None, gk, None)):  # generic, generated
        ws, cnt = ks.workspace(plan.kernel_args), np.zeros(kernels.N_COUNTERS)
        w, qdd, x, v = np.zeros(plan.m), np.zeros(model.n), q.copy(), np.zeros(plan.m)
        e = ks._phi_max(P, g, qp, w)
        phi = w.copy()
        ks.accelerations(P, g, f, q, qd, qdd, ws, cnt, True)
        ks._newton_step(P, g, ws, w, x)
        big = ks._jx(P, g, ws, qd, v)
        res.append((e, phi, qdd, x, big, v))
    for a, b in zip(*res, strict=True):
        scale = max(1.0, float(np.max(np.abs(a))))
        assert np.max(np.abs(np.asarray(a) - np.asarray(b))) < 1e-12 * scale
    sols = [integrate(model, st, case.times[case.times <= 0.5 + 1e-12],
                      Solver(Index1(generated=g), "dop853", Adaptive(rtol=1e-11, atol=1e-13)))
            for g in (False, True)]
    assert sols[0].counters["steps"] > 5
    assert np.max(np.abs(sols[0].q - sols[1].q)) < 1e-10 * max(1.0, np.max(np.abs(sols[0].q)))
    assert np.max(np.abs(sols[0].qd - sols[1].qd)) < 1e-9 * max(1.0, np.max(np.abs(sols[0].qd)))


@pytest.mark.parametrize("name", ["slider_crank", "pendulum", "five_bar"])
def test_generated_forces_equal_the_generic_ones(name):
    """A planar torque and a spring-damper added to a regular (slider_crank) and a singular
    (pendulum, five_bar: the regularised route) model: the generated kernels' accelerations
    equal the generic kernels' (regular M) or the general QR path's (singular M) at a
    random state. five_bar's massless points are touched by five of its eight rows: only
    those regularise M."""
    from scipy.linalg import null_space

    from natcoord.compiled.general import pack_forces

    _, model, st = _model(name)
    n, M = model.n, np.asarray(model.M, float)
    con = ConstraintSystem(model).con
    base = compiled_forces(model)
    G = np.zeros((2, 2, n + 1))  # torque 3 N m, spread over two difference vectors
    G[0, 0, 0], G[0, 1, 1], G[0, 0, n] = 1.0, 1.0, -0.1
    G[1, 0, 2], G[1, 1, 3], G[1, 1, n] = 1.0, 1.0, 0.2
    S = np.zeros((1, 2, n + 1))  # spring from (0.3, -0.2) to the point (q0, q1)
    S[0, 0, 0], S[0, 1, 1], S[0, 0, n], S[0, 1, n] = 1.0, 1.0, -0.3, 0.2
    frc = pack_forces(base[0], None, G, np.array([0, 2]), np.array([[3.0, 0, 0]]), S,
                      np.array([[50.0, 2.0, 0.4]]))
    q = np.asarray(st.q, float)
    rng = np.random.default_rng(5)
    qd = np.asarray(st.qd, float) + rng.standard_normal(n)
    if name == "five_bar":  # an admissible velocity (Phi_q qd = 0): its redundant rows
        N = null_space(ConstraintSystem(model).jacobian(q, 0.0))  # leave the accelerations
        qd = np.asarray(st.qd, float) + N @ rng.standard_normal(N.shape[1])  # of others
        # without a solution
    cnt = np.zeros(kernels.N_COUNTERS)
    regular = name == "slider_crank"
    plan = (sparsity.schur_plan(con, M) if regular else
            sparsity.dense_plan(con, M, 1.0))
    gk = codegen.load(plan, frc, None if regular else M)
    assert gk is not None
    if name == "five_bar":
        assert list(plan.reg) == [2, 3, 4, 5, 7]
    out = np.zeros(n)
    ks.accelerations(None, gk, None, q, qd, out, ks.workspace(plan.kernel_args), cnt, True)
    if regular:
        ref = np.zeros(n)
        ks.accelerations(plan.kernel_args, ks.NO_GK, frc, q, qd, ref,
                         ks.workspace(plan.kernel_args), cnt, True)
    else:
        from natcoord.compiled.general import acc_general, general, workspace
        ref = np.zeros(n)
        acc_general(general(con, M, 1e-9), frc, q, qd, ref, workspace(n, con.m), cnt)
    assert np.max(np.abs(ref)) > 1.0
    assert np.max(np.abs(out - ref)) < 1e-10 * np.max(np.abs(ref))


@pytest.mark.parametrize("name", COMPILED)
def test_compiled_index3_matches_the_python_loop(name):
    """The same trapezoidal steps; the two loops' Newton iterates may part by its stop
    (|dq| < 10 newton_tol max(1, |q|)), which the trapezoidal rule turns into 2/h of it in
    qd and 4/h^2 in qdd."""
    case, model, st = _model(name)
    h, window = STIFF.get(name, (H, WINDOW))
    times = np.linspace(0.0, min(window, 0.01), 3)
    runs = {c: integrate(model, st, times, Solver(Index3(compiled=c), "trapezoidal",
                                                  Fixed(h))) for c in (True, False)}
    a, b = runs[True], runs[False]
    assert a.counters["path"] == "index3" and b.counters["path"] == "python"
    assert a.counters["steps"] == b.counters["steps"]
    assert a.counters["newton"] == b.counters["newton"]
    stop = 10 * Index3().newton_tol * max(1.0, float(np.max(np.abs(b.q))))
    assert np.max(np.abs(a.q - b.q)) < 10 * stop
    assert np.max(np.abs(a.qd - b.qd)) < 10 * stop * 2 / h
    assert np.max(np.abs(a.qdd - b.qdd)) < 10 * stop * 4 / h ** 2


def test_compiled_index3_reports_a_step_its_newton_cannot_take():
    case, model, st = _model("four_bar")  # 0.25 s steps: too long for it at any penalty
    for compiled in (True, False):
        with pytest.raises(RuntimeError, match="Newton did not converge at t = 0.5 s"):
            integrate(model, st, np.linspace(0.0, 1.0, 5),
                      Solver(Index3(compiled=compiled), "trapezoidal", Fixed(0.25)))


def test_index3_tangent_carries_the_springs_stiffness():
    """parallelogram_3d_flexible's stiff spring-dampers: with their stiffness and damping in
    the Newton tangent (difference quotients over the coordinates they move) the
    trapezoidal rule converges on 1e-4 s steps (without them it failed there and at 2e-5
    s), in under two iterations a step, and is of order 2 against a Radau reference."""
    case, model, st = _model("parallelogram_3d_flexible")
    times = np.linspace(0.0, 0.02, 5)
    ref = integrate(model, st, times, Solver(Index1(), "Radau", Adaptive(1e-11, 1e-13)))
    err = {}
    for h in (1e-4, 5e-5):
        sol = integrate(model, st, times, Solver(Index3(), "trapezoidal", Fixed(h)))
        assert sol.counters["path"] == "index3"
        assert sol.counters["newton"] < 2 * sol.counters["steps"]
        err[h] = float(np.max(np.abs(sol.q - ref.q)))
    assert np.max(np.abs(ref.q - ref.q[0])) > 5e-4  # the springs do move it
    assert err[1e-4] < 2e-10
    assert 3.0 < err[1e-4] / err[5e-5] < 5.0


@pytest.mark.slow
@pytest.mark.parametrize("path", ["sparse", "generated", "general", "maggi", "index3"])
def test_a_compiled_path_compiles_first_in_a_fresh_process(tmp_path, path):
    """A new machine compiles the path its first case takes, alone, with empty caches. A
    function compiled without numba's reference counting hands that to a callee it
    compiles first, so a path that reached an allocating callee only that way failed to
    type there ("No implementation of function empty"), while any process that had
    compiled the callee elsewhere first (the test suite's order) passed."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               NATCOORD_CACHE_DIR=str(tmp_path / "natcoord"))
    done = subprocess.run(
        [sys.executable, "-c", "from natcoord.compiled import cache; "
                               f"cache.ensure_compiled({path!r})"],
        env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.parametrize("name, path", [("slider_crank", "generated"),
                                        ("a02_four_bar_n2", "generated"),
                                        ("a02_four_bar_n40", "sparse"),
                                        ("four_bar_3d", "general")])
def test_the_motion_does_not_depend_on_the_output_times(name, path):
    """Adaptive steps cross the samples, and a step's end is projected the same way whether
    samples fell inside it or not: asking for every tenth sample gives those samples bit
    for bit. (It did not: after the dense output's extra stages the step's end was
    projected with their factorization, not one at the end, and a02_four_bar_n2 moved by
    3.6e-8 m with the output times.)"""
    case, model, st = _model(name)
    times = case.times[case.times <= 2.0 + 1e-12]
    solver = Solver(Index1(), "dop853", Adaptive(rtol=1e-8, atol=1e-10))
    every = integrate(model, st, times, solver)
    tenth = integrate(model, st, times[::10], solver)
    assert every.counters["path"] == path
    assert every.counters["steps"] == tenth.counters["steps"] > 10
    for a, b in ((every.q, tenth.q), (every.qd, tenth.qd), (every.qdd, tenth.qdd)):
        assert np.array_equal(a[::10], b)


@pytest.mark.parametrize("name", ["slider_crank", "four_bar", "five_bar"])
def test_maggi_motion_depends_on_the_output_times_only_by_round_off(name):
    """The compiled maggi loop projects every stage and sample; a sample leaves behind the
    start basis of the next evaluation's R (unique up to round-off), so across output times
    its motion agrees to round-off: measured 7e-15, 8e-14 and 2e-15 m over 1 s."""
    case, model, st = _model(name)
    times = case.times[case.times <= 1.0 + 1e-12]
    solver = Solver(Maggi(compiled=True), "dop853", Adaptive(rtol=1e-8, atol=1e-10))
    every = integrate(model, st, times, solver)
    tenth = integrate(model, st, times[::10], solver)
    assert every.counters["path"] == "maggi"
    assert every.counters["steps"] == tenth.counters["steps"] > 10
    scale = max(1.0, float(np.max(np.abs(every.q))))
    assert np.max(np.abs(every.q[::10] - tenth.q)) < 1e-12 * scale


@pytest.mark.parametrize("name", ["slider_crank", "a04_bricard", "a02_four_bar_n2"])
def test_newton_bound_holds_after_a_true_newton_step(name):
    """A Newton step from q0 with the factorization at q0 leaves |Phi| below the bound of
    ks.newton_bound (the rows are quadratic), which settle uses to skip evaluating Phi: at
    every distance from the constraints, the bound is above |Phi| and not loose by more
    than the rows' structure allows."""
    case, model, st = _model(name)
    plan = sparsity.schur_plan(model.constraints, model.M)
    P = plan.kernel_args
    hq, gq = ks.newton_bound(P, model.n)
    assert hq > 0 and gq >= hq
    rng = np.random.default_rng(3)
    q = np.asarray(st.q, float)
    ws, cnt, w = ks.workspace(P), np.zeros(kernels.N_COUNTERS), np.zeros(plan.m)
    for dist in (1e-3, 1e-5, 1e-7, 1e-9):
        q0 = q + dist * rng.standard_normal(model.n)
        ks._phi_max(P, ks.NO_GK, q0, w)
        ks.refactor(P, ks.NO_GK, q0, ws, cnt)
        q1 = q0.copy()
        ks._newton_step(P, ks.NO_GK, ws, w, q1)
        e = ks._phi_max(P, ks.NO_GK, q1, w)
        bound = ks._newton_rest(q1, q0, (hq, gq))
        assert e <= bound, (dist, e, bound)
        if dist >= 1e-5:  # the quadratic part dominates: the bound is near |Phi|
            assert bound < 1e3 * e
