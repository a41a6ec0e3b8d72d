"""Index-1: the Lagrange equations with the acceleration constraints, Eq. (6), as an ODE in
y = [q, qd]. Solved through the Schur complement ``Phi_q M^-1 Phi_q^T`` with the constant
M^-1 when M is regular and Phi_q has full rank, otherwise through a rank-revealing (pivoted)
QR of Phi_q^T, which is the null-space form of Eq. (6) and holds for redundant constraints
and a singular M. Drift: projection after every step or Baumgarte. Its options
(:class:`Index1`), its Python loop (:class:`Index1Loop`) and, through
:meth:`Index1Loop.run_compiled`, its compiled loop (:mod:`natcoord.compiled.index1`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.linalg

from .common import FormulationLoop, Prepared, _alpha
from .options import Formulation, _choice, _flag, _positive


@dataclass(frozen=True)
class Index1(Formulation):
    """Index-1 Lagrange equations. ``baumgarte`` (alpha, beta) 1/s; compiled with
    projection and dop853, dopri5 or rk4; ``generated``: on its Schur path, with kernels
    written out for the model (:mod:`natcoord.compiled.codegen`) when it allows, else the generic
    sparse kernels."""

    name: ClassVar[str] = "index1"
    stabilization: str = "projection"
    baumgarte: tuple[float, float] = (10.0, 10.0)
    linsolve: str = "auto"
    generated: bool = True

    def __post_init__(self):
        super().__post_init__()
        _choice("Index1", "stabilization", self.stabilization, ("projection", "baumgarte",
                                                                 "none"))
        _choice("Index1", "linsolve", self.linsolve, ("auto", "schur", "qr"))
        if len(self.baumgarte) != 2:
            raise ValueError(f"Index1: baumgarte must be (alpha, beta), got {self.baumgarte!r}")
        for x in self.baumgarte:
            _positive("Index1", "baumgarte", x)
        _flag("Index1", "generated", self.generated)
        object.__setattr__(self, "baumgarte", tuple(float(x) for x in self.baumgarte))


class Index1Loop(FormulationLoop):
    """Eq. (6) as an ODE in y = [q, qd] (2n)."""

    options = Index1

    name = "index1"
    methods = Index1.methods

    def __init__(self, model, options, counters):
        super().__init__(model, options, counters)
        stab = self.opt["stabilization"]
        if stab not in ("projection", "baumgarte", "none"):
            raise ValueError(f"stabilization {stab!r}: expected projection, baumgarte or none")
        mode = self.opt["linsolve"]
        if mode not in ("auto", "schur", "qr"):
            raise ValueError(f"linsolve {mode!r}: expected auto, schur or qr")
        if mode == "schur" and not self.regular:
            raise ValueError("linsolve 'schur' needs a regular mass matrix")
        self.mode = mode

    @functools.cached_property
    def regular(self) -> bool:
        """Whether M is positive definite (block by block)."""
        from ..compiled.sparsity import is_spd
        return is_spd(self.M)

    def _eliminates(self) -> bool:
        """:attr:`elimination` with ``linsolve`` auto only. The compiled loop runs on the
        coordinates kept; a singular M's projections are M-orthogonal there (the kinetic
        metric) in both loops, or minimum-norm there where M_r stays singular."""
        return self.opt["linsolve"] == "auto"

    @functools.cached_property
    def Minv(self) -> np.ndarray:
        """M^-1 (n, n), dense, for the Python Schur path (block by block)."""
        from ..compiled.sparsity import block_inverse
        return block_inverse(self.M).toarray()

    def init(self, t, q, qd):
        if self.mode == "auto":
            r = np.linalg.matrix_rank(self.cs.jacobian(q, t), self.opt["rank_tol"])
            self.mode = "schur" if self.regular and r == self.cs.m else "qr"
        return np.concatenate([q, qd])

    def state(self, t, y):
        return y[:self.n], y[self.n:]

    def compiled_candidate(self, method: str, h) -> bool:
        """Whether the compiled loop may run (decided before ``init``): adaptive dop853 or
        dopri5, fixed-step rk4 or dopri5, projection, scleronomic constraints, forces
        :func:`compiled_forces` knows. A regular M runs the sparse Schur path (redundant rows
        included), a singular one (or ``linsolve = "qr"``) the null-space QR form."""
        from ..compiled import index1 as kernels
        return self._compiled_model(
            method in (kernels.ADAPTIVE if h is None else kernels.FIXED_STEP)
            and self.opt["stabilization"] == "projection")

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        """Model-only set-up of the compiled loop, kept out of the stepping time: the
        coordinates the constant linear rows fix eliminated (:attr:`elimination`), the
        sparsity plan of the Schur path on the rest (:func:`natcoord.compiled.sparsity.schur_plan`)
        and its generated kernels (:func:`natcoord.compiled.codegen.load`, None when the model has
        none). A singular M that no elimination makes regular takes the generated
        regularised route where it can (:func:`natcoord.compiled.sparsity.dense_plan`, alpha from M
        and Phi_q at ``q0``), else the general QR path (on the coordinates kept, where an
        elimination leaves M_r singular). The model's own plan (a regular M) serves the
        outputs."""
        from ..compiled import codegen
        sparse, self._plan, loop, kplan = self._routes(q0)
        self._plan_args = None if loop is None else loop.kernel_args
        _, frc, M = self._loop_model()
        self._kern = None if kplan is None else codegen.load(kplan, frc, M)
        if self._kern is not None:  # a dense plan drives the loop only: the outputs
            self._plan_args = kplan.kernel_args  # stay on the general path
        if self.mode == "auto":  # the compiled paths need no rank decision
            self.mode = "schur" if sparse else "qr"
        return Prepared(self.compiled_path, self._frc, self._plan,
                        None if self._plan is None else self._plan.kernel_args, self._kern,
                        self.elimination)

    def _routes(self, q0: np.ndarray | None) -> tuple:
        """What :meth:`prepare_compiled` sets up, nothing compiled: (whether the Schur
        path serves M, the outputs' plan or None, the loop's plan or None, the plan the
        generated kernels would be written from or None)."""
        from ..compiled.sparsity import dense_plan, schur_plan
        auto = self.opt["linsolve"] != "qr"
        sparse = self.regular and auto
        out = schur_plan(self.cs.con, self.M) if sparse else None
        con, _, M = self._loop_model()
        e = self.elimination
        loop = out if e is None else schur_plan(con, M) if e.regular else None
        kplan = None
        if auto and self.opt["generated"]:
            q0 = None if q0 is None else np.asarray(q0, float)[
                slice(None) if e is None else e.keep]
            kplan = loop if loop is not None else dense_plan(con, M, _alpha(con, M, q0))
        return sparse, out, loop, kplan

    def compiled_needs(self, q0: np.ndarray | None = None) -> tuple[str, ...]:
        """The compiled code a run from ``q0`` takes, decided as :meth:`prepare_compiled`
        does but compiling nothing: its path, and ``outputs`` when the samples'
        multipliers come from the sparse kernels (a regular M)."""
        from ..compiled import codegen
        _, out, loop, kplan = self._routes(q0)
        frc = self._loop_model()[1]
        path = ("generated" if kplan is not None and codegen.supported(kplan, frc)
                else "general" if loop is None else "sparse")
        return (path, "outputs") if out is not None else (path,)

    def _loop_model(self) -> tuple:
        """(constraints, packed forces, M) the compiled loop integrates: the model's, or
        over the coordinates an elimination keeps."""
        e = self.elimination
        return (self.cs.con, self._frc, self.M) if e is None else (e.con, e.frc, e.M)

    @property
    def compiled_path(self) -> str:
        """After :meth:`prepare_compiled`: the compiled loop's path for this model (one of
        :data:`natcoord.compiled.cache.PATHS`)."""
        if self._kern is not None:
            return "generated"
        return "general" if self._plan_args is None else "sparse"

    def compiled_ready(self) -> bool:
        """After ``init``: whether the compiled loop serves the mode ``init`` chose; both
        ``schur`` and ``qr`` have a compiled path (``integrate`` gates on this)."""
        return self.mode in ("schur", "qr")

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.compiled.index1.run`: (Q, QD, QDD) (T, n) at ``times``
        from y = [q, qd] (:meth:`compiled_runner` once)."""
        from ..compiled.index1 import add_counters
        out = tuple(np.zeros((len(times), self.n)) for _ in range(3))
        add_counters(self.compiled_runner(times, 0.0, y[:self.n], y[self.n:], method, rtol,
                                          atol, h)(*out), self.cnt)
        return out

    def compiled_runner(self, times, t0, q0, qd0, method, rtol, atol, h=None):
        """``go(Q, QD, QDD)``: the whole run from (q0, qd0) at ``times`` into (T, n) in place,
        returning its counter array (:func:`natcoord.compiled.index1.add_counters` adds it
        to the counters: once, after a benchmark's repeated runs, not in each)
        (:func:`natcoord.compiled.index1.prepare`: the sparse Schur path for a regular M or
        one left regular by an elimination, else the QR null-space form with M, on the
        coordinates kept where there is one), after :meth:`prepare_compiled` (made here
        when it was not); no ``init`` needed (the loop projects the start itself)."""
        from ..compiled import index1 as kernels
        if not hasattr(self, "_plan_args"):
            self.prepare_compiled()
        e = self.elimination
        con, frc, M = self._loop_model()
        go = kernels.prepare(method, con, frc, times,
                             kernels.Steps(rtol, atol, self.opt["project_tol"], h),
                             kernels.Route(self._plan_args, self._kern, M, self.opt["rank_tol"],
                                           None if e is None else e.dep_map))
        q0, qd0 = np.ascontiguousarray(q0, float), np.ascontiguousarray(qd0, float)
        return lambda Q, QD, QDD: go(q0, qd0, (Q, QD, QDD))

    def rhs(self, t, y):
        q, qd = y[:self.n], y[self.n:]
        return np.concatenate([qd, self.accelerations(t, q, qd)])

    def accelerations(self, t, q, qd):
        """qdd (n,) of Eq. (6) (Baumgarte terms in c when chosen)."""
        self.cnt.rhs += 1
        self.cnt.factorizations += 1
        F = self.model.forces(t, q, qd)
        p, J, pt, c = self.cs.all(q, qd, t)
        if self.opt["stabilization"] == "baumgarte":
            a, b = self.opt["baumgarte"]
            c = c - 2.0 * a * (J @ qd + pt) - b * b * p
        if self.mode == "schur":  # M^-1 constant: one (m, m) solve per evaluation
            MiF, MiJt = self.Minv @ F, self.Minv @ J.T
            lam = np.linalg.solve(J @ MiJt, J @ MiF - c)
            return MiF - MiJt @ lam
        Q1, Q2, R1, P = self._qr(J)
        r = R1.shape[0]
        y1 = np.linalg.solve(R1[:, :r].T, c[P[:r]]) if r else np.zeros(0)
        v1 = Q1 @ y1
        if Q2.shape[1] == 0:
            return v1
        K = Q2.T @ self.M @ Q2
        y2 = np.linalg.solve(K, Q2.T @ (F - self.M @ v1))
        return v1 + Q2 @ y2

    def _qr(self, J):
        """Pivoted QR of Phi_q^T: Phi_q^T[:, P] = Q R; rank r reveals redundant rows."""
        if J.shape[0] == 0:
            n = J.shape[1]
            return np.zeros((n, 0)), np.eye(n), np.zeros((0, 0)), np.zeros(0, int)
        Q, R, P = scipy.linalg.qr(J.T, pivoting=True)
        d = np.abs(np.diag(R))
        r = int(np.sum(d > self.opt["rank_tol"] * max(d[0], 1e-300))) if len(d) else 0
        return Q[:, :r], Q[:, r:], R[:r, :], P

    def _corrector(self, J, Lt=None):
        """dx = corr(rhs) with J dx = rhs (consistent rows), M-orthogonal when M is regular.
        ``Lt``: L^-T of M = L L^T for an M-orthogonal, rank-revealing correction (the
        minimum of dx^T M dx: dx = L^-T z with z the minimum-norm solution of J L^-T z =
        rhs)."""
        self.cnt.factorizations += 1
        if self.mode == "schur" and Lt is None:
            MiJt = self.Minv @ J.T
            W = J @ MiJt
            return lambda rhs: MiJt @ np.linalg.solve(W, rhs)
        Q1, _, R1, P = self._qr(J if Lt is None else J @ Lt)
        r = R1.shape[0]
        Q1 = Q1 if Lt is None else Lt @ Q1
        return lambda rhs: Q1 @ np.linalg.solve(R1[:, :r].T, rhs[P[:r]])

    def post_step(self, t, y):
        if self.opt["stabilization"] != "projection":
            return y
        return np.concatenate(self.project(t, y[:self.n], y[self.n:]))

    def project(self, t, q, qd):
        """Newton projection of q on Phi(q, t) = 0, then qd on Phi_q qd = -Phi_t:
        M-orthogonal for a regular M, and for a singular one in the coordinates its
        :attr:`elimination` keeps (minimum-norm where it has none)."""
        self._drift(t, q, qd)
        e = None if self.regular else self.elimination  # (a regular M's is the same)
        if e is None:
            return self._newton(self.cs.phi, self.cs.jacobian, self.cs.phi_t, t, q, qd)
        qr, qdr = self._newton(lambda x, t: e.con.phi(x), lambda x, t: e.con.jacobian(x),
                               lambda x, t: 0.0, t, q[e.keep], qd[e.keep], e.Lt)
        return e.T @ qr + e.b, e.T @ qdr

    def _newton(self, phi, jacobian, phi_t, t, q, qd, Lt=None):
        """Simplified Newton on phi(q, t) = 0 (one factorization), then qd on
        jacobian qd = -phi_t; ``Lt``: see :meth:`_corrector`."""
        from ..compiled.general import reachable  # (numba: imported when a loop runs)
        tol = reachable(self.opt["project_tol"], q, 2)  # what Phi's round-off allows
        q = q.copy()
        corr = None
        for _ in range(10):
            p = phi(q, t)
            if np.max(np.abs(p), initial=0.0) < tol:
                break
            if corr is None:  # simplified Newton: one factorization per projection
                corr = self._corrector(jacobian(q, t), Lt)
            q -= corr(p)
            self.cnt.newton += 1
        J = jacobian(q, t)
        res = J @ qd + phi_t(q, t)
        if np.max(np.abs(res), initial=0.0) > tol:
            qd = qd - self._corrector(J, Lt)(res)
        self.cnt.projections += 1
        return q, qd


Index1.loop = Index1Loop
