"""A stall ring buffer for the real-time loops: what a process was doing in a slow cycle.

A loop marks the phases of each cycle (``mark``) and closes it (``end``). One
``getrusage`` per cycle (≈ 1 µs) gives the deltas that tell the usual causes of a stall
apart: involuntary context switches (preempted: by another task, by the kernel, by the
real-time throttle), page faults (minor: first touch of memory; major: read from disk),
garbage collections that ran inside the cycle, and the wall time of each phase. Any cycle
longer than ``threshold_ms`` lands in a ring of the last ``capacity`` stalls (the counters
count all of them); ``summary()`` goes into the process's summary JSON.
"""

from __future__ import annotations

import gc
import resource
import time
from collections import deque
from typing import Any

STALL_MS = 5.0  # a cycle longer than this is a stall, ms
RING = 32  # stalls kept (the newest)


class StallWatch:
    """Per-cycle phase marks and resource deltas; keeps the cycles that were stalls."""

    def __init__(self, threshold_ms: float = STALL_MS, capacity: int = RING,
                 clock=time.perf_counter_ns) -> None:
        self.threshold_ns = int(threshold_ms * 1e6)
        self.ring: deque[dict[str, Any]] = deque(maxlen=capacity)
        self.stalls = 0
        self.worst_ms = 0.0
        self._clock = clock
        self._marks: list[tuple[str, int]] = []
        self._start = 0
        self._ru = resource.getrusage(resource.RUSAGE_SELF)
        self.gc_runs = 0  # collections so far (any generation), and their time, ns
        self.gc_ns = 0
        self._gc_t0 = 0
        self._gc_at_begin = (0, 0)
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, _info: dict) -> None:
        if phase == "start":
            self._gc_t0 = self._clock()
        else:
            self.gc_runs += 1
            self.gc_ns += self._clock() - self._gc_t0

    def begin(self, start_ns: int | None = None) -> None:
        """Start a cycle at ``start_ns`` (the loop's clock, ns; default now)."""
        self._start = self._clock() if start_ns is None else start_ns
        self._marks.clear()
        self._gc_at_begin = (self.gc_runs, self.gc_ns)

    def mark(self, phase: str) -> None:
        """``phase`` ended now."""
        self._marks.append((phase, self._clock()))

    def end(self, cycle: int, **context: Any) -> None:
        """Close the cycle (its last mark is its end); keep it if it was a stall.
        ``context``: extra fields for a stall's record (e.g. the step time)."""
        ru = resource.getrusage(resource.RUSAGE_SELF)
        prev, self._ru = self._ru, ru
        end = self._marks[-1][1] if self._marks else self._clock()
        total = end - self._start
        if total <= self.threshold_ns:
            return
        self.stalls += 1
        self.worst_ms = max(self.worst_ms, total / 1e6)
        phases, last = {}, self._start
        for name, t in self._marks:
            phases[name] = round((t - last) / 1e3, 1)
            last = t
        self.ring.append({
            "cycle": cycle, "wall_ms": round(total / 1e6, 3), "phases_us": phases,
            # since the previous cycle ended: a stall shows up in these
            "involuntary_switches": ru.ru_nivcsw - prev.ru_nivcsw,
            "voluntary_switches": ru.ru_nvcsw - prev.ru_nvcsw,
            "minor_faults": ru.ru_minflt - prev.ru_minflt,
            "major_faults": ru.ru_majflt - prev.ru_majflt,
            # inside the cycle (from begin)
            "gc_runs": self.gc_runs - self._gc_at_begin[0],
            "gc_ms": round((self.gc_ns - self._gc_at_begin[1]) / 1e6, 3),
            **context})

    def close(self) -> None:
        """Stop watching the garbage collector."""
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)

    def summary(self) -> dict[str, Any]:
        """Stall count, the longest (ms) and the ring of the newest stalls."""
        return {"threshold_ms": self.threshold_ns / 1e6, "stalls": self.stalls,
                "worst_ms": round(self.worst_ms, 3), "recent": list(self.ring)}
