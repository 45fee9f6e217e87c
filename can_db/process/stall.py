"""A stall ring buffer for the real-time loops: what a process was doing in a slow cycle.

A loop opens a cycle (``begin``), marks its phases (``mark``) and closes it (``end``). A
``getrusage`` and a thread CPU-time read at ``begin`` and at ``end`` (≈ 2 µs a cycle) give
the deltas that tell the usual causes of a stall apart, for the cycle's work and for the
wait before it (from the previous ``end``): the thread's CPU time against the wall time
(wall ≫ CPU with no involuntary switch: the thread was runnable or sleeping but did not run
— a late wake-up, or the virtual CPU itself was not running), involuntary context switches
(preempted by another task), page faults (minor: first touch of memory; major: read from
disk), garbage collections inside the cycle, and the wall time of each phase. Any cycle
longer than ``threshold_ms`` lands in a ring of the last ``capacity`` stalls (the counters
count all of them); ``summary()`` goes into the process's summary JSON.
``$RHONN_STALL_MS`` overrides the default threshold (e.g. 1 to see the ordinary slow cycles).
"""

from __future__ import annotations

import gc
import os
import resource
import time
from collections import deque
from typing import Any

STALL_MS = 5.0  # a cycle longer than this is a stall, ms
RING = 32  # stalls kept (the newest)


class StallWatch:
    """Per-cycle phase marks and resource deltas; keeps the cycles that were stalls."""

    def __init__(self, threshold_ms: float | None = None, capacity: int = RING,
                 clock=time.perf_counter_ns) -> None:
        if threshold_ms is None:
            threshold_ms = float(os.environ.get("RHONN_STALL_MS") or STALL_MS)
        self.threshold_ns = int(threshold_ms * 1e6)
        self.ring: deque[dict[str, Any]] = deque(maxlen=capacity)
        self.stalls = 0
        self.worst_ms = 0.0
        self._clock = clock
        self._marks: list[tuple[str, int]] = []
        self._start = 0
        self._ru_end = self._ru_begin = resource.getrusage(resource.RUSAGE_THREAD)
        self._cpu_end = self._cpu_begin = time.thread_time_ns()
        self._end_ns = clock()
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
        self._ru_begin = resource.getrusage(resource.RUSAGE_THREAD)
        self._cpu_begin = time.thread_time_ns()
        self._start = self._clock() if start_ns is None else start_ns
        self._marks.clear()
        self._gc_at_begin = (self.gc_runs, self.gc_ns)

    def mark(self, phase: str) -> None:
        """``phase`` ended now."""
        self._marks.append((phase, self._clock()))

    def end(self, cycle: int, **context: Any) -> None:
        """Close the cycle (its last mark is its end); keep it if it was a stall.
        ``context``: extra fields for a stall's record (e.g. the step time)."""
        ru, cpu = resource.getrusage(resource.RUSAGE_THREAD), time.thread_time_ns()
        ru_prev, cpu_prev, end_prev = self._ru_end, self._cpu_end, self._end_ns
        end = self._marks[-1][1] if self._marks else self._clock()
        self._ru_end, self._cpu_end, self._end_ns = ru, cpu, end
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
            "work": _deltas(self._ru_begin, ru, cpu - self._cpu_begin),
            "wait_before": dict(wall_ms=round((self._start - end_prev) / 1e6, 3),
                                **_deltas(ru_prev, self._ru_begin,
                                          self._cpu_begin - cpu_prev)),
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


def _deltas(a: resource.struct_rusage, b: resource.struct_rusage, cpu_ns: int
            ) -> dict[str, float | int]:
    """What the thread did between two ``getrusage`` readings."""
    return {"cpu_ms": round(cpu_ns / 1e6, 3),
            "involuntary_switches": b.ru_nivcsw - a.ru_nivcsw,
            "voluntary_switches": b.ru_nvcsw - a.ru_nvcsw,
            "minor_faults": b.ru_minflt - a.ru_minflt,
            "major_faults": b.ru_majflt - a.ru_majflt}
