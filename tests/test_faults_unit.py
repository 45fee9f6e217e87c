"""Fault spec parsing and the sender-side injector (in process)."""

from __future__ import annotations

import numpy as np
import pytest

from can_db.codec import Codec, Decoded, Rejected, Rejection, Transmitter
from can_db.faults import FaultInjector, FaultSpecError, parse_fault

CODEC = Codec()


def burst(tx: Transmitter, k: int) -> list:
    return [tx.message("MOTION_SENSORS", {"YAW_RATE": 0.1 * k, "AY": 1.0}),
            tx.message("SYNC", {"CYCLE": k, "SIM_TIME": 0.01 * k})]


def test_parse_grammar() -> None:
    f = parse_fault("loss:10%")
    assert (f.kind, f.amount, f.target, f.at_s) == ("loss", 0.1, None, 0.0)
    f = parse_fault("burst:200ms@3s")
    assert (f.kind, f.amount, f.at_s) == ("burst", 0.2, 3.0)
    f = parse_fault("crc:100%,MOTION_SENSORS@250ms")
    assert (f.amount, f.target, f.at_s) == (1.0, "MOTION_SENSORS", 0.25)
    assert parse_fault("kill-controller@4s").at_s == 4.0
    assert parse_fault("flood").amount == 5000.0
    for bad in ("nope", "loss:10", "loss:150%", "burst", "stuck", "kill-controller:3",
                "burst:fast@1s"):
        with pytest.raises(FaultSpecError):
            parse_fault(bad)


def test_unknown_names_and_unencodable_out_of_range_are_refused() -> None:
    with pytest.raises(FaultSpecError, match="unknown signal"):
        FaultInjector(CODEC, [parse_fault("stuck:NOPE")])
    with pytest.raises(FaultSpecError, match="unknown message"):
        FaultInjector(CODEC, [parse_fault("loss:5%,NOPE")])
    with pytest.raises(FaultSpecError, match="fills its raw range"):
        FaultInjector(CODEC, [parse_fault("out-of-range:YAW_RATE")])


def test_loss_rate_matches_and_is_seeded() -> None:
    tx = Transmitter(CODEC)
    frames = [f for k in range(5000) for f in burst(tx, k)]
    kept = [len(FaultInjector(CODEC, [parse_fault("loss:10%")], seed=s).apply(frames, 1.0))
            for s in (1, 1, 2)]
    assert kept[0] == kept[1] != kept[2]
    assert abs(1 - kept[0] / len(frames) - 0.10) < 0.01


def test_burst_drops_exactly_its_window() -> None:
    tx, inj = Transmitter(CODEC), FaultInjector(CODEC, [parse_fault("burst:200ms@1s")])
    sent = [len(inj.apply(burst(tx, k), 0.01 * k)) for k in range(300)]
    assert sent[:100] == [2] * 100 and sent[100:120] == [0] * 20 and sent[120:] == [2] * 180


def test_corruptions_are_what_the_receiver_sees() -> None:
    cases = {
        "crc:100%,MOTION_SENSORS": Rejection.BAD_CRC,
        "out-of-range:AY": Rejection.OUT_OF_RANGE,
    }
    for text, reason in cases.items():
        tx, inj = Transmitter(CODEC), FaultInjector(CODEC, [parse_fault(text)])
        motion = inj.apply(burst(tx, 1), 0.0)[0]
        result = CODEC.decode_message(motion)
        assert isinstance(result, Rejected) and result.reason is reason, text


def test_stuck_and_counter_faults_keep_frames_well_formed() -> None:
    tx = Transmitter(CODEC)
    inj = FaultInjector(CODEC, [parse_fault("stuck:YAW_RATE@0.05s"),
                                parse_fault("counter-freeze:SYNC@0.05s")])
    yaw, alive = [], []
    for k in range(10):
        for frame in inj.apply(burst(tx, k), 0.01 * k):
            d = CODEC.decode_message(frame)
            assert isinstance(d, Decoded)  # valid CRC: E2E cannot see these faults
            if d.name == "MOTION_SENSORS":
                yaw.append(d.values["YAW_RATE"])
            else:
                alive.append(d.counter)
    assert len(set(yaw[5:])) == 1 and yaw[5] == pytest.approx(0.5)
    assert alive[:5] == [0, 1, 2, 3, 4] and set(alive[5:]) == {5}


def test_delay_holds_frames_and_jitter_may_reorder() -> None:
    tx, inj = Transmitter(CODEC), FaultInjector(CODEC, [parse_fault("delay:20ms")],
                                                lockstep=True)
    out = [inj.apply(burst(tx, k), 0.01 * k) for k in range(5)]
    names = [[CODEC.decode_message(f).name for f in o] for o in out]
    # SYNC is the lockstep clock and is never held; sensor frames arrive two cycles late
    assert names[0] == ["SYNC"] and names[2] == ["SYNC", "MOTION_SENSORS"]
    tx, inj = Transmitter(CODEC), FaultInjector(CODEC, [parse_fault("jitter:30ms")], seed=4)
    seen = [CODEC.decode_message(f) for k in range(200) for f in inj.apply(burst(tx, k),
                                                                             0.01 * k)]
    counters = np.array([d.counter for d in seen if d.name == "MOTION_SENSORS"])
    assert np.any(np.diff(counters) % 16 != 1)  # out of order or missing at least once
