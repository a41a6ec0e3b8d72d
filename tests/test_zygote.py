"""Engine processes forked from the fork server (natcoord.suite.zygote) against fresh
interpreters: the same result files, a crash and a time limit reported the same way."""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from collections import Counter

import pandas as pd
import pytest

from natcoord.case.casefile import load_case
from natcoord.suite import runner, zygote
from tests.conftest import CASES

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="forkserver on Linux")


@pytest.fixture(autouse=True)
def _server_of_this_environment(monkeypatch):
    """A server started with this test's environment (another test may have started one
    with its own)."""
    monkeypatch.delenv("NATCOORD_NO_FORKSERVER", raising=False)
    zygote.stop()
    yield
    zygote.stop()


def _run(tmp_path, name, monkeypatch, fresh: bool, case="pendulum", timeout=120.0):
    if fresh:
        monkeypatch.setenv("NATCOORD_NO_FORKSERVER", "1")
    else:
        monkeypatch.delenv("NATCOORD_NO_FORKSERVER", raising=False)
    out = tmp_path / name
    rec = runner.run_subprocess(load_case(CASES / f"{case}.toml"), "natcoord", out, timeout)
    return rec, out / "results" / case / "natcoord.csv"


def _err_files() -> set[str]:
    """What the runner made in the temporary directory and left (its scratch folder holds
    a forked run's standard error's file)."""
    return {p for p in os.listdir(tempfile.gettempdir()) if p.startswith("natcoord-")}


def test_a_forked_run_writes_what_a_fresh_interpreter_writes(tmp_path, monkeypatch):
    assert zygote.usable(runner.worker_env())  # this test process may fork from the server
    private = tmp_path / "tmp"  # the worker's standard error goes to a temporary file:
    private.mkdir()  # here, not in the shared directory other natcoord runs write to
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    forked, f_csv = _run(tmp_path, "forked", monkeypatch, fresh=False)
    assert _err_files() == set()  # its standard error's file is gone
    fresh, s_csv = _run(tmp_path, "fresh", monkeypatch, fresh=True)
    assert forked["status"] == fresh["status"] == "ok"
    pd.testing.assert_frame_equal(pd.read_csv(f_csv), pd.read_csv(s_csv), check_exact=True)


def test_the_server_is_not_used_where_it_cannot_serve(monkeypatch):
    env = runner.worker_env()
    assert not zygote.usable({**env, "NATCOORD_NO_FORKSERVER": "1"})
    if zygote.usable(env):  # started: another environment than the server's falls back
        assert not zygote.usable({**env, "NATCOORD_SOMETHING_NEW": "1"})


@pytest.mark.parametrize("fresh", [False, True], ids=["forked", "fresh"])
def test_a_crash_and_a_time_limit_are_reported_and_leave_nothing_behind(tmp_path,
                                                                          monkeypatch, fresh):
    """A worker that fails and one killed at its time limit: each reported, and neither
    leaves its scratch folder (the runner removes it) or its standard error's file."""
    private = tmp_path / "tmp"  # where this process's and the engine processes' temporary
    private.mkdir()              # folders and files go
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    monkeypatch.setenv("TMPDIR", str(private))
    if fresh:
        monkeypatch.setenv("NATCOORD_NO_FORKSERVER", "1")
    else:
        monkeypatch.delenv("NATCOORD_NO_FORKSERVER", raising=False)
    assert zygote.usable(runner.worker_env()) is not fresh
    job = tmp_path / "job.pkl"
    job.write_bytes(b"not a pickle")  # the worker fails to read it: exit status 1
    code, err = runner.run_worker(job, tmp_path, 60.0)
    assert code == 1 and "UnpicklingError" in err
    rec, _ = _run(tmp_path, "slow", monkeypatch, fresh=fresh, case="a01_pendulum",
                  timeout=0.5)
    assert rec["status"] == "failed" and "timed out after 0.5 s" in rec["reason"]
    assert [p.name for p in private.iterdir() if p.name.startswith("natcoord-")] == []


def test_every_status_is_read_as_the_process_ended_with_many_at_once(tmp_path):
    """Engine processes started and waited for in four threads at once (as a parallel run
    does): each status read is the one its process exited with. multiprocessing's own
    reading of a forkserver child's status races with every other start (they poll all
    children): it reported 255, a crash, for one to a few of these 200."""
    assert zygote.usable(runner.worker_env())
    missing = str(tmp_path / "no-such-job")  # the worker's open() fails: exit status 1
    codes: list[int] = []

    def many():
        for i in range(50):
            err = tmp_path / f"{threading.get_ident()}-{i}.err"
            err.touch()  # as the runner makes it
            proc = zygote.Forked([missing, str(tmp_path)], str(err), None)
            codes.append(proc.wait(60))
            assert proc.returncode == codes[-1]
            assert "no-such-job" in err.read_text()  # it did end by the failed open

    threads = [threading.Thread(target=many) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(codes) == 200 and set(codes) == {1}, Counter(codes)


def _server_environ() -> bytes:
    """The fork server's environment (read again while it is still being exec'd: empty)."""
    import time
    from multiprocessing import forkserver
    for _ in range(1000):
        with open(f"/proc/{forkserver._forkserver._forkserver_pid}/environ", "rb") as f:
            if env := f.read():
                return env
        time.sleep(0.01)
    raise AssertionError("the fork server's environment stayed empty for 10 s")


def _kill_server() -> int:
    import signal
    import time
    from multiprocessing import forkserver
    pid = forkserver._forkserver._forkserver_pid
    os.kill(pid, signal.SIGKILL)
    while os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is None:
        time.sleep(0.01)
    return pid


@pytest.mark.parametrize("restarted_by", ["nobody", "multiprocessing"])
def test_a_server_that_died_is_started_again_with_the_engine_environment(
        tmp_path, monkeypatch, restarted_by):
    """The server killed (by a user, by the kernel out of memory): the next engine process
    forks from a new server with the engine processes' environment, even after
    multiprocessing started one in its place with this process's own environment."""
    monkeypatch.delenv("NATCOORD_TEST_MARK", raising=False)
    env = {**runner.worker_env(), "NATCOORD_TEST_MARK": "engine-environment"}
    assert zygote.usable(env)
    assert b"NATCOORD_TEST_MARK=engine-environment" in _server_environ()
    dead = _kill_server()
    if restarted_by == "multiprocessing":
        # a fork asked of the dead server: multiprocessing starts one with this process's
        # environment, and the fork, seeing another parent than the server it was asked
        # of, does not run
        (tmp_path / "e").touch()  # its standard error's file, as the runner makes it
        proc = zygote.Forked(["x", str(tmp_path)], str(tmp_path / "e"), None)
        assert proc.wait(60) == 1
        assert "fork server this run was asked of had died" in (tmp_path / "e").read_text()
        assert b"NATCOORD_TEST_MARK" not in _server_environ()
    assert zygote.usable(env)
    from multiprocessing import forkserver
    assert forkserver._forkserver._forkserver_pid != dead
    assert b"NATCOORD_TEST_MARK=engine-environment" in _server_environ()
    job = tmp_path / "job.pkl"
    job.write_bytes(b"not a pickle")
    monkeypatch.setattr(runner, "worker_env", lambda: env)
    code, err = runner.run_worker(job, tmp_path, 60.0)  # forked from it: it runs the worker
    assert code == 1 and "UnpicklingError" in err


def test_a_fork_whose_runner_gave_up_runs_nothing_and_leaves_nothing(tmp_path):
    """A fork that starts after its runner stopped waiting (an interruption while the fork
    was being made; the runner removed its standard error's file): it exits at once,
    without running the worker or making that file again."""
    assert zygote.usable(runner.worker_env())
    job = tmp_path / "job.pkl"
    job.write_bytes(b"not a pickle")
    gone = tmp_path / "removed.err"
    proc = zygote.Forked([str(job), str(tmp_path)], str(gone), None)
    assert proc.wait(60) == 1
    assert not gone.exists()
