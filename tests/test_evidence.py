"""A verdict rests on evidence: gate and compare judge the result files (checked against the
hashes the run stored) with the case file's tolerances and the stored reference, never the
numbers a summary holds. One test per fault, each on a real results folder (one natcoord
run of pendulum), tampered the way a tester did."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from natcoord import CaseError, load_case
from natcoord.errors import StoredFileError
from natcoord.suite import evidence, gate, outdir, references
from natcoord.suite.evidence import BadReference, sha256_of
from natcoord.suite.io import read_json, write_csv, write_json

from .conftest import CASES, REFERENCES

CELL = "pendulum/natcoord"


def _cli(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "natcoord.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def _clean(p):
    assert "Traceback" not in p.stdout + p.stderr, p.stderr[-1500:]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """One real results folder: pendulum in natcoord, as `natcoord run` writes it."""
    out = tmp_path_factory.mktemp("evidence") / "run"
    p = _cli("run", "pendulum", "--engines", "natcoord", "--out", out)
    assert p.returncode == 0, p.stderr
    return out


@pytest.fixture
def folder(run, tmp_path) -> Path:
    """A copy of the run to tamper with."""
    shutil.copytree(run, tmp_path / "r")
    return tmp_path / "r"


def _csv(folder: Path) -> Path:
    return folder / "results" / "pendulum" / "natcoord.csv"


def _edit_csv(folder: Path, change, *, rehash: bool = False) -> None:
    """Change the result CSV; with ``rehash`` also store its new sha256 in the summary (a
    forgery that keeps the hashes consistent: the errors must still be recomputed)."""
    table = pd.read_csv(_csv(folder))
    change(table)
    write_csv(_csv(folder), table)
    if rehash:
        _edit_summary(folder, lambda r: r["files"].__setitem__(
            "natcoord.csv", sha256_of(_csv(folder).read_bytes())))


def _edit_summary(folder: Path, change) -> None:
    summary = read_json(folder / "summary.json")
    change(summary["records"][0])
    write_json(folder / "summary.json", summary)


def _gate(folder: Path, tmp_path: Path, *args, env=None):
    p = _cli("gate", "--results", folder, "--baseline", tmp_path / "none.json", *args, env=env)
    _clean(p)
    return p


def _project(tmp_path: Path) -> tuple[Path, dict]:
    """A project folder holding pendulum's case file and reference, to damage."""
    home = tmp_path / "project"
    (home / "cases").mkdir(parents=True)
    (home / "references").mkdir()
    shutil.copy(CASES / "pendulum.toml", home / "cases")
    for f in ("pendulum.csv", "pendulum.json"):
        shutil.copy(REFERENCES / f, home / "references")
    return home, {"NATCOORD_HOME": str(home)}


# ---- the run stores its evidence -----------------------------------------------------------
def test_a_run_records_hashes_case_file_and_settings_and_its_gate_passes(run, tmp_path):
    rec = read_json(run / "summary.json")["records"][0]
    assert rec["files"]["natcoord.csv"] == sha256_of(_csv(run).read_bytes())
    assert rec["case_hash"] == load_case(CASES / "pendulum.toml").digest
    assert rec["settings"]["method"] and rec["engine_version"]
    p = _gate(run, tmp_path)
    assert p.returncode == 0 and "judged from their result files" in p.stdout, p.stderr


# ---- result files -------------------------------------------------------------------------
def test_a_shifted_column_fails_as_altered_in_gate_and_compare(run, folder, tmp_path):
    _edit_csv(folder, lambda t: t.__setitem__("x", t["x"] + 1e-3))
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and f"{_csv(folder)}: altered since the run" in p.stderr
    c = _cli("compare", run, folder)
    _clean(c)
    assert c.returncode == 1 and "altered since the run" in c.stderr


def test_a_shifted_column_with_its_hash_forged_fails_on_the_recomputed_error(folder, tmp_path):
    _edit_csv(folder, lambda t: t.__setitem__("x", t["x"] + 1e-3), rehash=True)
    p = _gate(folder, tmp_path)  # the summary still says every channel passed
    assert p.returncode == 1 and "pendulum/natcoord: x max error 0.001 m > tolerance" \
        in p.stderr, p.stderr


def test_a_nan_in_a_result_fails_its_cell(folder, tmp_path):
    _edit_csv(folder, lambda t: t.__setitem__("theta", t["theta"].where(t.index != 5, np.nan)),
              rehash=True)
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and "theta: non-finite values" in p.stderr, p.stderr


def test_a_deleted_result_file_fails_its_cell(folder, tmp_path):
    _csv(folder).unlink()
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and f"{_csv(folder)}: missing" in p.stderr, p.stderr


def test_every_result_deleted_fails_gate_and_compare(run, folder, tmp_path):
    shutil.rmtree(folder / "results")  # the summary still says ok
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and "missing (deleted since the run)" in p.stderr
    c = _cli("compare", run, folder)
    assert c.returncode == 1 and "missing" in c.stderr, c.stderr
    c = _cli("compare", folder, run)  # a base without evidence: bad input, not a pass
    assert c.returncode == 2 and "(base)" in c.stderr and "missing" in c.stderr, c.stderr


def test_a_summary_without_hashes_is_not_evidence(folder, tmp_path):
    _edit_summary(folder, lambda r: r.pop("files"))
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and "no content hash in the summary" in p.stderr


def test_an_unreadable_result_fails_its_cell(folder, tmp_path):
    _csv(folder).write_text("t,x\n0,not-a-number\n")
    _edit_summary(folder, lambda r: r["files"].__setitem__(
        "natcoord.csv", sha256_of(_csv(folder).read_bytes())))
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and f"{_csv(folder)}: unreadable" in p.stderr, p.stderr


# ---- the summary is an index, not a witness ------------------------------------------------
def test_a_record_stripped_of_its_channels_is_judged_from_its_files(folder, tmp_path):
    _edit_csv(folder, lambda t: t.__setitem__("y", t["y"] + 1e-3), rehash=True)
    _edit_summary(folder, lambda r: r.update(channels={}, verdict="pass"))
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and "y max error" in p.stderr, p.stderr


def test_a_tolerance_dropped_from_the_summary_switches_off_nothing(folder, tmp_path):
    """Baseline x = 1e-12; the run's x error 5e-9 (within the 1e-8 tolerance, but 5000x
    the baseline); the summary's x entry has no tolerance: the growth still fails."""
    _edit_csv(folder, lambda t: t.__setitem__("x", t["x"] + 5e-9), rehash=True)
    _edit_summary(folder, lambda r: r["channels"]["x"].update(
        max_abs=5e-9, tolerance=None, **{"pass": None}))
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {CELL: {"x": 1e-12}}})
    p = _cli("gate", "--results", folder, "--baseline", base)
    _clean(p)
    assert p.returncode == 1 and "pendulum/natcoord: x error 5.01e-09 m grew" in p.stderr


def test_tolerances_come_from_the_case_file(folder, tmp_path):
    home, env = _project(tmp_path)
    case = home / "cases" / "pendulum.toml"
    case.write_text(case.read_text().replace("[engines.natcoord.tolerance]\nangle = 1e-8",
                                             "[engines.natcoord.tolerance]\nangle = 1e-15"))
    p = _gate(folder, tmp_path, env=env)
    assert p.returncode == 1 and "theta max error" in p.stderr and "> tolerance 1e-15" \
        in p.stderr, p.stderr
    assert "changed since the run" in p.stderr
    r = _cli("report", "--results", folder, "--history", tmp_path / "none.db", env=env)
    _clean(r)  # the page says what the gate noted, beside its verdict
    assert r.returncode == 0 and "pendulum.toml changed since the run; judged with its " \
        "tolerances as they are now" in (folder / "index.html").read_text(), r.stderr


def test_the_baseline_stores_the_errors_judged_not_the_summarys(folder, tmp_path):
    _edit_summary(folder, lambda r: r["channels"]["x"].update(max_abs=1e-30))
    base = tmp_path / "baseline.json"
    p = _cli("gate", "--results", folder, "--baseline", base, "--update-baseline")
    _clean(p)
    assert p.returncode == 0 and "baseline updated for the 1 cells" in p.stdout, p.stderr
    stored = read_json(base)["errors"][CELL]["x"]
    assert stored > 1e-14 and stored == pytest.approx(
        gate.judge(read_json(folder / "summary.json"), folder,
                   cases=gate.CaseBook(CASES), references=REFERENCES).errors[CELL]["x"])


def test_a_failing_gate_updates_no_baseline(folder, tmp_path):
    _csv(folder).unlink()
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {CELL: {"x": 1e-12}}})
    before = base.read_text()
    p = _cli("gate", "--results", folder, "--baseline", base, "--update-baseline")
    assert p.returncode == 1 and base.read_text() == before


def test_two_baseline_updates_at_once_lose_no_cell(tmp_path, monkeypatch):
    """Threads updating different cells at once, each slow between reading and writing the
    baseline: under the lock every cell is kept."""
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {"kept/natcoord": {"x": 1.0}}})
    slow_write = gate.write_json

    def write(path, data):
        threading.Event().wait(0.05)  # widen the read-modify-write window
        slow_write(path, data)

    monkeypatch.setattr(gate, "write_json", write)
    cells = [f"c{i}/natcoord" for i in range(4)]
    start = threading.Barrier(len(cells))

    def update(cell):
        start.wait()
        gate.update_baseline(gate.Verdict(0, channels={cell: {"x": {"max_abs": 1e-9}}},
                                          outcome={cell: "pass"}), base)

    threads = [threading.Thread(target=update, args=(c,)) for c in cells]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert set(gate.load_baseline(base)) == {"kept/natcoord", *cells}


def test_a_baseline_that_cannot_be_written_is_not_a_regression(folder, tmp_path):
    (tmp_path / "file").write_text("")
    p = _cli("gate", "--results", folder, "--baseline", tmp_path / "file" / "baseline.json",
             "--update-baseline")
    _clean(p)
    assert p.returncode == gate.CANNOT_WRITE and "cannot write the baseline" in p.stderr


def test_a_bad_baseline_is_blamed_on_the_baseline_file(folder, tmp_path):
    base = tmp_path / "baseline.json"
    base.write_text(json.dumps({"errors": {CELL: 3}}))
    p = _cli("gate", "--results", folder, "--baseline", base)
    _clean(p)
    assert p.returncode == 2 and f"{base}: malformed baseline" in p.stderr
    assert "summary" not in p.stderr


# ---- references ---------------------------------------------------------------------------
def test_a_renamed_reference_column_is_bad_input_naming_the_reference(folder, tmp_path):
    home, env = _project(tmp_path)
    ref = home / "references" / "pendulum.csv"
    ref.write_text(ref.read_text().replace(",x,", ",X,", 1))
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {CELL: {"x": 1e-11}}})
    before = base.read_text()
    p = _cli("gate", "--results", folder, "--baseline", base, "--update-baseline", env=env)
    _clean(p)
    assert p.returncode == 2 and f"{ref}: reference lacks column(s) x" in p.stderr, p.stderr
    assert base.read_text() == before  # the channel's baseline is kept


def test_a_malformed_undetermined_field_is_bad_input_naming_the_provenance(folder, tmp_path):
    home, env = _project(tmp_path)
    prov = home / "references" / "pendulum.json"
    data = read_json(prov)
    data["undetermined"] = "x"
    write_json(prov, data)
    p = _gate(folder, tmp_path, env=env)
    assert p.returncode == 2 and f"{prov}: undetermined: must be a list" in p.stderr


def test_a_reference_of_an_edited_mechanism_is_stale_but_a_tolerance_edit_is_not(folder,
                                                                                   tmp_path):
    """The reference stores a digest of each part of the mechanism: a heavier bob after the
    run and its reference makes the gate refuse to judge (the reference is stale, named with
    the part that changed), while a loosened tolerance is judged against it as before."""
    home, env = _project(tmp_path)
    case = home / "cases" / "pendulum.toml"
    text = case.read_text()
    heavier, n = re.subn(r"^(mass = )([0-9.eE+-]+)", lambda m: f"{m[1]}{float(m[2]) * 2}",
                         text, count=1, flags=re.M)
    assert n == 1
    case.write_text(heavier)
    p = _gate(folder, tmp_path, env=env)
    ref = home / "references" / "pendulum.csv"
    assert p.returncode == 2, p.stdout + p.stderr
    assert f"{ref}: computed for another mechanism: the case's bodies changed" in p.stderr
    assert "natcoord reference update pendulum" in p.stderr
    looser = re.sub(r"^(angle = )([0-9.eE+-]+)", lambda m: f"{m[1]}{float(m[2]) * 10}", text,
                    count=1, flags=re.M)
    assert looser != text
    case.write_text(looser)
    p = _gate(folder, tmp_path, env=env)
    assert p.returncode == 0 and "stale" not in p.stdout + p.stderr, p.stdout + p.stderr


def test_every_shipped_reference_was_computed_for_its_case_as_it_is_now():
    """A physics edit of a shipped case without `natcoord reference update` fails here."""
    from natcoord.case.mechanism import mechanism_parts
    for prov in sorted(REFERENCES.glob("*.json")):
        data = read_json(prov)
        if not (isinstance(data, dict) and "case_file" in data):
            continue  # baseline.json, durations.json
        case = load_case(CASES / data["case_file"])
        assert data["mechanism"] == mechanism_parts(case), prov.name


@pytest.mark.parametrize("kernel", ["Prescott", "Sandybridge"])
def test_a_mechanism_digest_is_the_same_under_every_blas_kernel(kernel):
    """The digests a reference is stored with hold on every machine: derived values of a
    case (a rod's length, a unit axis) are rounded alike whatever BLAS kernel the CPU
    picks. Computed by numpy's norm, a rod of parallelogram_3d differed by an ulp under
    OpenBLAS's SkylakeX kernel, and its reference was stale there and current elsewhere.
    (OPENBLAS_CORETYPE is ignored off x86, where the two runs are alike.)"""
    from natcoord.case.mechanism import mechanism_parts
    code = ("import json, sys; from pathlib import Path; from natcoord import load_case; "
            "from natcoord.case.mechanism import mechanism_parts; "
            "print(json.dumps({p.name: mechanism_parts(load_case(p)) "
            "for p in sorted(Path(sys.argv[1]).glob('*.toml'))}))")
    r = subprocess.run([sys.executable, "-c", code, str(CASES)], capture_output=True,
                       text=True, env=os.environ | {"OPENBLAS_CORETYPE": kernel}, timeout=300)
    assert r.returncode == 0, r.stderr
    here = {p.name: mechanism_parts(load_case(p)) for p in sorted(CASES.glob("*.toml"))}
    assert len(here) >= 15 and json.loads(r.stdout) == here  # this process: its own kernel


def test_the_mechanism_digest_ignores_layout_and_names_the_part_that_changed(tmp_path):
    from natcoord.case.mechanism import mechanism_parts
    text = (CASES / "pendulum.toml").read_text()
    moved = tmp_path / "pendulum.toml"
    moved.write_text("# a comment\n" + text.replace(" = ", "   =   "))
    base = mechanism_parts(load_case(CASES / "pendulum.toml"))
    assert mechanism_parts(load_case(moved)) == base
    moved.write_text(re.sub(r"^(duration = )([0-9.eE+-]+)",
                            lambda m: f"{m[1]}{float(m[2]) / 2}", text, count=1, flags=re.M))
    changed = mechanism_parts(load_case(moved))
    assert {k for k in base if base[k] != changed[k]} == {"scenario"}


def test_a_nan_in_the_reference_is_blamed_on_the_reference(folder, tmp_path):
    home, env = _project(tmp_path)
    ref = home / "references" / "pendulum.csv"
    table = pd.read_csv(ref)
    table.loc[3, "O_y"] = np.nan
    write_csv(ref, table)
    p = _gate(folder, tmp_path, env=env)
    assert p.returncode == 2 and f"{ref}: non-finite values" in p.stderr and "O_y" in p.stderr
    assert "this engine" not in p.stderr


def test_a_missing_reference_is_not_nothing_ran(folder, tmp_path):
    home, env = _project(tmp_path)
    (home / "references" / "pendulum.csv").unlink()
    p = _gate(folder, tmp_path, env=env)
    assert p.returncode == 2 and "no reference stored" in p.stderr, p.stderr
    assert "nothing ran" not in p.stderr


def test_reference_update_refuses_to_write_corrupt_columns(tmp_path, monkeypatch):
    """A table whose time column a channel overwrote is never stored as a reference."""
    real = references.evaluate_channels

    def corrupt(case, motion):
        table = real(case, motion)
        table["t"] = table["x"]
        return table

    monkeypatch.setattr(references, "evaluate_channels", corrupt)
    case = load_case(CASES / "pendulum.toml")
    with pytest.raises(BadReference, match="not written: .*sample times"):
        references.update_reference(case, tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["t", "time"])
def test_channels_named_like_the_time_column_are_refused(tmp_path, name):
    text = (CASES / "pendulum.toml").read_text().replace("[channels]\ntheta =",
                                                         f"[channels]\n{name} =")
    assert f"[channels]\n{name} =" in text
    (tmp_path / "pendulum.toml").write_text(text)
    with pytest.raises(CaseError, match=f"channels.{name}: '{name}' is reserved"):
        load_case(tmp_path / "pendulum.toml")
    p = _cli("run", "pendulum", "--engines", "natcoord", "--cases-dir", tmp_path,
             "--out", tmp_path / "r")
    _clean(p)
    assert p.returncode == 2 and "is reserved for the time column" in p.stderr


# ---- compare ------------------------------------------------------------------------------
def test_compare_reports_version_case_file_and_settings_changes(run, folder):
    _edit_summary(folder, lambda r: (r.update(engine_version="9.9", case_hash="0" * 64),
                                     r["settings"].update(rtol=1e-6)))
    c = _cli("compare", run, folder)
    _clean(c)
    assert c.returncode == 0, c.stderr
    assert "pendulum/natcoord: engine version" in c.stderr and "-> 9.9" in c.stderr
    assert "case file changed" in c.stderr and "setting rtol: 1e-12 -> 1e-06" in c.stderr
    j = json.loads(_cli("compare", run, folder, "--json").stdout)
    assert len(j["changes"]) == 3



def test_a_record_relabelled_unsupported_cannot_hide_a_cell_the_baseline_holds(tmp_path):
    """Two cells ran; slider_crank's record is relabelled ``unsupported`` (an engine may
    refuse a case at run time, so the label alone proves nothing). With the baseline
    holding that cell's errors from a judged run: exit 3 naming the cell. Without a
    baseline entry for it, the label is all there is: the other cell is judged, exit 0."""
    out = tmp_path / "run"
    p = _cli("run", "pendulum", "slider_crank", "--engines", "natcoord", "--out", out)
    assert p.returncode == 0, p.stderr
    summary = read_json(out / "summary.json")
    (rec,) = [r for r in summary["records"] if r["case"] == "slider_crank"]
    rec.update(status="unsupported", reason="relabelled")
    write_json(out / "summary.json", summary)
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {"slider_crank/natcoord": {"theta": 1e-9}}})
    p = _cli("gate", "--results", out, "--baseline", base)
    _clean(p)
    assert p.returncode == gate.NOT_RUN and "slider_crank/natcoord: unsupported " \
        "(relabelled), but the baseline holds its errors" in p.stderr, p.stderr
    write_json(base, {"errors": {CELL: {"x": 1.0}}})  # without the baseline's entry: the
    p = _cli("gate", "--results", out, "--baseline", base)  # results on disk contradict it
    _clean(p)
    csv = out / "results" / "slider_crank" / "natcoord.csv"
    assert p.returncode == gate.REGRESSION and f"{csv} holds a run's results, but its record " \
        "in summary.json says 'unsupported'" in p.stderr, p.stderr
    report = _cli("report", "--results", out)  # the page shows the gate's verdict
    assert report.returncode == 0, report.stderr
    html = (out / "index.html").read_text()
    assert 'class="verdict v-fail"' in html and "holds a run&#39;s results" in html
    csv.unlink()  # its results deleted too: the folder's marker lists them
    p = _cli("gate", "--results", out, "--baseline", base)
    assert p.returncode == gate.REGRESSION and f"{csv}: missing" in p.stderr, p.stderr


def test_the_report_shows_the_verdict_the_files_give_not_the_summarys(folder, tmp_path):
    """`natcoord report` judges every cell from its files as the gate does: a deleted
    result fails the page (the summary still says pass), an intact folder passes it."""
    p = _cli("report", "--results", folder)
    assert p.returncode == 0, p.stderr
    assert 'class="verdict v-pass"' in (folder / "index.html").read_text()
    _csv(folder).unlink()
    p = _cli("report", "--results", folder)
    _clean(p)
    assert p.returncode == 0, p.stderr
    html = (folder / "index.html").read_text()
    assert 'class="verdict v-fail"' in html and "missing (deleted since the run)" in html


def test_a_result_that_is_not_a_regular_file_fails_its_cell_without_reading_it(folder,
                                                                               tmp_path):
    """A FIFO in place of the CSV hung the gate on its read; a link to a device would
    never end it."""
    _csv(folder).unlink()
    os.mkfifo(_csv(folder))
    p = _cli("gate", "--results", folder, "--baseline", tmp_path / "none.json", timeout=120)
    _clean(p)
    assert p.returncode == 1 and f"{_csv(folder)}: not a regular file" in p.stderr, p.stderr
    _csv(folder).unlink()
    _csv(folder).symlink_to("/dev/zero")
    p = _cli("gate", "--results", folder, "--baseline", tmp_path / "none.json", timeout=120)
    assert p.returncode == 1 and f"{_csv(folder)}: not a regular file" in p.stderr, p.stderr


def test_a_result_with_a_column_twice_fails_its_cell(folder, tmp_path):
    """A second column of a channel's name (its hash forged) was dropped by the reader,
    which judged the first."""
    head, *rows = _csv(folder).read_text().splitlines()
    _csv(folder).write_text("\n".join([head + ",theta"] + [r + ",1e3" for r in rows]) + "\n")
    _edit_summary(folder, lambda r: r["files"].__setitem__(
        "natcoord.csv", sha256_of(_csv(folder).read_bytes())))
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and f"{_csv(folder)}: duplicate columns (theta)" in p.stderr, \
        p.stderr


def test_a_marker_nested_too_deeply_is_a_damaged_marker(folder, tmp_path):
    (folder / outdir.MARKER).write_text("[" * 200000)
    p = _gate(folder, tmp_path)
    assert p.returncode == 2 and "damaged results marker" in p.stderr, p.stderr


def test_a_result_in_a_folder_that_cannot_be_looked_into_is_unreadable_not_missing(
        folder, monkeypatch):
    """A cell folder without read permission: its files are there (the gate fails the
    cell on reading them, exit 1), not missing from the folder, and no PermissionError
    escapes as a fault of the environment (exit 5)."""
    real = Path.stat

    def stat(self, *a, **k):
        if self.parent.name == "pendulum":
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *a, **k)
    monkeypatch.setattr(Path, "stat", stat)
    monkeypatch.setattr(evidence, "_files_on_disk", lambda results: [])  # as os.walk skips it
    assert evidence.unrecorded(folder, read_json(folder / "summary.json")["records"]) == []


@pytest.fixture(scope="module")
def two(tmp_path_factory) -> Path:
    """A results folder of two cells: pendulum and four_bar in natcoord."""
    out = tmp_path_factory.mktemp("evidence") / "two"
    p = _cli("run", "pendulum", "four_bar", "--engines", "natcoord", "--out", out)
    assert p.returncode == 0, p.stderr
    return out


def test_a_record_field_edited_to_another_type_is_bad_input_naming_it(two, tmp_path):
    """pendulum's record relabelled unsupported with an int for its reason, four_bar's
    intact: the gate (whose baseline holds pendulum's errors, so it says why the cell is
    missing) and compare (whose base judged it) used to crash on the reason; the summary is
    bad input naming the file and the field."""
    folder = tmp_path / "r"
    shutil.copytree(two, folder)
    _edit_summary(folder, lambda r: r.update(status="unsupported", reason=5))
    base = tmp_path / "baseline.json"
    write_json(base, {"errors": {CELL: {"x": 1e-9}}})
    where = f"{folder / 'summary.json'}: records[0].reason: not a string"
    p = _cli("gate", "--results", folder, "--baseline", base)
    _clean(p)
    assert p.returncode == 2 and where in p.stderr, p.stderr
    for c in (_cli("compare", two, folder), _cli("compare", folder, two)):
        _clean(c)
        assert c.returncode == 2 and where in c.stderr, c.stderr


@pytest.mark.parametrize("field, value", [
    ("reason", 5), ("verdict_reason", {}), ("case_hash", 7), ("engine_version", 1.5),
    ("settings", [1]), ("counters", "many"), ("notes", "one"), ("samples_s", [-1]),
    ("wall_time_s", "fast"), ("files", {"natcoord.csv": 3}),
    ("channels", {"x": {"max_abs": "small"}}), ("channels", {"x": {"pass": "yes"}})])
def test_every_record_field_a_reader_uses_has_its_type_checked(run, tmp_path, field, value):
    summary = read_json(run / "summary.json")
    summary["records"][0][field] = value
    write_json(tmp_path / "summary.json", summary)
    with pytest.raises(StoredFileError, match=re.escape(f"records[0].{field}")):
        gate.load_summary(tmp_path)


def test_a_record_taken_out_of_the_summary_fails_gate_and_compare(two, run, tmp_path):
    """pendulum's record deleted from the summary (and pendulum from its cases) while its
    result files stay, listed in the folder's marker: the gate used to pass on four_bar
    alone. It fails naming the file, compare too (bad input when that folder is the
    base); with the files deleted as well, the marker still names them. A run of fewer
    cases holds no result files of the others: it passes."""
    folder = tmp_path / "r"
    shutil.copytree(two, folder)
    summary = read_json(folder / "summary.json")
    summary["records"] = [r for r in summary["records"] if r["case"] != "pendulum"]
    summary["cases"].remove("pendulum")
    write_json(folder / "summary.json", summary)
    line = f"{_csv(folder)} has no record in summary.json"
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and line in p.stderr, p.stderr
    c = _cli("compare", two, folder)
    _clean(c)
    assert c.returncode == 1 and line in c.stderr, c.stderr
    c = _cli("compare", folder, two)
    _clean(c)
    assert c.returncode == 2 and f"(base): {line}" in c.stderr, c.stderr
    shutil.rmtree(folder / "results" / "pendulum")
    p = _gate(folder, tmp_path)
    assert p.returncode == 1 and f"{_csv(folder)}: missing (the folder's .natcoord-results " \
        "lists it" in p.stderr, p.stderr
    c = _cli("compare", two, run)  # pendulum alone: a run of fewer cases, which passes
    _clean(c)  # and lists what it did not run
    assert c.returncode == 0, c.stderr
    rows = json.loads(_cli("compare", two, run, "--json").stdout)["rows"]
    assert {(r["case"], r["status"]) for r in rows} == {("pendulum", "ok"),
                                                        ("four_bar", "absent")}, rows


def test_a_result_file_put_in_a_folder_without_a_marker_has_no_record(folder, tmp_path):
    """A results folder written without a marker (run_suite itself) is checked against its
    result CSVs; a damaged marker is bad input naming it."""
    (folder / ".natcoord-results").unlink()
    extra = folder / "results" / "four_bar" / "natcoord.csv"
    extra.parent.mkdir()
    shutil.copy(_csv(folder), extra)
    v = gate.judge(gate.load_summary(folder), folder, cases=gate.CaseBook(CASES),
                   references=REFERENCES)
    assert v.code == gate.REGRESSION and len(v.faults) == 1 and v.faults[0].startswith(
        f"{extra} has no record in summary.json"), v.lines
    assert v.outcome == {CELL: "pass"}
    assert v.folder_faults == v.faults and v.said == {}, v.said  # the folder's, no cell's
    extra.unlink()
    (folder / ".natcoord-results").write_text("{not json")
    v = gate.judge(gate.load_summary(folder), folder, cases=gate.CaseBook(CASES),
                   references=REFERENCES)
    assert v.code == gate.BAD_INPUT and ".natcoord-results: damaged results marker" in \
        v.faults[0], v.lines


def test_what_the_gate_says_of_a_cell_is_kept_as_the_cells(folder):
    """A cell whose file cannot be trusted: the gate keeps its line under the cell
    (``said``, without the cell's name), which the report shows as the cell's reason; the
    folder as a whole has no fault of its own."""
    from natcoord.report.html import as_judged

    _csv(folder).write_text("t,theta\n0,1\n")  # altered: its sha256 no longer matches
    summary = gate.load_summary(folder)
    v = gate.judge(summary, folder, cases=gate.CaseBook(CASES), references=REFERENCES)
    assert v.outcome == {CELL: "bad evidence"} and v.code == gate.REGRESSION, v.lines
    assert len(v.said[CELL]) == 1 and v.faults == [f"{CELL}: {v.said[CELL][0]}"], v.said
    assert v.folder_faults == []
    shown, whole = as_judged(summary["records"], v)
    cell = next(r for r in shown if f"{r['case']}/{r['engine']}" == CELL)
    assert cell["verdict"] == "fail" and cell["reason"] == v.said[CELL][0] and whole == []


def test_the_page_passes_only_what_the_gate_passes(folder, tmp_path):
    """A reference that cannot be trusted (a line of text appended): the gate cannot judge
    the cell (exit 2) and the page fails with its line, where it said PASS ("1 pass, 1
    ran") beside another cell that passed; a cell that ran without a tolerance leaves the
    page PARTLY GATED, not PASS."""
    from natcoord.report.html import as_judged, overall_verdict

    refs = tmp_path / "refs"
    shutil.copytree(REFERENCES, refs)
    with open(refs / "pendulum.csv", "a") as f:
        f.write("garbage,1\n")
    summary = gate.load_summary(folder)
    v = gate.judge(summary, folder, cases=gate.CaseBook(CASES), references=refs)
    assert v.code == gate.BAD_INPUT and v.outcome == {CELL: "cannot judge"}, v.lines
    shown, faults = as_judged(summary["records"], v)
    page = overall_verdict(shown, faults)
    assert page["word"] == "FAIL" and faults == [f"{CELL}: {v.said[CELL][0]}"], page
    assert "reference holds values that are not numbers" in faults[0], faults
    passed = {**shown[0], "verdict": "pass", "engine": "mujoco"}
    unjudged = {**shown[0], "verdict": "n/a", "reason": "no tolerance written"}
    page = overall_verdict([passed, unjudged])
    assert (page["word"], page["summary"]) == ("PARTLY GATED", "1 pass, 1 not judged"), page
    assert overall_verdict([passed])["word"] == "PASS"


def test_propose_keeps_an_existing_out_file(tmp_path):
    """`propose --out` onto an existing file: exit 2 before any run, the file unchanged;
    a folder in its place is never replaced, even with --force."""
    mine = tmp_path / "mine.toml"
    mine.write_text("# my notes\n")
    p = _cli("propose", "pendulum", "--engines", "natcoord", "--out", mine)
    _clean(p)
    assert p.returncode == 2 and "exists; give --force" in p.stderr
    assert mine.read_text() == "# my notes\n"
    p = _cli("propose", "pendulum", "--engines", "natcoord", "--out", tmp_path, "--force")
    _clean(p)
    assert p.returncode == 2 and "not a regular file" in p.stderr and tmp_path.is_dir()


def test_a_folder_replaced_while_the_gate_reads_it_is_judged_again(run, tmp_path):
    """A command publishing into the folder a gate is reading replaces it whole (by rename):
    the summary read before and the result files read after belong to two runs, whose
    hashes fail as altered (the first judging, asserted here, exits 1). The gate sees the
    folder change under it and judges the new one again: it passes."""
    folder, other = tmp_path / "r", tmp_path / "other"
    shutil.copytree(run, folder)
    shutil.copytree(run, other)  # another complete run: a column moved by 1e-12
    _edit_csv(other, lambda t: t.__setitem__(t.columns[1], t[t.columns[1]] + 1e-12),
              rehash=True)
    prog = f"""
import os, sys
from natcoord.suite import gate
real, calls = gate.judge, []
def judge(summary, results, **kw):
    if not calls:  # the summary is read; now a command publishes into the folder
        os.rename({str(folder)!r}, {str(folder)!r} + ".old")
        os.rename({str(other)!r}, {str(folder)!r})
    verdict = real(summary, results, **kw)
    calls.append(verdict.code)
    print("judged", verdict.code, file=sys.stderr)
    return verdict
gate.judge = judge
sys.argv = ["natcoord", *sys.argv[1:]]
from natcoord.cli import main
main()
"""
    p = subprocess.run([sys.executable, "-c", prog, "gate", "--results", str(folder),
                        "--baseline", str(tmp_path / "none.json"), "--history",
                        str(tmp_path / "none.db")], capture_output=True, text=True,
                       timeout=300)
    _clean(p)
    assert "judged 1" in p.stderr and "judging it again" in p.stderr, p.stderr
    assert p.returncode == 0, p.stderr


def test_the_suites_page_names_an_error_grown_past_the_baseline(folder):
    """The suite writes its page with the gate's verdict, baseline included: a cell failed
    for growth (no channel over its tolerance) says why."""
    from natcoord.report.html import build_context
    summary = gate.load_summary(folder)
    tol = gate.judge(summary, folder, cases=gate.CaseBook(CASES), references=REFERENCES
                     ).channels[CELL]["theta"]["tolerance"]
    _edit_csv(folder, lambda t: t.__setitem__("theta", t["theta"] + 0.5 * tol), rehash=True)
    v = gate.judge(gate.load_summary(folder), folder, cases=gate.CaseBook(CASES),
                   references=REFERENCES, baseline={CELL: {"theta": 1e-30}}, floor=1e-30)
    assert v.outcome[CELL] == "fail"
    ctx = build_context(folder, REFERENCES, None, v)
    (cell,) = [c for row in ctx["matrix"] for c in row["cells"] if c["engine"] == "natcoord"]
    assert cell["key"] == "fail" and "over the baseline" in cell["reason"], cell
    assert ctx["overall"]["state"] == "fail"
