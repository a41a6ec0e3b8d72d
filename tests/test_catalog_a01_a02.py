"""IFToMM A01 over its full 2000 s and A02 (N-four-bar) against exact solutions, the
N-four-bar generator, and the rank of natcoord's N-four-bar model."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from natcoord import evaluate_channels, load_case
from natcoord.case.generate import n_four_bar
from natcoord.derivations import exact
from natcoord.derivations.exact import n_four_bar_coefficients
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.model import casemodel
from natcoord.outputs import channels as outputs

from .conftest import CASES


def _natcoord(case):
    """natcoord's channels at the case file's own settings."""
    run = adapter("natcoord").run(case, initial_body_states(case),
                                  case.engine("natcoord").settings)
    return evaluate_channels(case, run.motion)


def test_a01_elliptic_solution_is_the_published_one():
    """The closed form itself: period 2.3678419 s (IFToMM A01), released at rest at (1, 0)."""
    s = exact.a01_pendulum(np.array([0.0, 2.3678419 / 2]))
    assert s["period"] == pytest.approx(2.3678419, abs=1e-7)
    assert s["x"][0] == pytest.approx(1.0, abs=1e-15) and abs(s["phi_dot"][0]) < 1e-12
    assert s["x"][1] == pytest.approx(-1.0, abs=1e-7)  # at the other side after half a period


def test_a01_natcoord_follows_the_elliptic_solution_for_2000_s():
    """natcoord at the case's settings within 1e-8 m of the Jacobi elliptic solution at every
    sample of 2000 s (about 845 periods), and energy conserved to 1e-10 J."""
    case = load_case(CASES / "a01_pendulum.toml")
    assert case.duration == 2000.0
    df = _natcoord(case)
    ex = exact.a01_pendulum(case.times)
    for c in ("x", "y", "theta"):
        assert np.max(np.abs(df[c].to_numpy() - ex[c])) < 1e-8, c
    assert abs(df["x"].iloc[-1] - ex["x"][-1]) < 1e-8
    assert np.ptp(df["energy"]) < 1e-10


def test_n_four_bar_reduction_conserves_energy_and_starts_right():
    """The one-equation model: B0 at (0, 1) moving at (+1, 0); energy constant to 1e-9 J."""
    for n in (1, 2, 40):
        s = exact.n_four_bar(n, np.linspace(0.0, 10.0, 1001))
        assert (s["x"][0], s["y"][0], s["vx"][0], s["vy"][0]) == pytest.approx(
            (0.0, 1.0, 1.0, 0.0), abs=1e-15)
        assert np.ptp(s["energy"]) < 1e-9 * abs(s["energy"][0])
    assert n_four_bar_coefficients(2) == (3.0, 3.5)


@pytest.mark.parametrize("n, duration, passes, pos, vel", [(2, 10.0, 10, 5e-8, 2.5e-7),
                                                         (40, 20.0, 20, 1e-8, 5e-8)])
def test_a02_natcoord_equals_the_exact_reduction(n, duration, passes, pos, vel):
    """natcoord's full model (all cranks, couplers and loops) and the one-equation Lagrange
    reduction agree on B0 over the specification's run, through every singular pass
    (N = 40: 20 of them, where Phi_q loses rank 40): to 1e-8 m for N = 40 (2.5-3.1e-9 m
    over one-ulp changes of an initial velocity); N = 2's passes amplify such a change
    to 3.8e-9 .. 1.8e-8 m and 2.0e-8 .. 9.4e-8 m/s (SkylakeX's initial velocities are one),
    so 5e-8 m and 2.5e-7 m/s."""
    case = load_case(CASES / f"a02_four_bar_n{n}.toml")
    assert case.duration == duration
    df = _natcoord(case)
    ex = exact.n_four_bar(n, case.times)
    assert np.sum(np.diff(np.floor(ex["phi"] / np.pi)) != 0) == passes
    for c, k in (("x_B0", "x"), ("y_B0", "y")):
        assert np.max(np.abs(df[c].to_numpy() - ex[k])) < pos, c
    for c, k in (("vx_B0", "vx"), ("vy_B0", "vy")):
        assert np.max(np.abs(df[c].to_numpy() - ex[k])) < vel, c
    assert np.max(np.abs(df["energy"].to_numpy() - ex["energy"])) < 1e-7


@pytest.mark.parametrize("n", [1, 2, 5])
def test_n_four_bar_rank(n):
    """Grübler: 3 (2N + 1) coordinates of motion, 2 (3N + 1) revolute equations: 1 DOF for
    every N, and natcoord finds no redundant constraint in a regular pose (each coupler closes
    its own loop). At the horizontal singular pose Phi_q loses rank N: DOF N + 1."""
    case = load_case(_generated(n))
    cm = casemodel.build(case, "joints")
    q0 = casemodel.initial_state(cm).q
    d = outputs.diagnostics(cm, q0)
    assert (d["dof"], d["redundant"]) == (1, 0)
    # the same chain generated at its horizontal pose: tip B_i at (i + 1, 0)
    flat = re.sub(r"B(\d+) = \[[-0-9.]+, 1\.0\]",
                  lambda m: f"B{m[1]} = [{int(m[1]) + 1}.0, 0.0]", n_four_bar(n))
    path = _generated(n)
    path.write_text(flat)
    cm = casemodel.build(load_case(path), "joints")
    q = cm.model.q0
    d = outputs.diagnostics(cm, q)
    assert d["dof"] == n + 1 and d["redundant"] == n


def _generated(n: int, tmp=None):
    import tempfile
    from pathlib import Path

    path = Path(tempfile.mkdtemp()) / f"a02_four_bar_n{n}.toml"
    path.write_text(n_four_bar(n))
    return path


def test_generator_reproduces_the_committed_case_files():
    """The committed A02 files are the generator's output, byte for byte, and load."""
    for path in sorted(CASES.glob("a02_four_bar_n*.toml")):
        n = int(path.stem.rsplit("n", 1)[1])
        assert path.read_text() == n_four_bar(n), path.name
        load_case(path)
    assert (CASES / "a02_four_bar_n2.toml").exists()


def test_generated_header_is_the_command_that_wrote_it():
    """The header names the generator's module and repeats every option given."""
    head = n_four_bar(3, name="a02_n3", duration=2.5).splitlines()[:2]
    assert head[0] == ("# Generated by `natcoord generate n_four_bar --n 3 --duration 2.5 "
                       "--out cases/a02_n3.toml`:")
    assert "natcoord/case/generate.py" in head[1]
    assert (Path(__file__).parents[1] / "natcoord/case/generate.py").is_file()
    assert "--duration" not in n_four_bar(3).splitlines()[0]


def test_generate_command_writes_a_loadable_case(tmp_path):
    from typer.testing import CliRunner

    from natcoord.cli import app

    out = tmp_path / "a02_four_bar_n7.toml"
    res = CliRunner().invoke(app, ["generate", "n_four_bar", "--n", "7", "--out", str(out)])
    assert res.exit_code == 0, res.output
    case = load_case(out)
    assert len(case.bodies) == 15 and len(case.joints) == 22
    assert {c.name for c in case.channels} == {"x_B0", "y_B0", "vx_B0", "vy_B0", "energy"}
    assert case.engine("natcoord").tolerance == {}  # N = 7 is not measured: none claimed
    bad = CliRunner().invoke(app, ["generate", "n_four_bar", "--n", "0", "--out", str(out)])
    assert bad.exit_code == 2
