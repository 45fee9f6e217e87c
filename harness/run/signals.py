"""Stop signals of the harness commands: SIGINT and SIGTERM both take the KeyboardInterrupt path.

:func:`install` is called by the ``main`` of ``rhonn-harness`` and of ``rhonn-bench soak``. It
sets the handler explicitly because a harness started in the background by a non-interactive
shell (``rhonn-harness run ... &``) inherits SIGINT as *ignored*, and Python then leaves it
ignored: ``kill -INT PID`` would do nothing. SIGTERM would otherwise end the process at once,
with no cleanup.

The handler raises :class:`Interrupted` (a ``KeyboardInterrupt``) in the main thread, so every
``except KeyboardInterrupt`` / ``finally`` in the code also runs on SIGTERM. Cleanup code runs
inside :func:`shielded`: a signal arriving there is recorded, not raised, so stopping the
children and closing the logs is never cut short. :func:`exit_code` gives the conventional
128 + signal number (130 for SIGINT, 143 for SIGTERM). :func:`arm_deadline` bounds the work
done after a signal (the analysis of a partial run): at the deadline :class:`DeadlineReached`
is raised the same way.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import NoReturn

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_received: list[tuple[int, float]] = []  # (signal number, monotonic s) in arrival order
_shield_depth = [0]
_owner = [0]  # the pid that installed the handler


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class DeadlineReached(KeyboardInterrupt):
    """The time given by :func:`arm_deadline` is spent."""


def _alarm(_signum: int, _frame: FrameType | None) -> None:
    if _shield_depth[0] == 0:
        raise DeadlineReached("deadline")


def arm_deadline(at_s: float) -> bool:
    """Raise :class:`DeadlineReached` in the main thread at monotonic time ``at_s`` (SIGALRM).

    Returns False (nothing armed) outside the main thread; :func:`disarm_deadline` cancels."""
    if threading.current_thread() is not threading.main_thread():
        return False
    signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, max(1e-3, at_s - time.monotonic()))
    return True


def disarm_deadline() -> None:
    """Cancel an armed deadline (no-op if none)."""
    if threading.current_thread() is threading.main_thread():
        signal.setitimer(signal.ITIMER_REAL, 0.0)


def _handler(signum: int, _frame: FrameType | None) -> None:
    if os.getpid() != _owner[0]:
        # a forked pool worker inherited the handler: it ends as an unhandled signal would
        signal.signal(signum, signal.SIG_DFL)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        os.kill(os.getpid(), signum)
        return
    _received.append((signum, time.monotonic()))
    if _shield_depth[0] == 0:
        raise Interrupted(signum)


def install() -> None:
    """SIGINT and SIGTERM raise :class:`Interrupted` in the main thread (no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        return
    _owner[0] = os.getpid()
    for sig in STOP_SIGNALS:
        signal.signal(sig, _handler)


def received() -> int | None:
    """The first stop signal that arrived in this process, or None."""
    return _received[0][0] if _received else None


def received_at() -> float | None:
    """Monotonic time (s) of the first stop signal, or None."""
    return _received[0][1] if _received else None


def check() -> None:
    """Raise :class:`Interrupted` if a stop signal has arrived (outside :func:`shielded`).

    Loops call this: the handler's own exception can be swallowed where Python only prints
    exceptions (an at-fork hook of ``subprocess``, a ``__del__``), and the signal must not be
    lost there."""
    if _received and _shield_depth[0] == 0:
        raise Interrupted(_received[0][0])


def exit_code(signum: int | None = None) -> int:
    """128 + the signal number (``signum``, else the first received; SIGINT if none)."""
    if signum is None:
        signum = received() or signal.SIGINT
    return 128 + int(signum)


def leave(code: int) -> NoReturn:
    """End the process now with ``code`` (stdout and stderr flushed), skipping exit hooks.

    For commands whose pools were stopped after a signal: the exit hooks of the pool
    libraries would otherwise wait many seconds for workers that are already gone. Every
    file of the command is written and closed before this is called."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def reset() -> None:
    """Forget received signals (tests, and commands that run several studies in a row)."""
    _received.clear()


@contextmanager
def shielded() -> Iterator[None]:
    """Inside: stop signals are recorded (see :func:`received`) but not raised."""
    _shield_depth[0] += 1
    try:
        yield
    finally:
        _shield_depth[0] -= 1
