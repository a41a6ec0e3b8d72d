"""natcoord's own solver as an engine: natural coordinates, index-1 with projection."""

from __future__ import annotations

import time

from .. import __version__
from ..dynamics import integrate
from ..kinematics import initial_state
from ..mechanism import Case
from ..model import build_model
from ..result import Motion
from .base import EngineRun, merged

NAME = "natcoord"
PACKAGE = "natcoord"
DEFAULTS = {"formulation": "index1", "method": "DOP853", "rtol": 1e-10, "atol": 1e-12}


def version() -> str:
    return __version__


def run(case: Case, init, settings: dict) -> EngineRun:
    s = merged(DEFAULTS, settings)
    t0 = time.perf_counter()
    model = build_model(case)
    state = initial_state(model)
    build = time.perf_counter() - t0
    sol = integrate(model, state, case.times, method=s["method"], rtol=s["rtol"],
                    atol=s["atol"])
    return EngineRun(motion_of(model, sol), build, sol.wall_time_s, sol.counters["steps"], s,
                     sol.counters)


def motion_of(model, sol) -> Motion:
    """Neutral motion from a natcoord solution."""
    origin, angle, velocity, omega = {}, {}, {}, {}
    for name in model.bodies:
        origin[name], angle[name], velocity[name], omega[name] = model.body_pose(
            name, sol.q, sol.qd)
    forces = {name: j.force(sol.lam, sol.q) for name, j in model.joints.items()}
    return Motion(sol.t, origin, angle, velocity, omega, forces)
