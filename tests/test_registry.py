"""Engine discovery (natcoord.engines.registry) from a given list of entry points: the order,
the fallback for the built-ins, and what is refused with a reason."""

from __future__ import annotations

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
