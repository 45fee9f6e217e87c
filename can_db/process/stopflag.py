"""Clean shutdown for our processes: SIGINT/SIGTERM set a flag the main loop polls.

Loops stop at their next iteration, so every log is flushed and every summary written
(nothing is lost); a second signal is not needed and does not interrupt that.
"""

from __future__ import annotations

import signal


class StopFlag:
    """Callable flag: ``stop()`` is True once SIGINT or SIGTERM arrived."""

    def __init__(self) -> None:
        self.stopped = False
        signal.signal(signal.SIGINT, self._set)
        signal.signal(signal.SIGTERM, self._set)

    def _set(self, *_: object) -> None:
        self.stopped = True

    def __call__(self) -> bool:
        return self.stopped
