"""Every stored error estimate is a real estimate: positive, finite, and at least the
round-off of the run it describes."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from natcoord.estimates import estimated_error
from tests.conftest import REFERENCES


@pytest.mark.parametrize("path", sorted(REFERENCES.glob("*.json")), ids=lambda p: p.stem)
def test_no_stored_estimate_is_zero(path):
    prov = json.loads(path.read_text())
    for field in (prov.get("estimated_error", {}),
                  prov.get("independent", {}).get("estimated_error", {})):
        for channel, x in field.items():
            assert isinstance(x, float) and math.isfinite(x) and x > 0, (channel, x)


def test_estimate_is_the_difference_or_the_round_off_floor():
    t = pd.Series(np.linspace(0.0, 3.0, 301))
    assert estimated_error(t, t + 1e-9, 100) == pytest.approx(1e-9)
    same = estimated_error(t, t.copy(), 400)  # two runs equal to the last bit
    assert same == pytest.approx(8 * np.finfo(float).eps * 3.0 * 20.0)
    zero = pd.Series(np.zeros(5))
    assert estimated_error(zero, zero, 1) > 0
