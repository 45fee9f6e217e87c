"""Random acceptance of the E2E check on the frames the controller acts on (≤ 1e-5).

The measurement is ``rhonn-bench e2e --fast`` (harness/bench/e2e.py): seeded random 8-byte
payloads on each ID, alone and between genuine frames, through the controller's RxMonitor;
a payload counts when the monitor returns it as data. The vectorised CRC pre-filter it uses
is checked against the codec here, and its counts against the full one-by-one path.

Sample: 2·10⁶ payloads per ID and stream, 5 IDs × 2 streams = 2·10⁷ payloads; the assertion
is on the one-sided 95 % Clopper-Pearson upper bound of the rate, per ID and stream (a rate
bound of ≈ 1.5·10⁻⁶ for 0 accepted, ≈ 9.8·10⁻⁶ for 12) and pooled (≈ 1.5·10⁻⁷ for 0,
≈ 2·10⁻⁶ for 20). The same measurement on a CRC-8 frame fails the bound by far.
"""

from __future__ import annotations

import numpy as np
import pytest

from can_db.codec import Codec, Decoded, Rejected, Rejection
from harness.bench.e2e import (
    ACTED_ON,
    STREAMS,
    crc_pass_mask,
    measure,
    random_payloads,
    upper_bound,
)

CODEC = Codec()
PAYLOADS = 2_000_000
LIMIT = 1e-5


@pytest.mark.parametrize("name", sorted(CODEC.messages))
def test_vectorised_crc_agrees_with_the_codec(name: str) -> None:
    """The pre-filter's CRC verdict equals the codec's on random and on sealed payloads."""
    fid = CODEC.messages[name].frame_id
    data = random_payloads(CODEC, name, "random", 20_000, seed=99)
    for row in data[::2]:  # half of them with a correct CRC
        sealed = bytearray(row.tobytes())
        CODEC.seal(fid, sealed)
        row[:] = np.frombuffer(bytes(sealed), dtype=np.uint8)
    mask = crc_pass_mask(CODEC, fid, data)
    codec_ok = np.array([not (isinstance(r := CODEC.decode(fid, row.tobytes()), Rejected)
                              and r.reason is Rejection.BAD_CRC) for row in data])
    assert mask.sum() >= 10_000 and np.array_equal(mask, codec_ok)


@pytest.mark.parametrize("stream", STREAMS)
def test_fast_count_equals_the_full_rx_path(stream: str) -> None:
    """Same accepted count with and without the pre-filter, on payloads of which 1 in 50 has
    a correct CRC (so the counter checks see thousands of frames)."""
    name = "MOTION_SENSORS"
    fid = CODEC.messages[name].frame_id
    data = random_payloads(CODEC, name, stream, 30_000, seed=5)
    for row in data[::50]:
        sealed = bytearray(row.tobytes())
        CODEC.seal(fid, sealed)
        row[:] = np.frombuffer(bytes(sealed), dtype=np.uint8)
    fast = measure(CODEC, name, stream, 0, 0, fast=True, data=data)
    full = measure(CODEC, name, stream, 0, 0, fast=False, data=data)
    assert fast.crc_passed == full.crc_passed >= 600
    assert fast.accepted == full.accepted > 0


def test_random_acceptance_of_the_acted_on_frames_is_below_1e_5() -> None:
    results = [measure(CODEC, name, stream, PAYLOADS, seed=1, fast=True)
               for name in ACTED_ON for stream in STREAMS]
    for r in results:
        assert r.profile == "CRC16", r.name
        assert upper_bound(r.accepted, r.payloads) <= LIMIT, r.as_dict()
    total_n = sum(r.payloads for r in results)
    total_k = sum(r.accepted for r in results)
    assert total_n == 2 * 10**7
    assert upper_bound(total_k, total_n) <= 0.5 * LIMIT, (total_k, total_n)


def test_the_same_measurement_fails_a_crc8_frame() -> None:
    """The check can fail: a CRC-8 frame (the controller's torque command, CRC-8 and the
    opendbc-style counter tolerance) accepts about one random payload in 3000."""
    r = measure(CODEC, "WHEEL_TORQUE_CMD", "random", 200_000, seed=1, fast=True)
    assert r.profile == "CRC8"
    assert r.accepted > 30 and r.rate > 10 * LIMIT


def test_a_genuine_stream_is_fully_accepted() -> None:
    """The window does not reject the sender's own frames (delta 1) on any acted-on ID."""
    from can_db.monitor import RxMonitor

    for name in ACTED_ON:
        mon = RxMonitor(CODEC, [name])
        for k in range(64):
            got = mon.process(CODEC.message(name, {}, k % 16), 0.01 * k)
            assert isinstance(got, Decoded), (name, k)
        assert mon.rejection_counts() == {}
