"""The spatial derivation's equations compiled with numba (see :mod:`.spatial`).

One implementation of the body-coordinate equations, called by :class:`.spatial.SpatialModel`
at every right-hand side (:func:`rhs`, :func:`jacobian`) and at every output sample
(constraints, loads, springs). Arrays only, so numba compiles them once per machine
(``cache=True``). Shapes: n moving bodies, the ground is body n (at rest, world frame);
state y (13 n + 2,): r (3 n), Euler parameters p (4 n), (v, w) per body (6 n), the work W
of applied loads and dampers and the dampers' part of it (J).

The model's constant tables (``tables``, built by ``SpatialModel``), in this order:

* mass (n,), inertia (n, 3, 3) body frame, gravity (3,)
* terms: tb (T,) body, tp (T,) 1.0 for a point 0.0 for a direction, ts (T, 3) its body
  vector (from the centre of mass for a point); S (E, T) each expression's coefficients
* rows: comp (C, 4) [row, expression, component, value], dot (D, 5) [row, expression 1,
  expression 2, value, scale]; m the number of rows
* forces: fb (F,) body, ft (F,) 1.0 for a force 0.0 for a torque, + 2.0 when fv is in the
  body's axes (else world), fv (F, 3) value, fs (F, 3) point from the centre of mass (body
  frame)
* springs: sb (K, 2) bodies, ss (K, 2, 3) points from each centre of mass (body frame),
  sk (K, 3) stiffness (N/m), damping (N s/m), rest length (m)
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def cross(a, b):
    return np.array([a[1]*b[2] - a[2]*b[1], a[2]*b[0] - a[0]*b[2], a[0]*b[1] - a[1]*b[0]])


@njit(cache=True)
def rotation(p):
    """Rotation matrix (3, 3) of Euler parameters p (4,), normalised here."""
    e0, e1, e2, e3 = p / np.sqrt(p @ p)
    return np.array([
        [e0*e0 + e1*e1 - e2*e2 - e3*e3, 2*(e1*e2 - e0*e3), 2*(e1*e3 + e0*e2)],
        [2*(e1*e2 + e0*e3), e0*e0 - e1*e1 + e2*e2 - e3*e3, 2*(e2*e3 - e0*e1)],
        [2*(e1*e3 - e0*e2), 2*(e2*e3 + e0*e1), e0*e0 - e1*e1 - e2*e2 + e3*e3]])


@njit(cache=True)
def kinematics(y, n):
    """r, v, w (n + 1, 3) and R (n + 1, 3, 3) of every body, the ground last."""
    r, v, w = np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros((n + 1, 3))
    R = np.zeros((n + 1, 3, 3))
    for i in range(n):
        r[i] = y[3*i:3*i + 3]
        R[i] = rotation(y[3*n + 4*i:3*n + 4*i + 4])
        v[i] = y[7*n + 6*i:7*n + 6*i + 3]
        w[i] = y[7*n + 6*i + 3:7*n + 6*i + 6]
    R[n] = np.eye(3)
    return r, R, v, w


@njit(cache=True)
def constraints(r, R, v, w, tb, tp, ts, S, comp, dot, m):
    """Phi (m,), G (m, 6 (n + 1)) over every body's (v, w) and gamma (m,), with
    Phi'' = G nu' + gamma."""
    n1 = r.shape[0]
    T, E = tb.shape[0], S.shape[0]
    val, vel, acc = np.zeros((E, 3)), np.zeros((E, 3)), np.zeros((E, 3))
    J = np.zeros((E, 3, 6 * n1))
    for t in range(T):
        b = tb[t]
        d = R[b] @ ts[t]
        wd = cross(w[b], d)
        wwd = cross(w[b], wd)
        for e in range(E):
            c = S[e, t]
            if c == 0.0:
                continue
            for k in range(3):
                val[e, k] += c * (tp[t] * r[b, k] + d[k])
                vel[e, k] += c * (tp[t] * v[b, k] + wd[k])
                acc[e, k] += c * wwd[k]
                J[e, k, 6*b + k] += c * tp[t]
            # -skew(d): the rows of d x (.) over w
            J[e, 0, 6*b + 4] += c * d[2]
            J[e, 0, 6*b + 5] -= c * d[1]
            J[e, 1, 6*b + 3] -= c * d[2]
            J[e, 1, 6*b + 5] += c * d[0]
            J[e, 2, 6*b + 3] += c * d[1]
            J[e, 2, 6*b + 4] -= c * d[0]
    phi, gam, G = np.zeros(m), np.zeros(m), np.zeros((m, 6 * n1))
    for i in range(comp.shape[0]):
        row, e, k = int(comp[i, 0]), int(comp[i, 1]), int(comp[i, 2])
        phi[row] = val[e, k] - comp[i, 3]
        gam[row] = acc[e, k]
        G[row] = J[e, k]
    for i in range(dot.shape[0]):
        row, e1, e2, sc = int(dot[i, 0]), int(dot[i, 1]), int(dot[i, 2]), dot[i, 4]
        phi[row] = sc * (val[e1] @ val[e2] - dot[i, 3])
        gam[row] = sc * (acc[e1] @ val[e2] + val[e1] @ acc[e2] + 2 * (vel[e1] @ vel[e2]))
        for k in range(3):
            G[row] += sc * (val[e1, k] * J[e2, k] + val[e2, k] * J[e1, k])
    return phi, G, gam


@njit(cache=True)
def springs(r, R, v, w, sb, ss, sk):
    """Per spring: tension (N), rate of length (m/s), length (m), unit vector (3,) from its
    first end to its second and each end's arm from its body's centre of mass (world)."""
    K = sb.shape[0]
    tension, ldot, length = np.zeros(K), np.zeros(K), np.zeros(K)
    u, arm = np.zeros((K, 3)), np.zeros((K, 2, 3))
    for s in range(K):
        x, xd = np.zeros((2, 3)), np.zeros((2, 3))
        for j in range(2):
            b = sb[s, j]
            d = R[b] @ ss[s, j]
            arm[s, j] = d
            x[j] = r[b] + d
            xd[j] = v[b] + cross(w[b], d)
        g = x[1] - x[0]
        length[s] = np.sqrt(g @ g)
        u[s] = g / length[s]
        ldot[s] = u[s] @ (xd[1] - xd[0])
        tension[s] = sk[s, 0] * (length[s] - sk[s, 2]) + sk[s, 1] * ldot[s]
    return tension, ldot, length, u, arm


@njit(cache=True)
def loads(r, R, v, w, mass, inertia, gravity, fb, ft, fv, fs, sb, ss, sk):
    """Q (n + 1, 6): force and moment about the centre of mass per body (gravity, applied
    loads, springs, gyroscopic; the ground's row collects what acts on it), the power (W)
    of the applied loads and dampers, and the dampers' part of it."""
    n = mass.shape[0]
    Q = np.zeros((n + 1, 6))
    power, damping = 0.0, 0.0
    for i in range(n):
        Q[i, :3] += mass[i] * gravity
        Iw = R[i] @ inertia[i] @ R[i].T
        Q[i, 3:] -= cross(w[i], Iw @ w[i])
    for f in range(fb.shape[0]):
        i = fb[f]
        val = R[i] @ fv[f] if ft[f] >= 2.0 else fv[f]  # 2, 3: in the body's axes
        if ft[f] == 0.0 or ft[f] == 2.0:  # torque
            Q[i, 3:] += val
            power += val @ w[i]
        else:
            d = R[i] @ fs[f]
            Q[i, :3] += val
            Q[i, 3:] += cross(d, val)
            power += val @ (v[i] + cross(w[i], d))
    tension, ldot, _, u, arm = springs(r, R, v, w, sb, ss, sk)
    for s in range(sb.shape[0]):
        for j in range(2):
            f = tension[s] * u[s] if j == 0 else -tension[s] * u[s]
            b = sb[s, j]
            Q[b, :3] += f
            Q[b, 3:] += cross(arm[s, j], f)
        damping -= sk[s, 1] * ldot[s] ** 2
    return Q, power + damping, damping


@njit(cache=True)
def independent_rows(G, rank):
    """Indices of ``rank`` rows of G (m, k), the best conditioned: Gram-Schmidt with
    pivoting (QR with column pivoting of G^T)."""
    m = G.shape[0]
    Rs = G.copy()
    norms = np.zeros(m)
    for i in range(m):
        norms[i] = np.sqrt(Rs[i] @ Rs[i])
    used = np.zeros(m, np.bool_)
    keep = np.empty(m, np.int64)
    count = 0
    for _ in range(rank):
        best, big = -1, -1.0
        for i in range(m):
            if not used[i] and norms[i] > big:
                best, big = i, norms[i]
        used[best] = True
        keep[count] = best
        count += 1
        q = Rs[best] / big
        for i in range(m):
            if not used[i]:
                Rs[i] -= (Rs[i] @ q) * q
                norms[i] = np.sqrt(Rs[i] @ Rs[i])
    return np.sort(keep[:count])


@njit(cache=True)
def accelerations(y, rank, mass, inertia, gravity, tb, tp, ts, S, comp, dot, m,
                  fb, ft, fv, fs, sb, ss, sk):
    """nu' (6 n,), the independent rows (indices) and their multipliers, and the powers
    (W) of :func:`loads`: [M G_k^T; G_k 0] [nu'; lam] = [Q; -gamma_k], M block-diagonal
    (m I, R I R^T; a uniform rod's inertia is singular, so no M^-1), G_k the ``rank`` rows
    :func:`independent_rows` picks at this state. Redundant rows add nothing to the motion;
    a set chosen once turns singular (a04_bricard's at t = 0 by 1.25 s: its condition
    number 21 -> 1.1e4), and a rank judged per call by a threshold takes the redundant row
    where the integrator's stages leave the constraints (1e-7 m measured): the blow-up."""
    n = mass.shape[0]
    r, R, v, w = kinematics(y, n)
    Q, power, damping = loads(r, R, v, w, mass, inertia, gravity, fb, ft, fv, fs, sb, ss,
                              sk)
    _, G, gam = constraints(r, R, v, w, tb, tp, ts, S, comp, dot, m)
    keep = independent_rows(G[:, :6 * n], rank)
    k, mk = 6 * n, keep.shape[0]
    A = np.zeros((k + mk, k + mk))
    b = np.zeros(k + mk)
    for i in range(n):
        for j in range(3):
            A[6*i + j, 6*i + j] = mass[i]
        A[6*i + 3:6*i + 6, 6*i + 3:6*i + 6] = R[i] @ inertia[i] @ R[i].T
        b[6*i:6*i + 6] = Q[i]
    for a in range(mk):
        A[k + a, :k] = G[keep[a], :k]
        A[:k, k + a] = G[keep[a], :k]
        b[k + a] = -gam[keep[a]]
    x = np.linalg.solve(A, b)
    return x[:k], keep, x[k:], power, damping


@njit(cache=True)
def rhs(y, rank, mass, inertia, gravity, tb, tp, ts, S, comp, dot, m,
        fb, ft, fv, fs, sb, ss, sk):
    """y' (13 n + 2,): v, p' = (0, w) * p / 2, nu', the power of loads and dampers, the
    dampers'."""
    n = mass.shape[0]
    acc, _, _, power, damping = accelerations(y, rank, mass, inertia, gravity, tb, tp, ts, S, comp,
                                  dot, m, fb, ft, fv, fs, sb, ss, sk)
    out = np.empty_like(y)
    out[:3*n] = y[7*n:13*n].reshape(n, 2, 3)[:, 0].copy().reshape(3 * n)
    for i in range(n):
        p = y[3*n + 4*i:3*n + 4*i + 4]
        wx, wy, wz = y[7*n + 6*i + 3], y[7*n + 6*i + 4], y[7*n + 6*i + 5]
        out[3*n + 4*i] = 0.5 * (-wx*p[1] - wy*p[2] - wz*p[3])
        out[3*n + 4*i + 1] = 0.5 * (wx*p[0] + wy*p[3] - wz*p[2])
        out[3*n + 4*i + 2] = 0.5 * (wy*p[0] + wz*p[1] - wx*p[3])
        out[3*n + 4*i + 3] = 0.5 * (wz*p[0] + wx*p[2] - wy*p[1])
    out[7*n:13*n] = acc
    out[13*n] = power
    out[13*n + 1] = damping
    return out


@njit(cache=True)
def jacobian(y, f0, rank, mass, inertia, gravity, tb, tp, ts, S, comp, dot, m,
             fb, ft, fv, fs, sb, ss, sk):
    """d y' / d y (N, N) by forward differences (f0 = rhs(y)), each column's step
    sqrt(eps) max(|y_j|, 1e-3)."""
    N = y.shape[0]
    out = np.zeros((N, N))
    h0 = np.sqrt(np.finfo(np.float64).eps)
    for j in range(N):
        yj = y.copy()
        h = h0 * max(abs(y[j]), 1e-3)
        yj[j] += h
        h = yj[j] - y[j]
        out[:, j] = (rhs(yj, rank, mass, inertia, gravity, tb, tp, ts, S, comp, dot, m,
                         fb, ft, fv, fs, sb, ss, sk) - f0) / h
    return out
