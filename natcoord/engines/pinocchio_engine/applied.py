"""Applied loads and spring-dampers as forces in Pinocchio joint frames, one compiled call.

The right-hand side of an explicit integrator calls this four times a step (stiff springs:
2e5 steps), so the loads and springs of every body are packed once into arrays per *slot*
(slot 0 the ground: identity pose, at rest; slot s >= 1 the s-th loaded joint) and one numba
kernel computes them all: no Python loop, no temporary arrays per spring.

* Load: force ``f`` (3,) N at point ``p`` (3,) m (joint frame) and torque ``m`` (3,) N m,
  constant in world axes: ``R^T f`` and ``p x R^T f + R^T m``; or body-fixed (``local``, in
  the joint frame already): ``f`` and ``p x f + m``.
* Spring-damper between points ``Pa`` of slot ``a`` and ``Pb`` of slot ``b``: tension
  ``T = k (l - l0) + c dl/dt`` (N, > 0 pulls the ends together), ``+T e`` on ``a`` and ``-T e``
  on ``b``, ``e`` the unit vector from a's end to b's.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Packed rows (few arguments: numba's dispatch costs ~0.3 us per argument, 4 calls a step):
# a slot: R (row-major, 9), t (3), V (linear, angular in joint axes, 6);
# a load: slot, p (3), f (3), m (3), the slot whose rotation turns f and m into joint axes
# (its own; 0, the identity, for a body-fixed load); a spring: slot a, slot b, Pa (3),
# Pb (3), k, c, l0.
SLOT, LOAD, SPRING = 18, 11, 11


@njit(cache=True)
def _add(F, X, s, r, P, f0, f1, f2):
    """F[s] += the force f at the point P (3,) (joint frame) of slot s, in joint axes: f in
    world axes turned by slot r's rotation (r = s; r = 0, the identity, when f is in joint
    axes already)."""
    R = X[r]
    a0 = R[0] * f0 + R[3] * f1 + R[6] * f2  # R^T f
    a1 = R[1] * f0 + R[4] * f1 + R[7] * f2
    a2 = R[2] * f0 + R[5] * f1 + R[8] * f2
    F[s, 0] += a0
    F[s, 1] += a1
    F[s, 2] += a2
    F[s, 3] += P[1] * a2 - P[2] * a1
    F[s, 4] += P[2] * a0 - P[0] * a2
    F[s, 5] += P[0] * a1 - P[1] * a0


@njit(cache=True)
def _point(X, s, P, r, u):
    """World position r (3,) and velocity u (3,) of point P (3,) (joint frame) of slot s."""
    x = X[s]
    b0 = x[12] + x[16] * P[2] - x[17] * P[1]  # v + w x P, joint axes
    b1 = x[13] + x[17] * P[0] - x[15] * P[2]
    b2 = x[14] + x[15] * P[1] - x[16] * P[0]
    for i in range(3):
        r[i] = x[3 * i] * P[0] + x[3 * i + 1] * P[1] + x[3 * i + 2] * P[2] + x[9 + i]
        u[i] = x[3 * i] * b0 + x[3 * i + 1] * b1 + x[3 * i + 2] * b2


@njit(cache=True)
def joint_forces(X, L, S, F, T):
    """Fill F (slots, 6) (force, moment in joint axes; row 0, the ground, unused) and the
    tensions T (springs,) from the slots X (slots, SLOT), loads L (loads, LOAD) and springs
    S (springs, SPRING)."""
    F[:] = 0.0
    for i in range(L.shape[0]):
        s, r = int(L[i, 0]), int(L[i, 10])
        _add(F, X, s, r, L[i, 1:4], L[i, 4], L[i, 5], L[i, 6])
        R = X[r]
        m0, m1, m2 = L[i, 7], L[i, 8], L[i, 9]
        F[s, 3] += R[0] * m0 + R[3] * m1 + R[6] * m2
        F[s, 4] += R[1] * m0 + R[4] * m1 + R[7] * m2
        F[s, 5] += R[2] * m0 + R[5] * m1 + R[8] * m2
    ra, va, rb, vb = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for i in range(S.shape[0]):
        sa, sb = int(S[i, 0]), int(S[i, 1])
        _point(X, sa, S[i, 2:5], ra, va)
        _point(X, sb, S[i, 5:8], rb, vb)
        d0, d1, d2 = rb[0] - ra[0], rb[1] - ra[1], rb[2] - ra[2]
        ln = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        e0, e1, e2 = d0 / ln, d1 / ln, d2 / ln
        T[i] = S[i, 8] * (ln - S[i, 10]) + S[i, 9] * (
            (vb[0] - va[0]) * e0 + (vb[1] - va[1]) * e1 + (vb[2] - va[2]) * e2)
        if sa:
            _add(F, X, sa, sa, S[i, 2:5], T[i] * e0, T[i] * e1, T[i] * e2)
        if sb:
            _add(F, X, sb, sb, S[i, 5:8], -T[i] * e0, -T[i] * e1, -T[i] * e2)


def is_view(read) -> bool:
    """Whether ``read()`` returns a view of the binding's storage (two reads share memory),
    not a copy: a view read once follows every later change."""
    return bool(np.shares_memory(read(), read()))


class Applied:
    """The loads ((joint, p, f, m) or (joint, p, f, m, local): ``model.Built.loads``) and
    springs (``.springs``) of a built model packed per slot, read from the Pinocchio ``data``
    whose kinematics the caller updates; ``joints`` the loaded joint ids (slot s is
    ``joints[s - 1]``), ``names`` the springs'."""

    def __init__(self, loads: list, springs: list, data):
        self.joints = sorted({x[0] for x in loads} | {e[0] for sp in springs
                                                      for e in sp[1:3]} - {0})
        slot = {0: 0} | {j: s for s, j in enumerate(self.joints, 1)}
        self.X = np.zeros((len(self.joints) + 1, SLOT))
        self.X[0, :9] = np.eye(3).ravel()  # the ground: identity, at rest
        # (destination, read): a slot's rows, and data's placement and velocity, read once
        # as views of its Eigen storage (rewritten in place by forwardKinematics) when the
        # bindings give views, else read at every call
        reads = [(self.X[s, a:b].reshape(shape), read)
                 for s, j in enumerate(self.joints, 1)
                 for a, b, shape, read in ((0, 9, (3, 3), lambda j=j: data.oMi[j].rotation),
                                           (9, 12, (3,), lambda j=j: data.oMi[j].translation),
                                           (12, 18, (6,), lambda j=j: data.v[j].vector))]
        self.live = all(is_view(read) for _, read in reads)
        self.copies = [(dst, read() if self.live else read) for dst, read in reads]
        self.L = np.array([[slot[j], *p, *f, *m, 0 if local and local[0] else slot[j]]
                           for j, p, f, m, *local in loads], dtype=float).reshape(-1, LOAD)
        self.S = np.array([[slot[a[0]], slot[b[0]], *a[1], *b[1], k, c, l0]
                           for _, a, b, k, c, l0 in springs], dtype=float).reshape(-1, SPRING)
        self.F = np.zeros((len(self.X), 6))
        self.names = [sp[0] for sp in springs]
        self.T = np.zeros(len(springs))

    def __call__(self):
        """Forces (slots, 6) from the joint placements and velocities of ``data`` (after
        ``forwardKinematics``); the spring tensions stay in ``self.T`` (N). Both arrays are
        rewritten by the next call."""
        for dst, src in self.copies:
            dst[...] = src if self.live else src()
        joint_forces(self.X, self.L, self.S, self.F, self.T)
        return self.F
