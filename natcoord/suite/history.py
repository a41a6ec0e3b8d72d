"""The nightly history in an embedded database (SQLite, WAL mode, versioned schema).

Readers (the gate, the report, compare) open it read-only with a bounded wait; a file that
is not natcoord's history (another schema, not SQLite, damaged, a folder) is refused with
the file and the problem, and never modified.

One row per run (``runs``), per case x engine x channel result (``results``) and per case x
engine benchmark with the raw wall time of every repeat (``bench``), with provenance: the
natcoord version and git commit, the sha256 of the case file, engine versions, settings and
the machine fingerprint (CPU model, cores). Several suites may append at once: each run is
one transaction that waits for the database (``BEGIN IMMEDIATE`` with a busy timeout).
Lines of the former ``history.jsonl`` are imported once. CPU-time samples, where a bench
measured them, are in ``bench_cpu``; samples relative to the reference work measured
beside each (:func:`natcoord.suite.speed.relative`), per clock, in ``bench_relative``.
"""

from __future__ import annotations

import json
import os
import sqlite3
import statistics
import subprocess
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import closing, contextmanager
from pathlib import Path
from typing import NamedTuple
from urllib.parse import quote_from_bytes

from ..errors import EnvironmentFault, NatcoordError, StoredFileError
from . import speed

SCHEMA_VERSION = 1
# Every table's columns: their SQL declaration and what a row's value may hold ("?": or
# NULL; None: not checked), in the order of the table (rows are inserted by position). One
# source for the tables a history gets, the columns it must have and the check of its rows:
# every row of a history is checked before anything reads it (a damaged row is named,
# exit 2, never a crash in whoever reads it).
RUN_ID = ("INTEGER REFERENCES runs(id)", "run")
CELL = {"run_id": RUN_ID, "case_name": ("TEXT", "text"), "engine": ("TEXT", "text"),
        "case_hash": ("TEXT", "text?")}  # the columns that name a run's cell, first
COLUMNS: dict[str, dict[str, tuple[str, str | None]]] = {
    "meta": {"key": ("TEXT PRIMARY KEY", None), "value": ("TEXT", None)},
    "runs": {"id": ("INTEGER PRIMARY KEY", None), "generated": ("TEXT", "text?"),
             "kind": ("TEXT", "text?"), "natcoord_version": ("TEXT", "text?"),
             "git_commit": ("TEXT", "text?"), "machine": ("TEXT", "text?"),
             "machine_info": ("TEXT", "text?"), "gate": ("INTEGER", "integer?"),
             "results_dir": ("TEXT", "text?")},
    "results": {**CELL, "engine_version": ("TEXT", "text?"), "status": ("TEXT", "text?"),
                "verdict": ("TEXT", "text?"), "settings": ("TEXT", "text?"),
                "channel": ("TEXT", "text?"), "kind": ("TEXT", "text?"),
                "max_abs": ("REAL", "number?"), "max_rel": ("REAL", "number?"),
                "tolerance": ("REAL", "number?"), "determined": ("INTEGER", "integer?")},
    "bench": {**CELL, "engine_version": ("TEXT", "text?"), "settings": ("TEXT", "text?"),
              "samples": ("TEXT", "samples"), "wall_time_s": ("REAL", "number?"),
              "us_per_step": ("REAL", "number?"), "n_steps": ("INTEGER", "integer?"),
              "counters": ("TEXT", "json object")},
    # CPU time per run of each sample (natcoord)
    "bench_cpu": {**CELL, "samples": ("TEXT", "samples")},
    # the cells a run's speed gate found slower (not accepted): no baseline for later runs
    "slower": {"run_id": ("INTEGER REFERENCES runs(id)", None), "case_name": ("TEXT", None),
               "engine": ("TEXT", None)},
    # samples / the reference work measured after each (clock 'wall' or 'cpu')
    "bench_relative": {**CELL, "clock": ("TEXT", "text"), "samples": ("TEXT", "samples")},
}
# the tables of every natcoord history; the others came later: a history written before
# them lacks them until its next write, and they are checked where present
REQUIRED = ("meta", "runs", "results", "bench")
INDEXES = ("CREATE INDEX IF NOT EXISTS results_cell ON results (case_name, engine, channel)",
           "CREATE INDEX IF NOT EXISTS bench_cell ON bench (case_name, engine, case_hash)")
ROWS = {t: {c: kind for c, (_, kind) in cols.items() if kind}
        for t, cols in COLUMNS.items() if any(kind for _, kind in cols.values())}


def _create(table: str) -> str:
    """The CREATE statement of ``table`` (:data:`COLUMNS`); nothing when it exists."""
    return (f"CREATE TABLE IF NOT EXISTS {table} ("
            + ", ".join(f"{c} {decl}" for c, (decl, _) in COLUMNS[table].items()) + ")")


READ_WAIT_S = 5.0  # a reader waits this long for a writer, then says so
WRITE_WAIT_S = 60.0


class HistoryError(StoredFileError):
    """The history database cannot be used: not natcoord's, damaged, unreadable or locked
    (names the file and the problem; exit 2). It is never modified then."""


class ChangedWhileRead(HistoryError):
    """A run was recorded into the history while it was read (run the command again)."""


class HistoryFull(EnvironmentFault):
    """The disk holding the history database is full (exit 5)."""


def _problem(path: Path, e: sqlite3.Error, wait_s: float) -> NatcoordError:
    """The error to raise for an SQLite error on ``path``: the file and the problem."""
    text = str(e)
    if "locked" in text or "busy" in text:
        return HistoryError(f"{path}: locked by another process for more than {wait_s:g} s "
                            "(a suite writing it?); try again when it has finished")
    if "full" in text:
        return HistoryFull(f"{path}: the disk is full ({text})")
    if "readonly" in text or "read-only" in text:
        return HistoryError(f"{path}: cannot be written ({text}): make it and its folder "
                            "writable, or give another --history")
    if "not a database" in text or "malformed" in text or "corrupt" in text:
        return HistoryError(f"{path}: not a natcoord history database, or damaged ({text})")
    return HistoryError(f"{path}: cannot be used as the history database ({text})")


def _check_file(path: Path) -> None:
    if path.is_dir():
        raise HistoryError(f"{path}: is a folder, not a history database")
    if path.exists() and not path.is_file():
        raise HistoryError(f"{path}: is not a regular file, not a history database")
    if path.exists() and not os.access(path, os.R_OK):
        raise HistoryError(f"{path}: cannot be read (permission denied)")


def _check_schema(path: Path, db: sqlite3.Connection) -> bool:
    """Raise HistoryError unless ``db`` is natcoord's history (or holds no table at all:
    then False, a new database). Checks the integrity too (a truncated file)."""
    names = {n for (n,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if not names:
        return False
    for table in (t for t in COLUMNS if t in REQUIRED or t in names):
        columns = set(COLUMNS[table])
        have = {r[1] for r in db.execute(f"PRAGMA table_info({table})")}
        if not columns <= have:
            raise HistoryError(f"{path}: not a natcoord history database (table {table!r} "
                               f"{'lacks columns' if have else 'missing'}; it has tables "
                               f"{', '.join(sorted(names))[:200]})")
    row = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    if row is None or not str(row[0]).isdigit():
        raise HistoryError(f"{path}: not a natcoord history database (no schema version)")
    if int(row[0]) > SCHEMA_VERSION:
        raise HistoryError(f"{path}: history schema {row[0]} is newer than this natcoord's "
                           f"({SCHEMA_VERSION}); upgrade natcoord")
    check = db.execute("PRAGMA quick_check").fetchone()
    if not check or check[0] != "ok":
        raise HistoryError(f"{path}: damaged (integrity check: {check and check[0]})")
    _check_rows(path, db, names)
    return True


_STORAGE = {"text": "'text'", "integer": "'integer'", "number": "'integer', 'real'"}
_NAMED = {"text": "text", "integer": "an integer", "number": "a number"}


def _bad(column: str, kind: str) -> list[tuple[str, str]]:
    """(SQL condition true when ``column`` does not hold ``kind`` (see ROWS), what it
    should hold), in the order to test them: a later condition may assume the earlier
    ones false (SQLite's CASE stops at the first true one)."""
    c = f'"{column}"'
    if kind.endswith("?"):
        return [(f"{c} IS NOT NULL AND typeof({c}) NOT IN ({_STORAGE[kind[:-1]]})",
                 f"{_NAMED[kind[:-1]]} or NULL")]
    if kind == "run":
        return [(f"typeof({c}) != 'integer'", "the id of a run"),
                (f"{c} NOT IN (SELECT id FROM runs)", "the id of a run in table runs (a "
                 "deleted run?)")]
    if kind == "samples":
        return [(f"typeof({c}) != 'text' OR NOT json_valid({c})", "a JSON list of times"),
                (f"json_type({c}) != 'array' OR json_array_length({c}) = 0 OR EXISTS ("
                 f"SELECT 1 FROM json_each({c}) WHERE type NOT IN ('integer', 'real'))",
                 "a JSON list of times (numbers, at least one)"),
                # 1e309 is read as infinity (and a view would print it as Infinity)
                (f"EXISTS (SELECT 1 FROM json_each({c}) WHERE NOT IFNULL(value > 0 AND "
                 "value <= 1.7976931348623157e308, 0))",
                 "a JSON list of times (finite and positive)")]
    if kind == "json object":
        return [(f"typeof({c}) != 'text' OR NOT json_valid({c})", "a JSON object"),
                (f"json_type({c}) NOT IN ('object', 'null')", "a JSON object")]
    return [(f"typeof({c}) NOT IN ({_STORAGE[kind]})", _NAMED[kind])]


_ROWS_CHECKED: dict[str, tuple] = {}  # file -> its signature when its rows last passed


def _signature(path: Path) -> tuple:
    """What changes when the database changes: the file's and its write-ahead log's
    identity, size and modification time."""
    out = []
    for p in (path, path.with_name(path.name + "-wal")):
        try:
            st = p.stat()
        except OSError:
            out.append(None)
        else:
            out.append((st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns))
    return tuple(out)


def _check_rows(path: Path, db: sqlite3.Connection, tables: set[str]) -> None:
    """Raise HistoryError naming the table, row and column of the first row that does not
    hold what its columns should (:data:`ROWS`): a number stored as text, samples that
    are not a JSON list of times, a result or benchmark of a run no longer in ``runs``.
    Once per state of the file in a process (a gate opens the history once a cell)."""
    key, signature = str(Path(path).resolve()), _signature(Path(path))
    if _ROWS_CHECKED.get(key) == signature:
        return
    _first_bad_row(path, db, tables)
    _ROWS_CHECKED[key] = signature


def _first_bad_row(path: Path, db: sqlite3.Connection, tables: set[str]) -> None:
    for table, columns in ROWS.items():
        if table not in tables:  # e.g. bench_cpu: a history written before CPU samples
            continue
        tests = [(column, cond, want) for column, kind in columns.items()
                 for cond, want in _bad(column, kind)]
        cases = " ".join(f"WHEN {cond} THEN {k}" for k, (_, cond, _) in enumerate(tests))
        row = db.execute(f"SELECT rowid, bad FROM (SELECT rowid, CASE {cases} END AS bad "
                         f"FROM {table}) WHERE bad IS NOT NULL LIMIT 1").fetchone()
        if row is None:
            continue
        rowid, (column, _, want) = row[0], tests[row[1]]
        (value,) = db.execute(f'SELECT quote("{column}") FROM {table} WHERE rowid = ?',
                              (rowid,)).fetchone()
        value = value if len(value) <= 60 else value[:57] + "..."
        raise HistoryError(f"{path}: damaged row: table {table}, row {rowid}, column "
                           f"{column} holds {value}, not {want}; delete or repair the row, "
                           "or give another --history")


def _wal_size(path: Path) -> int | None:
    """The size of the write-ahead log beside ``path`` (None when there is none)."""
    try:
        return Path(f"{path}-wal").stat().st_size
    except OSError:
        return None


def _stamp(path: Path) -> tuple:
    """What a writer changes: the file's identity, size and time, and whether a
    write-ahead log is beside it and its size."""
    st = path.stat()
    return st.st_ino, st.st_size, st.st_mtime_ns, _wal_size(path)


def _idle_wal(path: Path) -> bool:
    """Whether ``path`` is an SQLite database in WAL mode (header bytes 18-19 = 2) with no
    write-ahead log beside it, or an empty one (no frames: a stale log a killed process or
    a copy left): nothing in a log to read, and a writer that starts meanwhile changes
    the stamp (a database in rollback-journal mode is written in place, under locks only
    a locking open sees)."""
    try:
        with open(path, "rb") as f:
            head = f.read(20)
    except OSError:
        return False
    return head[:16] == b"SQLite format 3\x00" and head[18:20] == b"\x02\x02" \
        and not _wal_size(path)


@contextmanager
def reading(path: Path, wait_s: float = READ_WAIT_S) -> Iterator[sqlite3.Connection | None]:
    """Open the history database read-only, after checking it is natcoord's; yields None
    when there is none yet. Raises HistoryError naming the file and the problem.

    A database in WAL mode with no write-ahead log beside it, or an empty one (no writer
    at work: the last connection's close folds the log in and removes it) is opened
    ``immutable``:
    nothing is created beside it (a plain read-only open of a WAL database leaves
    ``-wal`` and ``-shm`` files), and a file that changed while it was read is an error
    that says to run again. Otherwise it is opened ``mode=ro``, which reads the log and
    waits for a writer's lock."""
    path = Path(path)
    if not path.exists():
        yield None
        return
    _check_file(path)
    idle = _idle_wal(path)
    before = _stamp(path)
    mode = "immutable=1" if idle else "mode=ro"
    # bytes: a name that is not valid UTF-8 (Latin-1 bytes) reaches SQLite as it is
    uri = f"file:{quote_from_bytes(os.fsencode(path.resolve()))}?{mode}"
    try:
        db = sqlite3.connect(uri, uri=True, timeout=wait_s, isolation_level=None)
    except sqlite3.Error as e:
        raise _problem(path, e, wait_s) from None
    with closing(db):
        try:
            db.execute(f"PRAGMA busy_timeout={int(wait_s * 1000)}")
            fresh = not _check_schema(path, db)
        except sqlite3.Error as e:
            raise _problem(path, e, wait_s) from None
        if fresh:
            yield None
            return
        try:
            yield db
        except sqlite3.Error as e:
            raise _problem(path, e, wait_s) from None
        if idle and _stamp(path) != before:
            raise ChangedWhileRead(f"{path}: a run recorded into it while it was read; run "
                                   "the command again")


CHECK_TRIES = 20  # a check that another writer's run overlapped is repeated


def check(path: Path, write: bool = False) -> None:
    """Raise HistoryError unless ``path`` is absent, empty or natcoord's history database
    (and, with ``write``, writable); the file is not touched. A check that another run's
    write overlapped is made again (two nights writing at once lost one of them, "recorded
    into it while it was read")."""
    for tries_left in range(CHECK_TRIES - 1, -1, -1):
        try:
            with reading(path):
                pass
            break
        except ChangedWhileRead:
            if not tries_left:
                raise
    path = Path(path)
    if write and path.exists() and not os.access(path, os.W_OK):
        raise HistoryError(f"{path}: read-only; make it writable or give another --history")


@contextmanager
def connect(path: Path) -> Iterator[sqlite3.Connection]:
    """Open (and create or migrate) the history database for writing; commits on success.
    A file that is not natcoord's history is refused (HistoryError) before anything is
    written to it."""
    path = Path(path)
    check(path)  # read-only first: a foreign or damaged file is never switched to WAL
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        db = sqlite3.connect(path, timeout=WRITE_WAIT_S, isolation_level=None)
    except sqlite3.Error as e:
        raise _problem(path, e, WRITE_WAIT_S) from None
    with closing(db):
        try:
            db.execute(f"PRAGMA busy_timeout={int(WRITE_WAIT_S * 1000)}")
            _wal(db, WRITE_WAIT_S)
            # the schema in one write transaction: BEGIN IMMEDIATE waits for another writer
            # (executescript would commit first and create tables outside any lock)
            db.execute("BEGIN IMMEDIATE")
            new = _check_schema(path, db) is False  # still empty: a new history
            for statement in (*map(_create, COLUMNS), *INDEXES):  # a history from before
                db.execute(statement)  # a table gets it too
            if new:
                db.execute("INSERT INTO meta VALUES ('schema_version', ?)",
                           (str(SCHEMA_VERSION),))
            db.execute("COMMIT")
        except sqlite3.Error as e:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise _problem(path, e, WRITE_WAIT_S) from None
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
        try:
            yield db
        except sqlite3.Error as e:
            raise _problem(path, e, WRITE_WAIT_S) from None


def _wal(db: sqlite3.Connection, wait_s: float = WRITE_WAIT_S) -> None:
    """Switch to write-ahead logging. Changing the journal mode needs the database to
    itself and SQLite does not wait for that (no busy handler), so retry for a while."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            db.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as e:
            if "locked" not in str(e) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def git_commit(folder: Path) -> str:
    """The git commit of a checkout ('' when it is not one)."""
    try:
        return subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], text=True,
                              capture_output=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def record(path: Path, *, kind: str, summary: dict | None = None, bench: dict | None = None,
           gate: int | None = None, results_dir: str = "", commit: str = "",
           slower: Iterable[tuple[str, str]] = ()) -> int:
    """Append one run (its summary's channel errors and its bench samples) in one
    transaction; returns the run id. ``slower``: the (case, engine) cells its speed gate
    found significantly slower, whose samples later runs do not take as their baseline
    (a lasting slowdown keeps failing until it is accepted)."""
    first = summary or bench or {}
    machine = first.get("machine", {})
    with connect(path) as db:
        db.execute("BEGIN IMMEDIATE")
        try:
            run_id = db.execute(
                "INSERT INTO runs (generated, kind, natcoord_version, git_commit, machine, "
                "machine_info, gate, results_dir) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (first.get("generated"), kind, first.get("natcoord_version"), commit,
                 machine.get("fingerprint", ""), json.dumps(machine), gate,
                 results_dir)).lastrowid
            for r in (summary or {}).get("records", []):
                base = (run_id, r["case"], r["engine"], r.get("case_hash", ""),
                        r.get("engine_version", ""), r["status"], r.get("verdict"),
                        json.dumps(r.get("settings", {}), sort_keys=True, default=str))
                rows = [(*base, name, c.get("kind"), c.get("max_abs"), c.get("max_rel"),
                         c.get("tolerance"), int(c.get("determined", True)))
                        for name, c in r.get("channels", {}).items()]
                db.executemany("INSERT INTO results VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, "
                               "?, ?, ?)", rows or [(*base, None, None, None, None, None, 1)])
            for r in (bench or {}).get("records", []):
                if not r.get("samples_s"):
                    continue
                db.execute("INSERT INTO bench VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           (run_id, r["case"], r["engine"], _bench_key(r),
                            r.get("engine_version", ""),
                            json.dumps(r.get("settings", {}), sort_keys=True, default=str),
                            json.dumps(r["samples_s"]), r.get("wall_time_s"),
                            r.get("us_per_step"), r.get("n_steps"),
                            json.dumps(r.get("counters", {}))))
                if r.get("cpu_samples_s"):  # CPU time per run of each sample (natcoord)
                    db.execute("INSERT INTO bench_cpu VALUES (?, ?, ?, ?, ?)",
                               (run_id, r["case"], r["engine"], _bench_key(r),
                                json.dumps(r["cpu_samples_s"])))
                db.executemany("INSERT INTO bench_relative VALUES (?, ?, ?, ?, ?, ?)",
                               [(run_id, r["case"], r["engine"], _bench_key(r),
                                 clock, json.dumps(xs))
                                for clock, xs in speed.relative(r).items()])
            db.executemany("INSERT INTO slower VALUES (?, ?, ?)",
                           [(run_id, c, e) for c, e in slower])
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
    return run_id


def import_jsonl(db_path: Path, jsonl: Path) -> int:
    """Import the lines of a former ``history.jsonl`` once (verdicts, worst relative
    errors and step costs per cell); returns how many lines were imported now."""
    jsonl = Path(jsonl)
    if not jsonl.exists():
        return 0
    with connect(db_path) as db:
        if db.execute("SELECT 1 FROM meta WHERE key = 'imported_jsonl'").fetchone():
            return 0
        lines = []
        for raw in jsonl.read_text(encoding="utf-8").splitlines():
            try:
                lines.append(json.loads(raw))
            except json.JSONDecodeError:
                continue  # a torn last line from a killed run is skipped, not trusted
        db.execute("BEGIN IMMEDIATE")
        for line in lines:
            run_id = db.execute(
                "INSERT INTO runs (generated, kind, natcoord_version, gate) VALUES "
                "(?, 'suite (imported)', ?, ?)", (line.get("generated"),
                                                  line.get("natcoord_version"),
                                                  line.get("gate"))).lastrowid
            for cell, v in (line.get("runs") or {}).items():
                case, _, engine = cell.partition("/")
                db.execute("INSERT INTO results (run_id, case_name, engine, status, verdict, "
                           "channel, max_rel) VALUES (?, ?, ?, ?, ?, 'worst', ?)",
                           (run_id, case, engine, v.get("status"), v.get("verdict"),
                            v.get("worst_rel")))
        db.execute("INSERT INTO meta VALUES ('imported_jsonl', ?)", (str(jsonl),))
        db.execute("COMMIT")
    return len(lines)


def _bench_key(r: dict) -> str:
    """The key a benchmark record is stored under: its ``bench_key`` (the mechanism and the
    engine's settings, :func:`natcoord.case.mechanism.bench_key`), or, written before
    there was one, its case file's sha256."""
    return r.get("bench_key") or r.get("case_hash", "")


def _keys(case_hash: str | Sequence[str]) -> tuple[str, ...]:
    return (case_hash,) if isinstance(case_hash, str) else tuple(case_hash)


def _recent(db, table: str, columns: str, case: str, engine: str,
            case_hash: str | Sequence[str], machine: str, last: int, exclude_dir: str,
            clock: str = "") -> list[tuple]:
    """``columns`` of ``table`` (bench, bench_cpu or, of one ``clock``, bench_relative) for
    the last ``last`` benchmarks of a cell stored under one of the keys ``case_hash`` (a
    record's bench key and its case file's sha256, which older histories keyed it by) on
    the same machine, not those of the folder ``exclude_dir`` nor those its speed gate
    found slower (the ``slower`` table, where the history has it)."""
    keys = _keys(case_hash)
    flagged = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND "
                         "name = 'slower'").fetchone()
    not_slower = (f" AND NOT EXISTS (SELECT 1 FROM slower WHERE slower.run_id = runs.id AND "
                  f"slower.case_name = {table}.case_name AND slower.engine = {table}.engine)"
                  if flagged else "")
    return db.execute(
        f"SELECT {columns} FROM {table} JOIN runs ON runs.id = {table}.run_id WHERE "
        f"{table}.case_name = ? AND {table}.engine = ? AND {table}.case_hash IN "
        f"({', '.join('?' * len(keys))}) AND "
        "runs.machine = ? AND (? = '' OR IFNULL(runs.results_dir, '') != ?)"
        f"{not_slower}{f' AND {table}.clock = ?' if clock else ''} ORDER BY runs.id DESC "
        "LIMIT ?", (case, engine, *keys, machine, exclude_dir, exclude_dir,
                    *([clock] if clock else []), last)).fetchall()


class Baseline(NamedTuple):
    """A cell's speed baseline: the pooled samples of its last benchmarks (see
    :func:`_baseline`)."""

    samples: list[float]  # wall time, s per run
    counters: dict | None  # the most recent benchmark's
    cpu: list[float]  # CPU time, s per run ([] when one of them lacks it)
    relative: dict[str, list[float]]  # per clock, relative to the reference work


def _baseline(db, case: str, engine: str, keys: tuple[str, ...], machine: str, last: int,
              exclude_dir: str) -> Baseline:
    """The baseline of one cell from the open history ``db``: the last ``last`` benchmarks
    of the cell with one of the ``keys`` (see :func:`_recent`) on ``machine``, not those of
    the results folder ``exclude_dir``. Relative samples of a clock are given only when
    every one of those benchmarks measured it ({} for a history from before the reference
    work): a baseline of other nights than the raw one's (the last ones that had
    references, older than the window) once passed a 3x slowdown and failed an accepted
    one. ``db`` None (no history yet): an empty baseline."""
    rows = [] if db is None else _recent(db, "bench", "runs.id, bench.samples, bench.counters",
                                         case, engine, keys, machine, last, exclude_dir)
    if not rows:
        return Baseline([], None, [], {})
    samples = [s for _, raw, _ in rows for s in json.loads(raw)]
    counters = json.loads(rows[0][2])
    try:
        cpu = [s for (raw,) in _recent(db, "bench_cpu", "bench_cpu.samples", case, engine,
                                       keys, machine, last, exclude_dir)
               for s in json.loads(raw)]
    except sqlite3.OperationalError as e:  # a history written before CPU samples
        if "no such table" not in str(e):
            raise
        cpu = []
    runs = [r for r, _, _ in rows]
    relative: dict[str, list[float]] = {}
    for clock in ("wall", "cpu"):
        try:
            got = db.execute(
                "SELECT run_id, samples FROM bench_relative WHERE case_name = ? AND "
                f"engine = ? AND case_hash IN ({', '.join('?' * len(keys))}) AND "
                f"clock = ? AND run_id IN ({', '.join('?' * len(runs))})",
                (case, engine, *keys, clock, *runs)).fetchall()
        except sqlite3.OperationalError as e:
            if "no such table" not in str(e):
                raise
            break
        by_run = {r: json.loads(raw) for r, raw in got}
        if set(by_run) == set(runs):  # newest first, as the raw samples are pooled
            relative[clock] = [x for r in runs for x in by_run[r]]
    return Baseline(samples, counters, cpu, relative)


def baselines(path: Path, cells: Iterable[tuple[str, str, str | Sequence[str]]],
              machine: str, *, last: int = 5,
              exclude_dir: str = "") -> dict[tuple[str, str], Baseline]:
    """:func:`_baseline` of every (case, engine, keys) in ``cells``, from one reading of the
    history (each reading runs the integrity check over the whole file: three readings per
    cell took 32 s for 136 cells of a 200-night history); empty baselines when there is
    no history yet."""
    with reading(path) as db:
        return {(case, engine): _baseline(db, case, engine, _keys(keys), machine, last,
                                          exclude_dir)
                for case, engine, keys in cells}


def _one(path: Path, case: str, engine: str, case_hash: str | Sequence[str], machine: str,
         last: int, exclude_dir: str) -> Baseline:
    return baselines(path, [(case, engine, case_hash)], machine, last=last,
                     exclude_dir=exclude_dir)[case, engine]


def past_samples(path: Path, case: str, engine: str, case_hash: str | Sequence[str],
                 machine: str, *, last: int = 5,
                 exclude_dir: str = "") -> tuple[list[float], dict | None]:
    """Pooled wall-time samples (s) of a cell's baseline (:func:`_baseline`) and the most
    recent counters; ([], None) when there are none."""
    b = _one(path, case, engine, case_hash, machine, last, exclude_dir)
    return b.samples, b.counters


def past_cpu_samples(path: Path, case: str, engine: str, case_hash: str | Sequence[str],
                     machine: str, *, last: int = 5, exclude_dir: str = "") -> list[float]:
    """Pooled CPU-time samples (s per run) of a cell's baseline ([] when none of its
    benchmarks measured CPU time)."""
    return _one(path, case, engine, case_hash, machine, last, exclude_dir).cpu


def past_relative(path: Path, case: str, engine: str, case_hash: str | Sequence[str],
                  machine: str, *, last: int = 5,
                  exclude_dir: str = "") -> dict[str, list[float]]:
    """Pooled samples relative to the reference work, per clock (``wall``, ``cpu``), of a
    cell's baseline (:func:`_baseline`)."""
    return _one(path, case, engine, case_hash, machine, last, exclude_dir).relative


def trends(path: Path, *, last: int = 30) -> dict:
    """For the report: per cell, the last ``last`` runs' worst determined relative error
    and median wall time, oldest first: ``{cell: {"generated": [...], "worst_rel": [...],
    "median_s": [...]}}``."""
    out: dict[str, dict] = {}
    with reading(path) as db:
        if db is None:
            return {}
        ids = [r[0] for r in db.execute("SELECT id FROM runs ORDER BY id DESC LIMIT ?",
                                        (last,))][::-1]
        if not ids:
            return {}
        marks = ",".join("?" * len(ids))
        gen = dict(db.execute(f"SELECT id, generated FROM runs WHERE id IN ({marks})", ids))
        for run_id, case, engine, worst in db.execute(
                f"SELECT run_id, case_name, engine, MAX(max_rel) FROM results WHERE run_id IN "
                f"({marks}) AND determined IS NOT 0 GROUP BY run_id, case_name, engine "
                f"ORDER BY run_id", ids):
            t = out.setdefault(f"{case}/{engine}", {"generated": [], "worst_rel": [],
                                                   "median_s": [], "bench_generated": []})
            t["generated"].append(gen[run_id])
            t["worst_rel"].append(worst)
        for run_id, case, engine, raw in db.execute(
                f"SELECT run_id, case_name, engine, samples FROM bench WHERE run_id IN "
                f"({marks}) ORDER BY run_id", ids):
            t = out.setdefault(f"{case}/{engine}", {"generated": [], "worst_rel": [],
                                                   "median_s": [], "bench_generated": []})
            t["bench_generated"].append(gen[run_id])
            t["median_s"].append(statistics.median(json.loads(raw)))
    return out
