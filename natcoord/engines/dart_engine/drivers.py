"""Drivers (prescribed motions) as DART joints with a VELOCITY actuator: the joint moves at
the commanded rate through the step, DART's hybrid dynamics supplies the force that takes
(constraint impulses included), and the joint's transmitted wrench carries it.

A driver is modelled only when the coordinate it prescribes is a tree-joint coordinate: an
angle driver on a body hanging from the ground on a revolute tree joint about z, a
coordinate driver on a body sliding on a prismatic tree joint from the ground along the
driven world axis. Anything else is :class:`~natcoord.errors.Unsupported`.
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Case, Driver
from ...errors import Unsupported
from ..planar import Frame, Z, node_point
from .skeleton import Skeleton, world_axis

AXES = {"x": 0, "y": 1, "z": 2}


class DrivenJoint:
    """One driver on its tree joint: commands the joint for the next step and reads the
    driver's effort (N m about z for an angle, N along the axis for a coordinate)."""

    def __init__(self, d: Driver, case: Case, sk: Skeleton, frames: dict[str, Frame]):
        j = _tree_joint_of(d, case, sk)
        st = frames[d.body]
        want = "revolute" if d.type == "angle" else "prismatic"
        self.dir = Z if d.type == "angle" else np.eye(3)[AXES[d.axis]]
        a = world_axis(j, frames)
        if j.type != want or abs(abs(a @ self.dir) - 1.0) > 1e-9:
            raise Unsupported(
                f"driver {d.name!r}: DART can prescribe a tree-joint coordinate only; "
                f"{d.body!r} is on {j.type} joint {j.name!r}, not on a {want} joint from "
                f"the ground along {'z' if d.type == 'angle' else d.axis}")
        self.s = float(np.sign(a @ self.dir))  # joint coordinate per unit of the driven value
        if d.type == "angle":
            x0 = float(np.arctan2(st.R[1, 0], st.R[0, 0]))
            self.p = node_point(case, d.body, j.points[j.bodies.index(d.body)])  # joint point
        else:
            x0 = float(st.point(node_point(case, d.body, d.point))[AXES[d.axis]])
        if abs(np.remainder(x0 - d.v0 + np.pi, 2 * np.pi) - np.pi) > 1e-7:
            raise RuntimeError(f"driver {d.name!r}: the assembled state has {x0:.9g}, the "
                               f"driver {d.v0:.9g} at t = 0")
        self.d, self.x0, self.joint = d, x0, sk.joints[j.name]
        self.node = sk.nodes[d.body]
        self.joint.setActuatorType(_velocity_actuator())

    def value(self, t: float) -> float:
        d = self.d
        return d.v0 + d.rate * t + 0.5 * d.accel * t * t

    def command(self, t: float, h: float) -> None:
        """Joint rate for the step t -> t + h (s) that ends exactly on the prescribed value
        (semi-implicit Euler moves the coordinate by h times the new rate)."""
        target = self.s * (self.value(t + h) - self.x0)
        self.joint.setCommand(0, (target - self.joint.getPosition(0)) / h)

    def effort(self, W) -> float:
        """What the driver applies to its body in the step just taken: the moment about z at
        the joint point (a revolute joint transmits none about its axis but the driver's),
        or the force along the driven axis."""
        w = np.asarray(self.joint.getWrenchToParentBodyNode(W))  # moment, force; world
        if self.d.type == "coordinate":
            return float(self.dir @ w[3:])
        M = self.node.getWorldTransform().matrix()
        x = M[:3, :3] @ self.p + M[:3, 3]
        return float(self.dir @ (w[:3] - np.cross(x, w[3:])))


def _tree_joint_of(d: Driver, case: Case, sk: Skeleton):
    """The tree joint that carries the driven body from the ground."""
    for name in sk.joints:
        j = case.joint(name)
        if d.body in j.bodies and GROUND in j.bodies:
            return j
    raise Unsupported(f"driver {d.name!r}: body {d.body!r} is not joined to the ground by a "
                      "tree joint, so its motion is not a DART joint coordinate")


def _velocity_actuator():
    import dartpy as dart

    return dart.dynamics.ActuatorType.VELOCITY


def make_drivers(case: Case, sk: Skeleton, frames, notes: list[str]) -> list[DrivenJoint]:
    out = [DrivenJoint(d, case, sk, frames) for d in case.drivers]
    if out:
        notes.append("driver(s) " + ", ".join(d.d.name for d in out) + ": DART VELOCITY "
                     "actuator on the tree joint, commanded each step to end on the prescribed "
                     "value; effort from the joint's transmitted wrench")
    return out
