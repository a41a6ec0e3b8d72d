"""Fuzz the case loader: mutated case files are loaded or refused with a CaseError, never a
traceback. Each example takes a shipped case file, replaces, deletes or nests some of its
values (random types, control characters, huge numbers, long strings) and loads it; the
command line is run on a sample of the mutants and must exit 0 or 2. Engine settings get
their own fuzz: random keys (declared or not), types and values in
``[engines.<name>].settings`` of every engine load cleanly or are refused naming the field.

The budget is bounded (``max_examples``, no deadline per example) so that it runs in CI.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from natcoord import CaseError, load_case
from natcoord.engines import adapter, engine_names
from natcoord.engines.schema import problems, shown

from .conftest import CASES

ENGINES = engine_names()  # the built-ins and any plug-in installed here

FILES = sorted(CASES.glob("*.toml")) + sorted((Path(__file__).parent / "data").glob(
    "[!p]*.toml"))  # tests/data/pivoted_3d.toml is a template, not a case file
TEXTS = {p.stem: tomllib.loads(p.read_text()) for p in FILES}

scalars = st.one_of(
    st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=20),
    st.text(alphabet=st.characters(min_codepoint=0, max_codepoint=40), max_size=5),
    st.sampled_from(["..", "../x", "ground", "45 deg", "1e400", "300 mm", "-1 s", "x" * 3000,
                     "nan", "2 kg", "9.81 m/s^2", "1 N m"]))
values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=12)


def _paths(data, prefix=()):
    """Every path (tuple of keys / indices) to a value in parsed TOML."""
    out = [prefix] if prefix else []
    items = data.items() if isinstance(data, dict) else enumerate(data) \
        if isinstance(data, list) else ()
    for k, v in items:
        out += _paths(v, prefix + (k,))
    return out


def _mutate(data, path, action, value):
    node = data
    for k in path[:-1]:
        node = node[k]
    last = path[-1]
    if action == "delete":
        del node[last]
    elif action == "nest":
        node[last] = [[[[[[[[[[node[last]]]]]]]]]]]
    else:
        node[last] = value


@settings(max_examples=600, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(st.data())
def test_mutated_case_files_load_or_are_refused_with_a_reason(tmp_path_factory, data):
    name = data.draw(st.sampled_from(sorted(TEXTS)))
    doc = tomllib.loads(tomli_w.dumps(TEXTS[name]))  # a deep copy
    for _ in range(data.draw(st.integers(1, 3))):
        paths = _paths(doc)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths))
        _mutate(doc, path, data.draw(st.sampled_from(["replace", "replace", "delete", "nest"])),
                data.draw(values))
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):  # not representable as TOML (e.g. a NaN key)
        return
    f = tmp_path_factory.mktemp("fuzz") / f"{name}.toml"
    f.write_text(text)
    try:
        load_case(f)
    except CaseError as e:
        assert str(f) in str(e)  # names the file


SCHEMAS = {e: adapter(e).SETTINGS for e in ENGINES}
SETTINGS_CASES = ("pendulum", "slider_crank", "four_bar_3d", "slider_crank_driven")


def _declared_value(s):
    """Values of the declared setting ``s``: valid ones, near misses and wrong types."""
    numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 10**6))
    by_type = {
        "number": numbers,
        "integer": st.one_of(st.integers(-10, 10**6), st.floats(0, 100)),
        "boolean": st.booleans(),
        "choice": st.one_of(st.sampled_from(s.choices), st.text(max_size=12),
                            st.just('RK4" gravity="0 0 0'),
                            st.just('<include file="/etc/hostname"/>')),
        "numbers": st.lists(st.floats(-1, 3), min_size=max(0, (s.length or 2) - 1),
                            max_size=(s.length or 2) + 1),
        "table": st.dictionaries(st.one_of(st.sampled_from([f.name for f in s.fields]),
                                           st.text(max_size=6)),
                                 st.one_of(numbers, st.text(max_size=8), st.booleans()),
                                 max_size=3),
    }
    return st.one_of(st.just(s.default) if s.default is not None else st.nothing(),
                     by_type[s.type], values)


@settings(max_examples=300, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(st.data())
def test_random_engine_settings_load_or_are_refused_naming_the_field(tmp_path_factory, data):
    name = data.draw(st.sampled_from(SETTINGS_CASES))
    engine = data.draw(st.sampled_from(ENGINES))
    declared = {s.name: s for s in SCHEMAS[engine]}
    chosen = {}
    for _ in range(data.draw(st.integers(1, 4))):
        key = data.draw(st.one_of(st.sampled_from(sorted(declared)), st.text(max_size=10)))
        chosen[key] = data.draw(_declared_value(declared[key]) if key in declared else values)
    doc = tomllib.loads(tomli_w.dumps(TEXTS[name]))
    doc.setdefault("engines", {}).setdefault(engine, {})["settings"] = chosen
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):
        return
    f = tmp_path_factory.mktemp("fuzz") / f"{name}.toml"
    f.write_text(text)
    try:
        case = load_case(f)
    except CaseError as e:
        assert e.file == str(f)
        assert e.field.startswith(f"engines.{engine}.settings"), str(e)
        rest = e.field[len(f"engines.{engine}.settings"):]
        if rest:  # names the key at fault
            assert any(rest == f".{shown(k)}" or rest.startswith((f".{k}.", f".{k}["))
                       for k in chosen), str(e)
    else:  # a clean load: every key declared, every value valid
        assert set(case.engine(engine).settings) <= set(declared)
        assert problems(adapter(engine), case.engine(engine).settings) == []


@pytest.mark.parametrize("text, field", [
    ("a = " + "[" * 2000 + "]" * 2000, "nested too deeply"),
    ("x = " + "{a = " * 200 + "1" + "}" * 200, "nested too deeply"),
])
def test_deeply_nested_files_are_refused(tmp_path, text, field):
    f = tmp_path / "deep.toml"
    f.write_text(text)
    with pytest.raises(CaseError, match=field):
        load_case(f)


def test_the_command_line_exits_0_or_2_on_mutants(tmp_path):
    """A sample of hand-made bad files through `natcoord cases`: exit 2, one line, no
    traceback."""
    base = (CASES / "pendulum.toml").read_text()
    bad = {
        "dimension": base.replace("dimension = 2", "dimension = 2.0"),
        "name": base.replace('name = "pendulum"', 'name = "pend\\u0000ulum"'),
        "samples": base.replace("output_dt = 0.01", "output_dt = 1e-9"),
        "nested": base + "\ntags = " + "[" * 500 + "]" * 500 + "\n",
        "mujoco setting": base.replace("[engines.mujoco]\nsettings = { dt = 1e-4 }",
                                       "[engines.mujoco]\nsettings = { solver = '<include/>' }"),
        "dart setting": base.replace("[engines.dart]\nsettings = { dt = 1e-4 }",
                                     "[engines.dart]\nsettings = { dtt = [{}] }"),
    }
    for label, text in bad.items():
        assert text != base, label
        d = tmp_path / label.replace(" ", "_")
        d.mkdir()
        (d / "pendulum.toml").write_text(text)
        p = subprocess.run([sys.executable, "-m", "natcoord.cli", "cases", "--cases-dir", str(d)],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2, (label, p.returncode, p.stderr[-500:])
        assert "Traceback" not in p.stderr and "error:" in p.stderr, (label, p.stderr[-500:])
