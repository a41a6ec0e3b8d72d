"""A faulty engine plug-in fails its own cells, with a reason, and nothing else: what its
run returns is checked before anything is kept of it, a fault in its declarations or
capability rules fails the cell (never passes for ``unsupported``), its rules run in its
engine process (under the time limit), and what it prints never reaches a command's JSON.

Plug-ins are written here as a module and its distribution's metadata (an entry point in a
``.dist-info`` folder), no install: in this process they are registered by patching the
registry's entry points (as tests/test_registry.py does); in a child process (an engine
process, a command) by putting their folder on PYTHONPATH."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import natcoord.engines.registry as reg
from natcoord.case.casefile import load_case
from natcoord.suite import worker
from natcoord.suite.runner import prepare

from .conftest import CASES, project_copy

HEAD = '''
from natcoord.engines.capabilities import Capabilities
from natcoord.engines.schema import Setting

NAME = "{name}"
PACKAGE = "p-{name}"
CAPABILITIES = Capabilities(dimensions={{2}})
SETTINGS = ()


def version():
    return "0.1"


def run(case, init, settings):
    from natcoord.engines import natcoord_engine
    return natcoord_engine.run(case, init, {{"method": "rk4", "h": 1e-3}})
'''


def write_plugin(folder: Path, name: str, body: str = "", *, head: bool = True) -> Path:
    """Plug-in ``name`` in ``folder``: module ``p_<name>`` (a valid adapter, ``body`` appended
    to override part of it; without ``head`` the module is ``body`` alone) and its
    entry point. Returns ``folder``."""
    info = folder / f"p_{name}-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: p-{name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[natcoord.engines]\n{name} = p_{name}\n")
    (folder / f"p_{name}.py").write_text((HEAD.format(name=name) if head else "") + body)
    return folder


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """``plugin(name, body)``: write a plug-in and register it (alone) in this process."""
    folder = tmp_path / "site"
    names = []

    def make(name: str, body: str = "", head: bool = True):
        write_plugin(folder, name, body, head=head)
        names.append(name)
        monkeypatch.syspath_prepend(str(folder))
        monkeypatch.setattr(reg, "_entries", lambda: [(n, f"p_{n}") for n in names])
        sys.modules.pop(f"p_{name}", None)
        reg.discover.cache_clear()
        return reg.discover()

    yield make
    reg.discover.cache_clear()
    for n in names:
        sys.modules.pop(f"p_{n}", None)


@pytest.fixture(scope="module")
def pendulum():
    """The pendulum over 0.1 s, assembled: a Job template."""
    case = load_case(CASES / "pendulum.toml")
    return prepare(dataclasses.replace(case, duration=0.1))


def run_in_process(job, engine: str) -> dict:
    res, _ = worker.run_job(dataclasses.replace(job, engine=engine))
    return worker.record_of(res, job.case.duration)


# --------------------------------------------------------------- what a run returns
@pytest.mark.parametrize("change, why", [
    ("r.settings = [1]", "settings [1] (list), not a dict"),
    ("r.counters = 'many'", "counters 'many' (str), not a dict"),
    ("r.counters = {'f': print}", "counters that JSON cannot hold"),
    ("r.settings = {1: 2}", "settings with the key 1, not a string"),
    ("r.notes = 'a note'", "notes 'a note', not a list of strings"),
    ("r.n_steps = 2.5", "n_steps = 2.5, not a whole number"),
    ("r.wall_time_s = float('nan')", "wall_time_s = nan, not a finite number"),
    ("r.build_time_s = None", "build_time_s = None, not a finite number"),
    ("r.methods = {'x': 1}", "method 'x''s motion 1 (int), not a natcoord Motion"),
    ("r.motion = None", "a motion None (NoneType), not a natcoord Motion"),
    ("r = {'motion': r.motion}", "not a natcoord EngineRun"),
    ("r.motion = dataclasses.replace(r.motion, t=r.motion.t * 1.01)",
     "a motion with 11 samples at other times than the case's 11"),
    ("r.motion = dataclasses.replace(r.motion, t=r.motion.t[:5])",
     "a motion with 5 samples at other times than the case's 11"),
    ("r.motion = dataclasses.replace(r.motion, origin={})",
     "the engine's motion does not give the case's channels: KeyError"),
])
def test_what_a_run_returns_is_checked_and_fails_its_cell(plugin, pendulum, change, why):
    """A run whose record later code would trust but cannot read (settings a list: the
    report crashed on it) fails its cell with the reason; nothing of it is kept."""
    plugin("ev", f'''
import dataclasses
_run = run
def run(case, init, settings):
    r = _run(case, init, settings)
    {change}
    return r
''')
    res, extra = worker.run_job(dataclasses.replace(pendulum, engine="ev"))
    assert res.status == "failed" and why in res.reason, res.reason
    assert res.table is None and extra == {} and res.samples_s == []
    rec = worker.record_of(res, 0.1)
    assert isinstance(rec["settings"], dict) and isinstance(rec["counters"], dict)
    json.dumps(rec)


def test_a_valid_run_is_kept_as_it_was(plugin, pendulum):
    plugin("ok")
    rec = run_in_process(pendulum, "ok")
    assert rec["status"] == "ok" and rec["n_steps"] == 100, rec
    assert rec["settings"]["method"] == "rk4" and rec["counters"]["steps"] == 100


@pytest.mark.parametrize("body, why", [
    ("def version():\n    raise RuntimeError('broke')\n",
     "the engine's version() raised RuntimeError: broke"),
    ("def version():\n    return 1\n", "the engine's version() returned 1, not a string"),
])
def test_a_broken_version_fails_the_cell(plugin, pendulum, body, why):
    plugin("vr", body)
    rec = run_in_process(pendulum, "vr")
    assert rec["status"] == "failed" and rec["reason"] == why
