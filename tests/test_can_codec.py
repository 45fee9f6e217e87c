"""Codec: round trips, E2E CRC (both profiles), saturation, layouts, and robustness against
arbitrary frames."""

from __future__ import annotations

import math

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_db.codec import Codec, Decoded, Rejected, Rejection
from can_db.crc import crc8_j1850, crc16_ccitt_false, frame_crc, frame_crc16

CODEC = Codec()
NAMES = sorted(CODEC.messages)


def test_crc8_j1850_check_value() -> None:
    # Published check value of CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF).
    assert crc8_j1850(b"123456789") == 0x4B


def test_crc16_ccitt_false_check_value() -> None:
    # Published check value of CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection,
    # xorout 0).
    assert crc16_ccitt_false(b"123456789") == 0x29B1


ACTED_ON = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")


def test_frames_the_controller_acts_on_use_the_16_bit_profile() -> None:
    """The profile follows the DBC's CRC signal: CRC16 frames carry the CRC in bytes 0-1 and
    ALIVE in bits 16-19; the rest keep CRC8 in byte 0 and ALIVE in bits 8-11."""
    for name, spec in CODEC.messages.items():
        signals = {s.name: s for s in CODEC.database.get_message_by_name(name).signals}
        if name in ACTED_ON:
            assert spec.crc_bits == 16 and "CRC16" in signals and "CRC8" not in signals
            assert (signals["CRC16"].start, signals["CRC16"].length) == (0, 16)
            assert signals["ALIVE"].start == 16, name
        else:
            assert spec.crc_bits == 8 and "CRC8" in signals, name
            assert signals["ALIVE"].start == 8, name


def test_crc16_frame_layout_bytes() -> None:
    """Bytes 0-1 are the CRC-16 (low byte first) over the data ID and bytes 2..7."""
    spec = CODEC.messages["MOTION_SENSORS"]
    data, _ = CODEC.encode("MOTION_SENSORS", {"YAW_RATE": 12.5, "AX": -3.0, "AY": 7.25}, 9)
    crc = crc16_ccitt_false(bytes((spec.frame_id >> 8, spec.frame_id & 0xFF)) + data[2:])
    assert data[0] | data[1] << 8 == crc == frame_crc16(spec.frame_id, data)
    assert data[2] & 0x0F == 9


def test_shrunk_signals_cover_what_the_plant_sends() -> None:
    """Ranges and resolutions of the CRC16 layouts: wheel speeds to the plant's 250 km/h at
    its rolling radius with ≤ 0.1 rad/s, accelerations ±40 m/s² at 5 mm/s², SIM_TIME beyond
    the longest plant run, CYCLE beyond a day at 100 Hz, and the plant's sensor quantisation
    equal to the CAN resolution (so no value is rounded twice)."""
    from plant_sim.params import load_vehicle_params
    from plant_sim.run_options import DURATION_MAX_S, SPEED_MAX_KMH

    car = load_vehicle_params()
    ws = {s.name: s for s in CODEC.messages["WHEEL_SPEEDS"].signals}
    for name in ("WS_FL", "WS_FR", "WS_RL", "WS_RR"):
        assert ws[name].scale <= 0.1 and ws[name].minimum < 0.0
        assert ws[name].maximum * car.wheel_radius_m * 3.6 >= SPEED_MAX_KMH
    mot = {s.name: s for s in CODEC.messages["MOTION_SENSORS"].signals}
    assert mot["AX"].scale == mot["AY"].scale == car.sensors.accel_res_mps2 == 0.005
    assert mot["AX"].maximum >= 40.0 and mot["AY"].minimum <= -40.0
    assert ws["WS_FL"].scale == car.sensors.wheel_speed_res_radps
    sync = {s.name: s for s in CODEC.messages["SYNC"].signals}
    assert sync["SIM_TIME"].maximum >= 2 * DURATION_MAX_S and sync["SIM_TIME"].scale == 0.01
    assert sync["CYCLE"].maximum * 0.01 >= 24 * 3600


def test_every_frame_of_design_section4_is_in_the_dbc() -> None:
    expected = {"DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC",
                "WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS"}
    assert expected <= set(CODEC.messages)
    for spec in CODEC.messages.values():
        assert spec.length == 8 and spec.frame_id < 0x800 and spec.cycle_time_s == 0.01


def test_control_resolution_meets_design() -> None:
    sig = {s.name: s for s in CODEC.messages["MOTION_SENSORS"].signals}
    assert sig["YAW_RATE"].scale <= 0.01  # deg/s per bit
    for s in CODEC.messages["WHEEL_TORQUE_CMD"].signals:
        if s.name.startswith("TQ_"):
            assert s.scale <= 0.5 and s.maximum >= 450.0  # N·m per bit, motor peak fits


@st.composite
def message_values(draw: st.DrawFn) -> tuple[str, dict[str, float]]:
    name = draw(st.sampled_from(NAMES))
    values = {s.name: draw(st.floats(s.minimum, s.maximum, allow_nan=False))
              for s in CODEC.messages[name].signals}
    return name, values


@given(message_values(), st.integers(0, 15))
def test_round_trip_within_half_a_bit(case: tuple[str, dict[str, float]], counter: int) -> None:
    name, values = case
    data, saturated = CODEC.encode(name, values, counter)
    assert saturated == ()
    result = CODEC.decode(CODEC.messages[name].frame_id, data)
    assert isinstance(result, Decoded) and result.counter == counter
    for sig in CODEC.messages[name].signals:
        assert abs(result.values[sig.name] - values[sig.name]) <= sig.scale / 2 + 1e-9


@given(message_values(), st.integers(0, 15))
def test_agrees_with_cantools_reference(case: tuple[str, dict[str, float]], counter: int) -> None:
    name, values = case
    data, _ = CODEC.encode(name, values, counter)
    reference = CODEC.database.get_message_by_name(name).decode(data, decode_choices=False)
    ours = CODEC.decode(CODEC.messages[name].frame_id, data)
    assert isinstance(ours, Decoded)
    crc = "CRC16" if CODEC.messages[name].crc_bits == 16 else "CRC8"
    assert reference["ALIVE"] == counter
    assert reference[crc] == int.from_bytes(data[: CODEC.messages[name].crc_bits // 8], "little")
    for key, value in ours.values.items():
        assert math.isclose(value, reference[key], abs_tol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_every_single_bit_flip_is_caught(name: str) -> None:
    spec = CODEC.messages[name]
    mid = {s.name: (s.minimum + s.maximum) / 3 for s in spec.signals}
    data, _ = CODEC.encode(name, mid, 7)
    for bit in range(64):
        corrupted = bytearray(data)
        corrupted[bit // 8] ^= 1 << (bit % 8)
        result = CODEC.decode(spec.frame_id, bytes(corrupted))
        assert isinstance(result, Rejected) and result.reason is Rejection.BAD_CRC, bit


def test_frame_copied_to_another_id_fails_crc() -> None:
    data, _ = CODEC.encode("DRIVER_INPUTS", {"SWA": 10.0}, 0)
    result = CODEC.decode(CODEC.messages["MOTION_SENSORS"].frame_id, data)
    assert isinstance(result, Rejected) and result.reason is Rejection.BAD_CRC


def test_out_of_range_values_saturate_and_are_reported() -> None:
    data, saturated = CODEC.encode(
        "WHEEL_TORQUE_CMD", {"TQ_FL": 5000.0, "TQ_FR": -5000.0, "TQ_RL": math.nan,
                             "TQ_RR": math.inf, "ECHO_CYCLE": 300}, 0)
    assert set(saturated) == {"TQ_FL", "TQ_FR", "TQ_RL", "TQ_RR", "ECHO_CYCLE"}
    result = CODEC.decode(CODEC.messages["WHEEL_TORQUE_CMD"].frame_id, data)
    assert isinstance(result, Decoded)
    assert result.values == {"TQ_FL": 511.5, "TQ_FR": -512.0, "TQ_RL": 0.0, "TQ_RR": 511.5,
                             "ECHO_CYCLE": 255.0}


def test_raw_value_beyond_dbc_range_is_rejected() -> None:
    spec = CODEC.messages["DRIVER_INPUTS"]
    sig = next(s for s in spec.signals if s.name == "ACCEL_PEDAL")
    word = (1023 << sig.start)  # 102.3 %: representable, but above the 100 % maximum
    payload = bytearray(word.to_bytes(8, "little"))
    CODEC.seal(spec.frame_id, payload)
    result = CODEC.decode(spec.frame_id, bytes(payload))
    assert isinstance(result, Rejected) and result.reason is Rejection.OUT_OF_RANGE
    assert "ACCEL_PEDAL" in result.detail


def test_unknown_id_wrong_length_and_non_data_frames() -> None:
    good, _ = CODEC.encode("SYNC", {"CYCLE": 1}, 1)
    sync_id = CODEC.messages["SYNC"].frame_id
    cases = [
        (CODEC.decode(0x7FF, good), Rejection.UNKNOWN_ID),
        (CODEC.decode(sync_id, good[:7]), Rejection.WRONG_LENGTH),
        (CODEC.decode(sync_id, good, is_remote_frame=True), Rejection.NOT_DATA_FRAME),
        (CODEC.decode(sync_id, good, is_extended_id=True), Rejection.NOT_DATA_FRAME),
        (CODEC.decode_message(can.Message(arbitration_id=sync_id, data=good, is_fd=True,
                                          is_extended_id=False)), Rejection.NOT_DATA_FRAME),
    ]
    for result, reason in cases:
        assert isinstance(result, Rejected) and result.reason is reason


@given(st.integers(0, 0x1FFFFFFF), st.binary(min_size=0, max_size=64), st.booleans(),
       st.booleans(), st.booleans())
def test_arbitrary_frames_never_raise(frame_id: int, data: bytes, ext: bool, remote: bool,
                                      fd: bool) -> None:
    result = CODEC.decode(frame_id, data, is_extended_id=ext, is_remote_frame=remote, is_fd=fd)
    assert isinstance(result, Decoded | Rejected)


@given(st.sampled_from(NAMES), st.binary(min_size=8, max_size=8))
def test_arbitrary_payloads_on_known_ids_never_raise(name: str, data: bytes) -> None:
    spec = CODEC.messages[name]
    result = CODEC.decode(spec.frame_id, data)
    if isinstance(result, Decoded):  # only possible when the random CRC happens to match
        width = spec.crc_bits // 8
        assert int.from_bytes(data[:width], "little") == CODEC.e2e_crc(spec.frame_id, data)


def test_word_crc_equals_frame_crc_on_random_frames() -> None:
    """The encoder's CRC from the payload integer is the byte-wise frame CRC."""
    import random

    from can_db.crc import id_seed, word_crc

    rng = random.Random(7)
    for _ in range(5000):
        fid = rng.randrange(0, 0x800)
        data = bytes(rng.randrange(256) for _ in range(8))
        word = int.from_bytes(data, "little")
        assert word_crc(id_seed(fid), word) == frame_crc(fid, data)


def test_word_crc16_equals_frame_crc16_on_random_frames() -> None:
    """The encoder's CRC-16 from the payload integer is the byte-wise frame CRC-16."""
    import random

    from can_db.crc import id_seed16, word_crc16

    rng = random.Random(11)
    for _ in range(5000):
        fid = rng.randrange(0, 0x800)
        data = bytes(rng.randrange(256) for _ in range(8))
        assert word_crc16(id_seed16(fid), int.from_bytes(data, "little")) \
            == frame_crc16(fid, data)


def test_seal_makes_a_changed_payload_pass_on_both_profiles() -> None:
    for name in ("MOTION_SENSORS", "WHEEL_TORQUE_CMD"):
        spec = CODEC.messages[name]
        data = bytearray(CODEC.encode(name, {}, 3)[0])
        data[6] ^= 0x10
        assert isinstance(CODEC.decode(spec.frame_id, bytes(data)), Rejected)
        CODEC.seal(spec.frame_id, data)
        assert isinstance(CODEC.decode(spec.frame_id, bytes(data)), Decoded)
