"""Joints, rods and spring-dampers: Exudyn constraints and connectors between body markers,
each with the reader that turns its sensor into natcoord's reaction (the force the joint
applies to the case's second body, world axes, N).

A joint factory is ``add(build, joint) -> reader``; ``reader(get, frames)`` returns (T, d),
``get`` a stored sensor (:func:`.solve.stored`), ``frames`` body -> the body's motion read
back (``R``: (T, d, d) body-to-world). The factories of each dimension are in
:data:`JOINTS`; a joint type without one is not modelled.
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Joint
from .system import Build, v3

J2 = np.array([[0.0, -1.0], [1.0, 0.0]])  # +90 deg rotation about z


def _rot2(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _R(frames: dict, body: str, n: int, d: int) -> np.ndarray:
    """(T, d, d) body-to-world rotation of a body (the ground's is the identity)."""
    return np.broadcast_to(np.eye(d), (n, d, d)) if body == GROUND else frames[body]["R"]


# ---- 2-D ------------------------------------------------------------------------------------

def revolute_2d(build: Build, j: Joint):
    """``ObjectJointRevolute2D`` with markers [first, second]: its Force output (world axes)
    is the force on the first marker's body, so the reaction is its negative."""
    (a, b), (pa, pb) = j.bodies, j.points
    jo = build.mbs.AddObject(build.ei.ObjectJointRevolute2D(
        markerNumbers=[build.marker(a, pa), build.marker(b, pb)]))
    sf = build.object_sensor(jo, build.exu.OutputVariableType.Force)
    build.note_once("revolute joints: ObjectJointRevolute2D; reaction = -Force output (Force "
                    "is the force on the first marker's body)")
    return lambda get, frames: -get(sf)[:, :2]


def _angle0(build: Build, body: str) -> float:
    """A body frame's angle at t = 0 (a particle's frame never turns), rad."""
    if body == GROUND or build.case.body(body).kind == "particle":
        return 0.0
    return float(build.init[body].angle)


def prismatic_2d(build: Build, j: Joint):
    """``ObjectJointPrismatic2D`` with markers [second, first], so that its normal
    (``normalMarker1``) turns with the case's first body, as the case's axis does. It has no
    Force output: a ``SensorUserFunction`` (called at the output times only) reads its first
    Lagrange multiplier lambda_0; the reaction is +lambda_0 times the first body's normal
    (axis turned +90 deg) in world axes. Its moment is not reported."""
    (a, b), (pa, pb) = j.bodies, j.points
    ei = build.ei
    u = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
    rel = _rot2(_angle0(build, a) - _angle0(build, b))  # a's frame -> b's frame at the start
    rigid_b = b == GROUND or build.case.body(b).kind != "particle"
    jo = build.mbs.AddObject(ei.ObjectJointPrismatic2D(
        markerNumbers=[build.marker(b, pb, rigid=True), build.marker(a, pa, rigid=True)],
        axisMarker0=v3(rel @ u), normalMarker1=v3(J2 @ u), constrainRotation=bool(rigid_b)))

    def lagrange(mbs_, t, sensor_numbers, factors, configuration):
        index = mbs_.systemData.GetObjectLTGAE(jo)[0]  # its first multiplier (after Assemble)
        return [mbs_.systemData.GetAECoordinates(configuration)[index]]

    sl = build.sensor(ei.SensorUserFunction, sensorUserFunction=lagrange)
    build.note_once("prismatic joints: ObjectJointPrismatic2D with markers [second, first] so "
                    "the normal turns with the first body; reaction = +lambda_0 times the "
                    "normal (the joint has no Force output; lambda_0 read by a sensor user "
                    "function at the output times); its moment is not reported")

    def reaction(get, frames):
        lam = get(sl)[:, 0]
        n = _R(frames, a, len(lam), 2) @ (J2 @ u)
        return lam[:, None] * n
    return reaction


# ---- 3-D ------------------------------------------------------------------------------------

def _frame_z(axis) -> np.ndarray:
    """A rotation whose third column is the unit ``axis`` (a joint frame with z on it)."""
    z = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.eye(3)[np.argmin(np.abs(z))]
    x = np.cross(t, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _frame_x(axis, y=None) -> np.ndarray:
    """A rotation whose first column is the unit ``axis`` (and second ``y``, if given)."""
    x = np.asarray(axis, float) / np.linalg.norm(axis)
    if y is None:
        F = _frame_z(x)
        return np.column_stack([x, F[:, 0], F[:, 1]])  # (x, F_x, F_y) is right-handed
    y = np.asarray(y, float) / np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])


def _framed(build: Build, j: Joint, A0: np.ndarray, slides: bool = False) -> list[int]:
    """Rigid markers at the joint points carrying the joint frame ``A0`` (given in the first
    body's frame) on both bodies: the second's ``A1`` is the same frame at t = 0. A joint
    that ``slides`` keeps its points' offset across the axis as it was at t = 0 (Exudyn
    makes the marker origins meet): its first marker sits where the second body's point
    is at t = 0."""
    (a, b), (pa, pb) = j.bodies, j.points
    A1 = build.rotation0(b).T @ build.rotation0(a) @ A0
    at = build.world0(b, pb) if slides else None
    return [build.marker(a, pa, A0, at=at), build.marker(b, pb, A1)]


def _local_reaction(sf: int, a: str, A0: np.ndarray):
    """Reader of a ForceLocal output (force on the first marker's body in its joint frame
    A0): the reaction is -R_a(t) A0 ForceLocal."""
    def reaction(get, frames):
        f = get(sf)[:, :3]
        return -(_R(frames, a, len(f), 3) @ A0 @ f[:, :, None])[:, :, 0]
    return reaction


def revolute_z(build: Build, j: Joint):
    """``ObjectJointRevoluteZ`` whose markers carry a joint frame with z on the case's axis."""
    A0 = _frame_z(j.axis)
    jo = build.mbs.AddObject(build.ei.ObjectJointRevoluteZ(markerNumbers=_framed(build, j, A0)))
    build.note_once("revolute joints: ObjectJointRevoluteZ with joint frames (z along the "
                    "axis) as marker localHT; reaction = -(rotation of the first body) x "
                    "(joint frame) x ForceLocal")
    sf = build.object_sensor(jo, build.exu.OutputVariableType.ForceLocal)
    return _local_reaction(sf, j.bodies[0], A0)


def spherical(build: Build, j: Joint):
    """``ObjectJointSpherical``: its Force output (world axes) is the force on the first
    marker's body, so the reaction is its negative."""
    (a, b), (pa, pb) = j.bodies, j.points
    jo = build.mbs.AddObject(build.ei.ObjectJointSpherical(
        markerNumbers=[build.marker(a, pa), build.marker(b, pb)]))
    build.note_once("spherical joints: ObjectJointSpherical; reaction = -Force output")
    sf = build.object_sensor(jo, build.exu.OutputVariableType.Force)
    return lambda get, frames: -get(sf)[:, :3]


# ObjectJointGeneric: constrained [translations x y z, rotations x y z] in the joint frame,
# whose x axis is the case's axis (universal: y is the second body's axis2)
GENERIC_AXES = {"prismatic": [0, 1, 1, 1, 1, 1],    # slides along x
                "cylindrical": [0, 1, 1, 0, 1, 1],  # slides along and turns about x
                "universal": [1, 1, 1, 0, 0, 1]}    # keeps x (first) and y (second) square


def generic(build: Build, j: Joint):
    """Prismatic, cylindrical and universal joints: ``ObjectJointGeneric`` with the joint's
    constrained axes; its ForceLocal output is read as the revolute's."""
    a, b = j.bodies
    y = None
    if j.type == "universal":  # axis2 is in b's frame: bring it to a's at t = 0
        y = build.rotation0(a).T @ build.rotation0(b) @ np.asarray(j.axis2, float)
    A0 = _frame_x(j.axis, y)
    jo = build.mbs.AddObject(build.ei.ObjectJointGeneric(
        markerNumbers=_framed(build, j, A0, slides=j.type != "universal"),
        constrainedAxes=GENERIC_AXES[j.type]))
    build.note_once(f"{j.type} joints: ObjectJointGeneric, constrained axes "
                    f"{GENERIC_AXES[j.type]} in a joint frame with x along the axis; reaction "
                    "= -(rotation of the first body) x (joint frame) x ForceLocal; the moment "
                    "is not reported")
    sf = build.object_sensor(jo, build.exu.OutputVariableType.ForceLocal)
    return _local_reaction(sf, a, A0)


JOINTS = {2: {"revolute": revolute_2d, "prismatic": prismatic_2d},
          3: {"revolute": revolute_z, "spherical": spherical, "prismatic": generic,
              "cylindrical": generic, "universal": generic}}


# ---- rods and spring-dampers ----------------------------------------------------------------

def connectors(build: Build) -> dict:
    """Massless rods (``ObjectConnectorDistance``, exact; its scalar Force output is the axial
    force, tension positive, whatever the marker order) and spring-dampers
    (``ObjectConnectorSpringDamper``; its Force output is ``tension * u``, u the unit vector
    from marker 0 to marker 1 (its Displacement output), so tension = Force . u) between
    position markers; returns name -> reader(get) giving the tension (T,), N."""
    ei, mbs, case = build.ei, build.mbs, build.case
    OV = build.exu.OutputVariableType
    out = {}
    for r in case.rods:
        (a, pa), (b, pb) = r.ends
        co = mbs.AddObject(ei.ObjectConnectorDistance(
            markerNumbers=[build.marker(a, pa), build.marker(b, pb)], distance=float(r.length)))
        sf = build.object_sensor(co, OV.Force)
        out[r.name] = (lambda get, sf=sf: get(sf)[:, 0])
    for sp in case.springs:
        (a, pa), (b, pb) = sp.ends
        co = mbs.AddObject(ei.ObjectConnectorSpringDamper(
            markerNumbers=[build.marker(a, pa), build.marker(b, pb)],
            referenceLength=float(sp.length), stiffness=float(sp.stiffness),
            damping=float(sp.damping)))
        sf, sd = build.object_sensor(co, OV.Force), build.object_sensor(co, OV.Displacement)

        def tension(get, sf=sf, sd=sd):
            d = get(sd)
            return np.sum(get(sf) * d, axis=1) / np.linalg.norm(d, axis=1)
        out[sp.name] = tension
    if case.rods:
        build.notes.append("massless rods: ObjectConnectorDistance (exact); axial force = its "
                           "Force output (tension positive)")
    if case.springs:
        build.notes.append("spring-dampers: ObjectConnectorSpringDamper (rest length = "
                           "the spring's); tension = Force output . unit Displacement")
    return out
