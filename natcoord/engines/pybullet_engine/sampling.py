"""Step a PyBullet multibody through a case's sample times and fill the samples: body
frames and rates at each sample, reactions over the step after it, the loops' gap."""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import GROUND, Case
from ..planar import Frame, Samples, check_start
from . import START_TOLERANCE
from .multibody import Built
from .reactions import Reactions
from .stepping import Loads, State


class Sampler:
    """Fills :class:`Samples` one sample at a time; ``drift`` is the widest loop gap (m)
    seen so far."""

    def __init__(self, pb, cid: int, built: Built, case: Case, dt: float):
        self.case, self.built = case, built
        self.state = State(pb, cid, built, case)
        self.loads = Loads(pb, cid, built, case, self.state)
        self.reactions = Reactions(pb, cid, built, case, self.state, self.loads, dt)
        self.out = Samples.empty(case, len(case.times))
        self.drift = 0.0

    def sample(self, i: int) -> None:
        """Frames, rates, spring tensions and loop gaps at the current state; remembers the
        velocities for the reactions of the next step."""
        st, out = self.state, self.out
        self.reactions.before()  # reads the state
        for b in self.case.bodies:
            n = b.name
            if b.kind == "particle":  # its frame keeps its rotation; the origin follows it
                p = next(iter(b.points.values()))
                out.origin[n][i] = st.point(n, next(iter(b.points))) - p
                out.rotation[n][i] = np.eye(3)
                out.velocity[n][i] = st.point_velocity(n, next(iter(b.points)))
            else:
                out.origin[n][i] = st.origin[n]
                out.rotation[n][i] = st.R[n]
                out.velocity[n][i] = st.v[n]
                out.omega[n][i] = st.w[n]
        for r in self.case.springs:
            out.rod_force[r.name][i] = self.loads.tension(r)[0]
        for (a, pa), (b, pb) in self.built.gaps:
            xa = pa if a == GROUND else st.origin[a] + st.R[a] @ pa
            xb = pb if b == GROUND else st.origin[b] + st.R[b] @ pb
            self.drift = max(self.drift, float(np.max(np.abs(xa - xb))))


def simulate(pb, cid: int, built: Built, case: Case, frames: dict[str, Frame], s: dict,
             k: int):
    """(samples, wall time of the steps s, steps, counters): ``k`` steps between samples;
    the reactions of each sample are read over the step after it (one more step after the
    last sample, not counted)."""
    sampler = Sampler(pb, cid, built, case, float(s["dt"]))
    loads, reactions, out = sampler.loads, sampler.reactions, sampler.out
    any_loads = bool(loads.torques or loads.point_forces or loads.springs)
    T = len(case.times)
    wall, n_steps = 0.0, 0
    start_gap = None
    for i in range(T):
        sampler.sample(i)
        if i == 0:
            check_start(case, frames, out, "PyBullet", START_TOLERANCE)
            start_gap = sampler.drift
        if sampler.drift > float(s["max_loop_drift"]):
            raise RuntimeError(f"a loop opened by {sampler.drift:.3g} m by t = "
                               f"{case.times[i]:.6g} s (max_loop_drift {s['max_loop_drift']} "
                               "m): the point-to-point constraints do not hold at these "
                               "settings")
        if not all(np.all(np.isfinite(x[i])) for x in out.origin.values()):
            raise RuntimeError(f"PyBullet's state is not finite at t = {case.times[i]:.6g} s")
        for step in range(k if i < T - 1 else 1):
            w0 = time.perf_counter()
            if any_loads:
                loads.apply()
            pb.stepSimulation(physicsClientId=cid)
            if i < T - 1:
                wall += time.perf_counter() - w0
                n_steps += 1
            if step == 0:
                reactions.after(out.forces, i)
    counters = {"loop_drift_m": sampler.drift, "start_loop_gap_m": start_gap}
    return out, wall, n_steps, counters
