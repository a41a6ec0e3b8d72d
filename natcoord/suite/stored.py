"""The shape of stored files that several commands read: a malformed one is refused with
the file, the field and the problem (StoredFileError: exit 2), never a traceback later."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import StoredFileError

_NUMBERS = ("wall_time_s", "us_per_step", "n_steps", "build_time_s")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


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
    for k in ("machine",):
        if k in data and not isinstance(data[k], dict):
            raise StoredFileError(f"{path}: {k}: not a table")
    for i, r in enumerate(records):
        where = f"{path}: records[{i}]"
        if not isinstance(r, dict):
            raise StoredFileError(f"{where}: not a table")
        for k in ("case", "engine"):
            if not isinstance(r.get(k), str):
                raise StoredFileError(f"{where}.{k}: missing or not a string")
        samples = r.get("samples_s", [])
        if not isinstance(samples, list) or not all(
                _number(s) and math.isfinite(s) and s >= 0 for s in samples):
            raise StoredFileError(f"{where}.samples_s: not a list of durations (s)")
        for k in _NUMBERS:
            if r.get(k) is not None and not _number(r[k]):
                raise StoredFileError(f"{where}.{k}: not a number")
        for k in ("counters", "settings"):
            if r.get(k) is not None and not isinstance(r[k], dict):
                raise StoredFileError(f"{where}.{k}: not a table")
    return data
