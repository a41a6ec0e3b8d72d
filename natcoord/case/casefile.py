"""Read and validate case files (TOML, data only: nothing in a case file is executed).

Every mistake is reported as :class:`~natcoord.errors.CaseError` naming the file, the field
and the reason. Quantities are SI numbers, or strings with a unit such as ``"45 deg"`` or
``"300 mm"``; a unit of the wrong dimension is an error.

Budgets, so that no file can exhaust the machine or write outside the output folder: a
file of at most ``MAX_FILE_BYTES``, tables nested at most ``MAX_DEPTH`` deep, at most
``MAX_SAMPLES`` output samples, a run of at most ``MAX_DURATION_S``; every name (case,
bodies, points, joints, rods, springs, drivers, channels) a short safe identifier
(``NAME_PATTERN``, at most ``MAX_NAME`` characters), and free text (descriptions, reasons)
printable and at most ``MAX_TEXT`` characters.
"""

from __future__ import annotations

import difflib
import hashlib
import math
import os
import re
import stat
import sys
import tomllib
from pathlib import Path

import numpy as np

from ..engines.schema import short, shown
from ..errors import CaseError
from .mechanism import (
    BODY_KINDS,
    CHANNEL_KINDS,
    DRIVER_TYPES,
    GROUND,
    JOINT_TYPES,
    LOAD_FRAMES,
    PLANAR_JOINTS,
    PLANES,
    REACTION_METHODS,
    Body,
    Case,
    Channel,
    Driver,
    EngineSpec,
    Force,
    Joint,
    Pose,
    Rod,
    Spring,
    reaction_method,
)

# unit -> (factor to SI, dimension)
UNITS = {
    "m": (1.0, "length"), "mm": (1e-3, "length"), "cm": (1e-2, "length"),
    "kg": (1.0, "mass"), "g": (1e-3, "mass"),
    "s": (1.0, "time"), "ms": (1e-3, "time"),
    "rad": (1.0, "angle"), "deg": (math.pi / 180, "angle"),
    "rad/s": (1.0, "angular velocity"), "deg/s": (math.pi / 180, "angular velocity"),
    "m/s": (1.0, "velocity"), "mm/s": (1e-3, "velocity"),
    "m/s^2": (1.0, "acceleration"),
    "rad/s^2": (1.0, "angular acceleration"), "deg/s^2": (math.pi / 180, "angular acceleration"),
    "N": (1.0, "force"), "N m": (1.0, "torque"), "Nm": (1.0, "torque"),
    "kg m^2": (1.0, "inertia"), "J": (1.0, "energy"),
    "kg m/s": (1.0, "momentum"), "kg m^2/s": (1.0, "angular momentum"),
    "N/m": (1.0, "stiffness"), "N s/m": (1.0, "damping"),
    "N m/rad": (1.0, "torsional stiffness"),
}
TOP_KEYS = {"name", "description", "dimension", "gravity", "duration", "output_dt", "ground",
            "bodies", "joints", "forces", "initial", "channels", "engines", "tags",
            "drivers", "rods", "springs", "reactions", "comparison", "timeout", "benchmark"}
ENGINE_KEYS = {"settings", "tolerance", "reason", "unsupported"}  # of [engines.<name>]
# the keys of every other table the loader reads (a key not in its set is refused)
GROUND_KEYS = {"points"}
BODY_KEYS = {"name", "kind", "mass", "points", "ends", "com", "inertia"}
JOINT_KEYS = {"name", "type", "bodies", "points", "axis", "axis2"}
FORCE_KEYS = {"type", "body", "frame", "value", "point"}
DRIVER_KEYS = {"name", "type", "body", "angle0", "rate", "accel", "point", "axis", "value0"}
CHANNEL_KEYS = {"kind", "body", "point", "axis", "joint", "joints", "driver", "rod", "points",
                "plane", "relative_to", "of", "work", "frame", "about", "vectors"}
INITIAL_KEYS = {"pose", "fix", "velocity"}
POSE_KEYS = {"origin", "angle"}
MAX_FILE_BYTES = 1 << 20
MAX_DEPTH = 8
MAX_SAMPLES = 1_000_000
MIN_TIMEOUT_S, MAX_TIMEOUT_S = 1e-3, 7 * 24 * 3600.0  # an engine run's time limit (s)
MAX_DURATION_S = 1e5
MAX_NAME = 64
MAX_MAGNITUDE = 1e150  # a quantity's size: its square (energies, norms) must not overflow
MIN_POSITIVE = 1e-150  # a positive quantity's least: its square must not underflow to 0, a
# ratio over it (an error over a tolerance of 1e-320) must not overflow to inf
MAX_TEXT = 10_000
RESERVED_CHANNELS = ("t", "time")  # result and reference CSVs' time column
# a name, at most MAX_NAME characters: the pattern bounds the length, so every check of a
# case name against it (a file name: longer ones the file system refuses) keeps the limit
NAME_PATTERN = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9_.+-]{{0,{MAX_NAME - 1}}}")


class _Reader:
    """Typed access to a parsed TOML table that reports errors with their field path."""

    def __init__(self, file: str):
        self.file = file

    def fail(self, field: str, reason: str):
        raise CaseError(self.file, field, reason)

    def get(self, table: dict, key: str, path: str, *, required=True, default=None):
        if not isinstance(table, dict):
            self.fail(path, f"must be a table, got {short(table)}")
        if key not in table:
            if required:
                self.fail(_join(path, key), "missing required field")
            return default
        return table[key]

    def table(self, table, key, path, *, required=True) -> dict:
        v = self.get(table, key, path, required=required, default={})
        if not isinstance(v, dict):
            self.fail(_join(path, key), f"must be a table, got {type(v).__name__}")
        return v

    def string(self, table, key, path, *, required=True, default=None, choices=None) -> str:
        if key not in table and not required:
            return default
        v = self.get(table, key, path)
        if not isinstance(v, str) or not v:
            self.fail(_join(path, key), f"must be a non-empty string, got {short(v)}")
        if choices and v not in choices:
            self.fail(_join(path, key),
                      f"unknown value {short(v)}; expected one of {', '.join(choices)}")
        if len(v) > MAX_TEXT or any(not (c.isprintable() or c in "\n\t") for c in v):
            self.fail(_join(path, key), f"must be printable text of at most {MAX_TEXT} "
                      "characters")
        return v

    def known(self, table, allowed, path: str) -> None:
        """Refuse a key of ``table`` (a table the loader reads) that is not in ``allowed``:
        a misspelt key would otherwise be ignored silently. The message names the table's
        path and the key, the expected keys and the closest of them to a typo."""
        unknown = sorted(set(table) - set(allowed)) if isinstance(table, dict) else []
        if unknown:
            key, expected = unknown[0], sorted(allowed)
            self.fail(_join(path, shown(key)), f"unknown field; expected some of "
                      f"{', '.join(expected)}{_did_you_mean(key, expected)}")

    def name(self, table, key, path) -> str:
        """A name: a short safe identifier (it becomes a file name or a CSV column)."""
        return self.identifier(self.string(table, key, path), _join(path, key))

    def identifier(self, v, field: str) -> str:
        if not isinstance(v, str) or len(v) > MAX_NAME or not NAME_PATTERN.fullmatch(v):
            self.fail(field, f"{short(v)} is not a name: use at most {MAX_NAME} letters, "
                      "digits and _ . + - (not starting with . + or -)")
        return v

    def quantity(self, value, field: str, dimension: str, *, positive=False) -> float:
        if isinstance(value, bool):
            self.fail(field, f"must be a number ({dimension}), got {value!r}")
        if isinstance(value, (int, float)):
            x = value  # an integer past a float is compared below, never converted
        elif isinstance(value, str):
            parts = value.strip().split(maxsplit=1)
            try:
                number = float(parts[0])
            except (ValueError, IndexError):
                self.fail(field, f"cannot read {value!r} as a number with a unit")
            unit = parts[1].strip() if len(parts) > 1 else ""
            if unit not in UNITS:
                self.fail(field, f"unknown unit {unit!r} in {value!r}")
            factor, dim = UNITS[unit]
            if dim != dimension:
                self.fail(field, f"expected a {dimension}, got {value!r} (a {dim})")
            x = number * factor
        else:
            self.fail(field, f"must be a number ({dimension}), got {type(value).__name__}")
        if isinstance(x, float) and not math.isfinite(x):
            self.fail(field, f"must be finite, got {short(value)}")
        if abs(x) > MAX_MAGNITUDE:  # gravity 1e200 loaded, then overflowed at run time
            self.fail(field, f"{short(value)} is beyond {MAX_MAGNITUDE:g} in size (its "
                      "square would overflow)")
        if positive and x <= 0:
            self.fail(field, f"must be positive, got {value!r}")
        if positive and x < MIN_POSITIVE:
            self.fail(field, f"{short(value)} is below {MIN_POSITIVE:g} (its square would "
                      "underflow to zero)")
        return float(x)

    def number(self, table, key, path, dimension, *, required=True, default=None,
               positive=False) -> float:
        v = self.get(table, key, path, required=required, default=default)
        if v is None:
            return v
        return self.quantity(v, _join(path, key), dimension, positive=positive)

    def vector(self, value, field: str, dim: int, dimension: str) -> np.ndarray:
        if not isinstance(value, list) or len(value) != dim:
            self.fail(field, f"must be a list of {dim} numbers ({dimension}), got {value!r}")
        return np.array([self.quantity(v, f"{field}[{i}]", dimension) for i, v in enumerate(value)])


def _did_you_mean(key, expected) -> str:
    """`` (did you mean X?)`` with the closest of ``expected`` to a typo, or nothing."""
    close = difflib.get_close_matches(str(key), list(expected), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _join(path: str, key) -> str:
    return f"{path}.{key}" if path else str(key)


def _depth(x, limit: int) -> int:
    """Nesting depth of tables and arrays (iterative: no recursion limit), stopping past
    ``limit``."""
    depth, level = 0, [x]
    while level and depth <= limit:
        nxt = []
        for v in level:
            if isinstance(v, dict):
                nxt.extend(v.values())
            elif isinstance(v, list):
                nxt.extend(v)
        level = nxt
        depth += 1 if nxt else 0
    return depth


def _read_bounded(path: Path, r: _Reader) -> bytes:
    """The bytes of a case file: a regular file (not a device, FIFO or socket, whatever a
    link points at), opened without blocking and read to at most MAX_FILE_BYTES."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(str(path))
        if not stat.S_ISREG(mode):
            r.fail("", "not a regular file (a device, FIFO or socket); a case file is a "
                       "short text file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_FILE_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_FILE_BYTES:
        r.fail("", f"larger than {MAX_FILE_BYTES} bytes; a case file is a short text")
    return data


def check_file_name(path: str | Path) -> None:
    """Refuse, before the file system is asked, a case file whose name without ``.toml`` is
    longer than a case name may be (``MAX_NAME``): the case's name must equal it, and a name
    past the file system's limit would otherwise be an error of the environment, not of the
    input. The name is shown cut (a 10 000-character name is not echoed)."""
    path = Path(path)
    if len(path.stem) > MAX_NAME:
        raise CaseError(path.parent / f"{path.stem[:MAX_NAME]}...{path.suffix}", "",
                        f"not a case file: its name is {len(path.stem)} characters long "
                        f"without {path.suffix or 'its extension'}; a case name (which must "
                        f"equal it) is at most {MAX_NAME}")


def load_case(path: str | Path) -> Case:
    """Parse and validate one case file.

    Raises
    ------
    CaseError
        With file, field and reason, for every malformed or inconsistent input.
    """
    path = Path(path)
    check_file_name(path)
    r = _Reader(str(path))
    try:
        raw = _read_bounded(path, r)  # read once: the hash below is of these bytes
        data = tomllib.loads(raw.decode("utf-8"))
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        r.fail("", "no such case file")
    except PermissionError:
        r.fail("", "cannot be read (permission denied)")
    except UnicodeDecodeError as e:
        r.fail("", f"not UTF-8 text ({e.reason})")
    except tomllib.TOMLDecodeError as e:
        r.fail("", f"not valid TOML: {e}")
    except RecursionError:
        r.fail("", f"nested too deeply (more than {MAX_DEPTH} levels)")
    if _depth(data, MAX_DEPTH) > MAX_DEPTH:
        r.fail("", f"nested too deeply (more than {MAX_DEPTH} levels of tables or arrays)")
    r.known(data, TOP_KEYS, "")

    name = r.name(data, "name", "")
    if name != path.stem:
        r.fail("name", f"{name!r} must equal the file name {short(path.stem)}")
    dim = r.get(data, "dimension", "")
    if type(dim) is not int or dim not in (2, 3):
        r.fail("dimension", f"must be the integer 2 or 3, got {short(dim)}")
    init = r.table(data, "initial", "", required=False)
    r.known(init, INITIAL_KEYS, "initial")
    reference_frame = "pose" not in init
    if dim == 3 and not reference_frame:
        r.fail("initial.pose", "3-D cases give every body point as its world position at "
               "t = 0; remove [initial.pose]")
    gravity = r.vector(r.get(data, "gravity", ""), "gravity", dim, "acceleration")
    duration = r.number(data, "duration", "", "time", positive=True)
    if duration > MAX_DURATION_S:
        r.fail("duration", f"{duration:g} s is beyond the budget of {MAX_DURATION_S:g} s")
    output_dt = r.number(data, "output_dt", "", "time", positive=True)
    if duration / output_dt > MAX_SAMPLES:
        r.fail("output_dt", f"{duration / output_dt:.3g} samples are beyond the budget of "
               f"{MAX_SAMPLES} (raise output_dt)")
    if output_dt > duration or abs(duration / output_dt - round(duration / output_dt)) > 1e-9:
        r.fail("output_dt", f"must divide duration {duration} s, got {output_dt} s")
    timeout = r.number(data, "timeout", "", "time", required=False, positive=True)
    if timeout is not None and not MIN_TIMEOUT_S <= timeout <= MAX_TIMEOUT_S:
        r.fail("timeout", f"must be between {MIN_TIMEOUT_S:g} s and {MAX_TIMEOUT_S:g} s (a "
               f"week), as --timeout, got {timeout:g} s")

    ground = {}
    gtable = r.table(data, "ground", "", required=False)
    r.known(gtable, GROUND_KEYS, "ground")
    for pname, value in r.table(gtable, "points", "ground", required=False).items():
        r.identifier(pname, "ground.points")
        ground[pname] = r.vector(value, f"ground.points.{pname}", dim, "length")

    bodies = tuple(_body(r, b, i, dim) for i, b in enumerate(_array(r, data, "bodies")))
    if reference_frame:  # a body point shared with the ground must be where the ground's is
        for i, b in enumerate(bodies):
            for pn, x in b.points.items():
                if pn in ground and np.linalg.norm(x - ground[pn]) > 1e-9:
                    r.fail(f"bodies[{i}] ({b.name}).points.{pn}",
                           f"is {x.tolist()}, but ground point {pn} is at "
                           f"{ground[pn].tolist()}")
    names = [b.name for b in bodies]
    for i, n in enumerate(names):
        if n == GROUND:
            r.fail(f"bodies[{i}].name", f"{GROUND!r} is reserved for the fixed frame")
        if names.index(n) != i:
            r.fail(f"bodies[{i}].name", f"duplicate body name {n!r}")
    points_of = {b.name: b.points for b in bodies} | {GROUND: ground}

    joints = tuple(_joint(r, j, i, dim, points_of)
                   for i, j in enumerate(_array(r, data, "joints", required=False)))
    jnames = [j.name for j in joints]
    for i, n in enumerate(jnames):
        if jnames.index(n) != i:
            r.fail(f"joints[{i}].name", f"duplicate joint name {n!r}")

    forces = tuple(_force(r, f, i, dim, points_of)
                   for i, f in enumerate(_array(r, data, "forces", required=False)))
    links = {}
    for key in ("rods", "springs"):
        for i, x in enumerate(_array(r, data, key, required=False)):
            link = _link(r, x, f"{key}[{i}]", key, dim, points_of, reference_frame)
            if link.name in links or link.name in names:
                r.fail(f"{key}[{i}].name", f"duplicate name {link.name!r}")
            links[link.name] = link
    rods = tuple(x for x in links.values() if isinstance(x, Rod))
    springs = tuple(x for x in links.values() if isinstance(x, Spring))

    drivers = tuple(_driver(r, d, i, names, points_of, dim)
                    for i, d in enumerate(_array(r, data, "drivers", required=False)))
    dnames = [d.name for d in drivers]
    for i, n in enumerate(dnames):
        if dnames.index(n) != i:
            r.fail(f"drivers[{i}].name", f"duplicate driver name {n!r}")
    channels = _channels(r, r.table(data, "channels", ""), names, points_of, joints, dnames,
                         dim, tuple(links))
    guess = {}
    for bname, pose in r.table(init, "pose", "initial", required=False).items():
        p = f"initial.pose.{bname}"
        if bname not in names:
            r.fail(p, f"unknown body {bname!r}; bodies are {', '.join(names)}")
        if not isinstance(pose, dict):
            r.fail(p, "must be a table {origin = [x, y], angle = ...}")
        r.known(pose, POSE_KEYS, p)
        guess[bname] = Pose(r.vector(r.get(pose, "origin", p), f"{p}.origin", dim, "length"),
                            r.number(pose, "angle", p, "angle", required=False, default=0.0))
    missing = [n for n in names if n not in guess]
    if reference_frame:
        guess = {n: Pose(np.zeros(dim), 0.0) for n in names}
    elif missing:
        r.fail("initial.pose", f"no initial pose for body {missing[0]!r}")
    fix = _channel_values(r, init, "fix", channels, ("angle", "position"))
    velocity = _channel_values(r, init, "velocity", channels, ("angle", "position"))

    engines, absent = {}, []
    for ename, spec in r.table(data, "engines", "", required=False).items():
        p = f"engines.{ename}"
        known = _engine_names()
        if ename not in known:
            from ..engines.registry import ENGINE_NAME
            close = difflib.get_close_matches(ename, known, n=1, cutoff=0.75)
            if close or not ENGINE_NAME.fullmatch(ename):  # a typo, or no engine's name
                r.fail(p, f"unknown engine {short(ename)}" + (
                    f" (did you mean {close[0]}?)" if close else "") + f"; engines are "
                    f"{', '.join(known)} (a plug-in engine must be installed: see "
                    "natcoord cases)")
        tol = {}
        for key, value in r.table(spec, "tolerance", p, required=False).items():
            if key not in CHANNEL_KINDS and key not in {c.name for c in channels}:
                r.fail(f"{p}.tolerance.{key}", "neither a channel name nor a channel kind")
            tol[key] = r.quantity(value, f"{p}.tolerance.{key}", _kind_dim(key, channels),
                                  positive=True)
        r.known(spec, ENGINE_KEYS, p)
        settings = r.table(spec, "settings", p, required=False)
        for field, reason in (_engine_settings(ename, settings, output_dt)
                              if ename in known else ()):
            r.fail(f"{p}.settings" + (f".{field}" if field else ""), reason)
        block = EngineSpec(
            settings=settings,
            tolerance=tol,
            reason=r.string(spec, "reason", p, required=bool(tol), default=""),
            unsupported=r.string(spec, "unsupported", p, required=False, default=""),
        )
        if ename in known:
            engines[ename] = block
        else:  # a plug-in not installed here: its block checked as far as it can be and
            absent.append(ename)  # not used (a case file shared with other machines loads)
    tags = r.get(data, "tags", "", required=False, default=[])
    if not isinstance(tags, list) or not all(isinstance(t, str) and len(t) <= MAX_NAME
                                             for t in tags):
        r.fail("tags", f"must be a list of short strings, got {short(tags)}")
    tags = tuple(tags)
    reactions = _reactions(r, r.table(data, "reactions", "", required=False), links, names)
    comparison = _comparison(r, r.table(data, "comparison", "", required=False), channels)
    benchmark = _benchmark(r, r.table(data, "benchmark", "", required=False), channels)
    case = Case(name=name, description=r.string(data, "description", ""), file=str(path),
                dimension=dim, gravity=gravity, duration=duration, output_dt=output_dt,
                ground=ground, bodies=bodies, joints=joints, forces=forces,
                guess=guess, fix=fix, velocity=velocity, channels=channels, engines=engines,
                absent_engines=tuple(absent),
                tags=tags, drivers=drivers, rods=rods, springs=springs, reactions=reactions,
                pose_tolerance=1e-6 if reference_frame else float("inf"),
                comparison=comparison, timeout=timeout, benchmark=benchmark,
                digest=hashlib.sha256(raw).hexdigest())
    _model_checks(r, case)
    return case


def _model_checks(r: _Reader, case: Case) -> None:
    """What the mechanism as a whole must be (:func:`natcoord.model.casemodel.check`): bodies
    whose points define their frames, at least one degree of freedom (drivers counted)."""
    from ..errors import ModelError
    from ..model.casemodel import check

    try:
        check(case)
    except ModelError as e:
        r.fail(e.field, e.reason)


def _engine_names() -> tuple[str, ...]:
    from ..engines import engine_names

    return engine_names()


def _engine_settings(engine: str, settings: dict, output_dt: float) -> list[tuple[str, str]]:
    """Problems of an engine's settings against the settings its adapter declares
    (:mod:`natcoord.engines.schema`; importing an adapter does not import its engine), and
    for an engine whose capabilities say its fixed step must divide the output interval
    (``output_steps``), a step given in the case file that does not divide ``output_dt``
    (s)."""
    from ..engines import adapter
    from ..engines.schema import problems

    mod = adapter(engine)
    out = problems(mod, settings)
    caps = getattr(mod, "CAPABILITIES", None)
    step = (caps.step or "dt") if caps is not None and caps.output_steps else ""
    h = settings.get(step) if step and not out else None
    if isinstance(h, (int, float)) and not isinstance(h, bool) and h > 0:
        k = output_dt / h
        if abs(k - round(k)) > 1e-9 * max(1.0, k) or round(k) < 1:
            out.append((step, f"{h:g} s must divide the output interval output_dt = "
                       f"{output_dt:g} s (a whole number of steps per sample)"))
    return out


def _comparison(r: _Reader, table: dict, channels) -> dict:
    """``[comparison] singular = {channel, angles, within}``: force channels are not compared
    on samples where the reference's angle ``channel`` is within ``within`` of one of
    ``angles`` (modulo 360 deg): singular positions, where rigid-body forces diverge."""
    r.known(table, {"singular"}, "comparison")
    if "singular" not in table:
        return {}
    p = "comparison.singular"
    spec = r.table(table, "singular", "comparison")
    r.known(spec, {"channel", "angles", "within"}, p)
    ch = r.string(spec, "channel", p)
    if ch not in {c.name for c in channels if c.kind == "angle"}:
        r.fail(f"{p}.channel", f"must name an angle channel, got {ch!r}")
    angles = r.get(spec, "angles", p)
    if not isinstance(angles, list) or not angles:
        r.fail(f"{p}.angles", "must be a non-empty list of angles")
    return {"singular": {
        "channel": ch,
        "angles": [r.quantity(a, f"{p}.angles[{k}]", "angle") for k, a in enumerate(angles)],
        "within": r.number(spec, "within", p, "angle", positive=True)}}


BENCHMARK_ERRORS = ("max_abs", "final_abs")


def _benchmark(r: _Reader, table: dict, channels) -> dict:
    """``[benchmark] channels, precision, error, source``: the output a published benchmark
    scores (channels of this case, all of one kind), the precision it asks for (in their
    unit) and how its error is taken: max |run - reference| over every output sample
    (``max_abs``) or at the last sample (``final_abs``)."""
    if not table:
        return {}
    r.known(table, {"channels", "precision", "error", "source"}, "benchmark")
    names = r.get(table, "channels", "benchmark")
    if (not isinstance(names, list) or not names
            or not all(isinstance(n, str) for n in names)):
        r.fail("benchmark.channels", f"must be a non-empty list of channel names, got "
               f"{short(names)}")
    kinds = {c.name: c.kind for c in channels}
    for k, n in enumerate(names):
        if n not in kinds:
            r.fail(f"benchmark.channels[{k}]", f"unknown channel {short(n)}; channels are "
                   f"{', '.join(kinds)}")
        if n in names[:k]:
            r.fail(f"benchmark.channels[{k}]", f"{short(n)} is listed twice")
    dims = {_kind_dim(n, channels) for n in names}
    if len(dims) > 1:
        r.fail("benchmark.channels", f"must share one unit (one precision), got "
               f"{', '.join(sorted(dims))}")
    return {"channels": tuple(names),
            "precision": r.number(table, "precision", "benchmark", dims.pop(), positive=True),
            "error": r.string(table, "error", "benchmark", required=False, default="max_abs",
                              choices=BENCHMARK_ERRORS),
            "source": r.string(table, "source", "benchmark")}


def _force(r: _Reader, f: dict, i: int, dim: int, points_of: dict) -> Force:
    p = f"forces[{i}]"
    r.known(f, FORCE_KEYS, p)
    ftype = r.string(f, "type", p, choices=("torque", "force"))
    body = r.string(f, "body", p)
    if body not in points_of or body == GROUND:
        r.fail(f"{p}.body", f"unknown body {body!r}; bodies are "
               f"{', '.join(b for b in points_of if b != GROUND)}")
    frame = r.string(f, "frame", p, required=False, default="world", choices=LOAD_FRAMES)
    if ftype == "torque":
        value = (r.number(f, "value", p, "torque") if dim == 2 else
                 r.vector(r.get(f, "value", p), f"{p}.value", 3, "torque"))
        return Force(ftype, body, value, frame="world" if dim == 2 else frame)
    if frame == "body" and dim == 2:
        r.fail(f"{p}.frame", "a body-fixed force (frame = \"body\") is 3-D only; give the "
               "force in world axes")
    point = r.string(f, "point", p)
    if point not in points_of[body]:
        r.fail(f"{p}.point", f"body {body!r} has no point {point!r}")
    return Force(ftype, body, r.vector(r.get(f, "value", p), f"{p}.value", dim, "force"), point,
                 frame)


def _link(r: _Reader, x: dict, p: str, key: str, dim: int, points_of: dict,
          reference_frame: bool) -> Rod | Spring:
    """A ``[[rods]]`` or ``[[springs]]`` entry: two body points, length at t = 0 (a spring's
    rest length: its ``length`` when given)."""
    name = r.name(x, "name", p)
    p = f"{p} ({name})"
    allowed = {"name", "ends"} | ({"stiffness", "damping", "length"} if key == "springs"
                                  else set())
    r.known(x, allowed, p)
    if not reference_frame:
        r.fail(p, f"{key} need body points given as world positions at t = 0 "
               "(a case without [initial.pose])")
    ends = r.get(x, "ends", p)
    if not (isinstance(ends, list) and len(ends) == 2 and all(
            isinstance(e, list) and len(e) == 2 and all(isinstance(s, str) for s in e)
            for e in ends)):
        r.fail(f"{p}.ends", f"must be [[body, point], [body, point]], got {ends!r}")
    xs = []
    for body, point in ends:
        if body not in points_of:
            r.fail(f"{p}.ends", f"unknown body {body!r}; bodies are {', '.join(points_of)}")
        if point not in points_of[body]:
            r.fail(f"{p}.ends", f"body {body!r} has no point {point!r}")
        xs.append(points_of[body][point])
    if ends[0][0] == ends[1][0]:
        r.fail(f"{p}.ends", "both ends are on the same body")
    length = _norm(xs[1] - xs[0])
    if length < 1e-9:
        r.fail(f"{p}.ends", "the two ends coincide at t = 0")
    ends_t = ((ends[0][0], ends[0][1]), (ends[1][0], ends[1][1]))
    if key == "rods":
        return Rod(name, ends_t, length)
    k = r.number(x, "stiffness", p, "stiffness", positive=True)
    c = r.number(x, "damping", p, "damping", required=False, default=0.0)
    if c < 0:
        r.fail(f"{p}.damping", f"must be >= 0, got {c}")
    # rest length: given, or the distance at t = 0 (unstretched)
    rest = r.number(x, "length", p, "length", required=False, default=length, positive=True)
    return Spring(name, ends_t, k, c, rest)


def _reactions(r: _Reader, table: dict, links: dict, bodies) -> dict[str, dict]:
    """``[reactions.<method>]``: natcoord's reaction methods; ``stiffness`` weights rows."""
    out = {}
    for method, spec in table.items():
        p = f"reactions.{shown(method)}"
        if reaction_method(method) is None:  # a typo used to run as a weighted method
            r.fail(p, f"unknown method; expected {', '.join(REACTION_METHODS)}"
                   f"{_did_you_mean(method, REACTION_METHODS)}")
        r.identifier(method, p)  # weighted_<label> becomes part of a CSV column's name
        if not isinstance(spec, dict):
            r.fail(p, "must be a table")
        r.known(spec, {"stiffness"}, p)
        if "stiffness" in spec and reaction_method(method) != "weighted":
            r.fail(f"{p}.stiffness", "only a weighted method (weighted or weighted_<label>) "
                   "takes stiffness")
        stiffness = {}
        for name, value in r.table(spec, "stiffness", p, required=False).items():
            f = f"{p}.stiffness.{name}"
            if name in links:
                stiffness[name] = r.quantity(value, f, "stiffness", positive=True)
            elif name in bodies:
                try:
                    stiffness[name] = r.quantity(value, f, "torsional stiffness", positive=True)
                except CaseError:
                    stiffness[name] = r.quantity(value, f, "stiffness", positive=True)
            else:
                r.fail(f, f"neither a rod, a spring nor a body: {name!r}")
        out[method] = {"stiffness": stiffness}
    return out


def _kind_dim(key: str, channels) -> str:
    kind = key if key in CHANNEL_KINDS else next(c.kind for c in channels if c.name == key)
    return {"angle": "angle", "position": "length", "velocity": "velocity",
            "reaction": "force", "energy": "energy", "acceleration": "acceleration",
            "driver": "torque", "axial": "force", "combination": "force",
            "loop_gap": "length", "angular_velocity": "angular velocity",
            "angular_momentum": "angular momentum", "momentum": "momentum",
            "vector_angle": "angle", "angular_acceleration": "angular acceleration"}[kind]


def _array(r: _Reader, data: dict, key: str, *, required=True) -> list[dict]:
    v = r.get(data, key, "", required=required, default=[])
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        r.fail(key, f"must be an array of tables ([[{key}]]), got {type(v).__name__}")
    if required and not v:
        r.fail(key, "must not be empty")
    return v


def _body(r: _Reader, b: dict, i: int, dim: int) -> Body:
    p = f"bodies[{i}]"
    name = r.name(b, "name", p)
    p = f"bodies[{i}] ({name})"
    r.known(b, BODY_KEYS, p)
    kind = r.string(b, "kind", p, choices=BODY_KINDS)
    mass = r.number(b, "mass", p, "mass", positive=True)
    pts = r.table(b, "points", p)
    points = {r.identifier(k, f"{p}.points"): r.vector(v, f"{p}.points.{k}", dim, "length")
              for k, v in pts.items()}
    need = 1 if kind == "particle" else 2
    if len(points) < need:
        r.fail(f"{p}.points", f"a {kind} needs at least {need} named point(s)")
    ends = None
    if kind == "particle":
        if len(points) != 1:
            r.fail(f"{p}.points", "a particle has exactly one point")
        com, inertia = next(iter(points.values())), 0.0 if dim == 2 else np.zeros((3, 3))
    else:
        if np.linalg.norm(list(points.values())[1] - list(points.values())[0]) < 1e-9:
            r.fail(f"{p}.points", "the first two points coincide; they define the body's axis")
        if kind == "uniform_rod":
            ends = r.get(b, "ends", p, required=False, default=list(points)[:2])
            if not isinstance(ends, list) or len(ends) != 2 or any(
                    not isinstance(e, str) or e not in points for e in ends):
                r.fail(f"{p}.ends", f"must name two of the body's points, got {short(ends)}")
            ends = tuple(ends)
            a, c = points[ends[0]], points[ends[1]]
            length = _norm(c - a)
            if length < 1e-9:
                r.fail(f"{p}.ends", "the two ends coincide")
            com = (a + c) / 2
            if dim == 2:
                inertia = mass * length**2 / 12
            else:
                e = (c - a) / length
                inertia = mass * length**2 / 12 * (np.eye(3) - np.outer(e, e))
        else:
            com = r.vector(r.get(b, "com", p), f"{p}.com", dim, "length")
            inertia = _inertia(r, r.get(b, "inertia", p), f"{p}.inertia", dim)
    return Body(name, kind, mass, points, com, inertia, ends)


def _inertia(r: _Reader, value, field: str, dim: int):
    """2-D: a moment (kg m^2, >= 0); 3-D: a symmetric positive semi-definite 3x3 tensor."""
    if dim == 2:
        x = r.quantity(value, field, "inertia")
        if x < 0:
            r.fail(field, f"must be >= 0, got {x}")
        return x
    if not (isinstance(value, list) and len(value) == 3):
        r.fail(field, f"must be a 3x3 tensor [[..], [..], [..]] (kg m^2), got {value!r}")
    J = np.array([r.vector(row, f"{field}[{k}]", 3, "inertia") for k, row in enumerate(value)])
    if np.abs(J - J.T).max() > 1e-12 * max(1.0, np.abs(J).max()):
        r.fail(field, "must be symmetric")
    ev = np.linalg.eigvalsh(J)
    if ev[0] < -1e-12 * max(1.0, ev[-1]):
        r.fail(field, f"must be positive semi-definite (eigenvalues {ev.round(6).tolist()})")
    if ev[0] + ev[1] < ev[2] - 1e-9 * max(1.0, ev[-1]):
        r.fail(field, "violates the triangle inequality of principal moments")
    return J


def _joint(r: _Reader, j: dict, i: int, dim: int, points_of: dict) -> Joint:
    p = f"joints[{i}]"
    name = r.name(j, "name", p)
    p = f"joints[{i}] ({name})"
    jtype = r.string(j, "type", p, choices=JOINT_TYPES)
    bodies = r.get(j, "bodies", p)
    if not (isinstance(bodies, list) and len(bodies) == 2
            and all(isinstance(x, str) for x in bodies)):
        r.fail(f"{p}.bodies", f"must be two body names, got {bodies!r}")
    if bodies[0] == bodies[1]:
        r.fail(f"{p}.bodies", f"a joint needs two different bodies, got {bodies!r}")
    for b in bodies:
        if b not in points_of:
            r.fail(f"{p}.bodies", f"unknown body {b!r}; bodies are {', '.join(points_of)}")
    pts = r.get(j, "points", p)
    if not (isinstance(pts, list) and len(pts) == 2 and all(isinstance(x, str) for x in pts)):
        r.fail(f"{p}.points", f"must be two point names (one on each body), got {pts!r}")
    for b, pt in zip(bodies, pts, strict=True):
        if pt not in points_of[b]:
            r.fail(f"{p}.points", f"body {b!r} has no point {pt!r}; it has "
                   f"{', '.join(points_of[b]) or 'none'}")
    r.known(j, JOINT_KEYS, p)
    if dim == 2 and jtype not in PLANAR_JOINTS:
        r.fail(f"{p}.type", f"{jtype!r} joints need a 3-D case; a 2-D case has "
               f"{' and '.join(PLANAR_JOINTS)} joints")
    if jtype == "revolute" and dim == 2 and "axis" in j:
        r.fail(f"{p}.axis", "a 2-D revolute turns about z; remove the axis")
    if jtype != "universal" and "axis2" in j:
        r.fail(f"{p}.axis2", "only a universal joint has a second axis")
    axis = axis2 = None
    if jtype != "spherical" and not (jtype == "revolute" and dim == 2):
        axis = _unit(r, r.get(j, "axis", p), f"{p}.axis", dim)
    if jtype == "universal":
        axis2 = _unit(r, r.get(j, "axis2", p), f"{p}.axis2", dim)
        if abs(axis @ axis2) > 1e-9:
            r.fail(f"{p}.axis2", f"must be perpendicular to axis at t = 0 (cosine "
                   f"{axis @ axis2:.3g})")
    return Joint(name, jtype, (bodies[0], bodies[1]), (pts[0], pts[1]), axis, axis2)


def _unit(r: _Reader, value, field: str, dim: int) -> np.ndarray:
    """A direction (dim,) normalised to a unit vector."""
    axis = r.vector(value, field, dim, "length")
    norm = _norm(axis)
    if norm < 1e-12:
        r.fail(field, "must not be zero")
    return axis / norm


def _norm(x) -> float:
    """|x| rounded alike on every machine (squares and an exactly rounded sum): numpy's norm
    sums through BLAS, whose kernels (one per CPU) round differently; a rod's length then
    moved by an ulp between machines, and with it the digest of the mechanism a reference
    is stored for (stale on one machine, current on another)."""
    return math.sqrt(math.fsum(float(v) * float(v) for v in x))


def _driver(r: _Reader, d: dict, i: int, bodies, points_of, dim: int) -> Driver:
    p = f"drivers[{i}]"
    name = r.name(d, "name", p)
    p = f"drivers[{i}] ({name})"
    r.known(d, DRIVER_KEYS, p)
    dtype = r.string(d, "type", p, choices=DRIVER_TYPES)
    body = r.string(d, "body", p)
    if body not in bodies:
        r.fail(f"{p}.body", f"unknown body {body!r}; bodies are {', '.join(bodies)}")
    if dtype == "angle":
        if dim == 3:
            r.fail(f"{p}.type", "an angle driver turns a body in the plane (2-D cases); in "
                   "3-D drive a point coordinate (type = \"coordinate\")")
        dims = ("angle", "angular velocity", "angular acceleration")
        v0 = r.number(d, "angle0", p, dims[0])
        point = axis = None
    else:
        dims = ("length", "velocity", "acceleration")
        v0 = r.number(d, "value0", p, dims[0])
        point = r.string(d, "point", p)
        if point not in points_of[body]:
            r.fail(f"{p}.point", f"body {body!r} has no point {point!r}")
        axis = r.string(d, "axis", p, choices=("x", "y", "z")[:dim])
    rate = r.number(d, "rate", p, dims[1], required=False, default=0.0)
    accel = r.number(d, "accel", p, dims[2], required=False, default=0.0)
    return Driver(name, dtype, body, v0, rate, accel, point, axis)


def _channels(r, table: dict, bodies, points_of, joints, drivers=(), dim: int = 2,
              links=()) -> tuple[Channel, ...]:
    out = []
    jnames = [j.name for j in joints]
    axes = ("x", "y", "z")[:dim]
    for name, c in table.items():
        r.identifier(name, "channels")
        p = f"channels.{name}"
        if name in RESERVED_CHANNELS:
            r.fail(p, f"{name!r} is reserved for the time column of result files; "
                   "name the channel otherwise")
        if not isinstance(c, dict):
            r.fail(p, "must be a table {kind = ..., ...}")
        r.known(c, CHANNEL_KEYS, p)
        kind = r.string(c, "kind", p, choices=CHANNEL_KINDS)
        body = point = joint = axis = driver = rod = points = relative_to = None
        plane, of, work, gap_joints = "xy", (), False, ()
        if kind == "loop_gap":  # joints = [...]: the joints it measures (default every one)
            names = r.get(c, "joints", p, required=False, default=list(jnames))
            if (not isinstance(names, list) or not names
                    or not all(isinstance(n, str) and n in jnames for n in names)):
                r.fail(f"{p}.joints", f"must be a non-empty list of joint names; joints are "
                       f"{', '.join(jnames) or 'none'}, got {short(names)}")
            gap_joints = tuple(names)
        frame, about = "world", ()
        if kind in ("angular_velocity", "angular_acceleration", "angular_momentum", "momentum"):
            body = r.string(c, "body", p, required=kind.startswith("angular_") and
                            kind != "angular_momentum")
            if body is not None and body not in bodies:
                r.fail(f"{p}.body", f"unknown body {body!r}; bodies are {', '.join(bodies)}")
            axis = r.string(c, "axis", p, choices=axes if kind == "momentum"
                            else ("x", "y", "z") if dim == 3 else ("z",))
        if kind in ("angular_velocity", "angular_acceleration"):
            frame = r.string(c, "frame", p, required=False, default="world",
                             choices=("world", "body"))
        vectors = ()
        if kind == "vector_angle":  # vectors = [[body, p, q], [body, p, q]]
            v = r.get(c, "vectors", p)
            if not (isinstance(v, list) and len(v) == 2 and all(
                    isinstance(x, list) and len(x) == 3 and all(isinstance(n, str) for n in x)
                    and x[0] in points_of and x[1] in points_of[x[0]]
                    and x[2] in points_of[x[0]] and x[1] != x[2] for x in v)):
                r.fail(f"{p}.vectors", "must be two [body, p, q] lists (r_q - r_p, two "
                       f"different points of that body or of ground), got {short(v)}")
            vectors = tuple(tuple(x) for x in v)
        if kind == "angular_momentum":
            about = r.get(c, "about", p, required=False, default=[0.0] * dim)
            if about != "com":
                about = tuple(r.vector(about, f"{p}.about", dim, "length"))
        if kind == "energy":  # work = true: the energy balance (minus non-conservative work)
            work = r.get(c, "work", p, required=False, default=False)
            if not isinstance(work, bool):
                r.fail(f"{p}.work", f"must be true or false, got {short(work)}")
        if kind in ("angle", "position", "velocity", "acceleration"):
            body = r.string(c, "body", p)
            if body not in bodies:
                r.fail(f"{p}.body", f"unknown body {body!r}; bodies are {', '.join(bodies)}")
        if kind in ("position", "velocity", "acceleration"):
            point = r.string(c, "point", p)
            if point not in points_of[body]:
                r.fail(f"{p}.point", f"body {body!r} has no point {point!r}")
            axis = r.string(c, "axis", p, choices=axes)
        if kind == "angle":
            pts = r.get(c, "points", p, required=dim == 3)
            if pts is not None:
                if not (isinstance(pts, list) and len(pts) == 2
                        and all(isinstance(x, str) and x in points_of[body] for x in pts)):
                    r.fail(f"{p}.points", f"must name two points of body {body!r}, got {pts!r}")
                points = (pts[0], pts[1])
            plane = r.string(c, "plane", p, required=False, default="xy",
                             choices=tuple(PLANES) if dim == 3 else ("xy",))
            relative_to = r.string(c, "relative_to", p, required=False)
            if relative_to is not None and relative_to not in {
                    x.name for x in out if x.kind == "angle" and x.plane == plane}:
                r.fail(f"{p}.relative_to", f"must name an angle channel in plane {plane} "
                       f"defined above this one, got {relative_to!r}")
        if kind == "reaction":
            joint = r.string(c, "joint", p)
            if joint not in jnames:
                r.fail(f"{p}.joint", f"unknown joint {joint!r}; joints are {', '.join(jnames)}")
            axis = r.string(c, "axis", p, choices=(*axes, "normal", "along", "across"))
            jt = joints[jnames.index(joint)]
            if axis == "normal" and (jt.type != "prismatic" or dim != 2):
                r.fail(f"{p}.axis", f"'normal' needs a 2-D prismatic joint; {joint!r} is a "
                       f"{dim}-D {jt.type} joint")
            if axis in ("along", "across") and (
                    dim != 3 or jt.type not in ("prismatic", "cylindrical", "revolute")):
                r.fail(f"{p}.axis", f"{axis!r} needs a 3-D prismatic, cylindrical or revolute "
                       f"joint (one with an axis); {joint!r} is a {dim}-D {jt.type} joint")
        if kind == "driver":
            driver = r.string(c, "driver", p)
            if driver not in drivers:
                r.fail(f"{p}.driver", f"unknown driver {driver!r}; drivers are "
                       f"{', '.join(drivers) or 'none'}")
        if kind == "axial":
            rod = r.string(c, "rod", p)
            if rod not in links:
                r.fail(f"{p}.rod", f"unknown rod or spring {rod!r}; they are "
                       f"{', '.join(links) or 'none'}")
        if kind == "combination":
            terms = r.table(c, "of", p)
            known = {x.name: x for x in out}
            for t, coef in terms.items():
                if t not in known or known[t].kind not in ("reaction", "axial"):
                    r.fail(f"{p}.of.{t}", "must name a reaction or axial channel defined "
                           "above this one")
                if isinstance(coef, bool) or not isinstance(coef, (int, float)):
                    r.fail(f"{p}.of.{t}", f"must be a number, got {coef!r}")
                # TOML has nan, inf and integers past a float: a NaN column ran "ok"
                if not abs(coef) <= sys.float_info.max:
                    r.fail(f"{p}.of.{t}", f"must be finite, got {short(coef)}")
            if not terms:
                r.fail(f"{p}.of", "must not be empty")
            of = tuple((t, float(v)) for t, v in terms.items())
        out.append(Channel(name, kind, body, point, joint, axis, driver, rod, points, plane,
                           of, relative_to, work, gap_joints, frame, about, vectors))
    if not out:
        r.fail("channels", "must define at least one channel")
    return tuple(out)


def _channel_values(r, init: dict, key: str, channels, kinds) -> dict[str, float]:
    by_name = {c.name: c for c in channels}
    out = {}
    for name, value in r.table(init, key, "initial", required=False).items():
        p = f"initial.{key}.{name}"
        if name not in by_name:
            r.fail(p, f"unknown channel {name!r}; channels are {', '.join(by_name)}")
        ch = by_name[name]
        if ch.relative_to is not None:
            r.fail(p, f"channel {name!r} is an angle relative to {ch.relative_to!r}; set the "
                   "initial state with absolute angle or position channels")
        if ch.kind not in kinds:
            r.fail(p, f"channel {name!r} is a {ch.kind}; only {' or '.join(kinds)} channels "
                   "can set the initial state")
        dim = {"angle": "angle", "position": "length"}[ch.kind]
        if key == "velocity":
            dim = {"angle": "angular velocity", "position": "velocity"}[ch.kind]
        out[name] = r.quantity(value, p, dim)
    return out


def load_cases(directory: str | Path = "cases") -> dict[str, Case]:
    """Load every ``*.toml`` in ``directory``, keyed by case name (sorted)."""
    return {p.stem: load_case(p) for p in sorted(Path(directory).glob("*.toml"))}
