"""MuJoCo, 3-D cases and massless rods / spring-dampers (any dimension).

Companion of :mod:`natcoord.engines.mujoco_engine` (which owns the 2-D tree builder and the
shared run checks). Modelling choices, each repeated in ``EngineRun.notes`` when it applies:

* Tree: :func:`natcoord.engines.tree.spanning_tree` as in 2-D. Revolute tree joints are hinges
  about the case's axis, spherical ones balls; a body not reached from the ground gets a
  free joint. Loop-closing revolute or spherical joints are ``connect``
  equalities between two sites (3 rows: a loop revolute's axis alignment is left to the tree,
  so the redundancy differs from natcoord's while the motion does not).
* Massless rods: a spatial tendon between two sites, its length held by a tendon equality
  (one row, soft like every MuJoCo equality, with the same accurate solref/solimp). Tension
  is ``-efc_force`` of that row (``efc_force`` acts along d(length)/dq: positive pushes the ends
  apart).
* Spring-dampers: the same tendon with ``stiffness``, ``damping`` and ``springlength`` = the
  length at t = 0 (MuJoCo's passive tendon spring: ``-k (l - l0) - c dl/dt`` along the
  tendon); tension ``k (l - l0) + c dl/dt`` from ``ten_length``/``ten_velocity``.
* A 3-D inertia tensor with a zero principal moment (a slender uniform rod about its own
  axis) gets ``zero_inertia`` x its largest principal moment along that axis: MuJoCo needs a
  positive definite inertia.
* Loads: constant torques and forces at the centre of mass through ``xfrc_applied`` (world
  axes, exact: MuJoCo applies it at the centre of mass and a torque is a free vector). A force
  at another point would need a moment that turns with the body inside each RK4 stage:
  unsupported.

Reactions (force on the joint's second body, world axes): tree joints ``cfrc_int[child, 3:]``
after ``mj_rnePostConstraint``, minus the rod and spring forces acting on the child's
subtree (``cfrc_ext`` holds ``xfrc_applied`` and connect forces but not tendon forces, so
``cfrc_int`` carries them); connect joints ``-efc_force`` of their rows.
"""

from __future__ import annotations

import dataclasses
import time
from xml.sax.saxutils import quoteattr

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun, steps_per_sample
from .tree import spanning_tree, tree_orientation, tree_parents


def _fmt(*xs) -> str:
    return " ".join(repr(float(x)) for x in xs)


def _pad3(p) -> np.ndarray:
    p = np.asarray(p, float)
    return np.concatenate([p, np.zeros(3 - len(p))])


def _point(case: Case, body: str, p: str) -> np.ndarray:
    """Body-frame coordinates (3,) of a named point (z = 0 in 2-D)."""
    if body == GROUND:
        return _pad3(case.ground[p])
    return _pad3(case.body(body).points[p])


def _quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, float).ravel())
    return q


# -------------------------------------------------------------------------------- tendons

@dataclasses.dataclass
class Tendons:
    """MJCF fragments of a case's rods and springs, and how to read their forces."""

    sites: dict[str, list[str]]  # body (or ground) -> <site .../> lines
    tendon: list[str]  # <spatial> lines
    equality: list[str]  # <tendon .../> equality lines
    notes: list[str]


def tendons_mjcf(case: Case, solref: tuple[float, float], solimp: str) -> Tendons:
    """Rods as tendon-length equalities, springs as passive tendon springs."""
    sites: dict[str, list[str]] = {}
    tendon, equality, notes = [], [], []
    rods, springs = getattr(case, "rods", ()), getattr(case, "springs", ())
    for kind, items in (("rod", rods), ("spring", springs)):
        for r in items:
            names = []
            for k, (b, p) in enumerate(r.ends):
                s = f"{kind}_{r.name}_{k}"
                names.append(s)
                sites.setdefault(b, []).append(
                    f"<site name={quoteattr(s)} pos=\"{_fmt(*_point(case, b, p))}\"/>")
            extra = ""
            if kind == "spring":
                extra = (f' stiffness="{float(r.stiffness)!r}" damping="{float(r.damping)!r}" '
                         f'springlength="{float(r.length)!r}"')
            tendon.append(f"    <spatial name={quoteattr(f'{kind}_{r.name}')}{extra}>"
                          f"<site site={quoteattr(names[0])}/><site site={quoteattr(names[1])}/>"
                          "</spatial>")
            if kind == "rod":
                equality.append(f"    <tendon name={quoteattr(f'rod_{r.name}')} "
                                f"tendon1={quoteattr(f'rod_{r.name}')} "
                                f'solref="{_fmt(*solref)}" solimp="{solimp}"/>')
    if rods:
        notes.append(f"massless rods {', '.join(r.name for r in rods)}: spatial tendons between "
                     f"two sites with a tendon-length equality (solref {_fmt(*solref)}, "
                     f"solimp {solimp}); tension = -efc_force of its row. MuJoCo's equality "
                     "leaves out the v^2/L term of the length's acceleration, so a rod swinging "
                     f"at speed v stretches by about tc^2 v^2 / L (tc = {solref[0]:g} s)")
    if springs:
        notes.append(f"spring-dampers {', '.join(r.name for r in springs)}: spatial tendons "
                     "with MuJoCo's passive stiffness and damping, springlength = length at "
                     "t = 0")
    return Tendons(sites, tendon, equality, notes)


class TendonForces:
    """Reads rod and spring tensions from an MjData, and the forces they put on bodies."""

    def __init__(self, mujoco, m, case: Case):
        self.mujoco = mujoco
        self.rods = list(getattr(case, "rods", ()))
        self.springs = list(getattr(case, "springs", ()))
        tid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n)  # noqa: E731
        eid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, n)  # noqa: E731
        sid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n)  # noqa: E731
        self.rod_eq = {r.name: eid(f"rod_{r.name}") for r in self.rods}
        self.spring_t = {r.name: tid(f"spring_{r.name}") for r in self.springs}
        self.ends = {}  # name -> ((body, site id), (body, site id))
        for kind, items in (("rod", self.rods), ("spring", self.springs)):
            for r in items:
                self.ends[r.name] = tuple((b, sid(f"{kind}_{r.name}_{k}"))
                                          for k, (b, _) in enumerate(r.ends))

    def tensions(self, d) -> tuple[dict[str, float], float]:
        """Tension of every rod and spring (N) and the largest rod length violation (m)."""
        mj = self.mujoco
        out: dict[str, float] = {}
        drift = 0.0
        if self.rods:
            rows = np.flatnonzero(d.efc_type == mj.mjtConstraint.mjCNSTR_EQUALITY)
            for r in self.rods:
                row = rows[d.efc_id[rows] == self.rod_eq[r.name]]
                out[r.name] = -float(d.efc_force[row[0]])
                drift = max(drift, abs(float(d.efc_pos[row[0]])))
        for r in self.springs:
            t = self.spring_t[r.name]
            out[r.name] = (r.stiffness * (d.ten_length[t] - r.length)
                           + r.damping * d.ten_velocity[t])
        return out, drift

    def body_forces(self, d, tension: dict[str, float]) -> dict[str, np.ndarray]:
        """Force (3,) world that the rods and springs apply to each body (ground excluded)."""
        out: dict[str, np.ndarray] = {}
        for name, ((b0, s0), (b1, s1)) in self.ends.items():
            u = d.site_xpos[s1] - d.site_xpos[s0]
            u = u / np.linalg.norm(u)
            for b, f in ((b0, tension[name] * u), (b1, -tension[name] * u)):
                if b != GROUND:
                    out[b] = out.get(b, np.zeros(3)) + f
        return out


def applied_loads(mujoco, m, case: Case) -> np.ndarray:
    """``xfrc_applied`` (nbody, 6) of the case's constant loads."""
    x = np.zeros((m.nbody, 6))
    for f in case.forces:
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f.body)
        b = case.body(f.body)
        if f.type == "torque":
            x[j, 3:] += np.array([0.0, 0.0, float(f.value)]) if case.dimension == 2 \
                else np.asarray(f.value, float)
        elif f.type == "force":
            p = b.points[f.point]
            if np.max(np.abs(np.asarray(p, float) - b.com)) > 1e-12:
                raise Unsupported(f"force on {f.body} at point {f.point}, not its centre of "
                                  "mass: MuJoCo's xfrc_applied acts at the centre of mass and "
                                  "is held over a step, so the moment of a force elsewhere "
                                  "would lag the body's rotation")
            x[j, :3] += _pad3(f.value)
        else:
            raise Unsupported(f"force type {f.type!r}")
    return x


def subtree_bodies(parent: dict) -> dict[str, set[str]]:
    """child -> every body of its subtree (itself included), from child -> (parent, joint)."""
    out = {c: {c} for c in parent}
    for c in parent:
        p = parent[c][0]
        while p in parent:
            out[p].add(c)
            p = parent[p][0]
    return out


# -------------------------------------------------------------------------------- 3-D MJCF

@dataclasses.dataclass
class Built3:
    xml: str
    loops: list
    parent: dict  # child -> (parent, case joint)
    qvel: list[float]
    notes: list[str]
    solref: tuple[float, float]


def _inertia(b, eps: float, notes: list[str]) -> np.ndarray:
    J = np.asarray(b.inertia, float)
    w, V = np.linalg.eigh(J)
    top = max(float(w.max()), 1e-12 * b.mass)
    small = w <= 1e-12 * top
    if np.any(small):
        add = eps * top
        J = J + add * sum(np.outer(V[:, k], V[:, k]) for k in np.flatnonzero(small))
        what = "its own axis (a slender rod)" if b.kind == "uniform_rod" else \
            "a principal axis"
        notes.append(f"body {b.name} has no inertia about {what}; MuJoCo needs a positive "
                     f"inertia, so it gets {add:.3g} kg m^2 there ({eps:g} of its largest "
                     "principal moment)")
    return J


def build_mjcf_3d(case: Case, init: dict, s: dict) -> Built3:
    """The MJCF text of a 3-D case, every body placed at its assembled state ``init``."""
    for j in case.joints:
        if j.type not in ("revolute", "spherical"):  # 3-D case files have no others
            raise Unsupported(f"joint {j.name}: type {j.type!r} in 3-D")
    if getattr(case, "drivers", ()):
        raise Unsupported("prescribed motions (drivers): MuJoCo has no rheonomic constraint, "
                          "and a stiff servo would be an approximation")
    for b in case.bodies:
        if b.mass <= 0:
            raise Unsupported(f"body {b.name} is massless; MuJoCo bodies need mass")
    tree, loops = spanning_tree(case)
    notes: list[str] = []
    parent = {child: (par, case.joint(j.name)) for j, par, child in tree_parents(tree)}
    children: dict[str, list[str]] = {}
    for child, (par, _) in parent.items():
        children.setdefault(par, []).append(child)

    dt = float(s["dt"])
    solref = (float(s["solref_steps"]) * dt, float(s["solref_damping"]))
    solimp = _fmt(*s["solimp"])
    ten = tendons_mjcf(case, solref, solimp)
    notes += ten.notes
    sites = {k: list(v) for k, v in ten.sites.items()}
    for j in loops:
        for k in (0, 1):
            b = j.bodies[k]
            sites.setdefault(b, []).append(
                f"<site name={quoteattr(f'loop_{j.name}_{k}')} "
                f"pos=\"{_fmt(*_point(case, b, j.points[k]))}\"/>")

    def state(name):
        if name == GROUND:
            return np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3)
        st = init[name]
        R = np.eye(3) if st.rotation is None else np.asarray(st.rotation, float)
        return (np.asarray(st.origin, float), R, np.asarray(st.velocity, float),
                np.asarray(st.omega, float))

    qvel: list[float] = []
    lines: list[str] = []

    def emit(name, indent):
        b = case.body(name)
        o, R, v, w = state(name)
        pad = " " * indent
        if name in parent:
            pname, cj = parent[name]
            po, pR, pv, pw = state(pname)
            rel, relR = pR.T @ (o - po), pR.T @ R
        else:
            rel, relR = o, R
        lines.append(f'{pad}<body name={quoteattr(name)} pos="{_fmt(*rel)}" '
                     f'quat="{_fmt(*_quat(relR))}">')
        if name in parent:
            k_child = 1 if cj.bodies[1] == name else 0
            pc = _point(case, name, cj.points[k_child])
            jname = quoteattr(cj.name)
            if cj.type == "revolute":
                first = cj.bodies[0]
                u = state(first)[1] @ np.asarray(cj.axis, float)  # world
                lines.append(f'{pad}  <joint name={jname} type="hinge" pos="{_fmt(*pc)}" '
                             f'axis="{_fmt(*(R.T @ u))}"/>')
                qvel.append(float((w - pw) @ u))
            else:  # spherical
                lines.append(f'{pad}  <joint name={jname} type="ball" pos="{_fmt(*pc)}"/>')
                qvel.extend((R.T @ (w - pw)).tolist())
        else:
            notes.append(f"body {name} is not joined to the ground: free joint")
            lines.append(f'{pad}  <freejoint name={quoteattr(name + "_free")}/>')
            qvel.extend(v.tolist() + (R.T @ w).tolist())
        J = _inertia(b, float(s["zero_inertia"]), notes)
        full = _fmt(J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2])
        lines.append(f'{pad}  <inertial pos="{_fmt(*_pad3(b.com))}" mass="{b.mass!r}" '
                     f'fullinertia="{full}"/>')
        for site in sites.get(name, []):
            lines.append(f"{pad}  {site}")
        for c in children.get(name, []):
            emit(c, indent + 2)
        lines.append(f"{pad}</body>")

    for c in children.get(GROUND, []):
        emit(c, 4)
    for b in case.bodies:
        if b.name not in parent:
            emit(b.name, 4)

    eq = [f'    <connect name={quoteattr(j.name)} site1="loop_{j.name}_0" '
          f'site2="loop_{j.name}_1" solref="{_fmt(*solref)}" solimp="{solimp}"/>'
          for j in loops] + ten.equality
    for j in loops:
        notes.append(f"connect equality (3 rows) for loop {j.type} joint {j.name} (site1 on "
                     f"{j.bodies[0]}, site2 on {j.bodies[1]}), solref {_fmt(*solref)}, "
                     f"solimp {solimp}")
    xml = mjcf_document(case, s, dt, _pad3(case.gravity), sites, lines, ten.tendon, eq)
    return Built3(xml, loops, parent, qvel, notes, solref)


# ------------------------------------------------- shared by mujoco_engine (2-D) and run_3d

def mjcf_document(case: Case, s: dict, dt: float, gravity, sites: dict, lines: list,
                  tendon: list, equality: list) -> str:
    """The MJCF model: options from the settings, the bodies' ``lines``, tendons and
    equalities."""
    return "\n".join([
        f"<mujoco model={quoteattr(case.name)}>",
        '  <compiler angle="radian" inertiafromgeom="false" balanceinertia="false"/>',
        f'  <option timestep="{dt!r}" gravity="{_fmt(*gravity)}" '
        f'integrator="{s["integrator"]}" solver="{s["solver"]}" '
        f'tolerance="{float(s["tolerance"])!r}" iterations="{int(s["iterations"])}" '
        f'ls_iterations="{int(s["ls_iterations"])}">',
        '    <flag contact="disable"/>',
        "  </option>",
        "  <worldbody>",
        *[f"    {site}" for site in sites.get(GROUND, [])],
        *lines,
        "  </worldbody>",
        *(["  <tendon>", *tendon, "  </tendon>"] if tendon else []),
        *(["  <equality>", *equality, "  </equality>"] if equality else []),
        "</mujoco>",
    ])


def load_model(mujoco, case: Case, build_mjcf):
    """(built, model, data, build time): ``build_mjcf()`` compiled, started at the built
    velocities with the case's constant loads applied."""
    t0 = time.perf_counter()
    built = build_mjcf()
    m = mujoco.MjModel.from_xml_string(built.xml)
    d = mujoco.MjData(m)
    build = time.perf_counter() - t0
    if len(built.qvel) != m.nv:
        raise RuntimeError(f"internal: {len(built.qvel)} initial velocities for nv = {m.nv}")
    d.qpos[:] = m.qpos0  # the XML places every body at its assembled pose
    d.qvel[:] = built.qvel
    d.xfrc_applied[:] = applied_loads(mujoco, m, case)
    return built, m, d, build


def forward(mujoco, m, d) -> int:
    """Positions, velocities, constraint and interaction forces at the current state; the
    solver's iteration count."""
    mujoco.mj_forward(m, d)
    mujoco.mj_rnePostConstraint(m, d)
    return int(d.solver_niter[0])


def read_forces(mujoco, d, ten, tree: dict, bid: dict, subtree: dict, loops, eqid: dict,
                dim: int, rod_force: dict, forces: dict, i: int) -> float:
    """Sample i of the rod/spring tensions (``rod_force``) and of every joint force
    (``forces``: tree joints from cfrc_int less the tendon forces, loop joints from their
    connect equalities), world axes, N; returns the largest constraint drift seen, m."""
    tension, drift = ten.tensions(d)
    for r, v in tension.items():
        rod_force[r][i] = v
    on_body = ten.body_forces(d, tension)  # cfrc_int carries them: take them out
    for name, (child, sign) in tree.items():
        forces[name][i] = sign * tree_force(d, bid[child], subtree[child], on_body, dim)
    loop_f, dr = connect_forces(mujoco, d, loops, eqid, dim)
    for name, f in loop_f.items():
        forces[name][i] = f
    return max(drift, dr)


def tree_force(d, body: int, subtree: list, on_body: dict, dim: int) -> np.ndarray:
    """Force through a tree joint from ``cfrc_int`` less the rods' and springs' forces on the
    child's subtree (``cfrc_int`` carries them)."""
    f = d.cfrc_int[body, 3:3 + dim].copy()
    for b in subtree:
        f -= on_body.get(b, np.zeros(3))[:dim]
    return f


def connect_forces(mujoco, d, loops, eqid: dict, dim: int) -> tuple[dict, float]:
    """Each loop's connect-equality force on its first body (``efc_force`` acts on site1's
    body; the second gets minus it) and the largest constraint violation."""
    out, drift = {}, 0.0
    if loops:
        eq_rows = np.flatnonzero(d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY)
        for j in loops:
            rows = eq_rows[d.efc_id[eq_rows] == eqid[j.name]]
            out[j.name] = -d.efc_force[rows[:dim]]
            drift = max(drift, float(np.max(np.abs(d.efc_pos[rows]))))
    return out, drift


def step_samples(mujoco, m, d, T: int, k: int, at_sample) -> tuple[float, int]:
    """Samples 1 .. T-1, ``k`` steps apart, ``at_sample(i)`` after each; (wall time of the
    steps, number of steps)."""
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


def engine_run(motion, built, m, s: dict, dt: float, build: float, wall: float, n_steps: int,
               drift: float, max_iter: int) -> EngineRun:
    counters = {"steps": n_steps, "nv": int(m.nv), "loop_drift_m": drift,
                "max_solver_iterations": max_iter}
    notes = list(built.notes)
    notes.append(f"integrator {s['integrator']}, solver {s['solver']}, tolerance "
                 f"{s['tolerance']}, contacts disabled, dt {dt} s")
    return EngineRun(motion, build, wall, n_steps, s, counters, notes)


# -------------------------------------------------------------------------------- 3-D run

def run_3d(case: Case, init, s: dict, check) -> EngineRun:
    """Run a 3-D case (``s``: merged settings; ``check``: mujoco_engine's state check)."""
    import mujoco

    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    built, m, d, build = load_model(mujoco, case, lambda: build_mjcf_3d(case, init, s))

    names = [b.name for b in case.bodies]
    bid = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in names}
    eqid = {j.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, j.name)
            for j in built.loops}
    tree = {cj.name: (child, tree_orientation(cj, par))
            for child, (par, cj) in built.parent.items()}
    subtree = subtree_bodies(built.parent)
    ten = TendonForces(mujoco, m, case)

    times = case.times
    T = len(times)
    origin = {n: np.zeros((T, 3)) for n in names}
    rotation = {n: np.zeros((T, 3, 3)) for n in names}
    velocity = {n: np.zeros((T, 3)) for n in names}
    omega = {n: np.zeros((T, 3)) for n in names}
    forces = {j.name: np.zeros((T, 3)) for j in case.joints}
    rod_force = {r.name: np.zeros(T) for r in ten.rods + ten.springs}
    vel6 = np.zeros(6)
    drift = 0.0
    max_iter = 0

    def sample(i):
        nonlocal drift, max_iter
        max_iter = max(max_iter, forward(mujoco, m, d))
        for n in names:
            j = bid[n]
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, j, vel6, 0)
            origin[n][i] = d.xpos[j]
            rotation[n][i] = d.xmat[j].reshape(3, 3)
            velocity[n][i] = vel6[3:]
            omega[n][i] = vel6[:3]
        drift = max(drift, read_forces(mujoco, d, ten, tree, bid, subtree, built.loops, eqid,
                                       3, rod_force, forces, i))

    sample(0)
    check(mujoco, m, d, 0.0)
    for n in names:
        st = init[n]
        err = max(np.max(np.abs(origin[n][0] - st.origin)),
                  np.max(np.abs(velocity[n][0] - st.velocity)),
                  np.max(np.abs(omega[n][0] - st.omega)),
                  0.0 if st.rotation is None else np.max(np.abs(rotation[n][0] - st.rotation)))
        if err > 1e-9:
            raise RuntimeError(f"internal: MuJoCo's initial state of body {n} differs from the "
                               f"assembled one by {err:.3g}")

    def at_sample(i):
        check(mujoco, m, d, times[i])
        sample(i)
        if drift > float(s["max_loop_drift"]):
            raise RuntimeError(f"a loop or rod opened by {drift:.3g} m by t = {times[i]:.6g} s "
                               f"(max_loop_drift {s['max_loop_drift']} m): the soft "
                               "constraints do not hold at these settings")

    wall, n_steps = step_samples(mujoco, m, d, T, k, at_sample)
    motion = Motion(np.asarray(times, float), origin, {}, velocity, omega, forces,
                    rotation=rotation, rod_force=rod_force)
    return engine_run(motion, built, m, s, dt, build, wall, n_steps, drift, max_iter)
