"""An independent solution of a planar case: joint coordinates, Kane's method (sympy).

It shares nothing with natcoord's formulation but the case data: no natural coordinates,
no natcoord model or assembly (its own: Newton on the loop equations from the case's
approximate pose, with the ``[initial] fix`` channels at their values), no multipliers.
The bodies are put on a spanning tree of the joints grown from the ground (a joint in
the tree adds one coordinate: a revolute the angle of its second body relative to its
first, a prismatic the slide); every joint left out closes a loop and gives
configuration constraints (a revolute: its two points meet, 2 rows; a prismatic: the
point on the line, and no relative turn unless a particle). sympy's
``physics.mechanics.KanesMethod`` derives the equations of motion symbolically with the
loop constraints as configuration and velocity constraints; they are lambdified and
integrated by scipy in the independent coordinates only (coordinate partitioning: the
dependent coordinates are solved from the loop equations by Newton at every evaluation,
so the loop never drifts). The independent coordinates are chosen from the fixed
channels of ``[initial]`` first, as long as the loop equations stay solvable for the
rest.

Reactions come from Newton-Euler afterwards: with the accelerations of the solution, each
body's ``m a = F`` and ``I alpha = M`` are solved (least squares) for the joint forces;
the residual of that over-determined system checks the Kane dynamics.

Supported: 2-D cases of revolute and prismatic joints, bodies, particles, gravity, constant
forces and torques, channels ``angle``, ``position``, ``velocity``, ``energy`` and
``reaction``. Anything else raises :class:`natcoord.errors.Unsupported`. Redundant loop
constraints (e.g. five_bar's two parallel couplers) are not handled: the loop Jacobian
must have full rank at t = 0. It may lose rank at isolated positions where two branches of
the loop cross (IFToMM A02's horizontal position: parallelogram and anti-parallelogram
cross, the Jacobian has rank 2 of 4 and no choice of dependent coordinates is solvable
there): Newton starts from the last solution moved along the loop's tangent there, which
keeps the branch the motion is on, and the integrator's stages land near the crossing,
never on it (``min_sigma``: the smallest singular value of the dependent columns met).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

from ..case.mechanism import GROUND, Case
from ..errors import NatcoordError, Unsupported
from ..estimates import estimated_error

METHOD = "Kane's method in joint coordinates (sympy), coordinate partitioning, {solver}"
SETTINGS = {"method": "DOP853", "rtol": 1e-13, "atol": 1e-15}
CHECK = {"method": "DOP853", "rtol": 1e-11, "atol": 1e-13}
MAX_BODIES = 12
CHANNELS = ("angle", "position", "velocity", "energy", "reaction")


def supported(case: Case) -> str:
    """'' when the case can be derived here, else the reason it cannot."""
    if case.dimension != 2:
        return "only planar (2-D) cases"
    if len(case.bodies) > MAX_BODIES:
        return (f"{len(case.bodies)} bodies: the symbolic derivation is kept to "
                f"{MAX_BODIES} (its expressions grow with every loop)")
    for what, items in (("drivers", case.drivers), ("rods", case.rods),
                        ("springs", case.springs)):
        if items:
            return f"{what} are not derived"
    bad = [j.name for j in case.joints if j.type not in ("revolute", "prismatic")]
    if bad:
        return f"joints {bad} are neither revolute nor prismatic"
    if any(c.kind == "angle" and c.points is not None and c.plane != "xy"
           for c in case.channels):
        return "angle channels in a plane other than xy"
    return ""


@dataclass
class _Tree:
    """Spanning tree: body -> (joint, parent) in the order the bodies are reached."""

    parent: dict
    cuts: list


def _spanning_tree(case: Case) -> _Tree:
    parent, seen, queue, used = {}, {GROUND}, deque([GROUND]), set()
    while queue:
        b = queue.popleft()
        for j in case.joints:
            if j.name in used or b not in j.bodies:
                continue
            other = j.bodies[1] if j.bodies[0] == b else j.bodies[0]
            if other in seen:
                continue
            used.add(j.name)
            parent[other] = (j, b)
            seen.add(other)
            queue.append(other)
    missing = [b.name for b in case.bodies if b.name not in seen]
    if missing:
        raise Unsupported(f"bodies {missing} are not joined to the ground")
    return _Tree(parent, [j for j in case.joints if j.name not in used])


class JointModel:
    """The case in joint coordinates: symbolic equations (Kane) and numeric functions.

    Attributes
    ----------
    coords : list[str]  one label per tree coordinate (joint name), n of them
    ind, dep : index arrays of the independent and dependent coordinates
    q0, u0 : (n,) coordinates (rad, m) and rates at t = 0
    """

    def __init__(self, case: Case):
        reason = supported(case)
        if reason:
            raise Unsupported(f"independent derivation: {reason}")
        try:
            import sympy as sp
            import sympy.physics.mechanics as me
        except ImportError as e:  # an extra: the nightly does not derive references
            raise NatcoordError("the independent derivation of a planar reference needs "
                                f"sympy ({e}): pip install 'natcoord[derive]'") from e

        self.case = case
        tree = _spanning_tree(case)
        t = me.dynamicsymbols._t
        N = me.ReferenceFrame("N")
        O = me.Point("O")
        O.set_vel(N, 0)
        q, labels, start = [], [], []
        # body -> (frame, angle expression, origin vector from O)
        frames = {GROUND: (N, sp.Integer(0), 0 * N.x)}
        guess_angle = {GROUND: 0.0, **{b: p.angle for b, p in case.guess.items()}}
        guess_origin = {GROUND: np.zeros(2), **{b: np.asarray(p.origin, float)
                                                for b, p in case.guess.items()}}

        def turns(body):
            return body != GROUND and case.body(body).kind != "particle"

        def local(body, name):
            return case.ground[name] if body == GROUND else case.body(body).points[name]

        def vec(frame, xy):
            return float(xy[0]) * frame.x + float(xy[1]) * frame.y

        def guess_point(body, name):
            a = guess_angle.get(body, 0.0)
            c, s = np.cos(a), np.sin(a)
            return guess_origin[body] + np.array([[c, -s], [s, c]]) @ local(body, name)

        for child, (j, par) in tree.parent.items():
            fp, ap, rp = frames[par]
            pp, pc = (j.points[0], j.points[1]) if j.bodies[0] == par else \
                     (j.points[1], j.points[0])
            if j.type == "revolute" and turns(child):
                qi = me.dynamicsymbols(f"q{len(q)}")
                q.append(qi)
                labels.append(j.name)
                start.append(guess_angle[child] - guess_angle[par])
                ac = ap + qi
            elif turns(child):  # prismatic: no relative turn from the pose at t = 0
                ac = ap + (guess_angle[child] - guess_angle[par])
            else:  # a particle: its frame never turns
                ac = sp.Float(guess_angle.get(child, 0.0))
            fc = N.orientnew(f"F_{child}", "Axis", (ac, N.z))
            rc = rp + vec(fp, local(par, pp)) - vec(fc, local(child, pc))
            if j.type == "prismatic":  # r(point on bodies[1]) - r(point on bodies[0]) = s a
                s_i = me.dynamicsymbols(f"q{len(q)}")
                q.append(s_i)
                labels.append(j.name)
                first = fp if j.bodies[0] == par else fc
                a = vec(first, j.axis)
                a0 = np.asarray(j.axis, float)
                ang0 = guess_angle.get(j.bodies[0], 0.0)
                a0 = np.array([[np.cos(ang0), -np.sin(ang0)], [np.sin(ang0), np.cos(ang0)]]) @ a0
                d0 = guess_point(j.bodies[1], j.points[1]) - guess_point(j.bodies[0], j.points[0])
                start.append(float(a0 @ d0))
                rc = rc + (s_i if j.bodies[1] == child else -s_i) * a
            frames[child] = (fc, ac, rc)

        def position(body, xy):
            f, _, r = frames[body]
            return r + vec(f, xy)

        # loop closure: the joints left out of the tree
        phi = []
        for j in tree.cuts:
            (b0, b1), (p0, p1) = j.bodies, j.points
            d = position(b1, local(b1, p1)) - position(b0, local(b0, p0))
            if j.type == "revolute":
                phi += [d.dot(N.x), d.dot(N.y)]
            else:
                f0 = frames[b0][0]
                n = vec(f0, (-j.axis[1], j.axis[0]))
                phi.append(d.dot(n))
                if turns(b0) and turns(b1):
                    phi.append(frames[b1][1] - frames[b0][1]
                               - (guess_angle[b1] - guess_angle[b0]))
        n, m = len(q), len(phi)
        if m >= n and m:
            raise Unsupported(f"independent derivation: {m} loop equations for {n} "
                              "coordinates (redundant or locked loops are not handled)")
        self.coords, self.n, self.m = labels, n, m

        # numeric stand-ins for the dynamic symbols
        Q = sp.symbols(f"Q0:{n}")
        U = sp.symbols(f"U0:{n}")
        A = sp.symbols(f"A0:{n}")
        u = [me.dynamicsymbols(f"u{i}") for i in range(n)]
        qd_u = {qi.diff(t): ui for qi, ui in zip(q, u, strict=True)}
        ud_a = {ui.diff(t): ai for ui, ai in zip(u, A, strict=True)}
        plain = {**{qi: Qi for qi, Qi in zip(q, Q, strict=True)},
                 **{ui: Ui for ui, Ui in zip(u, U, strict=True)}}

        def num(expr):  # dynamic symbols -> plain symbols (derivatives first)
            e = sp.sympify(expr)
            e = e.subs(qd_u).subs(ud_a).subs(qd_u)
            return e.xreplace(plain)

        def ddt(expr):  # time derivative with q' = u, u' = A
            return sp.sympify(expr).diff(t).subs(qd_u)

        def fn(exprs, *args):
            return sp.lambdify(args, sp.Matrix([num(e) for e in exprs]), "numpy", cse=True)

        self._phi = fn(phi, Q)
        jac = sp.Matrix(phi).jacobian(q) if m else sp.zeros(0, n)
        self._J = sp.lambdify([Q], jac.xreplace(plain), "numpy", cse=True) if m else None
        phi_dot = list(jac * sp.Matrix(u)) if m else []

        # bodies and loads
        g = float(case.gravity[0]) * N.x + float(case.gravity[1]) * N.y
        bodies, loads, kin = [], [], {}
        energy = 0
        for b in case.bodies:
            f, ang, r = frames[b.name]
            f.set_ang_vel(N, ddt(ang) * N.z)
            rg = position(b.name, b.com)
            vg = ddt(rg.to_matrix(N))
            G = O.locatenew(f"G_{b.name}", rg)
            G.set_vel(N, vg[0] * N.x + vg[1] * N.y)
            if turns(b.name):
                inertia = me.inertia(f, 0, 0, float(b.inertia))
                bodies.append(me.RigidBody(b.name, G, f, float(b.mass), (inertia, G)))
            else:
                bodies.append(me.Particle(b.name, G, float(b.mass)))
            loads.append((G, float(b.mass) * g))
            w = ddt(ang) if turns(b.name) else 0
            energy += (sp.Rational(1, 2) * float(b.mass) * (vg[0] ** 2 + vg[1] ** 2)
                       + sp.Rational(1, 2) * float(b.inertia if turns(b.name) else 0) * w ** 2
                       - float(b.mass) * rg.dot(g))
            kin[b.name] = [rg.dot(N.x), rg.dot(N.y), ddt(vg[0]), ddt(vg[1]),
                           ddt(w) if turns(b.name) else 0]
        applied = {}
        for ld in case.forces:
            f, _, _ = frames[ld.body]
            if ld.type == "torque":
                loads.append((f, float(ld.value) * N.z))
                applied.setdefault(ld.body, []).append(("torque", float(ld.value), None))
            else:
                p = O.locatenew(f"P_{ld.body}_{ld.point}",
                                position(ld.body, case.body(ld.body).points[ld.point]))
                v = ddt(p.pos_from(O).to_matrix(N))
                p.set_vel(N, v[0] * N.x + v[1] * N.y)
                loads.append((p, float(ld.value[0]) * N.x + float(ld.value[1]) * N.y))
                applied.setdefault(ld.body, []).append(("force", np.asarray(ld.value, float),
                                                        ld.point))
        self._applied = applied

        # partition: independent coordinates from the fixed channels first
        self._chan, self._chan_q = {}, {}  # channel -> f(q, u); fixed channel -> df/dq
        for c in case.channels:
            if c.kind == "angle" and c.points is None:
                e = frames[c.body][1]
            elif c.kind == "angle":
                pts = case.body(c.body).points
                d = (position(c.body, pts[c.points[1]]) - position(c.body, pts[c.points[0]]))
                e = sp.atan2(d.dot(N.y), d.dot(N.x))
            elif c.kind in ("position", "velocity"):
                r = position(c.body, case.body(c.body).points[c.point])
                e = r.dot({"x": N.x, "y": N.y}[c.axis])
                e = ddt(e) if c.kind == "velocity" else e
            elif c.kind == "energy":
                e = energy
            else:
                continue
            self._chan[c.name] = sp.lambdify([Q, U], num(e), "numpy", cse=True)
            if c.name in case.fix or c.name in case.velocity:
                self._chan_q[c.name] = sp.lambdify([Q], sp.Matrix([num(e)]).jacobian(Q),
                                                   "numpy")
        self.q0 = self._assemble(np.asarray(start, float))
        self.ind, self.dep = self._partition(self.q0)
        self.u0 = self._rates(self.q0)

        kd = [qi.diff(t) - ui for qi, ui in zip(q, u, strict=True)]
        kane = me.KanesMethod(
            N, q_ind=[q[i] for i in self.ind], u_ind=[u[i] for i in self.ind], kd_eqs=kd,
            q_dependent=[q[i] for i in self.dep], u_dependent=[u[i] for i in self.dep],
            configuration_constraints=phi or None,
            velocity_constraints=phi_dot or None)
        kane.kanes_equations(bodies, loads)
        self._M = sp.lambdify([Q, U], num(kane.mass_matrix), "numpy", cse=True)
        self._F = sp.lambdify([Q, U], num(kane.forcing), "numpy", cse=True)
        self._kin = {k: sp.lambdify([Q, U, A], sp.Matrix([num(e) for e in v]), "numpy",
                                    cse=True) for k, v in kin.items()}
        self._points = {}  # (body, point) -> world position (2,) from q
        for b in case.bodies:
            for p, xy in b.points.items():
                r = position(b.name, xy)
                self._points[(b.name, p)] = sp.lambdify(
                    [Q], sp.Matrix([num(r.dot(N.x)), num(r.dot(N.y))]), "numpy")
        self._angle = {b.name: sp.lambdify([Q], num(frames[b.name][1]), "numpy")
                       for b in case.bodies}
        self.min_sigma = np.inf
        self.restart()

    # ---- configuration --------------------------------------------------------------
    def _solve_loop(self, q: np.ndarray, free: np.ndarray, extra=None) -> np.ndarray:
        """Newton on the loop equations (and ``extra`` = (residual, jacobian) rows) for the
        coordinates ``free``, to round-off; returns the closed q."""
        q = q.copy()
        for _ in range(50):
            r = np.asarray(self._phi(q), float).ravel() if self.m else np.zeros(0)
            J = np.asarray(self._J(q), float).reshape(self.m, self.n) if self.m else \
                np.zeros((0, self.n))
            if extra:
                r2, J2 = extra(q)
                r, J = np.concatenate([r, r2]), np.vstack([J, J2])
            if r.size == 0:
                return q
            step = np.linalg.lstsq(J[:, free], -r, rcond=None)[0]
            q[free] += step
            if np.max(np.abs(step)) < 1e-15 * (1 + np.max(np.abs(q))):
                return q
        if np.max(np.abs(r)) > 1e-12:
            raise Unsupported(f"independent derivation: loop does not close (|phi| {r})")
        return q

    def _assemble(self, start: np.ndarray) -> np.ndarray:
        """q at t = 0: the loop closed with the fixed channels at their values."""
        fixed = [c for c in self.case.fix if c in self._chan]

        def extra(q):
            r = [self._chan[c](q, np.zeros(self.n)) - self.case.fix[c] for c in fixed]
            J = [np.asarray(self._chan_q[c](q), float).ravel() for c in fixed]
            return np.asarray(r, float), np.asarray(J, float).reshape(len(fixed), self.n)
        return self._solve_loop(start, np.arange(self.n), extra if fixed else None)

    def _partition(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dof = self.n - self.m
        J = np.asarray(self._J(q), float).reshape(self.m, self.n) if self.m else \
            np.zeros((0, self.n))
        order = []
        for c in list(self.case.fix) + list(self.case.velocity):
            if c in self._chan_q:
                g = np.abs(np.asarray(self._chan_q[c](q), float).ravel())
                order += [i for i in np.argsort(-g) if g[i] > 1e-12 and i not in order]
        order += [i for i in range(self.n) if i not in order]
        ind = []
        for i in order:
            if len(ind) == dof:
                break
            rest = [k for k in range(self.n) if k not in ind + [i]]
            if np.linalg.matrix_rank(J[:, rest]) == self.m:
                ind.append(i)
        dep = [k for k in range(self.n) if k not in ind]
        return np.array(sorted(ind), int), np.array(dep, int)

    def _rates(self, q: np.ndarray) -> np.ndarray:
        """u at t = 0 from the case's initial channel rates (zero where none is given)."""
        rows, rhs = [], []
        if self.m:
            rows.append(np.asarray(self._J(q), float).reshape(self.m, self.n))
            rhs.append(np.zeros(self.m))
        for c, v in self.case.velocity.items():
            if c in self._chan_q:
                rows.append(np.asarray(self._chan_q[c](q), float).reshape(1, self.n))
                rhs.append([v])
        if not rows:
            return np.zeros(self.n)
        return np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]

    def restart(self) -> None:
        """Start the dependent-coordinate continuation again from q0."""
        self._last = (self.q0[self.ind].copy(), self.q0[self.dep].copy(),
                      self._tangent(self.q0))

    def _tangent(self, q: np.ndarray) -> np.ndarray:
        """d q_dep / d q_ind (d, k) on the loop at q: -Phi_dep^-1 Phi_ind."""
        if not self.m:
            return np.zeros((0, len(self.ind)))
        J = np.asarray(self._J(q), float).reshape(self.m, self.n)
        return np.linalg.solve(J[:, self.dep], -J[:, self.ind])

    def full(self, qi: np.ndarray, ui: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All coordinates and rates from the independent ones (loop closed by Newton).

        Newton starts from the last solution moved along the loop's tangent there: where
        two branches of the loop cross (A02's horizontal position, the parallelogram and
        the anti-parallelogram) the start from the last solution alone may fall to the
        other branch; the tangent keeps the branch the motion is on."""
        q = np.empty(self.n)
        q[self.ind] = qi
        if self.m:
            qi0, qd0, tangent = self._last
            q[self.dep] = qd0 + tangent @ (qi - qi0)
            q = self._solve_loop(q, self.dep)
            J = np.asarray(self._J(q), float).reshape(self.m, self.n)
            self.min_sigma = min(self.min_sigma,
                                 float(np.linalg.svd(J[:, self.dep], compute_uv=False)[-1]))
            tangent = np.linalg.solve(J[:, self.dep], -J[:, self.ind])
            self._last = (q[self.ind].copy(), q[self.dep].copy(), tangent)
        u = np.empty(self.n)
        u[self.ind] = ui
        if self.m:
            u[self.dep] = tangent @ ui
        return q, u

    def accelerations(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """All coordinate accelerations: Kane's reduced equations stacked over the loop's
        acceleration constraints (sympy's ``mass_matrix``/``forcing`` with dependent
        speeds: n x n, speeds ordered independent then dependent)."""
        F = np.asarray(self._F(q, u), float).ravel()
        M = np.asarray(self._M(q, u), float).reshape(self.n, self.n)
        a = np.empty(self.n)
        a[np.concatenate([self.ind, self.dep])] = np.linalg.solve(M, F)
        return a

    # ---- time integration --------------------------------------------------------------
    def rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        k = len(self.ind)
        q, u = self.full(y[:k], y[k:])
        return np.concatenate([y[k:], self.accelerations(q, u)[self.ind]])

    def integrate(self, times: np.ndarray, settings: dict | None = None, **kw):
        """scipy's solve_ivp over ``times`` (s) in the independent coordinates; ``kw`` go
        to solve_ivp (e.g. ``dense_output``, ``events``)."""
        s = {**SETTINGS, **(settings or {})}
        self.restart()
        self.min_sigma = np.inf  # the smallest singular value of Phi_dep met (1)
        y0 = np.concatenate([self.q0[self.ind], self.u0[self.ind]])
        sol = solve_ivp(self.rhs, (times[0], times[-1]), y0, method=s["method"],
                        rtol=s["rtol"], atol=s["atol"], t_eval=times, **kw)
        if not sol.success:
            raise RuntimeError(f"independent integration failed: {sol.message}")
        return sol

    def channels(self, times: np.ndarray, y: np.ndarray) -> pd.DataFrame:
        """The case's channels at ``times`` from states ``y`` (2k, T); channels of kinds
        this derivation does not produce are left out."""
        k = len(self.ind)
        self.restart()
        cols = {"t": np.asarray(times, float)}
        rows = []
        for i in range(len(times)):
            q, u = self.full(y[:k, i], y[k:, i])
            rows.append((q, u, self.accelerations(q, u)))
        for c in self.case.channels:
            if c.name in self._chan:
                v = np.array([float(self._chan[c.name](q, u)) for q, u, _ in rows])
                if c.kind == "angle":  # the branch of unwrap(atan2) at t = 0
                    v = v - 2 * np.pi * np.round(v[0] / (2 * np.pi) - 1e-12)
                cols[c.name] = v
        forces = [self.reactions(*r) for r in rows]
        for c in self.case.channels:
            if c.kind == "reaction":
                cols[c.name] = np.array([f[c.joint][{"x": 0, "y": 1, "normal": 2}[c.axis]]
                                         for f in forces])
        self.newton_euler_residual = max(f["_residual"] for f in forces)
        return pd.DataFrame(cols)

    # ---- reactions by Newton-Euler -------------------------------------------------------
    def reactions(self, q: np.ndarray, u: np.ndarray, a: np.ndarray) -> dict:
        """joint -> (Fx, Fy, F.n): the force each joint applies to its second body (world
        axes, N; n the prismatic normal), from every body's Newton-Euler equations solved
        in the least-squares sense; ``_residual`` their largest residual (N, N m)."""
        case = self.case
        names = [b.name for b in case.bodies]
        rows = {b: 3 * i for i, b in enumerate(names)}
        kin = {b: np.asarray(self._kin[b](q, u, a), float).ravel() for b in names}
        unknowns = []  # (joint, kind)
        cols = []
        rhs = np.zeros(3 * len(names))
        g = np.asarray(case.gravity, float)
        for b in case.bodies:
            r = rows[b.name]
            x, y, ax, ay, al = kin[b.name]
            rhs[r:r + 2] = b.mass * (np.array([ax, ay]) - g)
            rhs[r + 2] = (b.inertia * al) if b.kind != "particle" else 0.0
            for kind, val, pt in self._applied.get(b.name, []):
                if kind == "torque":
                    rhs[r + 2] -= val
                else:
                    rhs[r:r + 2] -= val
                    d = self._point(b.name, pt, q) - np.array([x, y])
                    rhs[r + 2] -= d[0] * val[1] - d[1] * val[0]

        def column(force_on_b1, moment, j):
            """One unknown's column: unit force (2,) on bodies[1] at its joint point and
            the opposite on bodies[0]; ``moment`` a unit couple on bodies[1]."""
            col = np.zeros(3 * len(names))
            p1 = None
            if j.bodies[1] != GROUND:
                p1 = self._point(j.bodies[1], j.points[1], q)
            for sign, body in ((1.0, j.bodies[1]), (-1.0, j.bodies[0])):
                if body == GROUND:
                    continue
                r = rows[body]
                f = sign * force_on_b1
                at = p1 if p1 is not None else self._point(body, j.points[0], q)
                d = at - kin[body][:2]
                col[r:r + 2] += f
                col[r + 2] += d[0] * f[1] - d[1] * f[0] + sign * moment
            return col

        for j in case.joints:
            if j.type == "revolute":
                for e in (np.array([1.0, 0.0]), np.array([0.0, 1.0])):
                    cols.append(column(e, 0.0, j))
                    unknowns.append((j.name, "f"))
            else:
                nrm = self._normal(j, q)
                cols.append(column(nrm, 0.0, j))
                unknowns.append((j.name, "n"))
                turn = [b for b in j.bodies if b != GROUND and case.body(b).kind != "particle"]
                if len(turn) == 2 or (len(turn) == 1 and GROUND in j.bodies):
                    cols.append(column(np.zeros(2), 1.0, j))
                    unknowns.append((j.name, "m"))
        keep = [i for i, b in enumerate(case.bodies) if b.kind != "particle"]
        live = np.array([r for b in names for r in range(rows[b], rows[b] + 2)]
                        + [rows[case.bodies[i].name] + 2 for i in keep])
        A = np.array(cols).T[live]
        x, *_ = np.linalg.lstsq(A, rhs[live], rcond=None)
        out = {"_residual": float(np.max(np.abs(A @ x - rhs[live])))}
        for j in case.joints:
            idx = [i for i, (jn, _) in enumerate(unknowns) if jn == j.name]
            if j.type == "revolute":
                f = x[idx[:2]]
                out[j.name] = (f[0], f[1], np.nan)
            else:
                nrm = self._normal(j, q)
                out[j.name] = (x[idx[0]] * nrm[0], x[idx[0]] * nrm[1], x[idx[0]])
        return out

    def _point(self, body, name, q) -> np.ndarray:
        return np.asarray(self._points[(body, name)](q), float).ravel()

    def _normal(self, j, q) -> np.ndarray:
        """World unit normal of a prismatic joint: its axis turned +90 deg."""
        ang = 0.0 if j.bodies[0] == GROUND else float(self._angle[j.bodies[0]](q))
        c, s = np.cos(ang), np.sin(ang)
        a = np.array([[c, -s], [s, c]]) @ np.asarray(j.axis, float)
        return np.array([-a[1], a[0]])


def solve(case: Case, settings: dict | None = None) -> pd.DataFrame:
    """The case's channels at its sample times from the independent derivation."""
    model = JointModel(case)
    sol = model.integrate(case.times, settings)
    return model.channels(sol.t, sol.y)


def describe(settings: dict) -> str:
    return METHOD.format(solver=f"{settings['method']} rtol {settings['rtol']:g}")


def check(case: Case, reference: pd.DataFrame) -> dict | None:
    """The ``independent`` field of a reference's provenance: the independent solution at
    SETTINGS, its own error estimate (against CHECK) and ``max |reference - independent|``
    per channel it produces; None when the case is not supported."""
    if supported(case):
        return None
    try:
        model = JointModel(case)
    except Unsupported:  # e.g. redundant loops
        return None
    sol = model.integrate(case.times, SETTINGS)
    best = model.channels(sol.t, sol.y)
    residual = model.newton_euler_residual
    loose = model.channels(*_ty(model.integrate(case.times, CHECK)))
    names = [c for c in best.columns if c != "t" and c in reference.columns]
    return {
        "method": describe(SETTINGS) + "; reactions by Newton-Euler per body",
        "settings": dict(SETTINGS),
        "coordinates": {"all": model.coords,
                        "independent": [model.coords[i] for i in model.ind]},
        "max_abs_diff": {c: float(np.max(np.abs(best[c].to_numpy()
                                                - reference[c].to_numpy(float))))
                         for c in names},
        "estimated_error": {c: estimated_error(best[c], loose[c], len(sol.t)) for c in names},
        "estimated_error_method": "max |independent - its run at "
                                  f"{CHECK['method']} rtol {CHECK['rtol']:g}|",
        "newton_euler_residual": residual,
    }


def _ty(sol):
    return sol.t, sol.y
