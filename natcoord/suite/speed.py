"""Speed regressions told from noise.

A cell (case x engine) counts as slower only when both hold:

* its median wall time grew past a factor (default 1.25; per engine in ``FACTORS``), and
* a one-sided Mann-Whitney U test on the raw samples of every repeat says the new samples
  are larger at p < 0.002 (asv's rule). With 7 samples on each side the smallest p is
  1/3432, so a benchmark of 7 repeats has the power to see it; fewer samples never alarm.

Deterministic cost counters (steps, right-hand sides, factorizations) are compared exactly:
a change for the same case file and settings is a behaviour change, reported apart.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

from scipy.stats import mannwhitneyu

FACTOR = 1.25
FACTORS: dict[str, float] = {}  # engine -> its own factor (a noisier engine may need more)
ALPHA = 0.002


@dataclass(frozen=True)
class SpeedChange:
    """One cell's speed judgement: median ratio new/base, the test's p-value, the sample
    counts, whether it is a significant slowdown, and counters that changed."""

    case: str
    engine: str
    ratio: float
    p: float
    n_base: int
    n_new: int
    slower: bool
    counters: dict

    def line(self) -> str:
        what = "SLOWER" if self.slower else "faster" if self.ratio < 1 else "same"
        return (f"{self.case}/{self.engine}: {what}: median {self.ratio:.3g}x "
                f"(p = {self.p:.2g}, {self.n_new} vs {self.n_base} samples)")


def judge(case: str, engine: str, base: list[float], new: list[float],
          base_counters: dict | None = None, new_counters: dict | None = None,
          factor: float | None = None) -> SpeedChange:
    """Compare two sample sets of wall times (s) of one cell."""
    factor = FACTORS.get(engine, FACTOR) if factor is None else factor
    ratio = statistics.median(new) / statistics.median(base)
    p = float(mannwhitneyu(new, base, alternative="greater").pvalue) if ratio > 1 else 1.0
    changed = {k: (base_counters[k], v) for k, v in (new_counters or {}).items()
               if base_counters and k in base_counters and base_counters[k] != v}
    return SpeedChange(case, engine, ratio, p, len(base), len(new),
                       ratio > factor and p < ALPHA, changed)


def compare_bench(base: dict, new: dict) -> list[SpeedChange]:
    """Judge every cell two bench results share (``bench.json`` records with
    ``samples_s``)."""
    by_key = {(r["case"], r["engine"]): r for r in base.get("records", [])}
    out = []
    for r in new.get("records", []):
        b = by_key.get((r["case"], r["engine"]))
        if b and b.get("samples_s") and r.get("samples_s"):
            out.append(judge(r["case"], r["engine"], b["samples_s"], r["samples_s"],
                             b.get("counters"), r.get("counters")))
    return out
