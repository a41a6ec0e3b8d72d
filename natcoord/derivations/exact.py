"""Exact solutions of catalogue problems, independent of natcoord's model and integrators.

* :func:`a01_pendulum`: IFToMM A01, the simple pendulum released at rest from horizontal, in
  closed form by Jacobi elliptic functions.
* :func:`n_four_bar`: IFToMM A02, the N-four-bar, reduced exactly to one equation in the
  crank angle and integrated by scipy's DOP853 at a tight tolerance.

Both return arrays over the given sample times (T,), SI units.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import ellipj, ellipk

G = 9.81  # m/s^2, both problems


def a01_pendulum(t: np.ndarray, *, g: float = G, length: float = 1.0) -> dict[str, np.ndarray]:
    """Point mass on a massless link, pivot at the origin, released at rest with the link
    along +x (90 deg from the downward vertical).

    phi(t) = 2 asin(k sn(K - w t, k^2)), k = sin(45 deg), w = sqrt(g / L), phi measured from
    the downward vertical, counter-clockwise. The argument is reduced modulo the period 4K
    of sn so that its size (about 6e3 at 2000 s) costs no accuracy.

    Returns ``theta`` (link angle from +x, rad: phi - pi/2), ``x``, ``y`` (m), ``phi_dot``
    (rad/s) and ``period`` (s).
    """
    t = np.asarray(t, float)
    k = np.sin(np.pi / 4)
    K, w = ellipk(k**2), np.sqrt(g / length)
    u = np.mod(K - w * t, 4 * K)
    sn, cn, _, _ = ellipj(u, k**2)
    phi = 2 * np.arcsin(k * sn)
    return {"theta": phi - np.pi / 2, "x": length * np.sin(phi), "y": -length * np.cos(phi),
            "phi_dot": -2 * k * w * cn, "period": 4 * K / w}


def n_four_bar_coefficients(n: int, *, g: float = G) -> tuple[float, float]:
    """(J, c) of the reduced N-four-bar, J phi'' = -c g cos(phi).

    N + 1 cranks (uniform rods, m = 1 kg, L = 1 m) turn about their ground pivots by the same
    angle phi (from +x), so the N couplers (same rods) translate with the crank tips.
    Kinetic energy: cranks (N + 1) m L^2 / 6 phi'^2, couplers N m L^2 / 2 phi'^2, so
    J = (N + 1) m L^2 / 3 + N m L^2. Potential energy: crank centres at L/2 sin(phi),
    couplers at L sin(phi): V = c g sin(phi), c = m L ((N + 1) / 2 + N). Lagrange's equation
    in the one coordinate phi gives J phi'' = -c g cos(phi); exact for every N, through
    the singular positions (phi = 0, pi) where the constraint Jacobian loses rank N.
    Returns J (kg m^2) and c (kg m).
    """
    if n < 1:
        raise ValueError(f"N must be at least 1, got {n}")
    return (n + 1) / 3 + n, (n + 1) / 2 + n


def n_four_bar(n: int, t: np.ndarray, *, phi0: float = np.pi / 2, rate0: float = -1.0,
               rtol: float = 1e-13, atol: float = 1e-15, g: float = G) -> dict[str, np.ndarray]:
    """IFToMM A02 from the reduced equation J phi'' = -c g cos(phi) (see
    :func:`n_four_bar_coefficients`), integrated by scipy's DOP853 at ``rtol``/``atol`` with
    dense output at the sample times ``t`` (s, (T,), starting at 0).

    Default start: cranks vertical up (phi = pi/2), phi' = -1 rad/s, so the tip B0 of the
    leftmost crank (pivot at the origin) starts at (0, 1) m with velocity (+1, 0) m/s.

    Returns ``phi`` (rad), ``phi_dot`` (rad/s), B0's ``x``, ``y`` (m), ``vx``, ``vy``
    (m/s) and ``energy`` (kinetic + gravitational, J, zero at y = 0 for every centre).
    """
    t = np.asarray(t, float)
    J, c = n_four_bar_coefficients(n, g=g)

    def rhs(_, s):
        return [s[1], -c * g * np.cos(s[0]) / J]

    sol = solve_ivp(rhs, (t[0], t[-1]), [phi0, rate0], method="DOP853", t_eval=t,
                    rtol=rtol, atol=atol)
    if not sol.success:  # pragma: no cover - a smooth ODE at these tolerances
        raise RuntimeError(f"n_four_bar reference: {sol.message}")
    phi, phid = sol.y
    return {"phi": phi, "phi_dot": phid, "x": np.cos(phi), "y": np.sin(phi),
            "vx": -np.sin(phi) * phid, "vy": np.cos(phi) * phid,
            "energy": 0.5 * J * phid**2 + c * g * np.sin(phi)}
