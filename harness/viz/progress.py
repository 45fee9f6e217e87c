"""Progress bars for the long commands (paper, soak, fuzz), through tqdm.

On a terminal a tqdm bar is drawn on stderr; when stderr is not a terminal (CI logs, a pipe)
each update is one plain line instead, so logs stay readable. Nothing here touches stdout,
which keeps the commands' results.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, TextIO

from tqdm import tqdm


def _is_tty(stream: TextIO) -> bool:
    return bool(getattr(stream, "isatty", lambda: False)())


class Bar:
    """A counter with a total that may grow (the paper's bisection adds runs as it goes).

    ``unit``: what is counted ("run", "target", "sim s").
    """

    def __init__(self, desc: str, total: float | None = None, unit: str = "it",
                 stream: TextIO | None = None, line_every_s: float = 0.0) -> None:
        """``line_every_s``: off a terminal, at most one line per this many wall seconds
        (the last update always prints)."""
        self.stream = stream or sys.stderr
        self.line_every_s = line_every_s
        self._last_line = -math.inf
        self._done_shown = False
        self.tty = _is_tty(self.stream)
        self.desc, self.unit = desc, unit
        self.n, self.total = 0.0, total
        self._bar: Any = (tqdm(total=total, desc=desc, unit=unit, file=self.stream,
                               dynamic_ncols=True, leave=True) if self.tty else None)

    def set(self, n: float, total: float | None = None, note: str = "") -> None:
        """Move to ``n`` done of ``total`` (unchanged if None); ``note`` after the bar."""
        if total is not None:
            self.total = total
        step = n - self.n
        self.n = n
        if self._bar is not None:
            if total is not None:
                self._bar.total = total
            if note:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(step)
        else:
            now = time.monotonic()
            done = self.total is not None and n >= self.total
            if (now - self._last_line < self.line_every_s and not done) or \
                    (done and self._done_shown):
                return
            self._done_shown = done
            self._last_line = now
            of = f"/{self.total:g}" if self.total is not None else ""
            self.stream.write(f"{self.desc}: {n:g}{of} {self.unit}  {note}\n")
            self.stream.flush()

    def write(self, line: str) -> None:
        """A line of output above the bar (stdout)."""
        if self._bar is not None:
            self._bar.write(line, file=sys.stdout)
        else:
            print(line, flush=True)

    def close(self) -> None:
        """End the bar."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
