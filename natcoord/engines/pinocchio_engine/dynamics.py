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
from numba import njit

from ...errors import Unsupported
from .applied import Applied, is_view
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
        self.applied = Applied(b.loads, b.springs, self.aux)
        self.loaded = self.applied.joints
        self.fext_ = pin.StdVec_Force()  # aba's external forces, rewritten in place
        for _ in range(b.model.njoints):
            self.fext_.append(pin.Force.Zero())
        self.views = ([self.fext_[j].vector for j in self.loaded]  # views into fext_
                      if is_view(lambda: self.fext_[0].vector) else None)
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
        self.pin.forwardKinematics(self.model, self.aux, q, v)
        Fs = self.applied()
        F = np.zeros((self.model.njoints, 6))
        F[self.loaded] = Fs[1:]
        return F, dict(zip(self.applied.names, self.applied.T.tolist(), strict=True))

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
        pin.forwardKinematics(self.model, self.aux, q, v)
        Fs = self.applied()
        if self.views is not None:
            for s, view in enumerate(self.views, 1):
                view[:] = Fs[s]
        else:  # bindings that copy: a new Force per loaded joint
            for s, jid in enumerate(self.loaded, 1):
                self.fext_[jid] = pin.Force(Fs[s])
        return pin.aba(self.model, self.data, q, v, self.zero, self.fext_).copy()

    @property
    def lam(self):
        return self.data.lambda_c if self.looped else np.zeros(0)


@njit(cache=True)
def _rk4_stage(q, Z, s: int, c: float, vec: bool):
    """RK4 stage s + 1 (s = 1, 2, 3) in Z's rows (0 v, 1-3 the stage velocities, 4-7 the
    stage accelerations, 8 the stage position or, when not ``vec``, its increment):
    velocity v + c A_s, position q + c V_s."""
    for i in range(Z.shape[1]):
        Z[s, i] = Z[0, i] + c * Z[3 + s, i]
        Z[8, i] = (q[i] if vec else 0.0) + c * Z[s - 1, i]


@njit(cache=True)
def _rk4_combine(q, Z, dt6: float, vec: bool):
    """The step's new v (row 0) and position (q in place when ``vec``, else its increment
    in row 8) from the four stages, summed in the textbook order."""
    for i in range(Z.shape[1]):
        Z[8, i] = (q[i] if vec else 0.0) + dt6 * (Z[0, i] + 2 * Z[1, i] + 2 * Z[2, i]
                                                  + Z[3, i])
        Z[0, i] = Z[0, i] + dt6 * (Z[4, i] + 2 * Z[5, i] + 2 * Z[6, i] + Z[7, i])
        if vec:
            q[i] = Z[8, i]


def rk4_samples(acc, lam, step, q0, v0, nq: int, nl: int, times, k: int, dt: float,
                context: str = "", dexpinv=None):
    """Classic RK4 from (q0, v0), k steps per sample, ``acc(q, v)`` the acceleration, ``lam()``
    the constraint forces of its last call, ``step(q, dv)`` the position update (None: a
    vector configuration, q + dv): sampled Q (T, nq), V, A (T, nv), L (T, nl) and the step
    count. ``context`` is added to the error's dt. The stage arithmetic is two compiled
    calls (numpy on vectors this short costs ~1 us an operation, 24 a step).

    On a Lie group (``step`` given) the stages are Runge-Kutta-Munthe-Kaas: the position
    is q = step(q_n, u) with u integrated in the tangent at q_n, u' = dexpinv(q_n, u, v)
    (the inverse of step's Jacobian in u applied to v). Taking u' = v, as on a vector
    space, leaves the method second order wherever rotations do not commute (a spherical
    joint: errors fell 4x, not 16x, for half the step)."""
    T, nv = len(times), len(v0)
    Q, V, A, L = (np.empty((T, nq)), np.empty((T, nv)), np.empty((T, nv)), np.empty((T, nl)))
    h, dt6 = dt / 2, dt / 6
    vec = step is None
    q = q0.astype(float)
    Z = np.zeros((9, nv))
    Z[0] = v0
    v, dq = Z[0], Z[8]
    stages = [(s, c, Z[s], Z[4 + s]) for s, c in ((1, h), (2, h), (3, dt))]
    n = 0
    for i in range(T):
        Z[4] = acc(q, v)  # the sample's own state: its lambda gives the reactions
        Q[i], V[i], A[i], L[i] = q, v, Z[4], lam()
        if not (np.isfinite(Z[4]).all() and np.isfinite(L[i]).all()):
            raise RuntimeError(f"pinocchio: non-finite acceleration or constraint force at "
                               f"t = {times[i]:g} s (dt {dt:g} s{context})")
        if i == T - 1:
            break
        for j in range(k):
            if j:
                Z[4] = acc(q, v)
            for s, c, vs, a_s in stages:
                _rk4_stage(q, Z, s, c, vec)
                a_s[:] = acc(dq if vec else step(q, dq), vs)
                if not vec:  # the stage's rate of u: what the next stages and the
                    vs[:] = dexpinv(q, dq, vs)  # step's combination take of it
            _rk4_combine(q, Z, dt6, vec)
            if not vec:
                q = step(q, dq)
            n += 1
    return Q, V, A, L, n


def integrate_rk4(pin, b: Built, dyn: Dynamics, times, k: int, dt: float, context: str = ""):
    """Classic RK4, k steps of dt (s) per sample: sampled (Q, V, A, L) and step count."""
    model = b.model
    lie = model.nq != model.nv
    step = (lambda q, dv: pin.integrate(model, q, dv)) if lie else None

    def dexpinv(q, u, v):  # u' from v: step's Jacobian in its increment, inverted
        return np.linalg.solve(pin.dIntegrate(model, q, u, pin.ArgumentPosition.ARG1), v)

    return rk4_samples(dyn, lambda: dyn.lam, step, b.q0, b.v0, model.nq,
                       3 * len(dyn.cmodels), times, k, dt, context, dexpinv)


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
