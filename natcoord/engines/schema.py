"""Engine settings as declared data: what an engine reads from ``[engines.<name>].settings``.

Every adapter module declares ``SETTINGS``, a tuple of :class:`Setting` (name, type, range
or choices, unit, default, meaning), and may define ``check_settings(settings) -> list of
(field, reason)`` for rules that tie settings together (natcoord's solver combinations).
:func:`check` validates a case's settings against a schema, :func:`problems` against an
adapter; the case loader calls :func:`problems` for every engine of a case, so an unknown
key (a typo), a wrong type or a value out of range is refused when the case is loaded. A
plug-in engine declares its settings the same way.

Types (TOML values): ``number`` (an integer or a float, finite; never a boolean),
``integer``, ``boolean``, ``choice`` (one of ``choices``, strings), ``numbers`` (a list of
``length`` numbers, each within the range) and ``table`` (a table of the settings
``fields``). A range is JSON Schema's: ``minimum``/``maximum`` (inclusive) and
``exclusive_minimum``/``exclusive_maximum``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

TYPES = ("number", "integer", "boolean", "choice", "numbers", "table")
SETTING_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
C_INT_MAX = 2**31 - 1  # the largest count an engine reads into a C int (MuJoCo's XML, ...)


@dataclass(frozen=True)
class Setting:
    """One engine setting: what a case file may give and what it means.

    ``default`` is the value the engine uses when the case gives none (``None``: the
    setting is off; ``meaning`` says what happens then); ``unit`` the SI unit of a number
    (``""``: dimensionless).
    """

    name: str
    type: str
    default: object
    meaning: str
    unit: str = ""
    minimum: float | None = None
    exclusive_minimum: float | None = None
    maximum: float | None = None
    exclusive_maximum: float | None = None
    choices: tuple[str, ...] = ()
    length: int | None = None
    fields: tuple[Setting, ...] = ()

    def __post_init__(self):
        if self.type not in TYPES:
            raise ValueError(f"setting {self.name}: type {self.type!r} is not one of "
                             f"{', '.join(TYPES)}")
        if (self.type == "choice") != bool(self.choices):
            raise ValueError(f"setting {self.name}: choices go with type 'choice' only")
        if (self.type == "table") != bool(self.fields):
            raise ValueError(f"setting {self.name}: fields go with type 'table' only")
        if not isinstance(self.name, str) or not SETTING_NAME.fullmatch(self.name):
            raise ValueError(f"setting {short(self.name)}: a setting's name is letters, "
                             "digits and _, from a letter or _ (a case file's key)")
        bounds = (self.minimum, self.exclusive_minimum, self.maximum, self.exclusive_maximum)
        if not all(x is None or _is_number(x) for x in bounds):
            return  # a plug-in's mistyped bound: its discovery says so (not JSON numbers)
        lo = max((x for x in bounds[:2] if x is not None), default=-math.inf)
        hi = min((x for x in bounds[2:] if x is not None), default=math.inf)
        if not lo <= hi or (lo == hi and None in (self.minimum, self.maximum)):
            raise ValueError(f"setting {self.name}: no value is {self.range()}")
        if self.default is not None and self.type != "table":  # the engine's own value
            # must be one a case may give (a table's fields are checked where it is read)
            why = _value(self, self.default, self.name)
            if why:
                raise ValueError(f"setting {self.name}: its default {short(self.default)} "
                                 f"{why[0][1]}")

    def range(self) -> str:
        """The range as text: '> 0', '>= 2', 'in [0, 1]', '' when unbounded (an integer's
        bounds in full)."""
        def f(x):
            return str(x) if self.type == "integer" and float(x).is_integer() else f"{x:g}"
        lo = (f"[{f(self.minimum)}" if self.minimum is not None else
              f"({f(self.exclusive_minimum)}" if self.exclusive_minimum is not None else None)
        hi = (f"{f(self.maximum)}]" if self.maximum is not None else
              f"{f(self.exclusive_maximum)})" if self.exclusive_maximum is not None else None)
        if lo and hi:
            return f"in {lo}, {hi}"
        if lo:
            return (">= " if lo[0] == "[" else "> ") + lo[1:]
        if hi:
            return ("<= " if hi[-1] == "]" else "< ") + hi[:-1]
        return ""

    def describe(self) -> dict:
        """The declaration as plain data (JSON): name, type, range or choices, unit,
        default, meaning."""
        out = {"name": self.name, "type": self.type}
        for key in ("minimum", "exclusive_minimum", "maximum", "exclusive_maximum",
                    "length"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.choices:
            out["choices"] = list(self.choices)
        if self.range():
            out["range"] = self.range()
        out |= {"unit": self.unit, "default": self.default, "meaning": self.meaning}
        if self.fields:
            out["fields"] = [f.describe() for f in self.fields]
        return out


def short(v, n: int = 60) -> str:
    """repr of a value, cut to n characters (a 50 000-character name is not echoed); the
    count given is the string's own length (its repr's quotes and escapes not counted)."""
    s = repr(v)
    return s if len(s) <= n else f"{s[:n]}... ({len(v if isinstance(v, str) else s)} characters)"


def shown(key) -> str:
    """A key as it may appear in a message: itself when short and printable, else cut."""
    return key if len(str(key)) <= 60 and str(key).isprintable() else short(key)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _unit(s: Setting) -> str:
    return f" ({s.unit})" if s.unit else ""


def _in_range(s: Setting, x: float) -> bool:
    return ((s.minimum is None or x >= s.minimum)
            and (s.exclusive_minimum is None or x > s.exclusive_minimum)
            and (s.maximum is None or x <= s.maximum)
            and (s.exclusive_maximum is None or x < s.exclusive_maximum))


def _number(s: Setting, v, integer: bool = False) -> str | None:
    """Why ``v`` is not a valid value of the number setting ``s`` (None: it is)."""
    kind = "an integer" if integer else "a number"
    if not _is_number(v) or (integer and not isinstance(v, int)):
        return f"must be {kind}{_unit(s)}, got {short(v)}"
    if not math.isfinite(v):
        return f"must be finite, got {v!r}"
    if not _in_range(s, v):
        return f"must be {s.range()}{_unit(s)}, got {v!r}"
    return None


def _value(s: Setting, v, field: str) -> list[tuple[str, str]]:
    """Problems of one value ``v`` of setting ``s`` at ``field``."""
    why = None
    if s.type in ("number", "integer"):
        why = _number(s, v, s.type == "integer")
    elif s.type == "boolean":
        if not isinstance(v, bool):
            why = f"must be true or false, got {short(v)}"
    elif s.type == "choice":
        if not isinstance(v, str) or v not in s.choices:
            why = f"must be one of {', '.join(s.choices)}, got {short(v)}"
    elif s.type == "numbers":
        if not isinstance(v, (list, tuple)) or (s.length is not None and len(v) != s.length):
            n = f"{s.length} " if s.length is not None else ""
            why = f"must be a list of {n}numbers, got {short(v)}"
        else:
            for k, x in enumerate(v):
                sub = _number(s, x)
                if sub:
                    return [(f"{field}[{k}]", sub)]
    elif s.type == "table":
        if not isinstance(v, dict):
            why = f"must be a table of settings, got {short(v)}"
        else:
            return check(v, s.fields, field)
    return [(field, why)] if why else []


def check(settings, schema: tuple[Setting, ...], prefix: str = "") -> list[tuple[str, str]]:
    """Problems of ``settings`` (a table from a case file) against ``schema``: a list of
    (field, reason), empty when every key is known and every value valid. ``field`` is
    the key (``prefix.key`` under a prefix); an unknown key names the known ones."""
    if not isinstance(settings, dict):  # the field is the table itself ("" at the top)
        return [(prefix, f"must be a table of settings, got {short(settings)}")]
    by_name = {s.name: s for s in schema}
    out = []
    for key, v in settings.items():
        field = f"{prefix}.{key}" if prefix else str(key)
        if key not in by_name:
            out.append((f"{prefix}.{shown(key)}" if prefix else shown(key),
                        "unknown setting; known: " + (", ".join(by_name) or "none")))
            continue
        out += _value(by_name[key], v, field)
    return out


def problems(adapter, settings) -> list[tuple[str, str]]:
    """Problems of an engine's ``settings`` against its adapter's declared ``SETTINGS``
    and, when the schema holds, the adapter's own ``check_settings`` (rules between
    settings; a plug-in's is called in a child process). A ``check_settings`` that raises,
    ends its process or returns anything but (field, reason) pairs of strings is one
    problem saying so (field ""); what it prints goes to standard error."""
    import contextlib
    import sys

    from .registry import BUILTIN, isolated

    out = check(settings, tuple(getattr(adapter, "SETTINGS", ())))
    if not out and hasattr(adapter, "check_settings"):
        try:
            if getattr(adapter, "NAME", None) in BUILTIN:
                with contextlib.redirect_stdout(sys.stderr):
                    got = adapter.check_settings(settings)
            else:  # a plug-in's code in a child process: it cannot end or hang the command
                said = isolated(adapter.__name__, "check_settings", settings)
                if said.why:
                    return [("", f"the engine's check_settings {said.why}")]
                if said.value is None:
                    return [("", f"the engine's check_settings returned {said.shown}, not a "
                             "list of (field, reason) pairs")]
                got = said.value
            out = list(got)
        except (Exception, SystemExit) as e:  # the adapter's bug, said in one line
            return [("", f"the engine's check_settings raised {type(e).__name__}: {e}")]
        if not all(isinstance(x, (tuple, list)) and len(x) == 2
                   and all(isinstance(y, str) for y in x) for x in out):
            return [("", f"the engine's check_settings returned {short(got)}, not a list "
                     "of (field, reason) pairs")]
        out = [tuple(x) for x in out]
    return out


def particle_inertia(per_kg: bool, note: str = "") -> Setting:
    """The setting every engine that needs a rotational inertia for a particle declares:
    1e-6 per axis, per kg of the particle's mass (m^2) or absolute (kg m^2); ``note`` says
    why the engine needs it."""
    what = ("rotational inertia given to a particle, per kg of its mass" if per_kg else
            "inertia about every axis given to a particle")
    return Setting("particle_inertia", "number", 1e-6, what + (f" ({note})" if note else ""),
                   "m^2" if per_kg else "kg m^2", exclusive_minimum=0.0)


def defaults(schema: tuple[Setting, ...]) -> dict:
    """The declared defaults, by name (what the engine uses where a case gives none)."""
    return {s.name: s.default for s in schema}


def describe(schema: tuple[Setting, ...]) -> list[dict]:
    """A schema as plain data (``natcoord cases --json``)."""
    return [s.describe() for s in schema]
