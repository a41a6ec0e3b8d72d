"""Compile, start, step and sample a MuJoCo model; refuse a run MuJoCo silently reset or
whose soft constraints let go."""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import Case
from ..planar import Samples
from .forces import Reactions, applied_loads


def load_model(mujoco, case: Case, build):
    """(built, model, data, build time, s): ``build()`` compiled, started at the built
    velocities with the lifted case's constant loads applied."""
    t0 = time.perf_counter()
    built = build()
    m = mujoco.MjModel.from_xml_string(built.xml)
    d = mujoco.MjData(m)
    seconds = time.perf_counter() - t0
    if len(built.qvel) != m.nv:
        raise RuntimeError(f"internal: {len(built.qvel)} initial velocities for nv = {m.nv}")
    d.qpos[:] = m.qpos0  # the XML places every body at its assembled pose
    d.qvel[:] = built.qvel
    d.xfrc_applied[:] = applied_loads(mujoco, m, case)
    return built, m, d, seconds


def forward(mujoco, m, d) -> int:
    """Positions, velocities, constraint and interaction forces at the current state (not
    those of the step that produced it); the solver's iteration count."""
    mujoco.mj_forward(m, d)
    mujoco.mj_rnePostConstraint(m, d)
    return int(d.solver_niter[0])


def forward_start(mujoco, m, d) -> int:
    """:func:`forward` at the assembled state (t = 0), with the equality constraints' forces
    those of the full acceleration: J qacc = -Jdot qdot, hard. MuJoCo's reference
    acceleration there is 0 (no position or velocity error yet to feed back), so its
    efc_force would lack the Jdot qdot term (a rod's m v^2 / L) and carry only solimp's
    fraction of the rest until its stabilisation builds up over the first steps. Jdot qdot
    of each row: the second derivative of its efc_pos along the geodesic q(s) =
    integratePos(q, qvel, s), by a fourth-order central difference; redundant rows (a
    planar loop's) share their force as MuJoCo's regularisation does in its hard limit. A
    state with constraint rows other than equalities keeps MuJoCo's own forces."""
    niter = forward(mujoco, m, d)
    eq = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    if d.nefc == 0 or not np.all(eq):
        return niter
    scratch = mujoco.MjData(m)
    step = 1e-3 / max(1.0, float(np.max(np.abs(d.qvel))))

    def pos(s: float) -> np.ndarray:
        scratch.qpos[:] = d.qpos
        mujoco.mj_integratePos(m, scratch.qpos, d.qvel, s)
        mujoco.mj_fwdPosition(m, scratch)
        return scratch.efc_pos[:d.nefc].copy()

    jdqd = (-pos(2 * step) + 16 * pos(step) - 30 * pos(0.0) + 16 * pos(-step)
            - pos(-2 * step)) / (12 * step**2)
    J = np.zeros((d.nefc, m.nv))
    if mujoco.mj_isSparse(m):
        mujoco.mju_sparse2dense(J, d.efc_J, d.efc_J_rownnz, d.efc_J_rowadr, d.efc_J_colind)
    else:
        J[:] = d.efc_J[:d.nefc * m.nv].reshape(d.nefc, m.nv)
    MinvJt = np.zeros((m.nv, d.nefc))
    for k in range(d.nefc):
        col = np.zeros(m.nv)
        mujoco.mj_solveM(m, d, col[None], J[k][None])
        MinvJt[:, k] = col
    A = J @ MinvJt  # singular where rows are redundant (a planar loop's out-of-plane rows):
    # the limit of MuJoCo's regularisation, R proportional to diag(A), picks the solution of
    # least sum f^2 diag(A)
    w = np.sqrt(np.maximum(np.diag(A), 1e-300))
    g = np.linalg.lstsq(A / np.outer(w, w), (-jdqd - J @ d.qacc_smooth) / w, rcond=1e-10)[0]
    force = g / w
    d.efc_force[:d.nefc] = force
    d.qfrc_constraint[:] = J.T @ force
    d.qacc[:] = d.qacc_smooth + MinvJt @ force
    mujoco.mj_rnePostConstraint(m, d)
    return niter


def check_state(mujoco, d, t_expected: float) -> None:
    """MuJoCo resets an unstable simulation and only warns: turn that into a failure."""
    bad = [mujoco.mjtWarning(i).name for i in range(int(mujoco.mjtWarning.mjNWARNING))
           if d.warning[i].number > 0]
    if bad:
        raise RuntimeError(f"MuJoCo warned ({', '.join(bad)}) by t = {t_expected:.6g} s: the "
                           "simulation became unstable and MuJoCo reset its state")
    if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
            and np.all(np.isfinite(d.qacc))):
        raise RuntimeError(f"MuJoCo state is not finite at t = {d.time:.6g} s")
    if abs(d.time - t_expected) > 1e-6 * max(1.0, t_expected):
        raise RuntimeError(f"MuJoCo time {d.time:.6g} s, expected {t_expected:.6g} s: the "
                           "state was reset")


class Sampler:
    """Fills :class:`Samples` from an MjData, one sample at a time.

    A particle's frame keeps the rotation it started with (identity) and no angular
    velocity, its origin following its point: MuJoCo turns a welded particle with its parent.
    """

    def __init__(self, mujoco, m, d, case: Case, built):
        self.mujoco, self.m, self.d, self.case = mujoco, m, d, case
        self.reactions = Reactions(mujoco, m, case, built)
        self.bid = self.reactions.bid
        self.out = Samples.empty(case, len(case.times))
        self.drift = 0.0  # m, the largest loop or rod violation so far
        self.max_iter = 0
        self._vel6 = np.zeros(6)
        self._acc6 = np.zeros(6)
        T = len(case.times)
        self.out.acceleration = {b.name: np.zeros((T, 3)) for b in case.bodies}
        self.out.alpha = {b.name: np.zeros((T, 3)) for b in case.bodies}

    def sample(self, i: int) -> None:
        mj, d, out = self.mujoco, self.d, self.out
        self.max_iter = max(self.max_iter, (forward_start if i == 0 else forward)(mj, self.m, d))
        for b in self.case.bodies:
            j = self.bid[b.name]
            R = d.xmat[j].reshape(3, 3)
            mj.mj_objectVelocity(self.m, d, mj.mjtObj.mjOBJ_XBODY, j, self._vel6, 0)
            w, v = self._vel6[:3], self._vel6[3:]
            # classical acceleration of the frame origin (MuJoCo adds w x v to the spatial
            # one), from the cacc of forward's mj_rnePostConstraint, whose world body
            # accelerates by -gravity (an accelerometer's reading): add gravity back
            mj.mj_objectAcceleration(self.m, d, mj.mjtObj.mjOBJ_XBODY, j, self._acc6, 0)
            al, a = self._acc6[:3], self._acc6[3:] + self.m.opt.gravity
            if b.kind == "particle":
                p = next(iter(b.points.values()))
                rp = R @ p
                out.origin[b.name][i] = d.xpos[j] + rp - p
                out.rotation[b.name][i] = np.eye(3)
                out.velocity[b.name][i] = v + np.cross(w, rp)
                out.acceleration[b.name][i] = a + np.cross(al, rp) + np.cross(w, np.cross(w, rp))
            else:
                out.origin[b.name][i] = d.xpos[j]
                out.rotation[b.name][i] = R
                out.velocity[b.name][i] = v
                out.omega[b.name][i] = w
                out.acceleration[b.name][i] = a
                out.alpha[b.name][i] = al
        self.drift = max(self.drift, self.reactions.read(d, out.forces, out.rod_force, i))



def step_samples(mujoco, m, d, T: int, k: int, at_sample) -> tuple[float, int]:
    """Samples 1 .. T-1, ``k`` steps apart, ``at_sample(i)`` after each; (wall time of the
    steps, s, number of steps)."""
    wall = 0.0
    n_steps = 0
    for i in range(1, T):
        w0 = time.perf_counter()
        for _ in range(k):
            mujoco.mj_step(m, d)
        wall += time.perf_counter() - w0
        n_steps += k
        at_sample(i)
    return wall, n_steps
