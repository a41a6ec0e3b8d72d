"""Index-3: the augmented Lagrangian with the trapezoidal rule and mass-orthogonal
projections of velocities and accelerations (Bayo & Ledesma, 1996); it steps itself
(integrator ``trapezoidal``). Its options (:class:`Index3`), its Python loop
(:class:`Index3Loop`) and its compiled loop (:mod:`natcoord.compiled.index3`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .common import FormulationLoop, multipliers
from .index1 import Index1Loop
from .options import Formulation, _positive


@dataclass(frozen=True)
class Index3(Formulation):
    """Index-3 augmented Lagrangian; ``penalty`` alpha h^2/4 relative to max|M| (1e6 and
    above leave a round-off floor in lambda; Newton failures retry with it x100)."""

    name: ClassVar[str] = "index3"
    methods: ClassVar[tuple[str, ...]] = ("trapezoidal",)
    default_method: ClassVar[str] = "trapezoidal"
    penalty: float = 1e4

    def __post_init__(self):
        super().__post_init__()
        _positive("Index3", "penalty", self.penalty)


class Index3Loop(FormulationLoop):
    """Index-3 augmented Lagrangian, trapezoidal rule, mass-orthogonal projections.

    y = [q, qd, qdd, lambda*] (3n + m). Per step: Newton on
    ``M (q - qhat) + h^2/4 (Phi_q^T (lambda* + alpha Phi) - F) = 0`` (its tangent with the
    forces' stiffness and damping, :meth:`_force_tangent`) with lambda* updated
    by ``alpha Phi`` after every iteration, then qd and qdd projected onto
    ``Phi_q qd = -Phi_t`` and ``Phi_q qdd = c`` in the metric of M (Bayo & Ledesma).
    The whole run is one numba loop when the model allows (:mod:`natcoord.compiled.index3`,
    the same steps).
    """

    options = Index3

    name = "index3"
    ode = False
    methods = Index3.methods
    compiled_path = "index3"

    def init(self, t, q, qd):
        i1 = Index1Loop(self.model, {**self.opt, "linsolve": "qr"}, self.cnt)
        qdd = i1.accelerations(t, q, qd)
        lam = multipliers(self.model, self.cs, t, q, qd, qdd)
        self.mscale = float(np.max(np.abs(np.diag(self.M))))
        self._last_qdd = qdd
        from ..compiled.index3 import force_tangent  # (numba: imported when a loop runs)
        self._Kt = force_tangent(self._frc, self.n)
        return np.concatenate([q, qd, qdd, lam])

    def _force_tangent(self, t, q, qd, h, F):
        """K (n, n) = dF/dq + 2/h dF/dqd along the trapezoidal rule's qd(q) (the applied
        forces' stiffness and damping in the Newton tangent): the constant part and the
        columns by forward differences (relative step ``FD_STEP``, counted as evaluations)
        of :func:`natcoord.compiled.index3.force_tangent`; 0 for constant forces."""
        if self._Kt is None:
            return 0.0
        from ..compiled.index3 import FD_STEP
        K0, cols = self._Kt
        K = K0.copy()
        for a in cols:
            e = FD_STEP * max(1.0, abs(q[a]))
            dq = np.zeros(self.n)
            dq[a] = e
            K[:, a] = (self.model.forces(t, q + dq, qd + 2.0 / h * dq) - F) / e
        self.cnt.rhs += len(cols)
        return K

    def _split(self, y):
        n = self.n
        return y[:n], y[n:2 * n], y[2 * n:3 * n], y[3 * n:]

    def state(self, t, y):
        q, qd, _, _ = self._split(y)
        return q, qd

    def accelerations(self, t, q, qd):
        return self._last_qdd

    def compiled_candidate(self, method: str, h) -> bool:
        """Whether the compiled loop (:mod:`natcoord.compiled.index3`) may run: the
        trapezoidal rule, scleronomic constraints, forces :func:`compiled_forces` knows."""
        return self._compiled_model(method == "trapezoidal" and h is not None)

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.compiled.index3.run`: (Q, QD, QDD) (T, n) at
        ``times``, the same steps as :meth:`step`."""
        from ..compiled import index3 as kernels_index3
        steps = kernels_index3.Steps(h, self.opt["penalty"], self.mscale,
                                     self.opt["newton_tol"], self.opt["project_tol"])
        return kernels_index3.run(self.cs.con, self._frc, self.M, times, y, steps, self.cnt)

    def step(self, t, y, h):
        """One trapezoidal step. When Newton fails (near a singular position, where the
        multipliers grow without bound) the step is retried with the penalty x100, up to
        1e10 x max|M|; counted in ``rejected``."""
        q0, qd0, qdd0, _ = self._split(y)
        t1, cs = t + h, self.cs
        from ..compiled.index3 import PENALTY_MAX
        penalty = self.opt["penalty"]
        while True:
            beta = penalty * self.mscale  # alpha h^2 / 4
            qhat = q0 + h * qd0 + 0.25 * h * h * qdd0
            res = self._newton(t1, y, h, qhat, beta)
            if res is not None:
                break
            if penalty >= PENALTY_MAX:
                raise RuntimeError(f"index3: Newton did not converge at t = {t1:.6g} s")
            penalty *= 100.0
            self.cnt.rejected += 1
        q, lam = res
        qdd = 4.0 / (h * h) * (q - qhat)
        qd = qd0 + 0.5 * h * (qdd0 + qdd)
        self._drift(t1, q, qd)
        J = cs.jacobian(q, t1)
        Pinv = np.linalg.inv(self.M + beta * (J.T @ J))
        self.cnt.factorizations += 1
        qd = self._mproject(Pinv, J, beta, qd, -cs.phi_t(q, t1))
        qdd = self._mproject(Pinv, J, beta, qdd, cs.gamma(q, qd, t1))
        self.cnt.projections += 1
        self._last_qdd = qdd
        return np.concatenate([q, qd, qdd, lam])

    def _newton(self, t1, y, h, qhat, beta):
        """Newton on the augmented-Lagrangian step: (q, lambda*) or None when it fails."""
        q0, qd0, qdd0, lam = self._split(y)
        lam = lam.copy()
        alpha = 4.0 * beta / (h * h)
        q = q0 + h * qd0 + 0.5 * h * h * qdd0
        cs, con, n = self.cs, self.cs.con, self.n
        sel = (con.i < n) & (con.j < n)
        for _ in range(30):
            qdd = 4.0 / (h * h) * (q - qhat)
            qd = qd0 + 0.5 * h * (qdd0 + qdd)
            p, J = cs.phi(q, t1), cs.jacobian(q, t1)
            F = self.model.forces(t1, q, qd)
            self.cnt.rhs += 1
            mu = lam + alpha * p
            g = self.M @ (q - qhat) + 0.25 * h * h * (J.T @ mu - F)
            H = np.zeros(n * n)  # sum_k mu_k d2Phi_k/dq2 from the triplets
            np.add.at(H, con.i[sel] * n + con.j[sel], mu[con.k[sel]] * con.v[sel])
            Tg = self.M + beta * (J.T @ J) + 0.25 * h * h * (
                H.reshape(n, n) - self._force_tangent(t1, q, qd, h, F))
            dq = np.linalg.solve(Tg, -g)
            self.cnt.factorizations += 1
            self.cnt.newton += 1
            q = q + dq
            lam = lam + alpha * cs.phi(q, t1)
            if not np.all(np.isfinite(q)):
                return None
            if np.max(np.abs(dq)) < self.opt["newton_tol"] * 10 * max(1.0, np.max(np.abs(q))):
                return q, lam
        return None

    def _mproject(self, Pinv, J, beta, x, b):
        """argmin (x' - x)^T M (x' - x) subject to J x' = b, by augmented-Lagrangian sweeps
        (M + beta J^T J) x' = M x + J^T (beta b - sigma) that reuse one factorization."""
        Mx, sigma = self.M @ x, np.zeros(len(b))
        for _ in range(20):
            x = Pinv @ (Mx + J.T @ (beta * b - sigma))
            res = J @ x - b
            if np.max(np.abs(res), initial=0.0) < self.opt["project_tol"]:
                break
            sigma = sigma + beta * res
        return x


Index3.loop = Index3Loop
