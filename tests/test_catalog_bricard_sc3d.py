"""IFToMM A04 (Bricard) and the IFToMM spatial rigid slider-crank: redundancy and mobility,
energy conservation, the mirror symmetry of Bricard's libration, which reactions a
redundant loop determines, agreement with the best engine and with published solutions."""

import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from natcoord.case.casefile import load_case
from natcoord.dynamics.forward import integrate
from natcoord.dynamics.solver import case_solver
from natcoord.model import casemodel
from natcoord.outputs import channels as outputs
from natcoord.outputs import reactions
from natcoord.outputs.result import evaluate_channels

ROOT = Path(__file__).resolve().parents[1]


def _run(name: str, times=None):
    case = load_case(ROOT / "cases" / f"{name}.toml")
    cm = casemodel.build(case, "joints")
    sol = integrate(cm.model, casemodel.initial_state(cm),
                    case.times if times is None else times,
                    case_solver({"method": "dop853", "rtol": 1e-12, "atol": 1e-14}))
    first = next(iter(outputs.reactions_by_method(cm, sol).values()))
    return case, cm, sol, evaluate_channels(case, outputs.motion(cm, sol, first.lam)), first


@pytest.fixture(scope="module")
def bricard():
    return _run("a04_bricard")


@pytest.fixture(scope="module")
def crank3d():
    return _run("slider_crank_3d")


# ---- Bricard -----------------------------------------------------------------------------
def test_bricard_one_redundant_row_and_one_dof(bricard):
    _, cm, sol, _, _ = bricard
    m = cm.model
    # Gruebler: 5 links x 6 - 6 revolutes x 5 = 0 DOF; the loop moves with 1
    assert 5 * 6 - 6 * 5 == 0
    for k in (0, 250, 500, 999):
        N, rank = reactions.left_null_space(m.constraints.jacobian(sol.q[k]))
        assert rank == m.n - 1, "Phi_q must have rank n - 1 (1 DOF)"
        assert m.m - rank == 1 and N.shape[1] == 1, "exactly one redundant row"
    d = outputs.diagnostics(cm, sol.q[0])
    assert (d["dof"], d["redundant"]) == (1, 1)


def test_bricard_energy_drift(bricard):
    _, _, sol, ch, _ = bricard
    e = ch["energy"].to_numpy()
    assert e[0] == pytest.approx(-3 * 9.81 * 1.0, abs=1e-12)  # links 2, 3, 4 at y = -1
    assert np.ptp(e) < 1e-8
    assert sol.counters["max_phi"] < 1e-10
    assert np.ptp(ch["yP3"]) > 0.1  # it does move


def test_bricard_mirror_libration(bricard):
    """The ground joints (y axis at O1, x axis at P6) and gravity are symmetric under
    x -> -x: P3 librates between the start pose and its mirror, P3(t + T/2) = mirror P3(t)."""
    case, _, _, ch, _ = bricard
    t, x = case.times, ch["xP3"].to_numpy()
    k = int(np.argmin(np.where(t < 3.0, x, np.inf)))  # the first mirror pose, at rest
    half = t[k]
    assert x[k] == pytest.approx(-1.0, abs=1e-3) and 2.0 < half < 3.0
    # refine the half period: x is quadratic about the turning point (vertex of 3 samples)
    h = case.output_dt
    x0, x1, x2 = x[k - 1], x[k], x[k + 1]
    half += h * (x0 - x2) / (2 * (x0 - 2 * x1 + x2))
    s = np.arange(0.0, 10.0 - half, 0.05)  # from t = 0: integrate starts at the first time
    _, _, _, a, _ = _run("a04_bricard", s)
    _, _, _, b, _ = _run("a04_bricard", np.concatenate([[0.0], s + half]))
    b = b.iloc[1:].reset_index(drop=True)
    assert b["xP3"][0] == pytest.approx(-1.0, abs=1e-6)
    assert np.max(np.abs(b["xP3"] + a["xP3"])) < 5e-7  # measured 4.7e-8 m
    assert np.max(np.abs(b["yP3"] - a["yP3"])) < 5e-7
    assert np.max(np.abs(b["zP3"] - a["zP3"])) < 5e-7


def test_bricard_determined_and_undetermined_reactions(bricard):
    """One self-stress wrench runs round the loop: every world component of every joint
    force is undetermined, their differences J1 - J3, J1 - J6 are determined."""
    case, cm, sol, _, r = bricard
    und = set(outputs.undetermined(cm, sol, r))
    joints = {c.name for c in case.channels if c.kind == "reaction"}
    combos = {c.name for c in case.channels if c.kind == "combination"}
    assert joints and combos
    assert und == joints
    assert not und & combos


# ---- spatial slider-crank ----------------------------------------------------------------
def test_slider_crank_3d_energy_and_dof(crank3d):
    _, cm, sol, ch, _ = crank3d
    d = outputs.diagnostics(cm, sol.q[0])
    assert (d["dof"], d["redundant"]) == (1, 0)
    assert ch["theta"][0] == pytest.approx(0.0, abs=1e-12)
    assert ch["xC"][0] == pytest.approx(0.2, abs=1e-12)
    assert np.ptp(ch["energy"]) < 1e-10
    assert ch["theta"].iloc[-1] > 8 * 2 * np.pi  # it turns over: > 8 revolutions in 5 s


def test_slider_crank_3d_agrees_with_pinocchio(crank3d, tmp_path):
    """Pinocchio (RK4, 4th order: 1.4e-4, 8.9e-6, 2.3e-7 rad at dt 5e-4, 2.5e-4, 1e-4)
    at dt 2.5e-4 must sit within its own measured error of natcoord."""
    from natcoord.engines import pinocchio_engine
    from natcoord.engines.base import initial_body_states

    case, _, _, ch, _ = crank3d
    run = pinocchio_engine.run(case, initial_body_states(case), {"dt": 2.5e-4, "mu": 1e-8})
    pin = evaluate_channels(case, run.motion)
    e = float(np.max(np.abs(pin["theta"] - ch["theta"])))
    assert 1e-7 < e < 2e-5  # the truncation error of RK4 at dt 2.5e-4: measured 8.9e-6
    assert float(np.max(np.abs(pin["xC"] - ch["xC"]))) < 5e-7


def test_slider_crank_3d_published_solutions(crank3d):
    case, _, _, ch, _ = crank3d
    pub = tomllib.loads((ROOT / "references" / "published.toml").read_text())["slider_crank_3d"]
    idx = [int(round(t / case.output_dt)) for t in pub["t"]]
    dx = np.abs(ch["xC"].to_numpy()[idx] - np.array(pub["x_gonzalez"]))
    assert dx.max() < pub["tolerance_x_gonzalez"]  # measured 4.2e-5 m over 5 s
    assert dx[:2].max() < 2e-6  # 1.8e-6 m at 0.1 s, 1.7e-7 m at 0.5 s
    idx = [int(round(t / case.output_dt)) for t in pub["masarati_t"]]
    assert np.abs(ch["xC"].to_numpy()[idx] - pub["x_masarati"]).max() < 1e-3
    assert abs(ch["theta"][idx[0]] - pub["theta_masarati"][0]) < 2e-5
    assert np.abs(ch["theta"].to_numpy()[idx] - pub["theta_masarati"]).max() < 2e-2


def test_slider_crank_3d_reference_is_stored():
    ref = pd.read_csv(ROOT / "references" / "slider_crank_3d.csv")
    assert list(ref.columns) == ["t", "theta", "xC", "energy"]
    assert ref["t"].iloc[-1] == pytest.approx(5.0)
