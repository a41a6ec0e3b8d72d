"""A lifted (3-D) case as a Drake ``MultibodyPlant``: bodies, a tree of joints, loops closed by
ball constraints, spring-dampers and constant loads.

Frames: every Drake body frame *is* the case body's frame (the centre of mass and inertia are
given in it), so poses and velocities read from Drake need no offset. A tree joint's frames F
(on the parent) and M (on the child) are world-aligned at t = 0 and sit at the child's joint
point, so q = 0 is natcoord's assembled pose and the joint's axis is its world axis at t = 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...case.mechanism import GROUND, Case
from ...errors import Unsupported
from ..planar import Frame, frame_of, node_point
from ..tree import point_loop_tree, tree_orientation, tree_parents

JOINT_TYPES = ("revolute", "prismatic", "spherical")  # as tree joints
WHY_POINT_LOOP = "a Drake ball constraint pins a point and cannot slide"
CONTINUOUS_LOOPS = ("closed loops need the discrete plant: Drake's continuous MultibodyPlant "
                    "refuses constraints ('Continuous time does not support constraints')")


def split_tree(case: Case) -> tuple[list, list, list[str]]:
    """(tree, loops, notes): a spanning tree whose loop-closing joints join two bodies.

    Joints to the ground are taken into the tree first (then prismatic ones, which a ball
    constraint cannot close), so no constraint is attached to Drake's world body (such a
    constraint crashed Drake in an earlier trial; a constraint between two bodies did not).
    """
    first = sorted(case.joints, key=lambda j: (GROUND not in j.bodies, j.type != "prismatic"))
    tree, loops, _ = point_loop_tree(dataclasses.replace(case, joints=tuple(first)),
                                     WHY_POINT_LOOP)
    notes = []
    for j in loops:
        if GROUND in j.bodies:
            raise Unsupported(f"loop joint {j.name} must close at the ground: a Drake "
                              "constraint to the world body is avoided (it crashed in a trial)")
        if j.type not in ("revolute", "spherical"):
            raise Unsupported(f"loop-closing {j.type} joint {j.name}: {WHY_POINT_LOOP}")
        notes.append(f"loop {j.type} joint {j.name} closed by AddBallConstraint between "
                     f"{j.bodies[0]} and {j.bodies[1]} (SAP, soft)")
    return tree, loops, notes


def _check_loop_axes(case: Case, frames: dict[str, Frame], tree, loops) -> None:
    """A ball constraint holds a 3-D loop revolute's point, not its axis: accepted only when
    every tree joint is a revolute parallel to it (the tree then keeps the alignment, as in
    four_bar_3d); else Unsupported."""
    for j in loops:
        if j.type != "revolute":
            continue
        u = frame_of(frames, j.bodies[0]).R @ np.asarray(j.axis, float)
        u = u / np.linalg.norm(u)
        for t in tree:
            w = None if t.type != "revolute" else frame_of(frames, t.bodies[0]).R @ t.axis
            if w is None or np.linalg.norm(np.cross(u, w / np.linalg.norm(w))) > 1e-9:
                raise Unsupported(
                    f"loop-closing 3-D revolute {j.name}: the tree does not keep its axis "
                    f"(tree joint {t.name}), and a Drake ball constraint holds only the "
                    "point: the loop would gain a degree of freedom")


@dataclasses.dataclass
class Built:
    """The finalized plant and what the readout needs."""

    plant: object
    bodies: dict          # case body name -> Drake RigidBody (ground -> world body)
    tree: list            # (joint, parent, child, Drake joint, sign)
    loops: list           # case joints closed by ball constraints
    notes: list
    particle_points: dict  # particle name -> its point (3,) in its frame


def _inertia(b, s: dict):
    """(mass, com (3,), central inertia (3, 3)) of a lifted body; a particle gets
    ``particle_inertia`` x mass about every axis (no joint turns it when its point is on the
    axis; reported with natcoord's particle frame)."""
    J = np.asarray(b.inertia, dtype=float)
    if b.kind == "particle":
        J = float(s["particle_inertia"]) * b.mass * np.eye(3)
    return float(b.mass), np.asarray(b.com, float), J


def _frames_at(plant, RigidTransform, RotationMatrix, parent_body, child_body, fp: Frame,
               fc: Frame, p_child: np.ndarray, name: str):
    """Frames F on the parent and M on the child: world-aligned at t = 0, at the child's
    joint point (world position fc.point(p_child))."""
    from pydrake.multibody.tree import FixedOffsetFrame

    w = fc.point(p_child)
    X_PF = RigidTransform(RotationMatrix(fp.R.T), fp.R.T @ (w - fp.origin))
    X_CM = RigidTransform(RotationMatrix(fc.R.T), np.asarray(p_child, float))
    F = plant.AddFrame(FixedOffsetFrame(f"{name}_F", parent_body.body_frame(), X_PF))
    M = plant.AddFrame(FixedOffsetFrame(f"{name}_M", child_body.body_frame(), X_CM))
    return F, M


def build(case: Case, frames: dict[str, Frame], s: dict, planar: bool) -> Built:
    """The plant of a lifted ``case`` (every vector (3,)) at its t = 0 ``frames``; ``s`` the
    merged settings. A discrete plant (SAP) when ``s["dt"] > 0`` else a continuous one."""
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.plant import DiscreteContactApproximation, MultibodyPlant
    from pydrake.multibody.tree import (
        BallRpyJoint,
        LinearSpringDamper,
        PlanarJoint,
        PrismaticJoint,
        RevoluteJoint,
        RotationalInertia,
        SpatialInertia,
    )

    for j in case.joints:
        if j.type not in JOINT_TYPES:
            raise Unsupported(f"joint {j.name}: type {j.type!r} is not modelled by this adapter")
    tree, loops, notes = split_tree(case)
    if not planar:
        _check_loop_axes(case, frames, tree, loops)
    discrete = s["plant"] == "discrete"
    if loops and not discrete:
        raise Unsupported(CONTINUOUS_LOOPS)
    plant = MultibodyPlant(float(s["dt"]) if discrete else 0.0)
    if discrete:
        plant.set_discrete_contact_approximation(DiscreteContactApproximation.kSap)
        plant.SetUseSampledOutputPorts(bool(s["sampled_ports"]))
    plant.mutable_gravity_field().set_gravity_vector(np.asarray(case.gravity, float))
    bodies = {GROUND: plant.world_body()}
    particles = {}
    for b in case.bodies:
        m, com, J = _inertia(b, s)
        I = RotationalInertia(J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2])
        bodies[b.name] = plant.AddRigidBody(b.name, SpatialInertia.MakeFromCentralInertia(
            m, com, I))
        if b.kind == "particle":
            particles[b.name] = np.asarray(next(iter(b.points.values())), float)
    out_tree = []
    for j, parent, child in tree_parents(tree):
        fp, fc = frame_of(frames, parent), frame_of(frames, child)
        k = 1 if j.bodies[1] == child else 0
        F, M = _frames_at(plant, RigidTransform, RotationMatrix, bodies[parent],
                          bodies[child], fp, fc, node_point(case, child, j.points[k]), j.name)
        if j.type == "spherical":
            dj = plant.AddJoint(BallRpyJoint(j.name, F, M))
            if discrete:  # measured on a spinning rod: 29x DART's error at the same dt
                notes.append(f"spherical joint {j.name}: BallRpyJoint; the discrete plant "
                             "steps its roll-pitch-yaw angles (q += dt N(q) v), first order "
                             "with a constant that grows towards 90 deg pitch (DART and "
                             "PyBullet step the rotation itself); plant = \"continuous\" "
                             "for a tree without loops")
        else:
            axis = frame_of(frames, j.bodies[0]).R @ np.asarray(j.axis, float)
            axis = axis / np.linalg.norm(axis)
            kind = RevoluteJoint if j.type == "revolute" else PrismaticJoint
            dj = plant.AddJoint(kind(j.name, F, M, axis))
        out_tree.append((j, parent, child, dj, tree_orientation(j, parent)))
    reached = {c for _, _, c, _, _ in out_tree}
    for b in case.bodies:
        if b.name in reached or not planar:
            continue  # 3-D: Drake makes an unreached body free (quaternion floating joint)
        f = frames[b.name]
        F = plant.world_frame()
        from pydrake.multibody.tree import FixedOffsetFrame
        M = plant.AddFrame(FixedOffsetFrame(f"{b.name}_planar_M", bodies[b.name].body_frame(),
                                            RigidTransform(RotationMatrix(f.R.T), np.zeros(3))))
        dj = plant.AddJoint(PlanarJoint(f"{b.name}_planar", F, M))
        out_tree.append((None, GROUND, b.name, dj, 1))
        notes.append(f"body {b.name} is not joined to the ground: PlanarJoint (x, y, theta)")
    for j in loops:
        (a, c), (pa, pc) = j.bodies, j.points
        plant.AddBallConstraint(bodies[a], node_point(case, a, pa), bodies[c],
                                node_point(case, c, pc))
    for sp in case.springs:
        (a, pa), (c, pc) = sp.ends
        plant.AddForceElement(LinearSpringDamper(
            bodies[a], node_point(case, a, pa), bodies[c], node_point(case, c, pc),
            float(sp.length), float(sp.stiffness), float(sp.damping)))
    if case.springs:
        notes.append("spring-dampers as LinearSpringDamper force elements")
    plant.Finalize()
    return Built(plant, bodies, out_tree, list(loops), notes, particles)


def set_initial_state(built: Built, context, frames: dict[str, Frame], planar: bool) -> None:
    """Positions at q = 0 (the assembled pose) and every joint's rate from the bodies'
    velocities at t = 0; bodies without a joint (3-D) as free bodies."""
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.math import SpatialVelocity

    plant = built.plant
    for j, parent, child, dj, _ in built.tree:
        fp, fc = frame_of(frames, parent), frame_of(frames, child)
        if j is None:  # planar joint of a free body
            dj.set_translation(context, fc.origin[:2])
            dj.set_rotation(context, 0.0)
            dj.set_translational_velocity(context, fc.velocity[:2])
            dj.set_angular_velocity(context, float(fc.omega[2]))
            continue
        w_rel = fc.omega - fp.omega
        kind = type(dj).__name__
        if kind.startswith("RevoluteJoint"):
            dj.set_angular_rate(context, float(w_rel @ dj.revolute_axis()))
        elif kind.startswith("PrismaticJoint"):
            k = 1 if j.bodies[1] == child else 0
            p = fc.point(_child_point(built, j, k, frames, child))
            v_rel = fc.velocity + np.cross(fc.omega, p - fc.origin) - fp.point_velocity(
                fp.R.T @ (p - fp.origin))
            dj.set_translation_rate(context, float(v_rel @ dj.translation_axis()))
        else:  # BallRpyJoint at zero angles: the rpy rates are w_FM in F (world-aligned)
            dj.set_angular_velocity(context, w_rel)
    reached = {c for _, _, c, _, _ in built.tree}
    for name, body in built.bodies.items():
        if name == GROUND or name in reached:
            continue
        f = frames[name]
        plant.SetFreeBodyPose(context, body, RigidTransform(RotationMatrix(f.R), f.origin))
        plant.SetFreeBodySpatialVelocity(context, body, SpatialVelocity(f.omega, f.velocity))


def _child_point(built: Built, j, k: int, frames, child) -> np.ndarray:
    """The joint's point on the child (its own frame), from the Drake frame M."""
    M = built.plant.GetJointByName(j.name).frame_on_child()
    return M.GetFixedPoseInBodyFrame().translation()
