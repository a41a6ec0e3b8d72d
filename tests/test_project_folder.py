"""Every command works from any directory: outside a project, the checkout natcoord is
installed from is the project (its cases/, references/, reports/)."""

from __future__ import annotations

import os
import subprocess
import sys

from natcoord.case.project import home

from .conftest import CASES


def test_outside_a_project_the_installed_checkout_is_the_project(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no cases/ here or above
    monkeypatch.delenv("NATCOORD_HOME", raising=False)
    assert home() == CASES.parent


def test_a_command_run_elsewhere_finds_the_cases(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "NATCOORD_HOME"}
    out = subprocess.run([sys.executable, "-m", "natcoord.cli", "cases", "--json"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "slider_crank" in out.stdout
