"""The loopback bus server: python-can-remote serving a python-can ``virtual`` channel.

Used where the kernel has no SocketCAN (macOS, Windows, containers, our CI). It binds to
127.0.0.1 only. ``BusServer`` runs it as a managed child process: start, wait until it
accepts connections, stop; the child dies with its parent (PR_SET_PDEATHSIG on Linux), so a
crashed harness leaves no orphan server behind.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from types import TracebackType

from can_db.process.parent import die_with_parent

LOOPBACK = "127.0.0.1"


def free_port() -> int:
    """An unused TCP port on the loopback interface (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((LOOPBACK, 0))
        return int(sock.getsockname()[1])


START_TIMEOUT_S = 10.0  # default wait for a started server to listen, wall s


class BusServerError(RuntimeError):
    """The loopback bus server could not be started."""


class BusServer:
    """A python-can-remote server on 127.0.0.1:``port`` as a child process.
    ``start_timeout_s``: how long :meth:`start` (and :meth:`restart`) wait for it to accept
    connections, wall s."""

    def __init__(self, port: int | None = None, *, channel: str = "rhonn",
                 start_timeout_s: float = START_TIMEOUT_S) -> None:
        self.port = port if port is not None else free_port()
        self.channel = channel
        self.start_timeout_s = start_timeout_s
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """Client channel URL, e.g. ws://127.0.0.1:54321/."""
        return f"ws://{LOOPBACK}:{self.port}/"

    @property
    def spec(self) -> str:
        """Bus spec string for :func:`can_db.transport.bus.open_bus`."""
        return f"remote:{self.url}"

    def start(self, timeout_s: float | None = None) -> BusServer:
        """Start the server and wait until it accepts TCP connections (``timeout_s`` None:
        the server's ``start_timeout_s``)."""
        timeout_s = self.start_timeout_s if timeout_s is None else timeout_s
        cmd = [sys.executable, "-m", "can_remote", "-i", "virtual", "-c", self.channel,
               "-H", LOOPBACK, "-p", str(self.port), "-v"]
        # -v lowers the server's log level from DEBUG to ERROR-ish noise; stdout is discarded.
        self.process = subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL,
                                        preexec_fn=die_with_parent)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise BusServerError(
                    f"bus server exited with code {self.process.returncode} "
                    f"(port {self.port} in use?)")
            with contextlib.suppress(OSError), socket.create_connection(
                    (LOOPBACK, self.port), timeout=0.2):
                return self
            time.sleep(0.02)
        self.stop()
        raise BusServerError(f"bus server did not listen on {LOOPBACK}:{self.port} "
                             f"within {timeout_s} s")

    def restart(self) -> BusServer:
        """Stop the server and start a new one on the same port (clients reconnect)."""
        self.stop()
        return self.start()

    def alive(self) -> bool:
        """True while the server process runs."""
        return self.process is not None and self.process.poll() is None

    def stop(self, timeout_s: float = 3.0) -> None:
        """Terminate the server (SIGTERM, then SIGKILL) and reap it."""
        proc, self.process = self.process, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=timeout_s)

    def __enter__(self) -> BusServer:
        return self.start() if self.process is None else self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def vcan_available(name: str = "vcan0") -> bool:
    """True when a SocketCAN interface ``name`` exists and is up on this machine."""
    path = f"/sys/class/net/{name}/operstate"
    if not os.path.exists(path):
        return False
    with open(path) as fh:
        state = fh.read().strip()
    return state in {"up", "unknown"}
