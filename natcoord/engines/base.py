"""What every engine adapter shares: the contract, the initial state it starts from and
what it returns.

An adapter is a module (or a small subpackage; a plug-in's is in its own package) that
follows :class:`Adapter`, registered in the ``natcoord.engines`` entry-point group
(:mod:`natcoord.engines.registry`). ``init`` is the state natcoord assembled once per run
(the same for every engine), ``settings`` the case's ``[engines.<name>].settings`` over
the adapter's own defaults (declared in its ``SETTINGS``, :mod:`natcoord.engines.schema`;
importing the adapter must not import its engine, so that a case loads without it). Every body of a
case has its points in its own frame; ``init[body]`` gives that frame's pose and rates at
t = 0. All conventions of an engine (frames, signs, units, quaternion order) stay inside
its adapter; what it returns is a :class:`~natcoord.outputs.result.Motion` in natcoord's neutral
convention, sampled at ``case.times``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from ..case.mechanism import Case
from ..outputs.channels import BodyState, InitialState, initial_body_states
from ..outputs.result import Motion

__all__ = ["Adapter", "BodyState", "EngineRun", "InitialState", "initial_body_states",
           "merged", "steps_per_sample"]


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
    SETTINGS: tuple  # the settings it reads, as natcoord.engines.schema.Setting: the loader
    # refuses any other key or an invalid value; optional check_settings(settings) -> list
    # of (field, reason) adds rules between settings
    CAPABILITIES: object  # natcoord.engines.capabilities.Capabilities: what it can model;
    # a case it cannot run is unsupported (with the reason) before any run

    def version(self) -> str:
        """The engine's version; raises ImportError when its package is missing."""

    def run(self, case: Case, init: InitialState, settings: dict) -> EngineRun:
        """Simulate ``case`` from ``init`` at the case's sample times; raises
        :class:`natcoord.errors.Unsupported` (with the reason) for what it cannot model."""


def steps_per_sample(case: Case, dt: float) -> int:
    """How many steps of size dt make one output interval; dt must divide it."""
    k = case.output_dt / dt
    if abs(k - round(k)) > 1e-9 or round(k) < 1:
        raise ValueError(f"time step {dt} s must divide the output interval {case.output_dt} s")
    return int(round(k))


def merged(defaults: dict, settings: dict) -> dict:
    """Adapter defaults overridden by the case's settings (neither is mutated)."""
    return {**defaults, **(settings or {})}
