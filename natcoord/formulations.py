"""Equations of motion in natural coordinates: the loops behind the formulations of
:mod:`natcoord.solver`, by name (``RUNTIME``).

Every formulation works on any model with ``n``, ``M`` (n, n), ``constraints``
(:class:`~natcoord.constraints.QuadraticConstraints`), ``forces(t, q, qd) -> (n,)`` and
optionally ``drivers`` (rheonomic rows, :mod:`natcoord.drivers`). Equation numbers refer to
García de Jalón & Gutiérrez-López, "Multibody dynamics with redundant constraints and
singular mass matrix".

``index1``  Lagrange equations with the acceleration constraints, Eq. (6). Solved through
            the Schur complement ``Phi_q M^-1 Phi_q^T`` with the constant M^-1 when M is
            regular and Phi_q has full rank, otherwise through a rank-revealing (pivoted)
            QR of Phi_q^T, which is the null-space form of Eq. (6) and holds for redundant
            constraints and a singular M. Drift: projection after every step or Baumgarte.
``maggi``   Maggi / R-method, Eq. (23): independent coordinates from Gaussian elimination
            with full pivoting of Phi_q, Eqs. (13)-(15); dependent positions by Newton;
            re-partitioned when the dependent block degrades.
``index3``  Augmented Lagrangian index-3 with the trapezoidal rule and mass-orthogonal
            projections of velocities and accelerations (Bayo & Ledesma, 1996). It steps
            itself (integrator ``trapezoidal``).

A formulation is a small object with the state layout it integrates (``init``, ``state``)
and the stages the time loop of :mod:`natcoord.integrators` calls (``rhs`` or ``step``,
then ``post_step``); each also runs as one compiled loop that takes the same steps
(:mod:`natcoord.kernels`, :mod:`natcoord.kernels_maggi`, :mod:`natcoord.kernels_index3`).
Multipliers are computed once per output sample by :func:`multipliers` (minimum norm), so
every formulation reports the same lambda.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .drivers import ConstraintSystem
from .errors import ExistenceError, StepFailure
from .kernels_general import reachable
from .kernels_index3 import FD_STEP, PENALTY_MAX, force_tangent
from .solver import Index1, Index3, Maggi
from .sparsity import is_spd


@dataclass
class Counters:
    """Cost counters of one integration; they do not depend on machine noise.

    ``max_phi``/``max_phi_dot``: max |Phi| and |Phi_q qd + Phi_t| over the output samples;
    ``max_phi_step``/``max_phi_dot_step``: the same before each projection (what one step of
    the integrator lets drift).
    """

    steps: int = 0
    rejected: int = 0
    rhs: int = 0
    factorizations: int = 0
    projections: int = 0
    newton: int = 0
    repartitions: int = 0
    max_phi: float = 0.0
    max_phi_dot: float = 0.0
    max_phi_step: float = 0.0
    max_phi_dot_step: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Prepared:
    """The model-only set-up of a compiled loop (made before the stepping, never timed):
    ``path`` the loop that runs (:data:`natcoord.kernel_cache.PATHS`), ``frc`` the packed
    forces (:func:`compiled_forces`), ``plan`` the model's sparsity plan for the samples'
    multipliers (index1 with a regular M; None otherwise) with its ``out_args``
    (``plan.kernel_args``), ``kernels`` the generated kernels driving the loop (None: the
    generic ones), ``elimination`` the coordinates the loop leaves out (None: none)."""

    path: str
    frc: tuple | None
    plan: object | None = None
    out_args: tuple | None = None
    kernels: object | None = None
    elimination: object | None = None


# every option of every formulation with its default (:mod:`natcoord.solver` documents them)
DEFAULT_OPTIONS = {**Index1().options(), **Maggi().options(), **Index3().options()}


# ---- shared linear algebra ------------------------------------------------------------
def full_pivot_partition(J: np.ndarray, tol: float = 1e-9):
    """Gaussian elimination with full pivoting of Phi_q (m, n), Eqs. (13)-(15) and (25).

    Returns (rows (r,), dep (r,), indep (n - r,), pivots (r,)): the independent constraint
    rows, the dependent coordinates (pivot columns), the independent coordinates and the
    absolute pivots in elimination order. The rank r is the number of pivots above
    ``tol * max|Phi_q|``.
    """
    A = np.array(J, dtype=float)
    m, n = A.shape
    rows, cols = np.arange(m), np.arange(n)
    scale = max(np.max(np.abs(A), initial=0.0), 1e-300)
    pivots = []
    for k in range(min(m, n)):
        sub = np.abs(A[k:, k:])
        i, j = np.unravel_index(np.argmax(sub), sub.shape)
        if sub[i, j] <= tol * scale:
            break
        i, j = i + k, j + k
        A[[k, i]], rows[[k, i]] = A[[i, k]], rows[[i, k]]
        A[:, [k, j]], cols[[k, j]] = A[:, [j, k]], cols[[j, k]]
        pivots.append(abs(A[k, k]))
        A[k + 1:, k:] -= np.outer(A[k + 1:, k] / A[k, k], A[k, k:])
    r = len(pivots)
    return rows[:r].copy(), cols[:r].copy(), np.sort(cols[r:]), np.array(pivots)


def null_space(J: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis (n, f) of ker Phi_q by SVD."""
    n = J.shape[1]
    if J.shape[0] == 0:
        return np.eye(n)
    _, s, Vt = np.linalg.svd(J)
    r = int(np.sum(s > tol * max(s[0], 1e-300))) if len(s) else 0
    return Vt[r:].T


def check_existence(model, q: np.ndarray, t: float = 0.0, tol: float = 1e-9) -> None:
    """Raise ExistenceError unless ker M ∩ ker Phi_q = {0} at q (Eq. (37)).

    The test is that R^T M R is positive definite for an orthonormal basis R of ker Phi_q
    (Eq. (53)): every motion allowed by the constraints carries kinetic energy. The error
    names the coordinates (and bodies) of the motion that carries none.
    """
    cs = ConstraintSystem(model)
    R = null_space(cs.jacobian(q, t), tol)
    if R.shape[1] == 0:
        return
    w, V = np.linalg.eigh(R.T @ model.M @ R)
    mscale = max(np.max(np.abs(model.M)), 1e-300)
    if w[0] > tol * mscale:
        return
    x = R @ V[:, 0]
    x /= np.max(np.abs(x))
    moving = np.flatnonzero(np.abs(x) > 1e-6)
    names = _coordinate_names(model)
    desc = ", ".join(f"{names[k]} ({x[k]:+.3g})" for k in moving)
    bodies = sorted({names[k].split(".")[0] for k in moving if "." in names[k]})
    raise ExistenceError(
        "ker M ∩ ker Phi_q ≠ {0} (Eq. (37)): the constraints allow a motion with zero kinetic "
        f"energy, so the accelerations are not determined. Moving coordinates: {desc}"
        + (f" (bodies: {', '.join(bodies)})" if bodies else "")
        + ". Give the massless part mass or inertia, or constrain that motion.")


def _coordinate_names(model) -> list[str]:
    names = getattr(model, "coordinate_names", None)
    return names() if names else [f"q[{k}]" for k in range(model.n)]


def multipliers(model, cs: ConstraintSystem, t: float, q, qd, qdd) -> np.ndarray:
    """Minimum-norm lambda (m_all,) of Phi_q^T lambda = F - M qdd (Eq. (54))."""
    J = cs.jacobian(q, t)
    return np.linalg.lstsq(J.T, model.forces(t, q, qd) - model.M @ qdd, rcond=None)[0]


def compiled_forces(model) -> tuple | None:
    """The applied forces of ``model`` as the arrays of the compiled loop
    (:func:`natcoord.kernels_general.pack_forces`), or None for a force model it does not
    know (it knows :meth:`natcoord.model.Model.forces`: Q0, constant torques on bodies,
    linear spring-dampers)."""
    from .kernels_general import pack_forces
    from .model import Model
    if getattr(type(model), "forces", None) is not Model.forces:
        return None
    n, d = model.n, model.dim
    G, toff, tau = [np.zeros((0, d, n + 1))], [0], np.zeros((len(model.torques), 3))
    for t, (body, tq) in enumerate(model.torques):
        tq = np.atleast_1d(np.asarray(tq, float))
        if tq.shape != ((1,) if d == 2 else (3,)):
            return None
        G.append(np.asarray(model.bodies[body].G, float))  # difference maps (K, d, n + 1)
        toff.append(toff[-1] + len(G[-1]))
        tau[t, :len(tq)] = tq
    S = np.array([s.B - s.A for s in model.springs], float).reshape(-1, d, n + 1)
    spr = np.array([[s.k, s.c, s.l0] for s in model.springs], float).reshape(-1, 3)
    return pack_forces(model.Q0, None, np.concatenate(G), np.array(toff), tau, S, spr)


def _alpha(con, M: np.ndarray, q0: np.ndarray | None) -> float:
    """alpha of M + alpha J_S^T J_S: max diag M over max diag J^T J (at q0, or J's
    coefficients alone), rounded to a power of two (one model, one set of kernels)."""
    J = con.jacobian(q0) if q0 is not None else np.zeros((0, len(M)))
    jj = float(np.max(np.sum(J * J, axis=0), initial=0.0)) or 1.0
    mm = float(np.max(np.diag(M), initial=0.0)) or 1.0
    return float(2.0 ** round(math.log2(mm / jj)))


# ---- formulations ---------------------------------------------------------------------
class FormulationLoop:
    """Base: how a formulation meets the time loop.

    1. ``init(t, q, qd) -> y`` maps a consistent state to what is integrated.
    2. ODE forms give ``rhs(t, y) -> dy/dt``; stepping forms give ``step(t, y, h) -> y``.
    3. ``post_step(t, y) -> y`` after every accepted step (projection, re-partitioning).
    4. ``state(t, y) -> (q, qd)`` and ``accelerations(t, q, qd) -> qdd`` for the outputs.

    A formulation with a compiled loop says so in ``compiled_candidate(method, h)``, sets
    itself up in ``prepare_compiled(q0) -> Prepared`` (model only: not stepping time; the
    loop's path among :data:`natcoord.kernel_cache.PATHS`) and runs the whole integration in
    ``run_compiled(times, y, method, rtol, atol, h) -> (Q, QD, QDD)`` from ``init``'s y.
    """

    name = ""
    ode = True
    methods: tuple[str, ...] = ()
    compiled_path = "python"
    _plan = None  # a sparsity plan for the samples' multipliers (index1's Schur path)

    def __init__(self, model, options: dict, counters: Counters):
        self.model, self.opt, self.cnt = model, {**DEFAULT_OPTIONS, **options}, counters
        self.cs = ConstraintSystem(model)
        self.n = model.n
        self.M = np.asarray(model.M, dtype=float)

    def post_step(self, t, y):
        return y

    def compiled_candidate(self, method: str, h) -> bool:
        return False

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        return Prepared(self.compiled_path, self._frc)

    @functools.cached_property
    def _frc(self) -> tuple | None:
        """The model's forces packed for the compiled loops (:func:`compiled_forces`)."""
        return compiled_forces(self.model)

    def _compiled_model(self, methods) -> bool:
        """Whether the compiled loop may run with ``methods`` allowed: ``compiled`` on,
        numba present, scleronomic constraints and forces :func:`compiled_forces` knows."""
        from . import kernels
        return (bool(self.opt["compiled"]) and kernels.HAVE_NUMBA and bool(methods)
                and not self.cs.rheonomic and self._frc is not None)

    def _drift(self, t, q, qd):
        p, J, pt, _ = self.cs.all(q, qd, t)
        self.cnt.max_phi_step = max(self.cnt.max_phi_step, float(np.max(np.abs(p), initial=0)))
        self.cnt.max_phi_dot_step = max(self.cnt.max_phi_dot_step,
                                        float(np.max(np.abs(J @ qd + pt), initial=0)))


class Index1Loop(FormulationLoop):
    """Eq. (6) as an ODE in y = [q, qd] (2n)."""

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
        return is_spd(self.M)

    @functools.cached_property
    def elimination(self):
        """The coordinates the constant linear rows fix, eliminated
        (:class:`natcoord.elimination.Elimination`); None with drivers, ``linsolve`` other
        than auto, or no such row. The compiled loop runs on the coordinates kept; a
        singular M's projections are M-orthogonal there (the kinetic metric) in both loops,
        or minimum-norm there where M_r stays singular."""
        from .elimination import eliminate
        if self.cs.rheonomic or self.opt["linsolve"] != "auto":
            return None
        return eliminate(self.cs.con, self.M, self._frc)

    @functools.cached_property
    def Minv(self) -> np.ndarray:
        """M^-1 (n, n), dense, for the Python Schur path (block by block)."""
        from .sparsity import block_inverse
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
        from . import kernels
        return self._compiled_model(
            method in (kernels.ADAPTIVE if h is None else kernels.FIXED_STEP)
            and self.opt["stabilization"] == "projection")

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        """Model-only set-up of the compiled loop, kept out of the stepping time: the
        coordinates the constant linear rows fix eliminated (:attr:`elimination`), the
        sparsity plan of the Schur path on the rest (:func:`natcoord.sparsity.schur_plan`)
        and its generated kernels (:func:`natcoord.codegen.load`, None when the model has
        none). A singular M that no elimination makes regular takes the generated
        regularised route where it can (:func:`natcoord.sparsity.dense_plan`, alpha from M
        and Phi_q at ``q0``), else the general QR path (on the coordinates kept, where an
        elimination leaves M_r singular). The model's own plan (a regular M) serves the
        outputs."""
        from . import codegen
        from .sparsity import dense_plan, schur_plan
        auto = self.opt["linsolve"] != "qr"
        sparse = self.regular and auto
        self._plan = schur_plan(self.cs.con, self.M) if sparse else None  # the outputs'
        con, frc, M = self._loop_model()
        e = self.elimination
        loop = self._plan if e is None else schur_plan(con, M) if e.regular else None
        self._plan_args = None if loop is None else loop.kernel_args
        self._kern = None
        if auto and self.opt["generated"]:
            q0 = None if q0 is None else np.asarray(q0, float)[
                slice(None) if e is None else e.keep]
            plan = loop if loop is not None else dense_plan(con, M, _alpha(con, M, q0))
            self._kern = codegen.load(plan, frc, M)
            if self._kern is not None:  # a dense plan drives the loop only: the outputs
                self._plan_args = plan.kernel_args  # stay on the general path
        if self.mode == "auto":  # the compiled paths need no rank decision
            self.mode = "schur" if sparse else "qr"
        return Prepared(self.compiled_path, self._frc, self._plan,
                        None if self._plan is None else self._plan.kernel_args, self._kern, e)

    def _loop_model(self) -> tuple:
        """(constraints, packed forces, M) the compiled loop integrates: the model's, or
        over the coordinates an elimination keeps."""
        e = self.elimination
        return (self.cs.con, self._frc, self.M) if e is None else (e.con, e.frc, e.M)

    @property
    def compiled_path(self) -> str:
        """After :meth:`prepare_compiled`: the compiled loop's path for this model (one of
        :data:`natcoord.kernel_cache.PATHS`)."""
        if self._kern is not None:
            return "generated"
        return "general" if self._plan_args is None else "sparse"

    def compiled_ready(self) -> bool:
        """After ``init``: whether the compiled loop serves the mode ``init`` chose; both
        ``schur`` and ``qr`` have a compiled path (``integrate`` gates on this)."""
        return self.mode in ("schur", "qr")

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.kernels.run`: (Q, QD, QDD) (T, n) at ``times``
        (the sparse Schur path for a regular M or one left regular by an elimination, else
        the QR null-space form with M, on the coordinates kept where there is one), after
        :meth:`prepare_compiled` (made here when it was not)."""
        from . import kernels
        if not hasattr(self, "_plan_args"):
            self.prepare_compiled()
        q, qd, e = y[:self.n], y[self.n:], self.elimination
        con, frc, M = self._loop_model()
        return kernels.run(method, con, frc, times, q if e is None else q[e.keep],
                           qd if e is None else qd[e.keep],
                           plan=self._plan_args, kern=self._kern, M=M,
                           rank_tol=self.opt["rank_tol"],
                           rtol=rtol, atol=atol, ptol=self.opt["project_tol"], cnt=self.cnt,
                           h=h, dep=None if e is None else e.dep_map)

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


class MaggiLoop(FormulationLoop):
    """Eq. (23) as an ODE in y = [q^i, qd^i] (2f), R from coordinate partitioning.

    With dop853 or dopri5 (adaptive), rk4 or dopri5 (fixed step) the whole run is one numba
    loop when the model allows (:mod:`natcoord.kernels_maggi`: the same steps, Newton and
    re-partitions as this class and :func:`natcoord.integrators.time_loop`)."""

    name = "maggi"
    methods = Maggi.methods
    compiled_path = "maggi"

    def init(self, t, q, qd):
        self.q = np.array(q, dtype=float)
        self._partition(t, self.q)
        return np.concatenate([q[self.indep], qd[self.indep]])

    def compiled_candidate(self, method: str, h) -> bool:
        """Whether the compiled loop (:mod:`natcoord.kernels_maggi`) may run: adaptive
        dop853 or dopri5, fixed-step rk4 or dopri5, scleronomic constraints, forces
        :func:`compiled_forces` knows."""
        from . import kernels
        return self._compiled_model(
            method in (kernels.ADAPTIVE if h is None else kernels.FIXED_STEP))

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        """Model-only set-up: the constraint triplets and M's non-zeros packed for the
        compiled loop (:func:`natcoord.kernels_maggi.pack`)."""
        from . import kernels_maggi
        self._packed = kernels_maggi.pack(self.cs.con, self.M)
        return Prepared(self.compiled_path, self._frc)

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.kernels_maggi.run` from ``init``'s y = [q^i,
        qd^i] (2f), its q (n,) and partition: (Q, QD, QDD) (T, n) at ``times`` (T,) s, the
        same steps as the Python loop."""
        from . import kernels_maggi
        if not hasattr(self, "_packed"):
            self.prepare_compiled()
        return kernels_maggi.run(
            self._packed, self._frc, times, y, self.q, self.rows, self.dep, self.indep,
            method=method, rtol=rtol, atol=atol, h=h, newton_tol=self.opt["newton_tol"],
            rank_tol=self.opt["rank_tol"], repartition_growth=self.opt["repartition_growth"],
            cnt=self.cnt)

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


class Index3Loop(FormulationLoop):
    """Index-3 augmented Lagrangian, trapezoidal rule, mass-orthogonal projections.

    y = [q, qd, qdd, lambda*] (3n + m). Per step: Newton on
    ``M (q - qhat) + h^2/4 (Phi_q^T (lambda* + alpha Phi) - F) = 0`` (its tangent with the
    forces' stiffness and damping, :meth:`_force_tangent`) with lambda* updated
    by ``alpha Phi`` after every iteration, then qd and qdd projected onto
    ``Phi_q qd = -Phi_t`` and ``Phi_q qdd = c`` in the metric of M (Bayo & Ledesma).
    The whole run is one numba loop when the model allows (:mod:`natcoord.kernels_index3`,
    the same steps).
    """

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
        self._Kt = force_tangent(self._frc, self.n)
        return np.concatenate([q, qd, qdd, lam])

    def _force_tangent(self, t, q, qd, h, F):
        """K (n, n) = dF/dq + 2/h dF/dqd along the trapezoidal rule's qd(q) (the applied
        forces' stiffness and damping in the Newton tangent): the constant part and the
        columns by forward differences (relative step ``FD_STEP``, counted as evaluations)
        of :func:`natcoord.kernels_index3.force_tangent`; 0 for constant forces."""
        if self._Kt is None:
            return 0.0
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
        """Whether the compiled loop (:mod:`natcoord.kernels_index3`) may run: the
        trapezoidal rule, scleronomic constraints, forces :func:`compiled_forces` knows."""
        return self._compiled_model(method == "trapezoidal" and h is not None)

    def run_compiled(self, times, y, method, rtol, atol, h=None):
        """The whole run in :func:`natcoord.kernels_index3.run`: (Q, QD, QDD) (T, n) at
        ``times``, the same steps as :meth:`step`."""
        from . import kernels_index3
        return kernels_index3.run(self.cs.con, self._frc, self.M, times, y, h=h,
                                  penalty=self.opt["penalty"], mscale=self.mscale,
                                  newton_tol=self.opt["newton_tol"],
                                  project_tol=self.opt["project_tol"], cnt=self.cnt)

    def step(self, t, y, h):
        """One trapezoidal step. When Newton fails (near a singular position, where the
        multipliers grow without bound) the step is retried with the penalty x100, up to
        1e10 x max|M|; counted in ``rejected``."""
        q0, qd0, qdd0, _ = self._split(y)
        t1, cs = t + h, self.cs
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


RUNTIME: dict[str, type[FormulationLoop]] = {f.name: f for f in (Index1Loop, MaggiLoop,
                                                                   Index3Loop)}
