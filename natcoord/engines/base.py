"""What every engine adapter shares: the initial state it starts from and what it returns.

An adapter is a module in this package with

    NAME: str                      engine name used in cases and results
    PACKAGE: str                   the PyPI package that provides it
    def version() -> str           raises ImportError when the package is missing
    def run(case, init, settings) -> EngineRun
                                   raises natcoord.errors.Unsupported for what it cannot model

``init`` is the state natcoord assembled (the same for every engine), ``settings`` the
case's ``[engines.<name>].settings`` over the adapter's own defaults. All conventions of an
engine (frames, signs, units, quaternion order) stay inside its adapter; what it returns is
a :class:`~natcoord.result.Motion` in natcoord's neutral convention, sampled at
``case.times``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mechanism import Case
from ..result import Motion


@dataclass(frozen=True)
class BodyState:
    """Assembled state of one body frame: origin (d,) m, angle rad (2-D), velocity (d,) m/s
    of the frame origin, omega rad/s (2-D) or (3,) world axes (3-D), rotation (3, 3)
    body-to-world (3-D). In a reference-frame case every frame is the world frame at t = 0
    (origin 0, angle 0, identity rotation)."""

    origin: np.ndarray
    angle: float
    velocity: np.ndarray
    omega: float | np.ndarray
    rotation: np.ndarray | None = None


@dataclass
class EngineRun:
    """What an adapter returns: the motion plus costs and what it substituted."""

    motion: Motion
    build_time_s: float
    wall_time_s: float
    n_steps: int
    settings: dict = field(default_factory=dict)
    counters: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    methods: dict[str, Motion] = field(default_factory=dict)  # natcoord: one per reaction
    # method of the case (the primary motion is the first)


def initial_body_states(case: Case) -> dict[str, BodyState]:
    """Assemble the case with natcoord's kinematics and return every body's frame state."""
    from ..kinematics import initial_state
    from ..model import build_model

    if case.reference_frame:
        from .. import casemodel

        cm = casemodel.build(case, case.engine("natcoord").settings.get("coordinates",
                                                                          "joints"))
        s = casemodel.initial_state(cm)
        o, a, R, v, w = casemodel.frames(cm, s.q[None], s.qd[None])
        return {b: BodyState(o[b][0], float(a[b][0]) if b in a else 0.0, v[b][0],
                             float(w[b][0]) if case.dimension == 2 else w[b][0],
                             R[b][0] if b in R else None) for b in o}

    model = build_model(case)
    s = initial_state(model)
    out = {}
    for name in model.bodies:
        o, a, v, w = model.body_pose(name, s.q[None], s.qd[None])
        out[name] = BodyState(o[0], float(a[0]), v[0], float(w[0]))
    return out


def steps_per_sample(case: Case, dt: float) -> int:
    """How many steps of size dt make one output interval; dt must divide it."""
    k = case.output_dt / dt
    if abs(k - round(k)) > 1e-9 or round(k) < 1:
        raise ValueError(f"time step {dt} s must divide the output interval {case.output_dt} s")
    return int(round(k))


def merged(defaults: dict, settings: dict) -> dict:
    """Adapter defaults overridden by the case's settings (neither is mutated)."""
    return {**defaults, **(settings or {})}
