"""A case in 3-D and back, for the engines that only model space (MuJoCo, Pinocchio, DART):
the one place where a 2-D case becomes spatial, where natcoord's assembled state becomes 3-D
body frames, and where 3-D samples become a neutral :class:`~natcoord.outputs.result.Motion` in the
case's own dimension again.

A 2-D case is the planar case of a 3-D one (:func:`lift_case`): points (x, y, 0), a revolute
turns about z, a prismatic axis is (ax, ay, 0), gravity (gx, gy, 0), a torque (0, 0, tau)
and a scalar moment of inertia Izz the isotropic tensor ``Izz * I3``. Every joint of a
planar case turns about z and nothing can push a body out of the plane, so only Izz ever
acts: any valid tensor with that Izz gives the same motion, and the isotropic one is positive
definite (for Izz > 0) and meets the triangle inequality (MuJoCo, DART) without further
thought. What an engine needs beyond that (a point mass's substitute inertia, a floor on a
small one) is that engine's adjustment, applied to the lifted case in its adapter.

Units are SI throughout: m, m/s, rad/s, N, N m, kg m^2. Vectors are world axes unless said.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..case.mechanism import GROUND, Body, Case, Force, Joint
from ..outputs.result import Motion

Z = np.array([0.0, 0.0, 1.0])

# a rotation entry below this is assembly round-off and set to 0 (see lift_init)
ROTATION_ROUND_OFF = 1e-12


def v3(x) -> np.ndarray:
    """A 2- or 3-vector as a float (3,) vector; a 2-D one gets z = 0."""
    x = np.asarray(x, dtype=float).reshape(-1)
    return np.array([x[0], x[1], 0.0]) if x.size == 2 else x


def cross(a, b) -> np.ndarray:
    """a x b for 3-vectors, or column-wise for (3, n) arrays (np.cross costs ~30 us a call,
    which matters inside an integrator's right-hand side)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


@dataclasses.dataclass(frozen=True)
class Frame:
    """A body frame at t = 0, world axes: ``origin`` (3,) m, ``R`` (3, 3) body-to-world
    rotation, ``velocity`` (3,) m/s of the origin, ``omega`` (3,) rad/s."""

    origin: np.ndarray
    R: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray

    def point(self, p) -> np.ndarray:
        """World position (3,) m of the body point ``p`` (3,) m (body frame)."""
        return self.origin + self.R @ p

    def point_velocity(self, p) -> np.ndarray:
        """World velocity (3,) m/s of the body point ``p`` (3,) m (body frame)."""
        return self.velocity + cross(self.omega, self.R @ p)


GROUND_FRAME = Frame(np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3))


def frame_of(frames: dict[str, Frame], node: str) -> Frame:
    """The frame of a body, or :data:`GROUND_FRAME` for ``ground``."""
    return GROUND_FRAME if node == GROUND else frames[node]


def node_point(case: Case, node: str, name: str) -> np.ndarray:
    """A named point (d,) m in its body's frame (a ground point in world axes)."""
    return case.ground[name] if node == GROUND else case.body(node).points[name]


def plane_normal(case: Case) -> np.ndarray | None:
    """The normal (3,) of the plane of motion of a 2-D case (z: its bodies stay in the x-y
    plane), None for a 3-D case."""
    return Z if case.dimension == 2 else None

@dataclasses.dataclass
class Samples:
    """What an engine that simulates in 3-D, world axes, sampled: body -> origin (T, 3) m,
    rotation (T, 3, 3), velocity (T, 3) m/s, omega (T, 3) rad/s; joint -> force on its
    second body (T, 3) N; rod or spring -> tension (T,) N; optional: body -> acceleration
    of the origin (T, 3) m/s^2 and alpha (T, 3) rad/s^2 (empty: not reported)."""

    origin: dict
    rotation: dict
    velocity: dict
    omega: dict
    forces: dict
    rod_force: dict
    acceleration: dict = dataclasses.field(default_factory=dict)
    alpha: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def empty(cls, case: Case, T: int) -> Samples:
        names = [b.name for b in case.bodies]

        def vectors():
            return {n: np.zeros((T, 3)) for n in names}

        return cls(vectors(), {n: np.zeros((T, 3, 3)) for n in names}, vectors(), vectors(),
                   {j.name: np.zeros((T, 3)) for j in case.joints},
                   {r.name: np.zeros(T) for r in (*case.rods, *case.springs)})


def check_start(case: Case, frames: dict[str, Frame], out: Samples, engine: str,
                tol: float = 1e-9) -> None:
    """The engine's first sample must be natcoord's assembled state ``frames`` (to ``tol``
    relative; a particle's rotation and angular velocity are not states)."""
    for b in case.bodies:
        f, n = frames[b.name], b.name
        errs = [np.max(np.abs(out.origin[n][0] - f.origin)),
                np.max(np.abs(out.velocity[n][0] - f.velocity))]
        if b.kind != "particle":
            errs += [np.max(np.abs(out.rotation[n][0] - f.R)),
                     np.max(np.abs(out.omega[n][0] - f.omega))]
        if max(errs) > tol * (1.0 + max(np.max(np.abs(f.origin)), np.max(np.abs(f.velocity)))):
            raise RuntimeError(f"internal: {engine}'s initial state of body {n} differs "
                               f"from the assembled one by {max(errs):.3g}")



# ---- 2-D -> 3-D ---------------------------------------------------------------------------
def _inertia3(inertia) -> np.ndarray:
    """A 2-D Izz (scalar) as ``Izz * I3``, a 3-D tensor (3, 3) as it is; kg m^2."""
    return float(inertia) * np.eye(3) if np.ndim(inertia) == 0 else np.asarray(inertia, float)


def _body(b: Body) -> Body:
    return dataclasses.replace(b, points={k: v3(p) for k, p in b.points.items()},
                               com=v3(b.com), inertia=_inertia3(b.inertia))


def _joint(j: Joint) -> Joint:
    """A 2-D revolute (no axis) turns about z; a given axis gets z = 0."""
    axis = Z if j.axis is None and j.type == "revolute" else j.axis
    return dataclasses.replace(j, axis=None if axis is None else v3(axis),
                               axis2=None if j.axis2 is None else v3(j.axis2))


def _force(f: Force) -> Force:
    """A 2-D torque (scalar) is about z; a force (2,) gets z = 0."""
    if f.type == "torque" and np.ndim(f.value) == 0:
        return dataclasses.replace(f, value=float(f.value) * Z)
    return dataclasses.replace(f, value=v3(f.value))


def lift_case(case: Case) -> Case:
    """The planar 3-D case of a 2-D ``case``: ``dimension`` 3, every point, axis, force and
    gravity (3,), every inertia (3, 3) about the centre of mass in body axes (``Izz * I3``).
    Names, times, channels, drivers, rods, springs and settings are kept (``guess``, the
    assembly's input, is not lifted: engines start from ``init``). A 3-D case is returned as
    it is."""
    if case.dimension == 3:
        return case
    return dataclasses.replace(
        case, dimension=3, gravity=v3(case.gravity),
        ground={k: v3(p) for k, p in case.ground.items()},
        bodies=tuple(_body(b) for b in case.bodies),
        joints=tuple(_joint(j) for j in case.joints),
        forces=tuple(_force(f) for f in case.forces))


def lift_init(case: Case, init) -> dict[str, Frame]:
    """Every body's frame at t = 0 in 3-D, from ``init[body]`` (a
    :class:`~natcoord.engines.base.BodyState`, 2-D or 3-D): body name -> :class:`Frame`; a
    2-D omega (scalar) is about z.

    Rotation entries below :data:`ROTATION_ROUND_OFF` (1e-12) are set to 0. They are
    round-off of natcoord's assembly (converged to 1e-13), e.g. 3e-16 where a body's axis is
    exactly along a world axis. Left in, such a tilt can matter: a planar loop closed by
    DART's BallJointConstraint has a redundant row across its plane, a round-off tilt of the
    joint axes leaves a gap there that no motion can close, and DART's error reduction
    turns it into internal forces along that row (measured 53 N on four_bar_3d's
    undetermined O_x, D_x; exactly 0 with the entries cleaned); Pinocchio's parallelogram_3d
    moved by the same round-off. It is safe for every engine: an entry below 1e-12 is zero
    up to the assembly's accuracy, each entry moves by less than 1e-12, so the frame stays
    orthonormal to 1e-12 (MuJoCo makes a unit quaternion of it; MuJoCo and DART check their
    start against these frames to 1e-9 and 1e-7), and a frame along the world axes in exact
    arithmetic is kept exactly along them.
    """
    out = {}
    for b in case.bodies:
        st = init[b.name]
        r = np.asarray(st.rotation, dtype=float)  # (d, d); a 2-D frame turns about z
        R = np.eye(3)
        R[:len(r), :len(r)] = r
        R[np.abs(R) < ROTATION_ROUND_OFF] = 0.0
        w = float(st.omega) * Z if np.ndim(st.omega) == 0 else v3(st.omega)
        out[b.name] = Frame(v3(st.origin), R, v3(st.velocity), w)
    return out


# ---- 3-D -> the case's dimension ----------------------------------------------------------
def drop(case: Case, t, origin: dict, rotation: dict, velocity: dict, omega: dict,
         joint_force: dict, *, acceleration: dict | None = None, alpha: dict | None = None,
         driver_effort: dict | None = None, rod_force: dict | None = None) -> Motion:
    """The neutral Motion of the (original, unlifted) ``case`` from 3-D samples at times
    ``t`` (T,) s, world axes: body -> ``origin`` (T, 3) m, ``rotation`` (T, 3, 3)
    body-to-world, ``velocity`` (T, 3) m/s, ``omega`` (T, 3) rad/s; joint -> ``joint_force``
    (T, 3) N on its second body. Optional (None or empty: the engine does not report them,
    their channels become NaN): body -> ``acceleration`` (T, 3) m/s^2 of the origin,
    ``alpha`` (T, 3) rad/s^2; driver -> ``driver_effort`` (T,) N m or N; rod or spring ->
    ``rod_force`` (T,) N, tension positive.

    A 3-D case gets the samples as they are. A 2-D case gets per body the angle of its frame's
    x axis from world +x (T,) rad, unwrapped, omega and alpha about z (T,), and (T, 2)
    vectors (origin, velocity, acceleration, joint forces)."""
    t = np.asarray(t, dtype=float)
    extra = {"driver_effort": driver_effort or {}, "rod_force": rod_force or {}}
    acceleration, alpha = acceleration or {}, alpha or {}
    if case.dimension == 3:
        return Motion(t, origin, {}, velocity, omega, joint_force, acceleration=acceleration,
                      alpha=alpha, rotation=rotation, **extra)

    def xy(d):
        return {k: x[:, :2].copy() for k, x in d.items()}

    def about_z(d):
        return {k: x[:, 2].copy() for k, x in d.items()}

    angle = {k: np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0])) for k, R in rotation.items()}
    return Motion(t, xy(origin), angle, xy(velocity), about_z(omega), xy(joint_force),
                  acceleration=xy(acceleration), alpha=about_z(alpha), **extra)
