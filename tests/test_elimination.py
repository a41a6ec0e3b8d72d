"""The elimination of coordinates through the constant linear rows (natcoord.compiled.elimination):
the model over the coordinates it keeps is the same model, and both loops project in its
metric."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

from natcoord.case import casefile
from natcoord.compiled import general as kg
from natcoord.compiled import index1 as kernels
from natcoord.compiled import sparse as ks
from natcoord.compiled import sparsity
from natcoord.compiled.elimination import eliminate, linear_rows
from natcoord.dynamics.common import Counters, compiled_forces
from natcoord.dynamics.index1 import Index1Loop
from natcoord.model import casemodel
from natcoord.model.drivers import ConstraintSystem

from .conftest import CASES

# case: (coordinates kept, rows left) of (n, m); the first seven have a singular M
ELIMINATED = {"five_bar": (4, 4), "parallelogram_3d": (9, 9),
              "parallelogram_3d_flexible": (9, 3), "pendulum": (2, 1), "a01_pendulum": (2, 1),
              "a03_andrews": (8, 7), "a05_flyball_governor": (37, 33),
              "slider_crank": (3, 2), "four_bar": (4, 3), "a02_four_bar_n2": (6, 5),
              "a04_bricard": (38, 38), "slider_crank_3d": (20, 19)}


# A02 N = 2 runs on its shared points, which leave no constant linear row to eliminate; its
# joints model (one point per body and joint rows) still exercises the elimination
COORDINATES = {"a02_four_bar_n2": "joints"}


def _model(name):
    case = casefile.load_case(CASES / f"{name}.toml")
    engine = case.engines.get("natcoord")
    coords = COORDINATES.get(name) or (getattr(engine, "settings", None) or {}).get(
        "coordinates", "joints")
    cm = casemodel.build(case, coords)
    return cm.model, casemodel.initial_state(cm)


@pytest.mark.parametrize("name", ELIMINATED)
def test_the_kept_coordinates_carry_the_same_model(name):
    """At a random q_r: the solved rows vanish at q = T q_r + b, every other row equals
    its reduced form, M_r = T^T M T is regular, and the reduced forces are T^T Q; at the
    initial state with a random admissible velocity, T qdd_r equals the QR null-space
    accelerations of the whole model."""
    model, st = _model(name)
    con, M, frc = ConstraintSystem(model).con, np.asarray(model.M, float), compiled_forces(model)
    e = eliminate(con, M, frc)
    assert e is not None and (e.con.n, e.con.m) == ELIMINATED[name]
    massless = np.flatnonzero(~np.any(M != 0.0, axis=0))
    assert set(massless) <= set(e.dep)  # all of them went (by a row that holds them)
    rng = np.random.default_rng(11)
    qr, vr = rng.standard_normal(len(e.keep)), rng.standard_normal(len(e.keep))
    q, v = e.T @ qr + e.b, e.T @ vr
    phi = con.phi(q)
    assert np.max(np.abs(phi[e.rows])) < 1e-14 * max(1.0, np.max(np.abs(q)))
    rest = np.setdiff1d(np.arange(con.m), e.rows)
    assert e.con.labels == tuple(con.labels[r] for r in rest)
    assert np.max(np.abs(e.con.phi(qr) - phi[rest])) < 1e-13 * max(1.0, np.max(np.abs(phi)))
    T = e.T.toarray()
    assert np.array_equal(T[e.keep], np.eye(len(e.keep)))
    assert np.allclose(e.M, T.T @ M @ T, rtol=0, atol=1e-14 * np.max(np.abs(M)))
    assert np.min(np.linalg.eigvalsh(e.M)) > 0.0
    Q, Qr = np.zeros(len(q)), np.zeros(len(qr))
    kg.forces(frc, q, v, Q)
    kg.forces(e.frc, qr, vr, Qr)
    assert np.max(np.abs(Qr - e.T.T @ Q)) < 1e-12 * max(1.0, np.max(np.abs(Qr)))
    q0 = np.asarray(st.q, float)
    N = null_space(con.jacobian(q0))
    qd0 = np.asarray(st.qd, float) + N @ rng.standard_normal(N.shape[1])
    ref = Index1Loop(model, {"linsolve": "qr"}, Counters()).accelerations(0.0, q0, qd0)
    plan = sparsity.schur_plan(e.con, e.M)
    qdd = np.zeros(len(e.keep))
    ks.accelerations(plan.kernel_args, ks.NO_GK, e.frc, q0[e.keep], qd0[e.keep], qdd,
                     ks.workspace(plan.kernel_args), np.zeros(kernels.N_COUNTERS), True)
    assert np.max(np.abs(e.T @ qdd - ref)) < 1e-10 * max(1.0, np.max(np.abs(ref)))


def test_a_massless_coordinate_no_linear_row_fixes_leaves_m_r_singular():
    """four_bar_3d: 18 massless coordinates (its slender bodies' unit vectors, held by
    quadratic rows) and 16 linear rows. The elimination takes 16 coordinates; M_r stays
    singular on the unit vectors, so the general QR path runs on the 20 kept (22 rows
    instead of 38), and both loops project by minimum norm there: the linear rows hold
    exactly, the correction dq_r lies in the range of J_r^T."""
    model, st = _model("four_bar_3d")
    con, M = ConstraintSystem(model).con, np.asarray(model.M, float)
    assert len(linear_rows(con)[0]) == 16 and np.sum(~np.any(M != 0.0, axis=0)) == 18
    e = eliminate(con, M, compiled_forces(model))
    assert (len(e.dep), len(e.keep), e.con.m) == (16, 20, 22)
    assert not e.regular and e.Lt is None
    form = Index1Loop(model, {}, Counters())
    assert form.compiled_candidate("dop853", None)
    form.prepare_compiled(np.asarray(st.q, float))
    assert form.compiled_path == "general"
    rng = np.random.default_rng(2)
    q0, qd0 = np.asarray(st.q, float), np.asarray(st.qd, float)
    qp = q0 + 1e-7 * (e.T @ rng.standard_normal(len(e.keep)))
    q, qd = form.project(0.0, qp, qd0)
    assert np.max(np.abs(con.phi(q))) < 1e-12
    assert np.max(np.abs(con.jacobian(q) @ qd)) < 1e-12
    assert np.max(np.abs(e.T @ q[e.keep] + e.b - q)) < 1e-14  # linear rows exact
    Jr = e.con.jacobian(qp[e.keep])
    dq = q[e.keep] - qp[e.keep]
    coef, *_ = np.linalg.lstsq(Jr.T, dq, rcond=None)
    assert np.max(np.abs(Jr.T @ coef - dq)) < 1e-6 * np.max(np.abs(dq))  # min-norm


@pytest.mark.parametrize("name", ["five_bar", "parallelogram_3d"])
def test_projection_is_m_orthogonal_in_the_kept_coordinates(name):
    """The Python loop's projection of a perturbed state: the linear rows hold exactly,
    the other rows to the projection tolerance, the correction of the kept coordinates is
    M_r-orthogonal to the constraint manifold (M_r dq_r in the range of J_r^T) and the
    velocity satisfies Phi_q qd = 0. It is what the compiled loop does: its run from the
    same state lands on the same point."""
    model, st = _model(name)
    form = Index1Loop(model, {}, Counters())
    e = form.elimination
    rng = np.random.default_rng(4)
    q0, qd0 = np.asarray(st.q, float), np.asarray(st.qd, float)
    qp = q0 + 1e-6 * (e.T @ rng.standard_normal(len(e.keep)))  # (redundant rows: a larger
    # step leaves the redundancy and Newton with it)
    vp = qd0 + 1e-3 * rng.standard_normal(len(q0))
    q, qd = form.project(0.0, qp, vp)
    cs = ConstraintSystem(model)
    assert np.max(np.abs(cs.phi(q, 0.0))) < 1e-13
    assert np.max(np.abs(cs.jacobian(q, 0.0) @ qd)) < 1e-12
    dq = (q - qp)[e.keep]
    assert np.max(np.abs(dq)) > 1e-7  # it moved
    Jr = e.con.jacobian(qp[e.keep])  # simplified Newton: the Jacobian at the start
    lam, *_ = np.linalg.lstsq(Jr.T, e.M @ dq, rcond=None)
    assert np.max(np.abs(Jr.T @ lam - e.M @ dq)) < 1e-8 * np.max(np.abs(e.M @ dq))
    run = Index1Loop(model, {}, Counters())
    assert run.compiled_candidate("dop853", None)
    run.init(0.0, qp, vp)
    Q, QD, _ = run.run_compiled(np.array([0.0, 1e-9]), np.concatenate([qp, vp]),
                                 "dop853", 1e-10, 1e-12)
    assert run.compiled_path == "generated"
    assert np.max(np.abs(Q[0] - q)) < 1e-12
    assert np.max(np.abs(QD[0] - qd)) < 1e-10


def test_a_chain_keeps_its_shared_points(tmp_path):
    """An N-four-bar (N = 32, joints): eliminating the points its links share would couple
    every link in one block of M_r (M_r^-1 dense, the Schur path no longer linear in N), so
    no massive coordinate goes and, its M being regular, there is no elimination; its first
    two links alone would be eliminated (A02 N = 2)."""
    from natcoord.case.generate import n_four_bar
    from natcoord.compiled import elimination as el
    from natcoord.compiled.sparsity import blocks

    path = tmp_path / "a02_four_bar_n32.toml"
    path.write_text(n_four_bar(32))
    model = casemodel.build(casefile.load_case(path), "joints").model
    con, M = ConstraintSystem(model).con, np.asarray(model.M, float)
    _, Ac = linear_rows(con)
    _, _, _, T, _ = el._solve(Ac, np.zeros(model.n, bool), True)
    assert max(map(len, blocks(T.T @ (T.T @ M).T))) > el.MAX_BLOCK
    assert eliminate(con, M, compiled_forces(model)) is None
    assert max(map(len, blocks(M))) <= 4
