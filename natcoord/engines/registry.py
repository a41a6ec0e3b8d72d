"""Which engines there are: every adapter registered in the ``natcoord.engines`` entry-point
group, natcoord's own six first.

An entry point's name is the engine's name (in case files, ``--engines``, results) and its
value the adapter module (``natcoord.engines.mujoco_engine``; see
:class:`natcoord.engines.base.Adapter`). natcoord registers its built-in adapters the same
way in its ``pyproject.toml``; when natcoord's own metadata is missing (a source checkout on
``PYTHONPATH``, never installed), :data:`BUILTIN` registers them all the same. Order is
stable: the built-ins in :data:`BUILTIN`'s order, then the plug-ins by name.

A plug-in whose module fails to import (any exception, ``SystemExit`` too) or breaks the
contract (no ``NAME``, ``PACKAGE``, ``SETTINGS``, ``CAPABILITIES``, ``version`` or ``run``; a
``NAME`` other than its entry point's; ``CAPABILITIES`` not a
:class:`~natcoord.engines.capabilities.Capabilities`, ``SETTINGS`` not a tuple of
:class:`~natcoord.engines.schema.Setting`, or declarations that cannot be described as
JSON) is left out and listed in :attr:`Registry.problems` with the reason, and so is one
that takes a built-in's name: one broken plug-in never takes the suite down. What a
plug-in prints while it is imported goes to standard error, never into a command's output
(``cases --json``). Plug-ins are imported in a child process first (all in one, once per
command), so that one whose import ends its process (``os._exit``, a crash) or hangs is
listed with that, not obeyed by the command.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import importlib.metadata as md
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from types import ModuleType
from typing import NamedTuple

from .schema import short

GROUP = "natcoord.engines"

# name -> adapter module of natcoord's own engines, in the order tables list them
BUILTIN: dict[str, str] = {
    "natcoord": "natcoord.engines.natcoord_engine",
    "mujoco": "natcoord.engines.mujoco_engine",
    "pinocchio": "natcoord.engines.pinocchio_engine",
    "exudyn": "natcoord.engines.exudyn_engine",
    "dart": "natcoord.engines.dart_engine",
    "simbody": "natcoord.engines.simbody_engine",
    "drake": "natcoord.engines.drake_engine",
    "pybullet": "natcoord.engines.pybullet_engine",
}
REQUIRED = ("NAME", "PACKAGE", "SETTINGS", "CAPABILITIES", "version", "run")


@dataclass(frozen=True)
class Problem:
    """A registered engine that is left out: its name, entry point value and why."""

    name: str
    value: str
    error: str

    def line(self) -> str:
        return (f"engine plug-in {self.name!r} (entry point {GROUP}: {self.name} = "
                f"{self.value}) skipped: {self.error}")


@dataclass(frozen=True)
class Registry:
    """The engines that load (name -> adapter module path, in order) and the problems."""

    modules: dict[str, str]
    problems: tuple[Problem, ...] = field(default=())

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.modules)

    def builtin(self, name: str) -> bool:
        return BUILTIN.get(name) == self.modules.get(name)


def _entries() -> list[tuple[str, str]]:
    """(name, value) of every entry point in the group, duplicates (the same distribution
    seen twice on the path) once."""
    return list(dict.fromkeys((ep.name, ep.value) for ep in md.entry_points(group=GROUP)))


def _settings_error(schema, where: str = "SETTINGS") -> str:
    """Why ``schema`` is not a tuple of Setting (recursively, a table's ``fields`` too)."""
    from .schema import Setting

    if not isinstance(schema, tuple):
        return (f"its {where} is {short(schema)} ({type(schema).__name__}), not a tuple of "
                "natcoord.engines.schema.Setting")
    names = set()
    for s in schema:
        if not isinstance(s, Setting):
            return (f"its {where} holds {short(s)} ({type(s).__name__}), not a "
                    "natcoord.engines.schema.Setting")
        if not isinstance(s.name, str) or not s.name or s.name in names:
            return f"its {where} names a setting {short(s.name)}: not a new non-empty string"
        names.add(s.name)
        why = _settings_error(s.fields, f"setting {s.name!r}'s fields") if s.fields else ""
        if why:
            return why
    return ""


def _contract_error(name: str, module: ModuleType) -> str:
    """Why a plug-in's adapter module breaks the contract (:class:`natcoord.engines.base.
    Adapter`): a missing or mistyped declaration; "" when it holds."""
    from .capabilities import Capabilities
    from .schema import describe

    missing = [a for a in REQUIRED if not hasattr(module, a)]
    if missing:
        return f"the adapter module lacks {', '.join(missing)} (see natcoord.engines.base)"
    if module.NAME != name:
        return f"its NAME is {short(module.NAME)}, not the entry point's name {name!r}"
    if not isinstance(module.PACKAGE, str) or not module.PACKAGE:
        return f"its PACKAGE is {short(module.PACKAGE)}, not a package name (a string)"
    for fn in ("version", "run", "check_settings"):
        if hasattr(module, fn) and not callable(getattr(module, fn)):
            return f"its {fn} is {short(getattr(module, fn))}, not a function"
    caps = module.CAPABILITIES
    if not isinstance(caps, Capabilities):
        return (f"its CAPABILITIES is {short(caps)} ({type(caps).__name__}), not a "
                "natcoord.engines.capabilities.Capabilities")
    if caps.rules is not None and not callable(caps.rules):
        return f"its CAPABILITIES.rules is {short(caps.rules)}, not a function"
    if not isinstance(caps.step, str):
        return f"its CAPABILITIES.step is {short(caps.step)}, not a setting's name"
    why = _settings_error(module.SETTINGS)
    if why:
        return why
    named = {st.name for st in module.SETTINGS}
    for what, keys in (("step", [caps.step] if caps.step else []),
                       ("step_with", list(caps.step_with))):
        odd = [k for k in keys if k not in named]
        if odd:
            return (f"its CAPABILITIES.{what} names {', '.join(map(short, odd))}, not one "
                    "of its SETTINGS")
    try:  # what `natcoord cases --json` prints of it
        json.dumps({"capabilities": caps.summary(), "settings": describe(module.SETTINGS)},
                   allow_nan=False)
    except Exception as e:
        return (f"its declarations (CAPABILITIES, SETTINGS) cannot be described as JSON: "
                f"{type(e).__name__}: {e}")
    return ""


def _load(name: str, value: str) -> str:
    """Import a plug-in's adapter module and check its contract: "" when it loads, else
    why not. Whatever the plug-in raises (SystemExit too, not KeyboardInterrupt) is its
    own failure; what it prints goes to standard error."""
    with contextlib.redirect_stdout(sys.stderr):
        try:
            module = importlib.import_module(value.split(":")[0])
        except (Exception, SystemExit) as e:  # any failure of a plug-in is its own
            return f"import failed: {type(e).__name__}: {e}"
        try:
            return _contract_error(name, module)
        except (Exception, SystemExit) as e:  # a declaration whose reading raises
            return f"its declarations could not be read: {type(e).__name__}: {e}"


PROBE_TIMEOUT_S = 120.0  # for the imports of all plug-ins in the child process
_MARK = "natcoord-plugin-probe"


def _probe_child() -> None:
    """In the child process: :func:`_load` each (name, value) of argv[1] (JSON), marking on
    standard error where each plug-in's own output starts and writing a marked line with
    its answer to the real standard output as soon as it is known."""
    for name, value in json.loads(sys.argv[1]):
        print(f"{_MARK}\t{name}", file=sys.__stderr__, flush=True)
        try:
            why = _load(name, value)
        except KeyboardInterrupt:  # the plug-in's own: a user's reaches the command too
            why = "import failed: KeyboardInterrupt"
        print(f"{_MARK}\t{json.dumps([name, why])}", file=sys.__stdout__, flush=True)
    os._exit(0)  # what a plug-in left to run at exit is not the probe's business


def _ended(code: int, err: str) -> str:
    how = (f"signal {signal.Signals(-code).name}" if code < 0 and -code in
           signal.valid_signals() else f"exit status {code}")
    last = [ln for ln in err.splitlines() if ln.strip()]
    return f"importing it ended the process ({how})" + (f": {short(last[-1])}" if last else "")


def _by_plugin(err: str) -> dict[str, str]:
    """The child's standard error cut at its markers: name -> what followed it."""
    parts: dict[str, str] = {}
    name = ""
    for line in err.splitlines(keepends=True):
        if line.startswith(_MARK + "\t"):
            name = line.rstrip("\n").split("\t", 1)[1]
        elif name:
            parts[name] = parts.get(name, "") + line
    return parts


def _child(target: str, args: list[str], timeout_s: float) -> tuple[list, str, int | None]:
    """Run this module's ``target()`` in a child process with ``args`` (this process's
    import path, in a scratch folder of its own): (its answers, the JSON of each marked
    line it wrote to standard output; its standard error; its exit status, None when it
    did not finish within ``timeout_s``)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(os.path.abspath(p) for p in sys.path
                                                       if p)}
    code = [sys.executable, "-c", f"from natcoord.engines.registry import {target}; "
            f"{target}()", *args]
    try:  # in a scratch folder: what a plug-in writes in its current folder is dropped
        with tempfile.TemporaryDirectory(prefix="natcoord-plugin-") as tmp:
            p = subprocess.run(code, capture_output=True, env=env, stdin=subprocess.DEVNULL,
                               timeout=timeout_s, cwd=tmp)
        out, err, status = p.stdout, p.stderr, p.returncode
    except subprocess.TimeoutExpired as e:
        out, err, status = e.stdout or b"", e.stderr or b"", None
    answers = [json.loads(line.split("\t", 1)[1])
               for line in out.decode(errors="replace").splitlines()
               if line.startswith(_MARK + "\t")]
    return answers, err.decode(errors="replace"), status


def _probe(pairs: list[tuple[str, str]]) -> dict[str, str]:
    """name -> :func:`_load`'s answer for every plug-in, each imported in a child process
    (one for all, another after one that ends it): what their import does cannot end,
    hang or crash this process. What a plug-in that does not load printed there is passed
    on to standard error (one that loads prints again when imported here)."""
    found: dict[str, str] = {}
    while len(found) < len(pairs):
        todo = [(n, v) for n, v in pairs if n not in found]
        answers, err, status = _child("_probe_child", [json.dumps(todo)], PROBE_TIMEOUT_S)
        for name, why in answers:
            found[name] = why
        said = _by_plugin(err)
        culprit = next((n for n, _ in todo if n not in found), None)
        if culprit is not None:
            found[culprit] = (
                f"importing it did not finish within {PROBE_TIMEOUT_S:g} s" if status is None
                else _ended(status, said.get(culprit, "")))
        for name, _ in todo:
            if found.get(name) and said.get(name):
                sys.stderr.write(said[name])
    return found


ENGINE_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,39}")  # an engine's name: a file name
# (results/<case>/<engine>.csv), an item of --engines a,b, plain text in a table


@cache
def discover() -> Registry:
    """Discover the engines once per process (importing an adapter module does not import
    its engine)."""
    found: dict[str, str] = {}
    problems: list[Problem] = []
    for name, value in _entries():
        if not ENGINE_NAME.fullmatch(name):  # it names result files and --engines items
            problems.append(Problem(name, value, f"{short(name)} is not an engine name: "
                                    "use letters, digits and _ (at most 40, starting with a "
                                    "letter)"))
        elif name in BUILTIN and value != BUILTIN[name]:
            problems.append(Problem(name, value, f"{name!r} is a built-in engine's name; "
                                    "a plug-in must take another name"))
        elif name in found and found[name] != value:
            problems.append(Problem(name, value, f"another entry point already registers "
                                    f"{name!r} (= {found[name]})"))
        elif name not in BUILTIN:
            found[name] = value
    plugins = {}
    probed = _probe([(n, found[n]) for n in sorted(found)]) if found else {}
    for name in sorted(found):
        why = probed[name] or _load(name, found[name])
        if why:
            problems.append(Problem(name, found[name], why))
        else:
            plugins[name] = found[name].split(":")[0]
    return Registry({**BUILTIN, **plugins}, tuple(problems))


CALL_TIMEOUT_S = 120.0  # for a plug-in's function called in a child process


class Answer(NamedTuple):
    """What a plug-in's function gave in a child process (:func:`isolated`): ``value``
    (its JSON value; None when it gave none or none JSON can carry) and ``shown`` (its
    repr, cut), or ``why`` it gave none, completing "the engine's version() ...": "raised
    T: m", "ended the process (...)", "did not finish within ..."; ``missing``: it raised
    ImportError (its package is not installed)."""

    value: object = None
    shown: str = ""
    why: str | None = None
    missing: bool = False


def _call_child() -> None:
    """In the child process: adapter module argv[1]'s function argv[2] on the JSON
    arguments argv[3], its :class:`Answer` as a marked JSON line on the real standard
    output (what the adapter prints goes to standard error)."""
    with contextlib.redirect_stdout(sys.stderr):
        try:
            module = importlib.import_module(sys.argv[1])
            value = getattr(module, sys.argv[2])(*json.loads(sys.argv[3]))
            try:
                said = Answer(json.loads(json.dumps(value, allow_nan=False)), short(value))
            except (TypeError, ValueError):
                said = Answer(None, short(value))
        except (Exception, SystemExit, KeyboardInterrupt) as e:
            said = Answer(why=f"raised {type(e).__name__}: {e}",
                          missing=isinstance(e, ImportError))
    print(f"{_MARK}\t{json.dumps(said)}", file=sys.__stdout__, flush=True)
    os._exit(0)


@cache
def _isolated(module: str, fn: str, args: str, source: str) -> Answer:  # source: the cache's
    answers, err, status = _child("_call_child", [module, fn, args], CALL_TIMEOUT_S)
    sys.stderr.write(err)  # what the plug-in printed
    if answers:
        return Answer(*answers[0])
    return Answer(why=f"did not finish within {CALL_TIMEOUT_S:g} s" if status is None else
                  _ended(status, err).removeprefix("importing it "))


def isolated(module: str, fn: str, *args) -> Answer:
    """Adapter module ``module``'s function ``fn`` on the JSON-able ``args``, called in a
    child process, so that a plug-in's code cannot end, hang or crash the command (the
    answer is kept for the module's source as it is and the arguments)."""
    try:
        spec = importlib.util.find_spec(module)
        source = hashlib.sha256(Path(spec.origin).read_bytes()).hexdigest() if spec and \
            spec.origin and os.path.isfile(spec.origin) else ""
    except (ImportError, ValueError, OSError):
        source = ""
    return _isolated(module, fn, json.dumps(list(args), sort_keys=True), source)


def version_of(name: str) -> tuple[str | None, str, bool]:
    """Engine ``name``'s version() in a child process (:func:`isolated`): (the version,
    None when there is none; what went wrong, completing "the engine's version() ...";
    whether its package is missing)."""
    a = isolated(discover().modules[name], "version")
    if a.why is None and not isinstance(a.value, str):
        return None, f"returned {a.shown}, not a string", False
    return a.value if a.why is None else None, a.why or "", a.missing


def engine_names() -> tuple[str, ...]:
    """Every engine that loads: built-ins first in their order, then plug-ins by name."""
    return discover().names


def adapter(name: str) -> ModuleType:
    """The adapter module of engine ``name``; KeyError naming the engines for another."""
    reg = discover()
    if name not in reg.modules:
        raise KeyError(f"unknown engine {name!r}; engines are {', '.join(reg.names)}")
    return importlib.import_module(reg.modules[name])


def adapter_digest(engine: str) -> str:
    """sha256 (16 hex digits) of an engine adapter's source: its module, or every ``.py``
    of its package ('' when it cannot be found). Importing an adapter never imports its
    engine, and this does not even import the adapter."""
    module = discover().modules.get(engine)
    try:
        spec = importlib.util.find_spec(module) if module else None
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        return ""
    origin = Path(spec.origin)
    files = sorted(origin.parent.glob("*.py")) if origin.name == "__init__.py" else [origin]
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]
