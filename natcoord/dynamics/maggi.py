"""Maggi / R-method, Eq. (23): independent coordinates from Gaussian elimination with full
pivoting of Phi_q, Eqs. (13)-(15); dependent positions by Newton; re-partitioned when the
dependent block degrades. Its options (:class:`Maggi`), its Python loop
(:class:`MaggiLoop`) and its compiled loop (:mod:`natcoord.compiled.maggi`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import StepFailure
from .common import FormulationLoop, Prepared, _alpha, full_pivot_partition
from .options import Formulation, _flag, _positive


@dataclass(frozen=True)
class Maggi(Formulation):
    """Maggi's null-space equations; re-partition when max|R^d| grows by this factor.
    ``generated``: the compiled loop takes Phi and the accelerations from index-1's kernels
    written out for the model (:func:`natcoord.compiled.maggi.generated`) when it allows,
    else (or False) the generic kernels with Eq. (23)."""

    name: ClassVar[str] = "maggi"
    repartition_growth: float = 1.5
    generated: bool = True

    def __post_init__(self):
        super().__post_init__()
        _positive("Maggi", "repartition_growth", self.repartition_growth)
        _flag("Maggi", "generated", self.generated)


class MaggiLoop(FormulationLoop):
    """Eq. (23) as an ODE in y = [q^i, qd^i] (2f), R from coordinate partitioning.

    With dop853 or dopri5 (adaptive), rk4 or dopri5 (fixed step) the whole run is one numba
    loop when the model allows (:mod:`natcoord.compiled.maggi`: the same steps, Newton and
    re-partitions as this class and :func:`natcoord.dynamics.integrators.time_loop`)."""

    options = Maggi

    name = "maggi"
    methods = Maggi.methods
    compiled_path = "maggi"

    def init(self, t, q, qd):
        self.q = np.array(q, dtype=float)
        self._partition(t, self.q)
        return np.concatenate([q[self.indep], qd[self.indep]])

    def compiled_candidate(self, method: str, h) -> bool:
        """Whether the compiled loop (:mod:`natcoord.compiled.maggi`) may run: adaptive
        dop853 or dopri5, fixed-step rk4 or dopri5, scleronomic constraints, forces
        :func:`compiled_forces` knows."""
        from ..compiled import index1 as kernels
        return self._compiled_model(
            method in (kernels.ADAPTIVE if h is None else kernels.FIXED_STEP))

    def _eliminates(self) -> bool:
        """The compiled loop runs on :attr:`elimination`'s coordinates on its generated path
        only (:meth:`prepare_compiled`)."""
        return bool(self.opt["generated"])

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        """Model-only set-up: the constraint triplets and M's non-zeros packed for the
        compiled loop (:func:`natcoord.compiled.maggi.pack`), and index-1's generated
        kernels, which give Phi and the accelerations there
        (:func:`natcoord.compiled.maggi.generated`; None: the generic kernels). Where the
        constant linear rows fix coordinates and leave M_r regular (:attr:`elimination`,
        as index-1's compiled loop), the generated path runs on the coordinates kept, with
        index-1's kernels of that model: the same motion (the linear rows hold
        identically there), a quarter to a half of the work per evaluation on the
        catalogue's planar mechanisms. Else on the model's coordinates (a singular M's
        alpha from M and Phi_q at ``q0``)."""
        from ..compiled import maggi as kernels_maggi
        e, self._gen = self.elimination, None
        self._red = None
        if e is not None and e.regular:
            self._gen = kernels_maggi.generated(e.con, e.M, e.frc)
            if self._gen is not None:
                self._red = e
                self._packed = kernels_maggi.pack(e.con, e.M)
        if self._red is None:
            self._packed = kernels_maggi.pack(self.cs.con, self.M)
            q0 = None if q0 is None else np.asarray(q0, float)
            self._gen = kernels_maggi.generated(self.cs.con, self.M, self._frc, _alpha(
                self.cs.con, self.M, q0)) if self.opt["generated"] else None
        return Prepared(self.compiled_path, self._frc)

    def compiled_runner(self, times, t0, q0, qd0, method, rtol, atol, h=None):
        """``go(Q, QD, QDD)`` (:meth:`FormulationLoop.compiled_runner`); on the coordinates
        an elimination keeps (:meth:`prepare_compiled`), y = [q^i, qd^i] from the
        partition of their Jacobian at q0, every sample written back to all coordinates
        (q = T q_r + b)."""
        if not hasattr(self, "_packed"):
            self.prepare_compiled(q0)
        e = self._red
        if e is None:
            return super().compiled_runner(times, t0, q0, qd0, method, rtol, atol, h)
        from ..compiled import index1 as kernels
        from ..compiled import maggi as kernels_maggi
        y, qr, part = self.compiled_start(t0, q0, qd0)
        steps = self._steps(rtol, atol, h)

        def go(Q, QD, QDD):
            X = kernels_maggi.run(self._packed, e.frc, times, y, qr, part, method, steps,
                                  self.cnt, self._gen)
            kernels.expand(e.dep_map, *X, Q, QD, QDD)
        return go

    def compiled_start(self, t0, q0, qd0) -> tuple:
        """(y (2f), q (n_loop,), partition (rows, dep, indep)): the compiled loop's start
        from a consistent (q0, qd0) (n,), on its coordinates (after
        :meth:`prepare_compiled`: the model's, or those an elimination keeps)."""
        e = self._red
        if e is None:
            y = self.init(t0, q0, qd0)
            return y, self.q, (self.rows, self.dep, self.indep)
        qr, qdr = np.asarray(q0, float)[e.keep], np.asarray(qd0, float)[e.keep]
        part = full_pivot_partition(e.con.jacobian(qr), self.opt["rank_tol"])[:3]
        self.cnt.factorizations += 1
        return np.concatenate([qr[part[2]], qdr[part[2]]]), qr, part

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.compiled.maggi.run` from ``init``'s y = [q^i,
        qd^i] (2f), its q (n,) and partition: (Q, QD, QDD) (T, n) at ``times`` (T,) s, the
        same steps as the Python loop (on the model's coordinates: with an elimination,
        :meth:`compiled_runner`)."""
        from ..compiled import maggi as kernels_maggi
        if not hasattr(self, "_packed"):
            self.prepare_compiled()
        return kernels_maggi.run(self._packed, self._frc, times, y, self.q,
                                 (self.rows, self.dep, self.indep), method,
                                 self._steps(rtol, atol, h), self.cnt, self._gen)

    def _steps(self, rtol, atol, h):
        from ..compiled import maggi as kernels_maggi
        return kernels_maggi.Steps(rtol, atol, h, self.opt["newton_tol"], self.opt["rank_tol"],
                                   self.opt["repartition_growth"])

    def _partition(self, t, q):
        J = self.cs.jacobian(q, t)
        self.rows, self.dep, self.indep, _ = full_pivot_partition(J, self.opt["rank_tol"])
        self.f = len(self.indep)
        self.cnt.factorizations += 1
        self.R0 = self.R_last = None

    def _positions(self, t, qi):
        """Dependent coordinates by Newton on the independent rows: q (n,), started from
        the last solution moved along R and the rheonomic velocity S b (steps may be long).

        Raises StepFailure when Newton diverges: the step was too long.
        """
        q = self.q.copy()
        if self.R_last is not None:  # None right after a (re-)partition
            q += self.R_last @ (qi - q[self.indep]) + (t - self.tq) * self.sb
        q[self.indep] = qi
        cs, rows, dep, tol = self.cs, self.rows, self.dep, self.opt["newton_tol"]
        size = max(float(np.ptp(self.q)), 1e-300)
        for _ in range(20):
            p = cs.phi(q, t)[rows]
            if np.max(np.abs(p), initial=0.0) < tol:
                break
            J = cs.jacobian(q, t)
            dq = np.linalg.solve(J[np.ix_(rows, dep)], p)
            q[dep] -= dq
            self.cnt.newton += 1
            self.cnt.factorizations += 1
            if np.max(np.abs(dq)) < tol * 10 * max(1.0, size):  # round-off reached
                break
        else:
            raise StepFailure(f"maggi: position Newton did not converge at t = {t:.6g} s "
                              f"(max |Phi| = {np.max(np.abs(p)):.3g})")
        self.q = q
        return q

    def _kinematics(self, t, y):
        """(q, qd, R (n, f), Sc (n,), Rd) at the integrated independent state."""
        f, n = self.f, self.n
        q = self._positions(t, y[:f])
        p, J, pt, _ = self.cs.all(q, np.zeros(n), t)
        Jr = J[self.rows]
        Jd_inv = np.linalg.inv(Jr[:, self.dep])
        self.cnt.factorizations += 1
        Rd = -Jd_inv @ Jr[:, self.indep]
        R = np.zeros((n, f))
        R[self.dep], R[self.indep] = Rd, np.eye(f)
        qd = R @ y[f:]
        sb = np.zeros(n)
        sb[self.dep] = Jd_inv @ (-pt[self.rows])  # S b, Eq. (20)
        qd += sb
        self.R_last, self.sb, self.tq = R, sb, t  # the next Newton's predictor
        c = self.cs.gamma(q, qd, t)[self.rows]
        Sc = np.zeros(n)
        Sc[self.dep] = Jd_inv @ c  # Eq. (22) with qdd^i = 0
        return q, qd, R, Sc, Rd

    def rhs(self, t, y):
        q, qd, R, Sc, _ = self._kinematics(t, y)
        qdd_i = self._indep_acc(t, q, qd, R, Sc)
        return np.concatenate([y[self.f:], qdd_i])

    def _indep_acc(self, t, q, qd, R, Sc):
        self.cnt.rhs += 1
        self.cnt.factorizations += 1
        if self.f == 0:
            return np.zeros(0)
        F = self.model.forces(t, q, qd)
        A3 = R.T @ self.M @ R
        return np.linalg.solve(A3, R.T @ (F - self.M @ Sc))  # Eq. (23)

    def state(self, t, y):
        q, qd, *_ = self._kinematics(t, y)
        return q, qd

    def accelerations(self, t, q, qd):
        y = np.concatenate([q[self.indep], qd[self.indep]])
        self.q = q.copy()
        q, qd, R, Sc, _ = self._kinematics(t, y)
        return Sc + R @ self._indep_acc(t, q, qd, R, Sc)

    def post_step(self, t, y):
        """Re-partition when the dependent block Phi_q^d degrades (max |R^d| grows)."""
        q, qd, _, _, Rd = self._kinematics(t, y)
        g = float(np.max(np.abs(Rd), initial=0.0))
        if self.R0 is None:
            self.R0 = max(g, 1.0)
            return y
        if g > self.opt["repartition_growth"] * self.R0:
            self._partition(t, q)
            self.cnt.repartitions += 1
            return np.concatenate([q[self.indep], qd[self.indep]])
        return y


Maggi.loop = MaggiLoop
