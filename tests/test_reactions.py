"""Reactions with redundant constraints: minimum norm, weighted, left null space, existence."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from natcoord.errors import ExistenceError
from natcoord.model.builder import Builder
from natcoord.model.kinematics import State
from natcoord.model.model import rod_second_moment
from natcoord.outputs import reactions


def _redundant(seed: int, n: int, r: int, m: int):
    """Phi_q (m, n) of rank r, a resultant f in its row space, and the generator."""
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(m, r)) @ rng.normal(size=(r, n))
    Phi *= rng.uniform(0.1, 10.0, size=(m, 1))  # rows of different magnitudes (units)
    return Phi, Phi.T @ rng.normal(size=m), rng


dims = st.tuples(st.integers(0, 10**6), st.integers(2, 9), st.integers(1, 9),
                 st.integers(0, 4)).map(
    lambda t: (t[0], t[1], min(t[2], t[1]), min(t[2], t[1]) + t[3]))  # seed, n, r, m


@settings(max_examples=60, deadline=None)
@given(dims)
def test_min_norm_equals_pseudo_inverse_and_N_spans_left_kernel(d):
    seed, n, r, m = d
    Phi, f, _ = _redundant(seed, n, r, m)
    res = reactions.min_norm(Phi, f)
    assert res.rank == r and res.redundant == m - r
    scale = np.linalg.norm(np.linalg.pinv(Phi.T) @ f) + 1e-300
    assert np.allclose(res.lam, np.linalg.pinv(Phi.T) @ f, atol=1e-8 * scale)
    assert res.residual <= 1e-9 * max(1.0, np.abs(f).max())
    assert res.N.shape == (m, m - r)
    assert np.allclose(res.N.T @ res.N, np.eye(m - r), atol=1e-10)
    assert np.abs(Phi.T @ res.N).max(initial=0.0) <= 1e-9 * np.abs(Phi).max()
    # Eq. (70): [Phi_q^T; N^T] lambda = [f; 0] gives the same lambda
    lam70 = np.linalg.lstsq(np.vstack([Phi.T, res.N.T]), np.concatenate([f, np.zeros(m - r)]),
                            rcond=None)[0]
    assert np.allclose(res.lam, lam70, atol=1e-8 * scale)


@settings(max_examples=60, deadline=None)
@given(dims)
def test_weighted_min_norm_is_optimal_for_its_weights(d):
    seed, n, r, m = d
    Phi, f, rng = _redundant(seed, n, r, m)
    w = rng.uniform(0.01, 100.0, size=m)
    res = reactions.weighted(Phi, f, w)
    assert res.residual <= 1e-8 * max(1.0, np.abs(f).max())
    # stationarity of sum((lam / w)^2) on {Phi^T lam = f}: lam / w^2 ⊥ ker Phi^T
    N, _ = reactions.left_null_space(Phi)
    g = res.lam / w**2
    assert np.abs(N.T @ g).max(initial=0.0) <= 1e-8 * max(np.linalg.norm(g), 1e-300)
    # every method differs from the plain minimum norm by a self-equilibrating set only
    plain = reactions.min_norm(Phi, f)
    assert np.allclose(Phi.T @ (res.lam - plain.lam), 0.0, atol=1e-8 * max(1, np.abs(f).max()))
    assert np.array_equal(res.determined, plain.determined)
    assert np.allclose(res.lam[plain.determined], plain.lam[plain.determined],
                       atol=1e-7 * max(1.0, np.abs(plain.lam).max()))


def test_unique_multipliers_when_full_rank():
    Phi, f, _ = _redundant(3, 7, 4, 4)
    lam = np.linalg.solve(Phi @ Phi.T, Phi @ f)
    res = reactions.min_norm(Phi, f)
    assert res.rank == 4 and res.N.shape == (4, 0) and res.determined.all()
    assert np.allclose(res.lam, lam)


def test_determined_rows_of_a_duplicated_row():
    Phi = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    res = reactions.min_norm(Phi, np.array([3.0, 4.0]))
    assert res.determined.tolist() == [True, False, False]
    assert np.allclose(res.lam, [3.0, 2.0, 2.0])
    heavy = reactions.weighted(Phi, np.array([3.0, 4.0]), np.array([1.0, 3.0, 1.0]))
    assert np.allclose(heavy.lam, [3.0, 3.6, 0.4])  # lam ∝ w^2 on the redundant pair


def test_unit_invariant_scales_and_argument_check():
    assert np.allclose(reactions.unit_scales([0, 1, 2], 1000.0), [1.0, 1e-3, 1e-6])
    with pytest.raises(ValueError):
        reactions.unit_invariant(np.eye(2), np.ones(2))
    with pytest.raises(ValueError):
        reactions.weighted(np.eye(2), np.ones(2), np.array([1.0, 0.0]))


def test_stiffness_weights_eq_94():
    assert reactions.stiffness_weight(4e6, 2.0) == pytest.approx(1000.0)
    w = reactions.stiffness_weights(3, {1: (9.0, 3.0)})
    assert w.tolist() == [1.0, 1.0, 1.0]
    assert reactions.stiffness_weights(3, {2: (16.0, 2.0)})[2] == 2.0


def _dangling_massless_link():
    """Pendulum O-P (1 kg) with a massless link P-Q hanging from its tip: Q can swing
    without kinetic energy, so ker M ∩ ker Phi_q ≠ {0}."""
    b = Builder(dim=2)
    b.point("P", (1.0, 0.0))
    b.point("Q", (2.0, 0.0))
    b.fixed_point("O", (0.0, 0.0))
    b.body("link", ["O", "P"], mass=1.0, com=(0.5, 0.0),
           second_moment=rod_second_moment(1.0, (0, 0), (1, 0)))
    b.rod("PQ", "P", "Q")
    return b.build()


def test_massless_body_moving_without_kinetic_energy_is_refused():
    model = _dangling_massless_link()
    q = model.q0
    with pytest.raises(ExistenceError):
        reactions.check_existence(model.M, model.constraints.jacobian(q))
    from natcoord.dynamics import forward as dynamics

    with pytest.raises(ExistenceError):
        dynamics.integrate(model, State(q, np.zeros(model.n)), np.array([0.0, 0.01]))


def test_existence_holds_when_the_massless_link_is_closed():
    b = Builder(dim=2)
    b.point("P", (1.0, 0.0))
    b.point("Q", (2.0, 0.0))
    b.fixed_point("O", (0.0, 0.0))
    b.fixed_point("R", (2.0, -1.0))
    b.body("link", ["O", "P"], mass=1.0, com=(0.5, 0.0),
           second_moment=rod_second_moment(1.0, (0, 0), (1, 0)))
    b.rod("PQ", "P", "Q")
    b.rod("QR", "Q", "R")
    model = b.build()
    reactions.check_existence(model.M, model.constraints.jacobian(model.q0))


# ---- the batched path: every sample of a trajectory factored at once ---------------------
def _trajectory(name: str):
    from pathlib import Path

    from natcoord.case.casefile import load_case
    from natcoord.dynamics.forward import integrate
    from natcoord.dynamics.solver import case_solver
    from natcoord.model import casemodel
    case = load_case(Path(__file__).resolve().parents[1] / "cases" / f"{name}.toml")
    cm = casemodel.build(case, "joints")
    times = case.times[::4]
    sol = integrate(cm.model, casemodel.initial_state(cm), times,
                    case_solver(dict(case.engine("natcoord").settings)))
    return cm, sol


def _same_reactions(a: reactions.Reactions, b: reactions.Reactions):
    assert a.rank == b.rank
    scale = max(1.0, np.abs(b.lam).max())
    np.testing.assert_allclose(a.lam, b.lam, rtol=0, atol=1e-9 * scale)
    assert a.residual <= 1e-9 * scale and b.residual <= 1e-9 * scale
    np.testing.assert_allclose(a.N @ a.N.T, b.N @ b.N.T, rtol=0, atol=1e-10)  # same space
    assert np.array_equal(a.determined, b.determined)


def test_batched_reactions_equal_the_per_sample_ones_on_bricard(monkeypatch):
    """a04_bricard (one redundant row): along_all over 251 samples, in chunks of 7, gives
    each sample's weighted(); a sample with a row zeroed (the rank drops by one, a singular
    position's kind) is solved with its own rank beside the regular ones."""
    from natcoord.model.drivers import ConstraintSystem
    cm, sol = _trajectory("a04_bricard")
    m = cm.model
    con = ConstraintSystem(m)
    monkeypatch.setattr(reactions, "CHUNK", 7 * con.m * max(con.m, con.n))
    for w in cm.methods.values():
        batch = reactions.along_all(m, sol.t, sol.q, sol.qd, sol.qdd, w)
        assert (batch.rank == m.n - 1).all() and batch.null.shape == (len(sol.t), m.m, 1)
        for k in range(len(sol.t)):
            f = reactions.resultant(m, sol.t[k], sol.q[k], sol.qd[k], sol.qdd[k])
            _same_reactions(batch.at(k), reactions.weighted(con.jacobian(sol.q[k]), f, w))
    J = con.jacobian(sol.q, sol.t)
    f = reactions.resultant(m, sol.t, sol.q, sol.qd, sol.qdd)
    det = reactions.min_norm(J[0], f[0]).determined
    row = int(np.flatnonzero(det)[0])
    J[5, row] = 0.0  # that row no longer carries anything: rank n - 2 there
    f[5] = J[5].T @ reactions.min_norm(J[5], f[5]).lam  # a resultant it can carry
    batch = reactions.solve(J, f)
    assert batch.rank[5] == m.n - 2 and (np.delete(batch.rank, 5) == m.n - 1).all()
    assert batch.null.shape[2] == 2 and not batch.null[:4, :, 1].any()
    for k in range(10):
        _same_reactions(batch.at(k), reactions.min_norm(J[k], f[k]))


def test_batched_jacobian_with_drivers_equals_the_per_sample_one():
    from natcoord.model.drivers import ConstraintSystem
    cm, sol = _trajectory("slider_crank_driven")
    con = ConstraintSystem(cm.model)
    assert con.k > 0
    J = con.jacobian(sol.q, sol.t)
    for k in range(len(sol.t)):
        assert np.array_equal(J[k], con.jacobian(sol.q[k], sol.t[k]))
