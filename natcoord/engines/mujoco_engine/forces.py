"""Forces in and out of MuJoCo, world axes, 3-D (a lifted case):

* in: the case's constant loads as ``xfrc_applied``;
* out: rod and spring tensions, and every joint's reaction (the force on its second body).
  Tree joints: ``cfrc_int[child, 3:]`` after ``mj_rnePostConstraint`` (force of the parent
  on the child's subtree) times :func:`natcoord.engines.tree.tree_orientation`, less the rod
  and spring forces on that subtree (``cfrc_ext`` holds ``xfrc_applied`` and connect forces
  but not tendon forces, so ``cfrc_int`` carries them). Loop joints: ``efc_force`` of a
  connect equality's rows is the force on ``site1``'s body (the joint's first), so the
  second body gets minus it.
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import GROUND, Case
from ...errors import Unsupported
from ..tree import tree_orientation


def applied_loads(mujoco, m, case: Case) -> np.ndarray:
    """``xfrc_applied`` (nbody, 6) of the lifted case's constant loads.

    Exact: MuJoCo applies it at the centre of mass and a torque is a free vector. A force at
    another point would need a moment that turns with the body inside each RK4 stage.
    """
    x = np.zeros((m.nbody, 6))
    for f in case.forces:
        if f.frame == "body":
            raise Unsupported(f"{f.type} on {f.body} in its body's frame: "
                              "xfrc_applied is in world axes and held over a step")
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f.body)
        b = case.body(f.body)
        if f.type == "torque":
            x[j, 3:] += f.value
        elif f.type == "force":
            if np.max(np.abs(b.points[f.point] - b.com)) > 1e-12:
                raise Unsupported(f"force on {f.body} at point {f.point}, not its centre of "
                                  "mass: MuJoCo's xfrc_applied acts at the centre of mass and "
                                  "is held over a step, so the moment of a force elsewhere "
                                  "would lag the body's rotation")
            x[j, :3] += f.value
        else:
            raise Unsupported(f"force type {f.type!r}")
    return x


class TendonForces:
    """Reads rod and spring tensions from an MjData, and the forces they put on bodies."""

    def __init__(self, mujoco, m, case: Case):
        self.mujoco = mujoco
        self.rods, self.springs = list(case.rods), list(case.springs)
        obj = mujoco.mjtObj
        self.rod_eq = {r.name: mujoco.mj_name2id(m, obj.mjOBJ_EQUALITY, f"rod_{r.name}")
                       for r in self.rods}
        self.spring_t = {r.name: mujoco.mj_name2id(m, obj.mjOBJ_TENDON, f"spring_{r.name}")
                         for r in self.springs}
        self.ends = {}  # name -> ((body, site id), (body, site id))
        for kind, items in (("rod", self.rods), ("spring", self.springs)):
            for r in items:
                self.ends[r.name] = tuple(
                    (b, mujoco.mj_name2id(m, obj.mjOBJ_SITE, f"{kind}_{r.name}_{k}"))
                    for k, (b, _) in enumerate(r.ends))

    def tensions(self, d) -> tuple[dict[str, float], float]:
        """Tension of every rod and spring (N) and the largest rod length violation (m).

        A rod's tension is ``-efc_force`` of its equality row (``efc_force`` acts along
        d(length)/dq: positive pushes the ends apart); a spring's ``k (l - l0) + c dl/dt``.
        """
        out: dict[str, float] = {}
        drift = 0.0
        if self.rods:
            rows = np.flatnonzero(d.efc_type == self.mujoco.mjtConstraint.mjCNSTR_EQUALITY)
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


def subtree_bodies(parent: dict) -> dict[str, set[str]]:
    """child -> every body of its subtree (itself included), from child -> (parent, joint)."""
    out = {c: {c} for c in parent}
    for c in parent:
        p = parent[c][0]
        while p in parent:
            out[p].add(c)
            p = parent[p][0]
    return out


class Reactions:
    """Every joint's force on its second body and every rod's and spring's tension, read
    from an MjData after :func:`.stepping.forward`."""

    def __init__(self, mujoco, m, case: Case, built):
        self.mujoco = mujoco
        self.ten = TendonForces(mujoco, m, case)
        self.bid = {b.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b.name)
                    for b in case.bodies}
        self.loops = built.loops
        self.eqid = {j.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, j.name)
                     for j in built.loops}
        # a loop revolute held by a second connect along its axis (mjcf.loop_axis_offset)
        self.axis_eqid = {j.name: k for j in built.loops
                          if (k := mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY,
                                                     j.name + "_axis")) >= 0}
        self.tree = {cj.name: (child, tree_orientation(cj, par))
                     for child, (par, cj) in built.parent.items()}
        self.subtree = subtree_bodies(built.parent)

    def read(self, d, forces: dict, rod_force: dict, i: int) -> float:
        """Sample ``i`` of ``forces`` (joint -> (T, 3) N) and ``rod_force`` (-> (T,) N);
        returns the largest constraint violation of the loops and rods, m."""
        tension, drift = self.ten.tensions(d)
        for r, v in tension.items():
            rod_force[r][i] = v
        on_body = self.ten.body_forces(d, tension)  # cfrc_int carries them: take them out
        for name, (child, sign) in self.tree.items():
            f = d.cfrc_int[self.bid[child], 3:6].copy()
            for b in self.subtree[child]:
                f -= on_body.get(b, np.zeros(3))
            forces[name][i] = sign * f
        return max(drift, self._connects(d, forces, i))

    def _connects(self, d, forces: dict, i: int) -> float:
        """Each loop's connect force on its second body; the largest violation, m."""
        drift = 0.0
        if self.loops:
            eq = np.flatnonzero(d.efc_type == self.mujoco.mjtConstraint.mjCNSTR_EQUALITY)
            for j in self.loops:
                rows = eq[d.efc_id[eq] == self.eqid[j.name]]
                forces[j.name][i] = -d.efc_force[rows[:3]]
                drift = max(drift, float(np.max(np.abs(d.efc_pos[rows]))))
                if j.name in self.axis_eqid:  # the joint force is the sum of both connects
                    rows = eq[d.efc_id[eq] == self.axis_eqid[j.name]]
                    forces[j.name][i] -= d.efc_force[rows[:3]]
                    drift = max(drift, float(np.max(np.abs(d.efc_pos[rows]))))
        return drift
