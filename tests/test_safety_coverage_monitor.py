"""Rx monitor (can_db/monitor.py) at the edges its mutation run found unchecked: the per-stream
frame counts, the fault level's exact climb and recovery, the default limit, the timeout's
boundary, ``all_valid`` over several streams, and keyword-only options."""

from __future__ import annotations

import can
import pytest

from can_db.codec import Codec, Decoded, Rejected, Rejection
from can_db.monitor import RxMonitor

CODEC = Codec()


def torque(counter: int) -> can.Message:
    """A frame of the CRC8 profile (any counter jump accepted below the fault limit)."""
    return CODEC.message("WHEEL_TORQUE_CMD", {"TQ_FL": 1.0}, counter)


def sync(counter: int) -> can.Message:
    return CODEC.message("SYNC", {"CYCLE": counter}, counter)


def test_received_and_accepted_count_each_frame_once() -> None:
    mon = RxMonitor(CODEC, ["WHEEL_TORQUE_CMD"])
    stream = mon.streams["WHEEL_TORQUE_CMD"]
    assert (stream.received, stream.accepted) == (0, 0)
    for k, c in enumerate((0, 1, 2, 2, 3)):          # the repeated 2 is stale: rejected
        mon.process(torque(c), 0.01 * k)
    assert (stream.received, stream.accepted) == (5, 4)


def test_the_fault_level_climbs_and_recovers_one_per_frame() -> None:
    """The default limit is 5 faults; each frame with delta 1 lowers the level by exactly one
    down to 0, never below."""
    mon = RxMonitor(CODEC, ["WHEEL_TORQUE_CMD"])
    stream = mon.streams["WHEEL_TORQUE_CMD"]
    mon.process(torque(0), 0.0)
    counter, verdicts = 0, []
    for k in range(5):
        counter = (counter + 2) % 16
        verdicts.append(mon.process(torque(counter), 0.01 * (k + 1)))
    assert all(isinstance(v, Decoded) for v in verdicts[:4])           # four faults: accepted
    assert isinstance(verdicts[4], Rejected) and verdicts[4].reason is Rejection.COUNTER_FAULT
    assert stream.counter_fault_level == 5
    levels = []
    for k in range(7):
        counter = (counter + 1) % 16
        mon.process(torque(counter), 0.1 + 0.01 * k)
        levels.append(stream.counter_fault_level)
    assert levels == [4, 3, 2, 1, 0, 0, 0]
    # from level 0, four faults in a row are still tolerated: the level did not go below 0
    for k in range(4):
        counter = (counter + 2) % 16
        assert isinstance(mon.process(torque(counter), 0.2 + 0.01 * k), Decoded)
    assert stream.counter_fault_level == 4


def test_a_frame_exactly_one_timeout_old_is_still_valid() -> None:
    mon = RxMonitor(CODEC, ["SYNC"], timeouts_s={"SYNC": 0.03})
    mon.process(sync(0), 0.0)   # at 0 s: the age at `now` is `now` exactly
    assert mon.valid("SYNC", 0.03 + 1e-9)       # the bound itself (timeout + rounding margin)
    assert not mon.valid("SYNC", 0.031)
    assert mon.counts["timeout"] == 1


def test_all_valid_needs_every_stream_and_counts_every_timeout() -> None:
    names = ["SYNC", "WHEEL_TORQUE_CMD"]
    mon = RxMonitor(CODEC, names, timeouts_s={"SYNC": 0.03, "WHEEL_TORQUE_CMD": 0.03})
    mon.process(sync(0), 0.0)
    mon.process(torque(0), 0.0)
    assert mon.all_valid(names, 0.01)
    mon.process(torque(1), 0.02)                     # SYNC goes stale, the torque stays fresh
    assert not mon.all_valid(names, 0.045)
    assert not mon.all_valid(list(reversed(names)), 0.045)
    assert mon.all_valid([], 0.045)
    assert not mon.all_valid(names, 0.1)             # both stale now: each timeout counted
    assert mon.counts["timeout"] == 2


def test_the_monitors_options_are_keyword_only() -> None:
    with pytest.raises(TypeError):
        RxMonitor(CODEC, ["SYNC"], 3.0)  # type: ignore[misc]
