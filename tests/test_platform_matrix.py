"""Same verdict on every machine: natcoord's cell of every case passes under every OpenBLAS
kernel this CPU can run and with numba compiling for a generic x86-64 (tests/platform_matrix.py
runs them; ``python -m tests.platform_matrix`` prints the table and the spreads)."""

from __future__ import annotations

import pytest

from natcoord.case.casefile import load_case
from tests import platform_matrix as pm
from tests.conftest import CASES

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    return pm.matrix([], out=tmp_path_factory.mktemp("platforms"))


def test_every_runnable_variant_passes_every_case(result):
    ran = [n for n, v in result["variants"].items() if "cannot_run" not in v]
    # the matrix really ran: the host, numba's generic target and OpenBLAS's generic kernel
    # at least (those run on any x86-64), and every case in each
    assert {"host", "numba-generic", "openblas-Prescott"} <= set(ran)
    n_cases = len(list(CASES.glob("*.toml")))
    for name in ran:
        assert len(result["variants"][name].get("cells", {})) == n_cases, name
    assert pm.failures(result) == []


def test_tolerances_leave_the_platform_spread(result):
    """No natcoord tolerance is tighter than what another platform moved a result by."""
    for case, spread in result["spread"].items():
        c = load_case(CASES / f"{case}.toml")
        own = c.engine("natcoord")
        for ch in c.channels:
            tol = own.tolerance_for(ch)
            if tol is not None and ch.name in spread:
                assert spread[ch.name] <= tol, (case, ch.name, spread[ch.name], tol)
