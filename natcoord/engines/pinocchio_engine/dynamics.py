"""Accelerations of a built model, and the integrators (ours: Pinocchio only evaluates).

* Loops: ``constraintDynamics`` (proximal); applied loads and springs enter as
  ``tau = J^T f`` (it takes no external forces). No loops: ``aba`` with external forces.
* Spring-damper: a pair of opposite external forces along the line of its ends; its
  tension is reported as its axial force.
* Classic RK4 on (q, v) (``pinocchio.integrate`` when nq != nv: spherical or planar
  joints), or scipy's Radau IIA (``method = "radau"``, unconstrained, vector state).
"""

from __future__ import annotations

import numpy as np

from ...errors import Unsupported
from ..planar import cross
from .model import Built


class Dynamics:
    """Accelerations (nv,) of a :class:`Built` model at (q, v), counting proximal
    iterations; ``lam`` the constraint forces (3 per loop) of the last call."""

    def __init__(self, pin, b: Built, cmodels, s: dict):
        self.pin, self.b, self.cmodels = pin, b, cmodels
        self.model = b.model
        self.data = b.model.createData()
        self.aux = b.model.createData()  # kinematics for loads and springs
        self.cdatas = pin.StdVec_RigidConstraintData()
        for cm in cmodels:
            self.cdatas.append(cm.createData())
        self.looped = len(cmodels) > 0
        if self.looped:
            pin.initConstraintDynamics(self.model, self.data, cmodels, self.cdatas)
        self.prox = pin.ProximalSettings(float(s["accuracy"]), float(s["mu"]),
                                         int(s["max_iter"]))
        self.iters = 0
        self.zero = np.zeros(b.model.nv)
        self.loaded = sorted({x[0] for x in b.loads} | {e[0] for sp in b.springs
                                                         for e in sp[1:3]} - {0})
        groups = {}
        for name, (ja, pa), (jb, pb), k, c, l0 in b.springs:
            groups.setdefault((ja, jb), []).append((name, pa, pb, k, c, l0))
        self.groups = [(ja, jb, np.array([x[1] for x in g]), np.array([x[2] for x in g]),
                        *(np.array([x[i] for x in g]) for i in (3, 4, 5)),
                        [x[0] for x in g]) for (ja, jb), g in groups.items()]
        self.const_tau = None
        if not self.loaded:
            self.const_tau = self.zero
        elif b.one_axis and not b.springs and all(not x[2].any() and not x[4]
                                                  for x in b.loads):
            # pure moments, every rotation about one fixed direction: J^T f is constant
            self.const_tau = self.tau(b.q0, b.v0)

    def fext(self, q, v):
        """Applied loads and spring forces as Pinocchio external forces, (njoints, 6) in
        joint frames (linear, angular), and the spring tensions (name -> N)."""
        pin, data = self.pin, self.aux
        pin.forwardKinematics(self.model, data, q, v)
        F = np.zeros((self.model.njoints, 6))
        frames = {}
        for jid in self.loaded:
            M, vel = data.oMi[jid], data.v[jid]
            frames[jid] = (M.rotation, M.translation, vel.linear, vel.angular)
        for jid, p, fw, mw, local in self.b.loads:
            R = frames[jid][0]
            fl, ml = (fw, mw) if local else (R.T @ fw, R.T @ mw)
            F[jid, :3] += fl
            F[jid, 3:] += cross(p, fl) + ml
        tension = {}
        for ja, jb, Pa, Pb, k, c, l0, names in self.groups:  # vectorized per joint pair
            ra, va = self._ends(frames, ja, Pa)
            rb, vb = self._ends(frames, jb, Pb)
            d = rb - ra
            ln = np.sqrt(np.einsum("ij,ij->i", d, d))
            e = d / ln[:, None]
            T = k * (ln - l0) + c * np.einsum("ij,ij->i", vb - va, e)
            tension.update(zip(names, T, strict=True))
            for jid, P, sgn in ((ja, Pa, 1.0), (jb, Pb, -1.0)):
                if jid:
                    fl = (sgn * T[:, None] * e) @ frames[jid][0]  # rows R^T f
                    F[jid, :3] += fl.sum(0)
                    F[jid, 3:] += cross(P.T, fl.T).sum(1)
        return F, tension

    @staticmethod
    def _ends(frames, jid, P):
        """World positions and velocities (n, 3) of points P (n, 3) of joint jid."""
        if jid == 0:
            return P, 0.0
        R, tr, vl, w = frames[jid]
        return P @ R.T + tr, (vl[:, None] + cross(w[:, None], P.T)).T @ R.T

    def tau(self, q, v):
        """Generalized applied forces J^T f, (nv,)."""
        if self.const_tau is not None:
            return self.const_tau
        f, _ = self.fext(q, v)
        pin = self.pin
        pin.computeJointJacobians(self.model, self.aux, q)
        tau = np.zeros(self.model.nv)
        for jid in self.loaded:
            J = pin.getJointJacobian(self.model, self.aux, jid, pin.ReferenceFrame.LOCAL)
            tau += J.T @ f[jid]
        return tau

    def __call__(self, q, v):
        pin = self.pin
        if self.looped:
            a = pin.constraintDynamics(self.model, self.data, q, v, self.tau(q, v),
                                       self.cmodels, self.cdatas, self.prox)
            self.iters = max(self.iters, self.prox.iter)
            return a.copy()
        if not self.loaded:
            return pin.aba(self.model, self.data, q, v, self.zero).copy()
        f, _ = self.fext(q, v)
        fext = pin.StdVec_Force()
        for x in f:
            fext.append(pin.Force(x))
        return pin.aba(self.model, self.data, q, v, self.zero, fext).copy()

    @property
    def lam(self):
        return self.data.lambda_c if self.looped else np.zeros(0)


def rk4_samples(acc, lam, step, q0, v0, nq: int, nl: int, times, k: int, dt: float,
                context: str = ""):
    """Classic RK4 from (q0, v0), k steps per sample, ``acc(q, v)`` the acceleration, ``lam()``
    the constraint forces of its last call, ``step(q, dv)`` the position update: sampled
    Q (T, nq), V, A (T, nv), L (T, nl) and the step count. ``context`` is added to the
    error's dt."""
    T, nv = len(times), len(v0)
    Q, V, A, L = (np.empty((T, nq)), np.empty((T, nv)), np.empty((T, nv)), np.empty((T, nl)))
    h, dt6 = dt / 2, dt / 6
    q, v = q0.copy(), v0.copy()
    n = 0
    for i in range(T):
        a1 = acc(q, v)  # the sample's own state: its lambda gives the reactions
        Q[i], V[i], A[i], L[i] = q, v, a1, lam()
        if not (np.isfinite(a1).all() and np.isfinite(L[i]).all()):
            raise RuntimeError(f"pinocchio: non-finite acceleration or constraint force at "
                               f"t = {times[i]:g} s (dt {dt:g} s{context})")
        if i == T - 1:
            break
        for j in range(k):
            if j:
                a1 = acc(q, v)
            v2 = v + h * a1
            a2 = acc(step(q, h * v), v2)
            v3_ = v + h * a2
            a3 = acc(step(q, h * v2), v3_)
            v4 = v + dt * a3
            a4 = acc(step(q, dt * v3_), v4)
            q = step(q, dt6 * (v + 2 * v2 + 2 * v3_ + v4))
            v = v + dt6 * (a1 + 2 * a2 + 2 * a3 + a4)
            n += 1
    return Q, V, A, L, n


def integrate_rk4(pin, b: Built, dyn: Dynamics, times, k: int, dt: float, context: str = ""):
    """Classic RK4, k steps of dt (s) per sample: sampled (Q, V, A, L) and step count."""
    model = b.model
    lie = model.nq != model.nv
    step = (lambda q, dv: pin.integrate(model, q, dv)) if lie else (lambda q, dv: q + dv)
    return rk4_samples(dyn, lambda: dyn.lam, step, b.q0, b.v0, model.nq,
                       3 * len(dyn.cmodels), times, k, dt, context)


def integrate_radau(b: Built, dyn: Dynamics, times, s: dict):
    """Implicit Radau IIA (scipy, adaptive) for stiff spring-dampers, sampled by its dense
    output: (Q, V, A, L, steps, counters). Needs a vector configuration (nq == nv)."""
    from scipy.integrate import Radau

    nv = b.model.nv
    if b.model.nq != nv:
        raise Unsupported("Radau needs a vector configuration (a spherical or planar joint "
                          "has a unit complex or quaternion)")

    def rhs(t, y):
        return np.concatenate([y[nv:], dyn(y[:nv], y[nv:])])

    T = len(times)
    Y = np.empty((T, 2 * nv))
    Y[0] = np.r_[b.q0, b.v0]
    solver = Radau(rhs, times[0], Y[0], times[-1], rtol=float(s["rtol"]),
                   atol=float(s["atol"]))
    i, n = 1, 0
    while i < T:
        msg = solver.step()
        n += 1
        if solver.status == "failed" or not np.isfinite(solver.y).all():
            raise RuntimeError(f"pinocchio: Radau failed at t = {solver.t:g} s: {msg}")
        dense = solver.dense_output()
        while i < T and times[i] <= solver.t + 1e-12:
            Y[i] = dense(times[i])
            i += 1
    Q, V = Y[:, :nv], Y[:, nv:]
    A = np.array([dyn(q, v) for q, v in zip(Q, V, strict=True)])
    counters = {"rhs": solver.nfev, "jacobians": solver.njev, "lu": solver.nlu}
    return Q, V, A, np.zeros((T, 0)), n, counters
