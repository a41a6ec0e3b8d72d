"""The report's section on a case with redundant constraints: existence and uniqueness
diagnostics, the self-equilibrating force sets N = ker Phi_q^T in words and numbers, the
determined / undetermined split of the force channels with every engine's value and
natcoord's reaction methods side by side, their plots over time, and published values.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import plotly.graph_objects as go

from ..case.mechanism import FORCE_KINDS
from .sampling import minmax

METHOD_DASHES = ("dash", "dot", "dashdot", "longdash", "longdashdot")


def _published(references: Path, case: str) -> dict | None:
    path = references / "published.toml"
    if not path.is_file():
        return None
    try:
        return tomllib.loads(path.read_text(encoding="utf-8")).get(case)
    except (OSError, tomllib.TOMLDecodeError):
        return None


def _words(diag: dict) -> str:
    k = diag.get("redundant", 0)
    if not k:
        return ("Every constraint is independent: the multipliers, and every reaction, are "
                "unique.")
    sets = "one self-equilibrating set" if k == 1 else f"{k} independent self-equilibrating sets"
    return (f"{diag['m']} constraint equations on {diag['n']} coordinates have rank "
            f"{diag['rank']}: {diag['dof']} degree(s) of freedom and {k} redundant "
            f"equation(s). The multipliers are unique only up to {sets} (the columns of N "
            "below): adding any multiple of one to the multipliers changes no motion and no "
            "generalized force, only how the load is shared among the rows it touches. A "
            "force that depends on those rows is undetermined for a rigid model; every "
            "engine (and every reaction method) picks its own split. Rows that no set "
            "touches, and combinations such as resultants, are determined and gated.")


# A constraint row's label (the builder's naming) -> its meaning in words; first match wins.
ROW_WORDS = (
    (r"(.+) in (.+): ([xyz])", lambda m: f"{m[1]} fixed in body {m[2]}, {m[3]} component"),
    (r"(.+): \|(.+)\|",
     lambda m: f"rigid body {m[1]}: fixed distance between two of its points ({m[2]})"),
    (r"(.+): axis\.(\d+)", lambda m: f"joint {m[1]}: rotation axis kept aligned "
                                      f"(direction {int(m[2]) + 1} of 2)"),
    (r"(.+): cross", lambda m: f"universal joint {m[1]}: its two axes kept perpendicular"),
    (r"(.+): unit", lambda m: f"vector {m[1]} of unit length"),
    (r"(.+): ([xyz])", lambda m: f"joint {m[1]}: its two points coincide along {m[2]}"),
    (r"(.+): (.+)\.(.+)", lambda m: f"rigid body {m[1]}: fixed angle between {m[2]} and {m[3]}"),
    (r"\|(.+)\|", lambda m: f"fixed distance {m[1]}"),
)


def describe_row(label: str, forces: set[str] = frozenset()) -> str:
    """A constraint row's label in words (``"E in B: x"``, ``"B: |PQ|"``, ``"J: axis.0"``,
    ...); '' when the label says nothing more."""
    for pattern, words in ROW_WORDS:
        if m := re.fullmatch(pattern, label):
            return words(m)
    if label in forces:
        return f"rod {label}: fixed length (its multiplier is the axial force {label})"
    return ""


def methods_figure(name: str, unit: str, methods: pd.DataFrame | None,
                   runs: dict[str, pd.DataFrame], colors: dict[str, str],
                   height: int = 320) -> go.Figure:
    """One force channel over time: each engine (solid) and natcoord's reaction methods
    (dashed)."""
    fig = go.Figure()
    for eng, df in runs.items():
        if name in df.columns and np.any(np.isfinite(df[name].to_numpy(float))):
            x, y = minmax(df["t"].to_numpy(), df[name].to_numpy())
            fig.add_trace(go.Scatter(x=x, y=y, name=eng, mode="lines",
                                     line={"color": colors.get(eng, "#444"), "width": 1.4}))
    if methods is not None:
        cols = [c for c in methods.columns if c.startswith(f"{name}@")]
        for k, c in enumerate(cols):
            x, y = minmax(methods["t"].to_numpy(), methods[c].to_numpy())
            fig.add_trace(go.Scatter(x=x, y=y,
                                     name=f"natcoord {c.split('@', 1)[1]}", mode="lines",
                                     line={"color": "#222", "width": 1.6,
                                           "dash": METHOD_DASHES[k % len(METHOD_DASHES)]}))
    fig.update_layout(template="none", height=height, margin={"l": 64, "r": 14, "t": 20,
                                                              "b": 96},
                      legend={"orientation": "h", "y": -0.32, "font": {"size": 11}},
                      yaxis_title=f"{name} [{unit}]" if unit else name, xaxis_title="t [s]",
                      yaxis_automargin=True)
    return fig


def _at(df: pd.DataFrame, col: str, t: float) -> float | None:
    if col not in df.columns:
        return None
    k = int(np.argmin(np.abs(df["t"].to_numpy(float) - t)))
    v = float(df[col].iloc[k])
    return v if np.isfinite(v) else None


def section(case: str, records: list[dict], runs: dict[str, pd.DataFrame],
            ref: pd.DataFrame | None, provenance: dict | None, results_dir: Path,
            references: Path, colors: dict[str, str], fmt, add_figure) -> dict | None:
    """Template context of the section, or None when the case has no redundant constraints
    and no published values. ``add_figure(fig, config, height)`` turns a plotly figure into
    the template's payload."""
    counters = (provenance or {}).get("counters") or {}
    nat = next((r for r in records if r.get("engine") == "natcoord"), None)
    if not counters.get("redundant") and nat is not None:
        counters = nat.get("counters") or counters
    published = _published(references, case)
    if not counters.get("redundant") and not published:
        return None
    undetermined = set((provenance or {}).get("undetermined") or
                       (counters.get("undetermined") or []))
    methods = None
    for path in (results_dir / "results" / case / "natcoord.methods.csv",
                 references / f"{case}.methods.csv"):
        if path.is_file():
            methods = pd.read_csv(path)
            break
    kinds = {}
    for r in records:
        for name, ch in (r.get("channels") or {}).items():
            kinds.setdefault(name, (ch.get("kind"), ch.get("unit")))
    forces = [n for n, (k, _) in kinds.items() if k in FORCE_KINDS]
    t_show = None
    if ref is not None and len(ref):
        t_show = float(ref["t"].iloc[len(ref) // 4])  # before any late singular position
    method_names = [] if methods is None else list(dict.fromkeys(
        c.split("@", 1)[1] for c in methods.columns if "@" in c))
    engines = [e for e in runs if e != "natcoord"]
    rows = []
    for n in forces:
        cells = [fmt(_at(methods, f"{n}@{m}", t_show)) if methods is not None else "—"
                 for m in method_names]
        cells += [fmt(_at(runs[e], n, t_show)) for e in engines]
        rows.append({"name": n, "unit": kinds[n][1] or "", "determined": n not in undetermined,
                     "cells": cells})
    figures = [{"name": n, "determined": n not in undetermined,
                "fig": add_figure(methods_figure(n, kinds[n][1] or "", methods,
                                                 {e: runs[e] for e in engines}, colors),
                                  {"displaylogo": False, "responsive": True}, 320)}
               for n in forces]
    null_sets = []
    for k, s in enumerate(counters.get("null_space") or []):
        null_sets.append({"n": k + 1, "rows": [(label, describe_row(label, set(forces)),
                                                f"{v:+.4g}") for label, v in s.items()]})
    pub = None
    if published and "phi" in kinds and ref is not None:
        peak, end = published.get("phi_peak_deg"), published.get("phi_end_deg")
        entries = [("reference (natcoord)", ref)] + [(e, runs[e]) for e in runs]
        pub = {"citation": published.get("citation", ""), "source": published.get("source",
                                                                                    ""),
               "peak": peak, "end": end, "tol": published.get("tolerance_deg"),
               "rows": [(name, f"{np.degrees(df['phi'].max()):.3f}",
                         f"{np.degrees(df['phi'].iloc[-1]):.3f}") for name, df in entries
                        if "phi" in df.columns and np.all(np.isfinite(df["phi"]))]}
    return {
        "diag": {k: counters.get(k) for k in ("n", "m", "rank", "dof", "redundant")},
        "words": _words(counters) if counters.get("m") else "",
        "null_sets": null_sets,
        "determined_rows": [(label, describe_row(label, set(forces)))
                            for label in counters.get("determined_rows") or []],
        "t_show": t_show,
        "methods": method_names,
        "engines": engines,
        "rows": rows,
        "figures": figures,
        "published": pub,
    }
