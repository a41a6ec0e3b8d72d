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
