"""What every formulation shares: cost counters, the prepared set-up of a compiled loop,
the linear algebra of the paper's equations (full-pivoting partition, null space, the
existence condition Eq. (37), minimum-norm multipliers Eq. (54)), the forces packed for the
compiled loops, and :class:`FormulationLoop`, the base of the formulations' Python loops.
Equation numbers refer to García de Jalón & Gutiérrez-López, "Multibody dynamics with
redundant constraints and singular mass matrix"."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ExistenceError
from ..model.drivers import ConstraintSystem


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
    ``path`` the loop that runs (:data:`natcoord.compiled.cache.PATHS`), ``frc`` the packed
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


def _min_eig(M: np.ndarray) -> float:
    """Least eigenvalue of a symmetric M (n, n), block by block over the coordinates it
    couples (linear in n for a block-diagonal M); -inf for an empty M."""
    from ..compiled.sparsity import blocks

    return min((float(np.linalg.eigvalsh(M[np.ix_(b, b)])[0]) for b in blocks(M)),
               default=-np.inf)


def check_existence(model, q: np.ndarray, t: float = 0.0, tol: float = 1e-9) -> None:
    """Raise ExistenceError unless ker M ∩ ker Phi_q = {0} at q (Eq. (37)).

    The test is that R^T M R is positive definite for an orthonormal basis R of ker Phi_q
    (Eq. (53)): every motion allowed by the constraints carries kinetic energy. The error
    names the coordinates (and bodies) of the motion that carries none.
    """
    if _min_eig(model.M) > tol * max(np.max(np.abs(model.M)), 1e-300):
        return  # M positive definite: R^T M R >= lambda_min(M) for any orthonormal R
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


def multipliers(model, cs: ConstraintSystem, t, q, qd, qdd) -> np.ndarray:
    """Minimum-norm lambda of Phi_q^T lambda = F - M qdd (Eq. (54)): (m_all,) at one state
    t, q, qd, qdd (n,); (T, m_all) along samples t (T,), q, qd, qdd (T, n), by stacked
    pseudo-inverses (LAPACK's loop over the samples) a chunk at a time."""
    if np.ndim(q) == 1:
        J = cs.jacobian(q, t)
        return np.linalg.lstsq(J.T, model.forces(t, q, qd) - model.M @ qdd, rcond=None)[0]
    out = np.zeros((len(t), cs.m))
    step = max(1, (1 << 20) // max(1, cs.m * cs.n))
    for a in range(0, len(t), step):
        b = slice(a, a + step)
        F = (np.array([model.forces(*x) for x in zip(t[b], q[b], qd[b], strict=True)])
             if any(getattr(model, k, ()) for k in ("torques", "springs", "body_forces"))
             or not hasattr(model, "Q0") else np.broadcast_to(model.Q0, q[b].shape))
        Jt = cs.jacobian(q[b], t[b]).transpose(0, 2, 1)
        out[b] = (np.linalg.pinv(Jt) @ (F - qdd[b] @ model.M.T)[..., None])[..., 0]
    return out


def compiled_forces(model) -> tuple | None:
    """The applied forces of ``model`` as the arrays of the compiled loop
    (:func:`natcoord.compiled.general.pack_forces`), or None for a force model it does not
    know (it knows :meth:`natcoord.model.model.Model.forces`: Q0, constant torques on bodies
    (world or body axes), forces in a body's axes (on a basis that spans 3-D),
    linear spring-dampers)."""
    from ..compiled.general import pack_forces
    from ..model.model import Model
    if getattr(type(model), "forces", None) is not Model.forces:
        return None
    n, d = model.n, model.dim
    laws = [law for _, _, law in model.torques if law is not None]
    width = 3 + (max(len(c) for c in laws) if laws else 0)  # body-fixed: 3 + K + 1 columns
    G, toff, tau = [np.zeros((0, d, n + 1))], [0], np.zeros((len(model.torques), width))
    for t, (body, tq, law) in enumerate(model.torques):
        tq = np.atleast_1d(np.asarray(tq, float))
        if tq.shape != ((1,) if d == 2 else (3,)):
            return None
        G.append(np.asarray(model.bodies[body].G, float))  # difference maps (K, d, n + 1)
        toff.append(toff[-1] + len(G[-1]))
        if law is None:
            tau[t, :len(tq)] = tq
        else:  # tau_world = sum_k c_k d_k + c_K d_0 x d_1
            tau[t, 3], tau[t, 4:4 + len(law) - 1] = law[-1], law[:-1]
    Q0, T = model.Q0.copy(), np.zeros((n, n))
    for body, C, law in model.body_forces:  # C^T R(q) F: linear in q for a 3-D basis
        if law[-1]:
            return None  # a basis spanning a plane: R(q) has d_0 x d_1 (the Python loop)
        CG = np.einsum("an,kam->knm", C[:, :-1], model.bodies[body].G)  # (K, n, n + 1)
        T += np.tensordot(law[:-1], CG[:, :, :-1], 1)
        Q0 += np.tensordot(law[:-1], CG[:, :, -1], 1)
    S = np.array([s.B - s.A for s in model.springs], float).reshape(-1, d, n + 1)
    spr = np.array([[s.k, s.c, s.l0] for s in model.springs], float).reshape(-1, 3)
    return pack_forces(Q0, T if model.body_forces else None, np.concatenate(G),
                       np.array(toff), tau, S, spr)


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
    loop's path among :data:`natcoord.compiled.cache.PATHS`) and runs the whole integration in
    ``run_compiled(times, y, method, rtol, atol, h) -> (Q, QD, QDD)`` from ``init``'s y
    (``compiled_runner`` packs it once for repeated runs).
    """

    options: type  # the formulation's options (a Formulation), whose defaults fill ``options``
    name = ""
    ode = True
    methods: tuple[str, ...] = ()
    compiled_path = "python"
    _plan = None  # a sparsity plan for the samples' multipliers (index1's Schur path)

    def __init__(self, model, options: dict, counters: Counters):
        self.model, self.opt, self.cnt = model, {**self.options().options(), **options}, counters
        self.cs = ConstraintSystem(model)
        self.n = model.n
        self.M = np.asarray(model.M, dtype=float)

    def post_step(self, t, y):
        return y

    @functools.cached_property
    def elimination(self):
        """The coordinates the constant linear rows fix, eliminated
        (:class:`natcoord.compiled.elimination.Elimination`), on which the compiled loops
        run; None with drivers, no such row, or where the formulation declines
        (``_eliminates``)."""
        from ..compiled.elimination import eliminate
        if self.cs.rheonomic or not self._eliminates():
            return None
        return eliminate(self.cs.con, self.M, self._frc)

    def _eliminates(self) -> bool:
        return True

    def compiled_candidate(self, method: str, h) -> bool:
        return False

    def prepare_compiled(self, q0: np.ndarray | None = None) -> Prepared:
        return Prepared(self.compiled_path, self._frc)

    def compiled_needs(self, q0: np.ndarray | None = None) -> tuple[str, ...]:
        """The compiled code a run takes (its path, :data:`natcoord.compiled.cache.PATHS`),
        decided without compiling anything."""
        return (self.compiled_path,)

    def compiled_runner(self, times, t0, q0, qd0, method, rtol, atol, h=None):
        """``go(Q, QD, QDD)``: the whole compiled run from (q0, qd0) at t0 into (T, n) in
        place, set up before the timed part (a benchmark repeats ``go``): by default
        ``init`` once here (Python set-up: maggi's partition of the start was a quarter of a
        four_bar run) and ``run_compiled`` at every call (the compiled loops copy their
        start, so every run begins from the same state). Its counts are added to the
        formulation's counters in the run, and it returns None (index1's returns its
        counter array instead, added once by the caller)."""
        y = self.init(t0, q0, qd0)

        def go(Q, QD, QDD):
            Q[:], QD[:], QDD[:] = self.run_compiled(times, y, method, rtol, atol, h)
        return go

    @functools.cached_property
    def _frc(self) -> tuple | None:
        """The model's forces packed for the compiled loops (:func:`compiled_forces`)."""
        return compiled_forces(self.model)

    def _compiled_model(self, methods) -> bool:
        """Whether the compiled loop may run with ``methods`` allowed: ``compiled`` on,
        numba present, scleronomic constraints and forces :func:`compiled_forces` knows."""
        from ..compiled import index1 as kernels
        return (bool(self.opt["compiled"]) and kernels.HAVE_NUMBA and bool(methods)
                and not self.cs.rheonomic and self._frc is not None)

    def _drift(self, t, q, qd):
        p, J, pt, _ = self.cs.all(q, qd, t)
        self.cnt.max_phi_step = max(self.cnt.max_phi_step, float(np.max(np.abs(p), initial=0)))
        self.cnt.max_phi_dot_step = max(self.cnt.max_phi_dot_step,
                                        float(np.max(np.abs(J @ qd + pt), initial=0)))
