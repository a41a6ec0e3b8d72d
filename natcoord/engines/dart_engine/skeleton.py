"""The DART skeleton of a (lifted, 3-D) case: tree joints, bodies not reached by the tree,
light rods, the loop-closing constraints, and the state at t = 0 taken from natcoord's
assembled body frames."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...case.mechanism import GROUND, Case, Joint
from ...errors import Unsupported
from ..planar import Frame, frame_of, node_point
from ..tree import point_loop_tree, tree_orientation, tree_parents
from .loads import ROD_NOTE, LightRod, iso, slender_inertia

TREE_JOINTS = ("revolute", "prismatic", "spherical", "universal")


@dataclass
class Skeleton:
    """The built skeleton and what the stepping loop needs to read it."""

    skel: object
    nodes: dict[str, object]  # body -> BodyNode
    joints: dict[str, object]  # tree joint name -> Joint
    sign: dict[str, int]  # tree joint -> +1 if its first body is the tree parent
    children: dict[str, list] = field(default_factory=dict)  # body -> joints of its children
    loops: list[Joint] = field(default_factory=list)
    rods: list[LightRod] = field(default_factory=list)


def choose_tree(case: Case, notes: list[str]) -> tuple[list[Joint], list[Joint]]:
    """Tree and loop joints. DART closes loops with point constraints only (ball, revolute),
    so a prismatic loop joint makes the tree recut (prismatic joints first); a loop joint of
    another type is unsupported."""
    tree, loops, recut = point_loop_tree(case, "DART has no prismatic joint constraint")
    if recut:
        notes.append("natcoord's spanning tree closes a loop with a prismatic joint, which "
                     "DART cannot constrain; tree recomputed with prismatic joints first, "
                     "loops cut at " + ", ".join(j.name for j in loops))
    bad = [j for j in loops if j.type not in ("revolute", "spherical")]
    if bad:
        raise Unsupported(f"{bad[0].type} joint {bad[0].name!r} closes a loop: DART has joint "
                          "constraints for ball and revolute joints only")
    return tree, loops


def world_axis(j: Joint, frames: dict[str, Frame], which: int = 0) -> np.ndarray:
    """A joint axis (3,) in world at t = 0: ``axis`` lies in the first body's frame,
    ``axis2`` (which = 1) in the second's."""
    a = np.asarray(j.axis if which == 0 else j.axis2, dtype=float)
    return frame_of(frames, j.bodies[which]).R @ (a / np.linalg.norm(a))


def build(dart, case: Case, frames: dict[str, Frame], s: dict, normal, notes: list[str]):
    """The skeleton of a 3-D case, set to the assembled state at t = 0 (checked).

    ``normal`` (3,) is the plane a planar model's free bodies and light rods stay in (None
    for a 3-D model)."""
    tree, loops = choose_tree(case, notes)
    sk = Skeleton(dart.dynamics.Skeleton(case.name), {}, {}, {}, loops=loops)
    for j, parent, child in tree_parents(tree):
        joint = _tree_joint(dart, sk, case, frames, j, parent, child)
        sk.joints[j.name], sk.sign[j.name] = joint, tree_orientation(j, parent)
        sk.children.setdefault(parent, []).append(joint)
    for b in case.bodies:
        if b.name not in sk.nodes:
            _free_body(dart, sk, frames[b.name], b, normal, notes)
    _inertias(dart, case, sk, s, notes)
    axial = float(s["axial_inertia"])
    sk.rods = [LightRod(r, case, frames) for r in case.rods]
    for r in sk.rods:
        r.build(dart, sk.skel, sk.nodes, float(s["rod_mass"]), axial, normal)
        r.set_rate(normal)
        if r.ends[0][0] != GROUND:
            sk.children.setdefault(r.ends[0][0], []).append(r.joint)
    if sk.rods:
        notes.append(ROD_NOTE.format(names=", ".join(r.name for r in sk.rods),
                                     m=s["rod_mass"],
                                     joint="ball" if normal is None else "revolute"))
    check_assembly(case, sk.nodes, frames)
    return sk


def _tree_joint(dart, sk: Skeleton, case: Case, frames, j: Joint, parent: str, child: str):
    """Joint and body node of ``child``, at the assembled state. The joint frame sits at the
    joint point with the child's axes at t = 0 on both sides, so every rotation coordinate
    starts at 0 (a prismatic one at the points' offset along the axis)."""
    P, C = frame_of(frames, parent), frames[child]
    p_p = node_point(case, parent, j.points[j.bodies.index(parent)])
    p_c = node_point(case, child, j.points[j.bodies.index(child)])
    create = {"revolute": sk.skel.createRevoluteJointAndBodyNodePair,
              "prismatic": sk.skel.createPrismaticJointAndBodyNodePair,
              "spherical": sk.skel.createBallJointAndBodyNodePair,
              "universal": sk.skel.createUniversalJointAndBodyNodePair}[j.type]
    joint, node = create(None if parent == GROUND else sk.nodes[parent])
    if j.type == "prismatic":  # the parent side of the line the child point slides on
        a_w, d = world_axis(j, frames), C.point(p_c) - P.point(p_p)
        p_p = p_p + P.R.T @ (d - (a_w @ d) * a_w)
    joint.setTransformFromParentBodyNode(iso(dart, p_p, P.R.T @ C.R))
    joint.setTransformFromChildBodyNode(iso(dart, p_c))
    joint.setName(j.name)
    node.setName(child)
    sk.nodes[child] = node
    _set_axes_and_rates(joint, j, frames, P, C, (P.point(p_p), C.point(p_c)), parent)
    return joint


def _set_axes_and_rates(joint, j: Joint, frames, P: Frame, C: Frame, x, parent: str) -> None:
    """Axes (joint = child axes), the prismatic coordinate and every joint rate from the
    parent and child frames at t = 0; ``x`` holds the parent- and child-side joint points
    in world (3,) m."""
    w_rel = C.R.T @ (C.omega - P.omega)  # relative angular velocity, child (= joint) axes
    if j.type in ("revolute", "prismatic"):
        a_w = world_axis(j, frames)
        a = C.R.T @ a_w
        joint.setAxis(a)
        if j.type == "revolute":
            joint.setVelocity(0, float(a @ w_rel))
            return
        d = x[1] - x[0]
        v_rel = (C.point_velocity(C.R.T @ (x[1] - C.origin))
                 - P.point_velocity(P.R.T @ (x[0] - P.origin)) - np.cross(P.omega, d))
        joint.setPosition(0, float(a_w @ d))
        joint.setVelocity(0, float(a_w @ v_rel))
    elif j.type == "universal":  # DART: R(axis1, q1) R(axis2, q2), axis1 on the parent
        first = j.bodies[0] == parent
        a1 = C.R.T @ world_axis(j, frames, 0 if first else 1)
        a2 = C.R.T @ world_axis(j, frames, 1 if first else 0)
        joint.setAxis1(a1)
        joint.setAxis2(a2)
        joint.setVelocities(np.array([a1 @ w_rel, a2 @ w_rel]))
    else:
        joint.setVelocities(w_rel)


def _free_body(dart, sk: Skeleton, st: Frame, body, normal, notes: list[str]) -> None:
    """A body the tree does not reach: free in the plane of a planar model (a 2-D
    translational joint for a particle, which keeps angle 0), else a FreeJoint."""
    name = body.name
    if normal is None:
        joint, node = sk.skel.createFreeJointAndBodyNodePair(None)
        joint.setPositions(dart.dynamics.FreeJoint.convertToPositions(iso(dart, st.origin,
                                                                          st.R)))
        joint.setVelocities(np.concatenate([st.R.T @ st.omega, st.R.T @ st.velocity]))
        how = "DART FreeJoint"
    else:  # DART's planar joints move in the x-y plane of their parent frame
        if body.kind == "particle":
            joint, node = sk.skel.createTranslationalJoint2DAndBodyNodePair(None)
            joint.setPositions(st.origin[:2])
            joint.setVelocities(st.velocity[:2])
        else:
            joint, node = sk.skel.createPlanarJointAndBodyNodePair(None)
            angle = np.arctan2(st.R[1, 0], st.R[0, 0])
            joint.setPositions(np.array([st.origin[0], st.origin[1], angle]))
            joint.setVelocities(np.array([st.velocity[0], st.velocity[1], st.omega[2]]))
        how = "free in the plane (DART planar joint)"
    joint.setName(f"free {name}")
    node.setName(name)
    sk.nodes[name] = node
    notes.append(f"body {name!r} is not joined to the ground by the tree: {how}")


def _inertias(dart, case: Case, sk: Skeleton, s: dict, notes: list[str]) -> None:
    """Mass properties of every body node: a particle gets a tiny rotational inertia about
    its point, a slender rod ``axial_inertia`` times its transverse inertia about its axis
    (DART needs a positive definite inertia)."""
    r_gyr, axial = float(s["particle_radius_of_gyration"]), float(s["axial_inertia"])
    slender = []
    for b in case.bodies:
        J = np.asarray(b.inertia, dtype=float)
        if b.kind == "particle":
            J = b.mass * r_gyr**2 * np.eye(3)
            notes.append(f"particle {b.name!r}: point mass given a tiny rotational inertia "
                         f"({J[0, 0]:.3g} kg m^2) about its point; its angle is reported "
                         "as 0")
        elif b.kind == "uniform_rod":
            e0, e1 = b.ends or list(b.points)[:2]
            J = slender_inertia(b.mass, b.points[e0], b.points[e1], axial)
            slender.append(b.name)
        sk.nodes[b.name].setInertia(dart.dynamics.Inertia(b.mass, np.asarray(b.com, float), J))
    if slender:
        notes.append(f"slender rod(s) {', '.join(slender)}: inertia about the rod axis "
                     f"{axial:g} x the transverse one (DART needs it positive definite)")


def check_assembly(case: Case, nodes, frames: dict[str, Frame], tol: float = 1e-7) -> None:
    """Every body node must start at its assembled frame pose and rates (a particle's
    orientation and spin are meaningless and not checked)."""
    import dartpy as dart

    W = dart.dynamics.Frame.World()
    for b in case.bodies:
        node, st = nodes[b.name], frames[b.name]
        T = node.getWorldTransform().matrix()
        errs = [np.linalg.norm(T[:3, 3] - st.origin), np.abs(T[:3, :3] - st.R).max(),
                np.linalg.norm(np.asarray(node.getLinearVelocity(W, W)) - st.velocity),
                np.linalg.norm(np.asarray(node.getAngularVelocity(W, W)) - st.omega)]
        if b.kind == "particle":
            errs[1] = errs[3] = 0.0
        if max(errs) > tol * max(1.0, np.linalg.norm(st.velocity)):
            raise RuntimeError(
                f"DART adapter: body {b.name!r} does not match the assembled state (origin "
                "{:.2e} m, rotation {:.2e}, velocity {:.2e} m/s, omega {:.2e} rad/s)"
                .format(*errs))


def add_loop_constraints(dart, case: Case, sk: Skeleton, frames, s: dict, solver,
                         notes: list[str]) -> None:
    """A BallJointConstraint per spherical loop joint, and per revolute one when every
    revolute axis of the case is parallel (a planar loop: the tree keeps the rotations, only
    the point rows are needed); otherwise a RevoluteJointConstraint (``loop_constraint =
    "revolute"``). Light rods get a BallJointConstraint at their far end."""
    for r in sk.rods:
        solver.addConstraint(r.constraint(dart, sk.nodes))
    planar = _parallel_revolutes(case, frames)
    ball = [j for j in sk.loops if j.type == "spherical"
            or (s["loop_constraint"] == "ball" and planar)]
    rev = [j for j in sk.loops if j not in ball]
    if rev and s["loop_constraint"] != "revolute":
        raise Unsupported(
            f"loop joint(s) {', '.join(j.name for j in rev)}: revolute joints with "
            "different axes close the loop, a BallJointConstraint would drop their rotation "
            "rows (setting loop_constraint = 'revolute' uses DART's RevoluteJointConstraint)")
    for j in sk.loops:
        pos = frame_of(frames, j.bodies[1]).point(node_point(case, j.bodies[1], j.points[1]))
        ends = [sk.nodes[x] for x in j.bodies if x != GROUND]
        if j in ball:
            c = dart.constraint.BallJointConstraint(*ends, pos)
        else:
            a = world_axis(j, frames)
            c = dart.constraint.RevoluteJointConstraint(*ends, pos, *[a] * len(ends))
        solver.addConstraint(c)
    if ball:
        why = ("" if all(j.type == "spherical" for j in ball) else
               " (every revolute axis is parallel: the loop is planar and the tree keeps its "
               "rotations, so only the point rows are needed)")
        notes.append(f"loop joint(s) {', '.join(j.name for j in ball)}: DART "
                     f"BallJointConstraint, error-reduction parameter {s['erp']}{why}")
    if rev:
        notes.append(f"loop joint(s) {', '.join(j.name for j in rev)}: DART "
                     f"RevoluteJointConstraint, error-reduction parameter {s['erp']}")


def _parallel_revolutes(case: Case, frames) -> bool:
    axes = [world_axis(j, frames) for j in case.joints if j.type == "revolute"]
    return all(abs(abs(a @ axes[0]) - 1.0) < 1e-12 for a in axes)
