"""``natcoord bisect``: the first commit at which the gate fails for some cells.

``git bisect run`` in a temporary worktree of the repository (the user's checkout is never
touched): at each commit, that commit's natcoord (``PYTHONPATH`` and ``NATCOORD_HOME`` point
at the worktree) runs the cases in the engines and its gate judges them against its own case
files and references. Gate 0 is good; an accuracy regression, a failed or missing cell, a
timeout or a crash is bad; a commit whose natcoord cannot start or refuses its own cases
(bad input, exit 2) is skipped (``git bisect`` exit 125).
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

from ..errors import NatcoordError

STEP = r'''
import os, subprocess, sys, tempfile
wt, timeout, engines = sys.argv[1], float(sys.argv[2]), sys.argv[4]
cases = [c for c in sys.argv[3].split(",") if c]  # none: every case of the commit
env = {**os.environ, "PYTHONPATH": wt, "NATCOORD_HOME": wt}
def natcoord(*args):
    return subprocess.run([sys.executable, "-P", "-m", "natcoord.cli", *args], env=env,
                          capture_output=True, text=True, timeout=timeout)
with tempfile.TemporaryDirectory() as tmp:
    try:
        run = natcoord("run", *cases, "--engines", engines, "--out", tmp + "/r")
    except subprocess.TimeoutExpired:
        sys.exit(1)
    if run.returncode == 2 or "No module named" in run.stderr or not os.path.exists(
            tmp + "/r/summary.json"):
        print(run.stderr[-800:], file=sys.stderr)
        sys.exit(125)  # this commit cannot judge: skip it
    gate = natcoord("gate", "--results", tmp + "/r", "--baseline", tmp + "/none.json")
    print(gate.stderr[-800:], file=sys.stderr)
    sys.exit(0 if gate.returncode == 0 else 1)
'''


def _git(cwd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    if check and p.returncode != 0:
        raise NatcoordError(f"git {' '.join(args)}: {(p.stderr or p.stdout).strip()[-400:]}")
    return p


def bisect(repo: Path, good: str, bad: str, cases: list[str], engines: list[str], *,
           timeout_s: float = 600.0) -> dict:
    """``{"first_bad": sha or None, "subject": ..., "why": why none, "log": git bisect's
    output}``, after checking that the gate fails at ``bad`` and passes at ``good`` (else
    no commit is named, and ``why`` says which end does not hold); NatcoordError when
    ``repo`` is not a git repository or a revision is unknown."""
    repo = Path(repo)
    if not repo.is_dir():  # a path the user typed: bad input, not the machine
        raise NatcoordError(f"{repo}: not a git repository ("
                            f"{'not a folder' if repo.exists() else 'does not exist'})")
    top = _git(repo, "rev-parse", "--show-toplevel", check=False)
    if top.returncode != 0:
        raise NatcoordError(f"{repo}: not a git repository "
                            f"({(top.stderr or top.stdout).strip()[-300:]})")
    top = top.stdout.strip()
    revs = {r: _git(repo, "rev-parse", "--verify", f"{r}^{{commit}}").stdout.strip()
            for r in (good, bad)}
    shipped = {Path(f).stem for f in _git(repo, "ls-tree", "-r", "--name-only", revs[bad],
                                          "--", "cases").stdout.splitlines()
               if f.endswith(".toml")}
    unknown = [c for c in cases if not c.endswith(".toml") and "/" not in c
               and c not in shipped]
    if unknown:  # named before any commit runs (each would be skipped as "cannot judge")
        raise NatcoordError(f"{', '.join(map(repr, unknown))}: not a case of BAD ({bad}: "
                            f"{len(shipped)} case file(s) under cases/)")
    with tempfile.TemporaryDirectory(prefix="natcoord-bisect-") as tmp:
        wt = Path(tmp) / "worktree"
        _git(Path(top), "worktree", "add", "--detach", str(wt), revs[bad])
        try:
            step = Path(tmp) / "step.py"
            step.write_text(STEP, encoding="utf-8")
            command = [sys.executable, str(step), str(wt), str(timeout_s), ",".join(cases),
                       ",".join(engines)]
            # the ends first: a BAD the gate passes named a commit it never saw fail
            for rev, want, word, end_name in ((bad, 1, "passes", "BAD"),
                                              (good, 0, "fails", "GOOD")):
                _git(wt, "checkout", "--quiet", "--detach", revs[rev])
                end = subprocess.run(command, capture_output=True, text=True)
                if end.returncode != want:
                    why = (f"cannot judge {end_name} {rev} ({revs[rev][:12]}): its natcoord "
                           "does not start or refuses these cases" if end.returncode == 125
                           else f"the gate {word} at {end_name} {rev} ({revs[rev][:12]}) for "
                           "these cases and engines")
                    return {"first_bad": None, "subject": "", "good": revs[good],
                            "bad": revs[bad], "why": why, "log": end.stderr}
            _git(wt, "bisect", "start", revs[bad], revs[good])
            p = _git(wt, "bisect", "run", *command, check=False)
            log = p.stdout + p.stderr
            m = re.search(r"^([0-9a-f]{40}) is the first bad commit", log, re.M)
            first = m.group(1) if m else None
            subject = _git(wt, "log", "-1", "--format=%s", first).stdout.strip() if first \
                else ""
            _git(wt, "bisect", "reset", check=False)
        finally:
            _git(Path(top), "worktree", "remove", "--force", str(wt), check=False)
    return {"first_bad": first, "subject": subject, "good": revs[good], "bad": revs[bad],
            "why": "" if first else "git bisect named no commit", "log": log}
