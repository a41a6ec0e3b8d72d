"""Speed regressions told from noise.

A sample is a calibrated batch's time per run (:mod:`natcoord.suite.batches`): the stepping
repeated for at least 0.1 s, so a preemption costs it a few per cent, not 10x. The samples
judged are CPU times where both sides measured them (natcoord: time spent waiting for the
core, the usual noise of a shared machine, does not count), else wall times. A cell
(case x engine) counts as slower only when both hold:

* the median of its samples grew past a factor (``FACTOR``; per engine in ``FACTORS``),
  and
* a one-sided Mann-Whitney U test says the new samples are larger at p <= ``ALPHA``.

Where both sides measured the reference work after each sample (``ref_samples_s``,
``ref_cpu_samples_s``: :func:`natcoord.timing.reference_work`), each sample is judged
relative to it (sample / reference, same clock): a slow spell of the whole machine slows
both and cancels, a slower code slows only the sample.

The factor carries the weight: calibrated samples of an unchanged cell differ by a few per
cent on a quiet machine and by up to about 1.2x when the bench core is shared by several
busy processes (even CPU time then grows: caches are shared), so a false alarm needs a
shift past 1.5x, and a 2x slowdown clears it; the rank test asks that the shift is not one
odd sample. A test whose smallest possible p is above ``ALPHA`` (fewer than 3 samples on
a side against 3, 2 against 5, 1 against 19) cannot judge: it says so ("cannot judge
speed"), it does not pass silently.

Deterministic cost counters (steps, right-hand sides, factorizations) are compared exactly:
a change for the same mechanism and settings is a behaviour change, reported apart.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

from scipy.stats import mannwhitneyu

from .stored import carried

FACTOR = 1.5
FACTORS: dict[str, float] = {}  # engine -> its own factor (a noisier engine may need more)
ALPHA = 0.05


def min_p(n_base: int, n_new: int) -> float:
    """The smallest p-value the one-sided rank test can give on these sample counts (every
    new sample above every old one): 1 / C(n_base + n_new, n_new); 1 when a side is empty."""
    if n_base < 1 or n_new < 1:
        return 1.0
    return 1.0 / math.comb(n_base + n_new, n_new)


def has_power(n_base: int, n_new: int, alpha: float = ALPHA) -> bool:
    """Whether the rule can call a slowdown at all on these sample counts."""
    return min_p(n_base, n_new) <= alpha * (1 + 1e-9)


@dataclass(frozen=True)
class SpeedChange:
    """One cell's speed judgement: median ratio new/base, the test's p-value, the sample
    counts, the clock judged (``cpu`` or ``wall``), whether the counts had the power to
    judge (``judged``), whether it is a significant slowdown, and counters that changed."""

    case: str
    engine: str
    ratio: float
    p: float
    n_base: int
    n_new: int
    slower: bool
    counters: dict
    clock: str = "wall"
    judged: bool = True
    relative: bool = False  # judged relative to the reference work measured beside each sample

    @property
    def measure(self) -> str:
        """What was compared: ``cpu time``, ``wall time``, or either per reference work."""
        return f"{self.clock} time" + (" / reference work" if self.relative else "")

    def line(self) -> str:
        if not self.judged:
            return (f"{self.case}/{self.engine}: cannot judge speed: {self.n_base} -> "
                    f"{self.n_new} samples (the rank test needs at least 3 and 3 to reach "
                    f"p <= {ALPHA:g}; median {self.ratio:.3g}x, {self.measure})")
        what = "SLOWER" if self.slower else "faster" if self.ratio < 1 else "same"
        return (f"{self.case}/{self.engine}: {what}: median {self.ratio:.3g}x "
                f"(p = {self.p:.2g}, {self.n_base} -> {self.n_new} samples, "
                f"{self.measure})")


def positive_finite(xs) -> list[float]:
    """The timing samples (s) of ``xs`` that are positive finite numbers."""
    out = []
    for x in xs or []:
        try:
            v = float(x)
        except (TypeError, ValueError):
            continue
        if math.isfinite(v) and v > 0:
            out.append(v)
    return out


def relative(record: dict) -> dict[str, list[float]]:
    """A bench record's samples relative to the reference work measured after each:
    ``{"wall": [...], "cpu": [...]}``, a clock left out where the record lacks either list,
    they differ in length or hold a sample that is not a positive finite time."""
    out = {}
    for clock, key in (("wall", "samples_s"), ("cpu", "cpu_samples_s")):
        xs, refs = record.get(key) or [], record.get(f"ref_{key}") or []
        good_x, good_r = positive_finite(xs), positive_finite(refs)
        if good_x and len(good_x) == len(xs) == len(good_r) == len(refs):
            out[clock] = [x / r for x, r in zip(good_x, good_r, strict=True)]
    return out


def judge(case: str, engine: str, base: list[float], new: list[float],
          base_counters: dict | None = None, new_counters: dict | None = None,
          factor: float | None = None, base_cpu: list[float] | None = None,
          new_cpu: list[float] | None = None, base_relative: dict | None = None,
          new_relative: dict | None = None) -> SpeedChange:
    """Compare two sample sets of one cell (s per run): CPU times when both are given,
    else wall times; per reference work (``*_relative``, as :func:`relative` gives) where
    both sides have that clock's relative samples in numbers the rank test can judge."""
    factor = FACTORS.get(engine, FACTOR) if factor is None else factor
    bc, nc = positive_finite(base_cpu), positive_finite(new_cpu)
    clock, (b, n) = (("cpu", (bc, nc)) if bc and nc else
                     ("wall", (positive_finite(base), positive_finite(new))))
    rb = positive_finite((base_relative or {}).get(clock))
    rn = positive_finite((new_relative or {}).get(clock))
    per_ref = has_power(len(rb), len(rn))
    if per_ref:
        b, n = rb, rn
    ratio = statistics.median(n) / statistics.median(b) if b and n else float("nan")
    judged = has_power(len(b), len(n))
    p = (float(mannwhitneyu(n, b, alternative="greater", method="exact").pvalue)
         if b and n else float("nan"))  # the test's own p, also where too few samples
    # give it no power to reach ALPHA (then the cell is not judged on it)
    changed = {k: (base_counters[k], v) for k, v in (new_counters or {}).items()
               if base_counters and k in base_counters and base_counters[k] != v}
    return SpeedChange(case, engine, ratio, p, len(b), len(n),
                       judged and ratio > factor and p <= ALPHA * (1 + 1e-9), changed, clock,
                       judged, per_ref)


def compare_bench(base: dict, new: dict) -> list[SpeedChange]:
    """Judge every cell that ran (status ok) in both bench results (``bench.json``
    records): one judgement each, unjudged when either side has too few samples."""
    by_key = {(r.get("case"), r.get("engine")): r for r in base.get("records", [])
              if isinstance(r, dict)}
    out = []
    for r in new.get("records", []):
        if not isinstance(r, dict):
            continue
        b = by_key.get((r.get("case"), r.get("engine")))
        if carried(r):  # the suite's bench policy took it from elsewhere: nothing new
            continue
        if b and b.get("status", "ok") == "ok" and r.get("status", "ok") == "ok":
            out.append(judge(r["case"], r["engine"], b.get("samples_s"), r.get("samples_s"),
                             b.get("counters"), r.get("counters"),
                             base_cpu=b.get("cpu_samples_s"), new_cpu=r.get("cpu_samples_s"),
                             base_relative=relative(b), new_relative=relative(r)))
    return out
