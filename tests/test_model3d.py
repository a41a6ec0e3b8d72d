"""3-D natural coordinates: constraint kinds against finite differences, the constant mass
matrix against rigid-body kinetic energy, forces against virtual power."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from natcoord.model.builder import Builder
from natcoord.model.model import (
    GROUND,
    plate_second_moment,
    rod_second_moment,
    second_moment,
)


def _rot(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q * np.sign(np.diag(R))


def _two_bodies(seed: int) -> tuple[Builder, dict]:
    """Two 2-point-2-vector bodies at random poses, plus loose elements."""
    rng = np.random.default_rng(seed)
    b = Builder(dim=3)
    geo = {}
    for name in ("a", "b"):
        R, o = _rot(rng), rng.normal(size=3)
        b.point(f"{name}0", o)
        b.point(f"{name}1", o + R[:, 0] * rng.uniform(0.5, 2))
        b.vector(f"{name}u", R[:, 1])
        b.vector(f"{name}v", R[:, 2])
        geo[name] = (R, o)
    b.point("p", rng.normal(size=3))
    b.vector("w", _rot(rng)[:, 0])
    b.fixed_point("F", rng.normal(size=3))
    for name in ("a", "b"):
        b.body(name, [f"{name}0", f"{name}1", f"{name}u", f"{name}v"], mass=1.0,
               com=geo[name][1], second_moment=0.1 * np.eye(3))
    return b, geo


KINDS = {
    "distance": lambda b, g, x: b.distance("a0", "p"),
    "rod_to_fixed": lambda b, g, x: b.rod("rod", "F", "b1"),
    "dot_vectors": lambda b, g, x: b.dot("au", "w"),
    "dot_point_vector": lambda b, g, x: b.dot(("a0", "p"), "bv"),
    "dot_points": lambda b, g, x: b.dot(("a0", "a1"), ("b0", "p"), 0.3),
    "unit": lambda b, g, x: b.unit("w"),
    "linear": lambda b, g, x: b.linear({"a0": 1.0, "b1": -2.0, "p": 1.0}, const=x[:3]),
    "attach_point": lambda b, g, x: b.attach("p", "a"),
    "attach_vector": lambda b, g, x: b.attach("w", "b"),
    "coincident": lambda b, g, x: b.coincident(b.at("a", x[:3]), b.at("b", x[:3]), "c"),
    "spherical": lambda b, g, x: b.spherical("S", "a", "b", x[:3]),
    "revolute": lambda b, g, x: b.revolute("R", "a", "b", x[:3], x[3:]),
    "revolute_ground": lambda b, g, x: b.revolute("R", GROUND, "b", x[:3], x[3:]),
    "prismatic": lambda b, g, x: b.prismatic("P", "a", "b", x[:3], x[3:]),
    "cylindrical": lambda b, g, x: b.cylindrical("C", "a", "b", x[:3], x[3:]),
    "universal": lambda b, g, x: b.universal("U", "a", "b", x[:3], x[3:],
                                             np.cross(x[3:], [0.3, 0.1, 1.0])),
}


@pytest.mark.parametrize("kind", sorted(KINDS))
@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10**6))
def test_jacobian_and_acceleration_term_match_finite_differences(kind, seed):
    b, geo = _two_bodies(seed)
    rng = np.random.default_rng(seed + 1)
    x = np.concatenate([rng.normal(size=3), _rot(rng)[:, 0]])
    KINDS[kind](b, geo, x)
    model = b.build()
    con = model.constraints
    q = model.q0 + 0.3 * rng.normal(size=model.n)  # off the manifold: the forms are global
    qd = rng.normal(size=model.n)
    h = 1e-6
    J = con.jacobian(q)
    Jfd = np.array([(con.phi(q + h * e) - con.phi(q - h * e)) / (2 * h)
                    for e in np.eye(model.n)]).T
    assert np.allclose(J, Jfd, atol=1e-6 * max(1.0, np.abs(J).max())), \
        f"{kind}: Jacobian differs from finite differences"
    # d/dt (Phi_q qd) along qd = qd^T H qd (the velocity part of the acceleration rhs)
    dJ = (con.jacobian(q + h * qd) - con.jacobian(q - h * qd)) / (2 * h) @ qd
    assert np.allclose(con.quad_velocity(qd), dJ, atol=1e-6 * max(1.0, np.abs(dJ).max())), \
        f"{kind}: acceleration term differs from finite differences"
    if kind not in ("linear", "dot_points"):  # the others take their values from q0
        assert np.abs(con.phi(model.q0)).max() < 1e-12, f"{kind}: q0 violates the rows"


JOINT_ROWS = {"spherical": 3, "revolute": 5, "cylindrical": 4, "prismatic": 5, "universal": 4}


@pytest.mark.parametrize("kind", sorted(JOINT_ROWS))
def test_joint_rows_are_independent_and_remove_the_right_freedoms(kind):
    b, geo = _two_bodies(7)
    x = np.array([0.2, -0.1, 0.4, 0.0, 0.6, 0.8])
    KINDS[kind](b, geo, x)
    model = b.build()
    J = model.constraints.jacobian(model.q0)
    joint = model.rows[kind[0].upper()]
    assert len(joint) == JOINT_ROWS[kind]
    rigid = model.m - len(joint)
    assert np.linalg.matrix_rank(J) == rigid + JOINT_ROWS[kind]  # no redundancy
    # a loose point and a loose vector: 3 + 2 freedoms; two bodies 12 minus the joint rows
    assert model.n - np.linalg.matrix_rank(J) == 5 + 12 - JOINT_ROWS[kind]


def _rigid_motion(model, body, rng):
    """Velocities of a random rigid motion of ``body`` (others at rest): qd, v_o, omega."""
    bd = model.bodies[body]
    v0, w = rng.normal(size=3), rng.normal(size=3)
    qd = np.zeros(model.n)
    for name in bd.basis:
        e = model.elements[name]
        if e.fixed:
            continue
        qd[e.cols] = np.cross(w, e.x0) + (v0 if e.kind == "point" else 0.0)
    return qd, v0, w


@pytest.mark.parametrize("basis", ["2p2v", "3p1v", "4p", "1p3v", "3p_plate"])
def test_mass_matrix_gives_rigid_body_kinetic_energy(basis):
    rng = np.random.default_rng(11)
    R, o = _rot(rng), rng.normal(size=3)
    b = Builder(dim=3)
    pts = {"2p2v": 2, "3p1v": 3, "4p": 4, "1p3v": 1, "3p_plate": 3}[basis]
    vecs = {"2p2v": 2, "3p1v": 1, "4p": 0, "1p3v": 3, "3p_plate": 0}[basis]
    offs = [np.zeros(3), R[:, 0], R[:, 1], R[:, 2] + 0.2 * R[:, 0]]
    for k in range(pts):
        b.point(f"p{k}", o + offs[k])
    for k in range(vecs):
        b.vector(f"v{k}", R[:, 3 - vecs + k])
    mass, g = 2.5, o + R @ np.array([0.3, 0.2, 0.1 if basis != "3p_plate" else 0.0])
    if basis == "3p_plate":
        I = 0.0
        Jg = plate_second_moment(mass, 0.5 * R[:, 0], 0.4 * R[:, 1])
        I = np.trace(Jg) * np.eye(3) - Jg
    else:
        I = R @ np.diag([0.3, 0.5, 0.7]) @ R.T
        Jg = second_moment(I)
    b.body("B", [f"p{k}" for k in range(pts)] + [f"v{k}" for k in range(vecs)], mass=mass,
           com=g, second_moment=Jg)
    model = b.build()
    J = model.constraints.jacobian(model.q0)
    assert model.n - np.linalg.matrix_rank(J) == 6, "a rigid body has 6 freedoms"
    qd, v0, w = _rigid_motion(model, "B", rng)
    assert np.abs(J @ qd).max() < 1e-12
    vg = v0 + np.cross(w, g)
    T = 0.5 * mass * vg @ vg + 0.5 * w @ I @ w
    assert model.kinetic_energy(qd) == pytest.approx(T, rel=1e-12)
    # gravity: virtual power Q . qd = m g . v_G
    assert model.Q0 @ qd == pytest.approx(mass * np.array([0, 0, -9.81]) @ vg, rel=1e-12)


def test_forces_torques_and_springs_have_the_right_virtual_power():
    rng = np.random.default_rng(5)
    b, geo = _two_bodies(5)
    tau, F, x = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    b.torque("a", tau)
    b.force("a", x, F)
    model = b.build()
    q = model.q0
    qd, v0, w = _rigid_motion(model, "a", rng)
    g = model.bodies["a"].com
    power = (F @ (v0 + np.cross(w, x)) + tau @ w
             + 1.0 * np.array([0, 0, -9.81]) @ (v0 + np.cross(w, g)))
    assert model.forces(0.0, q, qd) @ qd == pytest.approx(power, rel=1e-10)

    b2 = Builder(dim=3, gravity=np.zeros(3))
    b2.point("p", (1.0, 0.0, 0.0))
    b2.fixed_point("O", (0.0, 0.0, 0.0))
    b2.spring("s", b2.E("O"), b2.E("p"), k=100.0, c=2.0, l0=0.5)
    m2 = b2.build()
    Q = m2.forces(0.0, np.array([2.0, 0.0, 0.0]), np.array([3.0, 1.0, 0.0]))
    assert np.allclose(Q, [-(100.0 * 1.5 + 2.0 * 3.0), 0.0, 0.0])
    assert m2.spring_tension(np.array([[2.0, 0, 0]]), np.array([[3.0, 1, 0]]))["s"][0] == 156.0


def test_body_mass_outside_its_basis_is_refused():
    b = Builder(dim=3)
    b.point("p0", (0.0, 0.0, 0.0))
    b.point("p1", (1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="outside the span"):
        b.body("rod", ["p0", "p1"], mass=1.0, com=(0.5, 0.0, 0.0),
               second_moment=0.1 * np.eye(3))


def test_slender_rod_on_two_points_and_elements_after_bodies():
    b = Builder(dim=3)
    b.point("p0", (0.0, 0.0, 0.0))
    b.point("p1", (2.0, 0.0, 0.0))
    b.body("rod", ["p0", "p1"], mass=3.0, com=(1.0, 0.0, 0.0),
           second_moment=rod_second_moment(3.0, (0, 0, 0), (2, 0, 0)))
    with pytest.raises(RuntimeError):
        b.point("late", (0.0, 0.0, 0.0))
    model = b.build()
    qd = np.concatenate([np.zeros(3), [0.0, 2.0, 0.0]])  # rotation about p0 at 1 rad/s
    assert model.kinetic_energy(qd) == pytest.approx(0.5 * 3.0 * 4.0 / 3.0)
