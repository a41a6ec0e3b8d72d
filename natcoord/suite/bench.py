"""Speed benchmark: per case x engine, best-of-N step cost, measured in one session.

Every repeat is a fresh engine process with single-threaded BLAS; build time is kept apart
from the stepping time. Ratios to natcoord are computed within the same benchmark run, so
machine load drifts cancel as far as they can; the spread of the repeats is stored with
every figure so that a gate can tell noise from a regression.
"""

from __future__ import annotations

import datetime as dt
import statistics
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from .. import __version__
from ..mechanism import Case
from .io import write_json
from .runner import machine_info, run_subprocess


def bench(cases: Sequence[Case], engines: Sequence[str], *, repeats: int = 3,
          timeout_s: float = 600.0, progress: Callable[[str, dict], None] | None = None) -> dict:
    """Benchmark and return ``{"records": [...], "machine": ..., "generated": ...}``."""
    records = []
    with tempfile.TemporaryDirectory(prefix="natcoord-bench-") as tmp:
        for case in cases:
            for engine in engines:
                runs = [run_subprocess(case, engine, Path(tmp), timeout_s)
                        for _ in range(repeats)]
                ok = [r for r in runs if r["status"] == "ok" and r.get("wall_time_s")]
                rec = {"case": case.name, "engine": engine, "repeats": len(ok),
                       "status": runs[-1]["status"], "reason": runs[-1].get("reason", ""),
                       "engine_version": runs[-1].get("engine_version", "")}
                if ok:
                    walls = [r["wall_time_s"] for r in ok]
                    best = min(ok, key=lambda r: r["wall_time_s"])
                    rec |= {"wall_time_s": best["wall_time_s"],
                            "wall_spread": (max(walls) - min(walls)) / min(walls),
                            "wall_median_s": statistics.median(walls),
                            "build_time_s": min(r["build_time_s"] or 0.0 for r in ok),
                            "n_steps": best["n_steps"], "us_per_step": best["us_per_step"],
                            "wall_per_sim_s": best["wall_time_s"] / case.duration,
                            "settings": best["settings"]}
                records.append(rec)
                if progress:
                    progress(f"{case.name}/{engine}", rec)
    by_key = {(r["case"], r["engine"]): r for r in records}
    for r in records:
        ref = by_key.get((r["case"], "natcoord"), {})
        if r.get("wall_time_s") and ref.get("wall_time_s"):
            r["wall_ratio_to_natcoord"] = r["wall_time_s"] / ref["wall_time_s"]
    return {"generated": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "natcoord_version": __version__, "machine": machine_info(), "repeats": repeats,
            "records": records}


def store(result: dict, out: Path, history_dir: Path | None = None) -> Path:
    """Write ``out/bench.json`` and, when asked, a dated copy under ``history_dir``."""
    write_json(Path(out) / "bench.json", result)
    if history_dir is not None:
        stamp = result["generated"].replace(":", "").replace("+0000", "Z")
        write_json(Path(history_dir) / f"bench-{stamp}.json", result)
    return Path(out) / "bench.json"
