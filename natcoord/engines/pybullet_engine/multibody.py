"""The PyBullet multibody of a lifted case (:func:`natcoord.engines.planar.lift_case`): one
fixed base (the ground, the world frame), one link per body, loops closed by
``JOINT_POINT2POINT`` constraints.

Each link's frame is its body's frame at t = 0 moved to the point of its tree joint (PyBullet
puts a joint at its child link's frame origin), so every joint starts at q = 0 and the
multibody at natcoord's assembled state. What PyBullet would otherwise do by itself, and is
overridden here (``TRAPS``), each checked in ``tests/test_engine_pybullet.py``:

* link damping: every link gets ``linearDamping`` and ``angularDamping`` 0.04 s^-1 by
  default, applied to the velocities each step: set to 0, and so is the joint damping;
* joint motors: every revolute and prismatic joint gets a velocity motor (target 0) that
  holds it still: disabled with ``VELOCITY_CONTROL`` at ``force`` 0;
* inertia: without a collision shape PyBullet invents one; every link gets its mass,
  ``localInertiaDiagonal`` (the principal moments) and its inertial frame (centre of mass
  and principal axes) explicitly;
* constraint pivots: ``createConstraint`` takes the pivot relative to each link's centre of
  mass, in its inertial (principal) axes, not relative to the link frame;
* joint speed: every joint's rate is capped at 100 rad/s (m/s), silently: raised to
  :data:`MAX_JOINT_VELOCITY` (a03_andrews' crank turns at 1.4e3 rad/s).

PyBullet renumbers the links depth first (:func:`depth_first`) and reports a joint's axis
in its link's principal axes, so both are kept here rather than read back.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...case.mechanism import GROUND, Case, Joint
from ...errors import Unsupported
from ..planar import GROUND_FRAME, Frame, cross, frame_of, node_point
from ..tree import point_loop_tree, tree_parents

TRAPS = {"damping": "link damping 0.04 s^-1 set to 0 (linear, angular and joint damping)",
         "motors": "default velocity motors disabled (VELOCITY_CONTROL, force 0)",
         "inertia": "masses and principal inertias set explicitly, not from shapes",
         "pivots": "point-to-point pivots given relative to each link's centre of mass",
         "speed": "joint speed cap of 100 rad/s (or m/s) raised to 1e10"}
MAX_JOINT_VELOCITY = 1e10  # rad/s or m/s, the joint speed cap (PyBullet's default 100)
TREE_TYPES = ("revolute", "prismatic", "spherical")
# a zero principal moment (a point mass, a slender rod's own axis) is raised to this
# fraction of the body's largest one, or of m r^2 for a point mass
ZERO_INERTIA_SUBSTITUTE = 1e-10


def quat(R: np.ndarray) -> list[float]:
    """PyBullet's quaternion (x, y, z, w) of a rotation matrix (3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, float)).as_quat().tolist()


def principal(b, s: dict, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(moments (3,) kg m^2, V (3, 3)): the body's inertia about its centre of mass is
    ``V diag(moments) V^T`` in body axes, ``V`` a rotation. A particle gets
    ``particle_inertia`` on every axis (its joints cannot turn it, or it is welded); a zero
    moment is raised (PyBullet's articulated-body algorithm needs them positive)."""
    if b.kind == "particle":
        return np.full(3, float(s["particle_inertia"])), np.eye(3)
    w, V = np.linalg.eigh(np.asarray(b.inertia, float))
    if np.linalg.det(V) < 0:
        V[:, 2] = -V[:, 2]
    w = np.clip(w, 0.0, None)
    if w.max() <= 0:
        reach = max(float(np.linalg.norm(p - b.com)) for p in b.points.values())
        w = np.full(3, ZERO_INERTIA_SUBSTITUTE * b.mass * reach**2)
        notes.append(f"body {b.name} is a point mass; it gets {w[0]:.1e} kg m^2 about every "
                     "axis (PyBullet needs positive inertia)")
    small = w <= 1e-12 * w.max()
    if np.any(small):
        w[small] = float(s["zero_inertia"]) * w.max()
        notes.append(f"body {b.name} has a zero principal moment; it gets "
                     f"{s['zero_inertia']:g} of its largest there")
    return w, V


@dataclasses.dataclass
class Link:
    """One body as a PyBullet link: ``index`` (link index), ``pc`` (3,) the link frame's
    origin in body coordinates (m), ``com`` (3,) its centre of mass there, ``V`` (3, 3) its
    principal axes in body axes, ``welded``: a particle fixed to its parent."""

    body: str
    index: int
    pc: np.ndarray
    com: np.ndarray
    V: np.ndarray
    moments: np.ndarray
    welded: bool = False
    axis: np.ndarray | None = None  # the tree joint's world axis (3,) at t = 0


@dataclasses.dataclass
class Built:
    """The multibody and what reading it needs."""

    uid: int
    links: dict[str, Link]
    tree: list[tuple[Joint, str, str]]  # (joint, parent, child), parent first
    loops: dict[str, list[int]]  # loop joint -> its constraint ids (the joint point; a
    # 3-D revolute's also a point along its axis)
    gaps: list[tuple[tuple[str, np.ndarray], tuple[str, np.ndarray]]]  # the pairs of body
    # points (body, point (3,) in its frame) the constraints hold together
    joint_index: dict[str, int]  # tree joint -> link (= PyBullet joint) index
    notes: list[str]


def split(case: Case) -> tuple[list[Joint], list[Joint], list[str]]:
    """Tree joints, loop joints and a note; a loop closes at a revolute or spherical
    joint only (a point-to-point constraint holds a point)."""
    for j in case.joints:
        if j.type not in TREE_TYPES:
            raise Unsupported(f"joint {j.name}: type {j.type!r}: a PyBullet multibody joint "
                              "is revolute, prismatic, spherical or fixed (a universal or "
                              "cylindrical joint would need a massless link in between)")
    tree, loops, recut = point_loop_tree(
        case, "PyBullet's user constraints (point-to-point, fixed, gear) hold no slide")
    note = ([f"loop cut at {', '.join(j.name for j in loops)} instead of prismatic "
             f"{', '.join(recut)} (a point-to-point constraint cannot slide)"] if recut else [])
    return tree, loops, note


def depth_first(tree: list[tuple[Joint, str, str]]) -> list[tuple[Joint, str, str]]:
    """The tree in depth-first preorder from the ground, children in tree order: PyBullet
    renumbers the links of ``createMultiBody`` that way (measured: a breadth-first list
    came back with its link indices permuted), so it must be their order already."""
    children: dict[str, list] = {}
    for entry in tree:
        children.setdefault(entry[1], []).append(entry)
    out: list[tuple[Joint, str, str]] = []

    def visit(node: str) -> None:
        for entry in children.get(node, []):
            out.append(entry)
            visit(entry[2])

    visit(GROUND)
    return out


def _relative(parent: Frame, origin: np.ndarray, R: np.ndarray):
    """(position (3,), rotation (3, 3)) of a frame in ``parent``'s frame."""
    return parent.R.T @ (origin - parent.origin), parent.R.T @ R


def build(pb, cid: int, case: Case, frames: dict[str, Frame], s: dict, planar: bool,
          keep: tuple[str, ...] = ()) -> Built:
    """The multibody of the lifted ``case`` at its ``frames`` (t = 0) in client ``cid``,
    with every trap of :data:`TRAPS` overridden and the loops closed; velocities are set by
    :func:`set_velocities`. ``planar``: a lifted 2-D case. ``keep`` names traps left as
    PyBullet has them (the tests show what each one does; never a run's choice)."""
    tree_joints, loops, notes = split(case)
    tree = depth_first(tree_parents(tree_joints))
    reached = {GROUND} | {c for _, _, c in tree}
    free = [b.name for b in case.bodies if b.name not in reached]
    if free:
        raise Unsupported(f"bodies {', '.join(free)} are not joined to the ground: the "
                          "adapter builds one fixed-base multibody")
    links: dict[str, Link] = {}
    origin_w: dict[str, np.ndarray] = {}  # world position of each link frame's origin
    args = {k: [] for k in ("linkMasses", "linkCollisionShapeIndices",
                            "linkVisualShapeIndices", "linkPositions", "linkOrientations",
                            "linkInertialFramePositions", "linkInertialFrameOrientations",
                            "linkParentIndices", "linkJointTypes", "linkJointAxis")}
    joint_index = {}
    for i, (j, par, child) in enumerate(tree):
        b = case.body(child)
        f = frames[child]
        k = 1 if j.bodies[1] == child else 0
        pc = node_point(case, child, j.points[k])
        origin_w[child] = f.point(pc)
        welded = b.kind == "particle" and j.type in ("revolute", "spherical")
        moments, V = principal(b, s, notes)
        links[child] = Link(child, i, pc, np.asarray(b.com, float), V, moments, welded)
        pf = frame_of(frames, par)
        p_origin = GROUND_FRAME.origin if par == GROUND else origin_w[par]
        pos, rot = _relative(Frame(p_origin, pf.R, pf.velocity, pf.omega), origin_w[child],
                             f.R)
        u = frame_of(frames, j.bodies[0]).R @ j.axis if j.axis is not None else np.zeros(3)
        if j.type == "prismatic" and k == 0:
            u = -u  # the slide of the second body against the first
        kind = {"revolute": pb.JOINT_REVOLUTE, "prismatic": pb.JOINT_PRISMATIC,
                "spherical": pb.JOINT_SPHERICAL}[j.type]
        if welded:
            kind = pb.JOINT_FIXED
            notes.append(f"particle {child} welded to {par} at its {j.type} joint {j.name} "
                         "(its rotation carries no energy: exact)")
        links[child].axis = u
        args["linkMasses"].append(float(b.mass))
        args["linkCollisionShapeIndices"].append(-1)
        args["linkVisualShapeIndices"].append(-1)
        args["linkPositions"].append(pos.tolist())
        args["linkOrientations"].append(quat(rot))
        args["linkInertialFramePositions"].append((b.com - pc).tolist())
        args["linkInertialFrameOrientations"].append(quat(V))
        args["linkParentIndices"].append(0 if par == GROUND else links[par].index + 1)
        args["linkJointTypes"].append(kind)
        args["linkJointAxis"].append((f.R.T @ u).tolist())
        joint_index[j.name] = i
    uid = pb.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1,
                             baseVisualShapeIndex=-1, basePosition=[0.0, 0.0, 0.0],
                             baseOrientation=[0.0, 0.0, 0.0, 1.0], physicsClientId=cid, **args)
    if uid < 0:
        raise RuntimeError("PyBullet refused the multibody (createMultiBody returned "
                           f"{uid})")
    _override_traps(pb, cid, uid, case, links, keep)
    built = Built(uid, links, tree, {}, [], joint_index, notes)
    offset = float(s["loop_axis_offset"])
    for j in loops:
        ends = [(n, np.asarray(node_point(case, n, p), float))
                for n, p in zip(j.bodies, j.points, strict=True)]
        pairs = [ends]
        if offset > 0 and j.type == "revolute" and case.dimension == 3 and planar is False:
            u = frame_of(frames, j.bodies[0]).R @ j.axis * offset  # world, at t = 0
            pairs.append([(n, p + frame_of(frames, n).R.T @ u) for n, p in ends])
            notes.append(f"loop revolute {j.name} also holds its axis: a second "
                         f"point-to-point constraint {offset:g} m along it (6 rows for 5; "
                         "the joint force is the sum of both)")
        built.loops[j.name] = [_point2point(pb, cid, uid, links, pair, s,
                                            "pivots" not in keep) for pair in pairs]
        built.gaps += [tuple(pair) for pair in pairs]
    notes += [f"loop {j.type} joint {j.name} closed by a JOINT_POINT2POINT constraint "
              f"(3 rows) between {j.bodies[0]} and {j.bodies[1]}" for j in loops]
    notes.append("PyBullet defaults overridden: "
                 + "; ".join(v for k, v in TRAPS.items() if k not in keep))
    return built


def _override_traps(pb, cid: int, uid: int, case: Case, links: dict[str, Link],
                    keep: tuple[str, ...]) -> None:
    """No link or joint damping, no motors, the declared masses and inertias (the inertial
    frames, centre of mass and principal axes, are set by ``createMultiBody``)."""
    n = pb.getNumJoints(uid, physicsClientId=cid)
    for link in links.values():
        if "inertia" not in keep:
            pb.changeDynamics(uid, link.index, mass=float(case.body(link.body).mass),
                              localInertiaDiagonal=link.moments.tolist(), physicsClientId=cid)
        if "damping" not in keep:
            pb.changeDynamics(uid, link.index, linearDamping=0.0, angularDamping=0.0,
                              jointDamping=0.0, physicsClientId=cid)
        if "speed" not in keep:
            pb.changeDynamics(uid, link.index, maxJointVelocity=MAX_JOINT_VELOCITY,
                              physicsClientId=cid)
    if "damping" not in keep:
        pb.changeDynamics(uid, -1, linearDamping=0.0, angularDamping=0.0,
                          physicsClientId=cid)
    if "motors" in keep:
        return
    single = [i for i in range(n) if pb.getJointInfo(uid, i, physicsClientId=cid)[2]
              in (pb.JOINT_REVOLUTE, pb.JOINT_PRISMATIC)]
    if single:
        pb.setJointMotorControlArray(uid, single, pb.VELOCITY_CONTROL,
                                     forces=[0.0] * len(single), physicsClientId=cid)
    for i in range(n):
        if pb.getJointInfo(uid, i, physicsClientId=cid)[2] == pb.JOINT_SPHERICAL:
            pb.setJointMotorControlMultiDof(uid, i, pb.POSITION_CONTROL,
                                            targetPosition=[0.0, 0.0, 0.0, 1.0],
                                            positionGain=0.0, velocityGain=0.0,
                                            force=[0.0, 0.0, 0.0], physicsClientId=cid)


def pivot(links: dict[str, Link], node: str, p: np.ndarray,
          from_com: bool = True) -> np.ndarray:
    """A body point ``p`` (3,) m (body frame) as PyBullet's constraint wants it: relative
    to the link's centre of mass, in its principal axes (the ground: world coordinates).
    ``from_com`` False: in the link frame, the mistake :data:`TRAPS` names."""
    if node == GROUND:
        return p
    link = links[node]
    return link.V.T @ (p - link.com) if from_com else p - link.pc


def _point2point(pb, cid, uid, links, pair, s: dict, from_com: bool) -> int:
    """A point-to-point constraint holding ``pair`` ((body, point), (body, point)) together;
    its state is the force on the second body, world axes."""
    (a, pa), (b, pb_) = pair
    c = pb.createConstraint(uid, -1 if a == GROUND else links[a].index,
                            uid, -1 if b == GROUND else links[b].index,
                            pb.JOINT_POINT2POINT, [0.0, 0.0, 0.0],
                            pivot(links, a, pa, from_com).tolist(),
                            pivot(links, b, pb_, from_com).tolist(), physicsClientId=cid)
    pb.changeConstraint(c, maxForce=float(s["max_constraint_force"]),
                        physicsClientId=cid)
    return c


def set_velocities(pb, cid: int, built: Built, case: Case, frames: dict[str, Frame]) -> None:
    """Every tree joint's rate at t = 0 from the assembled frames: a revolute's is the
    relative angular velocity along its axis, a slide's the joint point's relative velocity
    along it, a spherical joint's the relative angular velocity in the child's axes."""
    for j, par, child in built.tree:
        link = built.links[child]
        if link.welded:
            continue
        f, pf = frames[child], frame_of(frames, par)
        idx = built.joint_index[j.name]
        wrel = f.omega - pf.omega
        if j.type == "spherical":
            pb.resetJointStateMultiDof(built.uid, idx, [0.0, 0.0, 0.0, 1.0],
                                       (f.R.T @ wrel).tolist(), physicsClientId=cid)
            continue
        u = link.axis  # (getJointInfo gives it in the principal axes)
        x = f.point(link.pc)  # the parent's material point there moves with the parent
        vrel = f.point_velocity(link.pc) - (pf.velocity + cross(pf.omega, x - pf.origin))
        rate = float((wrel if j.type == "revolute" else vrel) @ u)
        pb.resetJointState(built.uid, idx, 0.0, rate, physicsClientId=cid)
