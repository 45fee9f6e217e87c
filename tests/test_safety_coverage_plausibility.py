"""Frozen-signal detection: thresholds, speed gate, per-message state and the counts."""

from __future__ import annotations

import pytest

from controller.runtime.plausibility import CHECKED, FrozenSignalMonitor

MOTION = {"YAW_RATE": 0.1, "AX": 0.2, "AY": 0.3}


def feed(mon: FrozenSignalMonitor, n: int, values: dict[str, float] | None = None,
         speed: float = 20.0, message: str = "MOTION_SENSORS") -> list[bool]:
    """Feed ``n`` identical frames; the faulty flag after each."""
    flags = []
    for _ in range(n):
        mon.update(message, dict(values or MOTION), speed)
        flags.append(mon.faulty(message))
    return flags


def test_checked_signals_are_the_noisy_inertial_and_estimator_signals() -> None:
    assert CHECKED == {"MOTION_SENSORS": ("YAW_RATE", "AX", "AY"),
                       "VEHICLE_EST": ("VX_EST", "VY_EST")}
    mon = FrozenSignalMonitor()
    assert mon.frozen_frames == 10 and mon.min_speed_mps == 1.0


def test_a_signal_identical_on_frozen_frames_consecutive_frames_is_a_fault() -> None:
    mon = FrozenSignalMonitor()
    flags = feed(mon, 12)
    assert flags == [False] * 9 + [True] * 3   # the 10th identical frame is the fault
    assert mon.detections == 1 and mon.any_faulty()


def test_a_changing_value_clears_the_fault_and_a_new_freeze_is_a_new_detection() -> None:
    mon = FrozenSignalMonitor(frozen_frames=3)
    assert feed(mon, 3) == [False, False, True]
    mon.update("MOTION_SENSORS", {**MOTION, "AX": 0.25}, 20.0)
    assert mon.faulty("MOTION_SENSORS")         # YAW_RATE and AY are still frozen
    mon.update("MOTION_SENSORS", {"YAW_RATE": 0.5, "AX": 0.6, "AY": 0.7}, 20.0)
    assert not mon.faulty("MOTION_SENSORS") and not mon.any_faulty()
    assert feed(mon, 3, {"YAW_RATE": 0.5, "AX": 0.6, "AY": 0.7}) == [False, True, True]
    assert mon.detections == 2


def test_a_single_frozen_signal_among_changing_ones_is_a_fault() -> None:
    mon = FrozenSignalMonitor(frozen_frames=4)
    flags = []
    for k in range(5):
        mon.update("MOTION_SENSORS", {"YAW_RATE": 0.1, "AX": 0.01 * k, "AY": -0.01 * k}, 5.0)
        flags.append(mon.faulty("MOTION_SENSORS"))
    assert flags == [False, False, False, True, True]


@pytest.mark.parametrize(("speed", "faulty"), [(0.0, False), (0.99, False), (1.0, True),
                                               (-1.0, True), (-0.5, False), (30.0, True)])
def test_standstill_is_no_fault_only_speeds_from_min_speed_count(speed: float, faulty: bool
                                                                 ) -> None:
    mon = FrozenSignalMonitor(frozen_frames=2)
    assert feed(mon, 3, speed=speed)[-1] is faulty


def test_a_stop_resets_the_repeat_count() -> None:
    mon = FrozenSignalMonitor(frozen_frames=3)
    feed(mon, 2)                              # one repeat at speed
    feed(mon, 1, speed=0.0)                   # standstill: count back to 0
    assert feed(mon, 2) == [False, True]       # two more repeats at speed needed


def test_unchecked_messages_are_ignored() -> None:
    mon = FrozenSignalMonitor(frozen_frames=2)
    feed(mon, 5, {"W_FL": 1.0}, message="WHEEL_SPEEDS")
    assert not mon.faulty("WHEEL_SPEEDS") and not mon.any_faulty()
    assert mon.detections == 0


def test_missing_signals_are_skipped_without_resetting_the_others() -> None:
    mon = FrozenSignalMonitor(frozen_frames=3)
    assert feed(mon, 3, {"VX_EST": 20.0}, message="VEHICLE_EST") == [False, False, True]
    assert not mon.faulty("MOTION_SENSORS")   # per-message state
    assert mon.any_faulty()
    mon.update("VEHICLE_EST", {}, 20.0)       # nothing checked in this frame
    assert not mon.faulty("VEHICLE_EST")


def test_frozen_frames_of_one_flags_the_first_frame() -> None:
    mon = FrozenSignalMonitor(frozen_frames=1)
    assert feed(mon, 2) == [True, True]
    assert mon.detections == 1


def test_a_missing_signal_does_not_stop_the_check_of_the_following_ones() -> None:
    mon = FrozenSignalMonitor(frozen_frames=3)
    flags = feed(mon, 3, {"AX": 0.2, "AY": 0.3})   # no YAW_RATE in these frames
    assert flags == [False, False, True]
