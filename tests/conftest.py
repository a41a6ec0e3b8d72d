"""Shared fixtures: the repository's folders and a helper to write case variants."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CASES = ROOT / "cases"
REFERENCES = ROOT / "references"
DATA = Path(__file__).resolve().parent / "data"

# 3-D bodies on a spherical joint, shared by the tests of the loader and the engines
# (written to a file of the case name: NAME.toml)
PLATE = """name = "plate"
description = "a 3-D body on a ball joint whose three points span a plane its inertia leaves"
dimension = 3
gravity = [0.0, 0.0, -9.81]
duration = 0.1
output_dt = 0.01
[ground]
points = { O = [0.0, 0.0, 0.0] }
[[bodies]]
name = "plate"
kind = "rigid"
mass = 1.0
com = [0.5, 0.0, 0.0]
inertia = [[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]]
points = { O = [0.0, 0.0, 0.0], A = [1.0, 0.0, 0.0], B = [0.0, 1.0, 0.0] }
[[joints]]
name = "O"
type = "spherical"
bodies = ["ground", "plate"]
points = ["O", "O"]
[channels]
x = { kind = "position", body = "plate", point = "A", axis = "x" }
"""

SPHERICAL_ROD = """
name = "spherical_rod"
description = "a rod on a spherical joint, released with a sideways spin"
dimension = 3
gravity = [0.0, 0.0, -9.81]
duration = 1.0
output_dt = 0.01

[ground]
points = { O = [0.0, 0.0, 0.0] }

[[bodies]]
name = "rod"
kind = "rigid"
mass = 1.0
com = [0.5, 0.0, 0.0]
inertia = [[0.001, 0.0, 0.0], [0.0, 0.0833333333, 0.0], [0.0, 0.0, 0.0833333333]]
points = { O = [0.0, 0.0, 0.0], P = [1.0, 0.0, 0.0], Q = [0.0, 1.0, 0.0], R = [0.0, 0.0, 1.0] }

[[joints]]
name = "O"
type = "spherical"
bodies = ["ground", "rod"]
points = ["O", "O"]

[initial]
velocity = { yP = 2.0, zP = 0.0, zQ = 0.0 }

[channels]
zQ = { kind = "position", body = "rod", point = "Q", axis = "z" }
yP = { kind = "position", body = "rod", point = "P", axis = "y" }
zP = { kind = "position", body = "rod", point = "P", axis = "z" }
"""


def project_copy(tmp_path: Path, *cases: str) -> Path:
    """A project folder (cases/, references/) holding copies of shipped cases."""
    home = tmp_path / "project"
    (home / "cases").mkdir(parents=True)
    shutil.copytree(REFERENCES, home / "references")
    for c in cases:
        shutil.copy(CASES / f"{c}.toml", home / "cases")
    return home


def worker_pids(where: Path) -> list[int]:
    """The natcoord engine processes running now for ``where``: a fresh interpreter whose
    command line names the worker and ``where``, or the fork server and its forks
    (:mod:`natcoord.suite.zygote`) whose environment names ``where``."""
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
                env = (Path(f"/proc/{pid}/environ").read_bytes()
                       if b"multiprocessing.forkserver" in cmd else b"")
            except OSError:
                continue
            if (b"natcoord.suite.worker" in cmd and str(where).encode() in cmd) or (
                    str(where).encode() in env):
                out.append(int(pid))
    return out


@pytest.fixture
def case_variant(tmp_path):
    """Write a copy of a case file with text substitutions into tmp_path; returns its path.

    ``case_variant("slider_crank", [(pattern, replacement), ...])`` applies ``re.sub`` once
    per pair and fails the test if a pattern does not match, so a variant never silently
    equals its original.
    """

    def make(name: str, subs=(), *, stem: str | None = None) -> Path:
        text = (CASES / f"{name}.toml").read_text()
        for pattern, repl in subs:
            text, n = re.subn(pattern, repl, text, count=1, flags=re.M)
            assert n == 1, f"pattern {pattern!r} not found in {name}.toml"
        path = tmp_path / f"{stem or name}.toml"
        path.write_text(text)
        return path

    return make


# the pendulum with its bob's vertical acceleration as a channel (ay, m/s^2)
PENDULUM_AY = [(r'^(y = \{ kind = "position", body = "link", point = "P", axis = "y" \})',
                r'\1\nay = { kind = "acceleration", body = "link", point = "P", axis = "y" }')]
