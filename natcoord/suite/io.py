"""Atomic file writes: a crash or Ctrl-C leaves the old file or the new one, never half;
and a lock for read-modify-write updates of a shared file."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pandas as pd

from ..errors import StoredFileError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(path: Path, text: str, *, replace: bool = True) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename.
    The file gets ordinary permissions (0666 less the umask), not the temporary's 0600.
    With ``replace=False`` an existing ``path`` is kept (FileExistsError): the temporary is
    linked into place, which fails when the name exists, so no reader ever sees part of it.
    A symbolic link (a user's baseline kept elsewhere) is never replaced: the file it
    leads to is written the same way, in that file's folder (a rename over the link would
    put a file in its place and leave its target as it was); a link loop, or a link into a
    folder that does not exist, raises OSError."""
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
        if path.is_symlink():  # a loop: realpath stops at a link
            raise OSError(errno.ELOOP, os.strerror(errno.ELOOP), str(path))
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def check_user_file(path: Path, *, force: bool = False) -> None:
    """What :func:`write_user_file` refuses, checked before the work that makes the text:
    NatcoordError when ``path`` is a folder, symlink or special file, or exists without
    ``force``."""
    from ..errors import NatcoordError

    path = Path(path)
    for parent in path.parents:  # the nearest that exists must be a folder
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                raise NatcoordError(f"{path}: cannot be written: {parent} is a file, not "
                                    "a folder")
            break
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise NatcoordError(f"{path}: exists and is not a regular file; not replaced")
    if path.exists() and not force:
        raise NatcoordError(f"{path}: exists; give --force to replace it")


def check_folder(path: Path, option: str) -> None:
    """Check, before the work, that files can be written in the folder ``path`` (given as
    ``option``), making nothing: it, or the nearest part of it that exists, must be a
    folder (else NatcoordError, exit 2) that this process may write (else
    EnvironmentFault, exit 5)."""
    from ..errors import EnvironmentFault, NatcoordError, unwritable

    bad = unwritable(path)
    if bad is None:
        return
    part, is_file = bad
    if is_file:
        raise NatcoordError(f"{option} {path}: cannot be a folder: {part} is a file, not a "
                            "folder")
    raise EnvironmentFault(f"{option} {path}: {part} cannot be written (permission denied "
                           "or a read-only folder)")


# errors of a path that cannot name the file to write (bad input), not of the machine
_BAD_PATH = (errno.ENOTDIR, errno.ENAMETOOLONG, errno.ELOOP, errno.EISDIR, errno.ENOENT)


def write_user_file(path: Path, text: str, *, force: bool = False) -> None:
    """Write a file a user named on the command line (a case file, a proposal): an existing
    file is kept unless ``force``, and a folder, symlink or special file in its place is
    never replaced; NatcoordError naming the path otherwise (EnvironmentFault when the
    machine refuses the write: a read-only folder, a full disk)."""
    from ..errors import EnvironmentFault, NatcoordError

    path = Path(path)
    check_user_file(path, force=force)
    try:
        write_atomic(path, text, replace=force)
    except FileExistsError:
        raise NatcoordError(f"{path}: exists; give --force to replace it") from None
    except OSError as e:
        if e.errno in _BAD_PATH:  # the path given cannot name the file: bad input
            raise NatcoordError(f"{path}: cannot be written ({e.strerror or e})") from None
        # the machine: a read-only folder, permissions, a full disk (exit 5)
        raise EnvironmentFault(f"{path}: cannot be written ({e.strerror or e}: a fault of "
                               "the environment)") from None


def _clean(x):
    """JSON-safe copy: NaN and inf become null, numpy scalars plain numbers."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "item") and not isinstance(x, (str, bytes)):
        try:
            x = x.item()
        except (ValueError, AttributeError):
            x = x.tolist()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def json_text(data) -> str:
    """``data`` as strict JSON (NaN and inf as null, never the NaN/Infinity tokens a JSON
    reader refuses; an object JSON has no type for as its text)."""
    return json.dumps(_clean(data), indent=1, default=str, allow_nan=False)


def write_json(path: Path, data) -> None:
    write_atomic(path, json_text(data) + "\n")


def write_csv(path: Path, table: pd.DataFrame) -> None:
    write_atomic(path, table.to_csv(index=False, float_format="%.17g"))


MAX_STORED_BYTES = 1 << 30  # no stored file natcoord writes comes near this


def read_json(path: Path):
    """The JSON content of a stored file. A file that cannot be read or is not JSON raises
    StoredFileError naming the file and the problem (the command exits 2)."""
    path = Path(path)
    try:
        if not path.is_file():
            raise StoredFileError(f"{path}: " + ("is a folder, not a JSON file" if path.is_dir()
                                                 else "no such file" if not path.exists()
                                                 else "not a regular file"))
        with open(path, encoding="utf-8") as f:
            text = f.read(MAX_STORED_BYTES + 1)
        if len(text) > MAX_STORED_BYTES:
            raise StoredFileError(f"{path}: larger than {MAX_STORED_BYTES} bytes")
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise StoredFileError(f"{path}: not valid JSON ({e})") from None
    except UnicodeDecodeError as e:
        raise StoredFileError(f"{path}: not UTF-8 text ({e.reason})") from None
    except RecursionError:
        raise StoredFileError(f"{path}: nested too deeply") from None
    except OSError as e:
        raise StoredFileError(f"{path}: cannot be read ({e.strerror or e})") from None


def read_csv(path: Path) -> pd.DataFrame:
    """A stored CSV table (results, references). A file that cannot be read or parsed
    raises StoredFileError naming the file and the problem (the command exits 2)."""
    path = Path(path)
    try:
        if not path.is_file():
            raise StoredFileError(f"{path}: " + ("no such file" if not path.exists()
                                                 else "not a regular file"))
        return pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError) as e:
        if isinstance(e, StoredFileError):
            raise
        raise StoredFileError(f"{path}: not a readable CSV table ({e})") from None
    except OSError as e:
        raise StoredFileError(f"{path}: cannot be read ({e.strerror or e})") from None


@contextlib.contextmanager
def locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock for updating ``path`` (waiting for another holder): a lock file
    ``.<name>.lock`` beside it, so that readers of ``path`` are never blocked and an atomic
    replacement of ``path`` does not lose the lock."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.parent / f".{path.name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
