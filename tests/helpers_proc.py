"""Helpers for cross-process tests: spawning children and checking none are left behind."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import psutil

from can_db.process.parent import die_with_parent


def _child_setup() -> None:
    """In the child before exec: die with the parent, and start with Ctrl-C as a user's shell
    gives it — default disposition, not blocked. Python installs its KeyboardInterrupt
    handler only when SIGINT is not ignored at start-up, and the disposition and the signal
    mask are inherited across exec, so a child forked while this test process had SIGINT
    ignored or blocked would never see Ctrl-C."""
    import signal

    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def spawn(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    """Start ``python -m ...`` with this interpreter; it dies if the test process dies and
    reacts to SIGINT like a program started from a shell."""
    return subprocess.Popen([sys.executable, *args], text=True,  # type: ignore[call-overload]
                            preexec_fn=_child_setup, **kwargs)


def interrupt_and_wait(proc: subprocess.Popen[str], timeout: float,
                       stderr_path: str | os.PathLike[str] | None = None) -> int:
    """Ctrl-C for a child (SIGINT) and its exit code. A child still running after ``timeout``
    s is sent SIGABRT — with ``PYTHONFAULTHANDLER=1`` in its environment Python then writes
    every thread's stack to its stderr — and the test fails with that stack (read from
    ``stderr_path``), so a hang at shutdown is diagnosable instead of a bare timeout."""
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        stack = ""
        if stderr_path is not None:
            with open(stderr_path, errors="replace") as f:
                stack = f.read()[-6000:]
        raise AssertionError(f"child {proc.args} ignored SIGINT for {timeout} s; "
                             f"its threads at SIGABRT:\n{stack}") from None


# multiprocessing's resource tracker: started once by the first in-process multiprocessing
# user (a dask LocalCluster of an in-process study) and kept by the test process itself
# until it exits. It is the test process's helper, never a child a run left behind.
_OWN_HELPERS = ("multiprocessing.resource_tracker",)


def live_children() -> list[psutil.Process]:
    """Descendant processes of this test process that are still running (not zombies),
    without the test process's own multiprocessing resource tracker."""
    out = []
    for proc in psutil.Process(os.getpid()).children(recursive=True):
        try:
            if proc.status() == psutil.STATUS_ZOMBIE:
                continue
            cmd = " ".join(proc.cmdline())
        except psutil.NoSuchProcess:
            continue
        if not any(h in cmd for h in _OWN_HELPERS):
            out.append(proc)
    return out


@contextmanager
def not_a_bus_server() -> Iterator[int]:
    """A TCP port on 127.0.0.1 that accepts connections and closes them at once (a bus
    server's start-up check passes, its websocket handshake fails); its port."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)

    def serve() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        server.shutdown(socket.SHUT_RDWR)
        server.close()
        thread.join(timeout=5.0)
