"""Results folders with integrity: one writer at a time, published whole or not at all,
and nothing natcoord did not write is ever removed or moved.

Every results folder natcoord publishes holds a marker, ``.natcoord-results`` (JSON: the
natcoord version, the command, when, and every file the command wrote). A command writes
into a staging folder beside its target (``.<name>.staging-<pid>``) and, when it
completes, swaps it in for the target. The target may be absent, an empty folder or a
previous natcoord results folder holding only what natcoord wrote; anything else (a file,
a link, a user's folder, a results folder with files added by hand) is refused before
anything is written. A previous results folder stays as it is until the new one is
complete; then the files its marker lists are removed, and nothing else. An interrupted,
crashed or refused command publishes nothing and leaves the previous folder as it was.
A lock file beside the target keeps a second command from writing the same folder (it is
refused with the other command's pid); staging folders of commands that were killed (their
pid is gone) are removed by the next command in the same parent folder, which also puts
back a previous folder that a command killed while swapping had set aside.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime as dt
import errno
import fcntl
import json
import os
import re
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

from .. import __version__
from ..errors import NatcoordError
from .io import write_atomic

MARKER = ".natcoord-results"
_STAGING = re.compile(r"^\.(?P<name>.+)\.(?P<kind>staging|replaced)-(?P<pid>\d+)$")
# the lock file of a stamped folder's name (see stamped): a reservation
_RESERVED = re.compile(r"^\.(?P<name>\d{8}T\d{6}Z-.+)\.lock$")


class FolderBusy(NatcoordError):
    """Another run holds the lock of the results folder."""


class NotResults(NatcoordError):
    """The target exists and is not a results folder natcoord may replace."""


def stamped(parent: Path, kind: str) -> Path:
    """A fresh folder name under ``parent``, ``<UTC time>-<kind>`` (then ``-2``, ``-3`` ...),
    reserved for this command: a name is free when nothing of it is in ``parent`` (the
    folder, its lock, a staging or set-aside folder of it), and taken by creating its lock
    file exclusively with this command's pid. Two commands started in the same second so
    get two folders (checking the folder alone gave both the same name, and the second
    was refused as a writer of the first's folder). The reservation is the lock file that
    :func:`publishing` then holds and removes; a command that ends before (refused or
    killed) leaves it, and the next command in ``parent`` removes it once its pid is gone
    (:func:`clean_stale`)."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    present = os.listdir(parent)
    k = 1
    while True:
        name = f"{stamp}-{kind}" + (f"-{k}" if k > 1 else "")
        k += 1
        if name in present or any(n.startswith(f".{name}.") for n in present):
            continue
        lock = parent / f".{name}.lock"
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue  # another command took it since the listing
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        if os.path.lexists(parent / name):  # published (and its lock removed) meanwhile
            lock.unlink(missing_ok=True)
            continue
        return parent / name


# ---- the marker ---------------------------------------------------------------------------
def read_marker(folder: Path) -> dict | None:
    """The marker of a natcoord results folder, or None when ``folder`` has no valid one."""
    path = Path(folder) / MARKER
    if path.is_symlink() or not path.is_file():
        return None
    try:
        with open(path, encoding="utf-8") as f:
            data = json.loads(f.read(1 << 22))
    except (OSError, ValueError, RecursionError):  # RecursionError: nested too deeply
        return None
    if not (isinstance(data, dict) and data.get("natcoord") and isinstance(data.get("files"),
                                                                            list)
            and all(isinstance(p, str) for p in data["files"])):
        return None
    return data


def _write_marker(folder: Path, kind: str, files: list[str], state: str) -> None:
    data = {"natcoord": __version__, "command": kind, "state": state, "pid": os.getpid(),
            "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "files": files}
    (Path(folder) / MARKER).write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")


def _relist(folder: Path, data: dict, files: list[str]) -> None:
    """Replace the file list of ``folder``'s marker (``data``, as read), atomically: a
    reader sees the old marker or the new one, never part of one."""
    write_atomic(Path(folder) / MARKER, json.dumps({**data, "files": files}, indent=1) + "\n")


def _listing(folder: Path) -> tuple[list[str], list[str]]:
    """(files, other entries) under ``folder``, relative paths; links and special files
    are 'other' (never followed)."""
    files, other = [], []
    for root, dirs, names in os.walk(folder):
        for d in list(dirs):
            if os.path.islink(os.path.join(root, d)):
                dirs.remove(d)
                other.append(os.path.relpath(os.path.join(root, d), folder))
        for n in names:
            p = os.path.join(root, n)
            rel = os.path.relpath(p, folder)
            (files if os.path.isfile(p) and not os.path.islink(p) else other).append(rel)
    return sorted(files), sorted(other)


def _ours(folder: Path, files: list[str]) -> set[str]:
    """The sub-folders natcoord makes in ``folder`` for ``files`` (relative paths): their
    parents, and ``results`` with the folder of every case in it."""
    out = {"results"} | {os.path.relpath(p, folder) for p in Path(folder).glob("results/*")
                         if p.is_dir() and not p.is_symlink()}
    for f in files:
        parts = Path(f).parts[:-1]
        out |= {os.path.join(*parts[:k]) for k in range(1, len(parts) + 1)}
    return out


def _foreign(folder: Path) -> list[str]:
    """Entries of a natcoord results folder that its marker does not list (a user's),
    empty folders included."""
    marker = read_marker(folder) or {"files": []}
    files, other = _listing(folder)
    listed = set(marker["files"]) | {MARKER}
    ours = _ours(folder, marker["files"])
    folders = [os.path.relpath(os.path.join(r, d), folder) for r, ds, _ in os.walk(folder)
               for d in ds if not os.path.islink(os.path.join(r, d))]
    return sorted([f for f in files if f not in listed] + other
                  + [d for d in folders if d not in ours])


def _remove_written(folder: Path) -> bool:
    """Remove the files ``folder``'s marker lists, then the folders natcoord made for
    them (:func:`_ours`) left empty; True when nothing is left (the folder itself is
    gone)."""
    marker = read_marker(folder)
    if marker is None:
        return False
    root = Path(folder).resolve()
    for rel in marker["files"]:
        p = (root / rel)
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            continue  # a marker never names a path outside its folder
        if p.is_file() and not p.is_symlink():
            p.unlink()
    (root / MARKER).unlink(missing_ok=True)
    for rel in sorted(_ours(root, marker["files"]), key=lambda d: -len(Path(d).parts)) + ["."]:
        with contextlib.suppress(OSError):
            os.rmdir(root / rel)  # only empty folders go
    return not root.exists()


# ---- checks -------------------------------------------------------------------------------
def check_target(target: Path) -> None:
    """Refuse (NotResults) a target that natcoord may not replace: anything but an absent
    path, an empty folder, or a natcoord results folder holding only what natcoord wrote."""
    target = Path(target)
    if target.is_symlink():
        raise NotResults(f"{target}: --out is a symbolic link; give a new folder or a "
                         "natcoord results folder itself")
    if not target.exists():
        return
    if not target.is_dir():
        raise NotResults(f"{target}: --out exists and is not a folder; natcoord never "
                         "replaces a file: give a new folder")
    if not any(target.iterdir()):
        return
    if read_marker(target) is None:
        raise NotResults(f"{target}: --out is a folder that natcoord did not write (no "
                         f"valid {MARKER} marker); natcoord only replaces its own results "
                         "folders: give a new or empty folder")
    foreign = _foreign(target)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5
                                          else "")
        raise NotResults(f"{target}: this results folder holds files natcoord did not "
                         f"write ({shown}); move them or give another --out")


# ---- adding files to a published folder ---------------------------------------------------
@contextlib.contextmanager
def recording(folder: Path, names: list[str]) -> Iterator[None]:
    """Write the files ``names`` (relative paths) into a folder after it was published
    (``report`` adds index.html): the block writes them, the folder's marker lists them, so
    that it stays a natcoord results folder that ``--out`` may replace. Under the folder's
    lock (FolderBusy while another command writes it); the marker lists every name before
    the block (a file a killed block leaves behind is natcoord's) and, after it, those
    that exist (what it listed before stays). A folder without a valid marker is no
    natcoord results folder: it gets none (with one, ``--out`` would take it for
    natcoord's and remove what it lists); a staging folder's command lists its files
    itself when it completes."""
    folder = Path(os.path.realpath(folder))
    data = read_marker(folder)
    if data is None or data.get("state") == "staging":
        yield
        return
    with contextlib.ExitStack() as held:
        try:  # FolderBusy (not an OSError) goes up: another command writes the folder
            held.enter_context(_locked(folder, "run this again when it has finished"))
        except OSError:
            pass  # no lock file beside it: no command can stage a replacement there either
        data = read_marker(folder)  # again, under the lock
        if data is None or data.get("state") == "staging":
            yield
            return
        before = list(data["files"])
        _relist(folder, data, before + [n for n in names if n not in before])
        try:
            yield
        finally:
            _relist(folder, data, before + [n for n in names if n not in before and
                                            (folder / n).is_file()])


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ---- the lock -----------------------------------------------------------------------------
@contextlib.contextmanager
def _locked(target: Path, hint: str = "wait for it or give another --out") -> Iterator[None]:
    """Hold the lock of ``target`` (``.<name>.lock`` beside it), or raise FolderBusy (its
    message ends with ``hint``). The lock file is removed on release (a waiter that opened
    it retries on the new one)."""
    lock_path = target.parent / f".{target.name}.lock"
    while True:
        lock = open(lock_path, "a+")  # noqa: SIM115 - held open for the whole block
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            who = lock.read().strip() or "?"
            lock.close()
            raise FolderBusy(f"{target}: another natcoord run (pid {who}) is writing this "
                             f"folder; {hint}") from None
        try:
            same = os.stat(lock_path).st_ino == os.fstat(lock.fileno()).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        lock.close()  # removed by its last holder while we opened it: take the new one
    try:
        lock.seek(0)
        lock.truncate()
        lock.write(str(os.getpid()))
        lock.flush()
        yield
    finally:
        with contextlib.suppress(OSError):
            lock_path.unlink()
        lock.close()


def clean_stale(parent: Path, held: str = "") -> list[Path]:
    """Tidy what killed commands left in ``parent`` (their pid is gone and their target's
    lock is free). A staging folder goes whole (natcoord made it). A set-aside previous
    results folder goes back in its target's place when the target is absent (the command
    was killed between the two renames of :func:`_swap`); it loses the files its marker
    lists only when the target holds that command's new results, and is kept otherwise.
    The lock file of a stamped name (:func:`stamped`) whose command is gone goes too.
    ``held``: the name of a target whose lock the caller holds already. Returns what was
    removed or put back."""
    removed = []
    try:
        entries = list(Path(parent).iterdir())
    except OSError:
        return removed
    for p in entries:
        m = _STAGING.match(p.name)
        if not m:
            lock = _RESERVED.match(p.name)
            if lock and lock["name"] != held and _stale_lock(p):
                with contextlib.suppress(FolderBusy, OSError), \
                        _locked(Path(parent) / lock["name"]):
                    removed.append(p)  # the lock file goes on release
            continue
        if p.is_symlink() or not p.is_dir() or int(m["pid"]) == os.getpid() \
                or _pid_alive(int(m["pid"])) or read_marker(p) is None:
            continue
        target = Path(parent) / m["name"]
        try:
            with contextlib.nullcontext() if m["name"] == held else _locked(target):
                if not p.exists():
                    continue  # tidied by another command meanwhile
                if m["kind"] == "staging":
                    shutil.rmtree(p)
                    removed.append(p)
                elif (fate := _set_aside_fate(p, target, int(m["pid"]))) == "put back":
                    _rename_noreplace(p, target)
                    removed.append(target)
                elif fate == "replaced":
                    _remove_written(p)
                    removed.append(p)
        except (FolderBusy, OSError):
            continue
    return removed


def _stale_lock(path: Path) -> bool:
    """True when the lock file ``path`` names a process that is gone (an empty one is
    being written: not stale)."""
    try:
        if path.is_symlink() or not path.is_file():
            return False
        text = path.read_text(encoding="ascii", errors="replace").strip()
    except OSError:
        return False
    return text.isdigit() and int(text) != os.getpid() and not _pid_alive(int(text))


def _set_aside_fate(aside: Path, target: Path, pid: int) -> str:
    """What becomes of ``aside``, the previous results of ``target`` that the killed
    command ``pid`` set aside in :func:`_swap`: "put back", "replaced" (its written files
    go) or "kept".

    ``target`` absent: the command was killed between the two renames; its staging folder
    holds its complete new results, ``aside`` the previous ones. The previous ones go back
    (a rename that replaces nothing: nothing is deleted), the staging folder goes as any
    killed command's: a killed command publishes nothing and leaves the previous folder as
    it was. Promoting the staging folder instead would publish results their command never
    reported, without the rest of its ending (``reports/latest``, a suite's report and
    history record), and its marker proves only that its files were listed, not that the
    command finished what it meant to do. ``target`` holding the command's own marker: it
    was killed after the swap, while removing the previous files. Anything else in
    ``target`` (put there by hand since): ``aside`` is kept, with a warning."""
    if not target.exists() and not target.is_symlink():
        return "put back"
    marker = None if target.is_symlink() else read_marker(target)
    if marker is not None and marker.get("pid") == pid:
        return "replaced"
    print(f"warning: {aside} holds the previous results of {target}, set aside by a "
          f"command that was killed (pid {pid}); {target} now holds something else: both "
          "are left as they are", file=sys.stderr)
    return "kept"


def _rename_noreplace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, never replacing ``dst`` (rename(2) would replace an empty
    folder): renameat2's RENAME_NOREPLACE, else a check just before the rename (the
    caller holds ``dst``'s lock, so no natcoord command creates it meanwhile)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        fn = None
    if fn is not None:
        at_fdcwd, rename_noreplace = -100, 1
        if fn(at_fdcwd, os.fsencode(src), at_fdcwd, os.fsencode(dst), rename_noreplace) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.ENOSYS, errno.EINVAL):  # EINVAL: a filesystem without it
            raise OSError(err, os.strerror(err), str(src), None, str(dst))
    if dst.exists() or dst.is_symlink():
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst))
    os.rename(src, dst)


# ---- publishing ---------------------------------------------------------------------------
@contextlib.contextmanager
def publishing(target: Path, kind: str = "run") -> Iterator[Path]:
    """Lock ``target``, check it may be replaced (:func:`check_target`: NotResults
    otherwise), yield a fresh staging folder and, when the block completes, mark it and
    swap it in for ``target``; the previous results folder then loses the files natcoord
    wrote. On any exception (an interruption included) the staging folder is removed and
    ``target`` is left as it was. Raises FolderBusy when another command writes
    ``target``."""
    target = Path(os.path.abspath(target))
    check_target(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with _locked(target):
        check_target(target)  # again, under the lock
        clean_stale(target.parent, held=target.name)
        staging = target.parent / f".{target.name}.staging-{os.getpid()}"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        try:
            _write_marker(staging, kind, [], "staging")
            yield staging
            files, _ = _listing(staging)
            _write_marker(staging, kind, [f for f in files if f != MARKER], "complete")
            _swap(staging, target)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise


def _swap(staging: Path, target: Path) -> None:
    """Put ``staging`` in ``target``'s place; a previous results folder there is set aside
    and loses what natcoord wrote (a file added meanwhile keeps it, named in a warning)."""
    if not target.exists():
        os.replace(staging, target)
        return
    check_target(target)
    if not any(target.iterdir()):
        os.replace(staging, target)  # over an empty folder
        return
    aside = target.parent / f".{target.name}.replaced-{os.getpid()}"
    os.replace(target, aside)
    try:
        os.replace(staging, target)
    except BaseException:
        os.replace(aside, target)
        raise
    if not _remove_written(aside):
        print(f"warning: {aside} keeps files added to the previous results folder while "
              "this command ran; nothing else of it is left", file=sys.stderr)


def point_latest(link: Path, target: Path) -> bool:
    """Make ``link`` (e.g. reports/latest) a symlink to ``target``, atomically. Anything
    but a symlink in its place (a user's folder or file) is left alone: returns False."""
    link = Path(link)
    if link.exists() and not link.is_symlink():
        return False
    tmp = link.parent / f".{link.name}.tmp-{os.getpid()}"
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(os.path.relpath(Path(target).resolve(), link.parent.resolve()))
    os.replace(tmp, link)
    return True
