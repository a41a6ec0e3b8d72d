"""The command line's help shows what it says: defaults and TOML table names in square
brackets are text, not markup that a terminal swallows."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _help(*command: str) -> str:
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", *command, "--help"],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "COLUMNS": "200"})
    assert p.returncode == 0, p.stderr
    return p.stdout


@pytest.mark.parametrize("command, shown", [
    (("run",), "Comma-separated engines [default: all]"),
    (("run",), "Folder of case files [default: <project>/cases]"),
    (("gate",), "[default: <project>/references/baseline.json]"),
    (("propose",), "[engines.*]"),
])
def test_help_keeps_square_brackets(command, shown):
    assert shown in " ".join(_help(*command).split())
