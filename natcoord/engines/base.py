"""What every engine adapter shares: the contract, the initial state it starts from and
what it returns.

An adapter is a module (or a small subpackage) of this package that follows
:class:`Adapter`. ``init`` is the state natcoord assembled once per run (the same for every
engine), ``settings`` the case's ``[engines.<name>].settings`` over the adapter's own
defaults. Every body of a case has its points in its own frame; ``init[body]`` gives that
frame's pose and rates at t = 0. All conventions of an engine (frames, signs, units,
quaternion order) stay inside its adapter; what it returns is a
:class:`~natcoord.result.Motion` in natcoord's neutral convention, sampled at
``case.times``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from ..mechanism import Case
from ..result import Motion


@dataclass(frozen=True)
class BodyState:
    """Assembled state of one body frame at t = 0.

    Attributes
    ----------
    origin : (d,) world position of the frame origin, m
    angle : float, rad: angle of the frame's x axis from world +x (2-D; 0 in 3-D)
    velocity : (d,) world velocity of the frame origin, m/s
    omega : float (2-D) rad/s, or (3,) world axes (3-D)
    rotation : (d, d) body-to-world rotation
    """

    origin: np.ndarray
    angle: float
    velocity: np.ndarray
    omega: float | np.ndarray
    rotation: np.ndarray

    def rotation3(self) -> np.ndarray:
        """(3, 3) body-to-world rotation (a 2-D frame turns about z)."""
        R = np.eye(3)
        R[:len(self.rotation), :len(self.rotation)] = self.rotation
        return R


@dataclass(frozen=True)
class InitialState(Mapping):
    """The case assembled at t = 0: natcoord's coordinates ``q``, ``qd`` (n,) and every
    body's frame state; ``init[body]`` is that body's :class:`BodyState`."""

    q: np.ndarray
    qd: np.ndarray
    bodies: dict[str, BodyState]

    def __getitem__(self, body: str) -> BodyState:
        return self.bodies[body]

    def __iter__(self) -> Iterator[str]:
        return iter(self.bodies)

    def __len__(self) -> int:
        return len(self.bodies)


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


@runtime_checkable
class Adapter(Protocol):
    """What an engine adapter module provides."""

    NAME: str       # engine name used in case files and results
    PACKAGE: str    # the PyPI package that provides the engine

    def version(self) -> str:
        """The engine's version; raises ImportError when its package is missing."""

    def run(self, case: Case, init: InitialState, settings: dict) -> EngineRun:
        """Simulate ``case`` from ``init`` at the case's sample times; raises
        :class:`natcoord.errors.Unsupported` (with the reason) for what it cannot model."""


def initial_body_states(case: Case) -> InitialState:
    """Assemble the case with natcoord's kinematics: q, qd and every body's frame state."""
    from ..kinematics import initial_state
    from ..model import build_model

    def rot2(a):
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    if case.reference_frame:
        from .. import casemodel

        cm = casemodel.build(case, case.engine("natcoord").settings.get("coordinates",
                                                                          "joints"))
        s = casemodel.initial_state(cm)
        o, a, R, v, w = casemodel.frames(cm, s.q[None], s.qd[None])
        return InitialState(s.q, s.qd, {
            b: BodyState(o[b][0], float(a[b][0]) if b in a else 0.0, v[b][0],
                         float(w[b][0]) if case.dimension == 2 else w[b][0],
                         R[b][0] if b in R else rot2(float(a[b][0]))) for b in o})

    model = build_model(case)
    s = initial_state(model)
    out = {}
    for name in model.bodies:
        o, a, v, w = model.body_pose(name, s.q[None], s.qd[None])
        out[name] = BodyState(o[0], float(a[0]), v[0], float(w[0]), rot2(float(a[0])))
    return InitialState(s.q, s.qd, out)


def steps_per_sample(case: Case, dt: float) -> int:
    """How many steps of size dt make one output interval; dt must divide it."""
    k = case.output_dt / dt
    if abs(k - round(k)) > 1e-9 or round(k) < 1:
        raise ValueError(f"time step {dt} s must divide the output interval {case.output_dt} s")
    return int(round(k))


def merged(defaults: dict, settings: dict) -> dict:
    """Adapter defaults overridden by the case's settings (neither is mutated)."""
    return {**defaults, **(settings or {})}
