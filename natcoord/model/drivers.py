"""Drivers (prescribed motions) as rheonomic constraints, and the full constraint system.

Every driver row is linear in q with time-dependent coefficients over ``qh = [q, 1]``:

    Phi_d(q, t) = a(t) @ qh,   Phi_q = a(t)[:n],   Phi_t = a'(t) @ qh,   Phi_tt = a''(t) @ qh

so that the acceleration right-hand side of a driver row is
``c = -(2 a'(t)[:n] @ qd + a''(t) @ qh)`` (the quadratic part is zero).

* angle driver (2-D) of a rigid body with a difference vector d (a map over qh, e.g.
  r_j - r_i of two of its points) and a world angle th(t) = value(t) + angle of d in the body
  frame: ``cross(e(th), d) = 0`` with ``e = (cos th, sin th)``. Its row never vanishes, so
  it holds through any angle. The torque it applies to the body is ``-lambda (e . d)``
  (N m).
* coordinate driver: a world coordinate of a body point equals value(t); its effort is
  ``-lambda`` (N along the axis).

:class:`ConstraintSystem` appends the driver rows after the model's ``m`` constraint rows,
so joint rows keep their indices in lambda.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constraints import QuadraticConstraints


@dataclass(frozen=True)
class DriverRow:
    """One rheonomic row; value(t) = v0 + rate t + accel t^2 / 2.

    ``kind`` "angle": ``C`` (2, n + 1) the map of the body's difference vector d, ``offset``
    the angle of d in the body frame (rad); "coordinate": ``C`` (n + 1,) the affine map of
    the driven world coordinate.
    """

    name: str
    kind: str
    v0: float
    rate: float
    accel: float
    C: np.ndarray
    offset: float = 0.0

    def law(self, t: float) -> tuple[float, float, float]:
        """(value, first, second derivative) of the prescribed motion at t."""
        return (self.v0 + self.rate * t + 0.5 * self.accel * t * t, self.rate + self.accel * t,
                self.accel)

    def coefficients(self, n: int, t: float | np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """a(t), a'(t), a''(t): (n + 1,) each at a time t, or (T, n + 1) at times t (T,)."""
        t = np.asarray(t, float)
        v, vd, vdd = (np.broadcast_to(x, t.shape)[..., None] for x in self.law(t))
        if self.kind == "angle":
            th = v + self.offset
            c, s = np.cos(th), np.sin(th)
            g = np.concatenate([-s, c], -1)           # cross(e, d) = g @ d
            gd = vd * np.concatenate([-c, -s], -1)    # dg/dt
            gdd = vdd * np.concatenate([-c, -s], -1) + vd * vd * np.concatenate([s, -c], -1)
            return g @ self.C, gd @ self.C, gdd @ self.C
        a = np.broadcast_to(self.C, t.shape + (n + 1,)).copy()
        ad, add = np.zeros_like(a), np.zeros_like(a)
        a[..., n:] -= v
        ad[..., n:], add[..., n:] = -vd, -vdd
        return a, ad, add

    def effort(self, lam: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Driving torque (N m) or force (N) from its multiplier lam (T,), q (T, n), t (T,)."""
        if self.kind == "angle":
            th = self.v0 + self.rate * t + 0.5 * self.accel * t * t + self.offset
            d = np.append(q, np.ones((len(q), 1)), axis=1) @ self.C.T
            return -lam * (np.cos(th) * d[:, 0] + np.sin(th) * d[:, 1])
        return -lam


class ConstraintSystem:
    """Scleronomic constraints (m rows) followed by driver rows (k rows): m_all = m + k.

    Works with any model exposing ``n``, ``constraints`` and optionally ``drivers``.
    """

    def __init__(self, model):
        self.n = model.n
        self.con: QuadraticConstraints = model.constraints
        self.drivers: tuple[DriverRow, ...] = tuple(getattr(model, "drivers", ()) or ())
        self.m0 = self.con.m
        self.k = len(self.drivers)
        self.m = self.m0 + self.k
        self.rheonomic = self.k > 0
        self.labels = tuple(self.con.labels) + tuple(f"driver {d.name}" for d in self.drivers)

    def _coef(self, t: float):
        """a, a', a'' of every driver row: (k, n + 1) each at a time t, (T, k, n + 1) at
        times t (T,)."""
        rows = [d.coefficients(self.n, t) for d in self.drivers]
        return tuple(np.stack([r[i] for r in rows], -2) for i in range(3))

    def phi(self, q: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Phi(q, t): (m_all,)."""
        p = self.con.phi(q)
        if not self.k:
            return p
        A, _, _ = self._coef(t)
        return np.concatenate([p, A @ np.append(q, 1.0)])

    def jacobian(self, q: np.ndarray, t: float | np.ndarray = 0.0) -> np.ndarray:
        """Phi_q: (m_all, n) at q (n,) and time t, or (T, m_all, n) at samples q (T, n),
        t (T,)."""
        J = self.con.jacobian(q)
        if not self.k:
            return J
        A, _, _ = self._coef(t)
        return np.concatenate([J, A[..., :-1]], -2)

    def phi_t(self, q: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Phi_t: (m_all,), zero on scleronomic rows; velocity constraint Phi_q qd = -Phi_t."""
        out = np.zeros(self.m)
        if self.k:
            _, Ad, _ = self._coef(t)
            out[self.m0:] = Ad @ np.append(q, 1.0)
        return out

    def gamma(self, q: np.ndarray, qd: np.ndarray, t: float = 0.0) -> np.ndarray:
        """c = -(Phi_q qd)_q qd - 2 Phi_qt qd - Phi_tt: (m_all,), with Phi_q qdd = c."""
        c = -self.con.quad_velocity(qd)
        if not self.k:
            return c
        _, Ad, Add = self._coef(t)
        cd = -(2.0 * Ad[:, :-1] @ qd + Add @ np.append(q, 1.0))
        return np.concatenate([c, cd])

    def drift(self, q: np.ndarray, qd: np.ndarray, t: np.ndarray) -> tuple[float, float]:
        """(max |Phi|, max |Phi_q qd + Phi_t|) over samples q, qd (T, n) at times t (T,)."""
        if not len(t):
            return 0.0, 0.0
        p, J = self.con.phi(q), self.con.jacobian(q)
        v = np.einsum("tmn,tn->tm", J, qd)
        if self.k:
            A, Ad, _ = self._coef(np.asarray(t, float))
            qh = np.concatenate([q, np.ones((len(q), 1))], 1)
            p = np.concatenate([p, np.einsum("tkn,tn->tk", A, qh)], 1)
            v = np.concatenate([v, np.einsum("tkn,tn->tk", A[..., :-1], qd)
                                + np.einsum("tkn,tn->tk", Ad, qh)], 1)
        return float(np.max(np.abs(p), initial=0.0)), float(np.max(np.abs(v), initial=0.0))

    def all(self, q: np.ndarray, qd: np.ndarray, t: float = 0.0):
        """(Phi, Phi_q, Phi_t, c) in one pass (the driver coefficients evaluated once)."""
        con = self.con
        p, J, c = con.phi(q), con.jacobian(q), -con.quad_velocity(qd)
        pt = np.zeros(self.m)
        if self.k:
            A, Ad, Add = self._coef(t)
            qh = np.append(q, 1.0)
            p = np.concatenate([p, A @ qh])
            J = np.vstack([J, A[:, :-1]])
            pt[self.m0:] = Ad @ qh
            c = np.concatenate([c, -(2.0 * Ad[:, :-1] @ qd + Add @ qh)])
        return p, J, pt, c
