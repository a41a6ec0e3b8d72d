"""Kinematics: mobility, coordinate partitioning, driven position and acceleration problems."""

from __future__ import annotations

import dataclasses

import numpy as np

from natcoord import load_case
from natcoord.case.mechanism import Joint
from natcoord.dynamics.common import full_pivot_partition
from natcoord.model.drivers import ConstraintSystem
from natcoord.model.kinematics import (
    kinematic_analysis,
    mobility,
    solve_acceleration,
    solve_position,
)
from tests.models import build_model, coordinate, initial_state


def test_mobility_counts_dof_and_redundant_rows():
    sc = build_model(load_case("cases/slider_crank.toml"))
    assert mobility(sc, initial_state(sc).q) == (9, 1, 0)
    c = load_case("cases/four_bar.toml")
    D2 = Joint("D2", "revolute", ("ground", "rocker"), ("D", "D"))
    red = build_model(dataclasses.replace(c, joints=c.joints + (D2,)))
    assert mobility(red, initial_state(red).q) == (11, 1, 2)
    dr = build_model(load_case("cases/slider_crank_driven.toml"))
    assert mobility(dr, initial_state(dr).q, drivers=True) == (10, 0, 0)


def test_partition_gives_a_null_space_basis():
    """R of Eq. (15) from full pivoting spans ker Phi_q, also with redundant rows."""
    c = load_case("cases/four_bar.toml")
    D2 = Joint("D2", "revolute", ("ground", "rocker"), ("D", "D"))
    m = build_model(dataclasses.replace(c, joints=c.joints + (D2,)))
    J = m.constraints.jacobian(initial_state(m).q)
    rows, dep, indep, piv = full_pivot_partition(J)
    assert len(rows) == 11 and len(indep) == 1 and np.all(piv > 1e-3)
    Jd = J[np.ix_(rows, dep)]
    R = np.zeros((m.n, 1))
    R[dep] = -np.linalg.solve(Jd, J[np.ix_(rows, indep)])
    R[indep] = 1.0
    assert np.max(np.abs(J @ R)) < 1e-12  # the redundant rows too


def test_driven_position_velocity_acceleration_problems():
    m = build_model(load_case("cases/slider_crank_driven.toml"))
    s = initial_state(m)
    t = np.linspace(0, 1, 41)
    Q, QD, QDD = kinematic_analysis(m, s.q, t)
    w = 2 * np.pi
    sn, cn = np.sin(w * t), np.cos(w * t)
    D = np.sqrt(4 - sn * sn)
    xB = coordinate(m, "slider", "B")
    np.testing.assert_allclose(Q[:, xB], cn + D, atol=1e-12)
    aB = -cn * w * w - w * w * (cn * cn - sn * sn) / D - sn * sn * cn * cn * w * w / D**3
    np.testing.assert_allclose(QDD[:, xB], aB, atol=1e-10)
    cs = ConstraintSystem(m)
    q, it = solve_position(m, Q[10] + 1e-3, t[10])
    assert it <= 6 and np.max(np.abs(cs.phi(q, t[10]))) < 1e-12
    np.testing.assert_allclose(solve_acceleration(m, Q[10], QD[10], t[10]), QDD[10], atol=1e-10)
