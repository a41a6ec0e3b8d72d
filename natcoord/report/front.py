"""The report's front page: who is accurate (the accuracy map), who is fast (speed at equal
accuracy), and a one-line profile per engine. Plain values for the template."""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable

from .speed import TARGET_KEY, _num, targets_of

MOTION_KINDS = ("angle", "position", "velocity", "acceleration")
# log10 of the relative error -> colour: viridis (perceptually uniform, colour-blind safe),
# yellow for 1e-14 and below, dark violet for 1e-2 and above, a colour per two decades
LOG_RANGE = (-14.0, -2.0)
VIRIDIS = ("#fde725", "#90d743", "#35b779", "#21918c", "#31688e", "#443983", "#440154")


SHORT = {"unsupported": "unsupp.", "no reference": "no ref."}  # accuracy-map words

def worst_motion(rec: dict | None) -> tuple[float | None, str]:
    """(worst relative error, channel) over a run's gated motion channels: determined
    angle / position / velocity / acceleration channels with a tolerance."""
    best: tuple[float | None, str] = (None, "")
    for name, ch in ((rec or {}).get("channels") or {}).items():
        if (ch.get("kind") not in MOTION_KINDS or ch.get("determined", True) is False
                or _num(ch.get("tolerance")) is None):
            continue
        v = _num(ch.get("max_rel"))
        if v is not None and (best[0] is None or v > best[0]):
            best = (v, name)
    return best


def colour(rel: float) -> tuple[str, str]:
    """(background, text colour) of a relative error on the map's log scale."""
    lo, hi = LOG_RANGE
    x = (math.log10(max(rel, 1e-300)) - lo) / (hi - lo)
    i = min(len(VIRIDIS) - 1, max(0, round(x * (len(VIRIDIS) - 1))))
    return VIRIDIS[i], ("#ffffff" if i >= 3 else "#1d232b")


def legend() -> list[dict]:
    """The map's colour key: one swatch per colour with the error it stands for."""
    lo, hi = LOG_RANGE
    n = len(VIRIDIS) - 1
    out = []
    for i, c in enumerate(VIRIDIS):
        e = lo + (hi - lo) * i / n
        out.append({"bg": c, "fg": "#ffffff" if i >= 3 else "#1d232b",
                    "text": ("≤ " if i == 0 else "≥ " if i == n else "") + f"1e{e:.0f}"})
    return out


def accuracy_map(by_key: dict, cases: list[str], engines: list[str], cell_for: Callable,
                 anchor: Callable, fmt_num: Callable) -> list[dict]:
    """Rows of the case x engine map: each cell the worst relative error of the gated
    motion channels, its colour, and the verdict as a mark (✓ within tolerance, ✗ not);
    a cell that did not give errors says why (unsupported, failed, no reference, ...)."""
    rows = []
    for case in cases:
        cells = []
        for e in engines:
            rec = by_key.get((case, e))
            c = cell_for(rec)
            v, ch = worst_motion(rec) if c["key"] in ("pass", "fail") else (None, "")
            if v is None:  # a short word in the cell (the map stays within a window)
                cells.append({"engine": e, "css": c["css"] + " map", "mark": "",
                              "text": SHORT.get(c["label"], c["label"]),
                              "style": "", "title": f"{e} · {c['label']}"
                              + (f": {c['reason']}" if c["reason"] else "")})
                continue
            bg, fg = colour(v)
            ok = c["key"] == "pass"
            cells.append({"engine": e, "css": ("pass" if ok else "fail") + " acc map",
                          "text": fmt_num(v), "mark": "✓" if ok else "✗",
                          "style": f"background:{bg};color:{fg}",
                          "title": f"{e} · {c['label']}: worst relative error {fmt_num(v)} "
                                   f"({ch})" + (f"; {c['reason']}" if c["reason"] else "")})
        rows.append({"case": case, "anchor": anchor("case", case), "cells": cells})
    return rows


def _base(engine: str) -> str:
    """'natcoord (index1 dop853)' -> 'natcoord'."""
    return engine.split(" (", 1)[0]


def equal_accuracy(bench: dict | None, cases: list[str], engines: list[str],
                   anchor: Callable, fmt_time: Callable, fmt_ratio: Callable) -> dict:
    """Per case and engine, the least wall time to reach each accuracy target (the best of
    the engine's variants) from bench.json's ``time_to_accuracy``, with the ratio to the
    case's fastest; ``missing`` says why there is none."""
    rows = [r for r in (bench or {}).get("time_to_accuracy") or [] if isinstance(r, dict)]
    if bench is None:
        return {"missing": "no benchmark (bench.json) in this results folder", "rows": []}
    if not rows:
        return {"missing": "bench.json has no work-precision sweep (time_to_accuracy): "
                           "speeds are only at each engine's own settings", "rows": []}
    targets = targets_of(rows)
    best: dict[tuple[str, str, str], float] = {}
    for r in rows:
        for t in targets:
            v = _num(r.get(TARGET_KEY + t))
            k = (str(r.get("case")), _base(str(r.get("engine", ""))), t)
            if v is not None and (k not in best or v < best[k]):
                best[k] = v
    shown = [c for c in cases if any(str(r.get("case")) == c for r in rows)]
    out = []
    for case in shown:
        swept = {_base(str(r.get("engine", ""))) for r in rows if str(r.get("case")) == case}
        fastest = {t: min((v for (c, _, tt), v in best.items() if c == case and tt == t),
                          default=None) for t in targets}
        cells = []
        for e in engines:
            lines = []
            for t in targets:
                v = best.get((case, e, t))
                if e not in swept:
                    continue
                if v is None:
                    lines.append({"text": "not reached", "best": False})
                else:
                    lines.append({"text": f"{fmt_time(v)} ({fmt_ratio(v / fastest[t])})",
                                  "best": v == fastest[t]})
            cells.append({"engine": e, "lines": lines})
        out.append({"case": case, "anchor": anchor("case", case), "cells": cells})
    return {"missing": "", "rows": out,
            "targets": [f"{float(t):.0e}".replace("e-0", "e-") for t in targets]}


def profiles(records: list[dict], bench: dict | None, engines: list[str],
             fmt_num: Callable, fmt_ratio: Callable) -> list[dict]:
    """Per engine: cases run (of those in the results), passes, the median of its worst
    relative motion errors, and the median over cases of its benchmark time (at its own
    settings) relative to natcoord's on the same case."""
    walls: dict[tuple[str, str], float] = {}
    for r in (bench or {}).get("records") or []:
        if isinstance(r, dict) and str(r.get("status", "ok")) == "ok":
            v = _num(r.get("wall_median_s")) or _num(r.get("wall_time_s"))
            if v:
                walls[(str(r.get("case")), str(r.get("engine")))] = v
    out = []
    for e in engines:
        mine = [r for r in records if str(r.get("engine")) == e]
        ran = [r for r in mine if str(r.get("status")) == "ok"]
        errs = [v for r in ran if (v := worst_motion(r)[0]) is not None]
        ratios = [w / walls[(c, "natcoord")] for (c, en), w in walls.items()
                  if en == e and walls.get((c, "natcoord"))]
        out.append({
            "engine": e, "ran": len(ran), "of": len(mine),
            "passed": sum(str(r.get("verdict")) == "pass" for r in ran),
            "median_error": fmt_num(statistics.median(errs)) if errs else "—",
            "speed": (fmt_ratio(statistics.median(ratios)) if ratios and e != "natcoord"
                      else "1×" if ratios else "no benchmark time"),
            "n_speed": len(ratios)})
    return out
