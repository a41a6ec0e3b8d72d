"""The Pinocchio model of a lifted case: the kinematic tree, its bodies, light rods for
massless rods, floating joints for bodies no joint reaches, and the applied loads.

Every Pinocchio joint frame is world-aligned at t = 0 (q = neutral), placed at its joint
point; a body frame is a fixed placement ``X`` in its joint frame, built from the body's
pose at t = 0 (``init``), so posed and reference-frame cases go through the same code.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...case.mechanism import GROUND, Case
from ...errors import Unsupported
from ..planar import GROUND_FRAME, Frame, cross, lift_case, lift_init, node_point, plane_normal
from ..tree import point_loop_tree, tree_orientation, tree_parents

ANY = "any"  # a joint that turns its child about any axis (spherical, universal, free)


@dataclass(frozen=True)
class Lifted:
    """A case in 3-D (:func:`natcoord.engines.planar.lift_case`) with its frames at t = 0:
    ``frames`` node -> :class:`~natcoord.engines.planar.Frame` (ground included), ``plane``
    the normal (3,) of a 2-D case's plane of motion, None in 3-D."""

    case: Case
    frames: dict[str, Frame]
    plane: np.ndarray | None

    @classmethod
    def of(cls, case: Case, init) -> Lifted:
        """``case`` (2-D or 3-D) and its state at t = 0 (``init[body]``) in 3-D."""
        return cls(lift_case(case), {GROUND: GROUND_FRAME, **lift_init(case, init)},
                   plane_normal(case))

    def point(self, node: str, name: str) -> np.ndarray:
        """A named point (3,) m in its node's frame (a ground point in world axes)."""
        return node_point(self.case, node, name)

    def world_point(self, node: str, name: str) -> np.ndarray:
        """World position (3,) of a named point at t = 0, m."""
        return self.frames[node].point(self.point(node, name))

    def world_velocity(self, node: str, name: str) -> np.ndarray:
        """World velocity (3,) of a named point at t = 0, m/s."""
        return self.frames[node].point_velocity(self.point(node, name))


@dataclass
class Edge:
    """One Pinocchio joint: ``child`` (a body, a light rod ``rod <name>`` or a floating
    body's translation carrier) hangs from ``parent`` through ``joint`` placed at world
    ``at`` (3,) m at t = 0, with ``X`` the child's frame in the joint frame (SE3), ``q0``,
    ``v0`` its initial configuration and velocity, ``turns`` the world axis (3,) it turns its
    child about at t = 0 (None: it does not, ``ANY``: any axis) and ``sign`` the case
    joint's orientation (+1: its second body is the child)."""

    parent: str
    child: str
    name: str
    joint: object
    at: np.ndarray
    X: object
    q0: list
    v0: list
    kind: str  # "joint" | "carrier" | "free" | "rod"
    turns: object = None
    sign: int = 1


@dataclass
class Built:
    """The Pinocchio model of a case and the maps back to natcoord.

    ``frame``: node -> (joint id, SE3 of the node's frame in that joint frame).
    ``edges``: joint id -> its :class:`Edge`. ``tree``: (case joint name, joint id, sign).
    ``loads``: (joint id, point (3,) in the joint frame, force (3,), torque (3,), local):
    world axes, or the joint frame's when ``local`` (a body-fixed load).
    ``springs``: (name, (jid, p), (jid, p), k, c, l0), points in joint frames, jid 0 ground.
    ``one_axis``: every rotating joint turns about one fixed world direction (planar
    cases, parallel revolutes), so the angular Jacobians are constant. ``particles``: body
    -> (its point (3,), its rotation at t = 0 (3, 3)).
    """

    lifted: Lifted
    model: object
    frame: dict
    edges: dict
    tree: list
    loads: list
    springs: list
    q0: np.ndarray
    v0: np.ndarray
    one_axis: bool
    particles: dict
    loop_joints: list = field(default_factory=list)  # case joints that close loops
    rods: list = field(default_factory=list)  # (rod, node, tip (3,) world, body, point)
    notes: list[str] = field(default_factory=list)


def refuse_unmodelled(case) -> None:
    """Unsupported for what the model cannot represent, with the reason."""
    if case.drivers:
        names = ", ".join(f"{d.name} ({d.type} of {d.body})" for d in case.drivers)
        raise Unsupported(f"driver(s) {names}: prescribed motions are not modelled (Pinocchio's "
                          "constraintDynamics has contact constraints only, no rheonomic "
                          "constraint on a joint coordinate)")
    for f in case.forces:
        if f.type not in ("torque", "force"):
            raise Unsupported(f"force type {f.type!r}")
        if f.type == "torque" and case.body(f.body).kind == "particle":
            raise Unsupported(f"torque on particle {f.body!r}: a particle has no rotation")


def tree_of(case):
    """Spanning tree, loop-closing joints and the note when a prismatic loop was moved."""
    tree, loops, recut = point_loop_tree(case, "a rigid point constraint cannot slide")
    notes = []
    if recut:
        notes.append("loop-closing prismatic joint moved into the tree (prismatic joints first); "
                     f"loops cut at {', '.join(j.name for j in loops)} instead")
    return tree, loops, notes


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a)


def _revolute(pin, axis: np.ndarray):
    """Joint model turning about the world axis (3,), and the axis its q counts about."""
    a = _unit(axis)
    for k, jm in enumerate((pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ)):
        if abs(abs(a[k]) - 1.0) < 1e-14:
            return jm(), np.eye(3)[k]  # q counts about +e_k whatever the case's sign
    return pin.JointModelRevoluteUnaligned(a), a


def _prismatic(pin, axis: np.ndarray):
    """Joint model sliding along the world axis (3,), and the axis its q counts along."""
    a = _unit(axis)
    for k, jm in enumerate((pin.JointModelPX, pin.JointModelPY, pin.JointModelPZ)):
        if abs(abs(a[k]) - 1.0) < 1e-14:
            return jm(), np.eye(3)[k]
    return pin.JointModelPrismaticUnaligned(a), a


@dataclass(frozen=True)
class _Relative:
    """A tree joint at t = 0, world axes: parent point rP (3,), child point rC (3,) m, the
    child's angular velocity relative to the parent wrel (3,) rad/s, the rate of the child
    point's offset along a sliding axis sdot (3,) m/s (to project), the joint axes (3,) in
    world (None when absent) and the case joint's orientation sign."""

    rP: np.ndarray
    rC: np.ndarray
    wrel: np.ndarray
    sdot: np.ndarray
    axis: np.ndarray | None
    axis2: np.ndarray | None
    sign: int


def _relative(lifted: Lifted, j, parent: str, child: str) -> _Relative:
    sign = tree_orientation(j, parent)
    pp, pc = j.points[::sign]
    fp, fc = lifted.frames[parent], lifted.frames[child]
    rP, rC = lifted.world_point(parent, pp), lifted.world_point(child, pc)
    # the relative point velocity less the parent's rotation carrying the offset rC - rP
    sdot = lifted.world_velocity(child, pc) - lifted.world_velocity(parent, pp) \
        - cross(fp.omega, rC - rP)
    a1, a2 = (None if a is None else lifted.frames[b].R @ a
              for a, b in zip((j.axis, j.axis2), j.bodies, strict=True))
    return _Relative(rP, rC, fc.omega - fp.omega, sdot, a1, a2, sign)


# Each maker: (joint model, joint origin (3,) world, q0, v0, turns). A sliding joint sits at
# the child's point (it need not lie on the parent point's line) and q counts from t = 0;
# the others sit at the parent's point.
def _make_revolute(pin, r: _Relative):
    jm, a = _revolute(pin, r.axis)
    return jm, r.rP, [0.0], [float(a @ r.wrel)], a


def _make_prismatic(pin, r: _Relative):
    jm, a = _prismatic(pin, r.axis)
    return jm, r.rC, [0.0], [float(a @ r.sdot)], None


def _make_cylindrical(pin, r: _Relative):
    jm = pin.JointModelComposite()  # slide, then turn about the same axis
    jp, a = _prismatic(pin, r.axis)
    jr, b = _revolute(pin, r.axis)
    jm.addJoint(jp)
    jm.addJoint(jr)
    return jm, r.rC, [0.0, 0.0], [float(a @ r.sdot), float(b @ r.wrel)], b


def _make_spherical(pin, r: _Relative):
    return pin.JointModelSpherical(), r.rP, [0.0, 0.0, 0.0, 1.0], list(r.wrel), ANY


def _make_universal(pin, r: _Relative):
    u1, u2 = (_unit(r.axis), _unit(r.axis2))[::r.sign]  # first axis on the parent
    rates = np.linalg.lstsq(np.c_[u1, u2], r.wrel, rcond=None)[0]
    return pin.JointModelUniversal(u1, u2), r.rP, [0.0, 0.0], list(rates), ANY


_MAKERS = {"revolute": _make_revolute, "prismatic": _make_prismatic,
           "cylindrical": _make_cylindrical, "spherical": _make_spherical,
           "universal": _make_universal}


def _joint_edge(pin, lifted: Lifted, j, parent: str, child: str) -> Edge:
    """The Pinocchio joint of a case tree joint, from both bodies' frames at t = 0."""
    if j.type not in _MAKERS:
        raise Unsupported(f"joint {j.name!r} of type {j.type!r}")
    r = _relative(lifted, j, parent, child)
    jm, at, q0, v0, turns = _MAKERS[j.type](pin, r)
    fc, pc = lifted.frames[child], lifted.point(child, j.points[::r.sign][1])
    # the child's point sits exactly on the joint origin (the assembly residual is dropped)
    X = pin.SE3(fc.R, -fc.R @ pc)
    return Edge(parent, child, j.name, jm, at, X, q0, v0, "joint", turns, r.sign)


def _free_edges(pin, lifted: Lifted, name: str) -> tuple[list[Edge], str]:
    """A body no joint reaches: in the plane of a planar case ``JointModelPlanar`` (x, y,
    angle); otherwise ``JointModelTranslation`` + ``JointModelSphericalZYX`` (six scalar dofs,
    a vector state for RK4 and Radau; ZYX angles are singular at 90 deg pitch). Placed at the
    body's frame origin, so the joint rates are the frame's own."""
    f = lifted.frames[name]
    X = pin.SE3(f.R, np.zeros(3))
    if lifted.plane is not None:
        return [Edge(GROUND, name, name, pin.JointModelPlanar(), f.origin, X,
                     [0.0, 0.0, 1.0, 0.0], [f.velocity[0], f.velocity[1], f.omega[2]], "free",
                     lifted.plane)], \
            f"body {name} joined by no joint: floating in the plane on JointModelPlanar (3 dof)"
    carrier = f"{name} translation"
    # ZYX rates at zero angles are (w_z, w_y, w_x)
    return [Edge(GROUND, carrier, carrier, pin.JointModelTranslation(), f.origin,
                 pin.SE3.Identity(), [0.0] * 3, list(f.velocity), "carrier"),
            Edge(carrier, name, name, pin.JointModelSphericalZYX(), f.origin, X, [0.0] * 3,
                 list(f.omega[::-1]), "free", ANY)], \
        (f"body {name} joined by no joint: floating on JointModelTranslation + "
         "JointModelSphericalZYX (6 dof, ZYX angles: singular at 90 deg pitch)")


def _perp(d: np.ndarray) -> np.ndarray:
    """A unit vector normal to the unit vector d (the world axis least aligned with it)."""
    a = np.eye(3)[int(np.argmin(np.abs(d)))]
    return _unit(a - (a @ d) * d)


def _rod_edge(pin, lifted: Lifted, rod, depth: dict) -> tuple[Edge, tuple]:
    """A massless rod as a light body rooted at the end nearer the ground: a revolute about
    the plane's normal in a planar case, else a universal joint whose two axes are normal to
    the rod (it cannot spin about itself). Returns the edge and (rod, node, tip (3,) world at
    t = 0, tip body, tip point)."""
    ends = list(rod.ends)
    for b, _ in ends:
        if b not in depth:
            raise Unsupported(f"rod {rod.name!r}: end body {b!r} is not modelled")
    if depth[ends[1][0]] < depth[ends[0][0]]:
        ends.reverse()
    (ba, pa), (bb, pb) = ends
    rP, rQ = lifted.world_point(ba, pa), lifted.world_point(bb, pb)
    L = float(np.linalg.norm(rQ - rP))
    d = (rQ - rP) / L
    fa = lifted.frames[ba]
    wrel = cross(d, lifted.world_velocity(bb, pb) - lifted.world_velocity(ba, pa)) / L - fa.omega
    node = f"rod {rod.name}"
    if lifted.plane is not None:
        jm, a = _revolute(pin, lifted.plane)
        q0, v0, turns = [0.0], [float(a @ wrel)], a
    else:
        u1 = _perp(d)
        u2 = cross(d, u1)
        jm, q0, turns = pin.JointModelUniversal(u1, u2), [0.0, 0.0], ANY
        v0 = list(np.linalg.lstsq(np.c_[u1, u2], wrel, rcond=None)[0])
    edge = Edge(ba, node, node, jm, rP, pin.SE3.Identity(), q0, v0, "rod", turns)
    return edge, (rod.name, node, rQ, bb, pb)


def _rod_inertia(pin, mass: float, tip: np.ndarray):
    """Uniform slender rod from the joint origin to ``tip`` (3,) (world-aligned frame), no
    axial moment."""
    L = np.linalg.norm(tip)
    d = tip / L
    return pin.Inertia(mass, tip / 2, mass * L**2 / 12 * (np.eye(3) - np.outer(d, d)))


def _body_inertia(pin, lifted: Lifted, body, s: dict) -> tuple[object, bool]:
    """Spatial inertia about the body frame, and whether its nonzero 3x3 is singular (a
    slender rod in 3-D: zero about its own axis). A particle gets ``particle_inertia`` kg
    m^2 per kg (a rotation nothing torques)."""
    com = body.com
    if body.kind == "particle":
        return pin.Inertia(body.mass, com, s["particle_inertia"] * body.mass * np.eye(3)), False
    I3 = body.inertia
    tr = np.trace(I3)
    return pin.Inertia(body.mass, com, I3), bool(tr > 0 and np.linalg.eigvalsh(I3)[0] <= 1e-12 * tr)


def _edges(pin, lifted: Lifted, tree, notes: list) -> tuple[dict, dict, list]:
    """Edges by parent node (tree joints, floating bodies, light rods, in that order), the
    depth of every node, and the rod closures."""
    children: dict[str, list[Edge]] = {}
    depth = {GROUND: 0}

    def add(e: Edge):
        children.setdefault(e.parent, []).append(e)
        depth[e.child] = depth[e.parent] + 1

    for j, parent, child in tree_parents(tree):
        add(_joint_edge(pin, lifted, j, parent, child))
    for b in lifted.case.bodies:
        if b.name not in depth:
            edges, note = _free_edges(pin, lifted, b.name)
            for e in edges:
                add(e)
            notes.append(note)
    closures = []
    for rod in lifted.case.rods:
        e, closure = _rod_edge(pin, lifted, rod, depth)
        add(e)
        closures.append(closure)
    return children, depth, closures


def build(pin, lifted: Lifted, s: dict) -> Built:
    """The Pinocchio model of a lifted case (joint loops are closed by :mod:`.loops`)."""
    case = lifted.case
    refuse_unmodelled(case)
    tree, loop_joints, notes = tree_of(case)
    children, _, closures = _edges(pin, lifted, tree, notes)
    model = pin.Model()
    model.gravity = pin.Motion(np.r_[case.gravity, 0.0, 0.0, 0.0])
    frame = {GROUND: (0, pin.SE3.Identity())}
    at = {0: np.zeros(3)}  # joint id -> world position of its frame at t = 0
    edges, q0, v0, tree_out, singular = {}, [], [], [], []
    tips = {c[1]: c[2] for c in closures}

    def add(node):  # depth-first: Pinocchio's algorithms want every subtree contiguous
        jp = frame[node][0]
        for e in children.get(node, ()):
            jid = model.addJoint(jp, e.joint, pin.SE3(np.eye(3), e.at - at[jp]), e.name)
            at[jid], edges[jid] = e.at, e
            frame[e.child] = (jid, e.X)
            if e.kind == "carrier":
                inertia = pin.Inertia.Zero()
            elif e.kind == "rod":
                inertia = _rod_inertia(pin, float(s["rod_mass"]), tips[e.child] - e.at)
            else:
                inertia, sing = _body_inertia(pin, lifted, case.body(e.child), s)
                inertia = inertia.se3Action(e.X)
                if sing:
                    singular.append(e.child)
            model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
            q0.extend(e.q0)
            v0.extend(e.v0)
            if e.kind == "joint":
                tree_out.append((e.name, jid, e.sign))
            add(e.child)

    add(GROUND)
    turns = [e.turns for e in edges.values() if e.turns is not None]
    one_axis = not any(isinstance(t, str) for t in turns) and all(
        np.linalg.norm(cross(t, turns[0])) < 1e-12 for t in turns)
    particles = {b.name: (next(iter(b.points.values())), lifted.frames[b.name].R)
                 for b in case.bodies if b.kind == "particle"}
    spinning = [n for n in particles if edges[frame[n][0]].turns is not None]
    if spinning:
        notes.append(f"particle(s) {', '.join(spinning)} on a turning joint get a rotational "
                     f"inertia of {s['particle_inertia']:g} kg m^2/kg (a free, untorqued "
                     "rotation that does not feed back)")
    if singular:
        notes.append(f"body(ies) {', '.join(singular)} keep their exact singular rotational "
                     "inertia (zero about a slender rod's axis): the joints never turn them "
                     "about it")
    loads, springs = _loads(lifted, frame), _springs(lifted, frame)
    if closures:
        joint = "revolute" if lifted.plane is not None else "universal (axes normal to the rod)"
        notes.append(f"massless rods ({', '.join(x[0] for x in closures)}) as light bodies: "
                     f"uniform slender rods of {s['rod_mass']:g} kg on a {joint} joint at one "
                     "end, CONTACT_3D at the other; axial force from the closing constraint")
    if springs:
        notes.append(f"spring-dampers ({', '.join(x[0] for x in springs)}) as external forces")
    return Built(lifted, model, frame, edges, tree_out, loads, springs, np.array(q0),
                 np.array(v0), one_axis, particles, loop_joints, closures, notes)


def _loads(lifted: Lifted, frame: dict) -> list:
    """(joint id, point in the joint frame (3,), force (3,), torque (3,), local) per applied
    load: world axes, or (local, ``frame = "body"``) the joint frame's, which turns with
    the body."""
    out = []
    zero = np.zeros(3)
    for f in lifted.case.forces:
        jid, X = frame[f.body]
        p = X.act(lifted.point(f.body, f.point)) if f.point is not None else zero
        local = f.frame == "body"
        v = X.rotation @ np.asarray(f.value, float) if local else f.value
        out.append((jid, p, v if f.type == "force" else zero,
                    v if f.type == "torque" else zero, local))
    return out


def _springs(lifted: Lifted, frame: dict) -> list:
    """(name, (jid, p), (jid, p), k, c, l0) per spring-damper, points in joint frames."""
    out = []
    for sp in lifted.case.springs:
        ends = [(frame[b][0], frame[b][1].act(lifted.point(b, p))) for b, p in sp.ends]
        out.append((sp.name, ends[0], ends[1], float(sp.stiffness), float(sp.damping),
                    float(sp.length)))
    return out
