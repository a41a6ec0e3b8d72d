"""Generated N-four-bars (IFToMM A02 for any N) run whole at the generator's settings: the
singular positions passed, the exact reduction matched, a cost per step linear in N
(asserted on the sparsity plan's sizes, never by timing), and `bench --scaling` measuring
those same runs."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from natcoord import CaseError, evaluate_channels, load_case
from natcoord.case.generate import N_FOUR_BAR_MEASURED, n_four_bar
from natcoord.compiled import sparsity
from natcoord.derivations import exact
from natcoord.engines import adapter
from natcoord.engines.base import initial_body_states
from natcoord.model import casemodel
from natcoord.model.drivers import ConstraintSystem
from natcoord.suite import scaling


def test_a_generated_n_four_bar_passes_its_singular_positions_on_the_exact_solution():
    """N = 8 (an N no one measured) for 3 s, three singular passes (Phi_q loses rank 8),
    run whole by natcoord's engine at the generated settings: B0 within 1e-8 m of the
    one-equation reduction (measured 2.5e-10 m; over 10 s 1.4e-9 m)."""
    case = scaling.generated_case(8, duration=3.0)
    run = adapter("natcoord").run(case, initial_body_states(case),
                                  case.engine("natcoord").settings)
    df = evaluate_channels(case, run.motion)
    ex = exact.n_four_bar(8, case.times)
    assert np.sum(np.diff(np.floor(ex["phi"] / np.pi)) != 0) == 3
    for c, k in (("x_B0", "x"), ("y_B0", "y")):
        assert np.max(np.abs(df[c].to_numpy() - ex[k])) < 1e-8, c
    assert run.n_steps == 3000  # fixed 1 ms steps: no stall at the passes


@pytest.mark.parametrize("n", [3, 7, 40, 64, 512])
def test_the_generator_writes_the_linear_cost_path_for_an_unmeasured_n(n):
    """Every body its own points (M block-diagonal), the Schur path, fixed RK4 steps; no
    tolerance claimed for any engine at an N nobody measured (N = 40 for 10 s included:
    only its 20 s member is measured). The file's text is read (loading a large member
    runs the loader's dense model checks, minutes at N = 512)."""
    engines = tomllib.loads(n_four_bar(n, duration=10.0))["engines"]
    s = engines["natcoord"]["settings"]
    assert (s["coordinates"], s["method"], s["h"], s["linsolve"]) == (
        "joints", "rk4", 1e-3, "schur")
    assert s["reference"]["h"] < s["h"]
    for name, block in engines.items():
        assert "tolerance" not in block, name


def test_the_measured_members_keep_their_measured_settings():
    for n in N_FOUR_BAR_MEASURED:
        case = scaling.generated_case(n)
        assert case.engine("natcoord").settings["coordinates"] == "shared"
        assert case.engine("natcoord").tolerance


def _plan(n: int, coordinates: str):
    cm = casemodel.build(scaling.generated_case(n, duration=1.0), coordinates)
    return sparsity.schur_plan(ConstraintSystem(cm.model).con, np.asarray(cm.model.M, float))


def _sizes(plan) -> np.ndarray:
    """What one evaluation's work is proportional to: rows, J's entries, the products
    forming Y = M^-1 J^T and W = J Y, the envelope of W's Cholesky factor."""
    return np.array([plan.m, len(plan.J_row), len(plan.y_j), len(plan.w_j), plan.envelope])


def test_the_generated_settings_cost_linearly_in_n():
    """Each of the plan's sizes grows by the same amount for every 16 couplers more (exactly
    linear) and L's rows stay 7 wide; with shared points (N = 40's settings) the envelope
    of W is its whole triangle, quadratic in N."""
    coordinates = scaling.generated_case(16).engine("natcoord").settings["coordinates"]
    a, b, c = (_sizes(_plan(n, coordinates)) for n in (16, 32, 48))
    assert np.array_equal(c - b, b - a) and np.all(b - a > 0)
    plan = _plan(48, coordinates)
    assert int(np.max(np.arange(plan.m) - plan.env_first)) + 1 == 7
    shared = [_plan(n, "shared") for n in (16, 32)]
    assert [p.envelope for p in shared] == [p.m * (p.m + 1) // 2 for p in shared]


def test_scaling_measures_whole_generated_runs():
    """`bench --scaling`'s records: the generated case's own settings, every output sample
    of its duration, build apart from stepping, and the error against the exact reduction."""
    out = scaling.scaling([4, 8], duration=1.5, repeats=1)
    assert "rk4" in out["method"] and out["size_ratio"] == 2.0
    for rec in out["records"]:
        assert (rec["coordinates"], rec["method"], rec["h"]) == ("joints", "rk4", 1e-3)
        assert rec["steps"] == 1500 and rec["duration_s"] == 1.5
        assert rec["error_m"] < 1e-8
        assert rec["build_time_s"] > 0 and len(rec["samples_s"]) == 1
        assert rec["us_per_step"] == pytest.approx(1e6 * rec["wall_time_s"] / 1500)
        assert rec["s_per_simulated_s"] == pytest.approx(rec["wall_time_s"] / 1.5)
    assert out["step_cost_ratio"] > 0


def test_scaling_times_the_sizes_in_interleaved_rounds(monkeypatch):
    """Every N gets the same number of whole runs, taken in rounds (N = 4, then 8, then 4
    again ...), so that a change in the machine's load falls on every size alike; at least
    two rounds even when the first one spends the budget."""
    order = []
    real = scaling._Member.run

    def run(self):
        order.append(self.N)
        return real(self)
    monkeypatch.setattr(scaling._Member, "run", run)
    monkeypatch.setattr(scaling, "BUDGET_S", 0.0)  # every round is over budget
    out = scaling.scaling([4, 8], duration=0.2, repeats=3)
    assert order == [4, 8, 4, 8]
    for rec in out["records"]:
        assert len(rec["samples_s"]) == 2 and rec["wall_time_s"] == min(rec["samples_s"])


@pytest.mark.parametrize("out, said", [
    ("newdir/", "names a folder; give the case file to write"),
    ("g/x.txt", "a case file ends in .toml"),
    ('a"b.toml', "its stem is the case name"),
])
def test_generate_refuses_an_out_that_is_not_a_case_file(tmp_path, out, said):
    """--out newdir/ (a folder that does not exist) used to write a file named newdir, and
    --out x.txt a case no command finds."""
    from typer.testing import CliRunner

    from natcoord.cli import app

    res = CliRunner().invoke(app, ["generate", "n_four_bar", "--n", "2", "--out",
                                   f"{tmp_path}/{out}"])
    assert res.exit_code == 2, res.output
    assert f"--out '{tmp_path}/{out}': {said}" in res.output, res.output
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("duration, said", [
    ("0.005", "--duration 0.005: must be a multiple of the output step 0.01 s"),
    ("20000", "--duration 20000: 2e+06 output samples (every 0.01 s) are beyond the budget"),
])
def test_generate_names_the_duration_option_it_cannot_take(tmp_path, duration, said):
    """The loader's complaint about a temporary file's output_dt used to stand for it."""
    from typer.testing import CliRunner

    from natcoord.cli import app

    res = CliRunner().invoke(app, ["generate", "n_four_bar", "--n", "2", "--out",
                                   str(tmp_path / "x.toml"), "--duration", duration])
    assert res.exit_code == 2, res.output
    assert said in res.output and "natcoord-generate" not in res.output, res.output
    assert list(tmp_path.iterdir()) == []


def test_a_model_past_the_coordinate_budget_is_refused_before_it_is_built(tmp_path):
    """N = 1100 couplers make 8804 coordinates: the model's arrays, growing as their
    square, took 2.6 GB at N = 1000 and would take about 10 GB at the loader's N = 2000.
    Refused (exit 2, naming the budget) before they are allocated: by the family at once,
    and by the loader for a case file as large written by hand (naming its field)."""
    import resource

    from typer.testing import CliRunner

    from natcoord.cli import app
    from natcoord.model.casemodel import MAX_COORDINATES

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    res = CliRunner().invoke(app, ["generate", "n_four_bar", "--n", "1100", "--out",
                                   str(tmp_path / "x.toml")])
    assert res.exit_code == 2, res.output
    assert "N = 1100 makes 8804 natural coordinates, beyond natcoord's budget of " \
        f"{MAX_COORDINATES} (N <= 1023)" in " ".join(res.output.split()), res.output
    assert list(tmp_path.iterdir()) == []
    text = n_four_bar(1023, name="x")  # 8188 coordinates; two free rods more, written by
    i = text.index("[[bodies]]")        # hand: the loader refuses them, naming the field
    extra = "".join(f'[[bodies]]\nname = "free{k}"\nkind = "uniform_rod"\nmass = 1.0\n'
                    f'points = {{ P{k} = [0.0, {k + 5}.0], Q{k} = [1.0, {k + 5}.0] }}\n\n'
                    for k in range(2))
    (tmp_path / "x.toml").write_text(text[:i] + extra + text[i:])
    with pytest.raises(CaseError) as e:
        load_case(tmp_path / "x.toml")
    assert e.value.field == "bodies" and "2049 bodies make 8196 natural coordinates " \
        "(joints), beyond natcoord's budget of 8192" in e.value.reason, e.value
    grew = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before  # KiB
    assert grew < 1_000_000, grew  # a model of 8804 coordinates takes about 3 GB
    assert 4 * (2 * 1000 + 1) <= MAX_COORDINATES < 4 * (2 * 1100 + 1)


def test_a_generated_file_that_does_not_load_is_named_by_its_path(tmp_path):
    from natcoord.case.generate import write_case
    from natcoord.errors import NatcoordError

    out = tmp_path / "x.toml"
    text = n_four_bar(2, name="x").replace("output_dt = 0.01", "output_dt = 0.03")
    with pytest.raises(NatcoordError) as e:
        write_case(out, text)
    assert str(e.value).startswith(f"generated file does not load: {out}: output_dt: must "
                                   "divide duration"), str(e.value)
    assert not out.exists()
