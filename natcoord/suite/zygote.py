"""Engine processes forked from a server that has imported the worker once.

An engine process (:mod:`natcoord.suite.worker`) spends about a second of processor time
importing numpy, scipy, pandas, numba and natcoord before it runs anything: a minute of a
first look's two, and more in a nightly's serial bench. Instead, the first engine process
of a command starts a fork server (:mod:`multiprocessing`'s ``forkserver``) that imports
those modules once, in the engine processes' environment (BLAS on one thread); each engine
process is then a fork of it. Each still runs in a process of its own, in a process group
of its own, so that a crash, a time limit or an interruption ends that run alone, as with
a fresh interpreter, and under the same name (``ps`` shows ``... -m natcoord.suite.worker
--cwd DIR JOB OUT``).

A request whose environment differs from the server's (a variable set after it started)
falls back to a fresh interpreter (:func:`usable` is False): the server's imports read the
environment once.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys
import threading
from multiprocessing import forkserver
from multiprocessing.connection import wait as mp_wait

import setproctitle

from ..engines.registry import BUILTIN

# what an engine process imports (the adapters, not their engines), natcoord's engine and
# what its runs import on first use (numba and the compiled kernels' modules, the outputs,
# scipy's splines for the work channels): 0.3-0.4 s less in each natcoord process
PRELOAD = ["natcoord.suite.worker", *BUILTIN.values(), "natcoord.dynamics.forward",
           "natcoord.model.casemodel", "natcoord.outputs.channels", "scipy.interpolate"]
_LOCK = threading.Lock()
_STATE: dict = {}  # "ctx": the forkserver context, "env": the environment it started with,
# "pid": the server's process id
_REAP = threading.Lock()  # held while an engine process starts or its status is read


def usable(env: dict) -> bool:
    """Whether engine processes of environment ``env`` can be forked from the server (it
    is started here on the first call): POSIX with ``forkserver``, not in a daemonic
    process, the same environment as the server's, ``NATCOORD_NO_FORKSERVER`` unset."""
    if (env.get("NATCOORD_NO_FORKSERVER") or "forkserver" not in mp.get_all_start_methods()
            or mp.current_process().daemon):  # e.g. a Dask worker: no children of its own
        return False
    with _LOCK:
        if _STATE.get("ctx") is not None and not _serving():
            # it died (killed by a user, or out of memory): a new one, with its environment
            server_env = _STATE["env"]
            _stop_locked()
            _start(server_env)
        if "ctx" not in _STATE:
            _start(env)
    return _STATE.get("env") == env


def _serving() -> bool:
    """Whether the server :func:`_start` started is the one running: alive, and not one
    that multiprocessing started in its place (with this process's environment, not the
    engine processes') when a fork was asked of a server that had died."""
    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    if pid is None or pid != _STATE.get("pid"):
        return False
    try:  # WNOWAIT: a dead server stays to be reaped by multiprocessing's own stop
        return os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is None
    except ChildProcessError:
        return False


def _start(env: dict) -> None:
    """Start the fork server with ``env`` as its environment and :data:`PRELOAD` imported
    (once per command)."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    saved = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)  # the server inherits this process's environment
    try:
        forkserver.ensure_running()
    except OSError:
        ctx = None
    finally:
        os.environ.clear()
        os.environ.update(saved)
    _STATE["ctx"], _STATE["env"] = ctx, (dict(env) if ctx is not None else None)
    _STATE["pid"] = getattr(forkserver._forkserver, "_forkserver_pid", None)


def stop() -> None:
    """Stop the fork server (the next :func:`usable` starts one with its environment)."""
    with _LOCK:
        _stop_locked()


def _stop_locked() -> None:
    """:func:`stop`, with :data:`_LOCK` held."""
    if _STATE.pop("ctx", None) is not None:
        getattr(forkserver._forkserver, "_stop", lambda: None)()
    _STATE.pop("env", None)
    _STATE.pop("pid", None)


class Forked:
    """An engine process forked from the server, with the part of ``subprocess.Popen``'s
    interface the runner uses (``pid``, ``wait``, ``returncode``).

    Its exit status is read once, by :meth:`wait`, under :data:`_REAP`. multiprocessing's
    forkserver ``Popen.poll`` is not thread-safe: the status is four bytes on a pipe, and
    every ``Process.start`` polls all the command's children. A start in another thread
    could read those bytes first, and this process's own read then meets the end of the
    pipe and reports status 255, a crash, for a run that ended cleanly (measured: 137 of
    800 trivial processes started and joined in four threads). So the process leaves
    multiprocessing's list of children as it starts, and it is reaped here alone."""

    def __init__(self, argv: list[str], err_path: str, cpu: int | None):
        server = getattr(forkserver._forkserver, "_forkserver_pid", None)
        self.process = _STATE["ctx"].Process(target=_child,
                                             args=(argv, err_path, cpu, server))
        self.returncode: int | None = None
        with _REAP:
            self.process.start()
            mp.process._children.discard(self.process)  # no other start polls it
        self.pid = self.process.pid

    def wait(self, timeout: float | None = None) -> int:
        """Its exit status, once it has ended (subprocess.TimeoutExpired after ``timeout``
        seconds)."""
        if self.returncode is None:
            if not mp_wait([self.process.sentinel], timeout):
                raise subprocess.TimeoutExpired("natcoord.suite.worker", timeout or 0.0)
            with _REAP:
                self.process.join(0)  # the status is there: it reads without blocking
                self.returncode = self.process.exitcode
        return self.returncode


def _child(argv: list[str], err_path: str, cpu: int | None,
           server: int | None) -> None:  # pragma: no cover - in the fork
    """The engine process: its own process group, SIGKILLed with the server (``server``:
    its pid; a fork whose server died before it asked for that ends here), pinned to
    ``cpu`` when given, standard error to ``err_path``, then the worker's ``main``."""
    from .runner import _die_with_parent

    os.setsid()
    alive = getattr(forkserver._forkserver, "_forkserver_alive_fd", None)
    if alive is not None:  # the server ends when the command does, only if no fork holds
        os.close(alive)    # its end of that pipe open: then every fork is SIGKILLed
    _die_with_parent(cpu)
    try:  # the runner made it, and removes it once it stops waiting for this run (an
        fd = os.open(err_path, os.O_WRONLY | os.O_TRUNC)  # interruption can come while
    except OSError:                                       # the fork is being made)
        os._exit(1)  # it gave up on this run already: nothing is run or left behind
    os.dup2(fd, 2)
    os.close(fd)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.close(null)
    if server is not None and os.getppid() != server:
        os.write(2, b"natcoord: the fork server this run was asked of had died; not run\n")
        os._exit(1)
    title = " ".join([sys.executable, "-m", "natcoord.suite.worker", *argv])
    # a path that is not valid UTF-8 (surrogate escapes) is shown with its bytes replaced
    setproctitle.setproctitle(os.fsencode(title).decode("utf-8", "replace"))
    from . import worker

    sys.exit(worker.main(argv))
