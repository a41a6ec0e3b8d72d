"""The sparse paths of a generated N-four-bar agree with the dense ones they replace:
the rank certificate, the model check's mobility, the initial velocities, the diagnostics
and the reactions along a run; and what they handle grows linearly in N."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from natcoord.case import generate
from natcoord.case.casefile import load_case
from natcoord.model import casemodel, kinematics, sparserank
from natcoord.model.drivers import ConstraintSystem
from natcoord.model.model import support
from natcoord.outputs import channels, reactions


@pytest.fixture(autouse=True)
def sparse_from_small(monkeypatch, request):
    """These N = 4..16 models stand in for large ones: the sparse shortcuts from 1
    coordinate on (a model under SPARSE_FROM keeps the dense path, tested below)."""
    if "small_model_keeps" not in request.node.name:
        monkeypatch.setattr(sparserank, "SPARSE_FROM", 1)


def _case(tmp_path, n: int, duration: float | None = None):
    p = tmp_path / f"a02_four_bar_n{n}.toml"
    p.write_text(generate.n_four_bar(n))
    case = load_case(p)
    return case if duration is None else dataclasses.replace(case, duration=duration)


@pytest.fixture(scope="module")
def n8(tmp_path_factory):
    case = _case(tmp_path_factory.mktemp("n8"), 8)
    cm = casemodel.build(case, "joints")
    return case, cm, casemodel.initial_state(cm)


def test_the_certificate_agrees_with_the_dense_rank(n8):
    _, cm, st = n8
    cs = ConstraintSystem(cm.model)
    A = sparserank.jacobian(cs, st.q)
    assert np.array_equal(A.toarray(), cs.jacobian(st.q))
    dense_rank = np.linalg.matrix_rank(A.toarray())
    assert dense_rank == A.shape[0] and sparserank.full_row_rank(A)
    # a repeated row, and a row within 1e-9 of a combination of two others: not certified
    J = A.toarray()
    assert not sparserank.full_row_rank(np.vstack([J, J[3]]))
    near = J.copy()
    near[5] = J[3] + 2 * J[4] + 1e-9 * np.eye(1, J.shape[1], 0)[0]
    assert not sparserank.full_row_rank(near)
    assert not sparserank.full_row_rank(J.T)  # more rows than columns


def test_the_min_norm_solve_is_lstsq(n8):
    _, cm, st = n8
    A = sparserank.jacobian(ConstraintSystem(cm.model), st.q)
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    x = sparserank.min_norm_solve(A, b)
    ref = np.linalg.lstsq(A.toarray(), b, rcond=None)[0]
    assert np.max(np.abs(x - ref)) < 1e-12 * np.max(np.abs(ref))


def test_mobility_velocity_and_diagnostics_match_the_dense_path(n8, monkeypatch):
    _, cm, st = n8
    sparse = (casemodel.mobility(cm, st.q), kinematics.solve_velocity(
        cm.model, st.q, [casemodel.prescribed(cm, "x_B0", 1.0)]),
        channels.diagnostics(cm, st.q))
    monkeypatch.setattr(sparserank, "full_row_rank", lambda A, rtol=0.0: False)
    dense = (casemodel.mobility(cm, st.q), kinematics.solve_velocity(
        cm.model, st.q, [casemodel.prescribed(cm, "x_B0", 1.0)]),
        channels.diagnostics(cm, st.q))
    assert sparse[0] == dense[0] == (68, 67, 67, 0)
    assert np.max(np.abs(sparse[1] - dense[1])) < 1e-13
    assert sparse[2] == dense[2]


def test_reactions_of_the_run_match_the_dense_ones(tmp_path):
    """N = 8 over 1 s (the first singular pass at t = 0.72 s): the sparse Schur path's
    unique multipliers against the per-sample SVD. Measured: median 6e-17 of max |lambda|,
    1.2e-8 at the sample on the singular pass (conditioning there)."""
    from natcoord.dynamics.forward import integrate
    from natcoord.dynamics.solver import case_solver

    case = _case(tmp_path, 8, duration=1.0)
    cm = casemodel.build(case, "joints")
    sol = integrate(cm.model, casemodel.initial_state(cm), case.times,
                    case_solver(case.engine("natcoord").settings))
    assert sol.unique is not None and sol.unique.all()
    new = channels.reactions_by_method(cm, sol)["min_norm"]
    old = reactions.along_all(cm.model, sol.t, sol.q, sol.qd, sol.qdd)
    scale = np.max(np.abs(old.lam))
    d = np.max(np.abs(new.lam - old.lam), 1) / scale
    assert np.median(d) < 1e-14 and np.max(d) < 1e-7
    assert np.array_equal(new.rank, old.rank) and new.null.shape[2] == 0
    assert np.max(new.residual) < 1e-10 * scale


def test_what_the_sparse_paths_handle_grows_linearly(tmp_path):
    """Jacobian non-zeros a row, and every body's and joint's columns, do not grow with N."""
    per_row, cols = [], []
    for n in (4, 16):
        cm = casemodel.build(_case(tmp_path, n), "joints")
        A = sparserank.jacobian(ConstraintSystem(cm.model), cm.model.q0)
        per_row.append(A.nnz / A.shape[0])
        cols.append(max(len(support(b.G0, b.G)) for b in cm.model.bodies.values()))
        cols[-1] = max(cols[-1], max(len(support(j.maps)) for j in cm.model.joints.values()))
    assert per_row[0] == pytest.approx(per_row[1], rel=0.05) and cols[0] == cols[1]


def test_a_small_model_keeps_the_dense_path_bit_for_bit(tmp_path):
    """Under SPARSE_FROM coordinates nothing is certified and the reactions are the dense
    ones exactly: the results the catalogue's references and baselines were made with."""
    from natcoord.dynamics.forward import integrate
    from natcoord.dynamics.solver import case_solver

    case = _case(tmp_path, 8, duration=0.2)
    cm = casemodel.build(case, "joints")
    assert cm.model.n < sparserank.SPARSE_FROM
    assert not sparserank.full_row_rank(sparserank.jacobian(ConstraintSystem(cm.model),
                                                            cm.model.q0))
    sol = integrate(cm.model, casemodel.initial_state(cm), case.times,
                    case_solver(case.engine("natcoord").settings))
    new = channels.reactions_by_method(cm, sol)["min_norm"]
    old = reactions.along_all(cm.model, sol.t, sol.q, sol.qd, sol.qdd)
    assert np.array_equal(new.lam, old.lam) and np.array_equal(new.residual, old.residual)
