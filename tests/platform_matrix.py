"""natcoord's cells of every case under several floating-point platforms on one machine.

A verdict must not depend on the BLAS kernel or the CPU target the code was compiled for:
the same commit runs natcoord (engine ``natcoord`` only) once per platform variant, each in
fresh processes with only the environment changed, and every cell must be ``ok`` and within
its tolerances. The variants:

- ``host``: this machine's environment as it is;
- ``openblas-<K>``: ``OPENBLAS_CORETYPE=K`` (read by OpenBLAS at start-up) for the kernels
  Haswell, Zen, SkylakeX, Sandybridge and Prescott (the generic x86-64 kernel). A kernel
  whose instructions this CPU lacks (SkylakeX needs AVX-512) cannot run here and is
  reported as such, never as a pass;
- ``numba-generic``: ``NUMBA_CPU_NAME=generic``: the compiled loops built for a generic
  x86-64 instead of this CPU (no FMA contraction, other vector widths).

Besides the verdicts it reports the spread per case: the largest difference of each channel
between a variant's result files and the host's (what another machine can move a result by).

Run it (it takes minutes: one natcoord run per variant)::

    python -m tests.platform_matrix [CASE ...] [--variants host,openblas-Zen] [--json]

Exit 0 when every runnable variant passes every cell, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
OPENBLAS_KERNELS = ("Haswell", "Zen", "SkylakeX", "Sandybridge", "Prescott")
NEEDS = {"SkylakeX": "avx512f", "Haswell": "avx2", "Zen": "avx2", "Sandybridge": "avx"}


def variants() -> dict[str, dict[str, str]]:
    """Variant name -> the environment it sets over the host's."""
    v = {"host": {}}
    v |= {f"openblas-{k}": {"OPENBLAS_CORETYPE": k} for k in OPENBLAS_KERNELS}
    v["numba-generic"] = {"NUMBA_CPU_NAME": "generic"}
    return v


def cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def cannot_run(env: dict[str, str], flags: set[str]) -> str | None:
    """Why this CPU cannot run a variant (None: it can)."""
    need = NEEDS.get(env.get("OPENBLAS_CORETYPE", ""))
    if need and flags and need not in flags:
        return f"this CPU lacks {need} (the kernel would stop with an illegal instruction)"
    return None


def run_variant(name: str, env: dict[str, str], cases: list[str], out: Path,
                timeout_s: float = 900.0) -> dict:
    """One ``natcoord run --engines natcoord`` under ``env``; its records by case."""
    folder = out / name
    cmd = [sys.executable, "-m", "natcoord.cli", "run", *cases, "--engines", "natcoord",
           "--out", str(folder)]
    proc = subprocess.run(cmd, env={**os.environ, **env}, capture_output=True, text=True,
                          timeout=timeout_s, cwd=ROOT)
    summary = folder / "summary.json"
    if not summary.exists():
        return {"error": f"no summary (exit {proc.returncode}): "
                         + "\n".join(proc.stderr.strip().splitlines()[-3:])}
    records = json.loads(summary.read_text())["records"]
    return {"folder": str(folder), "exit": proc.returncode,
            "cells": {r["case"]: {"status": r["status"], "verdict": r["verdict"],
                                  "reason": r.get("reason", ""),
                                  "errors": {c: v.get("max_abs") for c, v in
                                             r.get("channels", {}).items()}}
                      for r in records}}


def spread(host: Path, other: Path, case: str) -> dict[str, float]:
    """max |other - host| per channel of one case's natcoord result files."""
    a = pd.read_csv(host / "results" / case / "natcoord.csv")
    b = pd.read_csv(other / "results" / case / "natcoord.csv")
    cols = [c for c in a.columns if c != "t" and c in b.columns]
    return {c: float(np.nanmax(np.abs(a[c].to_numpy() - b[c].to_numpy()))) for c in cols}


def matrix(cases: list[str], names: list[str] | None = None,
           out: Path | None = None) -> dict:
    """Run every variant (``names``: a subset) and collect verdicts and spreads."""
    out = Path(out or tempfile.mkdtemp(prefix="natcoord-platforms-"))
    flags = cpu_flags()
    result: dict = {"variants": {}, "spread": {}}
    for name, env in variants().items():
        if names and name not in names:
            continue
        why = cannot_run(env, flags)
        result["variants"][name] = ({"cannot_run": why} if why else
                                    run_variant(name, env, cases, out))
    host = result["variants"].get("host", {})
    if "folder" in host:
        for name, v in result["variants"].items():
            if name == "host" or "folder" not in v:
                continue
            for case, cell in v["cells"].items():
                if cell["status"] == "ok" and host["cells"].get(case, {}).get("status") == "ok":
                    s = spread(Path(host["folder"]), Path(v["folder"]), case)
                    for c, x in s.items():
                        prev = result["spread"].setdefault(case, {}).get(c, 0.0)
                        result["spread"][case][c] = max(prev, x)
    return result


def failures(result: dict) -> list[str]:
    """Every runnable variant's cell that is not ok within tolerance."""
    bad = []
    for name, v in result["variants"].items():
        if "cannot_run" in v:
            continue
        if "error" in v:
            bad.append(f"{name}: {v['error']}")
            continue
        for case, cell in v["cells"].items():
            if cell["status"] != "ok" or cell["verdict"] != "pass":
                bad.append(f"{name}: {case}: {cell['status']} {cell['verdict']} "
                           f"{cell['reason']}".strip())
    return bad


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cases", nargs="*", help="cases (default: all)")
    p.add_argument("--variants", default="", help="comma-separated subset of: "
                   + ", ".join(variants()))
    p.add_argument("--out", default=None, help="folder for the runs (default: a temporary one)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    a = p.parse_args(argv)
    result = matrix(a.cases, [x for x in a.variants.split(",") if x] or None, a.out)
    if a.json:
        print(json.dumps(result, indent=1))
    else:
        for name, v in result["variants"].items():
            if "cannot_run" in v:
                print(f"{name:22s} cannot run here: {v['cannot_run']}")
            elif "error" in v:
                print(f"{name:22s} ERROR {v['error']}")
            else:
                ok = sum(c["status"] == "ok" and c["verdict"] == "pass"
                         for c in v["cells"].values())
                print(f"{name:22s} {ok}/{len(v['cells'])} cells ok within tolerance")
        print("\nspread against host (max over variants, per case: worst channel)")
        for case, s in sorted(result["spread"].items()):
            c, x = max(s.items(), key=lambda kv: kv[1]) if s else ("-", 0.0)
            print(f"  {case:28s} {x:9.2e}  ({c})")
    bad = failures(result)
    for line in bad:
        print("FAIL", line, file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
