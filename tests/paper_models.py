"""The examples of García de Jalón & Gutiérrez-López, built exactly as the paper writes them.

* :func:`five_bar`          Example 2 (Eqs. (76)-(86)): 8 coordinates (Eq. (84)), 8 rows of
                            rank 7, singular mass matrix;
* :func:`four_bar_3d`       Example 1: the 2-D four_bar in the Y-Z plane, revolutes along X,
                            three redundant constraints;
* :func:`parallelogram_3d`  Example 3 (Eqs. (95)-(115)), rigid (18 rows, rank 17) or with
                            the six rods as spring-dampers (``flexible=True``).

Geometry and loads are those of the case files of the same names. Each function returns a
:class:`PaperModel`: the model (dynamics protocol), its initial state, the duration, the row
weights of every reaction method, and :meth:`PaperModel.outputs` for the named channels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from natcoord.dynamics.forward import Solution, accelerations
from natcoord.model.builder import Builder
from natcoord.model.kinematics import State
from natcoord.model.model import GROUND, Model, plate_second_moment, rod_second_moment
from natcoord.outputs import reactions


@dataclass(frozen=True)
class PaperModel:
    """A paper example ready to integrate.

    Attributes
    ----------
    name : str
    model : Model
    state : State                 initial q (n,), qd (n,), consistent with the constraints
    duration : float              s
    methods : dict[str, (m,) or None]   row weights of each reaction method (None: min norm)
    unit : float                  model length unit in metres (1 m, or 1e-3 for mm);
                                  outputs are converted to SI (N)
    """

    name: str
    model: Model
    state: State
    duration: float
    methods: dict[str, np.ndarray | None] = field(default_factory=dict)
    unit: float = 1.0
    _outputs: object = None

    def reactions(self, sol, method: str = "min_norm") -> np.ndarray:
        """Multipliers (T, m) of the original rows along a Solution, for ``method``."""
        return reactions.along(self.model, sol.t, sol.q, sol.qd, sol.qdd, self.methods[method])

    def outputs(self, sol, method: str = "min_norm") -> dict[str, np.ndarray]:
        """Named channels (T,) along ``sol`` (SI: rad, N), reactions by ``method``."""
        return self._outputs(self, sol, method)


def integrate_stiff(model, state: State, times: np.ndarray, *, rtol: float = 1e-8,
                    atol: float = 1e-10) -> Solution:
    """Implicit (Radau IIA) integration of the index-1 equations, for stiff models such as
    the flexible parallelogram (spring-dampers of 17e6 N/m and 1e5 N s/m: eigenvalues near
    -1e4 1/s), where an explicit method needs ~1e5 steps for 2 s.

    Uses :func:`natcoord.dynamics.forward.accelerations`; no projection, so keep the run short or
    the tolerances tight (the drift is reported in ``counters["max_phi"]``).
    """
    n = model.n
    nrhs = 0

    def rhs(t, y):
        nonlocal nrhs
        nrhs += 1
        return np.concatenate([y[n:], accelerations(model, y[:n], y[n:], t)[0]])

    times = np.asarray(times, float)
    wall = time.perf_counter()
    s = solve_ivp(rhs, (times[0], times[-1]), np.concatenate([state.q, state.qd]),
                  method="Radau", t_eval=times, rtol=rtol, atol=atol)
    if not s.success:
        raise RuntimeError(f"Radau failed at t = {s.t[-1]:.6g} s: {s.message}")
    q, qd = s.y[:n].T, s.y[n:].T
    acc = [accelerations(model, q[k], qd[k], times[k]) for k in range(len(times))]
    qdd, lam = np.array([a[0] for a in acc]), np.array([a[1] for a in acc])
    drift = max(float(np.max(np.abs(model.constraints.phi(x)), initial=0.0)) for x in q)
    counters = {"rhs": nrhs, "steps": len(s.t), "nlu": s.nlu, "njev": s.njev,
                "max_phi": drift, "method": "Radau"}
    return Solution(times, q, qd, qdd, lam, counters, time.perf_counter() - wall)


# ---- Example 2: five-bar double parallelogram (Blajer) --------------------------------------
FIVE_BAR_K = 2.0  # k = |1-5| / |1-3|


def five_bar_weights(KL: float, KT: float, L1: float = 1.0, L2: float = 1.0,
                     unit: float = 1.0) -> np.ndarray:
    """Eq. (94): weights of rows (78), (80), (82), (83); the others (determined) are 1.

    Longitudinal stiffness of rods 3-4 and 5-6 ``KL * 2e5`` N/m, bending stiffness of
    bodies 1-3-5 and 2-4-6 as torsion springs ``KT * 5e4`` N m/rad. ``L1, L2`` in model
    units, ``unit`` the model's length unit in metres (N/m is the same in every length unit
    with consistent force units; N m/rad scales with length squared).
    """
    k_long, k_rot = KL * 2e5, KT * 5e4 / unit**2
    return reactions.stiffness_weights(8, {2: (k_rot, L1), 4: (k_rot, L1),
                                           6: (k_long, 2 * L2), 7: (k_long, 2 * L2)})


def five_bar(*, unit: float = 1.0, phi0_deg: float = 90.0, omega0: float = 1.0,
             torque: float = -200.0, gravity: bool = True) -> PaperModel:
    """Example 2 with q = [x3 y3 x4 y4 x5 y5 x6 y6] (Eq. (84)) and rows (76)-(83) in order.

    ``unit``: length unit of the model in metres (1e-3 builds it in millimetres: mm, kg, s,
    so forces are in mN internally; outputs stay in N).
    """
    f = 1.0 / unit  # model lengths per metre
    L1, L2, k = 1.0 * f, 1.0 * f, FIVE_BAR_K
    c, s = np.cos(np.radians(phi0_deg)), np.sin(np.radians(phi0_deg))
    e = np.array([c, s])
    r1, r2 = np.zeros(2), np.array([L2, 0.0])
    b = Builder(dim=2, gravity=np.array([0.0, -9.81 * f]) if gravity else np.zeros(2))
    for name, x in (("3", r1 + L1 * e), ("4", r2 + L1 * e), ("5", r1 + k * L1 * e),
                    ("6", r2 + k * L1 * e)):
        b.point(name, x)
    b.fixed_point("1", r1)
    b.fixed_point("2", r2)
    mass = 16.0
    for body, (p, mid) in {"135": ("1", "3"), "246": ("2", "4")}.items():
        x0, xm = b.elements[p].x0, b.elements[mid].x0
        b.body(body, [p, mid], mass=mass, com=xm,
               second_moment=rod_second_moment(mass, x0, x0 + k * (xm - x0)))  # (76), (77)
    b.attach("5", "135", name="5 in 135")  # (78), (79)
    b.attach("6", "246", name="6 in 246")  # (80), (81)
    b.rod("N34", "3", "4", L2)  # (82)
    b.rod("N56", "5", "6", L2)  # (83)
    b.torque("135", torque * f * f)
    model = b.build()
    J = np.array([[0.0, -1.0], [1.0, 0.0]])
    qd = np.zeros(8)
    for name, pivot in (("3", r1), ("4", r2), ("5", r1), ("6", r2)):
        qd[model.cols(name)] = omega0 * J @ (model.elements[name].x0 - pivot)
    scales = np.array([1 / L1**2, 1 / L1**2] + [1 / (k * L1)] * 4 + [1 / L2**2] * 2)
    methods = {"min_norm": None, "unit_invariant": scales,
               "weighted_KL1_KT1000": five_bar_weights(1, 1000, L1, L2, unit),
               "weighted_KL1000_KT1": five_bar_weights(1000, 1, L1, L2, unit)}
    return PaperModel("five_bar", model, State(model.q0.copy(), qd), 1.8, methods, unit,
                      _five_bar_outputs)


def _five_bar_outputs(pm: PaperModel, sol, method: str) -> dict[str, np.ndarray]:
    m = pm.model
    d = sol.q[:, m.cols("3")]  # r3 - r1, r1 = 0
    lam = pm.reactions(sol, method)
    force = pm.unit  # model force unit in N (kg * unit / s^2)
    return {"phi": np.unwrap(np.arctan2(d[:, 1], d[:, 0])),
            "N34": m.axial("N34", lam) * force, "N56": m.axial("N56", lam) * force}


def five_bar_null_vector(q: np.ndarray) -> np.ndarray:
    """Eq. (86): the basis vector of ker Phi_q^T at q (8,), as printed in the paper."""
    x3, x4, x5, x6 = q[0], q[2], q[4], q[6]
    return np.array([0, 0, 1, 0, -1, 0, -1 / (x4 - x3), 1 / (2 * (x6 - x5))])


# ---- Example 1: 3-D four-bar with parallel revolute axes ----------------------------------
def four_bar_3d() -> PaperModel:
    """The four_bar case moved into the Y-Z plane: ground pivots O = (0,0,0), D = (0,2,0),
    crank O-A 1 m, coupler A-C 2 m, rocker D-C 1.5 m, uniform rods of 1 kg/m, revolutes with
    their axes along X, gravity -z; released at rest with the crank at 60 deg.

    Each rod is a body of two points and two unit vectors (its X axis and the in-plane
    normal), so its mass matrix is singular (a slender rod has no inertia about its axis);
    each revolute is 3 coincidence + 2 alignment rows. 36 coordinates, 38 rows, rank 35.
    """
    th = np.radians(60.0)
    O, D = np.zeros(2), np.array([2.0, 0.0])
    A = np.array([np.cos(th), np.sin(th)])
    C = _circle_intersection(A, 2.0, D, 1.5)
    to3 = lambda p: np.array([0.0, p[0], p[1]])  # noqa: E731
    X = np.array([1.0, 0.0, 0.0])
    b = Builder(dim=3)
    rods = {"crank": (O, A), "coupler": (A, C), "rocker": (D, C)}
    for name, (p, r) in rods.items():
        e = to3(r - p) / np.linalg.norm(r - p)
        b.point(f"{name}.0", to3(p))
        b.point(f"{name}.1", to3(r))
        b.vector(f"{name}.u", X)
        b.vector(f"{name}.v", np.cross(X, e))
    for name, (p, r) in rods.items():
        L = float(np.linalg.norm(r - p))
        b.body(name, [f"{name}.0", f"{name}.1", f"{name}.u", f"{name}.v"], mass=L,
               com=to3((p + r) / 2), second_moment=rod_second_moment(L, to3(p), to3(r)))
    b.revolute("O", GROUND, "crank", to3(O), X)
    b.revolute("A", "crank", "coupler", to3(A), X)
    b.revolute("C", "coupler", "rocker", to3(C), X)
    b.revolute("D", GROUND, "rocker", to3(D), X)
    model = b.build()
    return PaperModel("four_bar_3d", model, State(model.q0.copy(), np.zeros(model.n)), 2.0,
                      {"min_norm": None,
                       "unit_invariant": reactions.unit_scales(model.constraints.length_dim)},
                      1.0, _four_bar_3d_outputs)


def _circle_intersection(p, rp, c, rc):
    """The intersection of circles (p, rp) and (c, rc) with the larger y."""
    d = np.linalg.norm(c - p)
    a = (rp**2 - rc**2 + d**2) / (2 * d)
    h = np.sqrt(rp**2 - a**2)
    e = (c - p) / d
    s = p + a * e
    cands = [s + h * np.array([-e[1], e[0]]), s - h * np.array([-e[1], e[0]])]
    return max(cands, key=lambda x: x[1])


def _four_bar_3d_outputs(pm: PaperModel, sol, method: str) -> dict[str, np.ndarray]:
    m = pm.model
    d = sol.q[:, m.cols("crank.1")] - sol.q[:, m.cols("crank.0")]
    lam = pm.reactions(sol, method)
    out = {"theta": np.unwrap(np.arctan2(d[:, 2], d[:, 1]))}
    for j in "OACD":
        for k, ax in enumerate("xyz"):
            out[f"{j}_{ax}"] = lam[:, m.rows[j][k]]
    return out


# ---- Example 3: 3-D parallelogram (Frączek & Wojtyra) -------------------------------------
PARALLELOGRAM_GROUND = {"A": (0.0, 0.0, 0.0), "C": (0.0, 0.6, 0.0), "E": (0.8, 0.6, 0.0),
                        "G": (0.8, 0.0, 0.0), "K": (-0.1, 0.0, 0.0), "M": (0.9, 0.6, 0.0)}
PARALLELOGRAM_RODS = (("A", "1"), ("C", "2"), ("E", "3"), ("G", "4"), ("K", "5"), ("M", "6"))
ROD_K, ROD_C, PLATE_FACTOR = 17e6, 1e5, 1e6


def parallelogram_weights(model: Model, k_rod: float = ROD_K,
                          k_plate: float = PLATE_FACTOR * ROD_K) -> np.ndarray:
    """Eq. (115): rods ``sqrt(k) / L``, the plate's warping rows (Eq. (105), point 4)
    ``sqrt(k_P) / 2``; every other row 1 (determined or never loaded by the
    self-equilibrating set)."""
    w = np.ones(model.m)
    for a, p in PARALLELOGRAM_RODS:
        name = f"{a}{p}"
        if name in model.rows:
            w[model.rows[name]] = np.sqrt(k_rod) / model.rod_length[name]
    w[model.rows["plate: 4"]] = 0.5 * np.sqrt(k_plate)
    return w


def parallelogram_3d(*, flexible: bool = False) -> PaperModel:
    """Example 3, Eqs. (95)-(106), with the geometry of cases/parallelogram_3d.toml.

    q = [r1 .. r6] (18). Rows: the six rod lengths A-1, C-2, E-3, G-4, K-5, M-6 (Eqs.
    (95)-(100)), plate distances 1-2, 2-3, 1-3, then the linear rows of point 4 (Eq. (105)),
    5 (Eq. (106)) and 6. Thin uniform 10 kg plate on points 1, 2, 3 (M singular on 4, 5, 6);
    10 N along +x at the plate's centre; released at rest; 2 s.

    ``flexible``: the rods are spring-dampers (17e6 N/m, 1e5 N s/m) instead of rows; the
    plate stays rigid (12 rows, 6 degrees of freedom).
    """
    off = np.array([0.0, 0.5, -0.8660254])
    g = {k: np.array(v) for k, v in PARALLELOGRAM_GROUND.items()}
    r = {"1": g["A"] + off, "2": g["C"] + off, "3": g["E"] + off, "4": g["G"] + off}
    r["5"], r["6"] = (r["1"] + r["4"]) / 2, (r["2"] + r["3"]) / 2
    b = Builder(dim=3)
    for k in "123456":
        b.point(k, r[k])
    for k, x in g.items():
        b.fixed_point(k, x)
    if not flexible:
        for a, p in PARALLELOGRAM_RODS:
            b.rod(f"{a}{p}", a, p)
    b.body("plate", ["1", "2", "3"], mass=10.0, com=(r["1"] + r["3"]) / 2,
           second_moment=plate_second_moment(10.0, r["2"] - r["1"], r["3"] - r["2"]),
           rigid=False)
    for a, p in (("1", "2"), ("2", "3"), ("1", "3")):
        b.distance(a, p, label=f"plate: |{a}{p}|")
    b.linear({"1": 1, "2": -1, "3": 1, "4": -1}, name="plate: 4")  # (105)
    b.linear({"1": 2, "2": -1, "3": 1, "5": -2}, name="plate: 5")  # (106)
    b.linear({"2": 1, "3": 1, "6": -2}, name="plate: 6")
    b.force("plate", (r["1"] + r["3"]) / 2, (10.0, 0.0, 0.0))
    if flexible:
        for a, p in PARALLELOGRAM_RODS:
            b.spring(f"{a}{p}", b.E(a), b.E(p), ROD_K, ROD_C)
    model = b.build()
    methods = {"min_norm": None}
    if not flexible:
        methods["unit_invariant"] = reactions.unit_scales(model.constraints.length_dim)
        methods["weighted"] = parallelogram_weights(model)
    name = "parallelogram_3d" + ("_flexible" if flexible else "")
    return PaperModel(name, model, State(model.q0.copy(), np.zeros(model.n)), 2.0, methods,
                      1.0, _parallelogram_outputs)


def _parallelogram_outputs(pm: PaperModel, sol, method: str) -> dict[str, np.ndarray]:
    m = pm.model
    d = sol.q[:, m.cols("1")] - PARALLELOGRAM_GROUND["A"]
    out = {"phi": np.unwrap(np.arctan2(d[:, 1], -d[:, 2]))}  # rod A-1 from the vertical
    if m.springs:
        out |= m.spring_tension(sol.q, sol.qd)
    else:
        lam = pm.reactions(sol, method)
        out |= {f"{a}{p}": m.axial(f"{a}{p}", lam) for a, p in PARALLELOGRAM_RODS}
    return out
