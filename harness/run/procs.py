"""Child processes of the harness: start, wait for their ready line, stop, never orphan.

Children are started with PR_SET_PDEATHSIG (they die if the harness dies) and are always
stopped SIGTERM-first (so they flush their logs), then SIGKILL after a grace period. They stay
in the harness's process group, so a terminal Ctrl-C reaches them too (they stop cleanly on
SIGINT); a child whose start is cut short by a signal is stopped before the signal goes on.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import psutil

from can_db.process.parent import die_with_parent
from harness.run.signals import check as check_signals
from harness.run.signals import shielded


def stop_descendants(grace_s: float = 1.0) -> int:
    """SIGTERM every descendant process of this one (pool and engine workers and the bus
    children they started), SIGKILL those left after ``grace_s``; returns how many there were.

    For a command stopped by a signal: its workers must not outlive it (nor take the time a
    graceful pool or cluster shutdown takes)."""
    procs = []
    for proc in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            # multiprocessing's resource tracker ends by itself with this process
            if not any("resource_tracker" in part for part in proc.cmdline()):
                procs.append(proc)
    for proc in procs:
        with contextlib.suppress(psutil.Error):
            proc.terminate()
    _, alive = psutil.wait_procs(procs, timeout=grace_s)
    for proc in alive:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    psutil.wait_procs(alive, timeout=grace_s)
    return len(procs)


POLL_EVERY_S = 0.02  # wall s between the calls of a waiter's poll function


class ChildStartError(RuntimeError):
    """A child process exited or stayed silent before printing its ready line."""


@dataclass
class Child:
    """One managed child process; its output is collected into ``lines`` (and a log file)."""

    name: str
    args: Sequence[str]
    log_path: Path | None = None
    stdin: bool = False  # a control channel: lines written with :meth:`send`
    proc: subprocess.Popen[str] | None = None
    lines: list[str] = field(default_factory=list)
    started_at: float = 0.0
    exited_at: float | None = None
    _reader: threading.Thread | None = None
    _line_added: threading.Condition = field(default_factory=threading.Condition)
    _log: TextIO | None = None
    _ready: threading.Event = field(default_factory=threading.Event)
    _ready_prefix: str = "ready"

    def start(self, ready_prefix: str = "ready", timeout_s: float = 30.0) -> Child:
        """Start and block until a stdout line starts with ``ready_prefix``."""
        return self.launch(ready_prefix).wait_ready(timeout_s)

    def launch(self, ready_prefix: str = "ready") -> Child:
        """Start the process without waiting (:meth:`wait_ready` waits): children that do not
        depend on each other import side by side."""
        self._log = open(self.log_path, "w", buffering=1) if self.log_path else None  # noqa: SIM115
        self.proc = subprocess.Popen([sys.executable, *self.args], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1,
                                     stdin=subprocess.PIPE if self.stdin else None,
                                     preexec_fn=die_with_parent)
        self.started_at = time.monotonic()
        ready = threading.Event()

        def pump() -> None:
            assert self.proc is not None and self.proc.stdout is not None
            for line in self.proc.stdout:
                with self._line_added:
                    self.lines.append(line.rstrip("\n"))
                    self._line_added.notify_all()
                if self._log is not None:
                    self._log.write(line)
                if line.startswith(ready_prefix):
                    ready.set()
            ready.set()
            with self._line_added:  # the end of the output: a waiter looks at the exit
                self._line_added.notify_all()

        self._reader = threading.Thread(target=pump, name=f"{self.name}-stdout", daemon=True)
        self._reader.start()
        self._ready, self._ready_prefix = ready, ready_prefix
        return self

    def wait_ready(self, timeout_s: float = 30.0) -> Child:
        """Block until the launched child prints its ready line, at most ``timeout_s`` wall s
        from its launch; ChildStartError (the child stopped) if it exits or stays silent."""
        ready, ready_prefix = self._ready, self._ready_prefix
        try:
            deadline = self.started_at + timeout_s
            while not ready.wait(0.05) and time.monotonic() < deadline:
                check_signals()
            check_signals()
        except BaseException:  # SIGINT/SIGTERM while it starts: not left behind
            with shielded():
                self.stop(grace_s=1.0)
            raise
        if not any(line.startswith(ready_prefix) for line in self.lines):
            self.stop()
            tail = "\n".join(self.lines[-10:])
            raise ChildStartError(f"{self.name} did not become ready:\n{tail}")
        return self

    def send(self, line: str) -> None:
        """Write one line to the child's control channel (its stdin); BrokenPipeError if it
        has gone."""
        if self.proc is None or self.proc.stdin is None:
            raise BrokenPipeError(f"{self.name} has no control channel")
        self.proc.stdin.write(line.rstrip("\n") + "\n")
        self.proc.stdin.flush()

    def wait_line(self, prefixes: tuple[str, ...], since: int, timeout_s: float,
                  poll: Callable[[], None] | None = None) -> str | None:
        """The first stdout line from index ``since`` on that starts with one of ``prefixes``;
        None if the child exits or ``timeout_s`` (wall s) passes first. Wakes on each new line
        (no polling of the pipe); ``poll`` is called about every 20 ms while waiting
        (signals, faults, progress)."""
        deadline = time.monotonic() + timeout_s
        seen = since
        while True:
            with self._line_added:
                for line in self.lines[seen:]:
                    if line.startswith(prefixes):
                        return line
                seen = len(self.lines)
                remaining = deadline - time.monotonic()
                if self.proc is None or self.proc.poll() is not None or remaining <= 0:
                    break
                self._line_added.wait(min(remaining, POLL_EVERY_S))
            if poll is not None:
                poll()
        if self.proc is not None and self.proc.poll() is not None:
            self.poll()
            if self._reader is not None:
                self._reader.join(timeout=1.0)  # the lines it wrote before it exited
        return next((ln for ln in self.lines[seen:] if ln.startswith(prefixes)), None)

    def poll(self) -> int | None:
        """Exit code if it has exited (and note when), else None."""
        if self.proc is None:
            return None
        code = self.proc.poll()
        if code is not None and self.exited_at is None:
            self.exited_at = time.monotonic()
        return code

    def stop(self, grace_s: float = 5.0) -> int | None:
        """SIGTERM, wait ``grace_s``, then SIGKILL; return the exit code."""
        if self.proc is None:
            return None
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()  # EOF on the control channel: a served child ends
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=min(grace_s, 2.0))
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=grace_s)
        self.poll()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
        if self._log is not None:
            self._log.close()
            self._log = None
        return self.proc.returncode

    def kill(self) -> None:
        """SIGKILL now (fault injection)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5.0)
            self.poll()
