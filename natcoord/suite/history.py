"""The nightly history in an embedded database (SQLite, WAL mode, versioned schema).

One row per run (``runs``), per case x engine x channel result (``results``) and per case x
engine benchmark with the raw wall time of every repeat (``bench``), with provenance: the
natcoord version and git commit, the sha256 of the case file, engine versions, settings and
the machine fingerprint (CPU model, cores). Several suites may append at once: each run is
one transaction that waits for the database (``BEGIN IMMEDIATE`` with a busy timeout).
Lines of the former ``history.jsonl`` are imported once. CPU-time samples, where a bench
measured them, are in ``bench_cpu``.
"""

from __future__ import annotations

import json
import sqlite3
import statistics
import subprocess
import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from pathlib import Path

SCHEMA_VERSION = 1
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY, generated TEXT, kind TEXT, natcoord_version TEXT,
    git_commit TEXT, machine TEXT, machine_info TEXT, gate INTEGER, results_dir TEXT);
CREATE TABLE IF NOT EXISTS results (
    run_id INTEGER REFERENCES runs(id), case_name TEXT, engine TEXT, case_hash TEXT,
    engine_version TEXT, status TEXT, verdict TEXT, settings TEXT, channel TEXT,
    kind TEXT, max_abs REAL, max_rel REAL, tolerance REAL, determined INTEGER);
CREATE TABLE IF NOT EXISTS bench (
    run_id INTEGER REFERENCES runs(id), case_name TEXT, engine TEXT, case_hash TEXT,
    engine_version TEXT, settings TEXT, samples TEXT, wall_time_s REAL, us_per_step REAL,
    n_steps INTEGER, counters TEXT);
CREATE TABLE IF NOT EXISTS bench_cpu (
    run_id INTEGER REFERENCES runs(id), case_name TEXT, engine TEXT, case_hash TEXT,
    samples TEXT);
CREATE INDEX IF NOT EXISTS results_cell ON results (case_name, engine, channel);
CREATE INDEX IF NOT EXISTS bench_cell ON bench (case_name, engine, case_hash);
"""


@contextmanager
def connect(path: Path) -> Iterator[sqlite3.Connection]:
    """Open (and create or migrate) the history database; commits on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with closing(sqlite3.connect(path, timeout=60.0, isolation_level=None)) as db:
        db.execute("PRAGMA busy_timeout=60000")
        _wal(db)
        # the schema in one write transaction: BEGIN IMMEDIATE waits for another writer
        # (executescript would commit first and create tables outside any lock)
        db.execute("BEGIN IMMEDIATE")
        for statement in filter(str.strip, SCHEMA.split(";")):
            db.execute(statement)
        version = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        if version is None:
            db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        db.execute("COMMIT")
        if version is not None and int(version[0]) > SCHEMA_VERSION:
            raise ValueError(f"{path}: history schema {version[0]} is newer than this "
                             f"natcoord's ({SCHEMA_VERSION}); upgrade natcoord")
        yield db


def _wal(db: sqlite3.Connection, wait_s: float = 60.0) -> None:
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
           gate: int | None = None, results_dir: str = "", commit: str = "") -> int:
    """Append one run (its summary's channel errors and its bench samples) in one
    transaction; returns the run id."""
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
                           (run_id, r["case"], r["engine"], r.get("case_hash", ""),
                            r.get("engine_version", ""),
                            json.dumps(r.get("settings", {}), sort_keys=True, default=str),
                            json.dumps(r["samples_s"]), r.get("wall_time_s"),
                            r.get("us_per_step"), r.get("n_steps"),
                            json.dumps(r.get("counters", {}))))
                if r.get("cpu_samples_s"):  # CPU time per run of each sample (natcoord)
                    db.execute("INSERT INTO bench_cpu VALUES (?, ?, ?, ?, ?)",
                               (run_id, r["case"], r["engine"], r.get("case_hash", ""),
                                json.dumps(r["cpu_samples_s"])))
            db.execute("COMMIT")
        except BaseException:
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


def past_samples(path: Path, case: str, engine: str, case_hash: str, machine: str, *,
                 last: int = 5, exclude_dir: str = "") -> tuple[list[float], dict | None]:
    """Pooled wall-time samples (s) of the last ``last`` benchmarks of a cell with the same
    case file and machine fingerprint (not those of the results folder ``exclude_dir``),
    and the most recent counters; ([], None) when there are none."""
    if not Path(path).exists():
        return [], None
    with connect(path) as db:
        rows = db.execute(
            "SELECT bench.samples, bench.counters FROM bench JOIN runs ON runs.id = "
            "bench.run_id WHERE case_name = ? AND engine = ? AND case_hash = ? AND "
            "runs.machine = ? AND (? = '' OR IFNULL(runs.results_dir, '') != ?) "
            "ORDER BY runs.id DESC LIMIT ?",
            (case, engine, case_hash, machine, exclude_dir, exclude_dir, last)).fetchall()
    samples = [s for raw, _ in rows for s in json.loads(raw)]
    return samples, (json.loads(rows[0][1]) if rows else None)


def past_cpu_samples(path: Path, case: str, engine: str, case_hash: str, machine: str, *,
                     last: int = 5, exclude_dir: str = "") -> list[float]:
    """Pooled CPU-time samples (s per run) of the same benchmarks as :func:`past_samples`
    ([] when none of them measured CPU time)."""
    if not Path(path).exists():
        return []
    with connect(path) as db:
        try:
            rows = db.execute(
                "SELECT bench_cpu.samples FROM bench_cpu JOIN runs ON runs.id = "
                "bench_cpu.run_id WHERE case_name = ? AND engine = ? AND case_hash = ? AND "
                "runs.machine = ? AND (? = '' OR IFNULL(runs.results_dir, '') != ?) "
                "ORDER BY runs.id DESC LIMIT ?",
                (case, engine, case_hash, machine, exclude_dir, exclude_dir, last)).fetchall()
        except sqlite3.OperationalError as e:  # a history written before CPU samples
            if "no such table" not in str(e):
                raise
            return []
    return [s for (raw,) in rows for s in json.loads(raw)]


def trends(path: Path, *, last: int = 30) -> dict:
    """For the report: per cell, the last ``last`` runs' worst determined relative error
    and median wall time, oldest first: ``{cell: {"generated": [...], "worst_rel": [...],
    "median_s": [...]}}``."""
    if not Path(path).exists():
        return {}
    out: dict[str, dict] = {}
    with connect(path) as db:
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
