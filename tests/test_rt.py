"""Real-time helpers: GC pause watch and the scheduling switch with its fallback."""

from __future__ import annotations

import gc
import os

from can_db.process.rt import GcWatch, make_realtime


def test_gc_watch_times_collections_by_generation() -> None:
    watch = GcWatch()
    try:
        gc.collect()
        gc.collect(0)
    finally:
        watch.close()
    summary = watch.summary()
    assert summary["collections"][2] >= 1 and summary["collections"][0] >= 1
    assert summary["max_pause_ms"][2] > 0.0
    gc.collect()
    assert watch.summary() == summary  # closed: no longer counting


def test_make_realtime_applies_or_explains() -> None:
    before, cpus = os.sched_getscheduler(0), os.sched_getaffinity(0)
    try:
        text = make_realtime("test", report=False)
        assert text.startswith(("SCHED_FIFO", "SCHED_OTHER (SCHED_FIFO not permitted"))
        assert os.sched_getaffinity(0) == cpus  # no pinning unless asked
        one = {max(cpus)}
        text = make_realtime("test", cpus=one, report=False)
        assert os.sched_getaffinity(0) == one and f"CPUs [{max(cpus)}]" in text
    finally:
        os.sched_setscheduler(0, before, os.sched_param(0))
        os.sched_setaffinity(0, cpus)
    assert os.sched_getscheduler(0) == before
