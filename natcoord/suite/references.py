"""Reference solutions: natcoord's high-accuracy run of each case, stored with provenance.

``references/<case>.csv`` holds the channels at the case's sample times and
``references/<case>.json`` how they were made: method, settings, versions, date, the
constraint drift, an error estimate from a second run at a 100x looser tolerance and,
for the cases :mod:`natcoord.derivations.independent` derives, ``independent``: how far a solution
in joint coordinates (Kane's method) is from the reference, per channel.
for the cases :mod:`natcoord.independent` (planar: Kane's method in joint coordinates) or
:mod:`natcoord.derivations.spatial` (3-D: body coordinates, Newton-Euler) derives,
``independent``: how far that solution is from the reference, per channel.
References change only through ``natcoord reference update``.
"""

from __future__ import annotations

import datetime as dt
import json
import platform
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..case.mechanism import Case, mechanism_parts
from ..derivations.independent import check as independent_check
from ..derivations.spatial import check as spatial_check
from ..engines.base import initial_body_states
from ..engines.natcoord_engine import run as natcoord_run
from ..estimates import estimated_error
from ..outputs.result import evaluate_channels, methods_table
from .evidence import BadReference, reference_problem
from .io import read_csv, read_json, write_csv, write_json

REFERENCE_SETTINGS = {"method": "DOP853", "rtol": 1e-12, "atol": 1e-14}
CHECK_SETTINGS = {"method": "DOP853", "rtol": 1e-10, "atol": 1e-12}
MODEL_SETTINGS = ("coordinates",)  # settings that choose the model, kept in the reference
# A case may replace both with ``[engines.natcoord.settings] reference = {...}`` and
# ``reference_check = {...}`` (five_bar: natcoord's own dop853, whose steps cross its
# singular positions; at rtol 1e-12 the step control stalls there).


def load_reference(case: str, directory: Path) -> pd.DataFrame | None:
    path = Path(directory) / f"{case}.csv"
    return read_csv(path) if path.exists() else None


def load_provenance(case: str, directory: Path) -> dict | None:
    path = Path(directory) / f"{case}.json"
    return read_json(path) if path.exists() else None


def usable_reference(case: Case, directory: Path) -> pd.DataFrame | None:
    """The stored reference of ``case`` when it can judge the case (None when there is none,
    or when :func:`natcoord.suite.evidence.reference_problem` finds it damaged or stale:
    errors against it would be made up)."""
    table = load_reference(case.name, directory)
    if table is None or reference_problem(case, table, load_provenance(case.name, directory)):
        return None
    return table


def _describe(settings: dict) -> str:
    """'dop853 rtol 1e-11' or 'rk4 h 0.0001 s'."""
    return f"{settings['method']} " + (f"h {settings['h']} s" if settings.get("h") else
                                       f"rtol {settings['rtol']}")


def _check_replaceable(case: Case, directory: Path) -> None:
    """BadReference, before any work, when a file ``update_reference`` would write is not
    natcoord's reference of ``case``: a link or a folder (a link was followed into a file
    outside the project), or files without natcoord's provenance of that case (a
    hand-made table; a case named 'baseline' would have replaced the gate's baseline)."""
    paths = [Path(directory) / f"{case.name}{s}" for s in (".csv", ".methods.csv", ".json")]
    for p in paths:
        if p.is_symlink() or (p.exists() and not p.is_file()):
            raise BadReference(f"{p}: not a regular file (a link or a folder): not replaced")
    if not any(p.exists() for p in paths):
        return
    try:
        prov = json.loads(paths[2].read_text(encoding="utf-8"))
    except (OSError, ValueError):
        prov = None
    if not (isinstance(prov, dict) and prov.get("case") == case.name
            and str(prov.get("method", "")).startswith("natcoord")):
        raise BadReference(f"{paths[2] if paths[2].exists() else paths[0]}: not a reference "
                           f"natcoord wrote for case {case.name!r} (no natcoord provenance): "
                           "not replaced; move it away to write the reference")


def update_reference(case: Case, directory: Path, init=None) -> dict:
    """Recompute and store the reference of one case (from its assembled state ``init``,
    assembled here when None); returns its provenance. Replaces only natcoord's own
    reference of the case (:func:`_check_replaceable`)."""
    _check_replaceable(case, directory)
    init = initial_body_states(case) if init is None else init
    own = case.engine("natcoord").settings
    model_settings = {k: v for k, v in own.items() if k in MODEL_SETTINGS}
    best = natcoord_run(case, init, model_settings | own.get("reference", REFERENCE_SETTINGS))
    check_settings = own.get("reference_check", CHECK_SETTINGS)
    check = natcoord_run(case, init, model_settings | check_settings)
    table = evaluate_channels(case, best.motion)
    columns = ["t", *(c.name for c in case.channels)]
    problem = (reference_problem(case, table) or
               ("" if list(table.columns) == columns else
                f"columns {list(table.columns)} are not t and the case's channels"))
    if problem:  # never store a reference that could not judge the case
        raise BadReference(f"{Path(directory) / f'{case.name}.csv'}: not written: {problem}")
    check_table = evaluate_channels(case, check.motion)
    steps = int(best.counters.get("steps") or best.n_steps or 1)
    estimate = {c.name: estimated_error(table[c.name], check_table[c.name], steps)
                for c in case.channels}
    provenance = {
        "case": case.name,
        "case_file": Path(case.file).name,
        "mechanism": mechanism_parts(case),
        "mechanism_method": "sha256 (16 hex digits) of each part of the case the motion and "
                            "the channels depend on; a part that differs makes the reference "
                            "stale",
        "method": "natcoord index-1 Lagrange (Eq. (6)), least-squares projection of q and "
                  f"qd, {_describe(best.settings)}",
        "settings": best.settings,
        "estimated_error": estimate,
        "estimated_error_method": f"max |reference - run with {_describe(check_settings)}| "
                                  "per channel (an upper bound of the reference's own "
                                  "error), at least the round-off of its steps "
                                  "(8 eps max|x| sqrt(steps))",
        "counters": best.counters,
        "undetermined": best.counters.get("undetermined", []),
        "undetermined_method": "channels that lambda + s N c changes (N = ker Phi_q^T at "
                               "every sample, c a random unit vector): never gated",
        "versions": {"natcoord": __version__, "numpy": np.__version__,
                     "python": platform.python_version()},
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }
    # None: the case is not derived there
    independent = (spatial_check(case, table, provenance["undetermined"])
                   if case.dimension == 3 else independent_check(case, table))
    if independent is not None:
        provenance["independent"] = independent
    write_csv(Path(directory) / f"{case.name}.csv", table)
    if best.methods:
        write_csv(Path(directory) / f"{case.name}.methods.csv", methods_table(case, best))
    write_json(Path(directory) / f"{case.name}.json", provenance)
    return provenance
