"""Sampled (q, v, a, lambda) back to natcoord quantities, in 3-D (dropped to the case's
dimension by :func:`natcoord.engines.planar.drop`).

Reactions: ``data.lambda_c`` is the force on joint1's contact frame (first body of the case
joint), in that frame's axes: the force on the second body is ``-R_c1 lambda``. Tree joints:
``rnea`` with the constraint forces, applied loads and springs as external forces;
``data.f[i]`` is then the force of the parent on the subtree through joint i in joint-i
axes, rotated to world and signed with :func:`natcoord.engines.tree.tree_orientation`
(``data.f`` after ``constraintDynamics`` is zero, hence the separate ``rnea``). A light
rod's axial force (tension positive) is its closing constraint force along the rod.
"""

from __future__ import annotations

import numpy as np

from ..planar import cross
from .model import Built


def _body_state(data, b: Built, name: str):
    """World origin (3,), rotation (3, 3), origin velocity (3,), omega (3,) of a body frame.
    A particle's frame never turns: it follows its (only) point at its t = 0 rotation."""
    jid, X = b.frame[name]
    oMi, vel = data.oMi[jid], data.v[jid]
    R = oMi.rotation
    if name in b.particles:
        p, R0 = b.particles[name]
        pl = X.act(p)
        return (oMi.act(pl) - R0 @ p, R0, R @ (vel.linear + cross(vel.angular, pl)),
                np.zeros(3))
    oMb = oMi * X
    return (oMb.translation, oMb.rotation, R @ (vel.linear + cross(vel.angular, X.translation)),
            R @ vel.angular)


def _constraint_forces(pin, data, loops, lam, fext, forces, rod_force, i, drift):
    """Add every closure's forces to ``fext`` (joint frames), store the reaction or the rod's
    axial force at sample i, and raise ``drift`` (position m, velocity m/s) to the opening."""
    zero3 = np.zeros(3)
    for n, lp in enumerate(loops):
        la = lam[3 * n:3 * n + 3]
        oMc1, oMc2 = data.oMi[lp.j1] * lp.M1, data.oMi[lp.j2] * lp.M2
        fw = oMc1.rotation @ la  # force on joint1's contact point, world axes
        fext[lp.j1] = fext[lp.j1] + lp.M1.act(pin.Force(la, zero3))
        fext[lp.j2] = fext[lp.j2] + lp.M2.act(pin.Force(-oMc2.rotation.T @ fw, zero3))
        if lp.kind == "joint":
            forces[lp.name][i] = -fw
        else:  # rod: tension pulls the tip towards the root
            e = oMc1.translation - data.oMi[lp.j1].translation
            rod_force[lp.name][i] = fw @ e / np.linalg.norm(e)
        drift[0] = max(drift[0], np.linalg.norm(oMc1.translation - oMc2.translation))
        vc1 = oMc1.rotation @ lp.M1.actInv(data.v[lp.j1]).linear
        vc2 = oMc2.rotation @ lp.M2.actInv(data.v[lp.j2]).linear
        drift[1] = max(drift[1], np.linalg.norm(vc1 - vc2))


def sample(pin, b: Built, dyn, loops, Q, V, A, L):
    """3-D samples of every body, joint, rod and spring, and the loop drift.

    Returns (origin, rotation, velocity, omega, forces, rod_force, drift): body -> (T, 3),
    (T, 3, 3), (T, 3), (T, 3); joint -> (T, 3) force on its second body, N; rod or spring ->
    (T,) tension, N; drift (2,): largest loop opening (m) and opening rate (m/s)."""
    model, case = b.model, b.lifted.case
    data = model.createData()
    T = len(Q)
    names = [x.name for x in case.bodies]
    origin = {n: np.empty((T, 3)) for n in names}
    velocity = {n: np.empty((T, 3)) for n in names}
    rotation = {n: np.empty((T, 3, 3)) for n in names}
    omega = {n: np.empty((T, 3)) for n in names}
    forces = {j.name: np.empty((T, 3)) for j in case.joints}
    rod_force = {x.name: np.empty(T) for x in case.rods} | {sp[0]: np.empty(T)
                                                            for sp in b.springs}
    drift = np.zeros(2)
    for i in range(T):
        q, v = Q[i], V[i]
        pin.forwardKinematics(model, data, q, v)
        for n in names:
            origin[n][i], rotation[n][i], velocity[n][i], omega[n][i] = _body_state(data, b, n)
        fl, tension = dyn.fext(q, v)
        for name, T_ in tension.items():
            rod_force[name][i] = T_
        fext = pin.StdVec_Force()
        for x in fl:
            fext.append(pin.Force(x))
        _constraint_forces(pin, data, loops, L[i], fext, forces, rod_force, i, drift)
        pin.rnea(model, data, q, v, A[i], fext)
        for name, jid, sign in b.tree:
            forces[name][i] = sign * (data.oMi[jid].rotation @ data.f[jid].linear)
    return origin, rotation, velocity, omega, forces, rod_force, drift
