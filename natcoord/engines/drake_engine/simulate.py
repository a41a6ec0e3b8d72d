"""Step a Drake plant to the case's sample times and read bodies, joint reactions and
spring tensions in 3-D, world axes (dropped to the case's dimension by
:func:`natcoord.engines.planar.drop`).

Reactions: a tree joint's ``get_reaction_forces_output_port`` entry is F_CJc_Jc, the force of
the parent on the child at the child frame M's origin, in M's axes: rotated to world and
signed with :func:`natcoord.engines.tree.tree_orientation` ("joint on its second body").
Drake reports no constraint forces, so a loop joint's force comes from Newton-Euler on its
second body: m a_cm - m g minus every other force on that body (its tree joints, springs,
applied loads). A body closed by two loop joints cannot split them: NaN there.
"""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import Case
from ..planar import node_point
from .model import Built


class Readout:
    """Samples of a lifted case from a plant context, one sample at a time."""

    def __init__(self, built: Built, case: Case, T: int):
        self.b, self.case = built, case
        names = [x.name for x in case.bodies]
        self.origin = {n: np.zeros((T, 3)) for n in names}
        self.rotation = {n: np.zeros((T, 3, 3)) for n in names}
        self.velocity = {n: np.zeros((T, 3)) for n in names}
        self.omega = {n: np.zeros((T, 3)) for n in names}
        self.forces = {j.name: np.full((T, 3), np.nan) for j in case.joints}
        self.rod_force = {sp.name: np.zeros(T) for sp in case.springs}
        self.gap = 0.0  # m: the widest loop opening seen
        # per body: the loop joints on it (Newton-Euler needs exactly one)
        self.loop_on = {}
        for j in built.loops:
            for n in j.bodies:
                self.loop_on.setdefault(n, []).append(j)

    def _point(self, ctx, node: str, name: str):
        """World position and velocity (3,) of the named point of ``node`` (a body or the
        ground)."""
        plant, body = self.b.plant, self.b.bodies[node]
        p = node_point(self.case, node, name)
        X = plant.EvalBodyPoseInWorld(ctx, body)
        V = plant.EvalBodySpatialVelocityInWorld(ctx, body)
        r = X.rotation().matrix() @ np.asarray(p, float)
        return X.translation() + r, V.translational() + np.cross(V.rotational(), r)

    def sample(self, ctx, i: int) -> None:
        plant, case = self.b.plant, self.case
        for x in case.bodies:
            body = self.b.bodies[x.name]
            X = plant.EvalBodyPoseInWorld(ctx, body)
            V = plant.EvalBodySpatialVelocityInWorld(ctx, body)
            R, o = X.rotation().matrix(), X.translation()
            w, v = V.rotational(), V.translational()
            if x.name in self.b.particle_points:  # natcoord's particle frame: no rotation
                p = self.b.particle_points[x.name]
                rp = R @ p
                o, v, R, w = o + rp - p, v + np.cross(w, rp), np.eye(3), np.zeros(3)
            self.origin[x.name][i], self.rotation[x.name][i] = o, R
            self.velocity[x.name][i], self.omega[x.name][i] = v, w
        body_force = {n: np.zeros(3) for n in self.b.bodies}  # on each body, but the loops'
        for sp in case.springs:
            (a, pa), (c, pc) = sp.ends
            (ra, va), (rc, vc) = self._point(ctx, a, pa), self._point(ctx, c, pc)
            d = rc - ra
            u = d / np.linalg.norm(d)
            tension = sp.stiffness * (np.linalg.norm(d) - sp.length) + sp.damping * (vc - va) @ u
            self.rod_force[sp.name][i] = tension
            body_force[a] += tension * u
            body_force[c] -= tension * u
        for f in case.forces:
            if f.type == "force":
                body_force[f.body] += f.value
        if self.b.tree:
            reactions = plant.get_reaction_forces_output_port().Eval(ctx)
            for j, parent, child, dj, sign in self.b.tree:
                M = dj.frame_on_child()
                f = M.CalcPoseInWorld(ctx).rotation().matrix() @ \
                    reactions[int(dj.index())].translational()
                body_force[child] += f
                body_force[parent] -= f
                if j is not None:
                    self.forces[j.name][i] = sign * f
        for j in self.b.loops:
            self._loop(ctx, j, body_force, i)

    def _loop(self, ctx, j, body_force: dict, i: int) -> None:
        """Newton-Euler on the loop joint's second body (or its first, negated)."""
        plant = self.b.plant
        (a, c), (pa, pc) = j.bodies, j.points
        ra, _ = self._point(ctx, a, pa)
        rc, _ = self._point(ctx, c, pc)
        self.gap = max(self.gap, float(np.linalg.norm(rc - ra)))
        for node, sign in ((c, 1.0), (a, -1.0)):
            if len(self.loop_on[node]) != 1:
                continue
            x = self.case.body(node)
            body = self.b.bodies[node]
            X = plant.EvalBodyPoseInWorld(ctx, body)
            V = plant.EvalBodySpatialVelocityInWorld(ctx, body)
            A = plant.EvalBodySpatialAccelerationInWorld(ctx, body)
            r = X.rotation().matrix() @ np.asarray(x.com, float)
            w = V.rotational()
            a_cm = A.translational() + np.cross(A.rotational(), r) + np.cross(w, np.cross(w, r))
            f = x.mass * (a_cm - self.case.gravity) - body_force[node]
            self.forces[j.name][i] = sign * f
            return


def step(simulator, ctx, times: np.ndarray, readout: Readout) -> float:
    """Advance to every sample time, reading each; the wall time of the stepping (s)."""
    wall = 0.0
    readout.sample(ctx, 0)
    for i in range(1, len(times)):
        t0 = time.perf_counter()
        simulator.AdvanceTo(float(times[i]))
        wall += time.perf_counter() - t0
        state = ctx.get_continuous_state_vector().CopyToVector() if ctx.num_continuous_states() \
            else ctx.get_discrete_state_vector().CopyToVector()
        if not np.all(np.isfinite(state)):
            raise RuntimeError(f"Drake's state is not finite at t = {times[i]:.6g} s")
        readout.sample(ctx, i)
    return wall
