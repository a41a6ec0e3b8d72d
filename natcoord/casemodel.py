"""A case as natural coordinates: :class:`~natcoord.mechanism.Case` -> :class:`CaseModel`,
its state at t = 0, and its outputs (body frames, joint and rod forces, reaction methods).

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

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from . import reactions
from .builder import Builder
from .drivers import ConstraintSystem
from .errors import AssemblyError
from .inertia import rod_second_moment, second_moment
from .kinematics import Prescribed, State, assemble, solve_velocity
from .mechanism import GROUND, PLANES, Case
from .model import Model
from .result import Motion, evaluate_channels

COORDINATES = ("joints", "shared")
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
                raise ValueError(f"{case.name}: joint {j.name!r} cannot be a shared point: its "
                                 "two points are apart in the file (give every point at its "
                                 "t = 0 position, or use coordinates = \"joints\")")
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

    for body in case.bodies:
        R0, o0 = frames[body.name]
        if body.kind == "uniform_rod":
            Jg = rod_second_moment(body.mass, *(ref[body.name][e] for e in body.ends))
        elif body.kind == "particle":
            Jg = np.zeros((d, d))
        else:
            Jg = (R0 @ second_moment(body.inertia) @ R0.T if d == 3 else
                  0.5 * body.inertia * np.eye(2))
        b.body(body.name, basis[body.name], mass=body.mass, com=o0 + R0 @ body.com,
               second_moment=Jg, frame=(R0, o0))
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
    for f in case.forces:
        if f.type == "torque":
            b.torque(f.body, f.value)
        else:
            b.force(f.body, ref[f.body][f.point], f.value)
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
        if name == "min_norm":
            out[name] = None
        elif name == "unit_invariant":
            out[name] = row_lengths(cm) ** -np.asarray(m.constraints.length_dim, float)
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
    """The angle or position channel ``name`` as a :class:`~natcoord.kinematics.Prescribed`
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
    fix = [prescribed(cm, name, v) for name, v in case.fix.items()]
    q, _ = assemble(m, m.q0, fix, tol=1e-13)
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


@dataclass(frozen=True)
class BodyState:
    """Assembled state of one body frame at t = 0.

    Attributes
    ----------
    origin : (d,) world position of the frame origin, m
    angle : float, rad: angle of the frame's x axis from world +x (2-D; 0 in 3-D)
    velocity : (d,) world velocity of the frame origin, m/s
    omega : float (2-D) rad/s, or (3,) world axes (3-D)
    rotation : (d, d) body-to-world rotation
    """

    origin: np.ndarray
    angle: float
    velocity: np.ndarray
    omega: float | np.ndarray
    rotation: np.ndarray

    def rotation3(self) -> np.ndarray:
        """(3, 3) body-to-world rotation (a 2-D frame turns about z)."""
        R = np.eye(3)
        R[:len(self.rotation), :len(self.rotation)] = self.rotation
        return R


@dataclass(frozen=True)
class InitialState(Mapping):
    """The case assembled at t = 0: natcoord's coordinates ``q``, ``qd`` (n,) in the model
    written with ``coordinates`` (see :func:`build`), and every body's frame state;
    ``init[body]`` is that body's :class:`BodyState`."""

    q: np.ndarray
    qd: np.ndarray
    bodies: dict[str, BodyState]
    coordinates: str = "joints"

    def __getitem__(self, body: str) -> BodyState:
        return self.bodies[body]

    def __iter__(self) -> Iterator[str]:
        return iter(self.bodies)

    def __len__(self) -> int:
        return len(self.bodies)


def initial_body_states(case: Case) -> InitialState:
    """Assemble the case once (natcoord's model, :func:`initial_state`) and return q, qd and
    every body frame's state at t = 0: what every engine starts from."""
    coordinates = case.engine("natcoord").settings.get("coordinates", "joints")
    cm = build(case, coordinates)
    s = initial_state(cm)
    fr = frames(cm, s.q[None], s.qd[None])
    return InitialState(s.q, s.qd, coordinates=coordinates, bodies={
        b: BodyState(fr.origin[b][0], float(fr.angle(b)[0]) if cm.dim == 2 else 0.0,
                     fr.velocity[b][0],
                     float(fr.omega[b][0]) if cm.dim == 2 else fr.omega[b][0],
                     fr.rotation[b][0]) for b in fr.origin})


# ---- body frames --------------------------------------------------------------------------
def _columns(body, q: np.ndarray, last: float) -> np.ndarray:
    """Difference columns (T, d, K) of a body at q (T, n) (``last`` 1 for positions, 0 for
    rates)."""
    qh = np.concatenate([q, np.full((len(q), 1), last)], 1)
    return np.einsum("kan,tn->tak", body.G, qh)


@dataclass(frozen=True)
class Frames:
    """Body frames along a trajectory, body -> array: origin (T, d) m, rotation (T, d, d)
    body-to-world, velocity (T, d) m/s, omega (T, 3) rad/s world axes (3-D) or (T,)
    (2-D), acceleration (T, d) m/s^2 and alpha like omega, rad/s^2 (when qdd is given)."""

    origin: dict
    rotation: dict
    velocity: dict
    omega: dict
    acceleration: dict
    alpha: dict

    def angle(self, body: str) -> np.ndarray:
        """(T,) unwrapped angle of a 2-D frame's x axis, rad."""
        R = self.rotation[body]
        return np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))


def _vee(W: np.ndarray, dim: int) -> np.ndarray:
    """Axial vector of the skew part of W (T, d, d): (T, 3) in 3-D, (T,) in 2-D."""
    if dim == 2:
        return 0.5 * (W[:, 1, 0] - W[:, 0, 1])
    return 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0],
                           W[:, 1, 0] - W[:, 0, 1]], 1)


def frames(cm: CaseModel, q: np.ndarray, qd: np.ndarray,
           qdd: np.ndarray | None = None) -> Frames:
    """Body frames along a trajectory q, qd (qdd) (T, n): R = D(q) D0^+ R0 with D the
    body's basis differences (completed by their normal when a 3-D basis spans a plane); a
    particle keeps its frame's orientation."""
    m, dim = cm.model, cm.dim
    qdd = np.zeros_like(q) if qdd is None else qdd
    out = Frames({}, {}, {}, {}, {}, {})
    for name, b in m.bodies.items():
        p0 = np.einsum("an,tn->ta", b.G0[:, :-1], q) + b.G0[:, -1]
        p0d, p0dd = qd @ b.G0[:, :-1].T, qdd @ b.G0[:, :-1].T
        p_body = b.R0.T @ (b.p0 - b.o0)
        T = len(q)
        if b.rank == 0:  # a particle: translation only
            R = np.broadcast_to(b.R0, (T, dim, dim)).copy()
            Rd = Rdd = np.zeros_like(R)
        else:
            D, Dd, Ddd = _columns(b, q, 1.0), _columns(b, qd, 0.0), _columns(b, qdd, 0.0)
            D0 = b.D
            if dim == 3 and np.linalg.matrix_rank(D0, 1e-9) == 2:
                D0 = np.column_stack([D0, np.cross(D0[:, 0], D0[:, 1])])
                c = np.cross(D[:, :, 0], D[:, :, 1])
                cd = np.cross(Dd[:, :, 0], D[:, :, 1]) + np.cross(D[:, :, 0], Dd[:, :, 1])
                cdd = (np.cross(Ddd[:, :, 0], D[:, :, 1]) + 2 * np.cross(Dd[:, :, 0], Dd[:, :, 1])
                       + np.cross(D[:, :, 0], Ddd[:, :, 1]))
                D, Dd, Ddd = (np.concatenate([X, x[:, :, None]], 2) for X, x in
                              ((D, c), (Dd, cd), (Ddd, cdd)))
            P = np.linalg.pinv(D0) @ b.R0
            R, Rd, Rdd = D @ P, Dd @ P, Ddd @ P  # (T, d, d)
        Rt = np.swapaxes(R, 1, 2)
        out.origin[name] = p0 - R @ p_body
        out.rotation[name] = R
        out.velocity[name] = p0d - Rd @ p_body
        out.acceleration[name] = p0dd - Rdd @ p_body
        out.omega[name] = _vee(Rd @ Rt, dim)
        out.alpha[name] = _vee(Rdd @ Rt, dim)  # skew(alpha) + skew(omega)^2, symmetric part
    return out


# ---- outputs ------------------------------------------------------------------------------
def motion(cm: CaseModel, sol, lam: np.ndarray) -> Motion:
    """Neutral motion along a Solution with multipliers ``lam`` (T, m_all) (one reaction
    method's; driver rows after the m constraint rows)."""
    m, case = cm.model, cm.case
    fr = frames(cm, sol.q, sol.qd, sol.qdd)
    forces = {j: jf.force(lam, sol.q) for j, jf in m.joints.items()}
    links = {r.name: m.axial(r.name, lam) for r in case.rods}
    links |= m.spring_tension(sol.q, sol.qd) if m.springs else {}
    for j in cm.shared_joints:
        f = _ground_reaction(cm, case.joint(j), sol, forces, links)
        if f is not None:
            forces[j] = f
    efforts = {d.name: d.effort(lam[:, m.m + k], sol.q, sol.t)
               for k, d in enumerate(m.drivers)}
    angle = {b: fr.angle(b) for b in fr.rotation} if cm.dim == 2 else {}
    return Motion(sol.t, fr.origin, angle, fr.velocity, fr.omega, forces, fr.acceleration,
                  fr.alpha, efforts, fr.rotation, links)


def _ground_reaction(cm: CaseModel, joint, sol, forces, links) -> np.ndarray | None:
    """Force of a shared-point ground joint on its second body, by Newton-Euler on the body
    it holds: m a_G - m g - applied forces - rod, spring and joint forces (T, d). None when
    the body has another shared joint (the balance would not separate them)."""
    case, m = cm.case, cm.model
    if GROUND not in joint.bodies:
        return None
    body = joint.bodies[1] if joint.bodies[0] == GROUND else joint.bodies[0]
    sign = 1.0 if joint.bodies[1] == body else -1.0
    others = [j for j in cm.shared_joints if j != joint.name and body in case.joint(j).bodies]
    if others:
        return None
    b = case.body(body)
    R0, o0 = _frame(case, body)
    G = m.bodies[body].point_map(o0 + R0 @ b.com)[:, :-1]
    F = b.mass * (sol.qdd @ G.T) - b.mass * case.gravity
    for f in case.forces:
        if f.type == "force" and f.body == body:
            F = F - f.value
    for link in (*case.rods, *case.springs):
        for k, (lb, lp) in enumerate(link.ends):
            if lb == body:
                here = sol.q @ cm.point_map(lb, lp)[:, :-1].T + cm.point_map(lb, lp)[:, -1]
                ob, op = link.ends[1 - k]
                there = sol.q @ cm.point_map(ob, op)[:, :-1].T + cm.point_map(ob, op)[:, -1]
                e = (there - here) / np.linalg.norm(there - here, axis=1)[:, None]
                F = F - links[link.name][:, None] * e  # tension pulls towards the other end
    for name, f in forces.items():
        j = case.joint(name)
        if body in j.bodies:
            F = F - (f if j.bodies[1] == body else -f)
    return sign * F


def reactions_by_method(cm: CaseModel, sol) -> dict[str, np.ndarray]:
    """Multipliers (T, m_all) of every reaction method of the case."""
    return {name: reactions.along(cm.model, sol.t, sol.q, sol.qd, sol.qdd, w)
            for name, w in cm.methods.items()}


def undetermined(cm: CaseModel, sol, lam: np.ndarray, *, rtol: float = 1e-7) -> list[str]:
    """The channels that a self-equilibrating set changes: evaluated with ``lam`` and with
    ``lam + s N c`` (N = ker Phi_q^T at each sample, c a fixed random unit vector, s the
    size of lam), a channel that moves by more than ``rtol`` of its size is undetermined
    (the paper, Section 3.2). Samples where the rank drops (singular positions) are
    skipped."""
    T, rng = len(sol.t), np.random.default_rng(0)
    con = ConstraintSystem(cm.model)
    Ns = [reactions.left_null_space(con.jacobian(q, t))[0] for t, q in zip(sol.t, sol.q,
                                                                          strict=True)]
    k0 = int(np.median([N.shape[1] for N in Ns]))
    if k0 == 0:
        return []
    keep = np.array([N.shape[1] == k0 for N in Ns])
    c = rng.standard_normal(k0)
    c /= np.linalg.norm(c)
    scale = float(np.max(np.abs(lam))) or 1.0
    moved = lam.copy()
    for k in range(T):
        if keep[k]:
            moved[k] += scale * Ns[k] @ c
    a = evaluate_channels(cm.case, motion(cm, sol, lam))
    b = evaluate_channels(cm.case, motion(cm, sol, moved))
    out = []
    for ch in cm.case.channels:
        d = np.abs(a[ch.name].to_numpy() - b[ch.name].to_numpy())[keep]
        size = float(np.nanmax(np.abs(a[ch.name].to_numpy()[keep]), initial=0.0)) + scale
        if np.nanmax(d, initial=0.0) > rtol * size:
            out.append(ch.name)
    return out


def diagnostics(cm: CaseModel, q: np.ndarray) -> dict:
    """Existence / uniqueness diagnostics at q: rank of Phi_q, DOF, redundant rows, and the
    self-equilibrating sets (columns of N over the rows, named)."""
    m = cm.model
    N, rank = reactions.left_null_space(m.constraints.jacobian(q))
    sets = []
    for k in range(N.shape[1]):
        v = N[:, k] / np.max(np.abs(N[:, k]))
        sets.append({m.constraints.labels[i]: float(v[i]) for i in np.flatnonzero(
            np.abs(v) > 1e-9)})
    return {"n": m.n, "m": m.m, "rank": int(rank), "dof": int(m.n - rank),
            "redundant": int(m.m - rank), "null_space": sets,
            "determined_rows": [m.constraints.labels[i] for i in
                                np.flatnonzero(reactions.determined_rows(N))]}
