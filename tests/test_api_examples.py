"""The Python API, as a newcomer uses it: build a model, integrate it, read the reactions.

Each example is checked against physics, not printed: a point-mass pendulum released from
horizontal keeps its energy and pulls its rod with 3 m g sin(theta) (the exact tension of a
release from rest), in every formulation; the reactions module gives the same multipliers
from the solution's accelerations.
"""

from __future__ import annotations

import numpy as np
import pytest

from natcoord import Builder, Index3, Maggi, Solver, State, integrate
from natcoord.dynamics.solver import Adaptive, Fixed
from natcoord.outputs import reactions

G, MASS, L = 9.81, 1.0, 1.0


def pendulum():
    """A 1 kg point mass P on a massless 1 m rod from the fixed point O, 2-D."""
    b = Builder(dim=2, gravity=[0.0, -G])
    b.fixed_point("O", [0.0, 0.0])
    b.point("P", [L, 0.0])
    b.body("bob", ["P"], mass=MASS)
    b.distance("O", "P", L, name="rod")
    return b.build()


@pytest.mark.parametrize("solver", [
    Solver(),  # index1, dop853, rtol 1e-10
    Solver(Maggi(), "dop853", Adaptive(rtol=1e-10, atol=1e-12)),
    Solver(Index3(), "trapezoidal", Fixed(1e-4))], ids=["index1", "maggi", "index3"])
def test_pendulum_energy_and_rod_tension(solver):
    model = pendulum()
    times = np.linspace(0.0, 1.0, 11)
    sol = integrate(model, State(np.array([L, 0.0]), np.zeros(2)), times, solver)
    x, y = sol.q[:, 0], sol.q[:, 1]
    energy = 0.5 * MASS * np.sum(sol.qd ** 2, axis=1) + MASS * G * y
    tol = 1e-6 if solver.formulation.name == "index3" else 1e-8
    assert np.max(np.abs(energy - energy[0])) < tol * MASS * G * L
    sin_theta = -y / L  # below the horizontal
    tension = model.axial("rod", sol.lam)  # N, tension positive
    assert np.max(np.abs(tension - 3 * MASS * G * sin_theta)) < 1e3 * tol * MASS * G
    assert np.allclose(np.hypot(x, y), L, atol=1e-9)


def test_reactions_from_the_solution():
    """reactions.min_norm on Phi_q and F - M qdd gives integrate's multipliers."""
    model = pendulum()
    sol = integrate(model, State(np.array([L, 0.0]), np.zeros(2)), np.linspace(0, 0.5, 6))
    from natcoord.model.drivers import ConstraintSystem
    cs = ConstraintSystem(model)
    for k in range(len(sol.t)):
        J = cs.jacobian(sol.q[k], sol.t[k])
        f = model.forces(sol.t[k], sol.q[k], sol.qd[k]) - model.M @ sol.qdd[k]
        r = reactions.min_norm(J, f)
        assert r.rank == 1 and r.residual < 1e-9
        assert np.allclose(r.lam, sol.lam[k], rtol=1e-9, atol=1e-9)
