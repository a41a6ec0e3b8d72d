"""An independent solution of a 3-D case: body coordinates, Newton-Euler, projection.

It shares nothing with natcoord's formulation but the case data (:class:`Case`): no
natural coordinates, no natcoord model, assembly, constraint or integrator code.

Why this method: it is the textbook alternative to natural coordinates (Nikravesh,
*Computer-Aided Analysis of Mechanical Systems*; Haug), it writes every joint straight from
its definition, so a future case in the same format needs no new code, and it handles
loops and redundant constraints without choosing a spanning tree or independent
coordinates (Bricard's six revolutes, parallelogram_3d's six rods).

Coordinates (per moving body, n of them): the centre of mass r (3,) and unit Euler
parameters p (4,) of the body frame (the world frame at t = 0 in a reference-frame case);
rates: the velocity v (3,) of the centre of mass and the angular velocity w (3,), world
axes. Equations of motion (Newton-Euler, world axes)::

    m a = F,   I_w alpha + w x I_w w = M,   I_w = R I R^T
    [M  G^T] [nu']   [Q     ]
    [G  0  ] [lam] = [-gamma],   G nu = d/dt Phi,   gamma = G' nu

solved by least squares (the minimum-norm multipliers where constraints are redundant:
their combinations the constraints leave undetermined are found and never compared).
Every constraint row is a component of a vector expression or a dot product of two
(points and body directions: rows, Jacobian and gamma follow from r_P = r + R s,
r_P' = v + w x (R s), r_P'' = a + alpha x R s + w x (w x R s)):

* spherical: r_P1 - r_P2 = 0 (3 rows); revolute: that and the axis a1 normal to two body-2
  directions across it (2 rows); universal: that and a1 . a2 = 0 (1 row);
* cylindrical: a1 parallel to a2 (2 rows) and r_P2 - r_P1 normal to a1 (2 rows);
  prismatic: that and no turn about the axis (1 row);
* massless rod: (|r_P2 - r_P1|^2 - L^2) / 2 = 0, its tension lam * L.

The right-hand side is compiled (numba, :mod:`.spatial_kernel`: the same equations for every
case, tables of terms and rows per case); at each call it solves the rank's best conditioned
rows (pivoted Gram-Schmidt), so a redundant loop (a04_bricard) never meets a singular set.

Integration: scipy's ``solve_ivp`` over CHUNK output intervals at a time, DOP853 at rtol
1e-12, or for a stiff case (:func:`stiff`: a spring-damper faster than STIFF_RATE) Radau
IIA (order 5) at rtol 1e-10 with the compiled finite-difference Jacobian; every output
sample is projected onto the constraints (positions by Gauss-Newton to 1e-13 m,
least-change; Euler parameters normalised; velocities by least squares, singular values
below RCOND dropped) and the integration restarts from the projected state at the chunk's
end; no Baumgarte terms. The work of applied loads and dampers is a state (exact in time).
Measured on a loaded 2-core machine, the whole case: a04_bricard (10 s) 1.4 s,
a05_flyball_governor (10 s, Radau) 63 s, parallelogram_3d_flexible (2 s, Radau) 23 s.

Supported: 3-D cases of rigid bodies and uniform rods, the five joint types, rods,
spring-dampers (stiff ones too), constant forces and torques, gravity; channels ``angle``
(two points), ``position``, ``velocity``, ``acceleration``, ``reaction`` (x, y, z),
``axial``, ``energy`` (and its balance: the dampers' work over the samples as the channel
defines it, or exact) and ``combination``. Drivers and particles raise
:class:`natcoord.errors.Unsupported`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

from ..case.mechanism import GROUND, Case
from ..errors import Unsupported
from ..estimates import estimated_error

METHOD = ("body coordinates (centre of mass, Euler parameters), Newton-Euler, joint "
          "constraints from their definitions, least-squares index-1 solve, projection at "
          "every sample, {solver}")
SETTINGS = {"method": "DOP853", "rtol": 1e-12, "atol": 1e-14}
CHECK = {"method": "DOP853", "rtol": 1e-10, "atol": 1e-12}
# stiff cases (stiff()): scipy's Radau IIA (order 5) with the compiled Jacobian
STIFF_SETTINGS = {"method": "Radau", "rtol": 1e-10, "atol": 1e-12}
STIFF_CHECK = {"method": "Radau", "rtol": 1e-8, "atol": 1e-10}
AXES = {"x": 0, "y": 1, "z": 2}
PLANES = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}
FORCE_KINDS = ("reaction", "axial", "combination")
KINDS = ("angle", "position", "velocity", "acceleration", "energy", *FORCE_KINDS)
PROJECT_TOL = 1e-13  # m: position projection's stop
# Least squares drop singular values below RCOND times the largest: a redundant row's
# direction (singular value ~1e-16 on the constraints, ~1e-13 a little off them) is never
# inverted; numpy's default (eps max(shape)) did, moving a04_bricard by 1.5 mm at a sample.
RCOND = 1e-10
STIFF_RATE = 1e3  # 1/s: a spring-damper faster than this makes a case stiff (see stiff())
IMPLICIT = ("Radau", "BDF", "LSODA")
CHUNK = 10  # output intervals integrated at once: the state is projected at their end
_I3 = np.eye(3)


def supported(case: Case) -> str:
    """'' when the case can be derived here, else the reason it cannot."""
    if case.dimension != 3:
        return "only spatial (3-D) cases"
    if case.drivers:
        return "drivers are not derived"
    if any(b.kind == "particle" for b in case.bodies):
        return "particles are not derived"
    for c in case.channels:
        if c.kind not in KINDS:
            return f"channel {c.name}: kind {c.kind} is not derived"
        if c.kind == "angle" and c.points is None:
            return f"channel {c.name}: a 3-D angle needs two points"
        if c.kind == "reaction" and c.axis not in AXES:
            return f"channel {c.name}: reaction axis {c.axis}"
        if c.kind == "driver" or c.relative_to is not None:
            return f"channel {c.name} ({c.kind}) is not derived"
    return ""


def stiff(case: Case) -> str:
    """'' unless a spring-damper makes the case stiff (a rate sqrt(k / m) or c / m above
    STIFF_RATE, m the lighter body it moves): then why it is integrated by an implicit
    method (STIFF_SETTINGS). On parallelogram_3d_flexible (17e6 N/m, 1e5 N s/m on 10 kg)
    the explicit DOP853's steps are held by stability (it had not finished the first
    0.03 s after 8 min with the Python right-hand side)."""
    for s in case.springs:
        masses = [case.body(b).mass for b, _ in s.ends if b != GROUND]
        m = min(masses)
        rate = max(np.sqrt(s.stiffness / m), s.damping / m)
        if rate > STIFF_RATE:
            return (f"spring {s.name}: rate {rate:.3g} /s (stiff): an explicit "
                    "integrator's steps are held by stability")
    return ""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two (3,) vectors (numpy's cross costs ~50x more on these)."""
    return np.array([a[1]*b[2] - a[2]*b[1], a[2]*b[0] - a[0]*b[2], a[0]*b[1] - a[1]*b[0]])


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[0]*b[0] - a[1:] @ b[1:],
                     *(a[0]*b[1:] + b[0]*a[1:] + _cross(a[1:], b[1:]))])


def _rotvec_quat(d: np.ndarray) -> np.ndarray:
    """Euler parameters of the rotation by the vector d (rad, world axes)."""
    a = float(np.linalg.norm(d))
    if a < 1e-300:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.array([np.cos(a / 2), *(np.sin(a / 2) * d / a)])


def _perpendiculars(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors normal to a and to each other."""
    a = a / np.linalg.norm(a)
    t = np.eye(3)[int(np.argmin(np.abs(a)))]
    b = _cross(a, t)
    b /= np.linalg.norm(b)
    return b, _cross(a, b)


@dataclass(frozen=True)
class _Term:
    """coef * (point or direction s of body ``body``); body n is the ground."""

    body: int
    s: np.ndarray  # body frame, relative to the centre of mass for a point (m)
    point: bool
    coef: float = 1.0


class _Kin:
    """The kinematic state of every body at one instant (ground last, at rest): r, v, w
    (n + 1, 3), R (n + 1, 3, 3), Euler parameters p (n, 4) and nu (6 n,)."""

    def __init__(self, model: SpatialModel, y: np.ndarray):
        n = model.n
        self.r, self.R, self.v, self.w = model.kernel.kinematics(y, n)
        self.p = y[3*n:7*n].reshape(n, 4)
        self.nu = y[7*n:13*n]


class SpatialModel:
    """The case in body coordinates.

    Attributes
    ----------
    n : number of moving bodies; their order is ``case.bodies``'
    rows : constraint rows, each ("comp", E, k, c) or ("dot", E1, E2, c), E a list of _Term
    joint_rows : joint or rod name -> (row indices, first body index, second body index)
    y0 : (13 n + 2,) state at t = 0: r, p, v, w per body, the work W of applied loads and
         dampers and the dampers' part Wd (J)
    """

    def __init__(self, case: Case):
        reason = supported(case)
        if reason:
            raise Unsupported(f"spatial derivation: {reason}")
        self.case = case
        self.n = n = len(case.bodies)
        self.index = {b.name: i for i, b in enumerate(case.bodies)}
        self.index[GROUND] = n
        self.mass = np.array([b.mass for b in case.bodies])
        self.inertia = [np.asarray(b.inertia, float).reshape(3, 3) for b in case.bodies]
        self.com = [np.asarray(b.com, float) for b in case.bodies] + [np.zeros(3)]
        self.gravity = np.asarray(case.gravity, float)
        from . import spatial_kernel  # numba: imported when a case is derived
        self.kernel = spatial_kernel
        self.rows: list = []
        self.joint_rows: dict[str, tuple[list[int], int, int]] = {}
        for j in case.joints:
            self._joint(j)
        for rod in case.rods:
            (b1, p1), (b2, p2) = rod.ends
            d = [self._point(b2, p2), self._point(b1, p1, -1.0)]
            self._add(rod.name, b1, b2, [("dot", d, d, rod.length**2)])
        self._tables()
        self.y0 = self._initial_state()
        self.rank = self._rank(self.y0)

    # ---- constraint rows from the joints' definitions -------------------------------------
    def _point(self, body: str, name: str, coef: float = 1.0) -> _Term:
        i = self.index[body]
        s = self.case.ground[name] if body == GROUND else self.case.body(body).points[name]
        return _Term(i, np.asarray(s, float) - self.com[i], True, coef)

    def _dir(self, body: str, s: np.ndarray) -> _Term:
        return _Term(self.index[body], np.asarray(s, float), False)

    def _add(self, name: str, b1: str, b2: str, rows: list) -> None:
        start = len(self.rows)
        self.rows.extend(rows)
        self.joint_rows[name] = (list(range(start, len(self.rows))),
                                 self.index[b1], self.index[b2])

    def _joint(self, j) -> None:
        (b1, b2), (p1, p2) = j.bodies, j.points
        gap = [self._point(b2, p2), self._point(b1, p1, -1.0)]  # r_P2 - r_P1
        coincide = [("comp", gap, k, 0.0) for k in range(3)]
        a = None if j.axis is None else np.asarray(j.axis, float) / np.linalg.norm(j.axis)
        rows = []
        if j.type in ("revolute", "cylindrical", "prismatic"):
            u, w = _perpendiculars(a)  # the frames are the world's at t = 0
            parallel = [("dot", [self._dir(b1, a)], [self._dir(b2, u)], 0.0),
                        ("dot", [self._dir(b1, a)], [self._dir(b2, w)], 0.0)]
            if j.type == "revolute":
                rows = coincide + parallel
            else:
                rows = parallel + [("dot", [self._dir(b1, u)], gap, 0.0),
                                   ("dot", [self._dir(b1, w)], gap, 0.0)]
                if j.type == "prismatic":
                    rows.append(("dot", [self._dir(b1, u)], [self._dir(b2, w)], 0.0))
        elif j.type == "spherical":
            rows = coincide
        elif j.type == "universal":
            rows = coincide + [("dot", [self._dir(b1, a)], [self._dir(b2, j.axis2)], 0.0)]
        else:
            raise Unsupported(f"spatial derivation: joint {j.name}: type {j.type}")
        self._add(j.name, b1, b2, rows)

    # ---- vector expressions: value, velocity, gamma part, Jacobian ------------------------
    def _expr(self, kin: _Kin, terms: list[_Term]):
        """Value (3,), velocity (3,), w x (w x .) part of the acceleration (3,) and the
        Jacobian (3, 6 (n + 1)) over (v, w) of every body, the ground's last."""
        val, vel, acc = np.zeros(3), np.zeros(3), np.zeros(3)
        jac = np.zeros((3, 6 * (self.n + 1)))
        for t in terms:
            d = kin.R[t.body] @ t.s
            w = kin.w[t.body]
            wd = _cross(w, d)
            val += t.coef * (kin.r[t.body] + d if t.point else d)
            vel += t.coef * (kin.v[t.body] + wd if t.point else wd)
            acc += t.coef * _cross(w, wd)
            c = 6 * t.body
            if t.point:
                jac[:, c:c + 3] += t.coef * _I3
            jac[:, c + 3:c + 6] -= t.coef * _skew(d)
        return val, vel, acc, jac

    def _tables(self) -> None:
        """The rows as arrays: every distinct term once, each expression a row of
        coefficients over the terms, so :meth:`constraints` is a few array operations."""
        terms, exprs, index = [], [], {}

        def expr(e) -> int:
            key = id(e)
            if key not in index:
                index[key] = len(exprs)
                exprs.append(e)
                for t in e:
                    tk = (t.body, t.point, tuple(t.s))
                    if tk not in terms:
                        terms.append(tk)
            return index[key]

        comp, dot = [], []
        for i, row in enumerate(self.rows):
            if row[0] == "comp":
                comp.append((i, expr(row[1]), row[2], row[3]))
            else:
                dot.append((i, expr(row[1]), expr(row[2]), row[3],
                            0.5 if row[1] is row[2] else 1.0))
        self._tb = np.array([t[0] for t in terms], int)
        self._tp = np.array([t[1] for t in terms], float)
        self._ts = np.array([t[2] for t in terms], float).reshape(-1, 3)
        self._S = np.zeros((len(exprs), len(terms)))
        for e, ts in enumerate(exprs):
            for t in ts:
                self._S[e, terms.index((t.body, t.point, tuple(t.s)))] += t.coef
        comp = np.array(comp, float).reshape(-1, 4)
        dot = np.array(dot, float).reshape(-1, 5)
        forces = self.case.forces
        fb = np.array([self.index[f.body] for f in forces], np.int64)
        # kind of load: 0 torque, 1 force; + 2 when its value is in the body's axes (the
        # world's at t = 0), turned by R at every call
        ft = np.array([float(f.type == "force") + 2.0 * (f.frame == "body") for f in forces])
        fv = np.array([np.asarray(f.value, float) for f in forces]).reshape(-1, 3)
        fs = np.array([np.asarray(self.case.body(f.body).points[f.point], float)
                       - self.com[self.index[f.body]] if f.type == "force" else np.zeros(3)
                       for f in forces]).reshape(-1, 3)
        ends = [[self._point(b, p) for b, p in s.ends] for s in self.case.springs]
        sb = np.array([[e.body for e in pair] for pair in ends], np.int64).reshape(-1, 2)
        ss = np.array([[e.s for e in pair] for pair in ends], float).reshape(-1, 2, 3)
        sk = np.array([[s.stiffness, s.damping, s.length] for s in self.case.springs],
                      float).reshape(-1, 3)
        inertia = np.array(self.inertia, float).reshape(-1, 3, 3)
        # the kernel's model tables (spatial_kernel's order)
        self._model = (self.mass, inertia, self.gravity)
        self._rows = (self._tb.astype(np.int64), self._tp, self._ts, self._S, comp, dot,
                      len(self.rows))
        self._loads = (fb, ft, fv, fs, sb, ss, sk)

    def constraints(self, kin: _Kin):
        """Phi (m,), its Jacobian G over every body's (v, w) (m, 6 (n + 1)) and gamma (m,)
        with Phi'' = G nu' + gamma."""
        return self.kernel.constraints(kin.r, kin.R, kin.v, kin.w, *self._rows)

    # ---- dynamics ------------------------------------------------------------------------
    def _springs(self, kin: _Kin):
        """Per spring: tension (N), rate of length (m/s), length (m)."""
        tension, ldot, length, _, _ = self.kernel.springs(kin.r, kin.R, kin.v, kin.w,
                                                          *self._loads[4:])
        return zip(self.case.springs, tension, ldot, length, strict=True)

    def loads(self, kin: _Kin):
        """Generalised forces Q (6 n,): force and moment about the centre of mass per body
        (gravity, applied loads, springs, gyroscopic), and the power (W) of the applied
        loads and dampers."""
        Q, power, _ = self.kernel.loads(kin.r, kin.R, kin.v, kin.w, *self._model,
                                        *self._loads)
        return Q[:self.n].ravel(), power

    def mass_matrix(self, kin: _Kin) -> np.ndarray:
        n = self.n
        M = np.zeros((6 * n, 6 * n))
        for i in range(n):
            M[6*i:6*i + 3, 6*i:6*i + 3] = self.mass[i] * np.eye(3)
            M[6*i + 3:6*i + 6, 6*i + 3:6*i + 6] = kin.R[i] @ self.inertia[i] @ kin.R[i].T
        return M

    def _rank(self, y: np.ndarray) -> int:
        """The rank of the constraint Jacobian at y (on the constraints), by SVD."""
        _, G, _ = self.constraints(_Kin(self, y))
        if not G.shape[0]:
            return 0
        s = np.linalg.svd(G[:, :6 * self.n], compute_uv=False)
        return int(np.sum(s > s[0] * 1e-10))

    def solve_acc(self, kin: _Kin):
        """nu' (6 n,), the minimum-norm multipliers of every row (m,), G (m, 6 (n+1)) and
        the power of applied loads and dampers (W): every row by least squares (at the
        output samples; :meth:`rhs` solves the independent rows only)."""
        _, G, gam = self.constraints(kin)
        Q, power = self.loads(kin)
        M = self.mass_matrix(kin)
        k, m = 6 * self.n, G.shape[0]
        A = np.zeros((k + m, k + m))
        A[:k, :k], A[:k, k:], A[k:, :k] = M, G[:, :k].T, G[:, :k]
        x, *_ = np.linalg.lstsq(A, np.concatenate([Q, -gam]), rcond=RCOND)
        return x[:k], x[k:], G, power

    def _args(self) -> tuple:
        return (self.rank, *self._model, *self._rows, *self._loads)

    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """y' (13 n + 2,) (compiled: :func:`spatial_kernel.rhs`)."""
        return self.kernel.rhs(y, *self._args())

    def jacobian(self, t: float, y: np.ndarray) -> np.ndarray:
        """d y' / d y (13 n + 2, 13 n + 2) by compiled forward differences, for the
        implicit integrators."""
        args = self._args()
        return self.kernel.jacobian(y, self.kernel.rhs(y, *args), *args)

    # ---- projection and the initial state ------------------------------------------------
    def project(self, y: np.ndarray) -> np.ndarray:
        """y moved onto Phi = 0 (least change, Gauss-Newton) and G nu = 0."""
        n, y = self.n, y.copy()
        for p in y[3*n:7*n].reshape(n, 4):
            p /= np.linalg.norm(p)
        for _ in range(50):
            kin = _Kin(self, y)
            phi, G, _ = self.constraints(kin)
            if np.max(np.abs(phi), initial=0.0) < PROJECT_TOL:
                break
            dx, *_ = np.linalg.lstsq(G[:, :6*n], -phi, rcond=RCOND)
            dx = dx.reshape(n, 2, 3)
            y[:3*n] += dx[:, 0].ravel()
            p = y[3*n:7*n].reshape(n, 4)
            for i in range(n):
                p[i] = _quat_mul(_rotvec_quat(dx[i, 1]), p[i])
                p[i] /= np.linalg.norm(p[i])
        else:
            raise Unsupported(f"spatial derivation: constraints not met: |Phi| {phi.max():.3g}")
        kin = _Kin(self, y)
        _, G, _ = self.constraints(kin)
        Gn = G[:, :6*n]
        dv, *_ = np.linalg.lstsq(Gn, -Gn @ kin.nu, rcond=RCOND)
        y[7*n:13*n] += dv
        return y

    def _initial_state(self) -> np.ndarray:
        n, case = self.n, self.case
        y = np.zeros(13 * n + 2)
        y[:3*n] = np.concatenate(self.com[:n])
        y[3*n:7*n] = np.tile([1.0, 0.0, 0.0, 0.0], n)
        y = self.project(y)
        if not case.velocity:
            return y
        kin = _Kin(self, y)
        _, G, _ = self.constraints(kin)
        rows, rhs = [G[:, :6*n]], [np.zeros(G.shape[0])]
        for name, rate in case.velocity.items():
            rows.append(self._rate_row(kin, case.channel(name))[None, :6*n])
            rhs.append([float(rate)])
        A, b = np.vstack(rows), np.concatenate(rhs)
        nu, *_ = np.linalg.lstsq(A, b, rcond=RCOND)  # rates left free: minimum norm
        if np.max(np.abs(A @ nu - b)) > 1e-9 * max(1.0, np.max(np.abs(b))):
            raise Unsupported("spatial derivation: the [initial] velocities contradict "
                              "the joints")
        y[7*n:13*n] = nu
        return y

    def _rate_row(self, kin: _Kin, ch) -> np.ndarray:
        """d(channel)/dt = row @ nu for an angle or position channel."""
        if ch.kind == "position":
            _, _, _, J = self._expr(kin, [self._point(ch.body, ch.point)])
            return J[AXES[ch.axis]]
        if ch.kind == "angle" and ch.points is not None:
            e = [self._point(ch.body, ch.points[1]), self._point(ch.body, ch.points[0], -1.0)]
            d, _, _, J = self._expr(kin, e)
            i, j = PLANES[ch.plane]
            return (d[i] * J[j] - d[j] * J[i]) / (d[i]**2 + d[j]**2)
        raise Unsupported(f"spatial derivation: initial rate of channel {ch.name} ({ch.kind})")

    # ---- integration and channels -------------------------------------------------------
    def integrate(self, times: np.ndarray, settings: dict | None = None) -> np.ndarray:
        """States (T, 13 n + 2) at ``times`` (each projected), by ``settings`` (default
        :meth:`settings`). The integrator runs over
        CHUNK output intervals at a time (its dense output gives the samples inside) and
        restarts from the projected state at the chunk's end."""
        s = {**self.settings()[0], **(settings or {})}
        out = [self.y0]
        y = self.y0
        for k in range(0, len(times) - 1, CHUNK):
            span = times[k:k + CHUNK + 1]
            implicit = {"jac": self.jacobian} if s["method"] in IMPLICIT else {}
            sol = solve_ivp(self.rhs, (span[0], span[-1]), y, method=s["method"],
                            rtol=s["rtol"], atol=s["atol"], t_eval=span[1:], **implicit)
            if not sol.success:
                raise RuntimeError(f"spatial derivation: {sol.message} at t = {span[0]:g} s")
            out.extend(self.project(x) for x in sol.y.T)
            y = out[-1]
        return np.array(out)

    def forces(self, kin: _Kin):
        """Joint reactions (force on the second body, world axes, N), rod and spring
        tensions (N) and which reaction components the constraints leave undetermined."""
        acc, lam, G, _ = self.solve_acc(kin)
        k = 6 * self.n
        if G.shape[0]:
            _, s, vt = np.linalg.svd(G[:, :k].T)
            null = vt[int(np.sum(s > s[0] * 1e-9)):].T  # ker G^T: self-equilibrating sets
        else:
            null = np.zeros((0, 0))
        react, free = {}, {}
        for name, (rows, b1, b2) in self.joint_rows.items():
            J = G[rows][:, 6 * b2:6 * b2 + 3]
            if b2 == self.n:  # the ground: the reaction on it, by action and reaction
                J = -G[rows][:, 6 * b1:6 * b1 + 3]
            react[name] = -J.T @ lam[rows]
            free[name] = -J.T @ null[rows] if null.size else np.zeros((3, 0))
        tension = {}
        for rod in self.case.rods:
            rows, _, _ = self.joint_rows[rod.name]
            tension[rod.name] = lam[rows[0]] * rod.length
            free[rod.name] = (null[rows[0]] * rod.length if null.size else np.zeros(0))
        for sp, t, _, _ in self._springs(kin):
            tension[sp.name] = t
        return acc, react, tension, free

    def energy(self, kin: _Kin) -> float:
        e = 0.0
        for i in range(self.n):
            Iw = kin.R[i] @ self.inertia[i] @ kin.R[i].T
            e += 0.5 * self.mass[i] * kin.v[i] @ kin.v[i] + 0.5 * kin.w[i] @ Iw @ kin.w[i]
            e -= self.mass[i] * kin.r[i] @ self.gravity
        for s, _, _, length in self._springs(kin):
            e += 0.5 * s.stiffness * (length - s.length) ** 2
        return e

    def settings(self) -> tuple[dict, dict]:
        """The integrator's settings for this case and for its error estimate (a 100x
        looser run): implicit Radau where :func:`stiff`, else DOP853."""
        return (STIFF_SETTINGS, STIFF_CHECK) if stiff(self.case) else (SETTINGS, CHECK)

    def balance_over_samples(self, times: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Energy minus work (T,), J, as the ``energy`` channel with ``work = true`` is
        defined for every engine (README, energy balance): the dampers' work the integral
        of their power at the samples (the not-a-knot cubic spline through it, integrated),
        the applied loads' exact. The derivation's own balance takes the dampers' work
        exactly (a state)."""
        from scipy.interpolate import CubicSpline
        n = self.n
        kins = [_Kin(self, y) for y in ys]
        energy = np.array([self.energy(k) for k in kins])
        power = np.array([-sum(s.damping * ldot**2 for s, _, ldot, _ in self._springs(k))
                          for k in kins])
        damped = (CubicSpline(times, power).antiderivative()(times) if len(times) > 1
                  else np.zeros(1))
        return energy - (ys[:, 13 * n] - ys[:, 13 * n + 1]) - damped

    def channels(self, times: np.ndarray, ys: np.ndarray, work: str = "samples"):
        """The case's channels (DataFrame: t, then each channel) and the set of force
        channels the redundant constraints leave undetermined. ``work``: an energy
        balance's damper work over the samples as the channel defines it ("samples",
        :meth:`balance_over_samples`) or exact ("exact")."""
        case = self.case
        cols: dict[str, list] = {"t": list(times)}
        cols.update({c.name: [] for c in case.channels})
        undetermined = set()
        rng = np.random.default_rng(0)
        for y in ys:
            kin = _Kin(self, y)
            acc, react, tension, free = self.forces(kin)
            nu_dot = acc.reshape(self.n, 2, 3)
            shift = {}  # each force channel moved along a random self-equilibrating set
            c = None
            for ch in case.channels:
                if ch.kind == "angle":
                    e = [self._point(ch.body, ch.points[1]),
                         self._point(ch.body, ch.points[0], -1.0)]
                    d = self._expr(kin, e)[0]
                    i, j = PLANES[ch.plane]
                    v = np.arctan2(d[j], d[i])
                elif ch.kind in ("position", "velocity", "acceleration"):
                    t = self._point(ch.body, ch.point)
                    x, xd, w2, _ = self._expr(kin, [t])
                    if ch.kind == "acceleration":
                        d = kin.R[t.body] @ t.s
                        xd = nu_dot[t.body, 0] + _cross(nu_dot[t.body, 1], d) + w2
                    v = (x if ch.kind == "position" else xd)[AXES[ch.axis]]
                elif ch.kind == "reaction":
                    f = free[ch.joint]
                    if c is None:
                        c = rng.standard_normal(f.shape[1]) if f.shape[1] else np.zeros(0)
                    v = react[ch.joint][AXES[ch.axis]]
                    shift[ch.name] = (f @ c)[AXES[ch.axis]] if f.size else 0.0
                elif ch.kind == "axial":
                    v = tension[ch.rod]
                    f = free.get(ch.rod)
                    if f is not None and f.size:
                        if c is None:
                            c = rng.standard_normal(f.shape[0])
                        shift[ch.name] = f @ c
                elif ch.kind == "energy":
                    v = self.energy(kin) - (y[13 * self.n] if ch.work else 0.0)
                else:  # combination
                    v = sum(k * cols[name][-1] for name, k in ch.of)
                    shift[ch.name] = sum(k * shift.get(name, 0.0) for name, k in ch.of)
                cols[ch.name].append(v)
            scale = max([abs(cols[n][-1]) for n in shift] + [1.0])
            undetermined |= {n for n, s in shift.items() if abs(s) > 1e-6 * scale}
        for ch in case.channels:
            if ch.kind == "angle":
                cols[ch.name] = np.unwrap(cols[ch.name])
            if ch.kind == "energy" and ch.work and work == "samples":
                cols[ch.name] = self.balance_over_samples(times, ys)
        return pd.DataFrame({k: np.asarray(v, float) for k, v in cols.items()}), undetermined


def solve(case: Case, settings: dict | None = None):
    """The case's channels at its sample times (DataFrame) and the undetermined force
    channels (set of names)."""
    model = SpatialModel(case)
    return model.channels(case.times, model.integrate(case.times, settings))


def _damped_balances(case: Case) -> list[str]:
    """The energy-balance channels whose work includes a damper's."""
    if not any(s.damping for s in case.springs):
        return []
    return [c.name for c in case.channels if c.kind == "energy" and c.work]


def describe(settings: dict) -> str:
    return METHOD.format(solver=f"{settings['method']} rtol {settings['rtol']:g}")


def compare(case: Case, mine: pd.DataFrame, reference: pd.DataFrame,
            undetermined: set) -> dict:
    """max |reference - mine| per channel both determine, and for force channels that
    relative to the channel's largest |reference| value."""
    kinds = {c.name: c.kind for c in case.channels}
    names = [c for c in mine.columns
             if c != "t" and c in reference.columns and c not in undetermined]
    diff = {c: float(np.max(np.abs(mine[c].to_numpy() - reference[c].to_numpy(float))))
            for c in names}
    rel = {c: diff[c] / max(float(np.max(np.abs(reference[c].to_numpy(float)))), 1e-300)
           for c in names if kinds[c] in FORCE_KINDS}
    return {"max_abs_diff": diff, "max_rel_diff": rel}


def check(case: Case, reference: pd.DataFrame, undetermined=()) -> dict | None:
    """The ``independent`` field of a 3-D reference's provenance: max |reference -
    derivation| per channel both determine (``undetermined``: the reference's), relative
    for forces, the derivation's own error estimate (against its run 100x looser); an
    energy balance with dampers as every engine's is defined (their work over the samples),
    and under ``exact_work`` how far the reference's is from the exact balance; None when
    the case is not supported."""
    if supported(case):
        return None
    model = SpatialModel(case)
    settings, loose_settings = model.settings()
    ys = model.integrate(case.times, settings)
    best, free = model.channels(case.times, ys)
    loose, _ = model.channels(case.times, model.integrate(case.times, loose_settings))
    skip = set(free) | set(undetermined)
    out = {"method": describe(settings) + "; reactions from the multipliers",
           "settings": dict(settings),
           "undetermined": sorted(free)}
    out |= compare(case, best, reference, skip)
    out["estimated_error"] = {c: estimated_error(best[c], loose[c], len(case.times))
                              for c in out["max_abs_diff"]}
    out["estimated_error_method"] = ("max |derivation - its run at "
                                     f"{loose_settings['method']} "
                                     f"rtol {loose_settings['rtol']:g}|")
    balances = _damped_balances(case)
    if balances:
        exact, _ = model.channels(case.times, ys, work="exact")
        out["exact_work"] = compare(case, exact[["t", *balances]], reference,
                                    skip)["max_abs_diff"]
        out["exact_work_method"] = ("max |reference - derivation| of the energy balance "
                                    "with the dampers' work exact (integrated with the "
                                    "motion), not over the samples")
    return out
