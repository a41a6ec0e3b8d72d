"""MuJoCo as an engine: a kinematic tree of hinge/slide joints plus soft `connect` equalities.

This module builds planar (2-D) cases: MuJoCo's 3-D model confined to the x-y plane, tree
joints hinges about z or slides along an in-plane axis, so nothing leaves the plane. 3-D
cases, and the massless rods, spring-dampers and applied loads of both, are built by
:mod:`natcoord.engines.mujoco_3d` (rods: tendon-length equalities; measured against a light
body with two connects on five_bar: angle error 3.7e-5 rad against 3.1e-3 rad for a 1e-3 kg
light rod, whose loops open past 0.1 mm when it is made lighter).

Modelling choices (each one that applies is repeated in ``EngineRun.notes``):

* Tree: :func:`natcoord.engines.tree.spanning_tree`. MuJoCo has no point-on-line equality, so
  when that tree would cut a prismatic joint, the tree is rebuilt with prismatic joints taken
  first (the loop is then cut at a revolute joint instead); a loop made only of prismatic
  joints is unsupported.
* Loop-closing revolute joints: ``connect`` equalities between two sites (``site1`` on the
  joint's first body, ``site2`` on its second). They are soft: the accurate recipe of
  ENGINE-NOTES.md (RK4, Newton, tolerance 1e-10, solimp 0.9999, solref time constant
  ``solref_steps`` x dt) keeps the loop closed to ~1e-9 m.
* Particles: a point mass. Hung from a revolute tree joint it is welded to its parent (its
  rotation carries no energy, so no hinge is needed); on a slide it cannot turn. MuJoCo wants a
  positive rotational inertia, so it is given ``particle_inertia`` (kg m^2). Its frame is
  reported with angle 0 (natcoord's convention), the origin following its point.
* Bodies not reached from the ground float in the plane: slide x, slide y (and hinge z unless a
  particle).

Reactions (force the joint applies to its second body, world axes):

* tree joints: ``cfrc_int[child, 3:]`` after ``mj_rnePostConstraint`` (force of the parent on
  the child, world axes), times :func:`natcoord.mechanism.tree_orientation`;
* ``connect`` joints: ``efc_force`` of the equality's rows is the force on ``site1``'s body;
  the second body receives minus that.
* with rods or springs, tree reactions exclude their forces on the child's subtree
  (``cfrc_int`` carries them: ``cfrc_ext`` has no tendon forces).

Both are evaluated at the stored state (``mj_forward`` then ``mj_rnePostConstraint``), not read
from the step that produced the state.
"""

from __future__ import annotations

import dataclasses
import math
from xml.sax.saxutils import quoteattr

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case, Joint
from ..result import Motion
from .base import EngineRun, merged, steps_per_sample
from .mujoco_3d import (
    TendonForces,
    _fmt,
    engine_run,
    forward,
    load_model,
    mjcf_document,
    read_forces,
    run_3d,
    step_samples,
    subtree_bodies,
    tendons_mjcf,
)
from .tree import point_loop_tree, tree_orientation, tree_parents

NAME = "mujoco"
PACKAGE = "mujoco"
DEFAULTS = {
    "dt": 1e-4,
    "integrator": "RK4",
    "solver": "Newton",
    "tolerance": 1e-10,
    "iterations": 100,
    "ls_iterations": 50,
    "solref_steps": 10.0,  # equality time constant in time steps
    "solref_damping": 1.0,  # damping ratio
    "solimp": [0.9999, 0.9999, 0.001, 0.5, 2.0],
    "particle_inertia": 1e-6,  # kg m^2, about every axis
    "max_loop_drift": 1e-4,  # m: a soft loop or rod opened wider than this is a failed run
    "zero_inertia": 1e-6,  # 3-D: added along a zero principal axis, x the largest moment
}


ZERO_INERTIA_SUBSTITUTE = 1e-10


def version() -> str:
    import mujoco

    return mujoco.__version__


# -------------------------------------------------------------------------------- geometry

def _rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _cross_z(w: float, r: np.ndarray) -> np.ndarray:
    """omega (about z) x r for an in-plane r."""
    return w * np.array([-r[1], r[0]])


def _quat_z(a: float) -> str:
    return _fmt(math.cos(a / 2), 0.0, 0.0, math.sin(a / 2))


# -------------------------------------------------------------------------------- the tree

def _tree(case: Case) -> tuple[list[Joint], list[Joint], list[str]]:
    """Tree joints (parent first), loop joints, notes."""
    tree, loops, recut = point_loop_tree(case, "MuJoCo has no point-on-line equality")
    notes = []
    if recut:
        notes.append(f"loop cut at revolute {', '.join(j.name for j in loops)} instead of "
                     f"prismatic {', '.join(recut)} (MuJoCo has no point-on-line equality); "
                     "prismatic joints are tree slide joints")
    return tree, loops, notes


def _parent_of(case: Case, tree: list[Joint]) -> dict[str, tuple[str, Joint]]:
    """child body -> (parent body, the case's joint), in tree order."""
    return {child: (parent, case.joint(j.name)) for j, parent, child in tree_parents(tree)}


# -------------------------------------------------------------------------------- MJCF

@dataclasses.dataclass
class _Built:
    xml: str
    tree: list[Joint]
    loops: list[Joint]
    parent: dict  # child -> (parent, case joint)
    qvel: list[float]  # initial joint velocities, in joint order of the XML
    notes: list[str]
    solref: tuple[float, float]


def build_mjcf(case: Case, init: dict, settings: dict) -> _Built:
    """The MJCF text of a planar case, placed at the assembled state ``init``."""
    s = merged(DEFAULTS, settings)
    if case.dimension != 2:
        raise Unsupported(f"the MuJoCo adapter models 2-D cases only (dimension {case.dimension})")
    if getattr(case, "drivers", ()):
        raise Unsupported("prescribed motions (drivers): MuJoCo has no rheonomic constraint, "
                          "and a stiff servo would be an approximation")
    for j in case.joints:
        if j.type not in ("revolute", "prismatic"):
            raise Unsupported(f"joint {j.name}: type {j.type!r}")
    for b in case.bodies:
        if b.mass <= 0:
            raise Unsupported(f"body {b.name} is massless; MuJoCo bodies need mass")

    tree, loops, notes = _tree(case)
    parent = _parent_of(case, tree)
    children: dict[str, list[str]] = {}
    for child, (par, _) in parent.items():
        children.setdefault(par, []).append(child)
    bodies = {b.name: b for b in case.bodies}

    def pose(name):
        if name == GROUND:
            return np.zeros(2), 0.0, np.zeros(2), 0.0
        st = init[name]
        return (np.asarray(st.origin, float), float(st.angle),
                np.asarray(st.velocity, float), float(st.omega))

    def point(name, p):
        return case.ground[p] if name == GROUND else bodies[name].points[p]

    dt = float(s["dt"])
    tc = float(s["solref_steps"]) * dt
    solref = (tc, float(s["solref_damping"]))
    solimp = _fmt(*s["solimp"])
    pin = float(s["particle_inertia"])
    qvel: list[float] = []
    lines: list[str] = []
    particles_welded, particles_slide = [], []

    # sites for loop joints and rod ends, by body
    ten = tendons_mjcf(case, solref, solimp)
    notes += ten.notes
    sites: dict[str, list[str]] = {k: list(v) for k, v in ten.sites.items()}
    for j in loops:
        for k in (0, 1):
            b, p = j.bodies[k], j.points[k]
            x, y = point(b, p)
            sites.setdefault(b, []).append(
                f'<site name={quoteattr(f"loop_{j.name}_{k}")} pos="{_fmt(x, y, 0.0)}"/>')

    def inertial(b):
        if b.kind == "particle":
            # welded to its parent its inertia would act, so none; turning nowhere else
            i = 0.0 if b.name in particles_welded else pin
            cx, cy = b.com
        else:
            i = b.inertia
            cx, cy = b.com
            if i <= 0:  # a point mass: MuJoCo refuses inertia below mjMINVAL (1e-15)
                reach = max(float(np.linalg.norm(p - b.com)) for p in b.points.values())
                i = ZERO_INERTIA_SUBSTITUTE * b.mass * reach**2
                notes.append(f"body {b.name} is a point mass (zero inertia); MuJoCo needs "
                             f"inertia > 1e-15, so it gets {i:.1e} kg m^2 "
                             f"({ZERO_INERTIA_SUBSTITUTE:.0e} of m r^2 about its farthest "
                             "point): a relative change of that size in its inertia")
        # planar: only Izz acts; Ixx = Iyy = Izz keeps the triangle inequality
        return (f'<inertial pos="{_fmt(cx, cy, 0.0)}" mass="{b.mass!r}" '
                f'diaginertia="{_fmt(i, i, i)}"/>')

    def emit(name, indent):
        b = bodies[name]
        o, a, v, w = pose(name)
        pad = " " * indent
        if name in parent:
            pname, cj = parent[name]
            po, pa, pv, pw = pose(pname)
            rel = _rot(pa).T @ (o - po)
            rel_a = a - pa
            head = (f'{pad}<body name={quoteattr(name)} pos="{_fmt(rel[0], rel[1], 0.0)}" '
                    f'quat="{_quat_z(rel_a)}">')
            lines.append(head)
            # joint point on this (child) body, in its frame
            k_child = 1 if cj.bodies[1] == name else 0
            pc = point(name, cj.points[k_child])
            if cj.type == "revolute":
                if b.kind == "particle":
                    particles_welded.append(name)
                else:
                    lines.append(f'{pad}  <joint name={quoteattr(cj.name)} type="hinge" '
                                 f'pos="{_fmt(pc[0], pc[1], 0.0)}" axis="0 0 1"/>')
                    qvel.append(w - pw)
            else:  # prismatic: axis in the joint's first body's frame
                if b.kind == "particle":
                    particles_slide.append(name)
                a0 = cj.bodies[0]
                ang0 = pose(a0)[1]
                u = _rot(ang0) @ cj.axis  # world
                u_child = _rot(a).T @ u
                # velocity of the joint point of the child relative to that of the parent
                pp = point(pname, cj.points[1 - k_child])
                rc, rp = _rot(a) @ pc, _rot(pa) @ pp
                vrel = (v + _cross_z(w, rc)) - (pv + _cross_z(pw, rp))
                sign = 1.0 if cj.bodies[1] == name else -1.0  # slide of second vs first
                lines.append(f'{pad}  <joint name={quoteattr(cj.name)} type="slide" '
                             f'pos="{_fmt(pc[0], pc[1], 0.0)}" '
                             f'axis="{_fmt(sign * u_child[0], sign * u_child[1], 0.0)}"/>')
                qvel.append(float(vrel @ (sign * u)))
        else:  # floating in the plane
            lines.append(f'{pad}<body name={quoteattr(name)} pos="{_fmt(o[0], o[1], 0.0)}" '
                         f'quat="{_quat_z(a)}">')
            notes.append(f"body {name} is not joined to the ground: slide x, slide y"
                         + ("" if b.kind == "particle" else ", hinge z"))
            if b.kind == "particle":
                particles_slide.append(name)
            ca, sa = math.cos(a), math.sin(a)
            lines.append(f'{pad}  <joint name={quoteattr(name + "_x")} type="slide" '
                         f'axis="{_fmt(ca, -sa, 0.0)}"/>')
            lines.append(f'{pad}  <joint name={quoteattr(name + "_y")} type="slide" '
                         f'axis="{_fmt(sa, ca, 0.0)}"/>')
            qvel.extend([float(v[0]), float(v[1])])
            if b.kind != "particle":
                lines.append(f'{pad}  <joint name={quoteattr(name + "_rz")} type="hinge" '
                             'axis="0 0 1"/>')
                qvel.append(w)
        lines.append(f"{pad}  {inertial(b)}")
        for site in sites.get(name, []):
            lines.append(f"{pad}  {site}")
        for c in children.get(name, []):
            emit(c, indent + 2)
        lines.append(f"{pad}</body>")

    for c in children.get(GROUND, []):
        emit(c, 4)
    reached = set(parent)
    for b in case.bodies:
        if b.name not in reached:
            emit(b.name, 4)

    gx, gy = case.gravity
    eq = [f'    <connect name={quoteattr(j.name)} site1="loop_{j.name}_0" '
          f'site2="loop_{j.name}_1" solref="{_fmt(*solref)}" solimp="{solimp}"/>'
          for j in loops]
    xml = mjcf_document(case, s, dt, (gx, gy, 0.0), sites, lines, ten.tendon,
                        eq + ten.equality)

    for j in loops:
        notes.append(f"connect equality for loop joint {j.name} (site1 on {j.bodies[0]}, "
                     f"site2 on {j.bodies[1]}), solref {_fmt(*solref)}, solimp {solimp}")
    for name in particles_welded:
        notes.append(f"particle {name} welded to its tree parent at its revolute joint "
                     "(no hinge, zero inertia: exact for a point mass)")
    for name in particles_slide:
        notes.append(f"particle {name} given inertia {pin:g} kg m^2 (MuJoCo needs one; "
                     "its joints cannot turn it, so it does not act)")
    return _Built(xml, tree, loops, parent, qvel, notes, solref)


# -------------------------------------------------------------------------------- run

def _check(mujoco, m, d, t_expected: float) -> None:
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


def _check_start(case, init, origin, angle, velocity, omega, tol=1e-9) -> None:
    """The MuJoCo model must start exactly at natcoord's assembled state."""
    for b in case.bodies:
        st = init[b.name]
        errs = [np.max(np.abs(origin[b.name][0] - st.origin)),
                np.max(np.abs(velocity[b.name][0] - st.velocity))]
        if b.kind != "particle":
            errs += [abs(math.remainder(angle[b.name][0] - st.angle, 2 * math.pi)),
                     abs(omega[b.name][0] - st.omega)]
        if max(errs) > tol * (1.0 + max(np.max(np.abs(st.origin)), np.max(np.abs(st.velocity)))):
            raise RuntimeError(f"internal: MuJoCo's initial state of body {b.name} differs "
                               f"from the assembled one by {max(errs):.3g}")


def run(case: Case, init, settings: dict) -> EngineRun:
    import mujoco

    s = merged(DEFAULTS, settings)
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    if float(s["solref_steps"]) < 2.0:
        raise ValueError("solref_steps below 2 is clamped by MuJoCo's refsafe; use >= 2")
    if case.dimension == 3:
        return run_3d(case, init, s, _check)

    built, m, d, build = load_model(mujoco, case, lambda: build_mjcf(case, init, s))

    bodies = [b for b in case.bodies]
    bid = {b.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b.name) for b in bodies}
    eqid = {j.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, j.name)
            for j in built.loops}
    tree_sign = {cj.name: (child, tree_orientation(cj, parent))
                 for child, (parent, cj) in built.parent.items()}
    subtree = subtree_bodies(built.parent)
    ten = TendonForces(mujoco, m, case)
    rod_force = {r.name: np.zeros(len(case.times)) for r in ten.rods + ten.springs}

    times = case.times
    T = len(times)
    origin = {b.name: np.zeros((T, 2)) for b in bodies}
    angle = {b.name: np.zeros(T) for b in bodies}
    velocity = {b.name: np.zeros((T, 2)) for b in bodies}
    omega = {b.name: np.zeros(T) for b in bodies}
    forces = {j.name: np.zeros((T, 2)) for j in case.joints}
    vel6 = np.zeros(6)
    drift = 0.0
    max_iter = 0

    def sample(i):
        nonlocal drift, max_iter
        max_iter = max(max_iter, forward(mujoco, m, d))
        for b in bodies:
            j = bid[b.name]
            R = d.xmat[j].reshape(3, 3)
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, j, vel6, 0)
            w = vel6[2]
            if b.kind == "particle":
                p = next(iter(b.points.values()))
                rp = R[:2, :2] @ p
                origin[b.name][i] = d.xpos[j, :2] + rp - p
                velocity[b.name][i] = vel6[3:5] + _cross_z(w, rp)
            else:
                origin[b.name][i] = d.xpos[j, :2]
                angle[b.name][i] = math.atan2(R[1, 0], R[0, 0])
                velocity[b.name][i] = vel6[3:5]
                omega[b.name][i] = w
        drift = max(drift, read_forces(mujoco, d, ten, tree_sign, bid, subtree, built.loops,
                                       eqid, 2, rod_force, forces, i))

    sample(0)
    _check(mujoco, m, d, 0.0)
    _check_start(case, init, origin, angle, velocity, omega)

    def at_sample(i):
        _check(mujoco, m, d, times[i])
        sample(i)
        _check(mujoco, m, d, times[i])
        if drift > float(s["max_loop_drift"]):
            raise RuntimeError(f"a loop opened by {drift:.3g} m by t = {times[i]:.6g} s "
                               f"(max_loop_drift {s['max_loop_drift']} m): the soft "
                               "constraints do not hold at these settings")

    wall, n_steps = step_samples(mujoco, m, d, T, k, at_sample)
    for b in bodies:
        angle[b.name] = np.unwrap(angle[b.name])
    motion = Motion(np.asarray(times, float), origin, angle, velocity, omega, forces,
                    rod_force=rod_force)
    return engine_run(motion, built, m, s, dt, build, wall, n_steps, drift, max_iter)
