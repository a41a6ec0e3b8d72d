"""The evidence behind a verdict: one cell's result files, checked and judged.

``natcoord run`` judges each case x engine with :func:`judge_cell` and stores in its record
the sha256 of every result file of the cell (``files``); ``gate`` and ``compare`` call the
same function on the same files, checked against those hashes, with the case file's
tolerances and the stored reference. The summary is an index of the cells, never a witness
of their errors. A result file that is missing, altered since the run, unreadable or at
other sample times fails its cell (:class:`BadEvidence`: a regression); a reference that is
missing or damaged is bad input naming the reference file (:class:`BadReference`).

The records themselves are checked against the folder (:func:`unrecorded`): a result file
on disk, or one the folder's marker lists as written by natcoord, with no record in the
summary means a cell was taken out of the summary (or a file put in); a result file the
marker lists that is gone means one was deleted. Either damages the folder's evidence.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import stat
from pathlib import Path, PurePosixPath

import numpy as np
import pandas as pd

from ..case.mechanism import Case, mechanism_parts
from ..errors import NatcoordError, StoredFileError
from . import outdir
from .compare import channel_errors

SUFFIXES = (".csv", ".methods.csv", ".json")  # a cell's result files: <engine><suffix>
NOT_RUN = ("unsupported", "skipped")  # statuses of a cell whose engine never ran it


class BadEvidence(NatcoordError):
    """A cell's result files cannot be trusted or read: the cell fails."""


class BadReference(NatcoordError, ValueError):
    """A case's stored reference is missing or damaged: bad input, naming the file."""


def cell_folder(results: Path, case: str) -> Path:
    return Path(results) / "results" / case


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hashes(results: Path, case: str, engine: str) -> dict[str, str]:
    """sha256 of each result file of a cell that exists, by file name (what ``run`` stores
    in the record's ``files``)."""
    folder = cell_folder(results, case)
    return {f"{engine}{s}": sha256_of((folder / f"{engine}{s}").read_bytes())
            for s in SUFFIXES if (folder / f"{engine}{s}").is_file()}


def _files_on_disk(results: Path) -> list[str]:
    """Every regular file under ``results/results``, as a path relative to ``results``
    (links are not followed)."""
    top = Path(results) / "results"
    out = []
    for root, dirs, names in os.walk(top):
        dirs[:] = [d for d in dirs if not os.path.islink(os.path.join(root, d))]
        out += [os.path.relpath(os.path.join(root, n), results) for n in names
                if os.path.isfile(os.path.join(root, n))]
    return sorted(out)


def _there(path: Path) -> bool:
    """Whether ``path`` is a regular file, or is there but cannot be looked at (an
    unreadable folder: judging its cell says so)."""
    try:
        return stat.S_ISREG(path.stat().st_mode)
    except (FileNotFoundError, NotADirectoryError):
        return False
    except OSError:
        return True


def unrecorded(results: Path, records: list[dict], staged: bool = False) -> list[str]:
    """What the folder holds (or its marker says natcoord wrote in it) that the summary's
    records do not account for, one line each: a result file (``results/<case>/<engine>``
    ``.csv``, ``.methods.csv``, ``.json``) whose cell has no record; a table of results
    whose record says its engine never ran (:data:`NOT_RUN`); a result file or
    ``bench.json`` the marker lists that is gone. A folder without a marker (written by
    :func:`natcoord.suite.runner.run_suite` itself) is checked against its CSVs alone; a
    run of some cases holds no result files of the others, so it passes. Raises
    StoredFileError when the marker is there but unreadable (the list of what natcoord
    wrote is lost: bad input), and when the marker says the command that wrote it did not
    finish (unless ``staged``: the caller judges its own staging folder)."""
    results = Path(results)
    marker = outdir.read_marker(results)
    path = results / outdir.MARKER
    if marker is None and (path.exists() or path.is_symlink()):
        raise StoredFileError(f"{path}: damaged results marker (not natcoord's JSON list of "
                              "the files it wrote): the folder's evidence cannot be checked")
    if marker is not None and not staged and marker.get("state", "complete") != "complete":
        raise StoredFileError(f"{path}: the folder of a command that did not finish (state "
                              f"{str(marker.get('state'))[:20]!r}): its results were never "
                              "published and are not evidence")
    listed = [] if marker is None else [
        f for f in marker["files"]
        if not PurePosixPath(f).is_absolute() and ".." not in PurePosixPath(f).parts]
    mine: dict[str, dict] = {}  # results/<case>/<file> -> the record the file belongs to
    for r in records:
        for s in SUFFIXES:
            mine[f"results/{r['case']}/{r['engine']}{s}"] = r
    lines = []
    on_disk = _files_on_disk(results)
    for rel in sorted({f for f in on_disk if f.endswith(".csv")}
                      | {f for f in listed if f.startswith("results/") and f in on_disk}):
        if rel not in mine:
            lines.append(f"{results / rel} has no record in summary.json (a result of a cell "
                         "the summary does not list: a record was removed, or the file "
                         "added, since the run)")
        elif rel.endswith(".csv") and mine[rel]["status"] in NOT_RUN:
            lines.append(f"{results / rel} holds a run's results, but its record in "
                         f"summary.json says {mine[rel]['status']!r} (a cell that did not "
                         "run writes none: the record was edited since the run)")
    for rel in listed:
        if not (rel.startswith("results/") or rel == "bench.json") or rel in on_disk \
                or _there(results / rel):
            continue
        r = mine.get(rel)
        if r is not None and r["status"] == "ok" and PurePosixPath(rel).name in \
                (r.get("files") or {}):
            continue  # judging its cell says it is missing
        lines.append(f"{results / rel}: missing (the folder's {outdir.MARKER} lists it as "
                     "written by natcoord: deleted since)")
    return lines


def bench_checked(results: Path, summary: dict) -> str | None:
    """Check ``results/bench.json`` against the sha256 the suite stored in its summary
    (``bench_sha256``): BadEvidence naming the file when it is gone, a link or altered
    since the run. Returns a note for a bench.json the summary does not list (a folder
    of ``run`` plus ``bench --out``, or of a natcoord before the hash): read as it is."""
    path = Path(results) / "bench.json"
    want = summary.get("bench_sha256")
    if want is None:
        return (f"{path}: not listed in summary.json (no sha256 of it stored by the run): "
                "its figures are judged as they are") if (path.exists() or
                                                          path.is_symlink()) else None
    _checked_bytes(path, want)
    return None


def _checked_bytes(path: Path, want: str) -> bytes:
    """The bytes of a file the run wrote and hashed (``want``, its sha256 in summary.json);
    BadEvidence naming it when it is gone, not a regular file (a link, a FIFO that would
    hang the read, a device that would never end it), unreadable or altered."""
    try:
        if not stat.S_ISREG(path.lstat().st_mode):
            raise BadEvidence(f"{path}: not a regular file" + (
                " (a symbolic link)" if path.is_symlink() else ""))
        blob = path.read_bytes()
    except FileNotFoundError:
        raise BadEvidence(f"{path}: missing (deleted since the run)") from None
    except OSError as e:
        raise BadEvidence(f"{path}: unreadable ({e.strerror or e})") from None
    if sha256_of(blob) != want:
        raise BadEvidence(f"{path}: altered since the run (its sha256 is not the one the "
                          "run stored in summary.json)")
    return blob


def _read_checked(results: Path, case: str, engine: str, files: dict[str, str]) -> bytes:
    """The bytes of the cell's CSV, after checking every file the run hashed; raises
    BadEvidence naming the file and what is wrong with it."""
    folder = cell_folder(results, case)
    csv_name = f"{engine}.csv"
    if not isinstance(files, dict) or csv_name not in files:
        raise BadEvidence(f"{folder / csv_name}: no content hash in the summary (written by "
                          "an older natcoord, or the summary was edited): run it again")
    for part in (Path(results) / "results", folder):  # links lead out of the folder the
        if part.is_symlink():                          # run wrote: to files it did not
            raise BadEvidence(f"{part}: a symbolic link, not the folder the run wrote")
    data = b""
    for name in (f"{engine}{s}" for s in SUFFIXES):
        if name in files:
            blob = _checked_bytes(folder / name, files[name])
            data = blob if name == csv_name else data
    return data


def read_table(data: bytes, path: Path, case: Case) -> pd.DataFrame:
    """A result CSV's table: numbers only, one column per name, at the case's sample
    times."""
    header = next(csv.reader([data.split(b"\n", 1)[0].decode("utf-8", "replace")]), [])
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:  # pandas would rename the second one and judge the first
        raise BadEvidence(f"{path}: duplicate columns ({', '.join(twice)[:200]})")
    try:
        table = pd.read_csv(io.BytesIO(data))
        table = table.apply(pd.to_numeric, errors="raise").astype(float)
    except (ValueError, TypeError, pd.errors.ParserError, pd.errors.EmptyDataError) as e:
        raise BadEvidence(f"{path}: unreadable ({type(e).__name__}: {e})") from None
    t = table["t"].to_numpy() if "t" in table else np.zeros(0)
    if len(t) != len(case.times) or not np.allclose(t, case.times, atol=1e-9):
        raise BadEvidence(f"{path}: {len(t)} samples at other times than the case's "
                          f"{len(case.times)}")
    return table


def read_reference(case: Case, directory: Path) -> tuple[pd.DataFrame, tuple[str, ...]]:
    """The stored reference of a case and its undetermined channels, checked: every channel
    of the case present and finite at the case's sample times, the provenance readable.
    Raises BadReference naming the file and the problem."""
    csv = Path(directory) / f"{case.name}.csv"
    prov = Path(directory) / f"{case.name}.json"
    fix = f"run `natcoord reference update {case.name}`"
    if not csv.is_file():
        raise BadReference(f"{csv}: no reference stored for case {case.name}; {fix}")
    try:
        table = pd.read_csv(csv)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError,
            pd.errors.EmptyDataError) as e:
        raise BadReference(f"{csv}: unreadable reference ({type(e).__name__}: {e})") from None
    try:
        provenance = json.loads(prov.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BadReference(f"{prov}: the reference's provenance is missing; {fix}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BadReference(f"{prov}: unreadable provenance ({e})") from None
    problem = reference_problem(case, table, provenance)
    if problem:
        raise BadReference(f"{csv}: {problem}; {fix}")
    undetermined = provenance.get("undetermined", []) if isinstance(provenance, dict) else None
    names = {c.name for c in case.channels}
    if not isinstance(undetermined, list) or not all(
            isinstance(x, str) and x in names for x in undetermined):
        raise BadReference(f"{prov}: undetermined: must be a list of the case's channel "
                           f"names, got {str(undetermined)[:80]}; {fix}")
    return table[["t", *names_in_order(case)]].astype(float), tuple(undetermined)


def names_in_order(case: Case) -> list[str]:
    return [c.name for c in case.channels]


def reference_problem(case: Case, table: pd.DataFrame, provenance=None) -> str:
    """What makes a reference table unfit to judge a case ("" when nothing): a channel of
    the case missing (renamed, damaged or stale), values that are not finite numbers,
    sample times other than the case's; with its ``provenance``, a part of the case's
    mechanism changed since the reference was computed (the digests of
    :func:`natcoord.case.mechanism.mechanism_parts` it stores; a reference without them is
    not checked so)."""
    stale = _stale_mechanism(case, provenance)
    if stale:
        return stale
    need = ["t", *names_in_order(case)]
    missing = [c for c in need if c not in table]
    if missing:
        return (f"reference lacks column(s) {', '.join(missing)} of case {case.name} "
                "(renamed, damaged or stale)")
    if not table.columns.is_unique:
        return "reference has duplicate columns"
    try:
        values = table[need].apply(pd.to_numeric, errors="raise").astype(float)
    except (ValueError, TypeError) as e:
        return f"reference holds values that are not numbers ({e})"
    bad = [c for c in need if not np.all(np.isfinite(values[c].to_numpy()))]
    if bad:
        return f"non-finite values (NaN or inf) in the reference's {', '.join(bad)}"
    t = values["t"].to_numpy()
    if len(t) != len(case.times) or not np.allclose(t, case.times, atol=1e-9):
        return "reference sample times differ from the case's (stale)"
    return ""


def _stale_mechanism(case: Case, provenance) -> str:
    """The parts of the case's mechanism whose digest differs from the one its reference's
    provenance stores ("" when none, or when it stores none)."""
    stored = provenance.get("mechanism") if isinstance(provenance, dict) else None
    if stored is None:
        return ""
    if not isinstance(stored, dict):
        return "the provenance's mechanism is not a table of part digests"
    changed = [p for p, h in mechanism_parts(case).items() if stored.get(p) != h]
    if not changed:
        return ""
    return (f"computed for another mechanism: the case's {', '.join(changed)} changed "
            "since (stale)")


def judge_cell(case: Case, engine: str, results: Path, references: Path,
               files: dict[str, str]) -> dict:
    """Errors and verdict of one cell, recomputed from its result files (each checked
    against ``files``, the sha256 the run stored), the stored reference and the case file's
    tolerances: ``{"channels", "verdict", "verdict_reason"}`` as in
    :func:`natcoord.suite.compare.channel_errors`. Raises BadEvidence (the cell fails) or
    BadReference (bad input)."""
    data = _read_checked(results, case.name, engine, files)
    table = read_table(data, cell_folder(results, case.name) / f"{engine}.csv", case)
    reference, undetermined = read_reference(case, references)
    channels, verdict, why = channel_errors(case, engine, table, reference, undetermined)
    return {"channels": channels, "verdict": verdict, "verdict_reason": why}
