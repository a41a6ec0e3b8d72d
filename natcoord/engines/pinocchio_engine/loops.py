"""Loop closures: ``RigidConstraintModel(CONTACT_3D)`` between two joint frames at a point.

A loop-closing revolute or spherical joint, and the free end of every light rod, is a
CONTACT_3D constraint (it pins a point, ``LOCAL``). A revolute loop is accepted only when
the tree path between its bodies turns about axes parallel to it or not at all (then
CONTACT_3D loses nothing: the alignment holds already; always so in a planar case);
otherwise Unsupported, as CONTACT_6D would also lock its rotation. In a planar case the
contact's normal row is all zero, hence the proximal ``mu > 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import Unsupported
from ..planar import cross
from .model import Built


@dataclass(frozen=True)
class Loop:
    """A CONTACT_3D closure: ``name`` a case joint or a rod; M1, M2 the contact frames
    (SE3) in the frames of joints j1, j2."""

    name: str
    kind: str  # "joint" | "rod"
    j1: int
    j2: int
    M1: object
    M2: object


def _path(b: Built, j1: int, j2: int) -> list[int]:
    """Joint ids on the tree path between joints j1 and j2 (their common ancestors off)."""
    parents = b.model.parents

    def up(j):
        out = []
        while j:
            out.append(j)
            j = parents[j]
        return out

    u1, u2 = up(j1), up(j2)
    common = set(u1) & set(u2)
    return [j for j in u1 + u2 if j not in common]


def _check_alignment(b: Built, joint, j1: int, j2: int) -> None:
    """Unsupported unless the tree already keeps a loop revolute's axis (world, t = 0)."""
    first = joint.bodies[0]
    axis = b.lifted.frames[first].R @ joint.axis
    axis = axis / np.linalg.norm(axis)
    for jid in _path(b, j1, j2):
        turns = b.edges[jid].turns
        if turns is None:
            continue
        if isinstance(turns, str) or np.linalg.norm(cross(turns, axis)) >= 1e-12:
            raise Unsupported(f"loop-closing 3-D revolute {joint.name!r}: the tree does not "
                              "enforce its axis alignment, and CONTACT_6D would lock its "
                              "rotation")


def close(pin, b: Built, loop_joints, s: dict):
    """CONTACT_3D constraints for the loop joints and light rods: (cmodels, loops); notes
    are appended to ``b.notes``."""
    cmodels = pin.StdVec_RigidConstraintModel()
    loops: list[Loop] = []

    def contact(name, kind, j1, p1, j2, p2):
        M1, M2 = pin.SE3(np.eye(3), p1), pin.SE3(np.eye(3), p2)
        cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, b.model, j1, M1, j2, M2,
                                      pin.ReferenceFrame.LOCAL)
        if s["baumgarte_kp"] or s["baumgarte_kd"]:
            cm.setBaumgarteCorrectorParameters(pin.BaumgarteCorrectorParameters(
                float(s["baumgarte_kp"]), float(s["baumgarte_kd"])))
        cm.name = name
        cmodels.append(cm)
        loops.append(Loop(name, kind, j1, j2, M1, M2))

    for j in loop_joints:
        if j.type not in ("revolute", "spherical"):
            raise Unsupported(f"loop-closing {j.type} joint {j.name!r}: a point contact "
                              "cannot model it")
        (a, c), (pa, pc) = j.bodies, j.points
        (j1, X1), (j2, X2) = b.frame[a], b.frame[c]
        if j.type == "revolute":
            _check_alignment(b, j, j1, j2)
        contact(j.name, "joint", j1, X1.act(b.lifted.point(a, pa)), j2,
                X2.act(b.lifted.point(c, pc)))
    if loop_joints:
        b.notes.append(f"loop joint(s) {', '.join(j.name for j in loop_joints)} closed by "
                       "RigidConstraintModel CONTACT_3D (LOCAL)")
    for name, node, tip, body, point in b.rods:  # the light rod's free end
        (j1, _), (j2, X2) = b.frame[node], b.frame[body]
        contact(name, "rod", j1, tip - b.edges[j1].at, j2, X2.act(b.lifted.point(body, point)))
    return cmodels, loops
