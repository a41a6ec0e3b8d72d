"""Engine-neutral description of a mechanism and its scenario.

Every engine adapter and natcoord's own model are built from these frozen objects; none of
them is mutated after :func:`natcoord.case.casefile.load_case` returns. All quantities are SI
(m, kg, s, N, rad).

Conventions
-----------
* A body frame is attached to each body; named points are given in that frame.
* 2-D: a pose is ``(x, y, angle)``; the angle of a body is the angle of its frame's x axis
  from world +x, counter-clockwise positive.
* ``Case.guess`` gives every body frame's pose at t = 0. A case file written in the
  *reference frame* (no ``[initial.pose]``; every 3-D case) gives every point as its world
  position at t = 0: its body frames are the world frame at t = 0 and its points close the
  joints exactly (``pose_tolerance`` 1e-6 m). A *posed* file gives each body an approximate
  pose, from which assembly closes the joints (``pose_tolerance`` infinite). After loading,
  both are the same kind of description.
* A joint joins ``bodies[0]`` and ``bodies[1]`` at ``points[0]`` (on the first) and
  ``points[1]`` (on the second). Its reaction is the force the joint applies to the second
  body, in world axes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

GROUND = "ground"

BODY_KINDS = ("uniform_rod", "particle", "rigid")
JOINT_TYPES = ("revolute", "prismatic", "spherical", "universal", "cylindrical")
PLANAR_JOINTS = ("revolute", "prismatic")  # the joint types a 2-D case can have
FORCE_TYPES = ("torque", "force")
LOAD_FRAMES = ("world", "body")  # the axes of a [[forces]] value
CHANNEL_KINDS = ("angle", "position", "velocity", "reaction", "energy", "acceleration",
                 "driver", "axial", "combination", "loop_gap", "angular_velocity",
                 "angular_momentum", "momentum", "vector_angle", "angular_acceleration")
PLANES = {"xy": (0, 1), "yz": (1, 2), "xz": (0, 2)}
DRIVER_TYPES = ("angle", "coordinate")
FORCE_KINDS = ("reaction", "axial", "combination")  # channels that are forces
# natcoord's reaction methods ([reactions.<method>]); a weighted one may carry a label,
# weighted_<label>, so that a case compares several stiffness sets
REACTION_METHODS = ("min_norm", "unit_invariant", "weighted")


def reaction_method(name: str) -> str | None:
    """The method of REACTION_METHODS a ``[reactions.<name>]`` table runs, or None."""
    if name in REACTION_METHODS:
        return name
    return "weighted" if name.startswith("weighted_") else None


@dataclass(frozen=True)
class Body:
    """A rigid body or a particle.

    Attributes
    ----------
    name : str
    kind : {"uniform_rod", "particle", "rigid"}
    mass : float, kg
    points : dict[str, ndarray (d,)]
        Named points in the body frame, m. Insertion order matters: the first two points
        are the body's basic points in natural coordinates (one for a particle).
    com : ndarray (d,)
        Centre of mass in the body frame, m.
    inertia : float or ndarray (3, 3)
        About the centre of mass, kg m^2: 2-D a scalar; 3-D the tensor in body axes (a
        slender rod's is singular: nothing about its own axis).
    ends : tuple[str, str] or None
        uniform_rod: the points its mass lies between (default its first two points).
    """

    name: str
    kind: str
    mass: float
    points: dict[str, np.ndarray]
    com: np.ndarray
    inertia: float | np.ndarray
    ends: tuple[str, str] | None = None


@dataclass(frozen=True)
class Joint:
    """A joint between two bodies (``ground`` allowed as either).

    Attributes
    ----------
    name : str
    type : {"revolute", "prismatic", "spherical", "universal", "cylindrical"}
    bodies : tuple[str, str]
    points : tuple[str, str]
        The joint point on each body.
    axis : ndarray (d,) or None
        Unit vector in the first body's frame: the sliding direction (prismatic,
        cylindrical), the rotation axis (3-D revolute, cylindrical), the first body's cross
        axis (universal). A 2-D revolute turns about z and has none.
    axis2 : ndarray (3,) or None
        Universal joint only: the second body's cross axis, in the second body's frame,
        perpendicular to ``axis`` at t = 0.
    """

    name: str
    type: str
    bodies: tuple[str, str]
    points: tuple[str, str]
    axis: np.ndarray | None = None
    axis2: np.ndarray | None = None


@dataclass(frozen=True)
class Rod:
    """A massless rod between two body points (``ground`` allowed): revolute ends in 2-D,
    spherical ends in 3-D. ``length`` (m) is the distance at t = 0; its output is the axial
    force, tension positive."""

    name: str
    ends: tuple[tuple[str, str], tuple[str, str]]
    length: float


@dataclass(frozen=True)
class Spring:
    """A linear spring-damper between two body points: tension
    ``stiffness (l - length) + damping dl/dt`` (N/m, N s/m, m; rest length ``length``: the
    file's ``length``, else the distance at t = 0)."""

    name: str
    ends: tuple[tuple[str, str], tuple[str, str]]
    stiffness: float
    damping: float
    length: float


@dataclass(frozen=True)
class Force:
    """A constant applied load on ``body``. ``torque``: moment ``value`` (N m; a scalar in
    2-D, (3,) in 3-D). ``force``: force ``value`` (d,) N applied at the body point
    ``point``. ``frame``: the axes of ``value``, ``"world"`` or ``"body"`` (3-D only: the
    body's own frame, the world frame at t = 0 in a 3-D case, so the load turns with the
    body; its world value is ``R(t) value``)."""

    type: str
    body: str
    value: float | np.ndarray
    point: str | None = None
    frame: str = "world"


@dataclass(frozen=True)
class Channel:
    """A named output: what to measure and in which component.

    kind ``angle`` (body; with ``points = (p, q)`` the angle of r_q - r_p in ``plane``, from
    its first axis towards its second; with ``relative_to`` that angle minus the angle
    channel ``relative_to``: a joint angle between two bodies),
    ``position``/``velocity``/``acceleration`` (body, point, axis x|y|z), ``reaction``
    (joint, axis x|y|z|normal (2-D prismatic)|along|across (3-D joint with an axis: the
    component along it, the size of the rest)), ``energy`` (kinetic + gravitational +
    spring, J; with ``work`` that minus the work done since t = 0 by applied loads,
    dampers and drivers: the energy balance, constant in exact physics, see
    :func:`natcoord.outputs.result.work`),
    ``driver`` (the effort a driver applies: N m for an angle driver, N for a coordinate),
    ``axial`` (tension of rod or spring ``rod``, N), ``combination``
    (``sum(c * channel)`` over ``of``, in the unit of its terms), ``loop_gap`` (the largest
    distance between the points the ``joints`` hold together, every joint when empty, m:
    see :func:`natcoord.outputs.result.loop_gap`), ``angular_velocity`` (body, axis; ``frame``
    world or body axes, rad/s), ``angular_momentum`` (of ``body``, or the system when it is
    None, about the world point ``about`` or ``"com"`` its centre of mass, world axis,
    kg m^2/s), ``momentum`` (linear, of ``body`` or the system, world axis, kg m/s); the
    angular ones take axis ``z`` in 2-D; ``vector_angle`` (the angle in [0, pi] between
    r_q - r_p of the two ``vectors`` (body, p, q), rad).
    """

    name: str
    kind: str
    body: str | None = None
    point: str | None = None
    joint: str | None = None
    axis: str | None = None
    driver: str | None = None
    rod: str | None = None
    points: tuple[str, str] | None = None
    plane: str = "xy"
    of: tuple[tuple[str, float], ...] = ()
    relative_to: str | None = None
    work: bool = False
    joints: tuple[str, ...] = ()  # loop_gap: the joints it measures (empty: every joint)
    frame: str = "world"  # angular_velocity, angular_acceleration: "world" or "body" axes
    about: str | tuple[float, ...] = ()  # angular_momentum: a world point (m), or "com"
    vectors: tuple[tuple[str, str, str], ...] = ()  # vector_angle: two (body, p, q)

    @property
    def unit(self) -> str:
        return {"angle": "rad", "position": "m", "velocity": "m/s", "reaction": "N",
                "energy": "J", "acceleration": "m/s^2", "driver": "N m", "axial": "N",
                "combination": "N", "loop_gap": "m", "angular_velocity": "rad/s",
                "angular_momentum": "kg m^2/s", "momentum": "kg m/s",
                "vector_angle": "rad", "angular_acceleration": "rad/s^2"}[self.kind]


@dataclass(frozen=True)
class Driver:
    """A prescribed motion (rheonomic constraint) ``value(t) = v0 + rate t + accel t^2 / 2``.

    type ``angle`` (2-D): the angle of ``body`` (rad); its effort is the driving torque on the
    body (N m). type ``coordinate``: world coordinate ``axis`` (x|y|z) of ``point`` of
    ``body`` (m); its effort is the driving force along that axis (N).
    """

    name: str
    type: str
    body: str
    v0: float
    rate: float = 0.0
    accel: float = 0.0
    point: str | None = None
    axis: str | None = None


@dataclass(frozen=True)
class EngineSpec:
    """Per-engine settings and tolerances of a case, with the reason they are what they are.

    ``tolerance`` maps a channel name or a channel kind to a maximum absolute error (SI).
    """

    settings: dict = field(default_factory=dict)
    tolerance: dict[str, float] = field(default_factory=dict)
    reason: str = ""
    unsupported: str = ""

    def tolerance_for(self, channel: Channel) -> float | None:
        return self.tolerance.get(channel.name, self.tolerance.get(channel.kind))


@dataclass(frozen=True)
class Pose:
    """Approximate initial pose of a body frame: origin (m) and angle (rad)."""

    origin: np.ndarray
    angle: float = 0.0


@dataclass(frozen=True)
class Case:
    """A mechanism plus its scenario, as read from one case file.

    ``reactions``: natcoord's reaction methods, name -> options (``stiffness``: rod, spring
    or body name -> N/m or N m/rad, for a weighted minimum norm); the first method gives
    natcoord's channel values. ``pose_tolerance`` (m): how far assembly may move a body
    point from where ``guess`` puts it (see the module docstring).
    ``comparison``: ``{"singular": {channel, angles (rad), within (rad)}}``, samples where
    force channels are not compared (see :func:`natcoord.suite.compare.channel_errors`).
    ``timeout``: the case's own time limit for one engine run, s (None: the command's).
    ``benchmark``: the output a published benchmark scores, ``{channels (tuple of channel
    names), precision (their unit), error ("max_abs" over every sample | "final_abs" at the
    last), source}``; {} for a case without one (see :func:`natcoord.suite.bench.scoring`).
    """

    name: str
    description: str
    file: str
    dimension: int
    gravity: np.ndarray
    duration: float
    output_dt: float
    ground: dict[str, np.ndarray]
    bodies: tuple[Body, ...]
    joints: tuple[Joint, ...]
    forces: tuple[Force, ...]
    guess: dict[str, Pose]
    fix: dict[str, float]
    velocity: dict[str, float]
    channels: tuple[Channel, ...]
    engines: dict[str, EngineSpec]
    tags: tuple[str, ...] = ()
    absent_engines: tuple[str, ...] = ()  # [engines.X] blocks of engines not installed
    # here (plug-ins of another machine): loaded, not used
    drivers: tuple[Driver, ...] = ()
    rods: tuple[Rod, ...] = ()
    springs: tuple[Spring, ...] = ()
    reactions: dict[str, dict] = field(default_factory=dict)
    pose_tolerance: float = float("inf")
    timeout: float | None = None  # s: the case's own time limit per engine run
    digest: str = ""  # sha256 of the case file: history compares runs of identical cases
    comparison: dict = field(default_factory=dict)
    benchmark: dict = field(default_factory=dict)

    @property
    def times(self) -> np.ndarray:
        """Output sample times, s: (T,)."""
        n = int(round(self.duration / self.output_dt))
        return np.linspace(0.0, n * self.output_dt, n + 1)

    def body(self, name: str) -> Body:
        return next(b for b in self.bodies if b.name == name)

    def joint(self, name: str) -> Joint:
        return next(j for j in self.joints if j.name == name)

    def channel(self, name: str) -> Channel:
        return next(c for c in self.channels if c.name == name)

    def engine(self, name: str) -> EngineSpec:
        return self.engines.get(name, EngineSpec())


# ---- what a case's motion and channels depend on ------------------------------------------
# A reference stores these parts' digests: an edit that changes one makes the reference stale
# (its name says which), while tolerances, engine settings, the description or the
# benchmark table may change freely.
MECHANISM_PARTS: dict[str, tuple[str, ...]] = {
    "scenario": ("dimension", "gravity", "duration", "output_dt"),
    "bodies": ("ground", "bodies"),
    "joints": ("joints", "rods", "drivers"),
    "loads": ("forces", "springs"),
    "initial state": ("guess", "fix", "velocity"),
    "channels": ("channels", "reactions"),
}


def _canonical(x):
    """x as JSON-ready data with one spelling: dataclasses as dicts of their fields, arrays
    and tuples as lists, floats as ``float.hex`` (exact), dict keys sorted by json."""
    if hasattr(x, "__dataclass_fields__"):
        return {k: _canonical(getattr(x, k)) for k in x.__dataclass_fields__}
    if isinstance(x, dict):
        return {str(k): _canonical(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [_canonical(v) for v in x.tolist()]
    if isinstance(x, (list, tuple)):
        return [_canonical(v) for v in x]
    if isinstance(x, (bool, np.bool_)):  # before int: bool is one
        return bool(x)
    if x is None or isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x).hex()
    return repr(x)


def _digest(data) -> str:
    """sha256 (hex) of JSON-ready ``data`` in one spelling (keys sorted, no spaces)."""
    return hashlib.sha256(json.dumps(data, sort_keys=True,
                                     separators=(",", ":")).encode()).hexdigest()


def mechanism_parts(case: Case) -> dict[str, str]:
    """sha256 (hex, 16 digits) of each part of ``case`` that its motion and channels depend
    on (:data:`MECHANISM_PARTS`), whatever the file's layout, comments or key order."""
    return {part: _digest({f: _canonical(getattr(case, f)) for f in fields})[:16]
            for part, fields in MECHANISM_PARTS.items()}


def bench_key(case: Case, engine: str) -> str:
    """sha256 (hex) of what a benchmark of ``engine`` on ``case`` runs: the mechanism's parts
    and the engine's settings in the case. The speed history compares the runs of one key,
    so that an edit of tolerances, reasons, the description or another engine's block keeps
    a cell's speed baseline."""
    return _digest({"mechanism": mechanism_parts(case), "engine": engine,
                    "settings": _canonical(case.engine(engine).settings)})
