"""The one place where a case's dimension is read: a 2-D case lifted into 3-D, and the
3-D samples dropped back to the case's own dimension.

A 2-D case is the planar case of a 3-D one: points (x, y, 0), a revolute turns about z, a
prismatic axis is (ax, ay, 0), gravity (gx, gy, 0), a torque (0, 0, T), a scalar moment of
inertia Izz becomes Izz * I3 (every joint of a planar case turns about z, so the x and y
moments never act). The lifted case keeps the plane's normal (``Lifted.plane``): the
builder needs it for the two choices a planar model makes (a body no joint reaches moves in
the plane; a light rod turns about the normal only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...mechanism import GROUND, Case
from ...result import Motion

Z = np.array([0.0, 0.0, 1.0])


def v3(p) -> np.ndarray:
    """(2,) or (3,) -> (3,): a plane vector gets z = 0."""
    p = np.asarray(p, float)
    return p if p.size == 3 else np.array([p[0], p[1], 0.0])


def cross(a, b) -> np.ndarray:
    """a x b for 3-vectors or (3, n) columns (np.cross costs ~30 us a call here)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


@dataclass(frozen=True)
class Frame0:
    """A body frame at t = 0: R (3, 3) body-to-world, o (3,) m, v (3,) m/s, w (3,) rad/s,
    all in world axes."""

    R: np.ndarray
    o: np.ndarray
    v: np.ndarray
    w: np.ndarray

    def point(self, p: np.ndarray) -> np.ndarray:
        """World position (3,) of the body point p (3,), m."""
        return self.o + self.R @ p

    def point_velocity(self, p: np.ndarray) -> np.ndarray:
        """World velocity (3,) of the body point p (3,), m/s."""
        return self.v + cross(self.w, self.R @ p)


GROUND_FRAME = Frame0(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3))


@dataclass(frozen=True)
class Lifted:
    """A case in 3-D. ``points``: node -> point -> (3,) in the node's frame (ground
    included); ``frames``: node -> :class:`Frame0`; ``inertia``: body -> (3, 3) about the
    centre of mass in body axes, kg m^2; ``com``: body -> (3,); ``axes``: joint -> (axis,
    axis2), (3,) or None, in the frames of its first and second body; ``loads``: (body,
    point name or None, force (3,) N, torque (3,) N m), world axes; ``plane``: the normal
    (3,) of the plane of motion of a 2-D case, None in 3-D."""

    case: Case
    plane: np.ndarray | None
    gravity: np.ndarray
    points: dict
    frames: dict
    inertia: dict
    com: dict
    axes: dict
    loads: tuple

    def world_point(self, node: str, point: str) -> np.ndarray:
        """World position (3,) of a named point at t = 0, m."""
        return self.frames[node].point(self.points[node][point])

    def world_velocity(self, node: str, point: str) -> np.ndarray:
        """World velocity (3,) of a named point at t = 0, m/s."""
        return self.frames[node].point_velocity(self.points[node][point])


def _omega3(w) -> np.ndarray:
    """A 2-D angular velocity (scalar, about z) or a 3-D one (3,), as (3,) rad/s."""
    return float(w) * Z if np.ndim(w) == 0 else np.asarray(w, float)


def _inertia3(inertia) -> np.ndarray:
    """A 2-D Izz (scalar) as Izz * I3, or a 3-D tensor (3, 3), kg m^2."""
    return float(inertia) * np.eye(3) if np.ndim(inertia) == 0 else np.asarray(inertia, float)


def lift(case: Case, init) -> Lifted:
    """The case and its state at t = 0 (``init[body]``: frame pose and rates) in 3-D."""
    plane = Z if case.dimension == 2 else None
    points = {b.name: {k: v3(p) for k, p in b.points.items()} for b in case.bodies}
    points[GROUND] = {k: v3(p) for k, p in case.ground.items()}
    frames = {GROUND: GROUND_FRAME}
    for b in case.bodies:
        st = init[b.name]
        frames[b.name] = Frame0(st.rotation3(), v3(st.origin), v3(st.velocity),
                                _omega3(st.omega))
    axes = {}
    for j in case.joints:  # a 2-D revolute has no axis: it turns about z
        axis = Z if j.axis is None and j.type == "revolute" else j.axis
        axes[j.name] = (None if axis is None else v3(axis),
                        None if j.axis2 is None else v3(j.axis2))
    loads = []
    for f in case.forces:
        value = _omega3(f.value) if f.type == "torque" else v3(f.value)
        zero = np.zeros(3)
        loads.append((f.body, f.point, value if f.type == "force" else zero,
                      value if f.type == "torque" else zero))
    return Lifted(case, plane, v3(case.gravity), points, frames,
                  {b.name: _inertia3(b.inertia) for b in case.bodies},
                  {b.name: v3(b.com) for b in case.bodies}, axes, tuple(loads))


def drop(lifted: Lifted, times, origin, rotation, velocity, omega, forces,
         rod_force) -> Motion:
    """The neutral Motion in the case's dimension from 3-D samples: ``origin``,
    ``velocity``, ``omega`` body -> (T, 3); ``rotation`` body -> (T, 3, 3); ``forces``
    joint -> (T, 3); ``rod_force`` rod or spring -> (T,). A planar case gets an unwrapped
    angle and omega about z per body and 2-component vectors (reactions (T, 2))."""
    t = np.asarray(times)
    if lifted.plane is None:
        return Motion(t, origin, {}, velocity, omega, forces, rotation=rotation,
                      rod_force=rod_force)

    def flat(d):
        return {k: x[:, :2].copy() for k, x in d.items()}

    angle = {n: np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0])) for n, R in rotation.items()}
    w = {n: x[:, 2].copy() for n, x in omega.items()}
    return Motion(t, flat(origin), angle, flat(velocity), w, flat(forces),
                  rod_force=rod_force)
