"""What a channel's relative error is relative to (the accuracy map's number)."""

from __future__ import annotations

import numpy as np

from natcoord import load_case
from natcoord.suite.compare import STILL, _scale, mechanism_size

from .conftest import CASES


def test_a_channel_that_hardly_moves_is_relative_to_the_mechanism_not_its_range():
    case = load_case(CASES / "four_bar.toml")
    pos = next(c for c in case.channels if c.kind == "position")
    size = mechanism_size(case)
    assert size == 2.0  # four_bar: ground pivots 2 m apart
    still = 1.0 + 1e-15 * np.sin(np.linspace(0, 6, 50))  # a round-off range, 2e-15 m
    scale, why = _scale(case, pos, still)
    assert scale == STILL * size and "hardly moves" in why
    moving = np.linspace(-0.5, 0.5, 50)
    assert _scale(case, pos, moving) == (1.0, "range of the reference")
    angle = next(c for c in case.channels if c.kind == "angle")
    assert _scale(case, angle, np.full(50, 0.3))[0] == STILL  # a thousandth of a radian
