"""The one place where a 2-D case becomes 3-D, and where 3-D results drop back to 2-D.

A 2-D case is the planar case of the 3-D model: points (x, y, 0), a revolute joint about z,
a prismatic axis (ax, ay, 0), gravity (gx, gy, 0), a torque (0, 0, tz), a body's moment
I_zz as a 3x3 tensor. Everything after :func:`lift` sees 3-D only; :func:`drop` turns the
3-D samples into natcoord's 2-D ``Motion`` (angle per body, 2-component vectors).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ...mechanism import Case
from ...result import Motion

Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Frame:
    """A body frame at t = 0 in world axes: origin (3,) m, body-to-world rotation R (3, 3),
    origin velocity (3,) m/s, angular velocity omega (3,) rad/s."""

    origin: np.ndarray
    R: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray

    def point(self, p: np.ndarray) -> np.ndarray:
        """World position (3,) of the body point p (3,)."""
        return self.origin + self.R @ p

    def point_velocity(self, p: np.ndarray) -> np.ndarray:
        """World velocity (3,) of the body point p (3,)."""
        return self.velocity + np.cross(self.omega, self.R @ p)


GROUND_FRAME = Frame(np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3))


def v3(x) -> np.ndarray:
    """A 2- or 3-vector as a 3-vector (z = 0 for a 2-D one)."""
    x = np.asarray(x, dtype=float).reshape(-1)
    return np.append(x, 0.0) if x.size == 2 else x


def lift(case: Case, init, r_gyr: float) -> tuple[Case, dict[str, Frame], list[str]]:
    """The case as a 3-D case, every body's frame at t = 0 (from ``init``) and notes.

    ``r_gyr`` (m) is the radius of gyration a 2-D body's I_zz is raised to when it is
    smaller (DART needs a positive definite inertia). A 3-D case is returned unchanged.
    """
    frames = {b.name: _frame(init[b.name]) for b in case.bodies}
    if case.dimension == 3:
        return case, frames, []
    notes: list[str] = []
    bodies = tuple(_body3(b, r_gyr, notes) for b in case.bodies)
    joints = tuple(dataclasses.replace(j, axis=Z if j.axis is None else v3(j.axis))
                   for j in case.joints)
    forces = tuple(dataclasses.replace(f, value=v3(f.value) if f.type == "force"
                                       else float(f.value) * Z) for f in case.forces)
    case3 = dataclasses.replace(
        case, dimension=3, gravity=v3(case.gravity), bodies=bodies, joints=joints,
        forces=forces, ground={k: v3(x) for k, x in case.ground.items()})
    return case3, frames, notes


def plane_normal(case: Case) -> np.ndarray | None:
    """z for a 2-D case (its bodies must stay in the x-y plane), None for a 3-D one."""
    return Z if case.dimension == 2 else None


def _frame(st) -> Frame:
    """A 2-D or 3-D ``BodyState`` as a 3-D frame.

    Rotation entries below 1e-12 are round-off of natcoord's assembly and set to 0: a
    planar loop closed by a BallJointConstraint has a redundant row across its plane, and a
    round-off tilt of the joint axes leaves a gap there that no motion can close; DART's
    error reduction then turns it into internal forces along that row (measured 53 N on
    four_bar_3d's undetermined O_x, D_x, exactly 0 with the entries cleaned)."""
    d = len(np.asarray(st.origin))
    R = np.eye(3)
    R[:d, :d] = np.asarray(st.rotation, dtype=float)
    R[np.abs(R) < 1e-12] = 0.0
    w = np.asarray(st.omega, dtype=float)
    omega = w.reshape(3) if w.size == 3 else float(w) * Z
    return Frame(v3(st.origin), R, v3(st.velocity), omega)


def _body3(b, r_gyr: float, notes: list[str]):
    """A 2-D body with 3-D points and a 3x3 inertia tensor about its centre of mass."""
    points = {k: v3(x) for k, x in b.points.items()}
    izz = float(b.inertia)
    if b.kind == "uniform_rod":  # slender: I_zz about every axis normal to the rod
        e0, e1 = b.ends or list(b.points)[:2]
        e = points[e1] - points[e0]
        e /= np.linalg.norm(e)
        inertia = izz * (np.eye(3) - np.outer(e, e))
    elif b.kind == "particle":
        inertia = np.zeros((3, 3))  # the skeleton gives every particle its tiny inertia
    else:
        if izz < b.mass * r_gyr**2:
            izz = b.mass * r_gyr**2
            notes.append(f"body {b.name!r}: inertia raised to {izz:.3g} kg m^2 (DART needs "
                         "it > 0)")
        inertia = np.diag([izz / 2, izz / 2, izz])  # planar lamina: I_xx + I_yy = I_zz
    return dataclasses.replace(b, points=points, com=v3(b.com), inertia=inertia)


# ---- back to the case's dimension ---------------------------------------------------------
def drop(case: Case, t: np.ndarray, s: dict[str, dict[str, np.ndarray]], force, rod_force,
         driver_effort) -> Motion:
    """natcoord's Motion from 3-D samples ``s[kind][body]`` (kinds origin (T, 3), R (T, 3, 3),
    velocity, omega, acceleration, alpha (T, 3)), joint forces (T, 3), axial forces and
    driver efforts (T,). A 2-D case gets angles, 2-component vectors and omega about z."""
    if case.dimension == 3:
        return _motion(t, s["origin"], {}, s["velocity"], s["omega"], force,
                       rotation=s["R"], acceleration=s["acceleration"], alpha=s["alpha"],
                       rod_force=rod_force, driver_effort=driver_effort)

    def xy(d):
        return {k: v[:, :2] for k, v in d.items()}

    def about_z(d):
        return {k: v[:, 2] for k, v in d.items()}

    angle = {k: np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0])) for k, R in s["R"].items()}
    return _motion(t, xy(s["origin"]), angle, xy(s["velocity"]), about_z(s["omega"]),
                   xy(force), acceleration=xy(s["acceleration"]), alpha=about_z(s["alpha"]),
                   rod_force=rod_force, driver_effort=driver_effort)


def _motion(t, origin, angle, vel, omega, force, **extra) -> Motion:
    """A Motion with the optional fields this natcoord version has (empty ones dropped)."""
    have = {f.name for f in dataclasses.fields(Motion)}
    return Motion(t, origin, angle, vel, omega, force,
                  **{k: v for k, v in extra.items() if k in have and v})
