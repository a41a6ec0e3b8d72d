"""The MJCF model of a lifted case (:func:`natcoord.engines.planar.lift_case`): one builder
for every case.

Nothing from a case file reaches the text unescaped: numbers are written by :func:`fmt`
(``repr`` of a float) or ``int``, every name and word through ``quoteattr`` (the loader has
also checked every setting against :data:`natcoord.engines.mujoco_engine.SETTINGS`).

Each body is placed at its assembled frame at t = 0 (relative to its tree parent), so
``qpos0`` is the assembled state; the joints' initial velocities are returned in the XML's
joint order.
"""

from __future__ import annotations

import dataclasses
from xml.sax.saxutils import quoteattr

import numpy as np

from ...case.mechanism import GROUND, Case, Joint
from ...errors import Unsupported
from ..planar import GROUND_FRAME, Frame, frame_of, node_point
from ..tree import spanning_tree, tree_parents

# a connect equality holds a point: it can close a loop only where a joint is a point joint
POINT_JOINTS = ("revolute", "spherical")
# how the joints a connect cannot close are built in the tree
TREE_FORM = {"prismatic": "slide joints", "cylindrical": "slide and hinge joints",
             "universal": "hinge pairs"}
# zero inertia of a point mass is replaced by this fraction of m r^2 (r: its farthest point)
ZERO_INERTIA_SUBSTITUTE = 1e-10


def fmt(*xs) -> str:
    """Numbers as MJCF text, exactly (repr)."""
    return " ".join(repr(float(x)) for x in xs)


def _quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (3, 3)."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, float).ravel())
    return q


def _named(joints: list[Joint]) -> str:
    return ", ".join(f"{j.type} {j.name}" for j in joints)


def split_tree(case: Case) -> tuple[list[Joint], list[Joint], list[str]]:
    """Tree joints (parent first), loop joints and a note.

    :func:`natcoord.engines.tree.spanning_tree`; when it would leave a joint that is not a
    point joint to close a loop, the tree is rebuilt with those joints first (the loop is cut
    at a revolute or spherical joint instead). Unsupported when one must still close a loop.
    """
    tree, loops = spanning_tree(case)
    recut = [j for j in loops if j.type not in POINT_JOINTS]
    if not recut:
        return tree, loops, []
    first = tuple(sorted(case.joints, key=lambda j: j.type in POINT_JOINTS))
    tree, loops = spanning_tree(dataclasses.replace(case, joints=first))
    bad = [j for j in loops if j.type not in POINT_JOINTS]
    if bad:
        raise Unsupported(f"{_named(bad)} must close a loop: MuJoCo has no point-on-line "
                          "equality (a connect equality holds a point only)")
    kinds = "; ".join(f"{k} joints are tree {TREE_FORM[k]}"
                      for k in sorted({j.type for j in recut}))
    return tree, loops, [f"loop cut at {_named(loops)} instead of {_named(recut)} (MuJoCo has "
                         f"no point-on-line equality); {kinds}"]


def _axial_loops(loops: list[Joint], offset: float, planar: bool) -> dict[str, float]:
    """Loop-closing 3-D revolutes that get a second connect ``offset`` m along their axis
    (setting ``loop_axis_offset``, 0: none): one connect leaves the joint a ball joint."""
    if offset <= 0.0 or planar:
        return {}
    return {j.name: offset for j in loops if j.type == "revolute" and j.axis is not None}


@dataclasses.dataclass
class Built:
    """The MJCF text and what reading the run needs."""

    xml: str
    tree: list[Joint]
    loops: list[Joint]
    parent: dict  # child -> (parent, the case's joint)
    qvel: list[float]  # initial joint velocities, in the XML's joint order
    notes: list[str]
    solref: tuple[float, float]


def _inertia(b, s: dict, welded: bool, notes: list[str]) -> np.ndarray:
    """The (3, 3) inertia MuJoCo gets, kg m^2, about the centre of mass in body axes.

    A particle welded to its parent gets none (its rotation is its parent's and carries no
    energy: exact); a particle on a slide or floating gets ``particle_inertia`` (its joints
    cannot turn it). A point mass (zero tensor) gets ZERO_INERTIA_SUBSTITUTE m r^2, a tensor
    with a zero principal moment ``zero_inertia`` x its largest one there: MuJoCo needs
    inertia > 1e-15.
    """
    if b.kind == "particle":
        return np.zeros((3, 3)) if welded else float(s["particle_inertia"]) * np.eye(3)
    J = np.asarray(b.inertia, float)
    w, V = np.linalg.eigh(J)
    if w.max() <= 0:
        reach = max(float(np.linalg.norm(p - b.com)) for p in b.points.values())
        i = ZERO_INERTIA_SUBSTITUTE * b.mass * reach**2
        notes.append(f"body {b.name} is a point mass (zero inertia); MuJoCo needs "
                     f"inertia > 1e-15, so it gets {i:.1e} kg m^2 "
                     f"({ZERO_INERTIA_SUBSTITUTE:.0e} of m r^2 about its farthest "
                     "point): a relative change of that size in its inertia")
        return i * np.eye(3)
    small = w <= 1e-12 * w.max()
    if np.any(small):
        eps = float(s["zero_inertia"])
        add = eps * float(w.max())
        J = J + add * sum(np.outer(V[:, k], V[:, k]) for k in np.flatnonzero(small))
        what = ("its own axis (a slender rod)" if b.kind == "uniform_rod"
                else "a principal axis")
        notes.append(f"body {b.name} has no inertia about {what}; MuJoCo needs a positive "
                     f"inertia, so it gets {add:.3g} kg m^2 there ({eps:g} of its largest "
                     "principal moment)")
    return J


def _inertial_xml(b, J: np.ndarray) -> str:
    full = fmt(J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2])
    return (f'<inertial pos="{fmt(*b.com)}" mass="{fmt(b.mass)}" '
            + (f'fullinertia="{full}"/>' if np.any(J) else 'diaginertia="0.0 0.0 0.0"/>'))


def _site(name: str, pos) -> str:
    return f"<site name={quoteattr(name)} pos=\"{fmt(*pos)}\"/>"


class _Writer:
    """Writes the bodies of the worldbody, depth first, and collects initial velocities."""

    def __init__(self, case: Case, frames: dict[str, Frame], parent: dict, sites: dict,
                 s: dict, planar: bool):
        self.case, self.frames, self.parent, self.sites, self.s = case, frames, parent, sites, s
        self.planar = planar
        self.children: dict[str, list[str]] = {}
        for child, (par, _) in parent.items():
            self.children.setdefault(par, []).append(child)
        self.lines: list[str] = []
        self.qvel: list[float] = []
        self.notes: list[str] = []
        self.welded: dict[str, str] = {}  # particle -> type of the joint it is welded at
        self.slid: list[str] = []

    def frame(self, name: str) -> Frame:
        return frame_of(self.frames, name)

    def joint(self, pad: str, name: str, kind: str, pos, axis) -> None:
        self.lines.append(f'{pad}  <joint name={quoteattr(name)} type="{kind}" '
                          f'pos="{fmt(*pos)}" axis="{fmt(*axis)}"/>')

    def tree_joints(self, name: str, pad: str) -> None:
        """The joint(s) between ``name`` and its tree parent, and their initial velocities
        (rates of the child against its parent at t = 0)."""
        b = self.case.body(name)
        pname, cj = self.parent[name]
        f, pf = self.frame(name), self.frame(pname)
        k = 1 if cj.bodies[1] == name else 0  # the child's end of the joint
        pc = node_point(self.case, name, cj.points[k])
        wrel = f.omega - pf.omega
        if b.kind == "particle" and cj.type in ("revolute", "spherical", "universal"):
            self.welded[name] = cj.type  # the joint passes through its mass: nothing to turn
            return
        if cj.type == "spherical":
            self.lines.append(f'{pad}  <joint name={quoteattr(cj.name)} type="ball" '
                              f'pos="{fmt(*pc)}"/>')
            self.qvel.extend((f.R.T @ wrel).tolist())
            return
        # velocity of the child's joint point against the parent's: a slide's rate along u
        pp = node_point(self.case, pname, cj.points[1 - k])
        vrel = (f.velocity + np.cross(f.omega, f.R @ pc)
                - pf.velocity - np.cross(pf.omega, pf.R @ pp))
        for jname, kind, u in self.dofs(cj, k, pf):
            if kind == "hinge" and b.kind == "particle":
                continue  # a particle's turn carries no energy
            self.joint(pad, jname, kind, pc, f.R.T @ u)
            self.qvel.append(float((wrel if kind == "hinge" else vrel) @ u))
        if b.kind == "particle":
            self.slid.append(name)

    def dofs(self, cj: Joint, k: int, pf: Frame) -> list[tuple[str, str, np.ndarray]]:
        """The MuJoCo joints (name, hinge | slide, world axis (3,) at t = 0) that make the
        case's joint ``cj`` whose end ``k`` is the child (``pf``: the parent's frame)."""
        if cj.type == "universal":
            # two hinges in one body compose as parent x Rot(a, q1) x Rot(b, q2): the first
            # axis stays on the parent, the second on the child (a Cardan joint, exact)
            on_parent, on_child = (cj.axis, cj.axis2) if k == 1 else (cj.axis2, cj.axis)
            return [(cj.name, "hinge", pf.R @ on_parent),
                    (cj.name + "_2", "hinge", self.frame(cj.bodies[k]).R @ on_child)]
        u = self.frame(cj.bodies[0]).R @ cj.axis  # world, on the first body
        if cj.type == "revolute":
            return [(cj.name, "hinge", u)]
        u = u if k == 1 else -u  # the slide of the second body against the first
        return [(cj.name, "slide", u)] + ([(cj.name + "_rot", "hinge", u)]
                                          if cj.type == "cylindrical" else [])

    def float_joints(self, name: str, pad: str) -> None:
        """A body the tree does not reach: in a planar case it stays in the plane (slide x,
        slide y, hinge z), in space a free joint; a particle translates only."""
        b, f = self.case.body(name), self.frame(name)
        axes = "xyz"[:2 if self.planar else 3]
        if b.kind == "particle" or self.planar:
            for i, ax in enumerate(axes):  # along the world axes, written in the body frame
                self.joint(pad, f"{name}_{ax}", "slide", np.zeros(3), f.R[i])
                self.qvel.append(float(f.velocity[i]))
            turn = "" if b.kind == "particle" else ", hinge z"
            if turn:
                self.joint(pad, f"{name}_rz", "hinge", np.zeros(3), f.R[2])
                self.qvel.append(float(f.omega[2]))
            else:
                self.slid.append(name)
            self.notes.append(f"body {name} is not joined to the ground: "
                              + ", ".join(f"slide {ax}" for ax in axes) + turn)
            return
        self.notes.append(f"body {name} is not joined to the ground: free joint")
        self.lines.append(f'{pad}  <freejoint name={quoteattr(name + "_free")}/>')
        self.qvel.extend(f.velocity.tolist() + (f.R.T @ f.omega).tolist())

    def body(self, name: str, indent: int) -> None:
        """``<body>`` of ``name`` at its frame relative to its parent, and its subtree."""
        pad = " " * indent
        f = self.frame(name)
        pf = self.frame(self.parent[name][0]) if name in self.parent else GROUND_FRAME
        rel, relR = pf.R.T @ (f.origin - pf.origin), pf.R.T @ f.R
        self.lines.append(f'{pad}<body name={quoteattr(name)} pos="{fmt(*rel)}" '
                          f'quat="{fmt(*_quat(relR))}">')
        if name in self.parent:
            self.tree_joints(name, pad)
        else:
            self.float_joints(name, pad)
        b = self.case.body(name)
        J = _inertia(b, self.s, name in self.welded, self.notes)
        self.lines.append(f"{pad}  {_inertial_xml(b, J)}")
        self.lines.extend(f"{pad}  {site}" for site in self.sites.get(name, []))
        for c in self.children.get(name, []):
            self.body(c, indent + 2)
        self.lines.append(f"{pad}</body>")

    def particle_notes(self) -> list[str]:
        pin = float(self.s["particle_inertia"])
        return ([f"particle {n} welded to its tree parent at its {t} joint (no hinge, "
                 "zero inertia: exact for a point mass)" for n, t in self.welded.items()]
                + [f"particle {n} given inertia {pin:g} kg m^2 (MuJoCo needs one; its joints "
                   "cannot turn it, so it does not act)" for n in self.slid])


def tendons(case: Case, solref: tuple[float, float], solimp: str):
    """Rods as tendon-length equalities, springs as passive tendon springs: (sites by body,
    ``<spatial>`` lines, ``<tendon>`` equality lines, notes)."""
    sites: dict[str, list[str]] = {}
    spatial, equality, notes = [], [], []
    for kind, items in (("rod", case.rods), ("spring", case.springs)):
        for r in items:
            names = [f"{kind}_{r.name}_{k}" for k in (0, 1)]
            for s, (b, p) in zip(names, r.ends, strict=True):
                sites.setdefault(b, []).append(_site(s, node_point(case, b, p)))
            extra = ""
            if kind == "spring":
                extra = (f' stiffness="{float(r.stiffness)!r}" damping="{float(r.damping)!r}" '
                         f'springlength="{float(r.length)!r}"')
            spatial.append(f"    <spatial name={quoteattr(f'{kind}_{r.name}')}{extra}>"
                           f"<site site={quoteattr(names[0])}/><site site={quoteattr(names[1])}/>"
                           "</spatial>")
            if kind == "rod":
                equality.append(f"    <tendon name={quoteattr(f'rod_{r.name}')} "
                                f"tendon1={quoteattr(f'rod_{r.name}')} "
                                f'solref="{fmt(*solref)}" solimp="{solimp}"/>')
    if case.rods:
        notes.append(f"massless rods {', '.join(r.name for r in case.rods)}: spatial tendons "
                     f"between two sites with a tendon-length equality (solref {fmt(*solref)}, "
                     f"solimp {solimp}); tension = -efc_force of its row. MuJoCo's equality "
                     "leaves out the v^2/L term of the length's acceleration, so a rod swinging "
                     f"at speed v stretches by about tc^2 v^2 / L (tc = {solref[0]:g} s)")
    if case.springs:
        notes.append(f"spring-dampers {', '.join(r.name for r in case.springs)}: spatial "
                     "tendons with MuJoCo's passive stiffness and damping, springlength = "
                     "the spring's rest length")
    return sites, spatial, equality, notes


def document(case: Case, s: dict, sites: dict, lines: list, spatial: list,
             equality: list) -> str:
    """The MJCF model: options from the settings, the bodies' ``lines``, tendons and
    equalities; contacts disabled."""
    return "\n".join([
        f"<mujoco model={quoteattr(case.name)}>",
        '  <compiler angle="radian" inertiafromgeom="false" balanceinertia="false"/>',
        f'  <option timestep="{float(s["dt"])!r}" gravity="{fmt(*case.gravity)}" '
        f'integrator={quoteattr(str(s["integrator"]))} solver={quoteattr(str(s["solver"]))} '
        f'tolerance="{float(s["tolerance"])!r}" iterations="{int(s["iterations"])}" '
        f'ls_iterations="{int(s["ls_iterations"])}">',
        '    <flag contact="disable"/>',
        "  </option>",
        "  <worldbody>",
        *[f"    {site}" for site in sites.get(GROUND, [])],
        *lines,
        "  </worldbody>",
        *(["  <tendon>", *spatial, "  </tendon>"] if spatial else []),
        *(["  <equality>", *equality, "  </equality>"] if equality else []),
        "</mujoco>",
    ])


def build(case: Case, frames: dict[str, Frame], s: dict, planar: bool) -> Built:
    """The MJCF of a lifted ``case`` (every vector (3,)) at its frames at t = 0; ``s`` the
    merged settings; ``planar``: bodies the tree does not reach stay in the plane."""
    tree, loops, notes = split_tree(case)
    parent = {child: (par, case.joint(j.name)) for j, par, child in tree_parents(tree)}
    solref = (float(s["solref_steps"]) * float(s["dt"]), float(s["solref_damping"]))
    solimp = fmt(*s["solimp"])
    sites, spatial, equality, ten_notes = tendons(case, solref, solimp)
    notes += ten_notes
    axial = _axial_loops(loops, float(s.get("loop_axis_offset", 0.0)), planar)
    for j in loops:
        for k in (0, 1):
            sites.setdefault(j.bodies[k], []).append(
                _site(f"loop_{j.name}_{k}", node_point(case, j.bodies[k], j.points[k])))
            if j.name in axial:  # the same point moved along the axis, in this body's frame
                fr = GROUND_FRAME if j.bodies[k] == GROUND else frames[j.bodies[k]]
                fa = GROUND_FRAME if j.bodies[0] == GROUND else frames[j.bodies[0]]
                off = fr.R.T @ (fa.R @ j.axis) * axial[j.name]
                sites[j.bodies[k]].append(_site(
                    f"loop_{j.name}_axis_{k}",
                    node_point(case, j.bodies[k], j.points[k]) + off))
    w = _Writer(case, frames, parent, sites, s, planar)
    for c in w.children.get(GROUND, []):
        w.body(c, 4)
    for b in case.bodies:
        if b.name not in parent:
            w.body(b.name, 4)
    eq = [f'    <connect name={quoteattr(j.name)} site1={quoteattr(f"loop_{j.name}_0")} '
          f'site2={quoteattr(f"loop_{j.name}_1")} solref="{fmt(*solref)}" solimp="{solimp}"/>'
          for j in loops]
    eq += [f'    <connect name={quoteattr(j.name + "_axis")} '
           f'site1={quoteattr(f"loop_{j.name}_axis_0")} '
           f'site2={quoteattr(f"loop_{j.name}_axis_1")} solref="{fmt(*solref)}" '
           f'solimp="{solimp}"/>' for j in loops if j.name in axial]
    notes += w.notes
    notes += [f"loop revolute {j} also holds its axis: a second connect {axial[j]:g} m along "
              "it (6 rows for 5, one redundant; the joint force is the sum of both)"
              for j in axial]
    notes += [f"connect equality (3 rows) for loop {j.type} joint {j.name} (site1 on "
              f"{j.bodies[0]}, site2 on {j.bodies[1]}), solref {fmt(*solref)}, solimp {solimp}"
              for j in loops]
    notes += w.particle_notes()
    xml = document(case, s, sites, w.lines, spatial, eq + equality)
    return Built(xml, tree, loops, parent, w.qvel, notes, solref)
