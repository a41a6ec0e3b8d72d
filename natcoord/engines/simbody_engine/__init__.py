"""Simbody (through OpenSim's Python bindings) as an engine.

Placeholder docstring: rewritten below once measured.
"""

from __future__ import annotations

import time

from ..base import EngineRun, merged

NAME = "simbody"
PACKAGE = "opensim"
DEFAULTS = {
    "integrator": "rk_merson",  # Simbody integrator (see simulate.INTEGRATORS)
    "accuracy": 1e-10,  # the integrator's relative accuracy (error-controlled methods)
    "constraint_tolerance": 1e-12,  # projection tolerance of the constraint manifold
    "dt": None,  # s: a fixed step instead (fixed-step integrators only)
    "step_limit": 100_000,  # internal steps per output interval before Simbody gives up (a
    # stall, e.g. five_bar at accuracy 1e-10 near its -180 deg singular position, fails fast)
    "min_step": 1e-12,  # s: a step Simbody would shrink below this is an error, not a stall
    "particle_inertia": 1e-6,  # kg m^2 per kg: rotational inertia given to a particle
    "velocity_check": 1e-9,  # m/s, rad/s: start must match natcoord's initial rates
}


def version() -> str:
    import opensim

    return opensim.__version__


def _quiet(osim) -> None:
    """No opensim.log in the working directory, nothing on stdout."""
    osim.Logger.removeFileSink()
    osim.Logger.setLevel(osim.Logger.Level_Off)


def run(case, init, settings: dict) -> EngineRun:
    """Build, integrate and sample ``case`` from ``init`` (see the module docstring)."""
    import opensim as osim

    from ..planar import drop, lift_case, lift_init
    from . import model, simulate

    _quiet(osim)
    s = merged(DEFAULTS, settings)
    t0 = time.perf_counter()
    case3 = lift_case(case)
    frames = lift_init(case3, init)
    b = model.build(osim, case3, frames, case.dimension == 2, s)
    state = simulate.initial_state(osim, b, float(s["velocity_check"]))
    build_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    times = case.times
    states = simulate.integrate(osim, b, state, times, s)
    (origin, rotation, velocity, omega, accel, alpha, forces, rod_force, effort, counters,
     drift) = simulate.sample(osim, b, states, len(times))
    wall = time.perf_counter() - t0
    notes = list(b.notes)
    what = f"fixed step {s['dt']:g} s" if s.get("dt") else f"accuracy {s['accuracy']:g}"
    notes.append(f"Simbody {s['integrator']}, {what}, constraint tolerance "
                 f"{s['constraint_tolerance']:g}, via OpenSim Manager")
    counters |= {"qerr_max": float(drift[0]), "uerr_max": float(drift[1])}
    motion = drop(case, times, origin, rotation, velocity, omega, forces,
                  acceleration=accel, alpha=alpha, driver_effort=effort, rod_force=rod_force)
    return EngineRun(motion, build_time, wall, counters["steps"], s, counters, notes)


__all__ = ["DEFAULTS", "NAME", "PACKAGE", "run", "version"]
