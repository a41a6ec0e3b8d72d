"""Engine discovery (natcoord.engines.registry) from a given list of entry points: the order,
the fallback for the built-ins, and what is refused with a reason."""

from __future__ import annotations

import os
import signal
import sys
import threading

import pytest

import natcoord.engines.registry as reg

from .conftest import DATA


@pytest.fixture
def entries(monkeypatch):
    """Discover from the entry points given, (name, value) pairs, in this process."""

    def use(pairs):
        monkeypatch.setattr(reg, "_entries", lambda: list(pairs))
        reg.discover.cache_clear()
        return reg.discover()

    monkeypatch.syspath_prepend(str(DATA / "plugin_engine"))
    yield use
    reg.discover.cache_clear()


def test_without_metadata_the_builtins_are_there_in_order(entries):
    r = entries([])
    assert r.names == ("natcoord", "mujoco", "pinocchio", "exudyn", "dart", "simbody", "drake",
                       "pybullet")
    assert r.problems == ()


def test_plugins_come_after_the_builtins_sorted_and_bad_ones_are_named(entries):
    r = entries([("rk4", "natcoord_rk4"), *reg.BUILTIN.items(), ("json", "json"),
                 ("dart", "natcoord_rk4"), ("zz", "natcoord_no_such_module"),
                 ("alpha", "natcoord_rk4")])
    assert r.names == (*reg.BUILTIN, "rk4")
    assert not r.builtin("rk4") and r.builtin("dart")
    why = {p.name: p.error for p in r.problems}
    assert "lacks NAME, PACKAGE, SETTINGS, CAPABILITIES, version, run" in why["json"]
    assert "built-in engine's name" in why["dart"]
    assert why["zz"].startswith("import failed: ModuleNotFoundError")
    assert "its NAME is 'rk4', not the entry point's name 'alpha'" in why["alpha"]
    line = next(p for p in r.problems if p.name == "zz").line()
    assert line.startswith("engine plug-in 'zz' (entry point natcoord.engines: zz = "
                           "natcoord_no_such_module) skipped")
    with pytest.raises(KeyError, match="unknown engine 'zz'"):
        reg.adapter("zz")
    assert reg.adapter("rk4").NAME == "rk4"


@pytest.mark.parametrize("name", ["../../tmp/escaped", "/abs", "pd[/]mk", "pd,comma",
                                  "1abc", "x" * 41, "a b"])
def test_a_plugin_name_that_cannot_name_files_and_options_is_refused(entries, name):
    """The name makes results/<case>/<engine>.csv (one with ../ wrote and deleted files
    outside --out), is an item of --engines a,b, and is drawn in tables (rich markup
    crashed `natcoord cases`): an engine name is letters, digits and _."""
    r = entries([(name, "natcoord_rk4")])
    assert name not in r.names
    (p,) = r.problems
    assert "is not an engine name" in p.error, p.error


VALID = '''
from natcoord.engines.capabilities import Capabilities
from natcoord.engines.schema import Setting

NAME = "{name}"
PACKAGE = "p-{name}"
SETTINGS = (Setting("dt", "number", 1e-3, "time step", "s", exclusive_minimum=0.0),)
CAPABILITIES = Capabilities(dimensions={{2}})


def version():
    return "0.1"


def run(case, init, settings):
    raise RuntimeError("not run here")
'''


@pytest.fixture
def modules(tmp_path, monkeypatch, entries):
    """``modules({name: body})``: adapter modules p_<name> (the valid one above with
    ``body`` appended, or ``body`` alone when it starts with "!"), discovered."""
    monkeypatch.syspath_prepend(str(tmp_path))
    made = []

    def make(bodies: dict):
        for name, body in bodies.items():
            text = body[1:] if body.startswith("!") else VALID.format(name=name) + body
            (tmp_path / f"p_{name}.py").write_text(text)
            sys.modules.pop(f"p_{name}", None)
            made.append(name)
        return entries([(n, f"p_{n}") for n in bodies])

    yield make
    for n in made:
        sys.modules.pop(f"p_{n}", None)


def test_declarations_that_contradict_themselves_are_refused_at_discovery(modules):
    """A range no value is in, a default outside its own range or choices, a setting's
    name no case file can write, capabilities naming dimensions, joints or drivers that do
    not exist (every case declined: check-engine passed with every check skipped), a step
    setting it does not declare: each plug-in is listed with its problem."""
    r = modules({
        "good": "",
        "empty": "SETTINGS = (Setting('dt', 'number', 1.0, 'dt', minimum=1.0, "
                 "maximum=0.5),)\n",
        "outside": "SETTINGS = (Setting('dt', 'number', -5.0, 'dt', minimum=1.0),)\n",
        "choice": "SETTINGS = (Setting('mode', 'choice', 'c', 'mode', choices=('a', 'b')),)\n",
        "badname": "SETTINGS = (Setting('bad name!', 'integer', 2, 'n'),)\n",
        "dims": "CAPABILITIES = Capabilities(dimensions={7})\n",
        "joints": "CAPABILITIES = Capabilities(joints=('wormhole',))\n",
        "drivers": "CAPABILITIES = Capabilities(drivers=('teleport',))\n",
        "step": "CAPABILITIES = Capabilities(step='nonexistent')\n",
    })
    assert r.names == (*reg.BUILTIN, "good")
    why = {p.name: p.error for p in r.problems}
    assert "no value is in [1, 0.5]" in why["empty"]
    assert "its default -5.0 must be >= 1" in why["outside"]
    assert "its default 'c' must be one of a, b" in why["choice"]
    assert "a setting's name is letters, digits and _" in why["badname"]
    assert "dimensions holds 7, not one of 2, 3" in why["dims"]
    assert "joints holds 'wormhole'" in why["joints"]
    assert "drivers holds 'teleport'" in why["drivers"]
    assert "CAPABILITIES.step names 'nonexistent', not one of its SETTINGS" in why["step"]


def test_mistyped_declarations_are_refused_at_discovery(modules):
    """CAPABILITIES a dict, SETTINGS strings or None, ...: the plug-in is listed with its
    problem (cases --json and check-engine crashed on it), the others load."""
    r = modules({
        "good": "",
        "capdict": "CAPABILITIES = {'dimensions': [2]}\n",
        "setstr": "SETTINGS = ('dt', 'number')\n",
        "setnone": "SETTINGS = None\n",
        "setlist": "SETTINGS = list(SETTINGS)\n",
        "fields": "SETTINGS = (Setting('t', 'table', {}, 'a table', fields=('x',)),)\n",
        "twice": "SETTINGS = SETTINGS * 2\n",
        "nanjson": "SETTINGS = (Setting('k', 'number', float('nan'), 'k'),)\n",
        "objdefault": "SETTINGS = (Setting('k', 'number', object(), 'k'),)\n",
        "strbound": "SETTINGS = (Setting('k', 'number', 1.0, 'k', minimum='0'),)\n",
        "rules": "CAPABILITIES = Capabilities(rules='no')\n",
        "why": "CAPABILITIES = Capabilities(why=[1])\n",
        "runnot": "run = 3\n",
        "package": "PACKAGE = None\n",
    })
    assert r.names == (*reg.BUILTIN, "good")
    why = {p.name: p.error for p in r.problems}
    assert set(why) == {"capdict", "setstr", "setnone", "setlist", "fields", "twice",
                        "nanjson", "objdefault", "strbound", "rules", "why", "runnot",
                        "package"}
    assert why["capdict"] == ("its CAPABILITIES is {'dimensions': [2]} (dict), not a "
                              "natcoord.engines.capabilities.Capabilities")
    assert why["setstr"] == ("its SETTINGS holds 'dt' (str), not a "
                             "natcoord.engines.schema.Setting")
    assert why["setnone"].startswith("its SETTINGS is None (NoneType), not a tuple")
    assert why["setlist"].startswith("its SETTINGS is [Setting(") and "(list)" in why["setlist"]
    assert why["fields"].startswith("its setting 't''s fields holds 'x' (str)")
    assert why["twice"] == "its SETTINGS names a setting 'dt': not a new non-empty string"
    for name in ("strbound", "why"):
        assert why[name].startswith("its declarations (CAPABILITIES, SETTINGS) cannot be "
                                    "described as JSON"), why[name]
    assert why["nanjson"] == ("import failed: ValueError: setting k: its default nan must be "
                              "finite, got nan")
    assert why["objdefault"].startswith("import failed: ValueError: setting k: its default "
                                        "<object object at"), why["objdefault"]
    assert why["rules"] == "its CAPABILITIES.rules is 'no', not a function"
    assert why["runnot"] == "its run is 3, not a function"
    assert why["package"] == "its PACKAGE is None, not a package name (a string)"


def test_a_plugin_that_exits_on_import_is_listed_not_obeyed(modules):
    """SystemExit from a plug-in's import (it took every command down, exit 1) is its own
    failure: listed, the other engines load."""
    r = modules({"bye": "!raise SystemExit('no')\n", "good": ""})
    assert r.names == (*reg.BUILTIN, "good")
    assert {p.name: p.error for p in r.problems} == {"bye": "import failed: SystemExit: no"}


def test_an_interrupt_while_a_plugin_imports_is_not_swallowed(modules):
    """A user's Ctrl-C while the plug-ins are imported (in the child process) interrupts
    the command; a plug-in raising KeyboardInterrupt itself is only its own failure."""
    # Python's own Ctrl-C handler: a process started in the background by a shell without
    # job control (a CI script's `cmd &`) inherits SIGINT ignored, and Python keeps that
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            modules({"slow": "!import time\ntime.sleep(60)\n"})
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, old)
    r = modules({"ctrlc": "!raise KeyboardInterrupt\n", "good": ""})
    assert r.names == (*reg.BUILTIN, "good")
    assert [p.error for p in r.problems] == ["import failed: KeyboardInterrupt"]


def test_what_a_plugin_prints_on_import_goes_to_stderr(modules, capsys):
    """Printed to standard output it corrupted every --json command's output."""
    r = modules({"loud": "!print('hello')\nraise ImportError('x')\n", "chatty": "print('hi')\n"})
    out, err = capsys.readouterr()
    assert out == "" and "hello" in err and "hi" in err
    assert "chatty" in r.names and r.problems[0].error == "import failed: ImportError: x"


@pytest.mark.parametrize("body, why", [
    ("def check_settings(settings):\n    print('chatter')\n    raise RuntimeError('broke')\n",
     "the engine's check_settings raised RuntimeError: broke"),
    ("def check_settings(settings):\n    return 'bad'\n",
     "the engine's check_settings returned 'bad', not a list of (field, reason) pairs"),
    ("def check_settings(settings):\n    return [('dt',)]\n",  # JSON from its process
     "the engine's check_settings returned [['dt']], not a list of (field, reason) pairs"),
    ("def check_settings(settings):\n    import os\n    os._exit(0)\n",  # it ended the
     "the engine's check_settings ended the process (exit status 0)"),    # command: exit 0
])
def test_a_broken_check_settings_is_one_problem_not_a_crash(modules, capsys, body, why):
    """A plug-in's check_settings that raised crashed every command loading a case that
    sets the engine's settings (a traceback), one that ended its process ended the command
    (a failing gate exited 0): it runs in a child process, and what went wrong is the
    case's problem, one line."""
    from natcoord.engines.schema import problems

    modules({"cs": body})
    assert problems(reg.adapter("cs"), {"dt": 1e-3}) == [("", why)]
    assert "chatter" not in capsys.readouterr().out


def test_a_plugin_that_ends_or_hangs_its_process_on_import_is_listed(modules, monkeypatch):
    """os._exit or a crash in a plug-in's import ended every command (the import ran in the
    command's process); a hang held it. Each is imported in a child process first and
    listed with what happened; the plug-ins after it still load."""
    monkeypatch.setattr(reg, "PROBE_TIMEOUT_S", 10.0)
    r = modules({"aexit": "!import os\nos._exit(3)\n",
                 "bkill": "!import os, signal\nos.kill(os.getpid(), signal.SIGKILL)\n",
                 "chang": "!import sys, time\nprint('waiting', file=sys.stderr)\n"
                          "time.sleep(600)\n",
                 "good": ""})
    assert r.names == (*reg.BUILTIN, "good")
    why = {p.name: p.error for p in r.problems}
    assert why == {"aexit": "importing it ended the process (exit status 3)",
                   "bkill": "importing it ended the process (signal SIGKILL)",
                   "chang": "importing it did not finish within 10 s"}
    assert "aexit" not in sys.modules and "p_aexit" not in sys.modules
