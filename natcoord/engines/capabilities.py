"""What an engine declares it can model, and why it cannot run a given case.

Every adapter has ``CAPABILITIES``, a :class:`Capabilities`; :func:`reasons` reads it against
a loaded case (and the settings it would run with) and returns the reasons the engine
cannot run it, empty when it can. ``natcoord cases`` shows them, and the runner records a
case x engine with a reason as ``unsupported`` without starting an engine process. What
the fields cannot say (a driver's joint, an axis the tree does not keep) goes in
``rules``, a function of the adapter that needs no engine import.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from ..case.mechanism import DRIVER_TYPES, GROUND, JOINT_TYPES, Case, Joint
from .schema import short

LOOPS = ("rigid", "soft", "none")


@dataclass(frozen=True)
class Capabilities:
    """An engine's declared modelling range.

    Attributes
    ----------
    dimensions : 2 and/or 3 (planar, spatial cases)
    joints : joint types it models in a kinematic tree
    loops : "rigid" (exact loop constraints), "soft" (constraints with compliance or
        stabilisation that lets a loop open by a small, setting-dependent gap) or "none"
    loop_joints : joint types that may close a loop
    recut : joint types the engine moves into its tree when natcoord's spanning tree
        (:func:`natcoord.engines.tree.spanning_tree`) leaves one to close a loop (the
        tree is then rebuilt with those types first, as
        :func:`natcoord.engines.tree.point_loop_tree` does for prismatic joints)
    drivers : driver types it prescribes (``angle``, ``coordinate``); empty: none
    springs : linear spring-dampers
    rods : massless rods (revolute ends in 2-D, spherical in 3-D)
    torques : applied torques on bodies
    forces : applied forces: "any" point, "com" only at a body's centre of mass, "none"
    body_loads : it applies torques and forces given in a body's frame (``frame = "body"``,
        turning with the body); False (the default, so a plug-in that does not say is never
        run with a load it would hold in world axes): such a case is refused
    particles : dimensions in which particles (no rotational inertia) are modelled
    reactions : it reports joint reactions (reaction, axial, driver channels); not a
        refusal (a case's motion channels run without them); without, check-engine skips
        its reaction checks
    step : the setting that fixes its time step (s), "" when it has none (``check-engine``
        then takes ``dt`` or ``h`` from its settings when it declares one)
    step_with : settings that go with a fixed step (natcoord: a fixed-step method)
    output_steps : its fixed step (``step``, else ``dt``) must divide the output interval
        (the case loader refuses one given in a case file that does not)
    why : capability field -> the engine's explanation, appended to a refusal
    rules : ``rules(case, settings) -> list[str]``: the adapter's further refusals (only
        asked when the fields above find none), ``settings`` over the adapter's defaults;
        rules that raise or return anything but a list of strings raise
        :class:`RulesError` (the run fails: a bug is not a refusal)
    """

    dimensions: frozenset = frozenset({2, 3})
    joints: frozenset = frozenset(JOINT_TYPES)
    loops: str = "rigid"
    loop_joints: frozenset = frozenset(JOINT_TYPES)
    recut: frozenset = frozenset()
    drivers: frozenset = frozenset(DRIVER_TYPES)
    springs: bool = True
    rods: bool = True
    torques: bool = True
    forces: str = "any"
    body_loads: bool = False
    particles: frozenset = frozenset({2, 3})
    reactions: bool = True
    step: str = ""
    step_with: Mapping[str, object] = field(default_factory=dict, compare=False)
    output_steps: bool = False
    why: Mapping[str, str] = field(default_factory=dict, compare=False)
    rules: Callable[[Case, dict], list[str]] | None = field(default=None, compare=False)

    def __post_init__(self):
        if self.loops not in LOOPS:
            raise ValueError(f"loops must be one of {LOOPS}, got {self.loops!r}")
        if self.forces not in ("any", "com", "none"):
            raise ValueError(f"forces must be 'any', 'com' or 'none', got {self.forces!r}")
        for name in ("dimensions", "joints", "loop_joints", "recut", "drivers", "particles"):
            object.__setattr__(self, name, frozenset(getattr(self, name)))
        known = {"dimensions": {2, 3}, "particles": {2, 3}, "joints": set(JOINT_TYPES),
                 "loop_joints": set(JOINT_TYPES), "recut": set(JOINT_TYPES),
                 "drivers": set(DRIVER_TYPES)}
        for name, allowed in known.items():  # a typo would decline (or claim) every case
            odd = [x for x in getattr(self, name) if x not in allowed]
            if odd:
                raise ValueError(f"{name} holds {', '.join(map(repr, odd))[:200]}, not one of "
                                 f"{', '.join(map(str, sorted(allowed, key=str)))}")

    def summary(self) -> dict:
        """JSON-friendly fields (``rules`` as the adapter function's name)."""
        out = {k: (sorted(v) if isinstance(v, frozenset) else v)
               for k, v in self.__dict__.items() if k not in ("rules", "why", "step_with")}
        out["why"], out["step_with"] = dict(self.why), dict(self.step_with)
        out["rules"] = getattr(self.rules, "__qualname__", None)
        return out


class RulesError(Exception):
    """An engine's capability ``rules`` raised, or returned something other than a list of
    reasons: a fault of the engine, never a reason it cannot run a case."""


def _rules(caps: Capabilities, case: Case, settings: dict) -> list[str]:
    """The reasons of ``caps.rules``; RulesError when they raise (SystemExit too) or return
    anything but a list (or tuple) of strings."""
    try:
        got = caps.rules(case, settings)
    except (Exception, SystemExit) as e:
        raise RulesError(f"the engine's capability rules raised {type(e).__name__}: "
                         f"{e}") from e
    if not isinstance(got, (list, tuple)) or not all(isinstance(x, str) for x in got):
        raise RulesError(f"the engine's capability rules returned {short(got)}, not a "
                         "list of reasons (strings)")
    return list(got)


def tree(case: Case, caps: Capabilities) -> tuple[list[Joint], list[Joint]]:
    """(tree joints, loop-closing joints) as this engine builds its tree: natcoord's
    spanning tree, rebuilt with the ``recut`` types first when it leaves one of them to
    close a loop (:mod:`natcoord.engines.tree`)."""
    from .tree import spanning_tree

    joints, loops = spanning_tree(case)
    if any(j.type in caps.recut for j in loops):
        first = tuple(sorted(case.joints, key=lambda j: j.type not in caps.recut))
        joints, loops = spanning_tree(replace(case, joints=first))
    return joints, loops


def _say(caps: Capabilities, what: str, text: str) -> str:
    return f"{text}: {caps.why[what]}" if what in caps.why else text


def reasons(caps: Capabilities, case: Case, settings: dict | None = None, *,
            rules: bool = True) -> list[str]:
    """Why an engine with ``caps`` cannot run ``case`` (at ``settings``: the case's own for
    the engine when None is given); [] when it can. ``rules``: False leaves out the
    adapter's ``rules`` (the declared fields only); else a fault of theirs raises
    :class:`RulesError`."""
    out: list[str] = []
    dim = case.dimension
    if dim not in caps.dimensions:
        out.append(_say(caps, "dimensions", f"{dim}-D cases are not modelled"))
    bad = [j for j in case.joints if j.type not in caps.joints]
    if bad:
        out.append(_say(caps, "joints", f"{bad[0].type} joint {bad[0].name!r} is not "
                        "modelled"))
    closing = tree(case, caps)[1]
    if closing and caps.loops == "none":
        out.append(_say(caps, "loops", f"closed loops are not modelled (joint "
                        f"{closing[0].name!r} closes one)"))
    elif caps.loops != "none":
        bad = [j for j in closing if j.type not in caps.loop_joints]
        if bad:
            out.append(_say(caps, "loop_joints", f"{bad[0].type} joint {bad[0].name!r} must "
                            f"close a loop; loops close at "
                            f"{', '.join(sorted(caps.loop_joints)) or 'no joint'} only"))
    bad = [d for d in case.drivers if d.type not in caps.drivers]
    if bad:
        out.append(_say(caps, "drivers", f"{bad[0].type} driver {bad[0].name!r}: prescribed "
                        "motions " + (f"of type {', '.join(sorted(caps.drivers))} only"
                                      if caps.drivers else "are not modelled")))
    if case.springs and not caps.springs:
        out.append(_say(caps, "springs", f"spring-damper {case.springs[0].name!r}: "
                        "spring-dampers are not modelled"))
    if case.rods and not caps.rods:
        out.append(_say(caps, "rods", f"rod {case.rods[0].name!r}: massless rods are not "
                        "modelled"))
    particles = {b.name for b in case.bodies if b.kind == "particle"}
    if particles and dim not in caps.particles:
        out.append(f"body {sorted(particles)[0]!r}: {dim}-D particles are not modelled")
    for f in case.forces:
        if f.body == GROUND:
            continue
        if f.type == "torque" and (not caps.torques or f.body in particles):
            out.append(f"torque on {f.body!r}: " + ("a particle has no rotation"
                                                    if caps.torques else "not modelled"))
        if f.frame == "body" and not caps.body_loads and case.dimension == 3:
            out.append(_say(caps, "body_loads", f"{f.type} on {f.body!r} in its body's frame "
                            "(frame = \"body\"): body-fixed loads are not modelled"))
        elif f.type == "force" and caps.forces != "any":
            b = case.body(f.body)
            if caps.forces == "none" or np.linalg.norm(b.points[f.point] - b.com) > 1e-12:
                out.append(f"force on {f.body!r} at point {f.point!r}: forces " + (
                    "only at a body's centre of mass" if caps.forces == "com"
                    else "are not modelled"))
    if rules and caps.rules is not None and not out:
        out += _rules(caps, case, settings if settings is not None else {})
    return out


def drivers_off_ground_joints(case: Case, caps: Capabilities) -> list[tuple[str, str, str]]:
    """For engines that prescribe a tree joint's coordinate: each driver whose body is not
    on a tree joint from the ground of its kind, as (driver, body, joint type wanted:
    revolute for an angle, prismatic for a coordinate)."""
    joints = tree(case, caps)[0]
    out = []
    for d in case.drivers:
        want = "revolute" if d.type == "angle" else "prismatic"
        j = next((j for j in joints if d.body in j.bodies and GROUND in j.bodies), None)
        if j is None or j.type != want:
            out.append((d.name, d.body, want))
    return out


def misaligned_loop_revolutes(case: Case, caps: Capabilities) -> list[str]:
    """Loop-closing 3-D revolutes whose axis (world, t = 0) some joint on the tree path
    between their bodies does not share (a non-revolute joint there counts as not sharing
    it; prismatic joints keep every axis): a point constraint lets them turn off it."""
    from .tree import tree_parents

    if case.dimension != 3:
        return []
    joints, closing = tree(case, caps)
    parent = {child: (j, par) for j, par, child in tree_parents(joints)}

    def up(body):
        path = []
        while body in parent:
            j, body = parent[body]
            path.append(j)
        return path

    out = []
    for j in closing:
        if j.type != "revolute":
            continue
        axis = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
        pa, pb = up(j.bodies[0]), up(j.bodies[1])
        common = {x.name for x in pa} & {x.name for x in pb}
        for t in (x for x in pa + pb if x.name not in common and x.type != "prismatic"):
            if t.type != "revolute" or np.linalg.norm(np.cross(
                    np.asarray(t.axis, float) / np.linalg.norm(t.axis), axis)) > 1e-9:
                out.append(j.name)
                break
    return out


def refuse(caps: Capabilities, case: Case, settings: dict) -> None:
    """Raise Unsupported with the first of :func:`reasons`: an adapter's run starts here,
    so that what it declares and what it refuses are one."""
    from ..errors import Unsupported

    why = reasons(caps, case, settings)
    if why:
        raise Unsupported(why[0])


def massless(case: Case, what: str) -> list[str]:
    """A rule for engines whose bodies need mass: the first massless body, else []."""
    return [f"body {b.name} is massless; {what} need mass"
            for b in case.bodies if b.mass <= 0][:1]


def why_not(case: Case, engine: str, settings: dict | None = None, *,
            rules: bool = True) -> str:
    """Why ``engine`` does not run ``case`` before any run: the case file's own
    ``unsupported`` (a measured reason), else its declared capabilities' reasons joined
    by "; " (at the case's settings for it over ``settings``); "" when it can.
    ``rules``: as :func:`reasons` (False: the adapter's own code is not run)."""
    from .registry import adapter
    from .schema import defaults

    spec = case.engine(engine)
    if spec.unsupported:
        return spec.unsupported
    mod = adapter(engine)
    merged = {**defaults(mod.SETTINGS), **spec.settings, **(settings or {})}
    return "; ".join(reasons(mod.CAPABILITIES, case, merged, rules=rules))
