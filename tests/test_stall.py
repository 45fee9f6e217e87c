"""The stall ring buffer of the real-time loops (can_db/process/stall.py), on a fake clock."""

from __future__ import annotations

import gc

from can_db.process.stall import StallWatch


class FakeClock:
    """A clock that moves only when told, ns."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def test_only_cycles_over_the_threshold_are_kept_with_their_phases() -> None:
    clock = FakeClock()
    watch = StallWatch(threshold_ms=5.0, capacity=2, clock=clock)
    try:
        for cycle, (node_us, send_us) in enumerate([(100, 20), (7000, 30), (50, 6000),
                                                    (10, 10), (9000, 0)]):
            watch.begin()
            clock.now += node_us * 1000
            if cycle == 1:
                gc.collect()  # a collection inside a stalled cycle is named in its record
            watch.mark("node")
            clock.now += send_us * 1000
            watch.mark("send")
            watch.end(cycle, step_us=1.0)
    finally:
        watch.close()
    summary = watch.summary()
    assert summary["stalls"] == 3 and summary["worst_ms"] == 9.0
    assert [r["cycle"] for r in summary["recent"]] == [2, 4]  # the ring keeps the newest
    rec = summary["recent"][0]
    assert rec["phases_us"] == {"node": 50.0, "send": 6000.0} and rec["wall_ms"] == 6.05
    assert rec["step_us"] == 1.0 and rec["gc_runs"] == 0
    for window in ("work", "wait_before"):
        for key in ("cpu_ms", "involuntary_switches", "voluntary_switches", "minor_faults",
                    "major_faults"):
            assert rec[window][key] >= 0
    # cycle 2 began where cycle 1 ended (7.03 ms on the fake clock): no wait before it
    assert rec["wait_before"]["wall_ms"] == 0.0


def test_a_collection_inside_a_stall_is_counted() -> None:
    clock = FakeClock()
    watch = StallWatch(threshold_ms=1.0, clock=clock)
    try:
        watch.begin()
        gc.collect()
        sum(i * i for i in range(200_000))  # some CPU work in the stalled cycle
        clock.now += 2_000_000
        watch.mark("work")
        watch.end(7)
    finally:
        watch.close()
    rec = watch.summary()["recent"][0]
    assert rec["gc_runs"] >= 1 and rec["work"]["cpu_ms"] > 0.0
    assert watch._on_gc not in gc.callbacks  # closed

