"""The shape of stored files that several commands read: a malformed one is refused with
the file, the field and the problem (StoredFileError: exit 2), never a traceback later."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import StoredFileError

_NUMBERS = ("wall_time_s", "us_per_step", "n_steps", "build_time_s")
# bench.json: the timing samples of a cell, each a list of durations (s) when present
_SAMPLES = ("samples_s", "cpu_samples_s")
# the reference work's times (natcoord.timing.reference_work, ~10 ms on a 2020s core):
# a value outside this range is no measurement of it, and would decide a speed verdict
_REFERENCES = ("ref_samples_s", "ref_cpu_samples_s")
REF_RANGE_S = (1e-4, 10.0)

# summary.json: what a record must hold, the statuses a run gives, and the type of every
# other field a reader uses (gate, compare, report, the suite's summary.md)
SUMMARY_REQUIRED = ("case", "engine", "status", "verdict", "channels")
STATUSES = ("ok", "failed", "skipped", "unsupported")
_TEXTS = ("reason", "verdict_reason", "engine_version", "case_hash", "description",
          "tolerance_reason")
_RECORD_NUMBERS = ("wall_time_s", "build_time_s", "n_steps", "us_per_step", "sim_time_s",
                   "process_time_s")
_TABLES = ("settings", "counters")
_CHANNEL_NUMBERS = ("max_abs", "max_rel", "tolerance", "scale")
_CHANNEL_FLAGS = ("pass", "determined", "balance")
_CHANNEL_TEXTS = ("kind", "unit", "note", "rel_to")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


MIN_SAMPLE_S = 1e-12  # a timing sample's least: a run of 0 s (or 1e-320 s) made speed
# ratios NaN or inf


def _durations(xs, least: float = 0.0) -> bool:
    return isinstance(xs, list) and all(_number(s) and math.isfinite(s) and s >= least
                                        for s in xs)


def _samples(xs) -> bool:
    """A list of timing samples (s per run), each at least MIN_SAMPLE_S."""
    return _durations(xs, MIN_SAMPLE_S)


_KINDS = {"a string": lambda x: isinstance(x, str), "a number": _number,
          "a table": lambda x: isinstance(x, dict), "true or false": lambda x: isinstance(x, bool)}


def _optional(table: dict, keys, what: str, prefix: str) -> None:
    """StoredFileError ``{prefix}{key}: not {what}`` for the first of ``keys`` that ``table``
    holds (not null) and that is not ``what`` (one of :data:`_KINDS`)."""
    ok = _KINDS[what]
    for k in keys:
        if table.get(k) is not None and not ok(table[k]):
            raise StoredFileError(f"{prefix}{k}: not {what}")


def carried(record: dict) -> bool:
    """True for a bench record (or work-precision point) that tonight's bench did not
    measure: reused from an earlier suite (``reused``) or taken from tonight's accuracy run
    (``timed_by``). The speed gate and the history judge and keep only measured ones."""
    return "reused" in record or "timed_by" in record


def check_bench(path: Path, data) -> dict:
    """``data`` (the content of ``path``, a bench.json) as it is, or StoredFileError."""
    if not isinstance(data, dict):
        raise StoredFileError(f"{path}: not a JSON object")
    records = data.get("records", [])
    if not isinstance(records, list):
        raise StoredFileError(f"{path}: records: not a list")
    for k in ("machine", "cold_start"):
        if k in data and not isinstance(data[k], dict):
            raise StoredFileError(f"{path}: {k}: not a table")
    if "samples_s" in data.get("cold_start", {}) and not _samples(
            data["cold_start"]["samples_s"]):
        raise StoredFileError(f"{path}: cold_start.samples_s: not a list of timing samples "
                              f"(s, each at least {MIN_SAMPLE_S:g})")
    for i, r in enumerate(records):
        where = f"{path}: records[{i}]"
        if not isinstance(r, dict):
            raise StoredFileError(f"{where}: not a table")
        for k in ("case", "engine"):
            if not isinstance(r.get(k), str):
                raise StoredFileError(f"{where}.{k}: missing or not a string")
        for k in _SAMPLES:
            if k in r and not _samples(r[k]):
                raise StoredFileError(f"{where}.{k}: not a list of timing samples (s, each at "
                                      f"least {MIN_SAMPLE_S:g})")
        lo, hi = REF_RANGE_S
        for k in _REFERENCES:
            if k in r and not (_durations(r[k]) and all(lo <= x <= hi for x in r[k])):
                raise StoredFileError(f"{where}.{k}: not a list of reference-work times (s, "
                                      f"each from {lo:g} to {hi:g})")
        if r.get("status", "ok") == "ok" and r.get("samples_s") == []:  # NaN speed ratios
            raise StoredFileError(f"{where}.samples_s: not a list of durations (s): "
                                  "empty, in a record with status ok")
        if "batch_runs" in r and not _durations(r["batch_runs"]):
            raise StoredFileError(f"{where}.batch_runs: not a list of run counts")
        _optional(r, ("status", "reason", "case_hash", "engine_version"), "a string",
                  f"{where}.")
        _optional(r, _NUMBERS, "a number", f"{where}.")
        _optional(r, ("counters", "settings"), "a table", f"{where}.")
    return data


def check_summary(path: Path, data) -> dict:
    """``data`` (the content of ``path``, a summary.json) as it is, or StoredFileError
    naming the file, the field (``records[3].reason``) and the problem: every field the
    readers use has its type checked here, once, so a summary edited by hand is refused as
    bad input, never a traceback in the gate or compare."""
    if not isinstance(data, dict):
        raise StoredFileError(f"{path}: not a JSON object")
    records = data.get("records")
    if not isinstance(records, list):
        raise StoredFileError(f"{path}: records: missing or not a list")
    for k in ("cases", "engines"):
        if k in data and not (isinstance(data[k], list)
                              and all(isinstance(x, str) for x in data[k])):
            raise StoredFileError(f"{path}: {k}: not a list of names")
    _optional(data, ("generated", "mode", "natcoord_version", "bench_sha256"), "a string",
              f"{path}: ")
    _optional(data, ("machine",), "a table", f"{path}: ")
    seen: dict[tuple, int] = {}
    for i, r in enumerate(records):
        _check_record(f"{path}: records[{i}]", r)
        first = seen.setdefault((r["case"], r["engine"]), i)
        if first != i:  # a run writes one record a cell: a copy would be judged twice
            raise StoredFileError(f"{path}: records[{i}]: a second record of "
                                  f"{r['case']}/{r['engine']} (the first is records[{first}]"
                                  "): the summary was edited since the run")
    return data


def _check_record(where: str, r) -> None:
    if not isinstance(r, dict):
        raise StoredFileError(f"{where}: not a table")
    missing = [k for k in SUMMARY_REQUIRED if k not in r]
    if missing:
        raise StoredFileError(f"{where}: missing field {missing[0]!r}")
    for k in ("case", "engine", "status", "verdict"):
        if not isinstance(r[k], str):
            raise StoredFileError(f"{where}.{k}: not a string")
    if r["status"] not in STATUSES:
        raise StoredFileError(f"{where}.status: {r['status'][:40]!r} is not one of "
                              f"{', '.join(STATUSES)}")
    _optional(r, _TEXTS, "a string", f"{where}.")
    _optional(r, _RECORD_NUMBERS, "a number", f"{where}.")
    _optional(r, _TABLES, "a table", f"{where}.")
    if "samples_s" in r and not _samples(r["samples_s"]):
        raise StoredFileError(f"{where}.samples_s: not a list of timing samples (s, each at "
                              f"least {MIN_SAMPLE_S:g})")
    if "notes" in r and not (isinstance(r["notes"], list)
                             and all(isinstance(x, str) for x in r["notes"])):
        raise StoredFileError(f"{where}.notes: not a list of strings")
    files = r.get("files", {})
    if not isinstance(files, dict) or not all(
            isinstance(k, str) and isinstance(x, str) for k, x in files.items()):
        raise StoredFileError(f"{where}.files: not a table of file hashes")
    if not isinstance(r["channels"], dict):
        raise StoredFileError(f"{where}.channels: not a table of channels")
    for name, c in r["channels"].items():
        at = f"{where}.channels.{name[:40]}"
        if not isinstance(c, dict):
            raise StoredFileError(f"{at}: not a table")
        _optional(c, _CHANNEL_NUMBERS, "a number", f"{at}.")
        _optional(c, _CHANNEL_FLAGS, "true or false", f"{at}.")
        _optional(c, _CHANNEL_TEXTS, "a string", f"{at}.")
