"""natcoord's natural coordinates for a reference-frame case (every 3-D case, and 2-D cases
with rods or springs): :class:`~natcoord.mechanism.Case` -> :class:`CaseModel`.

Two ways to write the joints (``[engines.natcoord].settings.coordinates``):

* ``"joints"`` (default): every body has its own points; a joint is a set of rows between
  two bodies (2-D revolute or 3-D spherical: 2/3 coincidence rows; 3-D revolute: 3
  coincidence + 2 alignment rows), so its first d multipliers are the force on its second
  body, world axes;
* ``"shared"``: the way the paper writes its examples. Point-to-point joints (2-D revolute,
  3-D spherical) do not exist as rows: the two bodies *share* the point (a ground point is a
  fixed point). With this, five_bar is exactly Eqs. (76)-(83) and parallelogram_3d
  Eqs. (95)-(106). A ground joint's reaction then follows from Newton-Euler on its body.

Row order: the bodies' rigid rows, the points attached to bodies (linear combinations),
joints, rods. A body's basis is its first points that span it (2-D: its first two), plus in
3-D the revolute axes and their completion when the points span less than the body needs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import reactions
from .builder3d import Builder
from .errors import AssemblyError
from .kinematics import State
from .mechanism import GROUND, PLANES, Case
from .model3d import NaturalModel, rod_second_moment, second_moment
from .result import Motion, evaluate_channels

COORDINATES = ("joints", "shared")


@dataclass(frozen=True)
class CaseModel:
    """A natural-coordinate model of a case, with what its channels need.

    Attributes
    ----------
    case : Case
    model : NaturalModel
    shared : bool                       joints written as shared points
    basis : body -> element names       each body's basis
    ref_points : body -> name -> (d,)   body points at t = 0 (world = body frame)
    joint_rows : joint -> (d,) rows     coincidence rows of row-written joints
    shared_joints : joints written as shared points (reaction by Newton-Euler)
    methods : method -> (m,) weights or None   reaction methods (None: plain minimum norm)
    """

    case: Case
    model: NaturalModel
    shared: bool
    basis: dict[str, list[str]]
    ref_points: dict[str, dict[str, np.ndarray]]
    joint_rows: dict[str, np.ndarray] = field(default_factory=dict)
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


def _point_classes(case: Case, shared: bool) -> dict[tuple[str, str], str]:
    """Element name of every (body, point) that shares its coordinates with another through a
    point-to-point joint (``shared`` only): the ground point's name when the class holds one,
    else ``body.point`` of its first member."""
    if not shared:
        return {}
    groups: list[list[tuple[str, str]]] = []
    for j in case.joints:
        if j.type == "spherical" or (j.type == "revolute" and case.dimension == 2):
            ends = list(zip(j.bodies, j.points, strict=True))
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


def _basis(case: Case, body, needs_full: bool) -> tuple[list[str], list[tuple[str, np.ndarray]]]:
    """Basis points (names) and added unit vectors ``(name, u)`` of a body."""
    pts = list(body.points.items())
    names, diffs = [pts[0][0]], []
    for name, x in pts[1:]:
        if case.dimension == 2 and len(names) == 2:
            break
        d = x - pts[0][1]
        if _rank(diffs + [d]) > len(diffs):
            names.append(name)
            diffs.append(d)
    vectors = []
    if case.dimension == 3 and _rank(diffs) < 3 and (needs_full or _rank(diffs) < 2):
        cands = [j.axis for j in case.joints if j.type == "revolute" and body.name in j.bodies]
        span = list(diffs)
        for u in cands:
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


def build(case: Case, coordinates: str = "joints") -> CaseModel:
    """The natural-coordinate model of a reference-frame case."""
    if coordinates not in COORDINATES:
        raise ValueError(f"coordinates must be one of {', '.join(COORDINATES)}, got "
                         f"{coordinates!r}")
    if not case.reference_frame:
        raise ValueError(f"{case.name}: casemodel needs a reference-frame case")
    shared = coordinates == "shared"
    d = case.dimension
    ref = {GROUND: dict(case.ground)} | {b.name: dict(b.points) for b in case.bodies}
    classes = _point_classes(case, shared)
    revolute_bodies = {b for j in case.joints if j.type == "revolute" for b in j.bodies}

    def element(body: str, point: str) -> str:
        return classes.get((body, point), point if body == GROUND else f"{body}.{point}")

    # elements: basis points, unit vectors, every joint / rod / spring end
    basis, used = {}, []
    vectors = {}
    for body in case.bodies:
        names, vecs = _basis(case, body, body.name in revolute_bodies)
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
        if body.kind == "uniform_rod":
            a, c = body.points[body.ends[0]], body.points[body.ends[1]]
            Jg = rod_second_moment(body.mass, a, c)
        elif body.kind == "particle":
            Jg = np.zeros((d, d))
        else:
            Jg = (second_moment(body.inertia) if d == 3 else
                  0.5 * body.inertia * np.eye(2))
        b.body(body.name, basis[body.name], mass=body.mass, com=body.com, second_moment=Jg)
    for name, bodies in owner.items():
        for body in bodies:
            if name not in basis[body]:
                b.attach(name, body)

    joint_rows, shared_joints = {}, []
    for j in case.joints:
        x = ref[j.bodies[0]][j.points[0]]
        if shared and (j.bodies[0], j.points[0]) in classes:
            shared_joints.append(j.name)
        elif j.type == "revolute" and d == 3:
            joint_rows[j.name] = b.revolute(j.name, j.bodies[0], j.bodies[1], x, j.axis)[:3]
        elif j.type in ("revolute", "spherical"):
            joint_rows[j.name] = b.spherical(j.name, j.bodies[0], j.bodies[1], x)
        else:
            raise ValueError(f"{case.name}: joint {j.name!r} ({j.type}) is not available in "
                             "reference-frame cases yet")
    for rod in case.rods:
        b.rod(rod.name, element(*rod.ends[0]), element(*rod.ends[1]))
    for s in case.springs:
        b.spring(s.name, b.E(element(*s.ends[0])), b.E(element(*s.ends[1])), s.stiffness,
                 s.damping)
    for f in case.forces:
        if f.type == "torque":
            b.torque(f.body, f.value)
        else:
            b.force(f.body, ref[f.body][f.point], f.value)
    model = b.build()
    cm = CaseModel(case, model, shared, basis, ref, joint_rows, tuple(shared_joints))
    return CaseModel(case, model, shared, basis, ref, joint_rows, tuple(shared_joints),
                     methods(cm))


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
def _velocity_row(cm: CaseModel, channel, q: np.ndarray) -> np.ndarray:
    """Row a (n,) with ``a @ qd`` the rate of an angle or position channel at q."""
    qh = np.append(q, 1.0)
    if channel.kind == "position":
        return cm.point_map(channel.body, channel.point)[
            "xyz".index(channel.axis), :-1]
    if channel.points is None:
        raise ValueError(f"channel {channel.name!r}: an angle velocity needs points = [p, q]")
    i, j = PLANES[channel.plane]
    C = cm.point_map(channel.body, channel.points[1]) - cm.point_map(channel.body,
                                                                      channel.points[0])
    v = C @ qh
    return (v[i] * C[j, :-1] - v[j] * C[i, :-1]) / (v[i] ** 2 + v[j] ** 2)


def initial_state(cm: CaseModel, *, tol: float = 1e-13) -> State:
    """The case's state at t = 0: q from the given points (Newton polish), qd from
    ``initial.velocity`` (at rest when the case gives none).

    Raises AssemblyError naming the rows the given points violate by more than 1e-6, or when
    the velocities given do not fix a unique qd.
    """
    m = cm.model
    q = m.q0.copy()
    phi = m.constraints.phi(q)
    if np.max(np.abs(phi), initial=0.0) > 1e-6:
        bad = np.argsort(-np.abs(phi))[:3]
        raise AssemblyError(f"case {cm.case.name!r}: the points given at t = 0 violate "
                            + ", ".join(f"{m.constraints.labels[k]} ({phi[k]:.3g})"
                                        for k in bad if abs(phi[k]) > 1e-6))
    for _ in range(20):
        r = m.constraints.phi(q)
        if np.max(np.abs(r), initial=0.0) < tol:
            break
        q -= np.linalg.lstsq(m.constraints.jacobian(q), r, rcond=None)[0]
    Jq = m.constraints.jacobian(q)
    dof = m.n - int(np.linalg.matrix_rank(Jq, 1e-9))
    given = cm.case.velocity
    if not given:
        return State(q, np.zeros(m.n))
    rows = [_velocity_row(cm, cm.case.channel(c), q) for c in given]
    A = np.vstack([Jq, rows])
    rhs = np.concatenate([np.zeros(m.m), list(given.values())])
    qd = np.linalg.lstsq(A, rhs, rcond=None)[0]
    if np.linalg.matrix_rank(A, 1e-9) < m.n or np.max(np.abs(A @ qd - rhs)) > 1e-9:
        raise AssemblyError(f"case {cm.case.name!r}: initial.velocity sets {len(given)} "
                            f"channel(s) for {dof} degree(s) of freedom; they must fix qd "
                            "uniquely and consistently")
    return State(q, qd)


# ---- body frames --------------------------------------------------------------------------
def _columns(body, q: np.ndarray, last: float) -> np.ndarray:
    """Difference columns (T, d, K) of a body at q (T, n) (``last`` 1 for positions, 0 for
    rates)."""
    qh = np.concatenate([q, np.full((len(q), 1), last)], 1)
    D = np.einsum("kan,tn->tak", body.G, qh)
    return D


def frames(cm: CaseModel, q: np.ndarray, qd: np.ndarray):
    """Body frames along a trajectory q, qd (T, n): dicts of origin (T, d), angle (T,) (2-D)
    or rotation (T, 3, 3) (3-D), velocity (T, d) and omega (T,) or (T, 3). The frame is the
    world frame at t = 0 (reference-frame case)."""
    m = cm.model
    origin, angle, rotation, velocity, omega = {}, {}, {}, {}, {}
    for name, b in m.bodies.items():
        D, Dd = _columns(b, q, 1.0), _columns(b, qd, 0.0)
        D0 = b.D
        if cm.dim == 3 and np.linalg.matrix_rank(D0, 1e-9) == 2:
            n0 = np.cross(D0[:, 0], D0[:, 1])
            D0 = np.column_stack([D0, n0])
            n, nd = np.cross(D[:, :, 0], D[:, :, 1]), (np.cross(Dd[:, :, 0], D[:, :, 1])
                                                      + np.cross(D[:, :, 0], Dd[:, :, 1]))
            D, Dd = np.concatenate([D, n[:, :, None]], 2), np.concatenate([Dd, nd[:, :, None]], 2)
        P = np.linalg.pinv(D0)
        R, Rd = D @ P, Dd @ P  # (T, d, d)
        p0 = np.einsum("an,tn->ta", b.G0[:, :-1], q) + b.G0[:, -1]
        p0d = np.einsum("an,tn->ta", b.G0[:, :-1], qd)
        origin[name] = p0 - R @ b.p0
        velocity[name] = p0d - Rd @ b.p0
        W = Rd @ np.swapaxes(R, 1, 2)  # skew(omega)
        if cm.dim == 2:
            angle[name] = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
            omega[name] = 0.5 * (W[:, 1, 0] - W[:, 0, 1])
        else:
            rotation[name] = R
            omega[name] = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0],
                                          W[:, 1, 0] - W[:, 0, 1]], 1)
    return origin, angle, rotation, velocity, omega


# ---- outputs ------------------------------------------------------------------------------
def motion(cm: CaseModel, sol, lam: np.ndarray) -> Motion:
    """Neutral motion along a Solution with multipliers ``lam`` (T, m) (one reaction
    method's)."""
    m, case = cm.model, cm.case
    origin, angle, rotation, velocity, omega = frames(cm, sol.q, sol.qd)
    forces = {j: lam[:, rows] for j, rows in cm.joint_rows.items()}
    links = {r.name: m.axial(r.name, lam) for r in case.rods}
    links |= m.spring_tension(sol.q, sol.qd) if m.springs else {}
    for j in cm.shared_joints:
        f = _ground_reaction(cm, case.joint(j), sol, forces, links)
        if f is not None:
            forces[j] = f
    return Motion(sol.t, origin, angle, velocity, omega, forces, rotation=rotation,
                  rod_force=links)


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
    G = m.bodies[body].point_map(b.com)[:, :-1]
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
    """Multipliers (T, m) of every reaction method of the case."""
    return {name: reactions.along(cm.model, sol.t, sol.q, sol.qd, sol.qdd, w)
            for name, w in cm.methods.items()}


def undetermined(cm: CaseModel, sol, lam: np.ndarray, *, rtol: float = 1e-7) -> list[str]:
    """The channels that a self-equilibrating set changes: evaluated with ``lam`` and with
    ``lam + s N c`` (N = ker Phi_q^T at each sample, c a fixed random unit vector, s the
    size of lam), a channel that moves by more than ``rtol`` of its size is undetermined
    (the paper, Section 3.2). Samples where the rank drops (singular positions) are
    skipped."""
    T, rng = len(sol.t), np.random.default_rng(0)
    Ns = [reactions.left_null_space(cm.model.constraints.jacobian(q))[0] for q in sol.q]
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
