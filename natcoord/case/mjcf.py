"""MuJoCo models (MJCF) as natcoord cases: ``natcoord import MODEL.xml --out CASE.toml``.

The model is read with MuJoCo's own parser (``mujoco.MjSpec``) and compiled, so masses,
centres of mass and inertias are MuJoCo's (from geoms or ``<inertial>``), and a ``connect``
equality's second anchor is the one MuJoCo computed at ``qpos0``. The case is written in
the reference frame (every point its world position at t = 0):

* bodies: each moving MuJoCo body a ``rigid`` body (mass, world centre of mass, world
  inertia tensor about it; 2-D: the moment about the plane's normal). A body without a
  joint is part of its parent (of the ground under the world body); a ``weld`` equality
  makes its two bodies one (closing a loop). Their mass and inertia are summed;
* joints: hinge -> revolute, slide -> prismatic, ball -> spherical, each at its world
  anchor; ``connect`` -> a loop-closing spherical joint (2-D: revolute) at its anchor;
* the initial state: the first keyframe if the model has one, else ``qpos0``, at rest or
  with the keyframe's ``qvel``; loops not closed there are closed by Gauss-Newton (least
  change of qpos) and the velocity projected onto them; a nonzero velocity is given through
  point-position channels that fix it;
* 2-D when every joint is a hinge about one direction n or a slide across it and gravity
  lies in the plane: coordinates (x, y) along e1 = e2 x n, e2 (gravity's -direction in the
  plane where there is gravity), so that a rotation about n is counter-clockwise.

What it cannot carry and does not change the motion of the model as written (sensors,
actuators at zero control without bias, contacts, joint ranges, soft-constraint tuning
``solref``/``solimp``, the integrator) is listed in the case file as comments and
returned as notes; what would change the motion (a free joint, joint damping, stiffness,
armature or friction, a tendon with stiffness or limits, other equalities, a biased
actuator, a fluid) is refused with a :class:`~natcoord.errors.CaseError` naming the file
and the element.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CaseError
from .casefile import MAX_MAGNITUDE
from .generate import OUTPUT_DT

PLANAR_TOL = 1e-9  # |sin| of the angle between a hinge axis and n, m/s^2 of gravity along n
CLOSE_TOL = 1e-12  # m: loop closure reached by assembly
NAME_RE = re.compile(r"[^A-Za-z0-9_.+-]")


@dataclass
class Imported:
    """A case imported from MJCF: its TOML text, the notes on what it does not carry and
    the facts a caller (and a round-trip test) needs to compare with MuJoCo run directly.

    ``qpos``, ``qvel``: the assembled initial state of the MuJoCo model (nq,), (nv,).
    ``bodies``: case body name -> MuJoCo body ids it is made of. ``loops``: loop joint
    name -> (MuJoCo body id, anchor in that body's frame (3,)) of its first body.
    ``frame``: (3, 3) rows e1, e2, n of a 2-D case (world -> plane), None in 3-D.
    """

    text: str
    notes: list[str]
    dimension: int
    qpos: np.ndarray
    qvel: np.ndarray
    bodies: dict[str, list[int]] = field(default_factory=dict)
    loops: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)
    frame: np.ndarray | None = None


def _mujoco():
    try:
        import mujoco
    except ImportError:  # pragma: no cover - mujoco is a dependency of the engines extra
        raise CaseError("", "", "reading MJCF needs MuJoCo: pip install mujoco") from None
    return mujoco


def _f(x: float) -> str:
    return repr(float(x)) if abs(x) > 1e-15 else "0.0"


def _vec(v) -> str:
    return "[" + ", ".join(_f(x) for x in v) + "]"


def _q(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _shown(s: str) -> str:
    """Text from outside (a file name) as one printable line: a newline in a comment would
    end it, and a control character is not allowed in a TOML string."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)


@contextmanager
def caught_warnings(mujoco) -> Iterator[list[str]]:
    """MuJoCo's warnings during the block, into the list yielded: its own handler prints
    them to stdout and appends them to MUJOCO_LOG.TXT in the current folder."""
    caught: list[str] = []
    old = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(caught.append)
    try:
        yield caught
    finally:
        mujoco.set_mju_user_warning(old)


def load_model(path: Path):
    """(spec, compiled model, MuJoCo's warnings) of an MJCF file; CaseError naming the
    file otherwise, and for a model holding a NaN or an infinity (MuJoCo only warns)."""
    mujoco = _mujoco()
    path = Path(path)
    if path.is_dir():
        raise CaseError(str(path), "", "a folder, not an MJCF file")
    if not path.is_file():
        raise CaseError(str(path), "", "no such MJCF file")
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:  # MuJoCo takes UTF-8 paths only (a TypeError otherwise)
        raise CaseError(_shown(str(path)), "", "the file name is not valid UTF-8; rename "
                        "the file") from None
    with caught_warnings(mujoco) as warned:
        try:
            spec = mujoco.MjSpec.from_file(str(path))
        except ValueError as e:
            raise CaseError(str(path), "", f"not a valid MJCF model: {_one_line(e)}") from None
        try:
            model = spec.compile()
        except ValueError as e:
            raise CaseError(str(path), _element(e),
                            f"does not compile: {_one_line(e)}") from None
    for w in warned:
        if re.search(r"\bnan\b|\binf", w, re.IGNORECASE):
            raise CaseError(str(path), "", f"not a valid MJCF model: {_one_line(w)}")
    _finite(str(path), model, mujoco)
    return spec, model, [f"MuJoCo warned: {_one_line(w)}" for w in warned]


# compiled arrays a case is read from, by the object they belong to (None: the model's)
_READ = {"mjOBJ_BODY": ("body_pos", "body_quat", "body_ipos", "body_iquat", "body_mass",
                        "body_inertia"),
         "mjOBJ_JOINT": ("jnt_pos", "jnt_axis"), "mjOBJ_EQUALITY": ("eq_data",),
         "mjOBJ_KEY": ("key_qpos", "key_qvel"), None: ("qpos0",)}


def _finite(file: str, m, mujoco) -> None:
    """CaseError naming the element of the first non-finite number the model holds
    (MuJoCo compiles an infinity without a word), or of one past the loader's
    MAX_MAGNITUDE (its square overflows: mass 1e300 warned of an overflow here)."""
    if not np.all(np.isfinite(m.opt.gravity)):
        raise CaseError(file, "option", "gravity is not finite")
    if np.abs(m.opt.gravity).max() > MAX_MAGNITUDE:
        raise CaseError(file, "option", f"gravity is beyond {MAX_MAGNITUDE:g} in size (its "
                        "square would overflow)")
    for obj, fields in _READ.items():
        for f in fields:
            rows = np.asarray(getattr(m, f), float)
            if not rows.size:
                continue
            rows = rows.reshape(len(rows), -1)
            bad = np.flatnonzero(~(np.abs(rows) <= MAX_MAGNITUDE).all(axis=1))  # NaN too
            if not len(bad):
                continue
            what = "the model"
            if obj is not None:
                name = mujoco.mj_id2name(m, getattr(mujoco.mjtObj, obj), int(bad[0]))
                what = f"{obj[6:].lower()} {name or int(bad[0])}"
            if np.isfinite(rows[bad[0]]).all():
                raise CaseError(file, what, f"{f} holds a value beyond {MAX_MAGNITUDE:g} in "
                                "size (its square would overflow)")
            raise CaseError(file, what, f"{f} holds a NaN or an infinity")


def _one_line(e: Exception) -> str:
    return " ".join(str(e).split())


def _element(e: Exception) -> str:
    """The element a MuJoCo compile error names ("... in equality constraint 0")."""
    m = re.search(r"in (\w[\w ]*?) (\d+)", str(e))
    return f"{m.group(1)} {m.group(2)}" if m else ""


class _Names:
    """Case names (safe identifiers, unique) for MuJoCo objects."""

    def __init__(self):
        self.used = {"ground"}

    def __call__(self, name: str, fallback: str) -> str:
        base = NAME_RE.sub("_", name or fallback)[:56] or fallback
        if base[0] in ".+-":
            base = "_" + base[1:]
        out, k = base, 1
        while out in self.used:
            k += 1
            out = f"{base}_{k}"
        self.used.add(out)
        return out


def _refuse(file: str, element: str, reason: str):
    raise CaseError(file, element, reason)


def _check(file: str, m, mujoco) -> list[str]:
    """Refuse what changes the motion and natcoord cannot carry; list what it drops."""
    name = lambda t, i: mujoco.mj_id2name(m, t, i) or f"#{i}"  # noqa: E731
    o = mujoco.mjtObj
    notes = []
    for j in range(m.njnt):
        jn, jt = f"joint {name(o.mjOBJ_JOINT, j)!r}", int(m.jnt_type[j])
        if jt == mujoco.mjtJoint.mjJNT_FREE:
            _refuse(file, jn, "a free joint (a floating body) is not supported: natcoord cases "
                    "join every body to the ground through joints")
        dofs = [d for d in range(m.nv) if m.dof_jntid[d] == j]
        for what, v in (("stiffness", m.jnt_stiffness[j]),
                        ("damping", max(m.dof_damping[dofs])),
                        ("armature", max(m.dof_armature[dofs])),
                        ("frictionloss", max(m.dof_frictionloss[dofs]))):
            if v != 0:
                _refuse(file, jn, f"{what} = {v:g} changes the dynamics and has no natcoord "
                        "counterpart; remove it or set it to 0")
        if m.jnt_limited[j]:
            notes.append(f"{jn}: range {m.jnt_range[j].tolist()} not enforced (a limit acts "
                         "only when reached: check the motion stays inside it)")
    for b in range(1, m.nbody):
        bn = f"body {name(o.mjOBJ_BODY, b)!r}"
        if int(m.body_jntnum[b]) > 1:
            _refuse(file, bn, f"{int(m.body_jntnum[b])} joints in one body are not supported "
                    "(one hinge, slide or ball per body)")
        if m.body_mocapid[b] >= 0:
            _refuse(file, bn, "a mocap body moves by prescription; not supported")
        if m.body_gravcomp[b] != 0:
            _refuse(file, bn, "gravcomp changes the dynamics; not supported")
    for t in range(m.ntendon):
        tn = f"tendon {name(o.mjOBJ_TENDON, t)!r}"
        if (m.tendon_stiffness[t] or m.tendon_damping[t] or m.tendon_frictionloss[t]
                or m.tendon_limited[t] or m.tendon_armature[t]):
            _refuse(file, tn, "a tendon with stiffness, damping, friction, armature or limits "
                    "changes the dynamics; not supported")
        notes.append(f"{tn}: not carried (no stiffness, damping or limits: it does not act)")
    for a in range(m.nu):
        an = f"actuator {name(o.mjOBJ_ACTUATOR, a)!r}"
        if np.any(m.actuator_biasprm[a] != 0):
            _refuse(file, an, "a biased actuator (position or velocity servo) applies force at "
                    "zero control; not supported")
        notes.append(f"{an}: not carried (zero control: no force)")
    for s in range(m.nsensor):
        notes.append(f"sensor {name(o.mjOBJ_SENSOR, s)!r}: not carried (outputs are the "
                     "case's channels)")
    for k in range(m.neq):
        en = f"equality {name(o.mjOBJ_EQUALITY, k)!r}"
        et = int(m.eq_type[k])
        if et not in (mujoco.mjtEq.mjEQ_CONNECT, mujoco.mjtEq.mjEQ_WELD):
            _refuse(file, en, f"a {mujoco.mjtEq(et).name[5:].lower()} equality is not "
                    "supported (connect and weld are)")
        if not m.eq_active0[k]:
            _refuse(file, en, "an inactive equality is not supported (its activation would "
                    "change the mechanism during the run)")
        notes.append(f"{en}: solref {m.eq_solref[k].tolist()}, solimp "
                     f"{np.round(m.eq_solimp[k], 6).tolist()} not carried (MuJoCo's soft "
                     "constraint tuning; natcoord's loops are rigid)")
    for what, v in (("viscosity", m.opt.viscosity), ("density", m.opt.density),
                    ("wind", np.linalg.norm(m.opt.wind))):
        if v != 0:
            _refuse(file, f"option {what}", f"{v:g}: fluid forces are not supported")
    if m.nflex:
        _refuse(file, "flex", "deformable (flex) bodies are not supported")
    if m.nplugin:
        _refuse(file, "plugin", "engine plugins are not supported")
    contacts = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT)
    colliding = [g for g in range(m.ngeom) if m.geom_contype[g] or m.geom_conaffinity[g]]
    if contacts and (colliding or m.npair):
        notes.append(f"contacts: {len(colliding)} colliding geom(s), {m.npair} pair(s) not "
                     "carried (natcoord has no contact; check that no geoms touch)")
    integ = mujoco.mjtIntegrator(int(m.opt.integrator)).name[6:]
    notes.append(f"option: integrator {integ}, timestep {m.opt.timestep:g} s not carried "
                 "(each engine's settings are in the case)")
    return notes


def _check_actuators(file: str, m, d, mujoco, start: str) -> None:
    """Refuse an actuator that applies force from the start (``d`` at it): a control from
    the keyframe, a ctrlrange that clamps zero control away from 0, or an activation that
    pushes or is about to change. natcoord carries actuators only as doing nothing."""
    mujoco.mj_forward(m, d)
    for a in range(m.nu):
        adr, num = int(m.actuator_actadr[a]), int(m.actuator_actnum[a])
        act = d.act[adr:adr + num] if adr >= 0 else np.zeros(0)
        moving = adr >= 0 and bool(np.any(d.act_dot[adr:adr + num] != 0))
        f = float(d.actuator_force[a])
        if f == 0 and not moving:
            continue
        ctrl = float(d.ctrl[a])
        lo, hi = m.actuator_ctrlrange[a]
        clamped = bool(m.actuator_ctrllimited[a]) and not lo <= ctrl <= hi
        why = [f"control {ctrl:g}" + (f", clamped to its ctrlrange [{lo:g}, {hi:g}]"
                                      if clamped else "")]
        if len(act):
            why.append(f"activation {_vec(act)}" + (", changing" if moving else ""))
        _refuse(file, f"actuator {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or a!r}",
                f"applies a force of {f:g} at the start ({start}: {'; '.join(why)}); "
                "natcoord carries an actuator only when it applies none: give it zero "
                "control and activation, or remove it")


def _assemble(file: str, m, d, mujoco, loops, welds) -> tuple[float, float]:
    """Close the connect and weld equalities at d.qpos by Gauss-Newton (least change of
    qpos, mj_integratePos) and project d.qvel onto them. Returns (qpos change, velocity
    change) norms."""
    q0, v0 = d.qpos.copy(), d.qvel.copy()
    for _ in range(50):
        r, J = _residual(m, d, mujoco, loops, welds)
        if r.size == 0 or np.abs(r).max() < CLOSE_TOL:
            break
        dq = -np.linalg.lstsq(J, r, rcond=1e-12)[0]
        mujoco.mj_integratePos(m, d.qpos, dq, 1.0)
    else:
        _refuse(file, "equality", f"the loops do not close from the initial state (residual "
                f"{np.abs(r).max():.3g} m after 50 Gauss-Newton steps)")
    r, J = _residual(m, d, mujoco, loops, welds)
    if r.size:
        d.qvel[:] = d.qvel - np.linalg.pinv(J, rcond=1e-10) @ (J @ d.qvel)
    dq = np.zeros(m.nv)
    mujoco.mj_differentiatePos(m, dq, 1.0, q0, d.qpos)
    return float(np.linalg.norm(dq)), float(np.linalg.norm(d.qvel - v0))


def _residual(m, d, mujoco, loops, welds):
    """Loop residuals (k,) and their Jacobian (k, nv) at d.qpos (kinematics updated)."""
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    rows, jac = [], []
    for b1, a1, b2, a2 in loops:
        p1, J1 = _point(m, d, mujoco, b1, a1)
        p2, J2 = _point(m, d, mujoco, b2, a2)
        rows.append(p1 - p2)
        jac.append(J1 - J2)
    for b1, b2, rel, a1, a2 in welds:  # R2 = R1 rel (MuJoCo's relpose), a1 = a2 there
        p1, J1 = _point(m, d, mujoco, b1, a1)
        p2, J2 = _point(m, d, mujoco, b2, a2)
        R1, R2 = d.xmat[b1].reshape(3, 3), d.xmat[b2].reshape(3, 3)
        E = R1 @ rel @ R2.T  # I when closed; its axial vector the small rotation 2 -> 1
        rows += [p1 - p2, 0.5 * np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0],
                                          E[1, 0] - E[0, 1]])]
        jac += [J1 - J2, _rot(m, d, mujoco, b1) - _rot(m, d, mujoco, b2)]
    if not rows:
        return np.zeros(0), np.zeros((0, m.nv))
    return np.concatenate(rows), np.vstack(jac)


def _point(m, d, mujoco, body: int, local: np.ndarray):
    x = d.xpos[body] + d.xmat[body].reshape(3, 3) @ local
    J = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, J, None, x, body)
    return x, J


def _rot(m, d, mujoco, body: int):
    J = np.zeros((3, m.nv))
    mujoco.mj_jacBody(m, d, None, J, body)
    return J


def _plane(m, d, mujoco, g: np.ndarray) -> np.ndarray | None:
    """Rows e1, e2, n of the plane every joint moves in, or None (3-D)."""
    axes = d.xaxis
    n = None
    for j in range(m.njnt):
        t = int(m.jnt_type[j])
        if t == mujoco.mjtJoint.mjJNT_BALL:
            return None
        if t == mujoco.mjtJoint.mjJNT_HINGE:
            if n is None:
                n = axes[j] / np.linalg.norm(axes[j])
            elif np.linalg.norm(np.cross(n, axes[j])) > PLANAR_TOL:
                return None
    if n is None:
        return None
    for j in range(m.njnt):
        if int(m.jnt_type[j]) == mujoco.mjtJoint.mjJNT_SLIDE and abs(axes[j] @ n) > PLANAR_TOL:
            return None
    if abs(g @ n) > PLANAR_TOL:
        return None
    gp = g - (g @ n) * n
    if np.linalg.norm(gp) > 0:
        e2 = -gp / np.linalg.norm(gp)
    else:
        k = int(np.argmin(np.abs(n)))
        e2 = np.cross(n, np.eye(3)[k])
        e2 /= np.linalg.norm(e2)
    e1 = np.cross(e2, n)
    if e1[np.argmax(np.abs(e1))] < 0:  # x along a world axis's positive sense
        e1, n = -e1, -n
    return np.array([e1, e2, n])


def import_mjcf(path: str | Path, name: str, *, duration: float = 2.0,
                output_dt: float = OUTPUT_DT) -> Imported:
    """The case text of an MJCF model (see the module docstring).

    Parameters
    ----------
    path : the MJCF file.
    name : the case name (the case file's stem).
    duration, output_dt : s, the scenario's length and output interval.

    Raises CaseError (file, element, reason) for a model it cannot carry.
    """
    mujoco = _mujoco()
    path = Path(path)
    file = str(path)
    _, m, warned = load_model(path)
    notes = warned + _check(file, m, mujoco)
    d = mujoco.MjData(m)
    if m.nkey:
        d.qpos[:], d.qvel[:] = m.key_qpos[0], m.key_qvel[0]
        d.ctrl[:], d.act[:] = m.key_ctrl[0], m.key_act[0]
        kn = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, 0) or "0"
        start = f"keyframe {kn!r}"
    else:
        d.qpos[:] = m.qpos0
        start = "qpos0, at rest"
    _check_actuators(file, m, d, mujoco, start)
    bname = lambda b: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}"  # noqa
    ename = lambda k: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_EQUALITY, k)  # noqa: E731

    # bodies: one group per rigid body (jointless children and welds merged), 0 = ground
    group = list(range(m.nbody))

    def find(b):
        while group[b] != b:
            b = group[b]
        return b

    def union(a, b):  # the lower id (closer to the root) names the group
        ra, rb = find(a), find(b)
        group[max(ra, rb)] = min(ra, rb)

    for b in range(1, m.nbody):
        if m.body_jntnum[b] == 0:
            union(b, int(m.body_parentid[b]))
    loops_eq, welds_eq = [], []
    for k in range(m.neq):
        o1, o2 = int(m.eq_obj1id[k]), int(m.eq_obj2id[k])
        data = m.eq_data[k]
        if int(m.eq_objtype[k]) == mujoco.mjtObj.mjOBJ_SITE:
            b1, b2 = int(m.site_bodyid[o1]), int(m.site_bodyid[o2])
            a1, a2 = m.site_pos[o1].copy(), m.site_pos[o2].copy()
        else:
            b1, b2, a1, a2 = o1, o2, data[0:3].copy(), data[3:6].copy()
        if int(m.eq_type[k]) == mujoco.mjtEq.mjEQ_CONNECT:
            loops_eq.append((k, b1, a1, b2, a2))
        else:
            if int(m.eq_objtype[k]) == mujoco.mjtObj.mjOBJ_SITE:
                _refuse(file, f"equality {ename(k) or k!r}", "a weld between sites is not "
                        "supported (weld bodies)")
            rel = np.zeros(9)
            mujoco.mju_quat2Mat(rel, data[6:10])
            rel = rel.reshape(3, 3)  # MuJoCo holds R2 = R1 rel, and this point of both:
            welds_eq.append((k, b1, b2, rel, data[3:6] + rel @ data[0:3], data[0:3].copy()))
    moved, dv = _assemble(file, m, d, mujoco, [x[1:] for x in loops_eq],
                          [x[1:] for x in welds_eq])
    if moved > 1e-12:
        notes.append(f"initial state ({start}): the loops did not close; closed by "
                     f"Gauss-Newton, qpos moved by {moved:.3g}")
    if dv > 1e-12:
        notes.append(f"initial velocity projected onto the loops (changed by {dv:.3g})")
    mujoco.mj_forward(m, d)
    for k, b1, b2, *_ in welds_eq:
        if find(b1) == find(b2):
            notes.append(f"equality {ename(k) or k!r}: weld within one rigid body, redundant")
        union(b1, b2)

    g = np.array(m.opt.gravity, float)
    if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        g = np.zeros(3)
    frame = _plane(m, d, mujoco, g)
    dim = 3 if frame is None else 2
    P = np.eye(3) if frame is None else frame[:2]

    names = _Names()
    roots = sorted({find(b) for b in range(1, m.nbody)} - {0})
    body_name = {r: names(bname(r), f"body{r}") for r in roots}
    members = {r: [b for b in range(1, m.nbody) if find(b) == r] for r in roots}
    cname = lambda b: "ground" if find(b) == 0 else body_name[find(b)]  # noqa: E731
    points: dict[str, dict[str, np.ndarray]] = {"ground": {}} | {body_name[r]: {} for r in roots}
    joints, loops = [], {}
    for j in range(m.njnt):  # tree joints, in tree order
        b = int(m.jnt_bodyid[j])
        parent = int(m.body_parentid[b])
        jn = names(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j), f"j{j}")
        if find(parent) == find(b):
            notes.append(f"joint {jn!r}: locked by a weld (its two sides are one body)")
            continue
        x = d.xanchor[j].copy()
        t = int(m.jnt_type[j])
        jtype = {mujoco.mjtJoint.mjJNT_HINGE: "revolute", mujoco.mjtJoint.mjJNT_SLIDE:
                 "prismatic", mujoco.mjtJoint.mjJNT_BALL: "spherical"}[t]
        axis = None
        if jtype == "prismatic" or (jtype == "revolute" and dim == 3):
            axis = P @ d.xaxis[j]
        for body in (cname(parent), cname(b)):
            points[body][jn] = x
        joints.append((jn, jtype, cname(parent), cname(b), axis))
    for k, b1, a1, b2, _ in loops_eq:
        jn = names(ename(k), f"connect{k}")
        x = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ a1
        if cname(b1) == cname(b2):
            _refuse(file, f"equality {jn!r}", "connects a body to itself (after welds)")
        for body in (cname(b1), cname(b2)):
            points[body][jn] = x
        joints.append((jn, "spherical" if dim == 3 else "revolute", cname(b1), cname(b2),
                       None))
        loops[jn] = (b1, a1)

    # mass properties (world, about the centre of mass) and the points each body needs
    bodies = []
    for r in roots:
        bn = body_name[r]
        mass = float(sum(m.body_mass[b] for b in members[r]))
        if mass <= 0:
            _refuse(file, f"body {bname(r)!r}", "a moving body without mass")
        com = sum(m.body_mass[b] * d.xipos[b] for b in members[r]) / mass
        J = np.zeros((3, 3))
        for b in members[r]:
            R = d.ximat[b].reshape(3, 3)
            c = d.xipos[b] - com
            J += R @ np.diag(m.body_inertia[b]) @ R.T + m.body_mass[b] * (c @ c * np.eye(3)
                                                                          - np.outer(c, c))
        pts = points[bn]
        _complete(pts, bn, com, dim, P, any(j[4] is not None and bn in j[2:4] for j in joints),
                  names)
        bodies.append((bn, mass, com, J, pts))

    # the initial velocity: point-position channels that fix it
    vel = _velocity_channels(m, d, mujoco, members, body_name, points, loops_eq, welds_eq, P)
    text = _text(path, name, m, d, mujoco, dim, P, frame, g, duration, output_dt, bodies,
                 joints, points, loops, vel, notes, start)
    return Imported(text, notes, dim, d.qpos.copy(), d.qvel.copy(),
                    {body_name[r]: members[r] for r in roots}, loops, frame)


def _complete(pts: dict, bn: str, com: np.ndarray, dim: int, P: np.ndarray,
              has_axis: bool, names: _Names) -> None:
    """Give a body the points that define its frame: two apart (the first two), and in 3-D
    one off their plane when they span a plane and no joint axis completes it. A point
    added is named by ``names`` (never a joint's name: a joint named 'rod_c' kept its
    point)."""
    xs = list(pts.items())
    if not xs:
        pts[names(f"{bn}_com", "com")] = com
        xs = list(pts.items())
    first = xs[0][1]
    far = [(k, x) for k, x in xs[1:] if np.linalg.norm(P @ (x - first)) > 1e-6]
    if not far:
        k = int(np.argmin(np.abs(P @ np.ones(3)))) if dim == 3 else 0
        off = com if np.linalg.norm(P @ (com - first)) > 1e-6 else first + P.T @ np.eye(dim)[k]
        far = [(names(f"{bn}_c", "c"), off)]
    rest = [(k, x) for k, x in xs[1:] if k != far[0][0]]
    ordered = [xs[0], far[0]] + rest
    if dim == 3 and not has_axis:
        D = np.array([x - first for _, x in ordered[1:]])
        if np.linalg.matrix_rank(D, tol=1e-9) == 2:
            u, s, vt = np.linalg.svd(D)
            scale = float(np.linalg.norm(far[0][1] - first))
            ordered.append((names(f"{bn}_n", "n"), first + vt[2] * scale))
    pts.clear()
    pts.update(ordered)


def _velocity_channels(m, d, mujoco, members, body_name, points, loops_eq, welds_eq,
                       P) -> list[tuple[str, str, str, str, float]]:
    """(channel, body, point, axis, velocity) rows: point-velocity components that fix the
    (projected) qvel among the velocities the loops allow; [] at rest."""
    if not np.any(d.qvel != 0):
        return []
    _, J = _residual(m, d, mujoco, [x[1:] for x in loops_eq], [x[1:] for x in welds_eq])
    if J.shape[0]:
        _, s, vt = np.linalg.svd(J)
        rank = int((s > 1e-10 * max(1.0, s[0])).sum())
        N = vt[rank:].T
    else:
        N = np.eye(m.nv)
    chosen, rows = [], np.zeros((0, N.shape[1]))
    axes = "xyz"[:P.shape[0]]
    for r, b_ids in members.items():
        bn = body_name[r]
        for pn, x in points[bn].items():
            _, Jp = _point(m, d, mujoco, b_ids[0], d.xmat[b_ids[0]].reshape(3, 3).T
                           @ (x - d.xpos[b_ids[0]]))
            for i, a in enumerate(axes):
                row = (P @ Jp)[i] @ N
                trial = np.vstack([rows, row])
                if np.linalg.matrix_rank(trial, tol=1e-9) > rows.shape[0]:
                    rows = trial
                    chosen.append((f"{a}_{bn}_{pn}"[:64], bn, pn, a,
                                   float((P @ Jp)[i] @ d.qvel)))
                if rows.shape[0] == N.shape[1]:
                    return chosen
    return chosen


def _text(path, name, m, d, mujoco, dim, P, frame, g, duration, output_dt, bodies, joints,
          points, loops, vel, notes, start) -> str:
    ax = "xyz"[:dim]
    file = _shown(path.name)
    L = [f"# Imported by `natcoord import {file} --out {name}.toml` from the MuJoCo model",
         f"# {file} ({start}); masses, centres of mass and inertias as MuJoCo compiled them.",
         "# Re-import rather than editing the mechanism; add engine tolerances from",
         f"# `natcoord reference update {name}` and `natcoord propose {name}`."]
    if frame is not None:
        L.append(f"# 2-D: x = world {_vec(frame[0])}, y = world {_vec(frame[1])}; every "
                 f"hinge turns about {_vec(frame[2])}.")
    L.append("# Not carried from the MJCF:")
    L += [f"#   {_shown(n)}" for n in notes]
    desc = (f"Imported from MuJoCo model {file}: {len(bodies)} bodies, {len(joints)} "
            f"joints, {len(loops)} loop(s) ({dim}-D, {duration:g} s)")
    tags = ["mjcf", f"{dim}d"] + (["closed-loop"] if loops else [])
    L += [f"name = {_q(name)}", f"description = {_q(desc)}", f"dimension = {dim}",
          f"gravity = {_vec(P @ g)}", f"duration = {_f(duration)}",
          f"output_dt = {_f(output_dt)}", "tags = [" + ", ".join(_q(t) for t in tags) + "]",
          "", "# No [initial.pose]: every point is its world position at t = 0.", "[ground]",
          "points = { " + ", ".join(f"{k} = {_vec(P @ x)}" for k, x in points["ground"].items())
          + " }", ""]
    for bn, mass, com, J, pts in bodies:
        n = frame[2] if frame is not None else None
        inertia = (_f(n @ J @ n) if dim == 2 else
                   "[" + ", ".join(_vec(row) for row in J) + "]")
        L += ["[[bodies]]", f"name = {_q(bn)}", 'kind = "rigid"', f"mass = {_f(mass)}",
              f"com = {_vec(P @ com)}", f"inertia = {inertia}",
              "points = { " + ", ".join(f"{k} = {_vec(P @ x)}" for k, x in pts.items()) + " }",
              ""]
    for jn, jtype, a, b, axis in joints:
        L += ["[[joints]]", f"name = {_q(jn)}", f"type = {_q(jtype)}",
              f"bodies = [{_q(a)}, {_q(b)}]", f"points = [{_q(jn)}, {_q(jn)}]"]
        if axis is not None:
            L.append(f"axis = {_vec(axis / np.linalg.norm(axis))}")
        L.append("")
    chans: dict[str, str] = {}  # name -> definition; names unique, definitions too

    def channel(name: str, definition: str) -> str:
        """The channel's name in the file: an identical channel's, else ``name`` made
        unique (a connect named 'crank_A' once gave the loop's position channel the name
        of a velocity channel, which then set the wrong point's velocity)."""
        for n, dfn in chans.items():
            if dfn == definition:
                return n
        base, out, k = name[:60], name[:64], 1
        while out in chans or out == "energy":
            k += 1
            out = f"{base}_{k}"
        chans[out] = definition
        return out

    first = next((j for j in joints if j[1] == "revolute" and j[2] == "ground"), None)
    if first is not None:
        bn, jn = first[3], first[0]
        other = next(k for k in points[bn] if k != jn)
        if dim == 2:
            channel(f"theta_{bn}", f'kind = "angle", body = {_q(bn)}, points = '
                    f'[{_q(jn)}, {_q(other)}]')
        else:
            k = int(np.argmax(np.abs(first[4])))
            if abs(abs(first[4][k]) - 1) < 1e-12:
                plane = {0: "yz", 1: "xz", 2: "xy"}[k]
                channel(f"theta_{bn}", f'kind = "angle", body = {_q(bn)}, points = '
                        f'[{_q(jn)}, {_q(other)}], plane = "{plane}"')
    for jn in loops:
        b = next(j[2] for j in joints if j[0] == jn)
        for a in ax:
            channel(f"{a}_{jn}", f'kind = "position", body = {_q(b)}, point = {_q(jn)}, '
                    f'axis = "{a}"')
    for jn in loops:
        for a in ax:
            channel(f"{jn}_{a}", f'kind = "reaction", joint = {_q(jn)}, axis = "{a}"')
    velocity = [(channel(cn, f'kind = "position", body = {_q(bn)}, point = {_q(pn)}, '
                         f'axis = "{a}"'), v) for cn, bn, pn, a, v in vel]
    L += ["[initial]"]
    L.append("velocity = { " + ", ".join(f"{cn} = {_f(v)}" for cn, v in velocity) + " }"
             if vel else "# at rest")
    lines = [f"{n} = {{ {dfn} }}" for n, dfn in chans.items()] + ['energy = { kind = "energy" }']
    L += ["", "[channels]"] + lines + [""]
    return "\n".join(L)
