"""Builder for natural-coordinate models: elements, bodies, constraint rows, joints, drivers,
forces.

Declare all elements first (:meth:`Builder.point`, :meth:`Builder.vector`, fixed ones), then
bodies, constraints, joints and forces; :meth:`Builder.build` returns a frozen
:class:`~natcoord.model.model.Model`. Maps are (d, n + 1) arrays ``C`` with ``C @ [q, 1]`` a world
position (m) or world direction components; row conventions are in :mod:`natcoord.model.model`.

Geometry is given in the *reference configuration*: the elements' reference values, in world
axes. Each body's reference placement only has to be rigid within the body; bodies need not
fit together there (a joint's two points are given apart, ``point`` on the first body and
``point_b`` on the second), so an approximate pose is a valid reference and the position
problem (:mod:`natcoord.model.kinematics`) closes the joints.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .constraints import ROUNDOFF, ConstraintBuilder
from .drivers import DriverRow
from .model import GROUND, J2, Body, Element, JointForce, Model, Spring, support


@dataclass
class Builder:
    """Collects elements, bodies, constraints and forces (mutable, build time only).

    Parameters
    ----------
    dim : 2 or 3
    gravity : (dim,) m/s^2, default -9.81 along the last axis
    """

    dim: int = 3
    gravity: np.ndarray | None = None
    elements: dict[str, Element] = field(default_factory=dict)
    bodies: dict[str, Body] = field(default_factory=dict)
    rows: dict[str, np.ndarray] = field(default_factory=dict)
    rod_length: dict[str, float] = field(default_factory=dict)
    torques: list = field(default_factory=list)
    springs: list = field(default_factory=list)
    joints: dict[str, JointForce] = field(default_factory=dict)
    drivers: list = field(default_factory=list)
    body_forces: list = field(default_factory=list)
    _n: int = 0
    _cb: ConstraintBuilder | None = None
    _M: np.ndarray | None = None
    _Q0: np.ndarray | None = None
    _qh: np.ndarray | None = None  # [q0, 1] once the elements are all declared

    def __post_init__(self):
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim}")
        if self.gravity is None:
            self.gravity = np.zeros(self.dim)
            self.gravity[-1] = -9.81
        self.gravity = np.asarray(self.gravity, float)

    # ---- elements (declare them all first) ----------------------------------------------
    def _element(self, name, kind, x, fixed):
        if self._cb is not None:
            raise RuntimeError(f"element {name!r} declared after bodies or constraints; "
                               "declare every point and vector first")
        if name in self.elements or name == GROUND:
            raise ValueError(f"element {name!r} already exists")
        x = np.asarray(x, float)
        if x.shape != (self.dim,):
            raise ValueError(f"element {name!r}: expected {self.dim} components, got {x}")
        if kind == "vector" and abs(np.linalg.norm(x) - 1.0) > 1e-9:
            raise ValueError(f"vector {name!r} must be a unit vector, |v| = {np.linalg.norm(x)}")
        cols = np.zeros(0, int) if fixed else np.arange(self._n, self._n + self.dim)
        self._n += 0 if fixed else self.dim
        self.elements[name] = Element(name, kind, fixed, cols, x)

    def point(self, name: str, x) -> None:
        """A moving point, reference position x (dim,), m."""
        self._element(name, "point", x, False)

    def vector(self, name: str, u) -> None:
        """A moving unit vector, reference components u (dim,); its unit norm row is added
        with the first constraint."""
        self._element(name, "vector", u, False)

    def fixed_point(self, name: str, x) -> None:
        self._element(name, "point", x, True)

    def fixed_vector(self, name: str, u) -> None:
        self._element(name, "vector", u, True)

    def _start(self):
        if self._cb is None:
            n = self._n
            self._cb = ConstraintBuilder(n)
            self._M, self._Q0 = np.zeros((n, n)), np.zeros(n)
            for e in self.elements.values():
                if e.kind == "vector" and not e.fixed:
                    self.rows[f"{e.name}: unit"] = np.array(
                        [self._cb.dot(self.E(e.name), self.E(e.name), 1.0,
                                      f"{e.name}: unit", 0)])
        return self._cb

    @property
    def n(self) -> int:
        return self._n

    # ---- maps ---------------------------------------------------------------------------
    def E(self, name: str) -> np.ndarray:
        """(d, n + 1) map of an element (position of a point, components of a vector)."""
        e = self.elements[name]
        C = np.zeros((self.dim, self._n + 1))
        if e.fixed:
            C[:, -1] = e.x0
        else:
            C[:, e.cols] = np.eye(self.dim)
        return C

    def _ldim(self, name: str) -> int:
        return 1 if self.elements[name].kind == "point" else 0

    def at(self, body: str, x) -> np.ndarray:
        """Map of the point of ``body`` (or ``ground``) at reference position x."""
        if body == GROUND:
            C = np.zeros((self.dim, self._n + 1))
            C[:, -1] = x
            return C
        return self.bodies[body].point_map(x)

    def along(self, body: str, v) -> np.ndarray:
        """Map of the direction of ``body`` (or ``ground``) with reference components v."""
        if body == GROUND:
            C = np.zeros((self.dim, self._n + 1))
            C[:, -1] = v
            return C
        return self.bodies[body].dir_map(v)

    # ---- bodies -------------------------------------------------------------------------
    def body(self, name: str, basis: list[str], *, mass: float = 0.0, com=None,
             second_moment=None, rigid: bool = True, frame=None) -> None:
        """A rigid body on the elements ``basis`` (the first must be a point).

        Adds its mass to M and its weight to Q0, and (``rigid``) the rigid-body rows among
        the basis: all point-point distances, the dot products of the point differences
        ``r_k - r_0`` with the vectors, and the vector-vector dot products. With a basis of
        two points and two vectors that is the classical 6 rows.

        ``second_moment``: ∫ (x - g)(x - g)^T dm about the com (dim, dim), kg m^2, in the
        reference configuration (see :func:`second_moment` to convert an inertia tensor).
        ``frame``: ``(R0 (dim, dim), o0 (dim,))``, the pose of the body's own frame in the
        reference configuration (default: the world frame); it only names the body's frame
        in outputs.
        """
        self._start()
        if name in self.bodies or name == GROUND:
            raise ValueError(f"body {name!r} already exists")
        els = [self.elements[b] for b in basis]
        if not els or els[0].kind != "point":
            raise ValueError(f"body {name!r}: the first basis element must be a point")
        p0 = els[0].x0
        G = [self.E(e.name) - (self.E(basis[0]) if e.kind == "point" else 0.0)
             for e in els[1:]]
        if self.dim == 2 and len(G) == 1:  # in 2-D, J d is linear in q: a free second column
            G.append(J2 @ G[0])
        G = np.array(G).reshape(len(G), self.dim, self._n + 1)
        qh0 = self._qh0()
        D = np.einsum("kan,n->ak", G, qh0)
        com = p0 if com is None else np.asarray(com, float)
        Jg = np.zeros((self.dim, self.dim)) if second_moment is None else \
            np.asarray(second_moment, float)
        R0, o0 = (np.eye(self.dim), np.zeros(self.dim)) if frame is None else \
            (np.asarray(frame[0], float), np.asarray(frame[1], float))
        b = Body(name, tuple(basis), self.E(basis[0]), G, D, p0, float(mass), com, Jg, R0, o0)
        if mass > 0:
            cbar = b.coeffs(com, point=True)
            Jo = mass * np.outer(com - p0, com - p0) + Jg
            P = D @ np.linalg.pinv(D)
            if np.linalg.norm(Jo - P @ Jo @ P) > 1e-9 * max(1.0, np.linalg.norm(Jo)):
                raise ValueError(f"body {name!r}: its mass lies outside the span of the basis "
                                 f"{basis}; add a point or a unit vector")
            Dp = np.linalg.pinv(D)
            K = len(G)
            Mab = np.zeros((K + 1, K + 1))
            Mab[0, 0] = mass
            Mab[0, 1:] = Mab[1:, 0] = mass * cbar
            Mab[1:, 1:] = Dp @ Jo @ Dp.T
            # symmetric, and an entry at round-off of the largest is an exact zero (1e-17
            # from a rotated frame): zeroed, so that M's structural zeros stay zeros, and
            # with them those of M^-1 and of the generated kernels
            Mab = 0.5 * (Mab + Mab.T)
            Mab[np.abs(Mab) < ROUNDOFF * np.max(np.abs(Mab))] = 0.0
            maps = [b.G0[:, :-1]] + [g[:, :-1] for g in G]
            cols = support(*maps)
            sub = [x[:, cols] for x in maps]  # the body's own columns: O(1) per body
            Mb = sum(Mab[a, c] * sub[a].T @ sub[c] for a in range(K + 1)
                     for c in range(K + 1))
            self._M[np.ix_(cols, cols)] += Mb
            self._Q0 += mass * b.point_map(com)[:, :-1].T @ self.gravity
        self.bodies[name] = b
        if rigid:
            rows = []
            pts = [e.name for e in els if e.kind == "point"]
            vecs = [e.name for e in els if e.kind == "vector"]
            for i, a in enumerate(pts):
                for c in pts[i + 1:]:
                    rows.append(self.distance(a, c, name=None, label=f"{name}: |{a}{c}|"))
            for a in pts[1:]:
                for v in vecs:
                    rows.append(self.dot((pts[0], a), v, label=f"{name}: {pts[0]}{a}.{v}"))
            for i, u in enumerate(vecs):
                for v in vecs[i + 1:]:
                    rows.append(self.dot(u, v, label=f"{name}: {u}.{v}"))
            self.rows[name] = np.array(rows, int)

    def _qh0(self) -> np.ndarray:
        """[q0, 1] (n + 1,): the elements' reference coordinates (a copy); made once after
        the last element (every body and constraint asks: O(n) each, O(n^2) in all)."""
        if self._qh is None or self._cb is None:
            q = np.zeros(self._n + 1)
            q[-1] = 1.0
            for e in self.elements.values():
                if not e.fixed:
                    q[e.cols] = e.x0
            if self._cb is None:
                return q
            self._qh = q
        return self._qh.copy()

    # ---- constraint kinds ---------------------------------------------------------------
    def _vec(self, x):
        """Map and length dimension of a vector expression: a vector name, a point pair
        (a, b) meaning r_b - r_a, or an explicit (map, length_dim)."""
        if isinstance(x, str):
            if self.elements[x].kind != "vector":
                raise ValueError(f"{x!r} is a point; give a pair (a, b) for r_b - r_a")
            return self.E(x), 0
        if isinstance(x, tuple) and len(x) == 2 and isinstance(x[0], str):
            return self.E(x[1]) - self.E(x[0]), 1
        C, ld = x
        return np.asarray(C, float), int(ld)

    def distance(self, a: str, b: str, L: float | None = None, *, name: str | None = None,
                 label: str | None = None) -> int:
        """Constant distance ``|r_b - r_a|^2 - L^2 = 0`` (L from the reference if None).

        A massless rod with spherical ends; with ``name`` its axial force (``2 L lambda``,
        tension positive) is available as ``model.axial(name, lam)``.
        """
        cb = self._start()
        C = self.E(b) - self.E(a)
        L = float(np.linalg.norm(C @ self._qh0())) if L is None else float(L)
        row = cb.dot(C, C, L * L, label or name or f"|{a}{b}|", 2)
        if name:
            self.rows[name] = np.array([row])
            self.rod_length[name] = L
        return row

    def rod(self, name: str, a: str, b: str, L: float | None = None) -> int:
        """Massless rod between points a and b: a named :meth:`distance`."""
        return self.distance(a, b, L, name=name)

    def dot(self, x, y, value: float | None = None, *, label: str | None = None) -> int:
        """Constant dot product of two vector expressions (see :meth:`_vec`)."""
        cb = self._start()
        (A, la), (B, lb) = self._vec(x), self._vec(y)
        if value is None:
            qh0 = self._qh0()
            value = float((A @ qh0) @ (B @ qh0))
        return cb.dot(A, B, value, label or f"{x}.{y}", la + lb)

    def unit(self, v: str) -> int:
        """Unit norm |v|^2 - 1 = 0 (added automatically for every moving vector)."""
        return self._start().dot(self.E(v), self.E(v), 1.0, f"{v}: unit", 0)

    def linear(self, coeffs: dict[str, float], *, const=None, name: str | None = None,
               label: str | None = None) -> list[int]:
        """Linear combination ``sum_e c_e e + const = 0`` (dim rows), e.g. Eq. (105)
        ``{"1": 1, "2": -1, "3": 1, "4": -1}``."""
        cb = self._start()
        C = sum(c * self.E(e) for e, c in coeffs.items())
        if const is not None:
            C[:, -1] += const
        ld = max(self._ldim(e) for e in coeffs)
        rows = cb.linear_rows(C, label or name or "+".join(f"{c:g}{e}" for e, c in
                                                           coeffs.items()), ld)
        if name:
            self.rows[name] = np.array(rows)
        return rows

    def attach(self, element: str, body: str, *, name: str | None = None) -> list[int]:
        """Make a moving element a constant linear combination of a body's basis (at its
        reference value): an extra point or vector of the body (dim rows)."""
        cb = self._start()
        e = self.elements[element]
        C = self.E(element) - (self.at(body, e.x0) if e.kind == "point" else
                               self.along(body, e.x0))
        rows = cb.linear_rows(C, name or f"{element} in {body}", self._ldim(element))
        self.rows[name or f"{element} in {body}"] = np.array(rows)
        return rows

    def coincident(self, A: np.ndarray, B: np.ndarray, label: str, length_dim: int = 1):
        """``A qh - B qh = 0`` for two maps: coincident points or equal vectors (dim rows).
        Equal unit vectors give one redundant row (both norms are already fixed)."""
        return self._start().linear_rows(A - B, label, length_dim)

    # ---- joints (geometry in the reference configuration, world axes) --------------------
    def _perp(self, axis) -> np.ndarray:
        """(dim - 1, dim) orthonormal directions normal to ``axis`` (2-D: J2 axis)."""
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        if self.dim == 2:
            return (J2 @ a)[None]
        return np.linalg.svd(a[None, :])[2][1:]

    def _joint(self, name, rows, force_rows, force_maps):
        self.rows[name] = np.array(rows, int)
        self.joints[name] = JointForce(np.array(force_rows, int),
                                       np.array(force_maps, float).reshape(
                                           len(force_rows), self.dim, self._n + 1))
        return self.rows[name]

    def _coincident_joint(self, name, a, b, point, point_b) -> tuple[list[int], list]:
        """Coincidence rows r_a - r_b (dim rows) and their unit force maps."""
        rows = self.coincident(self.at(a, point), self.at(b, point if point_b is None
                                                           else point_b), name)
        maps = []
        for k in range(self.dim):
            C = np.zeros((self.dim, self._n + 1))
            C[k, -1] = 1.0
            maps.append(C)
        return rows, maps

    def spherical(self, name: str, a: str, b: str, point, point_b=None) -> np.ndarray:
        """Spherical joint: the point of a and the point of b coincide (dim rows); lambda is
        the force on b."""
        rows, maps = self._coincident_joint(name, a, b, point, point_b)
        return self._joint(name, rows, rows, maps)

    def _aligned(self, name, a, b, axis) -> list[int]:
        """Axis of a ⊥ two directions of b that are ⊥ the axis: 2 rows, independent."""
        ua = self.along(a, axis)
        return [self._start().dot(ua, self.along(b, p), 0.0, f"{name}: axis.{k}", 0)
                for k, p in enumerate(self._perp(axis))]

    def revolute(self, name: str, a: str, b: str, point, axis=None,
                 point_b=None) -> np.ndarray:
        """Revolute joint about ``axis`` through ``point``: 3 coincidence + 2 alignment rows
        (5 independent; 2-D: the 2 coincidence rows). The first dim multipliers are the
        force on b (N), world axes."""
        rows, maps = self._coincident_joint(name, a, b, point, point_b)
        extra = self._aligned(name, a, b, axis) if self.dim == 3 else []
        return self._joint(name, rows + extra, rows, maps)

    def universal(self, name: str, a: str, b: str, point, axis_a, axis_b,
                  point_b=None) -> np.ndarray:
        """Universal (Cardan) joint: coincident points and axis_a of a ⊥ axis_b of b."""
        rows, maps = self._coincident_joint(name, a, b, point, point_b)
        cross = self._start().dot(self.along(a, axis_a), self.along(b, axis_b), 0.0,
                                  f"{name}: cross", 0)
        return self._joint(name, rows + [cross], rows, maps)

    def _on_line(self, name, a, b, point, axis, point_b) -> tuple[list[int], list]:
        """The point of b on a's line through ``point`` along ``axis`` (dim - 1 rows
        ``p_a . (r_b - r_a)``) and their force maps ``-p_a``."""
        if a != GROUND and self.bodies[a].rank == 0:
            raise ValueError(f"joint {name!r}: its first body {a!r} is a particle and has no "
                             "direction to slide along; name the other body first")
        rel = self.at(b, point if point_b is None else point_b) - self.at(a, point)
        rows, maps = [], []
        for k, p in enumerate(self._perp(axis)):
            pa = self.along(a, p)
            rows.append(self._start().dot(pa, rel, 0.0, f"{name}: line.{k}", 1))
            maps.append(-pa)
        return rows, maps

    def _turns(self, body: str) -> bool:
        return body == GROUND or self.bodies[body].rank > 0

    def cylindrical(self, name: str, a: str, b: str, point, axis, point_b=None) -> np.ndarray:
        """Cylindrical joint: the point of b on a's line (2 rows), axes parallel (2 rows)."""
        rows, maps = self._on_line(name, a, b, point, axis, point_b)
        extra = self._aligned(name, a, b, axis) if self._turns(b) else []
        return self._joint(name, rows + extra, rows, maps)

    def prismatic(self, name: str, a: str, b: str, point, axis, point_b=None) -> np.ndarray:
        """Prismatic joint: the point of b on a's line and no relative rotation (5 rows in
        3-D, 2 in 2-D; a particle as second body only keeps to the line)."""
        rows, maps = self._on_line(name, a, b, point, axis, point_b)
        extra = []
        if self._turns(b):
            p = self._perp(axis)
            if self.dim == 3:
                extra = self._aligned(name, a, b, axis) + [self._start().dot(
                    self.along(a, p[0]), self.along(b, p[1]), 0.0, f"{name}: no spin", 0)]
            else:
                extra = [self._start().dot(self.along(a, p[0]), self.along(b, axis), 0.0,
                                           f"{name}: no spin", 0)]
        return self._joint(name, rows + extra, rows, maps)

    # ---- drivers ------------------------------------------------------------------------
    def drive_angle(self, name: str, body: str, law: tuple[float, float, float]) -> None:
        """A 2-D rheonomic row: the angle of ``body``'s frame follows ``law`` = (v0, rate,
        accel) (rad, rad/s, rad/s^2), written on its first basis difference."""
        b = self.bodies[body]
        if self.dim != 2 or b.rank == 0:
            raise ValueError(f"driver {name!r}: an angle driver needs a 2-D rigid body")
        d_body = b.R0.T @ b.D[:, 0]
        self.drivers.append(DriverRow(name, "angle", *law, C=b.G[0].copy(),
                                      offset=float(np.arctan2(d_body[1], d_body[0]))))

    def drive_coordinate(self, name: str, body: str, point, axis: int,
                         law: tuple[float, float, float]) -> None:
        """A rheonomic row: world coordinate ``axis`` of the body point (reference position
        ``point``) follows ``law`` = (v0, rate, accel) (m, m/s, m/s^2)."""
        self.drivers.append(DriverRow(name, "coordinate", *law,
                                      C=self.at(body, point)[axis].copy()))

    # ---- forces -------------------------------------------------------------------------
    def force(self, body: str, point, F, frame: str = "world") -> None:
        """Constant force F (dim,) N at the body point with reference position ``point``, in
        world axes or (``frame = "body"``) in the body's own frame, turning with it."""
        self._start()
        if frame == "body":
            b = self.bodies[body]
            self.body_forces.append((body, self.at(body, point), b.frame_law(F)))
            return
        self._Q0 += self.at(body, point)[:, :-1].T @ np.asarray(F, float)

    def force_on(self, element: str, F) -> None:
        """Constant force F (dim,) N on a point element."""
        self._start()
        self._Q0 += self.E(element)[:, :-1].T @ np.asarray(F, float)

    def torque(self, body: str, tau, frame: str = "world") -> None:
        """Constant torque on a body, (3,) N m, or a scalar in 2-D (where the frame does not
        matter), in world axes or (``frame = "body"``) in the body's own frame."""
        self._start()
        tau = np.atleast_1d(np.asarray(tau, float))
        law = self.bodies[body].frame_law(tau) if frame == "body" and self.dim == 3 else None
        self.torques.append((body, tau, law))

    def spring(self, name: str, A: np.ndarray, B: np.ndarray, k: float, c: float = 0.0,
               l0: float | None = None) -> None:
        """Linear spring-damper between the points of maps A and B (e.g. ``b.E("1")`` or
        ``b.at(body, x)``): tension ``k (l - l0) + c l_dot``, N (l0 from the reference)."""
        self._start()
        l0 = float(np.linalg.norm((B - A) @ self._qh0())) if l0 is None else float(l0)
        self.springs.append(Spring(name, A, B, float(k), float(c), l0))

    def build(self) -> Model:
        cb = self._start()
        return Model(self.dim, self._n, self._M.copy(), cb.build(), self._Q0.copy(),
                     self._qh0()[:-1], dict(self.elements), dict(self.bodies),
                     dict(self.rows), dict(self.rod_length), tuple(self.torques),
                     tuple(self.springs), dict(self.joints), tuple(self.drivers),
                     tuple(self.body_forces))
