"""The report's energy-balance figure of a case: how far each engine's conserved energy
channel drifts from its value at t = 0.

A channel is drawn when the runner marked it a balance (``balance`` in its summary entry,
:func:`natcoord.outputs.result.is_balance`): kinetic + gravitational + spring energy in a case
without non-conservative loads, or that minus the work of applied loads, dampers and drivers
(``work = true``). Exact physics keeps it constant, so |B(t) - B(0)| is each engine's
conservation error. It is drawn relative to the energy scale the comparison uses
(``scale`` in the entry, :func:`natcoord.suite.compare.energy_scale`), on a log axis (the
engines' drifts span many decades), downsampled keeping each bucket's peak.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd
import plotly.graph_objects as go

from .look import style
from .sampling import envelope

REFERENCE_COLOR = "#222222"
HEIGHT = 420  # px


def channels(records: list[dict]) -> list[str]:
    """The balance channels of a case's records, in channel order."""
    out: list[str] = []
    for r in records:
        for name, c in (r.get("channels") or {}).items():
            if isinstance(c, dict) and c.get("balance") and name not in out:
                out.append(name)
    return out


def _scale(records: list[dict], name: str) -> float | None:
    for r in records:
        s = ((r.get("channels") or {}).get(name) or {}).get("scale")
        if isinstance(s, (int, float)) and s > 0:
            return float(s)
    return None


def drift(df: pd.DataFrame, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Times (T,) and B(t) - B(0) (T,) of one run's channel, J (None: not in the run, or
    not finite at t = 0)."""
    if name not in df.columns or len(df) == 0:
        return None
    b = df[name].to_numpy(float)
    if not np.isfinite(b[0]):
        return None
    return df["t"].to_numpy(float), b - b[0]


def figure(name: str, series: dict[str, tuple[np.ndarray, np.ndarray]],
           colors: dict[str, str], scale: float | None) -> go.Figure:
    """|B(t) - B(0)| / scale against t, one line per engine (``series``: engine or
    ``reference`` -> (t, drift in J)), log y."""
    fig = go.Figure()
    div = scale or 1.0
    for who, (t, d) in series.items():
        e = np.abs(d) / div
        e[e <= 0] = np.nan  # t = 0 and exact zeros are not drawable on a log axis
        te, ee = envelope(t, e)
        ref = who == "reference"
        fig.add_trace(go.Scatter(
            x=te, y=ee, name=who, mode="lines",
            line={"color": REFERENCE_COLOR if ref else colors.get(who, "#7f7f7f"),
                  "width": 1.8 if ref else 1.4, **({"dash": "dash"} if ref else {})},
            hovertemplate=f"{who}<br>t=%{{x:.4g}} s<br>%{{y:.3g}}<extra></extra>"))
    style(fig, HEIGHT, bottom=90, legend={"orientation": "h", "x": 0, "xanchor": "left",
                                          "y": -0.22, "yanchor": "top"})
    fig.update_xaxes(title_text="t [s]")
    fig.update_yaxes(title_text="|drift| / energy scale" if scale else "|drift| [J]",
                     type="log")
    if not fig.data:
        fig.add_annotation(text="no data", showarrow=False, xref="paper", yref="paper",
                           x=0.5, y=0.5)
    return fig


def section(records: list[dict], runs: dict[str, pd.DataFrame], ref: pd.DataFrame | None,
            colors: dict[str, str], fmt_num: Callable, add: Callable) -> list[dict]:
    """Per balance channel of a case: its figure payload (``add(fig)``) and a row per engine
    (and the reference) with the largest |drift| in J and relative to the scale."""
    out = []
    for name in channels(records):
        scale = _scale(records, name)
        series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for engine, df in runs.items():
            d = drift(df, name)
            if d is not None:
                series[engine] = d
        if ref is not None and (d := drift(ref, name)) is not None:
            series["reference"] = d
        rows = []
        for who, (t, d) in series.items():
            ok = np.isfinite(d)
            if not ok.any():
                rows.append({"who": who, "abs": "n/a", "rel": "n/a", "at": "n/a", "final": "n/a",
                             "color": colors.get(who, REFERENCE_COLOR)})
                continue
            k = int(np.nanargmax(np.abs(d)))
            rows.append({"who": who, "abs": fmt_num(abs(d[k]), "J"),
                         "rel": fmt_num(abs(d[k]) / scale) if scale else "n/a",
                         "at": fmt_num(t[k], "s"), "final": fmt_num(d[-1], "J"),
                         "color": colors.get(who, REFERENCE_COLOR)})
        out.append({"name": name, "scale": fmt_num(scale, "J") if scale else "",
                    "rows": rows, "fig": add(figure(name, series, colors, scale))})
    return out
