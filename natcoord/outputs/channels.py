"""What a case's natural-coordinate model gives out: every body frame along a trajectory,
the neutral :class:`~natcoord.outputs.result.Motion` (joint, rod and spring forces, driver efforts)
for each reaction method, the channels that redundant constraints leave undetermined, the
existence and uniqueness diagnostics, and the assembled state at t = 0 in body frames, which
every engine starts from (:func:`initial_body_states`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from ..case.mechanism import GROUND, Case
from ..model import sparserank
from ..model.casemodel import CaseModel, _frame, build, initial_state
from ..model.drivers import ConstraintSystem
from ..model.model import at_columns, support
from . import reactions
from .result import Motion, evaluate_channels


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


MOVE_NOTED = 1e-6  # m and rad: an assembly move past this is said (a reference-frame file's
# points close the joints within 1e-6 m)


def assembly_note(case: Case, init: InitialState) -> str:
    """What assembly changed of the case file's poses: the body it moved farthest (m, and
    deg in 2-D) from its pose in ``case.guess``, when past :data:`MOVE_NOTED`; "" else. A
    posed file's poses are approximate by design (they choose the assembly branch), so a
    move is information, not an error."""
    worst = (0.0, 0.0, "")
    for b, pose in case.guess.items():
        if b not in init.bodies:
            continue
        s = init[b]
        d = float(np.linalg.norm(np.asarray(s.origin, float) - np.asarray(pose.origin, float)))
        a = (abs((s.angle - pose.angle + np.pi) % (2 * np.pi) - np.pi)
             if case.dimension == 2 else 0.0)
        if max(d, a) > max(worst[:2]):
            worst = (d, a, b)
    d, a, b = worst
    if max(d, a) <= MOVE_NOTED:
        return ""
    did = " and ".join(([f"moved body {b!r} {d:.3g} m"] if d > MOVE_NOTED else [])
                       + ([f"turned {'it' if d > MOVE_NOTED else f'body {b!r}'} "
                           f"{np.degrees(a):.3g} deg"] if a > MOVE_NOTED else []))
    return (f"assembly {did} from its pose in the case file (the largest change; every "
            "engine starts from the assembled state)")


# ---- body frames --------------------------------------------------------------------------
def _columns(body, q: np.ndarray, last: float, cols: np.ndarray) -> np.ndarray:
    """Difference columns (T, d, K) of a body at q (T, n) (``last`` 1 for positions, 0 for
    rates); ``cols`` the columns of [q, 1] its maps use (:func:`support`)."""
    return np.einsum("kan,tn->tak", body.G[..., cols], at_columns(q, cols, last))


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
        c = support(b.G0, b.G)  # the body's own columns: O(1) per body, not O(n)
        G0 = b.G0[:, c]
        p0 = at_columns(q, c, 1.0) @ G0.T
        p0d, p0dd = at_columns(qd, c, 0.0) @ G0.T, at_columns(qdd, c, 0.0) @ G0.T
        p_body = b.R0.T @ (b.p0 - b.o0)
        T = len(q)
        if b.rank == 0:  # a particle: translation only
            R = np.broadcast_to(b.R0, (T, dim, dim)).copy()
            Rd = Rdd = np.zeros_like(R)
        else:
            D, Dd, Ddd = (_columns(b, x, last, c) for x, last in
                           ((q, 1.0), (qd, 0.0), (qdd, 0.0)))
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


def reactions_by_method(cm: CaseModel, sol) -> dict[str, reactions.ReactionsAlong]:
    """Reactions along the solution (multipliers ``.lam`` (T, m_all), null spaces, ranks) of
    every reaction method of the case; on a large model (:func:`sparserank.large`) samples
    where the run's multipliers are the unique ones (``sol.unique``: the sparse Schur path,
    every row independent) take them."""
    known = (None if getattr(sol, "unique", None) is None or not sparserank.large(cm.model.n)
             else (sol.lam, sol.unique))  # a small model's reactions stay the dense ones
    return {name: reactions.along_all(cm.model, sol.t, sol.q, sol.qd, sol.qdd, w,
                                      unique=known)
            for name, w in cm.methods.items()}


def undetermined(cm: CaseModel, sol, r: reactions.ReactionsAlong, *,
                 rtol: float = 1e-7) -> list[str]:
    """The channels that a self-equilibrating set changes: evaluated with ``lam`` and with
    ``lam + s N c`` (N = ker Phi_q^T at each sample from ``r``, one method's reactions along
    ``sol``; c a fixed random unit vector, s the size of lam), a channel that moves by more
    than ``rtol`` of its size is undetermined (the paper, Section 3.2). Samples where the
    rank drops (singular positions) are skipped."""
    rng, lam = np.random.default_rng(0), r.lam
    free = lam.shape[1] - r.rank
    k0 = int(np.median(free))
    if k0 == 0:
        return []
    keep = free == k0
    c = rng.standard_normal(k0)
    c /= np.linalg.norm(c)
    scale = float(np.max(np.abs(lam))) or 1.0
    moved = lam.copy()
    moved[keep] += scale * r.null[keep][:, :, :k0] @ c
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
    if sparserank.certified(ConstraintSystem(m), q, rows=m.m) is not None:
        N, rank = np.zeros((m.m, 0)), m.m  # certified independent rows: no SVD (sparse)
    else:
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
