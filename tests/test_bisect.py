"""`natcoord bisect` names the commit that broke a cell: a test repository (a copy of the
package, the pendulum case and its reference) whose third commit loosens natcoord's
integration tolerance in the case file to rtol 1e-4 (its error passes the case's 1e-8 rad:
the gate fails); the commits around it change nothing that matters. (A change of the mass
would make the reference stale instead, which the gate refuses to judge: see
test_evidence.) The user's checkout is not touched."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import CASES, REFERENCES

ROOT = Path(__file__).resolve().parents[1]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
                          cwd=repo, capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture
def repo(tmp_path) -> tuple[Path, list[str]]:
    r = tmp_path / "repo"
    shutil.copytree(ROOT / "natcoord", r / "natcoord",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (r / "cases").mkdir()
    (r / "references").mkdir()
    shutil.copy(CASES / "pendulum.toml", r / "cases")
    for f in REFERENCES.glob("pendulum.*"):
        shutil.copy(f, r / "references")
    _git(r, "init", "-q")
    shas = []

    def commit(message: str) -> None:
        _git(r, "add", "-A")
        _git(r, "commit", "-q", "-m", message)
        shas.append(_git(r, "rev-parse", "HEAD"))

    commit("good: the pendulum as shipped")
    (r / "NOTES.md").write_text("a note\n")
    commit("a note")
    case = r / "cases" / "pendulum.toml"
    text = case.read_text()
    assert "[engines.natcoord]\n" in text
    loose = "[engines.natcoord]\nsettings = { rtol = 1e-4, atol = 1e-6 }\n"
    case.write_text(text.replace("[engines.natcoord]\n", loose, 1))
    commit("natcoord's tolerance loosened")
    (r / "NOTES.md").write_text("another note\n")
    commit("another note")
    return r, shas


def test_bisect_names_the_commit_that_loosened_the_solver(repo):
    r, shas = repo
    before = _git(r, "status", "--porcelain")
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bisect", shas[0], shas[-1],
                        "pendulum", "--engines", "natcoord", "--repo", str(r), "--json"],
                       capture_output=True, text=True, timeout=1200, env=dict(os.environ))
    assert p.returncode == 0, p.stderr[-3000:]
    found = json.loads(p.stdout)
    assert found["first_bad"] == shas[2] and found["subject"] == "natcoord's tolerance loosened"
    assert _git(r, "status", "--porcelain") == before  # the checkout untouched
    assert _git(r, "rev-parse", "HEAD") == shas[-1]
    assert "worktree" not in _git(r, "worktree", "list").split("\n", 1)[-1]


def test_bisect_names_no_commit_when_an_end_does_not_hold(repo):
    """BAD where the gate passes (before the tolerance changed): bisect named a first bad commit
    it never saw fail, exit 0; the ends are judged first now, and it says which does not
    hold (exit 3); GOOD where the gate fails likewise."""
    r, shas = repo
    for good, bad, said in ((shas[0], shas[1], "the gate passes at BAD"),
                            (shas[2], shas[3], "the gate fails at GOOD")):
        p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bisect", good, bad,
                            "pendulum", "--engines", "natcoord", "--repo", str(r)],
                           capture_output=True, text=True, timeout=1200, env=dict(os.environ))
        assert p.returncode == 3 and said in p.stderr, p.stderr[-2000:]
        assert "first bad commit:" not in p.stdout
    assert "worktree" not in _git(r, "worktree", "list").split("\n", 1)[-1]


def test_an_unknown_case_is_bad_input_before_any_commit_runs(repo):
    r, shas = repo
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bisect", shas[0], shas[-1],
                        "pendulm", "--engines", "natcoord", "--repo", str(r)],
                       capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert p.returncode == 2 and "'pendulm': not a case of BAD" in p.stderr, p.stderr[-2000:]
    assert "Traceback" not in p.stderr
    assert "worktree" not in _git(r, "worktree", "list").split("\n", 1)[-1]


def test_a_repo_that_is_not_a_git_repository_is_bad_input(tmp_path):
    """--repo is a path the user typed: one that does not exist (was exit 5, "a fault of
    the environment"), a file or a folder outside any repository is exit 2, named."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "plain").mkdir()
    for repo, why in (("nonexist", "does not exist"), ("afile", "not a folder"),
                      ("plain", "not a git repository")):
        p = subprocess.run([sys.executable, "-m", "natcoord.cli", "bisect", "--repo",
                            str(tmp_path / repo), "HEAD~1", "HEAD", "pendulum"],
                           capture_output=True, text=True, timeout=120,
                           env=dict(os.environ), cwd=tmp_path)
        assert p.returncode == 2, (repo, p.returncode, p.stderr)
        assert f"{tmp_path / repo}: not a git repository" in p.stderr, p.stderr
        assert why in p.stderr and "Traceback" not in p.stderr, p.stderr


def _suite(r: Path, db: Path) -> subprocess.CompletedProcess:
    """The suite of the checkout at ``r`` (its own case files and references; the pendulum
    in natcoord, no bench), recorded in the history ``db``."""
    out = db.parent / f"night-{_git(r, 'rev-parse', '--short', 'HEAD')}"
    return subprocess.run([sys.executable, "-m", "natcoord.cli", "suite", "pendulum",
                           "--engines", "natcoord", "--repeats", "0", "--jobs", "1",
                           "--history", str(db), "--out", str(out)],
                          cwd=r, capture_output=True, text=True, timeout=1200,
                          env={k: v for k, v in os.environ.items() if k != "NATCOORD_HOME"})


def test_since_green_names_the_commit_that_loosened_the_solver(repo, tmp_path):
    """Two nights in the test repository: the shipped pendulum (green), then the commit
    that loosened natcoord's tolerance. `history --since-green` names the failing cell, the last
    green commit and the commit of the failing night."""
    r, shas = repo
    db = tmp_path / "history.db"
    _git(r, "checkout", "-q", shas[0])
    assert _suite(r, db).returncode == 0
    _git(r, "checkout", "-q", shas[2])
    night = _suite(r, db)
    assert night.returncode == 1, night.stdout[-2000:] + night.stderr[-2000:]
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", "history", "--since-green",
                        "--json", "--history", str(db)], cwd=r, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 1, p.stderr
    found = json.loads(p.stdout)
    assert [x["cell"] for x in found["regressed"]] == ["pendulum/natcoord"]
    assert found["green"]["commit"] == shas[0] and found["latest"]["commit"] == shas[2]
