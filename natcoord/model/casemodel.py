"""A case as natural coordinates: :class:`~natcoord.case.mechanism.Case` -> :class:`CaseModel`,
and its state at t = 0 (its outputs are in :mod:`natcoord.outputs.channels`).

Every case style goes through :func:`build`: each body is placed where the case puts it at
t = 0 (``case.guess``: its frame's pose; exact in a case without ``[initial.pose]``,
approximate otherwise) and :func:`initial_state` closes the joints from there.

Two ways to write the joints (``[engines.natcoord].settings.coordinates``):

* ``"joints"`` (default): every body has its own points; a joint is a set of rows between
  two bodies (coincidence rows for revolute, spherical and universal joints, point-on-line
  rows for prismatic and cylindrical ones, plus the rows that keep axes aligned), so its
  multipliers give the force on its second body, world axes;
* ``"shared"``: the way the paper by García de Jalón & Gutiérrez-López writes its examples.
  Point-to-point joints (2-D revolute, 3-D spherical) do not exist as rows: the two bodies
  *share* the point (a ground point is a fixed point). With this, five_bar is exactly that
  paper's Eqs. (76)-(83) and parallelogram_3d its Eqs. (95)-(106). A ground joint's reaction
  then follows from Newton-Euler on its body. The shared points must coincide in the file.

Row order: the bodies' rigid rows, the points attached to bodies (linear combinations),
joints, rods; driver rows come after all of them. A body's basis is its first points that
span it (2-D: its first two; a particle: its point), plus in 3-D the joint axes and their
completion when the points span less than the body needs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..case.mechanism import GROUND, PLANES, REACTION_METHODS, Case, reaction_method
from ..errors import AssemblyError, ModelError
from ..outputs import reactions
from . import sparserank
from .builder import Builder
from .drivers import ConstraintSystem
from .inertia import rod_second_moment, second_moment
from .kinematics import Prescribed, State, assemble, solve_velocity
from .model import Model

COORDINATES = ("joints", "shared")
MAX_COORDINATES = 8192  # the model's dense arrays (M, each body's and joint's maps) grow
# as n^2: 2.6 GB at n = 8004 (a chain of 1000 four-bars); past this a case is refused
POINT_JOINTS = ("spherical",)  # joints that are a shared point (with 2-D revolute joints)


@dataclass(frozen=True)
class CaseModel:
    """A natural-coordinate model of a case, with what its channels need.

    Attributes
    ----------
    case : Case
    model : Model
    shared : bool                       joints written as shared points
    basis : body -> element names       each body's basis
    ref_points : body -> name -> (d,)   body points in the reference configuration (world
                                        axes; where the case puts them at t = 0)
    shared_joints : joints written as shared points (reaction by Newton-Euler)
    methods : method -> (m,) weights or None   reaction methods (None: plain minimum norm)
    """

    case: Case
    model: Model
    shared: bool
    basis: dict[str, list[str]]
    ref_points: dict[str, dict[str, np.ndarray]]
    shared_joints: tuple[str, ...] = ()
    methods: dict[str, np.ndarray | None] = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return self.case.dimension

    def point_map(self, body: str, point: str) -> np.ndarray:
        """(d, n + 1) map of a named body (or ground) point."""
        x = self.ref_points[body][point]
        if body == GROUND:
            C = np.zeros((self.dim, self.model.n + 1))
            C[:, -1] = x
            return C
        return self.model.bodies[body].point_map(x)


def _frame(case: Case, body: str) -> tuple[np.ndarray, np.ndarray]:
    """(R0 (d, d), o0 (d,)): where the case puts a body's frame at t = 0."""
    pose = case.guess[body]
    if case.dimension == 2:
        c, s = np.cos(pose.angle), np.sin(pose.angle)
        return np.array([[c, -s], [s, c]]), np.asarray(pose.origin, float)
    return np.eye(3), np.asarray(pose.origin, float)


def _point_classes(case: Case, shared: bool, ref) -> dict[tuple[str, str], str]:
    """Element name of every (body, point) that shares its coordinates with another through a
    point-to-point joint (``shared`` only): the ground point's name when the class holds one,
    else ``body.point`` of its first member."""
    if not shared:
        return {}
    groups: list[list[tuple[str, str]]] = []
    for j in case.joints:
        if j.type in POINT_JOINTS or (j.type == "revolute" and case.dimension == 2):
            ends = list(zip(j.bodies, j.points, strict=True))
            xa, xb = (ref[b][p] for b, p in ends)
            if np.linalg.norm(xa - xb) > 1e-9:
                raise ModelError(f"joints[{case.joints.index(j)}] ({j.name}).points",
                                 "cannot be a shared point (engines.natcoord.settings."
                                 "coordinates = \"shared\"): its two points are apart in the "
                                 "file (give every point at its t = 0 position, or use "
                                 "coordinates = \"joints\")")
            hit = [g for g in groups if any(e in g for e in ends)]
            merged = [e for g in hit for e in g] + [e for e in ends
                                                    if not any(e in g for g in hit)]
            groups = [g for g in groups if g not in hit] + [merged]
    out = {}
    for g in groups:
        ground = [p for b, p in g if b == GROUND]
        name = ground[0] if ground else f"{g[0][0]}.{g[0][1]}"
        out |= {e: name for e in g}
    return out


def _rank(vectors: list[np.ndarray]) -> int:
    return int(np.linalg.matrix_rank(np.array(vectors), tol=1e-9)) if vectors else 0


def _basis(case: Case, body, ref: dict, axes: list[np.ndarray]) -> tuple[list[str], list]:
    """Basis points (names) and added unit vectors ``(name, u)`` (world, reference) of a
    body; ``axes`` the joint axes on it (world)."""
    pts = list(ref.items())
    names, diffs = [pts[0][0]], []
    if body.kind == "particle":
        return names, []
    for name, x in pts[1:]:
        if case.dimension == 2 and len(names) == 2:
            break
        d = x - pts[0][1]
        if _rank(diffs + [d]) > len(diffs):
            names.append(name)
            diffs.append(d)
    vectors = []
    if case.dimension == 3 and _rank(diffs) < 3 and (axes or _rank(diffs) < 2):
        span = list(diffs)
        for u in axes:
            if _rank(span + [u]) > len(span):
                span.append(u / np.linalg.norm(u))
                vectors.append(span[-1])
        while len(span) < 3:  # complete with the normal of what is there
            if len(span) == 1:
                u = np.cross(span[0], np.eye(3)[int(np.argmin(np.abs(span[0])))])
            else:
                u = np.cross(span[0], span[1])
            u = u / np.linalg.norm(u)
            span.append(u)
            vectors.append(u)
    return names, [(f"{body.name}.u{k}", v) for k, v in enumerate(vectors)]


def _joint_axes(case: Case, frames: dict) -> dict[str, tuple]:
    """World axes (reference configuration) of every joint: (axis, axis2) or Nones."""
    out = {}
    for j in case.joints:
        a, b = j.bodies
        Ra = np.eye(case.dimension) if a == GROUND else frames[a][0]
        Rb = np.eye(case.dimension) if b == GROUND else frames[b][0]
        out[j.name] = (None if j.axis is None else Ra @ j.axis,
                       None if j.axis2 is None else Rb @ j.axis2)
    return out


def build(case: Case, coordinates: str = "joints") -> CaseModel:
    """The natural-coordinate model of a case."""
    if coordinates not in COORDINATES:
        raise ValueError(f"coordinates must be one of {', '.join(COORDINATES)}, got "
                         f"{coordinates!r}")
    shared = coordinates == "shared"
    d = case.dimension
    frames = {b.name: _frame(case, b.name) for b in case.bodies}
    ref = {GROUND: dict(case.ground)} | {
        b.name: {p: frames[b.name][1] + frames[b.name][0] @ x for p, x in b.points.items()}
        for b in case.bodies}
    classes = _point_classes(case, shared, ref)
    axes = _joint_axes(case, frames)
    body_axes = {b.name: [u for j in case.joints if b.name in j.bodies and j.type != "spherical"
                          for u in axes[j.name] if u is not None] for b in case.bodies}

    def element(body: str, point: str) -> str:
        return classes.get((body, point), point if body == GROUND else f"{body}.{point}")

    # elements: basis points, unit vectors, every joint / rod / spring end
    basis, used, vectors = {}, [], {}
    for body in case.bodies:
        names, vecs = _basis(case, body, ref[body.name], body_axes[body.name])
        basis[body.name] = [element(body.name, p) for p in names] + [v for v, _ in vecs]
        vectors[body.name] = vecs
        used += [(body.name, p) for p in names]
    for link in (*case.rods, *case.springs):
        used += list(link.ends)
    if shared:
        used += [(b, p) for j in case.joints for b, p in zip(j.bodies, j.points, strict=True)
                 if (b, p) in classes]
    b = Builder(dim=d, gravity=case.gravity)
    owner: dict[str, list[str]] = {}
    for body, point in used:
        name = element(body, point)
        owner.setdefault(name, [])
        if body != GROUND and body not in owner[name]:
            owner[name].append(body)
        if name in b.elements:
            continue
        if body == GROUND or any(c[0] == GROUND for c, e in classes.items() if e == name):
            b.fixed_point(name, ref[GROUND][name] if name in ref[GROUND] else ref[body][point])
            # a body point merged with a ground point: where the ground's is (loader checks)
        else:
            b.point(name, ref[body][point])
    for body in case.bodies:
        for name, u in vectors[body.name]:
            b.vector(name, u)
    if b.n > MAX_COORDINATES:  # refused before the arrays that grow as n^2
        raise ModelError("bodies", f"{len(case.bodies)} bodies make {b.n} natural coordinates "
                         f"({coordinates}), beyond natcoord's budget of {MAX_COORDINATES}: "
                         "the model's memory grows as their square (2.6 GB at 8004)")

    for i, body in enumerate(case.bodies):
        R0, o0 = frames[body.name]
        if body.kind == "uniform_rod":
            Jg = rod_second_moment(body.mass, *(ref[body.name][e] for e in body.ends))
        elif body.kind == "particle":
            Jg = np.zeros((d, d))
        else:
            Jg = (R0 @ second_moment(body.inertia) @ R0.T if d == 3 else
                  0.5 * body.inertia * np.eye(2))
        try:
            b.body(body.name, basis[body.name], mass=body.mass, com=o0 + R0 @ body.com,
                   second_moment=Jg, frame=(R0, o0))
        except ValueError:  # its mass leaves the span of its points: no frame to carry it
            pts = np.array(list(ref[body.name].values()), float)
            com = o0 + R0 @ body.com
            span = np.linalg.matrix_rank(pts[1:] - pts[0], 1e-9) if len(pts) > 1 else 0
            off = np.linalg.matrix_rank(np.vstack([pts[1:] - pts[0], com - pts[0]]),
                                        1e-9) > span
            what = "its centre of mass" if off else "its inertia (a moment about the plane)"
            raise ModelError(f"bodies[{i}] ({body.name}).points", "its points span only a "
                             f"plane and no joint gives it an axis out of that plane, but "
                             f"{what} leaves that plane: they cannot define its frame; add "
                             "a point out of the plane") from None
    for name, bodies in owner.items():
        for body in bodies:
            if name not in basis[body]:
                b.attach(name, body)

    shared_joints = []
    for j in case.joints:
        (a, c), (pa, pc) = j.bodies, j.points
        if shared and (a, pa) in classes:
            shared_joints.append(j.name)
            continue
        xa, xc = ref[a][pa], ref[c][pc]
        axis, axis2 = axes[j.name]
        if j.type in ("revolute", "spherical"):
            getattr(b, j.type)(j.name, a, c, xa, *([axis] if j.type == "revolute" else []),
                               point_b=xc)
        elif j.type == "universal":
            b.universal(j.name, a, c, xa, axis, axis2, point_b=xc)
        else:  # prismatic, cylindrical
            getattr(b, j.type)(j.name, a, c, xa, axis, point_b=xc)
    for rod in case.rods:
        b.rod(rod.name, element(*rod.ends[0]), element(*rod.ends[1]), rod.length)
    for s in case.springs:
        b.spring(s.name, b.E(element(*s.ends[0])), b.E(element(*s.ends[1])), s.stiffness,
                 s.damping, s.length)
    for i, f in enumerate(case.forces):
        try:
            if f.type == "torque":
                b.torque(f.body, f.value, f.frame)
            else:
                b.force(f.body, ref[f.body][f.point], f.value, f.frame)
        except ValueError as e:  # a body-fixed load on a body whose frame is not fixed
            raise ModelError(f"forces[{i}].frame", str(e)) from None
    for dr in case.drivers:
        law = (dr.v0, dr.rate, dr.accel)
        if dr.type == "angle":
            b.drive_angle(dr.name, dr.body, law)
        else:
            b.drive_coordinate(dr.name, dr.body, ref[dr.body][dr.point], "xyz".index(dr.axis),
                               law)
    model = b.build()
    cm = CaseModel(case, model, shared, basis, ref, tuple(shared_joints))
    return CaseModel(case, model, shared, basis, ref, tuple(shared_joints), methods(cm))


def row_lengths(cm: CaseModel) -> np.ndarray:
    """A natural length (m) per row for the unit-invariant scaling (Section 3.5): a distance
    row its distance, a point attached to a body the distance to the body's first basis
    point (the paper's k L1), every other row 1 m."""
    m = cm.model
    L = np.ones(m.m)
    for name, rows in m.rows.items():
        if name in m.rod_length:
            L[rows] = m.rod_length[name]
        elif " in " in name:
            element, body = name.split(" in ")
            p0 = m.elements[cm.basis[body][0]].x0
            lever = float(np.linalg.norm(m.elements[element].x0 - p0))
            L[rows] = lever if lever > 0 else 1.0
    for body, names in cm.basis.items():  # the body's own distance rows
        for i, a in enumerate(names):
            for c in names[i + 1:]:
                key = f"{body}: |{a}{c}|"
                if key in m.constraints.labels:
                    r = m.constraints.labels.index(key)
                    L[r] = float(np.linalg.norm(m.elements[c].x0 - m.elements[a].x0))
    return L


def methods(cm: CaseModel) -> dict[str, np.ndarray | None]:
    """Row weights of every reaction method of the case (plain minimum norm first when the
    case names none)."""
    m = cm.model
    out: dict[str, np.ndarray | None] = {}
    for name, spec in (cm.case.reactions or {"min_norm": {}}).items():
        method = reaction_method(name)  # the loader refused any other name
        if method == "min_norm":
            out[name] = None
        elif method == "unit_invariant":
            out[name] = row_lengths(cm) ** -np.asarray(m.constraints.length_dim, float)
        elif method != "weighted":
            raise ValueError(f"unknown reaction method {name!r}; expected one of "
                             f"{', '.join(REACTION_METHODS)}")
        else:
            w = np.ones(m.m)
            for key, k in spec.get("stiffness", {}).items():
                if key in m.rod_length:  # axial: lever 2 L (Eq. (94), w7, w8)
                    w[m.rows[key]] = reactions.stiffness_weight(k, 2 * m.rod_length[key])
                else:  # a body: its attached points' rows, lever = its basis length
                    names = cm.basis[key]
                    lever = float(np.linalg.norm(m.elements[names[1]].x0
                                                 - m.elements[names[0]].x0))
                    for rname, rows in m.rows.items():
                        if rname.endswith(f" in {key}"):
                            w[rows] = reactions.stiffness_weight(k, lever)
            out[name] = w
    return out


# ---- initial state ------------------------------------------------------------------------
def prescribed(cm: CaseModel, name: str, value: float) -> Prescribed:
    """The angle or position channel ``name`` as a :class:`~natcoord.model.kinematics.Prescribed`
    row at ``value``."""
    ch = cm.case.channel(name)
    if ch.kind == "position":
        return Prescribed(name, "position",
                          cm.point_map(ch.body, ch.point)["xyz".index(ch.axis)], value)
    if ch.points is not None:  # the angle of r_q - r_p in a plane
        i, j = PLANES[ch.plane]
        C = cm.point_map(ch.body, ch.points[1]) - cm.point_map(ch.body, ch.points[0])
        return Prescribed(name, "angle", C[[i, j]], value)
    body = cm.model.bodies[ch.body]
    if body.rank == 0:
        raise AssemblyError(f"channel {name!r}: a particle has no angle to set")
    d_body = body.R0.T @ body.D[:, 0]  # the body angle from its first basis difference
    return Prescribed(name, "angle", body.G[0], value, float(np.arctan2(d_body[1], d_body[0])))


def initial_positions(cm: CaseModel) -> np.ndarray:
    """q at t = 0: the bodies where the case puts them, joints closed by Newton-Raphson with
    ``initial.fix`` held (AssemblyError when they do not close)."""
    m = cm.model
    fix = [prescribed(cm, name, v) for name, v in cm.case.fix.items()]
    return assemble(m, m.q0, fix, tol=1e-13)[0]


def mobility(cm: CaseModel, q: np.ndarray) -> tuple[int, int, int, int]:
    """(n coordinates, rank of Phi_q, rank with the driver rows, number of drivers) at q:
    from a sparse certificate when every row is independent (linear in the model's size),
    else by dense SVDs."""
    con = ConstraintSystem(cm.model)
    if sparserank.certified(con, q) is not None:  # every row independent (and
        return con.n, con.m0, con.m, con.k                     # so those of Phi_q alone)
    J = con.jacobian(q)
    rank = reactions.left_null_space(J[:con.m0])[1] if con.m0 else 0
    return con.n, rank, reactions.left_null_space(J)[1] if con.m else 0, con.k


def check(case: Case) -> None:
    """Refuse (ModelError, naming the field) a case natcoord's model cannot carry: a body
    whose points cannot define its frame (:func:`build`), or a mechanism with no degree of
    freedom at its initial configuration.

    The rule, at q(0) with n coordinates: rank Phi_q = n (joints, rods) is a locked
    structure; and each driver must take a degree of freedom of its own (the rank with the
    driver rows = rank Phi_q + drivers), else the drivers over-constrain it (a four-bar with
    a driver on each crank). Redundant constraints are fine (Bricard: 6 revolutes, Grübler
    0, rank one short: mobility 1), and so is a mechanism whose drivers take every degree of
    freedom (slider_crank_driven: the driver is the motion). A case that does not assemble
    passes here: preparing it reports that."""
    cm = build(case, case.engine("natcoord").settings.get("coordinates", "joints"))
    try:
        q = initial_positions(cm)
    except AssemblyError:
        return
    n, r0, r, d = mobility(cm, q)
    if r0 >= n:
        raise ModelError("joints", f"the mechanism has no degree of freedom: {n} coordinates, "
                         f"rank Phi_q = {r0}, drivers {d}")
    if r - r0 < d:
        raise ModelError("joints", f"the mechanism has no degree of freedom for its drivers: "
                         f"{n} coordinates, rank Phi_q = {r} with the drivers ({r0} "
                         f"without: {n - r0} degree(s) of freedom), drivers {d}")


def initial_state(cm: CaseModel) -> State:
    """The case's state at t = 0: the bodies where the case puts them, joints closed by
    Newton-Raphson with ``initial.fix`` held; qd from ``initial.velocity`` and the drivers
    (at rest when neither gives a rate).

    Raises AssemblyError when the pose does not assemble, when assembly has to move a point
    further than the case allows (``case.pose_tolerance``: points given exactly must
    already close the joints; the error names the rows they violate), or when the rates do
    not fix a unique qd.
    """
    m, case = cm.model, cm.case
    con = ConstraintSystem(m)
    q = initial_positions(cm)
    moved = float(np.max(np.abs(q - m.q0), initial=0.0))
    if moved > case.pose_tolerance:
        phi = con.phi(m.q0)
        bad = np.argsort(-np.abs(phi))[:3]
        raise AssemblyError(f"case {case.name!r}: the points given at t = 0 violate "
                            + ", ".join(f"{con.labels[k]} ({phi[k]:.3g})" for k in bad
                                        if abs(phi[k]) > case.pose_tolerance)
                            + f" (assembly moves a point by {moved:.3g} m)")
    given = [prescribed(cm, name, v) for name, v in case.velocity.items()]
    try:
        qd = solve_velocity(m, q, given)
    except AssemblyError as e:
        raise AssemblyError(f"case {case.name!r}: {e}") from None
    return State(q, qd)
