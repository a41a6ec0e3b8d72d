"""What a PyBullet multibody is doing, world axes, 3-D (a lifted case): its body frames and
rates (:class:`State`), the case's loads applied before every step (:class:`Loads`;
PyBullet clears external forces after each ``stepSimulation``) and the samples."""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Case
from ...errors import Unsupported
from ..planar import cross, node_point
from .multibody import Built


class State:
    """The frames of every link at the current state: ``read()`` refreshes them."""

    def __init__(self, pb, cid: int, built: Built, case: Case):
        self.pb, self.cid, self.built, self.case = pb, cid, built, case
        self.names = list(built.links)
        self.idx = [built.links[n].index for n in self.names]
        self.R: dict[str, np.ndarray] = {}
        self.origin: dict[str, np.ndarray] = {}
        self.v: dict[str, np.ndarray] = {}
        self.w: dict[str, np.ndarray] = {}
        self._points: dict[tuple[str, str], np.ndarray] = {}

    def read(self, names: list[str] | None = None) -> None:
        """Refresh every link's frame and rates, or those of ``names`` only."""
        pb = self.pb
        names = self.names if names is None else names
        idx = self.idx if names is self.names else [self.built.links[n].index for n in names]
        states = pb.getLinkStates(self.built.uid, idx, computeLinkVelocity=1,
                                  computeForwardKinematics=1, physicsClientId=self.cid)
        for n, st in zip(names, states, strict=True):
            link = self.built.links[n]
            R = np.array(pb.getMatrixFromQuaternion(st[5])).reshape(3, 3)
            o = np.asarray(st[4]) - R @ link.pc
            w = np.asarray(st[7], float)
            self.R[n], self.origin[n], self.w[n] = R, o, w
            self.v[n] = np.asarray(st[6], float) + cross(w, o - np.asarray(st[0]))

    def local(self, node: str, name: str) -> np.ndarray:
        """A named point (3,) m in its body's frame (a ground point in world axes)."""
        key = (node, name)
        if key not in self._points:
            self._points[key] = np.asarray(node_point(self.case, node, name), float)
        return self._points[key]

    def point(self, node: str, name: str) -> np.ndarray:
        """World position (3,) m of a named point at the last read."""
        p = self.local(node, name)
        return p if node == GROUND else self.origin[node] + self.R[node] @ p

    def point_velocity(self, node: str, name: str) -> np.ndarray:
        """World velocity (3,) m/s of a named point at the last read."""
        if node == GROUND:
            return np.zeros(3)
        return self.v[node] + cross(self.w[node], self.R[node] @ self.local(node, name))


class Loads:
    """The case's constant torques, forces at body points and spring-dampers, applied
    before a step from the state at its start (PyBullet's step is semi-implicit Euler:
    the forces are held over the step like every other force)."""

    def __init__(self, pb, cid: int, built: Built, case: Case, state: State):
        self.pb, self.cid, self.uid, self.case, self.state = pb, cid, built.uid, case, state
        self.link = {n: ln.index for n, ln in built.links.items()}
        if any(f.frame == "body" for f in case.forces):
            raise Unsupported("a load in its body's frame: the adapter applies loads in "
                              "world axes")
        self.torques = [(self.link[f.body], np.asarray(f.value, float).tolist())
                        for f in case.forces if f.type == "torque"]
        self.point_forces = [f for f in case.forces if f.type == "force"]
        self.springs = list(case.springs)
        ends = [b for r in self.springs for b, _ in r.ends] + [f.body for f in
                                                                self.point_forces]
        self.bodies = [n for n in built.links if n in ends]  # the links a load reads

    def tension(self, r) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """(tension N, unit vector from end 0 to end 1, their world points)."""
        st = self.state
        (b0, p0), (b1, p1) = r.ends
        x0, x1 = st.point(b0, p0), st.point(b1, p1)
        d = x1 - x0
        length = float(np.linalg.norm(d))
        u = d / length
        rate = float(u @ (st.point_velocity(b1, p1) - st.point_velocity(b0, p0)))
        return r.stiffness * (length - r.length) + r.damping * rate, u, x0, x1

    def apply(self) -> None:
        pb, cid, uid = self.pb, self.cid, self.uid
        if self.bodies:
            self.state.read(self.bodies)
        for link, tau in self.torques:
            pb.applyExternalTorque(uid, link, tau, pb.WORLD_FRAME, physicsClientId=cid)
        for f in self.point_forces:
            pb.applyExternalForce(uid, self.link[f.body], np.asarray(f.value, float).tolist(),
                                  self.state.point(f.body, f.point).tolist(), pb.WORLD_FRAME,
                                  physicsClientId=cid)
        for r in self.springs:
            t, u, x0, x1 = self.tension(r)
            for (b, _), x, sign in ((r.ends[0], x0, 1.0), (r.ends[1], x1, -1.0)):
                if b != GROUND:
                    pb.applyExternalForce(uid, self.link[b], (sign * t * u).tolist(),
                                          x.tolist(), pb.WORLD_FRAME, physicsClientId=cid)

