"""Kinematic trees for the engines that need one: which joints form the tree rooted at the
ground and which close loops, the same rule in every adapter so they cut the same loops."""

from __future__ import annotations

from dataclasses import replace

from ..case.mechanism import GROUND, Case, Joint
from ..errors import Unsupported


def spanning_tree(case: Case) -> tuple[list[Joint], list[Joint]]:
    """Split the joints into a tree rooted at the ground and the loop-closing rest.

    Breadth-first from ``ground`` in file order, so every adapter cuts the same loops.
    Tree joints are returned parent before child, unchanged: a joint may name its child
    first, and :func:`tree_orientation` gives the sign that turns "parent on child" into the
    case convention "joint on its second body".
    """
    reached = {GROUND}
    tree: list[Joint] = []
    remaining = list(case.joints)
    progress = True
    while progress:
        progress = False
        for j in list(remaining):
            a, b = j.bodies
            if (a in reached) != (b in reached):
                tree.append(j)
                reached.add(b if a in reached else a)
                remaining.remove(j)
                progress = True
                break
    return tree, remaining


def point_loop_tree(case: Case, why: str) -> tuple[list[Joint], list[Joint], list[str]]:
    """Spanning tree for engines that close loops with point constraints (MuJoCo ``connect``,
    Pinocchio ``CONTACT_3D``, DART ball joints), which cannot slide.

    When :func:`spanning_tree` leaves a prismatic joint to close a loop, the tree is
    recomputed with prismatic joints first so that the loop is cut at a revolute joint.
    Returns ``(tree, loops, recut)``, ``recut`` naming the prismatic joints the plain tree
    would have left as loops (empty when it was kept). Raises Unsupported (``why`` says
    what the engine lacks) when a prismatic joint must still close a loop.
    """
    tree, loops = spanning_tree(case)
    recut = [j.name for j in loops if j.type == "prismatic"]
    if not recut:
        return tree, loops, recut
    first = tuple(sorted(case.joints, key=lambda j: j.type != "prismatic"))
    tree, loops = spanning_tree(replace(case, joints=first))
    bad = [j.name for j in loops if j.type != "revolute"]
    if bad:
        raise Unsupported(f"prismatic joint(s) {', '.join(bad)} must close a loop: {why}")
    return tree, loops, recut


def tree_parents(tree: list[Joint]) -> list[tuple[Joint, str, str]]:
    """``(joint, parent, child)`` in tree order; the parent is the end the tree reached first
    (a joint may name its child first)."""
    reached = {GROUND}
    out = []
    for j in tree:
        a, b = j.bodies
        parent, child = (a, b) if a in reached else (b, a)
        if parent not in reached or child in reached:
            raise ValueError(f"joint {j.name!r} does not extend the tree")
        reached.add(child)
        out.append((j, parent, child))
    return out


def tree_orientation(joint: Joint, parent: str) -> int:
    """+1 when ``joint.bodies[0]`` is the tree parent, -1 when the joint points child-first.

    Multiply a force computed as "parent on child" by this sign to get the case convention
    "joint on its second body".
    """
    return 1 if joint.bodies[0] == parent else -1
