"""Rx monitor: alive-counter tolerance, timeouts, per-reason counts."""

from __future__ import annotations

import can

from can_db.codec import Codec, Decoded, Rejected, Rejection
from can_db.monitor import RxMonitor

CODEC = Codec()


def frame(counter: int, cycle: int = 0) -> can.Message:
    return CODEC.message("SYNC", {"CYCLE": cycle}, counter)


def test_continuous_counter_is_valid_and_decoded() -> None:
    mon = RxMonitor(CODEC, ["SYNC"])
    for k in range(40):
        result = mon.process(frame(k % 16, k), now_s=k * 0.01)
        assert isinstance(result, Decoded) and result.values["CYCLE"] == k
        assert mon.valid("SYNC", k * 0.01)
    assert mon.rejection_counts() == {}


def torque(counter: int) -> can.Message:
    """A frame of the CRC8 profile (the controller's torque command)."""
    return CODEC.message("WHEEL_TORQUE_CMD", {"TQ_FL": 1.0}, counter)


def test_a_few_missed_frames_are_tolerated_then_fault_after_n() -> None:
    """CRC8 profile: any jump is accepted and counted until the fault level reaches N."""
    mon = RxMonitor(CODEC, ["WHEEL_TORQUE_CMD"], counter_fault_limit=5)
    mon.process(torque(0), 0.0)
    # One lost frame: accepted, counted as a jump, still valid.
    assert isinstance(mon.process(torque(2), 0.02), Decoded)
    assert mon.valid("WHEEL_TORQUE_CMD", 0.02) and mon.counts["counter_jump"] == 1
    # Keep jumping: the fault level climbs one per fault; the 5th fault invalidates.
    counter, results = 2, []
    for i in range(4):
        counter = (counter + 3) % 16
        results.append(mon.process(torque(counter), 0.03 + 0.01 * i))
    assert all(isinstance(r, Decoded) for r in results[:3])
    assert isinstance(results[3], Rejected) and results[3].reason is Rejection.COUNTER_FAULT
    assert not mon.valid("WHEEL_TORQUE_CMD", 0.07)
    # Recovery needs good frames to bring the level back under the limit.
    counter = (counter + 1) % 16
    assert isinstance(mon.process(torque(counter), 0.08), Decoded)
    assert mon.valid("WHEEL_TORQUE_CMD", 0.08)


def test_crc16_profile_counter_window_accepts_delta_1_to_3_only() -> None:
    """CRC16 profile (SYNC): delta 2 or 3 = one or two frames lost, accepted and counted;
    delta 4..15 is a
    wrong sequence, rejected; the next frame after it resynchronises on its counter."""
    mon = RxMonitor(CODEC, ["SYNC"], counter_fault_limit=5)
    assert isinstance(mon.process(frame(0, 0), 0.0), Decoded)
    assert isinstance(mon.process(frame(2, 2), 0.02), Decoded)  # one lost
    assert isinstance(mon.process(frame(5, 5), 0.05), Decoded)  # two lost
    assert mon.counts["counter_jump"] == 2
    for delta in range(4, 16):
        mon = RxMonitor(CODEC, ["SYNC"], counter_fault_limit=5)
        mon.process(frame(4, 4), 0.0)
        result = mon.process(frame((4 + delta) % 16, 9), 0.01)
        assert isinstance(result, Rejected) and result.reason is Rejection.WRONG_SEQUENCE, delta
        assert mon.latest("SYNC").values["CYCLE"] == 4  # the rejected frame gave no data
        # resynchronised: the frame after the rejected one (delta 1 from it) is accepted
        resync = mon.process(frame((5 + delta) % 16, 10), 0.02)
        assert isinstance(resync, Decoded) and resync.values["CYCLE"] == 10, delta
        assert mon.counts["wrong_sequence"] == 1 and mon.valid("SYNC", 0.02)


def test_crc16_profile_faults_still_raise_the_fault_level() -> None:
    """Five counter faults in a row invalidate a CRC16 message too (rejected as
    counter_fault), and good frames bring it back."""
    mon = RxMonitor(CODEC, ["SYNC"], counter_fault_limit=5)
    counter = 0
    mon.process(frame(counter), 0.0)
    reasons = []
    for i in range(5):
        counter = (counter + 2) % 16
        result = mon.process(frame(counter), 0.01 * (i + 1))
        reasons.append(result.reason if isinstance(result, Rejected) else None)
    assert reasons == [None, None, None, None, Rejection.COUNTER_FAULT]
    assert not mon.valid("SYNC", 0.05)
    counter = (counter + 1) % 16
    assert isinstance(mon.process(frame(counter), 0.06), Decoded)


def test_frozen_counter_rejects_the_stale_frame() -> None:
    mon = RxMonitor(CODEC, ["SYNC"])
    mon.process(frame(3, cycle=1), 0.0)
    result = mon.process(frame(3, cycle=2), 0.01)
    assert isinstance(result, Rejected) and result.reason is Rejection.COUNTER_FROZEN
    assert mon.latest("SYNC").values["CYCLE"] == 1  # the stale copy did not replace data


def test_timeout_after_three_cycles_counted_once_and_recovers() -> None:
    mon = RxMonitor(CODEC, ["SYNC"])  # 10 ms cycle -> 30 ms timeout
    assert not mon.valid("SYNC", 0.0)  # never received
    mon.process(frame(0), 1.000)
    assert mon.valid("SYNC", 1.030)
    assert not mon.valid("SYNC", 1.0301)
    assert not mon.valid("SYNC", 1.5)
    assert mon.counts["timeout"] == 1 and mon.streams["SYNC"].rejections == {"timeout": 1}
    mon.process(frame(1), 1.6)
    assert mon.valid("SYNC", 1.6)


def test_rejections_are_counted_by_reason() -> None:
    mon = RxMonitor(CODEC, ["SYNC"])
    good = frame(0)
    bad = bytearray(good.data)
    bad[3] ^= 0x10
    mon.process(can.Message(arbitration_id=good.arbitration_id, data=bad,
                            is_extended_id=False), 0.0)
    mon.process(can.Message(arbitration_id=0x7AB, data=bytes(8), is_extended_id=False), 0.0)
    mon.process(can.Message(arbitration_id=good.arbitration_id, data=bytes(3),
                            is_extended_id=False), 0.0)
    assert mon.rejection_counts() == {"bad_crc": 1, "unknown_id": 1, "wrong_length": 1}
    # A well-formed frame of a message this node does not monitor is ignored, not rejected.
    assert mon.process(CODEC.message("CTRL_REFS", {}, 0), 0.0) is None and mon.ignored == 1


def test_counter_faults_past_the_limit_keep_the_message_invalid() -> None:
    """At the limit every further fault is a counter_fault rejection and the message stays
    invalid; good frames bring the level back one per frame."""
    mon = RxMonitor(CODEC, ["WHEEL_TORQUE_CMD"], counter_fault_limit=5)
    counter = 0
    mon.process(torque(counter), 0.0)
    reasons = []
    for i in range(9):
        counter = (counter + 2) % 16
        result = mon.process(torque(counter), 0.01 * (i + 1))
        reasons.append(result.reason if isinstance(result, Rejected) else None)
        assert mon.valid("WHEEL_TORQUE_CMD", 0.01 * (i + 1)) == (i < 4), i
    assert reasons == [None] * 4 + [Rejection.COUNTER_FAULT] * 5
    assert mon.streams["WHEEL_TORQUE_CMD"].counter_fault_level == 5
    assert mon.counts["counter_fault"] == 5


def test_a_timeout_is_counted_again_after_the_stream_came_back() -> None:
    """Each loss of the stream is one timeout: the report re-arms when a frame is accepted."""
    mon = RxMonitor(CODEC, ["SYNC"])
    for k, t in enumerate((1.0, 1.5, 2.0)):
        mon.process(frame(k), t)
        assert mon.valid("SYNC", t)
        assert not mon.valid("SYNC", t + 0.1) and not mon.valid("SYNC", t + 0.2)
        assert mon.counts["timeout"] == k + 1


def test_the_transmitter_s_alive_counter_wraps_at_16() -> None:
    """0, 1, …, 15, 0, …: 40 frames of one message carry k mod 16 and a monitor accepts every
    one of them (a wrap at 15 would repeat or skip a value)."""
    from can_db.codec import Transmitter

    tx, mon = Transmitter(CODEC), RxMonitor(CODEC, ["SYNC"])
    for k in range(40):
        result = mon.process(tx.message("SYNC", {"CYCLE": k}), k * 0.01)
        assert isinstance(result, Decoded) and result.counter == k % 16, k
    assert mon.rejection_counts() == {}
