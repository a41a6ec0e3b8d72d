"""Results folders with integrity: one writer at a time, published whole or not at all.

A run first moves the previous content of its target aside (to ``.<name>.previous``
beside it, replacing an older one), writes into a staging folder and, when it completes,
renames the staging folder to the target. An interrupted, crashed or refused run removes
its staging folder and leaves no target: a gate then finds no summary (exit 2) instead of
judging the previous run as if it were this one. So no stale file of an earlier run
survives into a new one, and no mixture of two runs is ever published. A lock file beside
the target keeps a second run from writing the same folder (it is refused with the other
run's pid).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from ..errors import NatcoordError


class FolderBusy(NatcoordError):
    """Another run holds the lock of the results folder."""


def stamped(parent: Path, kind: str) -> Path:
    """A fresh folder name under ``parent``: ``<UTC time>-<kind>`` (made unique)."""
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    path = Path(parent) / f"{stamp}-{kind}"
    k = 1
    while path.exists():
        k += 1
        path = Path(parent) / f"{stamp}-{kind}-{k}"
    return path


@contextlib.contextmanager
def publishing(target: Path) -> Iterator[Path]:
    """Lock ``target``, move its previous content aside, yield a fresh staging folder and on
    success rename it to ``target``. On any exception (an interruption included) the
    staging folder is removed and ``target`` is left absent. Raises FolderBusy when another
    run writes ``target``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    lock_path = target.parent / f".{target.name}.lock"
    with open(lock_path, "a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            who = lock.read().strip() or "?"
            raise FolderBusy(f"{target}: another natcoord run (pid {who}) is writing this "
                             "folder; wait for it or give another --out") from None
        lock.seek(0)
        lock.truncate()
        lock.write(str(os.getpid()))
        lock.flush()
        previous = target.parent / f".{target.name}.previous"
        if target.is_symlink() or target.is_file():
            target.unlink()
        elif target.exists():
            shutil.rmtree(previous, ignore_errors=True)
            os.replace(target, previous)
        staging = target.parent / f".{target.name}.staging-{os.getpid()}"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        try:
            yield staging
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        os.replace(staging, target)


def point_latest(link: Path, target: Path) -> None:
    """Make ``link`` (e.g. reports/latest) a symlink to ``target``, atomically. A real
    folder in its place (from an older natcoord) is moved beside ``target`` first."""
    link = Path(link)
    if link.exists() and not link.is_symlink():
        os.replace(link, stamped(Path(target).parent, "earlier"))
    tmp = link.parent / f".{link.name}.tmp-{os.getpid()}"
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(os.path.relpath(Path(target).resolve(), link.parent.resolve()))
    os.replace(tmp, link)
