"""A case in 3-D and back: the one place where a planar case becomes spatial, and where
MuJoCo's spatial samples become a planar :class:`~natcoord.result.Motion` again.

A 2-D case is the planar case of the 3-D model: points (x, y, 0), a 2-D revolute a hinge
about z, a 2-D prismatic axis (ax, ay, 0), gravity (gx, gy, 0), a 2-D torque (0, 0, tau) and a
scalar inertia ``i`` the tensor ``i I``. Only Izz acts in the plane; Ixx = Iyy = Izz keeps
MuJoCo's triangle inequality. Nothing can push a lifted body out of the plane, so the model
builder needs no dimension.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...mechanism import Body, Case, Force, Joint
from ...result import Motion

Z = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass(frozen=True)
class Frame:
    """A body frame at t = 0 in 3-D: origin (3,) m, rotation (3, 3) body-to-world, velocity
    (3,) m/s of the origin, omega (3,) rad/s, all world axes."""

    origin: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray


GROUND_FRAME = Frame(np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3))


def pad3(v) -> np.ndarray:
    """(d,) -> (3,): a planar vector gets z = 0."""
    v = np.asarray(v, float)
    return np.concatenate([v, np.zeros(3 - len(v))])


def _inertia3(inertia) -> np.ndarray:
    """A scalar (planar) inertia, kg m^2, as the isotropic tensor; a tensor as it is."""
    if np.ndim(inertia) == 0:
        return float(inertia) * np.eye(3)
    return np.asarray(inertia, float)


def _body(b: Body) -> Body:
    return dataclasses.replace(b, points={p: pad3(x) for p, x in b.points.items()},
                               com=pad3(b.com), inertia=_inertia3(b.inertia))


def _joint(j: Joint) -> Joint:
    """A planar revolute turns about z; every axis becomes (3,)."""
    axis = Z if j.axis is None and j.type == "revolute" else j.axis
    return dataclasses.replace(j, axis=None if axis is None else pad3(axis),
                               axis2=None if j.axis2 is None else pad3(j.axis2))


def _force(f: Force) -> Force:
    """A planar torque is about z; a force (d,) gets z = 0."""
    if f.type == "torque" and np.ndim(f.value) == 0:
        return dataclasses.replace(f, value=float(f.value) * Z)
    return dataclasses.replace(f, value=pad3(f.value))


def lift_case(case: Case) -> Case:
    """The case with every vector (3,) and every inertia (3, 3); a 3-D case is unchanged in
    value. Names, times, channels and settings are kept."""
    return dataclasses.replace(
        case, dimension=3, gravity=pad3(case.gravity),
        ground={p: pad3(x) for p, x in case.ground.items()},
        bodies=tuple(_body(b) for b in case.bodies),
        joints=tuple(_joint(j) for j in case.joints),
        forces=tuple(_force(f) for f in case.forces))


def lift_init(case: Case, init) -> dict[str, Frame]:
    """Every body's frame at t = 0 (``init[body]``, a :class:`~natcoord.engines.base.BodyState`)
    in 3-D; a planar omega (scalar) is about z."""
    out = {}
    for b in case.bodies:
        st = init[b.name]
        w = st.omega * Z if np.ndim(st.omega) == 0 else np.asarray(st.omega, float)
        out[b.name] = Frame(pad3(st.origin), st.rotation3(), pad3(st.velocity), w)
    return out


@dataclasses.dataclass
class Samples:
    """MuJoCo's samples in 3-D, world axes: body -> origin (T, 3) m, rotation (T, 3, 3),
    velocity (T, 3) m/s, omega (T, 3) rad/s; joint -> force on its second body (T, 3) N;
    rod or spring -> tension (T,) N."""

    origin: dict
    rotation: dict
    velocity: dict
    omega: dict
    forces: dict
    rod_force: dict

    @classmethod
    def empty(cls, case: Case, T: int) -> Samples:
        names = [b.name for b in case.bodies]
        return cls({n: np.zeros((T, 3)) for n in names},
                   {n: np.zeros((T, 3, 3)) for n in names},
                   {n: np.zeros((T, 3)) for n in names},
                   {n: np.zeros((T, 3)) for n in names},
                   {j.name: np.zeros((T, 3)) for j in case.joints},
                   {r.name: np.zeros(T) for r in (*case.rods, *case.springs)})


def to_motion(case: Case, s: Samples) -> Motion:
    """The neutral Motion of the (original, unlifted) ``case``: in 2-D the angle of each
    frame's x axis (unwrapped), omega about z, (T, 2) vectors; in 3-D the samples as they are."""
    t = np.asarray(case.times, float)
    if case.dimension == 3:
        return Motion(t, s.origin, {}, s.velocity, s.omega, s.forces, rotation=s.rotation,
                      rod_force=s.rod_force)
    angle = {n: np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0])) for n, R in s.rotation.items()}
    flat = lambda d: {k: v[:, :2] for k, v in d.items()}  # noqa: E731
    return Motion(t, flat(s.origin), angle, flat(s.velocity),
                  {n: w[:, 2] for n, w in s.omega.items()}, flat(s.forces),
                  rod_force=s.rod_force)
