"""Exudyn 3-D model of a case (called by :mod:`.exudyn_engine` for ``dimension = 3``).

Every body is a free rigid body (``NodeRigidBodyEP`` + ``ObjectRigidBody``) with its node at
the centre of mass and its node frame equal to the body frame; every joint, rod and spring
is a constraint or connector, so loops need no tree.

Conventions handled here (measured with exudyn 1.13.6, see tests/test_engine_exudyn.py):

* Revolute joints: ``ObjectJointRevoluteZ`` whose markers (``MarkerBodyRigid`` with a
  ``localHT``) carry a joint frame J with its z axis along the case's axis. Its only force
  output is ``ForceLocal``: the force on the body of marker 0, in J of marker 0. The force
  on the case's second body is ``-R_0(t) A_0 ForceLocal``, R_0 the rotation of marker 0's
  body and A_0 the marker's joint-frame rotation. The case's first body is marker 0.
* Spherical joints: ``ObjectJointSpherical``; its ``Force`` output (world axes) is the force
  on the body of marker 0, so the reaction on the second body is its negative.
* A slender rod (``uniform_rod``) has no inertia about its own axis; Exudyn's mass matrix
  must be regular, so a small one (``axial_inertia`` times its largest moment) is added.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun
from .exudyn_engine import (
    connectors,
    engine_run,
    model_notes,
    new_system,
    solve,
    step_plan,
    stored,
)

AXIAL_INERTIA = 1e-6  # uniform rods: axial inertia added, relative to the largest moment


def _frame(axis) -> np.ndarray:
    """A rotation whose third column is the unit ``axis`` (a joint frame with z on it)."""
    z = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.eye(3)[np.argmin(np.abs(z))]
    x = np.cross(t, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _check(case: Case) -> None:
    for j in case.joints:
        if j.type not in ("revolute", "spherical"):
            raise Unsupported(f"joint {j.name}: type {j.type!r} is not modelled in 3-D by "
                              "the Exudyn adapter")
    for f in case.forces:
        if f.type not in ("torque", "force"):
            raise Unsupported(f"force on {f.body}: type {f.type!r} is not modelled")
    for b in case.bodies:
        if b.kind == "particle":
            raise Unsupported(f"body {b.name}: 3-D particles are not modelled by the Exudyn "
                              "adapter")


def _rotation0(init, body: str) -> np.ndarray:
    if body == GROUND:
        return np.eye(3)
    r = getattr(init[body], "rotation", None)
    return np.eye(3) if r is None else np.asarray(r, float)


def run3d(case: Case, init, s: dict) -> EngineRun:
    _check(case)
    h, _, _, n_steps = step_plan(case, s)

    import exudyn as exu
    from exudyn import itemInterface as ei

    OV = exu.OutputVariableType
    eps = float(s.get("axial_inertia", AXIAL_INERTIA))
    notes = model_notes(
        case, s, h,
        "redundant absolute coordinates: one NodeRigidBodyEP (Euler parameters) + "
        "ObjectRigidBody per body at its centre of mass; every joint is a constraint")

    t0 = time.perf_counter()
    SC, mbs, ground = new_system(exu, ei)
    from exudyn.rigidBodyUtilities import RotationMatrix2EulerParameters

    nodes, objs, rot0, padded = {}, {}, {}, []
    for b in case.bodies:
        st = init[b.name]
        R = _rotation0(init, b.name)
        rc = R @ b.com
        pos = np.asarray(st.origin, float) + rc
        w = np.asarray(st.omega, float).reshape(3)
        vel = np.asarray(st.velocity, float) + np.cross(w, rc)
        J = np.array(b.inertia, float).reshape(3, 3)
        if b.kind == "uniform_rod":
            ends = b.ends or tuple(b.points)[:2]
            u = b.points[ends[1]] - b.points[ends[0]]
            u /= np.linalg.norm(u)
            J = J + eps * np.max(np.linalg.eigvalsh(J)) * np.outer(u, u)
            padded.append(b.name)
        # Euler-parameter velocities from the world angular velocity: ep_t = G^T w / 2
        ep = np.asarray(RotationMatrix2EulerParameters(R), float)
        e0, e1, e2, e3 = ep
        G = np.array([[-e1, e0, -e3, e2], [-e2, e3, e0, -e1], [-e3, -e2, e1, e0]])
        n = mbs.AddNode(ei.NodeRigidBodyEP(
            referenceCoordinates=[*pos, *ep], initialCoordinates=[0.0] * 7,
            initialVelocities=[*vel, *(0.5 * G.T @ w)]))
        o = mbs.AddObject(ei.ObjectRigidBody(
            nodeNumber=n, mass=float(b.mass),
            inertia=[J[0, 0], J[1, 1], J[2, 2], J[1, 2], J[0, 2], J[0, 1]]))
        nodes[b.name], objs[b.name], rot0[b.name] = n, o, R
        if np.any(case.gravity != 0):
            mm = mbs.AddMarker(ei.MarkerBodyMass(bodyNumber=o))
            mbs.AddLoad(ei.LoadMassProportional(markerNumber=mm,
                                                loadVector=[float(g) for g in case.gravity]))
    if padded:
        notes.append(f"uniform rod(s) {', '.join(padded)}: axial inertia {eps:g} x the largest "
                     "moment added (Exudyn needs a regular mass matrix); the joints lock that "
                     "rotation")

    def local(body: str, point: str) -> list[float]:
        if body == GROUND:
            return [float(x) for x in case.ground[point]]
        b = case.body(body)
        return [float(x) for x in b.points[point] - b.com]

    def marker(body: str, point: str, rotation=None):
        num = ground if body == GROUND else objs[body]
        if rotation is None:
            return mbs.AddMarker(ei.MarkerBodyPosition(bodyNumber=num,
                                                       localPosition=local(body, point)))
        return mbs.AddMarker(ei.MarkerBodyRigid(
            bodyNumber=num, localHT=exu.HT(rotation=np.asarray(rotation, float),
                                           translation=local(body, point))))

    for f in case.forces:
        if f.body == GROUND:
            continue
        v = [float(x) for x in np.asarray(f.value, float).reshape(3)]
        if f.type == "torque":
            mr = mbs.AddMarker(ei.MarkerBodyRigid(bodyNumber=objs[f.body]))
            mbs.AddLoad(ei.LoadTorqueVector(markerNumber=mr, loadVector=v))
        else:
            mbs.AddLoad(ei.LoadForceVector(markerNumber=marker(f.body, f.point),
                                           loadVector=v))

    joint_objs, joint_frame = {}, {}
    for j in case.joints:
        a, b = j.bodies
        pa, pb = j.points
        if j.type == "revolute":
            A0 = _frame(j.axis)  # joint frame in a's frame
            A1 = _rotation0(init, b).T @ _rotation0(init, a) @ A0  # the same frame in b's
            jo = mbs.AddObject(ei.ObjectJointRevoluteZ(
                markerNumbers=[marker(a, pa, A0), marker(b, pb, A1)]))
            joint_frame[j.name] = A0
        else:
            jo = mbs.AddObject(ei.ObjectJointSpherical(
                markerNumbers=[marker(a, pa), marker(b, pb)]))
        joint_objs[j.name] = jo
    if any(j.type == "revolute" for j in case.joints):
        notes.append("revolute joints: ObjectJointRevoluteZ with joint frames (z along the "
                     "axis) as marker localHT; reaction = -(rotation of the first body) x "
                     "(joint frame) x ForceLocal")
    if any(j.type == "spherical" for j in case.joints):
        notes.append("spherical joints: ObjectJointSpherical; reaction = -Force output")

    def sensor(**kw):
        return mbs.AddSensor(kw.pop("kind")(storeInternal=True, writeToFile=False, **kw))

    tensions = connectors(ei, mbs, case, lambda body, point: marker(body, point), sensor, notes)
    sens = {b.name: [sensor(kind=ei.SensorNode, nodeNumber=nodes[b.name],
                            outputVariableType=v)
                     for v in (OV.Position, OV.Velocity, OV.RotationMatrix,
                               OV.AngularVelocity)]
            for b in case.bodies}
    jsens = {j.name: sensor(kind=ei.SensorObject, objectNumber=joint_objs[j.name],
                            outputVariableType=OV.ForceLocal if j.type == "revolute"
                            else OV.Force)
             for j in case.joints}
    mbs.Assemble()
    build = time.perf_counter() - t0

    wall, solver = solve(exu, mbs, case, s, n_steps, h)

    def get(sn: int) -> np.ndarray:
        return stored(mbs, case, sn)

    origin, velocity, omega, rotation = {}, {}, {}, {}
    for b in case.bodies:
        ps, vs, rs, ws = (get(x) for x in sens[b.name])
        R = rs.reshape(-1, 3, 3)
        rc = R @ b.com
        origin[b.name] = ps - rc
        velocity[b.name] = vs - np.cross(ws, rc)
        omega[b.name], rotation[b.name] = ws, R
    forces = {}
    for j in case.joints:
        f = get(jsens[j.name])[:, :3]
        if j.type == "revolute":
            a = j.bodies[0]
            Ra = rotation[a] if a != GROUND else np.eye(3)
            f = (Ra @ joint_frame[j.name] @ f[:, :, None])[:, :, 0]
        forces[j.name] = -f
    rod_force = {name: fn(get) for name, fn in tensions.items()}
    m = Motion(case.times.copy(), origin, {}, velocity, omega, forces, rotation=rotation,
               rod_force=rod_force)
    return engine_run(case, s, m, (*origin.values(), *rotation.values(), *forces.values(),
                                   *rod_force.values()), build, wall, solver, n_steps, notes)
