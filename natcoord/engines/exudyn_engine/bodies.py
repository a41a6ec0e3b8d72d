"""Bodies: one free node at each body's centre of mass (node frame = body frame), with the
sensors that read its motion back. One element set per dimension:

* 2-D: ``NodeRigidBody2D`` + ``ObjectRigidBody2D``; a particle is ``NodePoint2D`` +
  ``ObjectMassPoint2D``, unless it takes part in a prismatic joint (that needs orientation
  markers): then a 2-D rigid node whose rotation is locked to zero by a
  ``CoordinateConstraint`` (the locked rotation carries no kinetic energy, no reaction).
* 3-D: ``NodeRigidBodyEP`` (Euler parameters) + ``ObjectRigidBody``. A slender rod
  (``uniform_rod``) has no inertia about its own axis; Exudyn's mass matrix must be regular,
  so a small one (``axial_inertia`` times its largest moment) is added. 3-D particles are
  not modelled.
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import Body
from ...errors import Unsupported
from .system import Build, v3

AXIAL_INERTIA = 1e-6  # uniform rods (3-D): axial inertia added, relative to the largest moment


def spin(omega, r: np.ndarray) -> np.ndarray:
    """omega x r for r (d,) or (T, d): in 2-D omega is the rate about z (scalar or (T,)),
    in 3-D a vector ((3,) or (T, 3))."""
    r = np.asarray(r, float)
    if r.shape[-1] == 3:
        return np.cross(omega, r)
    w = np.asarray(omega, float)
    w = w[..., None] if w.ndim else w
    return w * np.stack([-r[..., 1], r[..., 0]], -1)


def centre_state(build: Build, b: Body) -> tuple[np.ndarray, np.ndarray]:
    """World position and velocity (d,) of the body's centre of mass at t = 0, from the
    assembled frame state ``init[body]`` (origin, rotation, velocity, omega)."""
    st = build.init[b.name]
    rc = np.asarray(st.rotation, float) @ b.com
    return np.asarray(st.origin, float) + rc, np.asarray(st.velocity, float) + spin(st.omega,
                                                                                   rc)


class Planar:
    """2-D element set: rigid 2-D nodes, point masses, angles about z."""

    @staticmethod
    def check(case) -> None:
        for f in case.forces:
            if f.type == "torque" and f.body in {b.name for b in case.bodies
                                                 if b.kind == "particle"}:
                raise Unsupported(f"torque on particle {f.body}: a particle has no rotation")

    @staticmethod
    def add(build: Build, b: Body, oriented: bool) -> tuple[int, int]:
        """(node, object) of body ``b``; ``oriented``: it needs orientation markers."""
        ei, mbs = build.ei, build.mbs
        pos, vel = centre_state(build, b)
        st = build.init[b.name]
        if b.kind == "particle" and not oriented:
            n = mbs.AddNode(ei.NodePoint2D(referenceCoordinates=v3(pos)[:2],
                                           initialCoordinates=[0.0, 0.0],
                                           initialVelocities=v3(vel)[:2]))
            build.notes.append(f"particle {b.name}: NodePoint2D + ObjectMassPoint2D")
            return n, mbs.AddObject(ei.ObjectMassPoint2D(nodeNumber=n, mass=b.mass))
        particle = b.kind == "particle"
        phi, w = (0.0, 0.0) if particle else (float(st.angle), float(st.omega))
        # a locked rotation: its inertia only conditions the matrix
        inertia = (b.mass if b.mass > 0 else 1.0) if particle else b.inertia
        n = mbs.AddNode(ei.NodeRigidBody2D(
            referenceCoordinates=[pos[0], pos[1], phi], initialCoordinates=[0.0, 0.0, 0.0],
            initialVelocities=[vel[0], vel[1], w]))
        o = mbs.AddObject(ei.ObjectRigidBody2D(nodeNumber=n, mass=b.mass, inertia=inertia))
        if particle:
            build.nodes[b.name] = n
            mbs.AddObject(ei.CoordinateConstraint(markerNumbers=[
                build.node_coordinate(None, 0), build.node_coordinate(b.name, 2)]))
        return n, o

    @staticmethod
    def note(build: Build, oriented: set[str]) -> None:
        locked = [b.name for b in build.case.bodies
                  if b.kind == "particle" and b.name in oriented]
        if locked:
            build.notes.append(f"particle(s) {', '.join(locked)} in a prismatic joint: rigid "
                               "2-D node with rotation locked to 0 (a prismatic joint needs "
                               "orientation markers)")

    @staticmethod
    def sensors(build: Build, b: Body) -> list[int]:
        OV = build.exu.OutputVariableType
        kinds = (OV.Position, OV.Velocity, OV.Acceleration)
        if b.kind != "particle":
            kinds += (OV.Rotation, OV.AngularVelocity, OV.AngularAcceleration)
        return [build.node_sensor(b.name, v) for v in kinds]

    @staticmethod
    def read(get, b: Body, sensors: list[int]) -> dict[str, np.ndarray]:
        """The body frame's motion: origin, velocity, acceleration (T, 2), angle, omega,
        alpha (T,), R (T, 2, 2). The accelerations are those generalized-alpha solves the
        equations of motion for at each step."""
        pc, vc, ac = (get(x)[:, :2] for x in sensors[:3])
        if len(sensors) == 3:  # a particle (or a locked rotation): its frame never turns
            phi = w = alpha = np.zeros(len(pc))
        else:
            phi, w, alpha = (get(x)[:, 2] for x in sensors[3:])
        c, s = np.cos(phi), np.sin(phi)
        R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        rc = R @ b.com
        return {"origin": pc - rc, "velocity": vc - spin(w, rc), "angle": phi, "omega": w,
                "acceleration": ac - spin(alpha, rc) + (w * w)[:, None] * rc, "alpha": alpha,
                "R": R}


class Spatial:
    """3-D element set: Euler-parameter rigid nodes, rotation matrices."""

    @staticmethod
    def check(case) -> None:
        for b in case.bodies:
            if b.kind == "particle":
                raise Unsupported(f"body {b.name}: 3-D particles are not modelled by the Exudyn "
                                  "adapter")

    @staticmethod
    def inertia(build: Build, b: Body) -> np.ndarray:
        """(3, 3) inertia about the centre of mass, body axes; a uniform rod's padded."""
        J = np.array(b.inertia, float).reshape(3, 3)
        if b.kind != "uniform_rod":
            return J
        eps = float(build.settings.get("axial_inertia", AXIAL_INERTIA))
        ends = b.ends or tuple(b.points)[:2]
        u = b.points[ends[1]] - b.points[ends[0]]
        u /= np.linalg.norm(u)
        return J + eps * np.max(np.linalg.eigvalsh(J)) * np.outer(u, u)

    @staticmethod
    def add(build: Build, b: Body, oriented: bool) -> tuple[int, int]:
        from exudyn.rigidBodyUtilities import RotationMatrix2EulerParameters

        ei, mbs = build.ei, build.mbs
        pos, vel = centre_state(build, b)
        R = np.asarray(build.init[b.name].rotation, float)
        w = np.asarray(build.init[b.name].omega, float).reshape(3)
        # Euler-parameter velocities from the world angular velocity: ep_t = G^T w / 2
        ep = np.asarray(RotationMatrix2EulerParameters(R), float)
        e0, e1, e2, e3 = ep
        G = np.array([[-e1, e0, -e3, e2], [-e2, e3, e0, -e1], [-e3, -e2, e1, e0]])
        n = mbs.AddNode(ei.NodeRigidBodyEP(
            referenceCoordinates=[*pos, *ep], initialCoordinates=[0.0] * 7,
            initialVelocities=[*vel, *(0.5 * G.T @ w)]))
        J = Spatial.inertia(build, b)
        o = mbs.AddObject(ei.ObjectRigidBody(
            nodeNumber=n, mass=float(b.mass),
            inertia=[J[0, 0], J[1, 1], J[2, 2], J[1, 2], J[0, 2], J[0, 1]]))
        return n, o

    @staticmethod
    def note(build: Build, oriented: set[str]) -> None:
        padded = [b.name for b in build.case.bodies if b.kind == "uniform_rod"]
        if padded:
            eps = float(build.settings.get("axial_inertia", AXIAL_INERTIA))
            build.notes.append(f"uniform rod(s) {', '.join(padded)}: axial inertia {eps:g} x "
                               "the largest moment added (Exudyn needs a regular mass "
                               "matrix); the joints lock that rotation")

    @staticmethod
    def sensors(build: Build, b: Body) -> list[int]:
        OV = build.exu.OutputVariableType
        return [build.node_sensor(b.name, v) for v in (
            OV.Position, OV.Velocity, OV.RotationMatrix, OV.AngularVelocity,
            OV.Acceleration, OV.AngularAcceleration)]

    @staticmethod
    def read(get, b: Body, sensors: list[int]) -> dict[str, np.ndarray]:
        """The body frame's motion: origin, velocity, omega, acceleration, alpha (T, 3),
        R = rotation (T, 3, 3). The accelerations are those generalized-alpha solves the
        equations of motion for at each step."""
        ps, vs, rs, ws, acs, als = (get(x) for x in sensors)
        R = rs.reshape(-1, 3, 3)
        rc = R @ b.com
        return {"origin": ps - rc, "velocity": vs - np.cross(ws, rc), "omega": ws, "R": R,
                "rotation": R, "alpha": als,
                "acceleration": acs - np.cross(als, rc) - np.cross(ws, np.cross(ws, rc))}


ELEMENTS = {2: Planar, 3: Spatial}  # the element set of a case, by its dimension
