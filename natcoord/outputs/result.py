"""What an engine run returns: neutral motion, named channels, status and costs."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from ..case.mechanism import FORCE_KINDS, GROUND, PLANES, Case


class Status(StrEnum):
    """Outcome of one case x engine run."""

    OK = "ok"
    FAILED = "failed"  # the engine ran and crashed, hung, diverged or returned NaN
    UNSUPPORTED = "unsupported"  # the engine cannot model the case; reason says what
    SKIPPED = "skipped"  # not run here (engine package missing, or not asked for)


@dataclass(frozen=True)
class Motion:
    """Raw engine output at the case's sample times, in natcoord's neutral convention.

    Attributes
    ----------
    t : (T,) sample times, s
    origin : body -> (T, d) world position of the body frame origin, m
    angle : body -> (T,) angle of the body frame x axis from world +x, rad (2-D only)
    velocity : body -> (T, d) world velocity of the body frame origin, m/s
    omega : body -> (T,) angular velocity, rad/s (2-D); (T, 3) world axes (3-D)
    joint_force : joint -> (T, d) force the joint applies to its *second* body, world
        axes, N. A joint an engine cannot report is absent; its channels become NaN.
    rotation : body -> (T, 3, 3) body-to-world rotation (3-D only)
    rod_force : rod or spring -> (T,) axial force, tension positive, N
    """

    t: np.ndarray
    origin: dict[str, np.ndarray]
    angle: dict[str, np.ndarray]
    velocity: dict[str, np.ndarray]
    omega: dict[str, np.ndarray]
    joint_force: dict[str, np.ndarray] = field(default_factory=dict)
    # optional (an engine that cannot report them leaves them empty; channels become NaN):
    # body -> (T, d) acceleration of the frame origin, m/s^2; body -> (T,) angular
    # acceleration, rad/s^2; driver -> (T,) effort of a driver (N m for an angle driver)
    acceleration: dict[str, np.ndarray] = field(default_factory=dict)
    alpha: dict[str, np.ndarray] = field(default_factory=dict)
    driver_effort: dict[str, np.ndarray] = field(default_factory=dict)
    rotation: dict[str, np.ndarray] = field(default_factory=dict)
    rod_force: dict[str, np.ndarray] = field(default_factory=dict)

    def R(self, body: str) -> np.ndarray:
        """(T, d, d) body-to-world rotation."""
        return self.rotation[body] if body in self.rotation else _rot(self.angle[body])


def _rot(angle: np.ndarray) -> np.ndarray:
    """(T,) angles -> (T, 2, 2) rotation matrices."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def point_position(case: Case, motion: Motion, body: str, point: np.ndarray) -> np.ndarray:
    """World position (T, d) of a body-frame point (d,)."""
    if body == GROUND:
        return np.broadcast_to(point, (len(motion.t), len(point)))
    return motion.origin[body] + motion.R(body) @ point


def point_velocity(case: Case, motion: Motion, body: str, point: np.ndarray) -> np.ndarray:
    """World velocity (T, d) of a body-frame point (d,): v_O + omega x (R p)."""
    if body == GROUND:
        return np.zeros((len(motion.t), len(point)))
    rp = motion.R(body) @ point
    if case.dimension == 3:
        return motion.velocity[body] + np.cross(motion.omega[body], rp)
    w = motion.omega[body][:, None]
    return motion.velocity[body] + w * np.stack([-rp[:, 1], rp[:, 0]], -1)


def point_acceleration(case: Case, motion: Motion, body: str, point: np.ndarray) -> np.ndarray:
    """World acceleration (T, d) of a body-frame point: a_O + alpha x (R p) + omega x
    (omega x R p) (2-D: - omega^2 R p); NaN where the engine reports no accelerations."""
    if body == GROUND:
        return np.zeros((len(motion.t), len(point)))
    if body not in motion.acceleration or body not in motion.alpha:
        return np.full((len(motion.t), len(point)), np.nan)
    rp = motion.R(body) @ point
    if case.dimension == 3:
        w = motion.omega[body]
        return (motion.acceleration[body] + np.cross(motion.alpha[body], rp)
                + np.cross(w, np.cross(w, rp)))
    w, a = motion.omega[body][:, None], motion.alpha[body][:, None]
    return motion.acceleration[body] + a * np.stack([-rp[:, 1], rp[:, 0]], -1) - w * w * rp


def energy(case: Case, motion: Motion) -> np.ndarray:
    """Kinetic plus gravitational potential energy (T,), J (zero potential at the origin)."""
    e = np.zeros_like(motion.t)
    for b in case.bodies:
        vg = point_velocity(case, motion, b.name, b.com)
        rg = point_position(case, motion, b.name, b.com)
        w = motion.omega[b.name]
        if case.dimension == 3:  # 1/2 w^T R I R^T w, I in body axes
            wb = np.einsum("tji,tj->ti", motion.R(b.name), w)
            rot = 0.5 * np.einsum("ti,ij,tj->t", wb, b.inertia, wb)
        else:
            rot = 0.5 * b.inertia * w**2
        e += 0.5 * b.mass * np.sum(vg**2, axis=1) + rot
        e -= b.mass * rg @ case.gravity
    for s in case.springs:  # elastic energy
        pa, pb = (point_position(case, motion, body, _point(case, body, p))
                  for body, p in s.ends)
        e += 0.5 * s.stiffness * (np.linalg.norm(pb - pa, axis=1) - s.length) ** 2
    return e


def work(case: Case, motion: Motion) -> np.ndarray:
    """Work done on the system since t = 0 (T,), J, by the loads :func:`energy` leaves out:
    applied forces and torques, the springs' dampers and the drivers' efforts. Then
    ``energy - work`` stays at its value at t = 0 (the energy balance).

    Exact from the samples where the work is a function of the position: a constant force F
    at a point P does F . (r_P(t) - r_P(0)), a constant 2-D torque tau does
    tau (angle(t) - angle(0)). A constant 3-D torque does tau . (integral of omega), from
    the rotations at the samples (:func:`_turn`: exact while the body turns about a fixed
    axis, whatever its rate; else fourth order in the output step); a body-fixed one
    (``frame = "body"``, power tau . R^T omega) the same with omega in body axes (the
    integral of R^T's own rotation). A body-fixed force's power (R F) . v_P is integrated
    over the samples, like the rest. The rest is the time
    integral of a power sampled at the output times (:func:`cumulative_integral`): a
    damper's -c (dl/dt)^2 (dl/dt from its end points' velocities); a driver's effort times
    the rate of its driven coordinate, rate + accel t (NaN where the engine reports no
    effort).
    """
    t = motion.t
    w = np.zeros_like(t)
    power = np.zeros_like(t)  # W, integrated once at the end
    for f in case.forces:
        if f.type == "force" and f.frame == "body":  # (R F) . v_P
            p = case.body(f.body).points[f.point]
            F = np.einsum("tij,j->ti", motion.R(f.body), np.asarray(f.value, float))
            power += np.sum(F * point_velocity(case, motion, f.body, p), axis=1)
        elif f.type == "force":
            r = point_position(case, motion, f.body, case.body(f.body).points[f.point])
            w += (r - r[0]) @ np.asarray(f.value, float)
        elif case.dimension == 2:
            a = np.unwrap(motion.angle[f.body])
            w += float(f.value) * (a - a[0])
        else:
            R, omega = motion.R(f.body), motion.omega[f.body]
            if f.frame == "body":  # tau . omega_body; R^T turns with -omega_body (world form)
                R, omega = np.swapaxes(R, 1, 2), -np.einsum("tji,tj->ti", R, omega)
            turn = _turn(R, omega, motion.t)
            sign = -1.0 if f.frame == "body" else 1.0
            if turn is None:  # turning too fast between samples to tell the rotation
                power += sign * omega @ np.asarray(f.value, float)
            else:
                w += sign * turn @ np.asarray(f.value, float)
    for s in case.springs:
        if s.damping:
            (ba, pa), (bb, pb) = s.ends
            d = (point_position(case, motion, bb, _point(case, bb, pb))
                 - point_position(case, motion, ba, _point(case, ba, pa)))
            v = (point_velocity(case, motion, bb, _point(case, bb, pb))
                 - point_velocity(case, motion, ba, _point(case, ba, pa)))
            ldot = np.sum(d * v, axis=1) / np.linalg.norm(d, axis=1)
            power -= s.damping * ldot**2
    for dr in case.drivers:
        effort = motion.driver_effort.get(dr.name, np.full_like(t, np.nan))
        power += effort * (dr.rate + dr.accel * t)
    if np.any(power != 0):
        w += cumulative_integral(power, t)
    return w


def _turn(R: np.ndarray, w: np.ndarray, t: np.ndarray,
          max_step: float = 1.0) -> np.ndarray | None:
    """The integral of a 3-D body's angular velocity w (T, 3) (world axes; rotations R
    (T, 3, 3) at times t (T,), s) from t[0] to every sample, (T, 3) rad. Over each sample
    interval: along the interval's rotation vector r (that of
    R(t + h) R(t)^T less the Magnus expansion's second and third terms,
    :func:`_magnus23`), r itself, which is exact when the axis stays fixed whatever the
    rate; across r, the integral of the cubic spline through omega (zero for a fixed axis).
    None when the samples are not finite or the body turns more than ``max_step`` rad over
    an interval (the rotation vector would be ambiguous near pi)."""
    if len(t) < 2:
        return np.zeros((len(t), 3))
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(w))):
        return None
    speed = np.linalg.norm(w, axis=1)
    if np.max(np.maximum(speed[1:], speed[:-1]) * np.diff(t)) > max_step:
        return None
    from scipy.interpolate import CubicSpline  # imported when used: start-up time
    from scipy.spatial.transform import Rotation

    r = Rotation.from_matrix(R[1:] @ np.swapaxes(R[:-1], 1, 2)).as_rotvec() - _magnus23(w, t)
    P = CubicSpline(t, w, axis=0).antiderivative()
    step = P(t[1:]) - P(t[:-1])
    size = np.linalg.norm(r, axis=1)
    n = np.divide(r, size[:, None], out=np.zeros_like(r), where=size[:, None] > 0)
    step += (size - np.sum(step * n, axis=1))[:, None] * n
    return np.concatenate([np.zeros((1, 3)), np.cumsum(step, 0)])


def _magnus23(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The Magnus expansion's second and third terms over each sample interval (T - 1, 3),
    omega the cubic spline through the samples (world axes, rad/s); with P(s) the integral
    of omega over the interval up to s:

    Omega2 = 1/2 int omega x P,
    Omega3 = 1/6 int (omega1 x Q1 + M1 omega1 - (m1) omega1), Q, M, m the running integrals
    of omega x P, omega P^T, P . omega (from the triple integral of [A1, [A2, A3]] +
    [A3, [A2, A1]]). Polynomial integrands: nested Gauss-Legendre (6 points outside, 4
    inside) is exact. Both vanish when omega keeps its direction."""
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(t, w, axis=0)
    anti = spline.antiderivative()
    h, t0 = np.diff(t)[:, None], t[:-1]

    def at(s):  # omega and P at local times s (K, ...) from each interval's start
        idx = (slice(None),) + (None,) * (s.ndim - 1)
        return spline(t0[idx] + s), anti(t0[idx] + s) - anti(t0)[idx]

    xo, go = np.polynomial.legendre.leggauss(6)
    xi, gi = np.polynomial.legendre.leggauss(4)
    so = 0.5 * h * (xo + 1)  # (K, 6) outer nodes
    si = 0.5 * so[:, :, None] * (xi + 1)  # (K, 6, 4) inner nodes on [0, so]
    wo, Po = at(so)  # (K, 6, 3)
    wi, Pi = at(si)  # (K, 6, 4, 3)
    half = 0.5 * so[:, :, None]  # inner weights' scale (K, 6, 1)
    Q = half * np.einsum("b,kabi->kai", gi, np.cross(wi, Pi))
    M = half[..., None] * np.einsum("b,kabi,kabj->kaij", gi, wi, Pi)
    m = half[..., 0] * np.einsum("b,kabi,kabi->ka", gi, wi, Pi)
    f2 = 0.5 * np.cross(wo, Po)
    f3 = (np.cross(wo, Q) + np.einsum("kaij,kaj->kai", M, wo) - m[..., None] * wo) / 6
    return 0.5 * h * np.einsum("a,kai->ki", go, f2 + f3)


def cumulative_integral(y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The integral of y from t[0] to every sample (T,): the not-a-knot cubic spline through
    the samples, integrated exactly (error O(dt^4) at every sample for a smooth y; a
    cumulative Simpson rule is O(dt^3) at every other sample and alternates). NaN from the
    first non-finite sample on."""
    out = np.full(len(t), np.nan)
    bad = ~np.isfinite(y)
    n = int(np.argmax(bad)) if bad.any() else len(t)
    if n == 1:
        out[0] = 0.0
    elif n > 1:
        from scipy.interpolate import CubicSpline  # imported when used: start-up time
        out[:n] = CubicSpline(t[:n], y[:n]).antiderivative()(t[:n])
    return out


def loop_gap(case: Case, motion: Motion, joints=()) -> np.ndarray:
    """The largest distance (T,), m, between the points the ``joints`` (every joint when
    empty) hold together, from the body poses the engine reports: a revolute, spherical or
    universal joint's two joint points; a prismatic or cylindrical joint's second point from
    the line through its first point along its axis (only the part across the axis: sliding
    along it is motion). Zero in exact physics; an engine that closes a loop softly (a
    penalty, a stabilised constraint) shows how far it lets the loop open. The joints'
    angular conditions (a hinge's axis) are not in it."""
    gap = np.zeros_like(motion.t)
    for name in joints or [j.name for j in case.joints]:
        j = case.joint(name)
        (ba, bb), (pa, pb) = j.bodies, j.points
        d = (point_position(case, motion, bb, _point(case, bb, pb))
             - point_position(case, motion, ba, _point(case, ba, pa)))
        if j.type in ("prismatic", "cylindrical"):
            u = joint_axis(case, motion, name)  # (T, d) unit, world axes
            d = d - np.sum(d * u, axis=-1, keepdims=True) * u
        gap = np.maximum(gap, np.linalg.norm(d, axis=1))
    return gap


def vector_angle(case: Case, motion: Motion, a, b) -> np.ndarray:
    """The angle (T,) in [0, pi], rad, between two body vectors, each (body, p, q): r_q - r_p
    in world axes (by atan2 of |u x v| and u . v: accurate near 0 and pi)."""
    def vec(body, p, q):
        return (point_position(case, motion, body, _point(case, body, q))
                - point_position(case, motion, body, _point(case, body, p)))

    u, v = vec(*a), vec(*b)
    cross = _cross(u, v)
    size = np.abs(cross) if cross.ndim == 1 else np.linalg.norm(cross, axis=1)
    return np.arctan2(size, np.sum(u * v, axis=1))


def angular_velocity(case: Case, motion: Motion, body: str, frame: str = "world"
                     ) -> np.ndarray:
    """Angular velocity of ``body``, rad/s: (T, 3) in world axes, or body axes with
    ``frame = "body"`` (R^T omega); (T,) about z in 2-D (both frames)."""
    w = motion.omega[body]
    if case.dimension == 2 or frame == "world":
        return w
    return np.einsum("tji,tj->ti", motion.R(body), w)


def angular_acceleration(case: Case, motion: Motion, body: str, frame: str = "world"
                         ) -> np.ndarray:
    """Angular acceleration of ``body``, rad/s^2: (T, 3) d(omega)/dt in world axes, or in
    body axes with ``frame = "body"`` (R^T alpha, which is also d/dt of the body-axes
    omega); (T,) about z in 2-D; NaN where the engine reports no accelerations."""
    a = motion.alpha.get(body)
    if a is None:
        return np.full((len(motion.t), 3) if case.dimension == 3 else len(motion.t), np.nan)
    if case.dimension == 2 or frame == "world":
        return a
    return np.einsum("tji,tj->ti", motion.R(body), a)


def momentum(case: Case, motion: Motion, body: str | None = None) -> np.ndarray:
    """Linear momentum (T, d), kg m/s, of ``body`` or of every body (None): sum m v_G."""
    out = np.zeros((len(motion.t), case.dimension))
    for b in case.bodies if body is None else [case.body(body)]:
        out += b.mass * point_velocity(case, motion, b.name, b.com)
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b row by row: (T, 3), or its z component (T,) for 2-D vectors."""
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] if a.shape[1] == 2 else np.cross(a, b)


def angular_momentum(case: Case, motion: Motion, body: str | None = None,
                     about=()) -> np.ndarray:
    """Angular momentum, kg m^2/s, of ``body`` or of every body (None) about a point: the
    world point ``about`` (m, default the origin; a fixed point) or ``"com"``, the centre
    of mass of what is measured (moving). Sum of m (r_G - P) x v_G + R I R^T omega: (T, 3)
    world axes, (T,) about z in 2-D."""
    bodies = case.bodies if body is None else [case.body(body)]
    T, d = len(motion.t), case.dimension
    rg = {b.name: point_position(case, motion, b.name, b.com) for b in bodies}
    if isinstance(about, str):  # "com": sum m r_G / sum m
        mass = sum(b.mass for b in bodies)
        P = sum(b.mass * rg[b.name] for b in bodies) / mass
    else:
        P = np.broadcast_to(np.asarray(about, float) if len(about) else np.zeros(d), (T, d))
    out = np.zeros((T, 3)) if d == 3 else np.zeros(T)
    for b in bodies:
        vg = point_velocity(case, motion, b.name, b.com)
        out = out + b.mass * _cross(rg[b.name] - P, vg)
        w = motion.omega.get(b.name)
        if w is None or not np.any(b.inertia):
            continue
        if d == 3:  # R I R^T omega, I in body axes
            R = motion.R(b.name)
            out = out + np.einsum("tij,jk,tlk,tl->ti", R, b.inertia, R, w)
        else:
            out = out + b.inertia * w
    return out


def is_balance(case: Case, channel) -> bool:
    """Whether an energy channel is constant in exact physics: it includes the work of
    non-conservative loads (``work``), or the case has none (no applied force or torque,
    no damper, no driver: :func:`energy` then holds every force's potential)."""
    if channel.kind != "energy":
        return False
    return channel.work or not (case.forces or case.drivers
                                or any(s.damping for s in case.springs))


def _point(case: Case, body: str, point: str) -> np.ndarray:
    return case.ground[point] if body == GROUND else case.body(body).points[point]


def evaluate_channels(case: Case, motion: Motion) -> pd.DataFrame:
    """The case's output channels from a neutral motion: column ``t`` then one per channel."""
    import pandas as pd  # imported when used: start-up time
    cols: dict[str, np.ndarray] = {"t": motion.t}
    axis_index = {"x": 0, "y": 1, "z": 2}
    for ch in case.channels:
        if ch.kind == "angle" and ch.points is not None:
            pts = case.body(ch.body).points
            d = (point_position(case, motion, ch.body, pts[ch.points[1]])
                 - point_position(case, motion, ch.body, pts[ch.points[0]]))
            i, j = PLANES[ch.plane]
            v = np.unwrap(np.arctan2(d[:, j], d[:, i]))
        elif ch.kind == "angle":
            v = np.unwrap(motion.angle[ch.body])
        elif ch.kind == "position":
            p = case.body(ch.body).points[ch.point]
            v = point_position(case, motion, ch.body, p)[:, axis_index[ch.axis]]
        elif ch.kind == "velocity":
            p = case.body(ch.body).points[ch.point]
            v = point_velocity(case, motion, ch.body, p)[:, axis_index[ch.axis]]
        elif ch.kind == "acceleration":
            p = case.body(ch.body).points[ch.point]
            v = point_acceleration(case, motion, ch.body, p)[:, axis_index[ch.axis]]
        elif ch.kind == "driver":
            v = motion.driver_effort.get(ch.driver, np.full_like(motion.t, np.nan))
        elif ch.kind == "energy":
            v = energy(case, motion) - (work(case, motion) if ch.work else 0.0)
        elif ch.kind == "axial":
            v = motion.rod_force.get(ch.rod, np.full_like(motion.t, np.nan))
        elif ch.kind == "combination":
            v = sum(c * cols[name] for name, c in ch.of)
        elif ch.kind == "vector_angle":
            v = vector_angle(case, motion, *ch.vectors)
        elif ch.kind == "loop_gap":
            v = loop_gap(case, motion, ch.joints)
        elif ch.kind in ("angular_velocity", "angular_acceleration", "angular_momentum",
                         "momentum"):
            if ch.kind == "momentum":
                v = momentum(case, motion, ch.body)
            elif ch.kind == "angular_velocity":
                v = angular_velocity(case, motion, ch.body, ch.frame)
            elif ch.kind == "angular_acceleration":
                v = angular_acceleration(case, motion, ch.body, ch.frame)
            else:
                v = angular_momentum(case, motion, ch.body, ch.about)
            v = v if v.ndim == 1 else v[:, axis_index[ch.axis]]
        else:  # reaction
            f = motion.joint_force.get(ch.joint)
            if f is None:
                v = np.full_like(motion.t, np.nan)
            elif ch.axis == "normal":
                j = case.joint(ch.joint)
                n = normal_direction(case, motion, j.name)
                v = np.sum(f * n, axis=1)
            elif ch.axis in ("along", "across"):  # 3-D: the joint's axis, turned with its
                u = joint_axis(case, motion, ch.joint)  # first body
                along = np.sum(f * u, axis=1)
                v = along if ch.axis == "along" else np.linalg.norm(
                    f - along[:, None] * u, axis=1)
            else:
                v = f[:, axis_index[ch.axis]]
        if ch.relative_to is not None:  # a joint angle: both unwrapped from t = 0
            v = v - cols[ch.relative_to]
        cols[ch.name] = np.asarray(v, dtype=float)
    return pd.DataFrame(cols)


def methods_table(case: Case, run) -> pd.DataFrame:
    """Force channels of every reaction method of a run (``run.methods``: method ->
    Motion): column ``t`` then ``<channel>@<method>``."""
    import pandas as pd  # imported when used: start-up time
    cols: dict[str, np.ndarray] = {}
    for method, motion in run.methods.items():
        table = evaluate_channels(case, motion)
        cols.setdefault("t", table["t"].to_numpy())
        for ch in case.channels:
            if ch.kind in FORCE_KINDS:
                cols[f"{ch.name}@{method}"] = table[ch.name].to_numpy()
    return pd.DataFrame(cols)


def joint_axis(case: Case, motion: Motion, joint: str) -> np.ndarray:
    """(T, d) unit world direction of a joint's ``axis`` (given in its first body's frame)."""
    j = case.joint(joint)
    u = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
    if j.bodies[0] == GROUND:
        return np.broadcast_to(u, (len(motion.t), len(u)))
    return motion.R(j.bodies[0]) @ u


def normal_direction(case: Case, motion: Motion, joint: str) -> np.ndarray:
    """(T, 2) unit normal of a prismatic joint: its axis turned +90 deg, in world axes."""
    j = case.joint(joint)
    a = j.bodies[0]
    angle = motion.angle[a] if a in motion.angle else np.zeros_like(motion.t)
    u = _rot(angle) @ j.axis
    return np.stack([-u[:, 1], u[:, 0]], -1)


@dataclass
class Result:
    """One case x engine run.

    ``table`` has column ``t`` (s) then the case's channels (SI, angles unwrapped).
    ``counters`` holds cost counters (steps, rhs evaluations, factorizations, Newton
    iterations) and constraint drift; ``notes`` lists modelling substitutions to report.
    """

    case: str
    engine: str
    engine_version: str = ""
    status: Status = Status.OK
    reason: str = ""
    table: pd.DataFrame | None = None
    build_time_s: float = float("nan")
    wall_time_s: float = float("nan")
    n_steps: int = 0
    settings: dict = field(default_factory=dict)
    counters: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    methods: pd.DataFrame | None = None  # natcoord: force channels per reaction method
    samples_s: list[float] = field(default_factory=list)  # wall time of every repeat, s

    @property
    def us_per_step(self) -> float:
        return 1e6 * self.wall_time_s / self.n_steps if self.n_steps else float("nan")

