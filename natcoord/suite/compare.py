"""Compare an engine's channels with the case's reference, channel by channel."""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
import pandas as pd

from ..case.mechanism import FORCE_KINDS, Case
from ..outputs.result import is_balance


def channel_errors(case: Case, engine: str, table: pd.DataFrame,
                   reference: pd.DataFrame | None,
                   undetermined: Collection[str] = ()) -> tuple[dict, str, str]:
    """Per-channel errors and the verdict of one engine run.

    Returns ``(channels, verdict, reason)``; ``channels[name]`` holds kind, unit,
    ``max_abs`` (max |engine - reference| over the reference's samples), ``max_rel``
    (``max_abs`` over the scale named in ``rel_to``, whose value is ``scale``: the reference
    channel's range, or for energy the system's energy scale), ``tolerance`` and ``pass``
    (None when not gated: no tolerance, or channel undetermined). A gated channel that the
    engine's output lacks, or that is NaN or infinite anywhere, fails with the reason in
    ``note``. ``undetermined``: channels a self-equilibrating set of the redundant
    constraints changes (from N = ker Phi_q^T, stored with the reference): never gated,
    whatever the case file's tolerances say. An energy channel's ``balance`` says whether it
    is constant in exact physics (:func:`natcoord.outputs.result.is_balance`). Verdict: ``pass``,
    ``fail``, ``no-reference`` or ``not-gated``.
    """
    spec = case.engine(engine)
    out: dict[str, dict] = {}
    if reference is None:
        return out, "no-reference", "no reference stored; run `natcoord reference update`"
    if len(reference) != len(table) or not np.allclose(reference["t"], table["t"],
                                                       atol=1e-9):
        return out, "no-reference", ("reference sample times differ from this run's; "
                                     "the reference is stale: run `natcoord reference update`")
    gated = failed = 0
    keep, why_skip = _comparable(case, reference)
    for ch in case.channels:
        ref = reference[ch.name].to_numpy() if ch.name in reference else None
        val = table[ch.name].to_numpy(dtype=float) if ch.name in table else None
        tol = spec.tolerance_for(ch)
        determined = ch.name not in undetermined
        entry = {"kind": ch.kind, "unit": ch.unit, "max_abs": None, "max_rel": None,
                 "tolerance": tol, "pass": None, "determined": determined, "note": ""}
        if ch.kind == "energy":  # the report draws a balance's drift on the energy scale
            entry["balance"] = is_balance(case, ch)
        bad = ("missing from this engine's results" if val is None else
               "not reported by this engine (all NaN)" if np.all(np.isnan(val)) else "")
        if ref is None:
            entry["note"] = "channel missing from the reference"
        elif bad:
            entry["note"] = bad
            if determined and tol is not None:  # a gated channel must be there
                entry["pass"] = False
                gated += 1
                failed += 1
        else:
            err = np.abs(val - ref)
            if ch.kind in FORCE_KINDS and not keep.all():
                err = err[keep]
                entry["note"] = why_skip
            max_abs = float(np.max(err)) if np.all(np.isfinite(err)) else float("inf")
            if not np.isfinite(max_abs):
                entry["note"] = "non-finite values (NaN or inf) in this engine's results"
            span, entry["rel_to"] = _scale(case, ch, ref)
            entry["scale"] = span
            entry["max_abs"], entry["max_rel"] = max_abs, max_abs / span
            if not determined:
                entry["note"] = "undetermined (redundant constraints): shown, not gated"
                # (an undetermined channel is never gated, whatever the tolerances say)
            elif tol is not None:
                entry["pass"] = bool(max_abs <= tol)
                gated += 1
                failed += not entry["pass"]
        out[ch.name] = entry
    if failed:
        return out, "fail", f"{failed} of {gated} gated channels over tolerance"
    if not gated:
        return out, "not-gated", "no tolerance written for this engine in the case file"
    return out, "pass", ""



def mechanism_size(case: Case) -> float:
    """The largest distance between two of the mechanism's points at t = 0, m."""
    pts = [np.asarray(x, float) for b in case.bodies for x in b.points.values()]
    pts += [np.asarray(x, float) for x in case.ground.values()]
    return max((float(np.linalg.norm(a - b)) for a in pts for b in pts), default=0.0)


def energy_scale(case: Case) -> float:
    """The system's energy scale, J: the weight of every body times the size of the
    mechanism (:func:`mechanism_size`)."""
    return sum(b.mass for b in case.bodies) * float(np.linalg.norm(case.gravity)) * \
        mechanism_size(case)


STILL = 1e-3  # a position or angle channel that moves less than this fraction of the
# mechanism's size (of a radian) is relative to that: its range is no scale


def _scale(case: Case, ch, ref: np.ndarray) -> tuple[float, str]:
    """What a channel's relative error is relative to: its range over the run; for energy,
    which a conservative system keeps constant (a range near zero), the larger of the
    energy scale (:func:`energy_scale`), its range and its size; for a position or angle
    that hardly moves, STILL of the mechanism's size or of a radian."""
    span = float(np.ptp(ref))
    if ch.kind == "energy":
        scale = max(energy_scale(case), span, float(np.max(np.abs(ref))))
        return (scale or 1.0), "energy scale (total weight x mechanism size)"
    still = STILL * {"position": mechanism_size(case), "angle": 1.0}.get(ch.kind, 0.0)
    if span < still:
        return still, ("mechanism size / 1000" if ch.kind == "position" else "1 mrad") + \
            " (the channel hardly moves)"
    return (span or float(np.max(np.abs(ref))) or 1.0), "range of the reference"


def _comparable(case: Case, reference: pd.DataFrame) -> tuple[np.ndarray, str]:
    """Samples (T,) on which force channels are compared, and why some are not: near the
    case's singular positions (``[comparison] singular``) rigid-body reactions diverge
    (the paper, Section 3.6.1), so a finite error there says nothing about an engine."""
    spec = case.comparison.get("singular")
    keep = np.ones(len(reference), bool)
    if not spec or spec["channel"] not in reference:
        return keep, ""
    phi = reference[spec["channel"]].to_numpy()
    for a in spec["angles"]:
        d = np.angle(np.exp(1j * (phi - a)))  # wrapped to (-pi, pi]
        keep &= np.abs(d) > spec["within"]
    n = int((~keep).sum())
    return keep, (f"{n} sample(s) within {np.degrees(spec['within']):.3g} deg of a singular "
                  f"position of {spec['channel']} not compared (forces diverge there)")
