"""The lifted 3-D case as an OpenSim Model (Simbody underneath): bodies, tree joints, loop
constraints, rods, springs, loads and drivers, every joint frame at its joint point and
world-aligned in its joint's own sense at t = 0 (all coordinates 0 at t = 0).

OpenSim conventions used here: ``Body(name, m, com, Inertia(Ixx, Iyy, Izz, Ixy, Ixz, Iyz))``
with the inertia about the centre of mass in body axes; a joint's frames are given as a
location and body-fixed X-Y-Z Euler angles in each body; ``PinJoint`` turns about its frames'
Z, ``SliderJoint`` slides along X, ``UniversalJoint`` turns about the parent's X then the
child's Y, ``BallJoint`` and ``FreeJoint`` use quaternions (speeds: the angular velocity in
the parent frame; FreeJoint then the translation rate in the parent frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...case.mechanism import GROUND, Case, Joint
from ...errors import Unsupported
from ..planar import Frame, cross, frame_of, node_point
from ..tree import point_loop_tree, tree_orientation, tree_parents

WHY_POINT = ("Simbody's loop constraints here pin a point (PointConstraint); a sliding loop "
             "joint would need PointOnLine plus an orientation lock")


@dataclass
class Built:
    """The model and what the readout needs: ``tree`` (case joint, OpenSim joint, sign),
    ``loops`` (case joint, OpenSim constraint, first body, second body), ``rods`` (rod, its
    constraint, end nodes and points), ``springs`` (spring, ends), ``drivers`` (driver,
    coordinate, offset), ``frames`` (t = 0 frames), ``notes``."""

    model: object
    case: Case
    frames: dict[str, Frame]
    bodies: dict[str, object]
    tree: list = field(default_factory=list)
    loops: list = field(default_factory=list)
    rods: list = field(default_factory=list)
    springs: list = field(default_factory=list)
    drivers: list = field(default_factory=list)
    speeds: list = field(default_factory=list)  # (OpenSim joint, its rates) at t = 0
    planar: bool = False
    notes: list[str] = field(default_factory=list)


def vec3(osim, x) -> object:
    x = np.asarray(x, dtype=float)
    return osim.Vec3(float(x[0]), float(x[1]), float(x[2]))


def body_fixed_xyz(R: np.ndarray) -> np.ndarray:
    """Body-fixed X-Y-Z Euler angles (rad) of a rotation R = Rx(a) Ry(b) Rz(c).

    b from atan2, not asin(R[0, 2]): near b = +-90 deg (a slider along world z: its frame's
    X is z) asin loses half the digits, a 1.5e-8 rad tilt that put a05's slider 1.05e-8 m
    off its start. Near there a alone is ill-conditioned (only a and c together matter),
    so c is taken from what Rx(a) Ry(b) leaves of R: R reproduced to round-off."""
    cb = np.hypot(R[1, 2], R[2, 2])
    b = np.arctan2(R[0, 2], cb)
    a = np.arctan2(-R[1, 2], R[2, 2]) if cb > 1e-12 else np.arctan2(R[2, 1], R[1, 1])
    ca, sa, cy, sy = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    rest = np.array([[cy, sy * sa, -sy * ca], [0.0, ca, sa], [sy, -cy * sa, cy * ca]]) @ R
    return np.array([a, b, np.arctan2(rest[1, 0], rest[0, 0])])


def basis_with(first: np.ndarray, second: np.ndarray | None = None, column: int = 2):
    """A right-handed rotation (3, 3) whose ``column`` is the unit vector ``first`` and (for
    column 0) whose column 1 is ``second`` when given."""
    e = first / np.linalg.norm(first)
    if second is not None:
        y = second - (second @ e) * e
        y /= np.linalg.norm(y)
        return np.column_stack([e, y, cross(e, y)])
    helper = np.eye(3)[int(np.argmin(np.abs(e)))]
    u = cross(helper, e)
    u /= np.linalg.norm(u)
    v = cross(e, u)
    cols = [u, v, e] if column == 2 else [e, u, v]
    return np.column_stack(cols)


def _inertia(osim, b, particle_inertia: float):
    I = np.asarray(b.inertia, dtype=float)
    if b.kind == "particle":
        I = particle_inertia * b.mass * np.eye(3)
    return osim.Inertia(I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2])


def _joint_rotation(j: Joint, parent: str, frames) -> np.ndarray:
    """The joint frame's rotation in world at t = 0 (columns: its axes)."""
    first = frame_of(frames, j.bodies[0])
    axis = first.R @ j.axis if j.axis is not None else None
    if j.type == "revolute":
        return basis_with(axis, column=2)
    if j.type == "prismatic":
        return basis_with(axis, column=0)
    if j.type == "universal":
        a2 = frame_of(frames, j.bodies[1]).R @ j.axis2
        return basis_with(axis, a2) if j.bodies[0] == parent else basis_with(a2, axis)
    return np.eye(3)  # spherical


def _joint_speeds(j: Joint, J: np.ndarray, P: Frame, C: Frame, at: np.ndarray) -> list[float]:
    """Coordinate rates at q = 0 from the bodies' t = 0 rates (``at``: the joint point,
    world)."""
    w = J.T @ (C.omega - P.omega)
    v = J.T @ (C.velocity + cross(C.omega, at - C.origin)
               - P.velocity - cross(P.omega, at - P.origin))
    if j.type == "revolute":
        return [w[2]]
    if j.type == "prismatic":
        return [v[0]]
    if j.type == "universal":
        return [w[0], w[1]]
    return [w[0], w[1], w[2]]  # spherical: angular velocity in the parent's joint frame


def _add_joint(osim, b: Built, j: Joint, parent: str, child: str):
    cls = {"revolute": osim.PinJoint, "prismatic": osim.SliderJoint,
           "spherical": osim.BallJoint, "universal": osim.UniversalJoint}.get(j.type)
    if cls is None:  # before the geometry: a joint type it lacks is a refusal, not an error
        raise Unsupported(f"{j.type} joint {j.name!r}: no OpenSim joint is wired up for it")
    frames = b.frames
    P, C = frame_of(frames, parent), frame_of(frames, child)
    pi = j.bodies.index(parent) if j.bodies[0] != j.bodies[1] else 0
    pp = np.asarray(node_point(b.case, parent, j.points[pi]), float)
    pc = np.asarray(node_point(b.case, child, j.points[1 - pi]), float)
    J = _joint_rotation(j, parent, frames)
    at = C.point(pc)
    gap = at - P.point(pp)
    if j.type == "prismatic":  # slid along its axis since its parent point: frame moves there
        gap -= (gap @ J[:, 0]) * J[:, 0]
        pp = P.R.T @ (at - P.origin)
    if np.linalg.norm(gap) > 1e-9:
        raise ValueError(f"joint {j.name!r} is open at t = 0 by {np.linalg.norm(gap):.3g} m")
    oj = cls(j.name, _phys(b, parent), vec3(osim, pp), vec3(osim, body_fixed_xyz(P.R.T @ J)),
             b.bodies[child], vec3(osim, pc), vec3(osim, body_fixed_xyz(C.R.T @ J)))
    b.model.addJoint(oj)
    b.tree.append((j, oj, tree_orientation(j, parent)))
    b.speeds.append((oj, _joint_speeds(j, J, P, C, at)))


def _phys(b: Built, node: str):
    return b.model.getGround() if node == GROUND else b.bodies[node]


def _free_joint(osim, b: Built, name: str, planar: bool):
    """A body no joint reaches: PlanarJoint (2-D: stays in the plane) or FreeJoint at its
    origin, world-aligned."""
    F = b.frames[name]
    zero = vec3(osim, np.zeros(3))
    cls = osim.PlanarJoint if planar else osim.FreeJoint
    oj = cls(f"free_{name}", b.model.getGround(), vec3(osim, F.origin), zero,
             b.bodies[name], zero, vec3(osim, body_fixed_xyz(F.R.T)))
    b.model.addJoint(oj)
    rates = [F.omega[2], F.velocity[0], F.velocity[1]] if planar else [*F.omega, *F.velocity]
    b.speeds.append((oj, rates))
    b.notes.append(f"body {name!r}: {'PlanarJoint' if planar else 'FreeJoint'} to ground")


def _path_turns(b: Built, parents: dict, a: str, c: str) -> list[np.ndarray | str]:
    """The world axes (t = 0) of the tree joints between bodies a and c (a string for a
    joint that turns about more than one axis)."""
    def up(n):
        out = []
        while n != GROUND:
            out.append(n)
            n = parents[n][1]
        return out

    ua, uc = up(a), up(c)
    common = set(ua) & set(uc)
    turns = []
    for n in ua + uc:
        if n in common:
            continue
        j = parents[n][0]
        if j.type == "revolute":
            turns.append(frame_of(b.frames, j.bodies[0]).R @ j.axis)
        elif j.type != "prismatic":
            turns.append(j.type)
    return turns


def _add_loop(osim, b: Built, j: Joint, parents: dict, axis_offset: float = 0.0):
    """A PointConstraint at the loop joint's point; a 3-D revolute whose axis the tree does
    not keep aligned gets a second one ``axis_offset`` m along its axis (the two points on
    the axis line pin it: 6 rows, the axial one redundant, so Simbody's least-squares
    multipliers split the axial force; the joint's force is their sum, determined)."""
    if j.type not in ("revolute", "spherical"):
        raise Unsupported(f"loop-closing {j.type} joint {j.name!r}: {WHY_POINT}")
    (a, c), (pa, pc) = j.bodies, j.points
    ra, rc = node_point(b.case, a, pa), node_point(b.case, c, pc)
    points = [(ra, rc)]
    if j.type == "revolute" and b.case.dimension == 3 and not b.planar:
        axis = frame_of(b.frames, a).R @ j.axis
        for t in _path_turns(b, parents, a, c):
            if isinstance(t, str) or np.linalg.norm(cross(t, axis)) > 1e-12 * np.linalg.norm(t):
                if axis_offset <= 0:
                    raise Unsupported(f"loop-closing 3-D revolute {j.name!r}: the tree does "
                                      "not keep its axis aligned, and a WeldConstraint would "
                                      "lock its rotation (setting loop_axis_offset > 0: a "
                                      "second PointConstraint along the axis)")
                e = axis / np.linalg.norm(axis) * axis_offset
                points.append((ra + frame_of(b.frames, a).R.T @ e,
                               rc + frame_of(b.frames, c).R.T @ e))
                b.notes.append(f"loop revolute {j.name!r}: a second PointConstraint "
                               f"{axis_offset:g} m along its axis")
                break
    for k, (p1, p2) in enumerate(points):
        con = osim.PointConstraint(_phys(b, a), vec3(osim, p1), _phys(b, c), vec3(osim, p2))
        con.setName(f"loop_{j.name}" + (f"_axis{k}" if k else ""))
        b.model.addConstraint(con)
        b.loops.append((j, con, a, c))


def _add_rod(osim, b: Built, rod):
    (n1, p1), (n2, p2) = rod.ends
    r1, r2 = node_point(b.case, n1, p1), node_point(b.case, n2, p2)
    length = np.linalg.norm(frame_of(b.frames, n1).point(r1) - frame_of(b.frames, n2).point(r2))
    con = osim.ConstantDistanceConstraint(_phys(b, n1), vec3(osim, r1), _phys(b, n2),
                                          vec3(osim, r2), float(length))
    con.setName(f"rod_{rod.name}")
    b.model.addConstraint(con)
    b.rods.append((rod, con, n1, r1, n2, r2))


def _add_spring(osim, b: Built, sp):
    """ExpressionBasedPointToPointForce: its expression is the tension (k (d - l0) + c
    d'); a positive value pulls the two points together."""
    (n1, p1), (n2, p2) = sp.ends
    r1, r2 = node_point(b.case, n1, p1), node_point(b.case, n2, p2)
    expr = f"{sp.stiffness!r}*(d-{sp.length!r})+{sp.damping!r}*ddot"
    f = osim.ExpressionBasedPointToPointForce(_phys(b, n1).getName(), vec3(osim, r1),
                                              _phys(b, n2).getName(), vec3(osim, r2), expr)
    f.setName(sp.name)
    b.model.addForce(f)
    b.springs.append((sp, n1, r1, n2, r2))


def _add_load(osim, b: Built, k: int, f):
    """A constant load in world axes, or (``frame = "body"``) in the body's frame (the
    OpenSim body's: its points are the case's): PrescribedForce with constant functions."""
    pf = osim.PrescribedForce(f"load{k}", b.bodies[f.body])
    pf.setForceIsInGlobalFrame(f.frame != "body")
    pf.setPointIsInGlobalFrame(False)
    v = np.asarray(f.value, dtype=float)
    const = [osim.Constant(float(x)) for x in v]
    if f.type == "torque":
        pf.setTorqueFunctions(*const)
    else:
        pf.setForceFunctions(*const)
        p = node_point(b.case, f.body, f.point)
        pf.setPointFunctions(*[osim.Constant(float(x)) for x in p])
    b.model.addForce(pf)


def _add_driver(osim, b: Built, d, parents: dict):
    """A driver as a prescribed coordinate (Simbody PrescribedMotion): an angle driver on a
    body pinned to the ground, or a coordinate driver of a body sliding on the ground along
    that world axis. Anything else is Unsupported."""
    entry = parents.get(d.body)
    j = entry[0] if entry else None
    oj = next((o for jj, o, _ in b.tree if j is not None and jj.name == j.name), None)
    F = b.frames[d.body]
    if d.type == "angle" and j is not None and j.type == "revolute" and entry[1] == GROUND:
        axis = frame_of(b.frames, j.bodies[0]).R @ j.axis
        if abs(abs(axis[2]) - 1.0) > 1e-12:
            raise Unsupported(f"driver {d.name!r}: its pin does not turn about the plane normal")
        # q = angle(t) - angle(0) about +z; a pin whose frame z is -z turns the other way
        sign = float(np.sign(axis[2]))
        offset = float(np.arctan2(F.R[1, 0], F.R[0, 0]))
    elif d.type == "coordinate" and j is not None and j.type == "prismatic" \
            and entry[1] == GROUND:
        axis = frame_of(b.frames, j.bodies[0]).R @ j.axis
        k = "xyz".index(d.axis)
        if abs(abs(axis[k]) - 1.0) > 1e-12:
            raise Unsupported(f"driver {d.name!r}: its slider is not along world {d.axis}")
        sign = float(np.sign(axis[k]))
        offset = float(F.point(node_point(b.case, d.body, d.point))[k])
    else:
        raise Unsupported(f"driver {d.name!r}: a prescribed coordinate needs the driven body "
                          "on a pin (angle) or slider (coordinate) to the ground")
    coord = oj.upd_coordinates(0)
    # q(t) = sign (v0 - offset + rate t + accel t^2 / 2)
    c0, c1, c2 = sign * (d.v0 - offset), sign * d.rate, sign * d.accel / 2.0
    fn = osim.PolynomialFunction(osim.Vector([c2, c1, c0])) if c2 else \
        osim.LinearFunction(c1, c0)
    coord.setPrescribedFunction(fn)
    coord.setDefaultIsPrescribed(True)
    b.drivers.append((d, oj, sign))


def build(osim, case3: Case, frames: dict[str, Frame], planar: bool, s: dict) -> Built:
    """The OpenSim Model of the lifted case ``case3`` with t = 0 frames ``frames``."""
    model = osim.Model()
    model.setName(case3.name)
    model.setGravity(vec3(osim, case3.gravity))
    b = Built(model, case3, frames, {}, planar=planar)
    for body in case3.bodies:
        ob = osim.Body(body.name, float(body.mass), vec3(osim, body.com),
                       _inertia(osim, body, float(s["particle_inertia"])))
        model.addBody(ob)
        b.bodies[body.name] = ob
    tree, loops, recut = point_loop_tree(case3, WHY_POINT)
    if recut:
        b.notes.append(f"prismatic joint(s) {', '.join(recut)} kept in the tree; the loop is "
                       "cut at a revolute instead")
    parents = {}
    for j, parent, child in tree_parents(tree):
        _add_joint(osim, b, j, parent, child)
        parents[child] = (j, parent)
    reached = set(parents)
    for body in case3.bodies:
        if body.name not in reached:
            _free_joint(osim, b, body.name, planar)
    for body in case3.bodies:
        if body.kind == "particle" and (body.name not in parents
                                        or parents[body.name][0].type != "prismatic"):
            b.notes.append(f"particle {body.name!r} gets rotational inertia "
                           f"{s['particle_inertia']:g} kg m^2 per kg (it can turn)")
    for j in loops:
        _add_loop(osim, b, j, parents, float(s.get("loop_axis_offset") or 0.0))
    if loops:
        b.notes.append(f"loop joint(s) {', '.join(j.name for j in loops)} closed by "
                       "PointConstraint")
    for rod in case3.rods:
        _add_rod(osim, b, rod)
    if case3.rods:
        b.notes.append("massless rods as ConstantDistanceConstraint (exact)")
    for sp in case3.springs:
        _add_spring(osim, b, sp)
    for k, f in enumerate(case3.forces):
        _add_load(osim, b, k, f)
    for d in case3.drivers:
        _add_driver(osim, b, d, parents)
    return b
