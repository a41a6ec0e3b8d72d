"""The report's look for a summary figure: axes, fonts, margins, one place."""

from __future__ import annotations

import plotly.graph_objects as go

AXIS = {"showline": True, "linecolor": "#999", "ticks": "outside", "tickcolor": "#999",
        "gridcolor": "#e8e8e8", "zeroline": False, "mirror": True, "exponentformat": "power",
        "automargin": True}  # long or negative tick labels widen the margin, never clipped
FONT = {"family": "system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif", "size": 12}


def style(fig: go.Figure, height: int, *, bottom: int = 60,
          legend: dict | None = None) -> None:
    """Give ``fig`` the report's look (trends, work-precision, energy balance): ``height``
    and ``bottom`` margin in px, the legend's layout (default: plotly's, font 11)."""
    fig.update_layout(
        template="none", height=height, margin={"l": 70, "r": 14, "t": 20, "b": bottom},
        font=FONT, legend={"font": {"size": 11}, **(legend or {})}, hovermode="closest",
        paper_bgcolor="white", plot_bgcolor="white")
    fig.update_xaxes(**AXIS)
    fig.update_yaxes(**AXIS)
