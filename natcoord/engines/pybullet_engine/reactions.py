"""Joint reactions from a PyBullet step, world axes: the force each joint applies to its
second body.

* Loop joints: ``getConstraintState`` of the point-to-point constraint, the applied impulse
  of each of its three rows over the step, is the force on the constraint's child (the
  joint's second body) in world axes (checked against the reference on four_bar and
  slider_crank).
* Tree joints: Newton's law on the subtree the joint carries, with the accelerations
  PyBullet's step produced: ``sum(m a - m g - F_applied - F_springs - F_loops)`` over the
  subtree's bodies, ``a`` the centre-of-mass velocity change over the step divided by dt.
  PyBullet's joint force-torque sensor (``enableJointForceTorqueSensor``) is right on a tree
  (hanging rod, pendulum) but leaves out the loop constraints: on four_bar at t = 0.5 s
  (dt 1e-4) it gave O = (-121.5, -5.5) N against the reference's (-80.4, -2.5) N, while the
  subtree balance gives the reference to the step's first order.

Both are read over the first step after a sample (semi-implicit Euler: that step's
velocity change is the acceleration at the sample's state).
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Case
from ..planar import cross
from ..tree import tree_orientation
from .multibody import Built
from .stepping import Loads, State


class Reactions:
    """Reads every joint's force on its second body over one step."""

    def __init__(self, pb, cid: int, built: Built, case: Case, state: State, loads: Loads,
                 dt: float):
        self.pb, self.cid, self.built, self.case = pb, cid, built, case
        self.state, self.loads, self.dt = state, loads, dt
        self.mass = {b.name: float(b.mass) for b in case.bodies}
        self.g = np.asarray(case.gravity, float)
        self.loop_joints = [case.joint(n) for n in built.loops]
        children: dict[str, list[str]] = {}
        for _, par, child in built.tree:
            children.setdefault(par, []).append(child)

        def subtree(n):
            out = {n}
            for c in children.get(n, []):
                out |= subtree(c)
            return out

        self.tree = [(j.name, subtree(child), tree_orientation(j, par))
                     for j, par, child in built.tree]
        self.com_v0: dict[str, np.ndarray] = {}

    def com_velocities(self) -> dict[str, np.ndarray]:
        """Every body's centre-of-mass velocity (3,) m/s, world, at the current state."""
        st = self.state
        st.read()
        return {n: st.v[n] + cross(st.w[n], st.R[n] @ self.case.body(n).com)
                for n in st.names}

    def before(self) -> None:
        """Remember the velocities at the sample, before the step."""
        self.com_v0 = self.com_velocities()
        self.applied = self._applied()

    def _applied(self) -> dict[str, np.ndarray]:
        """Applied forces (3,) N, world, on each body at the current state: point forces
        and springs (torques do not enter a force balance)."""
        out: dict[str, np.ndarray] = {}

        def add(b, f):
            if b != GROUND:
                out[b] = out.get(b, np.zeros(3)) + f

        for f in self.loads.point_forces:
            add(f.body, np.asarray(f.value, float))
        for r in self.loads.springs:
            t, u, _, _ = self.loads.tension(r)
            add(r.ends[0][0], t * u)
            add(r.ends[1][0], -t * u)
        return out

    def after(self, forces: dict, i: int) -> None:
        """Sample ``i`` of ``forces`` (joint -> (T, 3) N) from the step just taken."""
        pb, cid = self.pb, self.cid
        on_body: dict[str, np.ndarray] = {n: f.copy() for n, f in self.applied.items()}
        for j in self.loop_joints:
            f = sum(np.asarray(pb.getConstraintState(c, physicsClientId=cid)[:3], float)
                    for c in self.built.loops[j.name])
            forces[j.name][i] = f
            a, b = j.bodies
            for body, sign in ((b, 1.0), (a, -1.0)):
                if body != GROUND:
                    on_body[body] = on_body.get(body, np.zeros(3)) + sign * f
        v1 = self.com_velocities()
        inertial = {n: self.mass[n] * ((v1[n] - self.com_v0[n]) / self.dt - self.g)
                    for n in v1}
        for name, bodies, sign in self.tree:
            f = sum(inertial[n] - on_body.get(n, 0.0) for n in bodies)
            forces[name][i] = sign * f
