"""The natural-coordinate model: points, unit vectors, rigid bodies, joints, forces (2-D and
3-D alike; 2-D is the planar case).

García de Jalón & Bayo (1994): the coordinates are the world positions of *points* and the
world components of *unit vectors*, 3 numbers each (2 in a 2-D model). A rigid body is a
*basis* of such elements (two points and two unit vectors, three points and one vector,
four non-coplanar points, a point and three vectors, or a degenerate basis for a rod or a
thin plate whose mass lies in the span of the basis); every other point or vector of the
body is a constant linear combination of its basis, so

* the mass matrix is constant (possibly singular: massless bodies, extra points),
* every constraint is at most quadratic, held as arrays by
  :class:`~natcoord.model.constraints.ConstraintBuilder`.

Everything is written in terms of *maps*: a (d, n + 1) array ``C`` with ``C @ [q, 1]`` the
world position of a point or the world components of a direction. Bodies are defined in
their reference configuration (world axes), which is also the initial guess ``q0``.

This module holds the frozen model (:class:`Element`, :class:`Body`, :class:`Spring`,
:class:`JointForce`, :class:`Model` and its force evaluation). Models are assembled with
:class:`~natcoord.model.builder.Builder`; inertia helpers live in :mod:`natcoord.model.inertia`.

Build order: declare all elements first (:meth:`Builder.point`, :meth:`Builder.vector`,
fixed ones), then bodies, constraints, joints, drivers and forces; :meth:`Builder.build`
returns a frozen :class:`Model` that follows the dynamics protocol (``n, m, M,
constraints, drivers, forces(t, q, qd)``).

Row conventions (so that multipliers read as forces):
* coincidence rows are ``r_a - r_b`` (a on the first body): lambda is the force that the
  joint applies to the second body, world axes, N;
* a distance row ``|r_b - r_a|^2 - L^2``: the axial force is ``2 L lambda``, tension
  positive;
* a point-on-line row ``p_a . (r_b - r_a)`` (p_a a direction of the first body normal to the
  line): the force on the second body is ``-lambda p_a``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..case.mechanism import GROUND
from .constraints import QuadraticConstraints
from .inertia import plate_second_moment, rod_second_moment, second_moment

__all__ = ["GROUND", "J2", "Element", "Body", "Spring", "JointForce", "Model",
           "second_moment", "rod_second_moment", "plate_second_moment"]

J2 = np.array([[0.0, -1.0], [1.0, 0.0]])  # +90 deg rotation in the plane


@dataclass(frozen=True)
class Element:
    """A point or unit vector: ``cols`` (d,) in q (empty when fixed), reference ``x0`` (d,)."""

    name: str
    kind: str  # "point" | "vector"
    fixed: bool
    cols: np.ndarray
    x0: np.ndarray


@dataclass(frozen=True)
class Body:
    """A rigid body: origin map G0 (d, n+1), difference maps G (K, d, n+1) whose reference
    values are the columns of D (d, K); mass (kg), com (d,), second moment about the com
    ``Jg = ∫ (x - g)(x - g)^T dm`` (d, d), all in the reference configuration (world axes).
    ``R0`` (d, d), ``o0`` (d,): the pose of the body's own frame in that configuration (its
    points in its frame are ``R0^T (x - o0)``)."""

    name: str
    basis: tuple[str, ...]
    G0: np.ndarray
    G: np.ndarray
    D: np.ndarray
    p0: np.ndarray
    mass: float
    com: np.ndarray
    Jg: np.ndarray
    R0: np.ndarray | None = None
    o0: np.ndarray | None = None

    @property
    def rank(self) -> int:
        """Number of independent directions the basis spans (0 for a particle)."""
        return int(np.linalg.matrix_rank(self.D, 1e-9)) if self.D.size else 0

    def coeffs(self, x: np.ndarray, *, point: bool) -> np.ndarray:
        """c (K,) with ``x - p0 = D c`` (point) or ``x = D c`` (direction); checks the span."""
        v = np.asarray(x, float) - (self.p0 if point else 0.0)
        c = np.linalg.lstsq(self.D, v, rcond=None)[0]
        if np.linalg.norm(self.D @ c - v) > 1e-9 * max(1.0, np.linalg.norm(v)):
            raise ValueError(f"body {self.name!r}: {x} is outside the span of its basis "
                             f"{self.basis}; add a point or a unit vector to the basis")
        return c

    def point_map(self, x: np.ndarray) -> np.ndarray:
        """(d, n + 1) map to the body point at reference position x (d,)."""
        return self.G0 + np.tensordot(self.coeffs(x, point=True), self.G, 1)

    def dir_map(self, v: np.ndarray) -> np.ndarray:
        """(d, n + 1) map to the body-fixed direction with reference components v (d,)."""
        return np.tensordot(self.coeffs(v, point=False), self.G, 1)

    def frame_law(self, v) -> np.ndarray:
        """c (K + 1,) with ``R(q) v = sum_k c_k d_k(q) + c_K (d_0 x d_1)(q)`` for a vector v
        (d,) in the body's own frame: R = D(q) D0^+ R0, the body frame of the outputs (a 3-D
        basis that spans a plane completed by its normal; c_K = 0 otherwise). ValueError for
        a body whose basis does not fix its frame (a particle, a 3-D basis along a line)."""
        D0, dim = self.D, len(self.p0)
        if self.rank < dim and not (dim == 3 and self.rank == 2):
            raise ValueError(f"body {self.name!r}: its basis {self.basis} does not fix its "
                             "frame (points along a line); a body-fixed load needs a body "
                             "whose points span a plane")
        plane = dim == 3 and self.rank == 2
        if plane:
            D0 = np.column_stack([D0, np.cross(D0[:, 0], D0[:, 1])])
        c = np.linalg.pinv(D0) @ self.R0 @ np.asarray(v, float)
        return c if plane else np.append(c, 0.0)

    def turned(self, c: np.ndarray, qh: np.ndarray) -> np.ndarray:
        """The world vector (d,) of :meth:`frame_law`'s ``c`` at qh = [q, 1] (n + 1,)."""
        d = self.G @ qh  # (K, d)
        out = c[:-1] @ d
        return out + c[-1] * np.cross(d[0], d[1]) if c[-1] else out


@dataclass(frozen=True)
class Spring:
    """Linear spring-damper between maps A and B (d, n+1): tension ``k (l - l0) + c l_dot``."""

    name: str
    A: np.ndarray
    B: np.ndarray
    k: float
    c: float
    l0: float


@dataclass(frozen=True)
class JointForce:
    """How a joint's multipliers make the force it applies to its second body.

    ``force = sum_k lambda[rows[k]] * (maps[k] @ [q, 1])``: coincidence rows have a constant
    unit map (lambda is the force component), point-on-line rows the map ``-p_a`` of the
    normal they are written along. rows (r,), maps (r, d, n + 1).
    """

    rows: np.ndarray
    maps: np.ndarray

    def force(self, lam: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Force on the second body (T, d), N, from lambda (T, m_all) and q (T, n)."""
        c = support(self.maps)
        return np.einsum("tk,kan,tn->ta", lam[:, self.rows], self.maps[..., c],
                         at_columns(q, c, 1.0))


def support(*maps: np.ndarray) -> np.ndarray:
    """The columns (of the n + 1 of ``[q, 1]``) where any map (..., n + 1) is non-zero:
    a body's or a joint's few, so that products along samples cost O(1) per element, not
    O(n)."""
    return np.flatnonzero(np.any([np.any(x.reshape(-1, x.shape[-1]) != 0, 0) for x in maps],
                                 0))


def at_columns(q: np.ndarray, cols: np.ndarray, last: float) -> np.ndarray:
    """``[q, last][:, cols]`` (T, len(cols)) of samples q (T, n) without forming [q, last]."""
    out = np.full((len(q), len(cols)), float(last))
    inner = cols < q.shape[1]
    out[:, inner] = q[:, cols[inner]]
    return out


@dataclass(frozen=True)
class Model:
    """A frozen natural-coordinate model.

    Attributes
    ----------
    dim : int                  2 or 3
    n : int                    number of coordinates
    M : (n, n)                 constant mass matrix, kg (kg m^2 on unit-vector coordinates)
    constraints : QuadraticConstraints   m rows
    Q0 : (n,)                  constant generalized forces (gravity, constant forces), N
    q0 : (n,)                  reference configuration (initial guess), m
    elements : dict[str, Element]
    bodies : dict[str, Body]
    rows : dict[str, ndarray]  named groups of constraint rows (joints, rods, ...)
    rod_length : dict[str, float]   length L of each named distance row (axial = 2 L lambda)
    torques : tuple            (body, tau, law): constant torques, N m: world axes (law None)
                               or ``tau`` in the body's frame (law :meth:`Body.frame_law`)
    springs : tuple[Spring, ...]
    joints : dict[str, JointForce]  force each joint applies to its second body
    drivers : tuple[DriverRow, ...]  rheonomic rows, after the m rows in lambda
    body_forces : tuple        (body, C (d, n+1), law): constant forces given in a body's
                               frame (law :meth:`Body.frame_law`) at the point of map C, N
    """

    dim: int
    n: int
    M: np.ndarray
    constraints: QuadraticConstraints
    Q0: np.ndarray
    q0: np.ndarray
    elements: dict[str, Element]
    bodies: dict[str, Body]
    rows: dict[str, np.ndarray]
    rod_length: dict[str, float]
    torques: tuple = ()
    springs: tuple[Spring, ...] = ()
    joints: dict[str, JointForce] = field(default_factory=dict)
    drivers: tuple = ()
    body_forces: tuple = ()

    @property
    def m(self) -> int:
        return self.constraints.m

    def coordinate_names(self) -> list[str]:
        """A name per coordinate (n,): ``element.x|y|z``."""
        names = [f"q[{k}]" for k in range(self.n)]
        for e in self.elements.values():
            for c, ax in zip(e.cols, "xyz", strict=False):
                names[c] = f"{e.name}.{ax}"
        return names

    def forces(self, t: float, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Generalized applied forces Q(t, q, qd): (n,), N (N m on unit-vector coordinates)."""
        Q = self.Q0.copy()
        if not (self.torques or self.springs or self.body_forces):
            return Q
        qh, vh = np.append(q, 1.0), np.append(qd, 0.0)
        for body, tau, law in self.torques:
            b = self.bodies[body]
            Q += _torque_force(b, tau if law is None else b.turned(law, qh), qh)
        for body, C, law in self.body_forces:
            Q += C[:, :-1].T @ self.bodies[body].turned(law, qh)
        if self.springs:  # all at once: a loop over them was most of a stiff run's time
            D, k, c, l0 = self.spring_arrays
            d, dd = D @ qh, D @ vh  # (S, d)
            ln = np.sqrt(np.einsum("sa,sa->s", d, d))
            e = d / ln[:, None]
            tension = k * (ln - l0) + c * np.einsum("sa,sa->s", e, dd)
            Q -= np.einsum("san,sa->n", D[:, :, :-1], tension[:, None] * e)
        return Q

    @cached_property
    def spring_arrays(self) -> tuple[np.ndarray, ...]:
        """The spring-dampers as arrays: D = B - A (S, d, n+1), k (N/m), c (N s/m), l0 (m)
        (S,)."""
        return (np.array([s.B - s.A for s in self.springs], dtype=float),
                *(np.array([getattr(s, f) for s in self.springs], dtype=float)
                  for f in ("k", "c", "l0")))

    def spring_tension(self, q: np.ndarray, qd: np.ndarray) -> dict[str, np.ndarray]:
        """Tension (T,) of every spring-damper, N, from q, qd (T, n)."""
        qh = np.append(q, np.ones((len(q), 1)), 1)
        vh = np.append(qd, np.zeros((len(q), 1)), 1)
        out = {}
        for s in self.springs:
            d, dd = qh @ (s.B - s.A).T, vh @ (s.B - s.A).T
            ln = np.linalg.norm(d, axis=1)
            out[s.name] = s.k * (ln - s.l0) + s.c * np.sum(d * dd, 1) / ln
        return out

    def axial(self, name: str, lam: np.ndarray) -> np.ndarray:
        """Axial force of distance row ``name`` from lambda (..., m): ``2 L lambda``, tension
        positive, N."""
        return 2.0 * self.rod_length[name] * lam[..., self.rows[name][0]]

    def cols(self, name: str) -> np.ndarray:
        return self.elements[name].cols

    def kinetic_energy(self, qd: np.ndarray) -> np.ndarray:
        """1/2 qd^T M qd for qd (..., n), J."""
        return 0.5 * np.einsum("...i,ij,...j->...", qd, self.M, qd)


def _cross_matrix(d: np.ndarray) -> np.ndarray:
    """B (r, dim) with B @ f = d x f (r = 3 in 3-D, 1 in 2-D)."""
    if len(d) == 2:
        return np.array([[-d[1], d[0]]])
    return np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])


def _torque_force(body: Body, tau, qh: np.ndarray) -> np.ndarray:
    """Generalized force (n,) of a torque ``tau`` (world, N m) on a body.

    Forces f_k on the body's difference vectors d_k with sum d_k x f_k = tau (minimum norm):
    a rigid rotation dtheta moves d_k by dtheta x d_k, so the virtual work is dtheta . tau.
    """
    d = body.G @ qh  # (K, dim)
    B = np.hstack([_cross_matrix(dk) for dk in d])
    f = np.linalg.lstsq(B, np.atleast_1d(tau).astype(float), rcond=None)[0]
    return np.einsum("kan,ka->n", body.G[:, :, :-1], f.reshape(len(d), -1))
