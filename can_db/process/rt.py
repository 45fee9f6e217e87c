"""Real-time helpers for our bus processes: scheduling class, garbage collector, pacing.

* :func:`make_realtime` asks for ``SCHED_FIFO`` (and optionally a CPU set) and falls back to
  the normal scheduler with a one-line reason where that is not permitted (no root, no
  ``CAP_SYS_NICE``, macOS). The kernel's RT throttling (95 % by default) still bounds what a
  runaway FIFO task could take.
* :func:`freeze_heap` runs a full collection and moves every object alive after set-up into
  the permanent generation (``gc.freeze``): later gen-2 collections then scan only what the
  loop itself allocated (measured in the controller: 14–18 ms → well under 1 ms).
* :func:`sleep_until` sleeps to shortly before a deadline, then spins the last stretch, so
  wake-up latency of the OS timer does not become period jitter.
"""

from __future__ import annotations

import gc
import os
import sys
import time

FIFO_PRIORITY = 40  # above normal tasks, below the kernel's own threaded IRQs (50)
SPIN_S = 0.0003  # spin this long before a deadline, s


def make_realtime(role: str, priority: int = FIFO_PRIORITY, cpus: set[int] | None = None,
                  report: bool = True) -> str:
    """Switch this process to SCHED_FIFO at ``priority`` (and pin it to ``cpus`` if given).

    ``$RHONN_RT_CPUS`` (comma-separated CPU numbers, or ``all``) overrides ``cpus``. Pinning
    is a trade-off measured on the 2-core VM: every real-time process of a run on one CPU
    makes the lockstep hand-offs plain context switches (dlc-paper 27.3× vs 17.5–18.5× real
    time, alternating runs) but costs the real-time soak its period jitter (p99 583–1172 µs
    pinned vs 215 µs unpinned, 2-minute runs), so it is not the default. Returns what was
    applied, e.g. ``"SCHED_FIFO 40, CPUs [1]"`` or ``"SCHED_OTHER (…not permitted)"``; with
    ``report`` it is also printed to stderr as ``ROLE: realtime: …``. Called from a thread
    other than the main one, it applies to that thread only (Linux).
    """
    applied = []
    env_cpus = os.environ.get("RHONN_RT_CPUS")
    if env_cpus == "all":
        cpus = None
    elif env_cpus:
        cpus = {int(c) for c in env_cpus.split(",") if c.strip()}
    if cpus and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, cpus)
            applied.append(f"CPUs {sorted(cpus)}")
        except OSError as exc:
            applied.append(f"affinity not set ({exc.strerror})")
    if hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_FIFO"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            applied.insert(0, f"SCHED_FIFO {priority}")
        except OSError as exc:
            applied.insert(0, f"SCHED_OTHER (SCHED_FIFO not permitted: {exc.strerror})")
    else:
        applied.insert(0, "SCHED_OTHER (no SCHED_FIFO on this platform)")
    text = ", ".join(applied)
    if report:
        print(f"{role}: realtime: {text}", file=sys.stderr, flush=True)
    return text


def freeze_heap() -> None:
    """Collect once, then exempt everything alive now from future collections."""
    gc.collect()
    gc.freeze()


def sleep_until(deadline_s: float, clock=time.monotonic, spin_s: float = SPIN_S) -> None:
    """Return at ``deadline_s`` (on ``clock``, s): OS sleep until ``spin_s`` before it, then
    spin."""
    remaining = deadline_s - clock()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while clock() < deadline_s:
        pass


class GcWatch:
    """Times every garbage collection of this process (``gc.callbacks``): count and
    longest pause per generation, ms. ``summary()`` for the process's JSON summary."""

    def __init__(self, clock=time.perf_counter) -> None:
        self._clock = clock
        self._start = 0.0
        self.count = [0, 0, 0]
        self.max_ms = [0.0, 0.0, 0.0]
        gc.callbacks.append(self._callback)

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._start = self._clock()
            return
        gen = int(info.get("generation", 0))
        pause_ms = (self._clock() - self._start) * 1000.0
        self.count[gen] += 1
        if pause_ms > self.max_ms[gen]:
            self.max_ms[gen] = pause_ms

    def summary(self) -> dict[str, list[float] | list[int]]:
        """Collections per generation and the longest pause of each, ms."""
        return {"collections": list(self.count),
                "max_pause_ms": [round(m, 3) for m in self.max_ms]}

    def close(self) -> None:
        """Stop timing."""
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)
