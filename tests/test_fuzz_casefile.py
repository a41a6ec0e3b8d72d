"""Fuzz the case loader: mutated case files are loaded or refused with a CaseError, never a
traceback. Each example takes a shipped case file, replaces, deletes or nests some of its
values (random types, control characters, huge numbers, long strings) and loads it; the
command line is run on a sample of the mutants and must exit 0 or 2.

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

from .conftest import CASES

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
    }
    for label, text in bad.items():
        d = tmp_path / label
        d.mkdir()
        (d / "pendulum.toml").write_text(text)
        p = subprocess.run([sys.executable, "-m", "natcoord.cli", "cases", "--cases-dir", str(d)],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2, (label, p.returncode, p.stderr[-500:])
        assert "Traceback" not in p.stderr and "error:" in p.stderr, (label, p.stderr[-500:])
