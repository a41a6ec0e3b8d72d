"""The paper's examples (García de Jalón & Gutiérrez-López): published angles, null spaces,
determined multipliers, agreement of the reaction methods, unit invariance, flexible model."""

import numpy as np
import pytest

import natcoord
from natcoord.dynamics.forward import Solution, accelerations, integrate
from natcoord.dynamics.solver import Fixed, Solver
from natcoord.model.kinematics import mobility
from natcoord.outputs import reactions
from tests import paper_models as paper
from tests.models import body_angle, build_model, initial_state


# ---- five-bar (Example 2) ----------------------------------------------------------------
@pytest.fixture(scope="module")
def five_bar_run():
    pm = paper.five_bar()
    # The run crosses the singular positions 0 and -180 deg, where rank Phi_q drops to 6
    # and the coupler forces go through +-infinity. Fixed steps of 1 ms (5th order, q and
    # qd projected after every step) cross them reliably; the adaptive step control can
    # stall there depending on where the samples fall (reported to the dynamics owner).
    sol = integrate(pm.model, pm.state, np.linspace(0.0, 1.8, 361),
                    Solver(method="dopri5", step=Fixed(1e-3)))
    return pm, sol, {k: pm.outputs(sol, k) for k in pm.methods}


def test_five_bar_coordinates_rows_rank_and_null_space(five_bar_run):
    pm, sol, _ = five_bar_run
    m = pm.model
    assert (m.n, m.m) == (8, 8)
    assert np.count_nonzero(np.diag(m.M)) == 4  # points 5 and 6 carry no mass: M singular
    for k in (0, 40, 150, 300):  # away from the singular positions
        q = sol.q[k]
        N, r = reactions.left_null_space(m.constraints.jacobian(q))
        assert r == 7 and N.shape == (8, 1)
        n86 = paper.five_bar_null_vector(q)
        cos = abs(N[:, 0] @ n86) / np.linalg.norm(n86)
        assert cos == pytest.approx(1.0, abs=1e-10), "ker Phi_q^T differs from Eq. (86)"
        res = reactions.min_norm(m.constraints.jacobian(q),
                                 reactions.resultant(m, sol.t[k], q, sol.qd[k], sol.qdd[k]))
        # determined: Eqs. (76), (77), (79), (81) -> rows 0, 1, 3, 5
        assert np.flatnonzero(res.determined).tolist() == [0, 1, 3, 5]


def test_five_bar_published_angles(five_bar_run):
    _, sol, out = five_bar_run
    phi = np.degrees(out["min_norm"]["phi"])
    assert phi.max() == pytest.approx(96.7, abs=0.05)
    assert phi[-1] == pytest.approx(-330.97, abs=0.05)
    assert phi.min() < -180.0  # through both singular positions, 0 and -180 deg
    assert sol.counters["max_phi"] < 1e-10


def test_five_bar_moment_about_2_is_the_same_for_every_method(five_bar_run):
    _, _, out = five_bar_run
    ref = out["min_norm"]["N34"] + 2 * out["min_norm"]["N56"]
    for method, o in out.items():
        s = o["N34"] + 2 * o["N56"]
        assert np.allclose(s, ref, rtol=1e-9, atol=1e-9), method
    # while the individual forces do differ between methods
    assert np.max(np.abs(out["weighted_KL1_KT1000"]["N34"] - out["min_norm"]["N34"])) > 1.0
    assert np.max(np.abs(out["weighted_KL1000_KT1"]["N56"] -
                         out["weighted_KL1_KT1000"]["N56"])) > 1.0


def test_five_bar_unit_invariance_millimetres(five_bar_run):
    pm, sol, out = five_bar_run
    pmm = paper.five_bar(unit=1e-3)
    sel = slice(0, None, 12)
    t, q, qd = sol.t[sel], sol.q[sel] * 1e3, sol.qd[sel] * 1e3
    qdd = np.array([accelerations(pmm.model, a, b, tt)[0]
                    for a, b, tt in zip(q, qd, t, strict=True)])
    assert np.allclose(qdd * 1e-3, sol.qdd[sel], rtol=1e-8, atol=1e-8)
    smm = Solution(t, q, qd, qdd, np.zeros((len(t), 8)))
    inv, plain = pmm.outputs(smm, "unit_invariant"), pmm.outputs(smm, "min_norm")
    for name in ("N34", "N56"):
        ref = out["unit_invariant"][name][sel]
        assert np.allclose(inv[name], ref, rtol=1e-9, atol=1e-9), name
        # the plain minimum norm depends on the unit (Wojtyra & Frączek)
        assert np.max(np.abs(plain[name] - out["min_norm"][name][sel])) > 1.0, name


# ---- 3-D four-bar (Example 1) --------------------------------------------------------------
@pytest.fixture(scope="module")
def four_bar_runs():
    pm = paper.four_bar_3d()
    case = natcoord.load_case("cases/four_bar.toml")
    m2 = build_model(case)
    sol2 = integrate(m2, initial_state(m2), case.times)
    sol3 = integrate(pm.model, pm.state, case.times)
    return pm, sol3, m2, sol2


def test_four_bar_3d_mobility(four_bar_runs):
    pm, *_ = four_bar_runs
    r, dof, redundant = mobility(pm.model, pm.state.q)
    assert (dof, redundant) == (1, 3)


def test_four_bar_3d_moves_like_the_2d_four_bar(four_bar_runs):
    pm, sol3, m2, sol2 = four_bar_runs
    th2 = body_angle(m2, "crank", sol2.q, sol2.qd)
    out = pm.outputs(sol3)
    assert np.max(np.abs(out["theta"] - th2)) < 1e-8
    for j in "OACD":
        rows = m2.joints[j].rows  # coincidence rows: lambda is the force
        for k, ax in ((0, "y"), (1, "z")):  # in-plane reactions, force on the second body
            assert np.allclose(out[f"{j}_{ax}"], sol2.lam[:, rows[k]], atol=1e-7), (j, ax)


def test_four_bar_3d_in_plane_reactions_determined_out_of_plane_not(four_bar_runs):
    pm, sol3, *_ = four_bar_runs
    m, k = pm.model, 60
    res = reactions.min_norm(m.constraints.jacobian(sol3.q[k]),
                             reactions.resultant(m, sol3.t[k], sol3.q[k], sol3.qd[k],
                                                 sol3.qdd[k]))
    assert res.rank == 35 and res.N.shape == (38, 3)
    for j in "OACD":
        x, y, z = m.rows[j][:3]
        assert res.determined[y] and res.determined[z] and not res.determined[x], j
    # the out-of-plane components are undetermined: another method gives other values
    w = reactions.unit_invariant(m.constraints.jacobian(sol3.q[k]),
                                 reactions.resultant(m, sol3.t[k], sol3.q[k], sol3.qd[k],
                                                     sol3.qdd[k]),
                                 row_scales=np.linspace(1.0, 5.0, m.m))
    assert np.allclose(w.lam[res.determined], res.lam[res.determined], atol=1e-8)


# ---- 3-D parallelogram (Example 3) ---------------------------------------------------------
RODS = [f"{a}{p}" for a, p in paper.PARALLELOGRAM_RODS]


@pytest.fixture(scope="module")
def parallelogram_runs():
    pm, pf = paper.parallelogram_3d(), paper.parallelogram_3d(flexible=True)
    t = np.linspace(0.0, 0.5, 51)
    return pm, integrate(pm.model, pm.state, t), pf, paper.integrate_stiff(pf.model, pf.state, t)


def test_parallelogram_rank_and_determined_rods(parallelogram_runs):
    pm, sol, *_ = parallelogram_runs
    m = pm.model
    assert (m.n, m.m) == (18, 18)
    r, dof, redundant = mobility(m, sol.q[20])
    assert (r, dof, redundant) == (17, 1, 1)
    res = reactions.min_norm(m.constraints.jacobian(sol.q[20]),
                             reactions.resultant(m, sol.t[20], sol.q[20], sol.qd[20],
                                                 sol.qdd[20]))
    det = dict(zip(m.constraints.labels, res.determined, strict=True))
    assert det["K5"] and det["M6"]
    assert not any(det[r] for r in ("A1", "C2", "E3", "G4"))
    # the self-equilibrating set: alternating signs on the four parallel rods (Eq. (108))
    n = res.N[[m.rows[r][0] for r in ("A1", "C2", "E3", "G4")], 0]
    assert np.allclose(n / n[0], [1, -1, 1, -1], atol=1e-9)


def test_parallelogram_weighted_matches_flexible_rods(parallelogram_runs):
    pm, sol, pf, solf = parallelogram_runs
    assert np.max(np.abs(pm.outputs(sol)["phi"] - pf.outputs(solf)["phi"])) < 1e-4
    w, flex = pm.outputs(sol, "weighted"), pf.outputs(solf)
    late = sol.t >= 0.1  # the flexible transient (time constant c/k ~ 6 ms) has decayed
    for rod in RODS:
        err = np.max(np.abs(w[rod][late] - flex[rod][late]))
        assert err <= 0.01 * np.max(np.abs(flex[rod][late])), rod
    # the plain minimum norm does not (the rods are not symmetric about the load)
    mn = pm.outputs(sol, "min_norm")
    assert np.max(np.abs(mn["A1"][late] - flex["A1"][late])) > 0.1 * np.max(flex["A1"][late])
    # all methods agree on the determined rods
    for rod in ("K5", "M6"):
        assert np.allclose(mn[rod], w[rod], atol=1e-8)
