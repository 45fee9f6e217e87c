"""The codec's E2E layout checks, its exact frames and verdicts against independent
references (cantools' own encode/decode, hand-computed values, can_db/crc.py), the
transmitter's alive counter and saturation counts, the early rejections and their bounded
cache, and the shape of its records."""

from __future__ import annotations

import dataclasses
import math
import random
from pathlib import Path

import can
import pytest

from can_db import codec as codec_module
from can_db.codec import (
    Codec,
    Decoded,
    MessageSpec,
    Rejected,
    Rejection,
    SignalSpec,
    Transmitter,
    parsed_dbc,
)
from can_db.crc import frame_crc, frame_crc16

HEAD = 'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A B\n\n'
CODEC = Codec()
DB = CODEC.database


def dbc(tmp_path: Path, signals: str, name: str = "t.dbc") -> Path:
    path = tmp_path / name
    path.write_text(HEAD + "BO_ 256 M: 8 A\n" + signals + "\n")
    return path


@pytest.mark.parametrize(
    ("signals", "words"),
    [
        (' SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n', "every frame needs one of"),
        (' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n', "every frame needs one of"),
        (
            ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ CRC16 : 8|16@1+ (1,0) [0|65535] "" B\n'
            ' SG_ ALIVE : 24|4@1+ (1,0) [0|15] "" B\n',
            "every frame needs one of",
        ),
        (
            ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ ALIVE : 12|4@1+ (1,0) [0|15] "" B\n',
            "must be bits 0..7",
        ),
        (
            ' SG_ CRC16 : 0|16@1+ (1,0) [0|65535] "" B\n SG_ ALIVE : 20|4@1+ (1,0) [0|15] "" B\n',
            "must be bits 0..15",
        ),
        (
            ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n'
            ' SG_ X : 23|8@0+ (1,0) [0|255] "" B\n',
            "only Intel byte order",
        ),
    ],
)
def test_a_frame_without_the_e2e_layout_is_refused(
    tmp_path: Path, signals: str, words: str
) -> None:
    with pytest.raises(ValueError, match=words):
        Codec(dbc(tmp_path, signals))


def test_a_frame_with_the_e2e_layout_is_accepted(tmp_path: Path) -> None:
    codec = Codec(
        dbc(
            tmp_path,
            ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n'
            ' SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n'
            ' SG_ X : 12|8@1+ (1,0) [0|255] "" B\n',
        )
    )
    assert list(codec.messages) == ["M"]


# ----------------------------------------------------------------- references for the frames
def reference_frame(name: str, raw: dict[str, int], counter: int) -> bytes:
    """The frame of ``name`` with the raw signal values ``raw`` (others 0) and ``counter``,
    packed by cantools (no range check) and sealed with can_db/crc.py's byte-wise CRC."""
    message = DB.get_message_by_name(name)
    crc16 = CODEC.messages[name].crc_bits == 16
    values = {s.name: 0 for s in message.signals} | raw | {"ALIVE": counter}
    data = bytearray(message.encode(values, scaling=False, strict=False))
    if crc16:
        crc = frame_crc16(message.frame_id, data)
        data[0], data[1] = crc & 0xFF, crc >> 8
    else:
        data[0] = frame_crc(message.frame_id, data)
    return bytes(data)


def alive_modulo(name: str) -> int:
    """How many values the DBC's 4-bit ALIVE signal has (16)."""
    return 1 << DB.get_message_by_name(name).get_signal_by_name("ALIVE").length


# --------------------------------------------------------------------- transmitter (hot path)
@pytest.mark.parametrize("name", ["WHEEL_TORQUE_CMD", "CTRL_STATUS", "MOTION_SENSORS", "SYNC"])
def test_the_transmitter_sends_the_codecs_frames_with_a_wrapping_alive_counter(name: str) -> None:
    """Frame k of a transmitter carries ALIVE = k mod 16 (read back by cantools), the CRC
    of its profile over the rest (can_db/crc.py, byte-wise), and is the frame Codec.message
    makes for that counter: same bytes, ID, flags and timestamp."""
    rng = random.Random(name)
    spec = CODEC.messages[name]
    tx = Transmitter(CODEC)
    message = DB.get_message_by_name(name)
    for k in range(2 * alive_modulo(name) + 3):
        values = {s.name: rng.uniform(s.minimum, s.maximum) for s in spec.signals}
        sent = tx.message(name, values)
        ref = CODEC.message(name, values, k % alive_modulo(name))
        assert (
            sent.arbitration_id,
            sent.is_extended_id,
            sent.is_remote_frame,
            sent.is_error_frame,
            sent.is_fd,
            sent.dlc,
            sent.timestamp,
        ) == (spec.frame_id, False, False, False, False, 8, 0.0)
        assert (
            ref.arbitration_id,
            ref.is_extended_id,
            ref.is_remote_frame,
            ref.is_error_frame,
            ref.timestamp,
        ) == (spec.frame_id, False, False, False, 0.0)
        assert bytes(sent.data) == bytes(ref.data), k
        decoded = message.decode(bytes(sent.data), decode_choices=False)
        assert decoded["ALIVE"] == k % 16, k
        if spec.crc_bits == 16:
            assert decoded["CRC16"] == frame_crc16(spec.frame_id, bytes(sent.data))
        else:
            assert decoded["CRC8"] == frame_crc(spec.frame_id, bytes(sent.data))
        for sig in spec.signals:
            assert abs(decoded[sig.name] - values[sig.name]) <= sig.scale / 2 + 1e-9
    assert tx.saturations == {}


def test_the_transmitter_counts_each_saturated_signal_per_frame() -> None:
    tx = Transmitter(CODEC)
    frames = [
        {"TQ_FL": 5000.0, "TQ_FR": 10.0},
        {"TQ_FL": -5000.0, "TQ_FR": math.nan},
        {"TQ_FL": 600.0},
        {"TQ_FL": 100.0},
    ]
    for values in frames:
        tx.message("WHEEL_TORQUE_CMD", values)
    tx.message("CTRL_REFS", {"DELTA_M": 1e6})
    assert tx.saturations == {
        "WHEEL_TORQUE_CMD.TQ_FL": 3,
        "WHEEL_TORQUE_CMD.TQ_FR": 1,
        "CTRL_REFS.DELTA_M": 1,
    }


def test_each_message_has_its_own_alive_counter() -> None:
    tx = Transmitter(CODEC)
    alive = []
    for name in ("SYNC", "SYNC", "MOTION_SENSORS", "SYNC", "WHEEL_TORQUE_CMD"):
        data = bytes(tx.message(name, {}).data)
        alive.append(DB.get_message_by_name(name).decode(data)["ALIVE"])
    assert alive == [0, 1, 0, 2, 0]


@pytest.mark.parametrize(
    ("name", "byte", "shift"), [("WHEEL_TORQUE_CMD", 1, 0), ("MOTION_SENSORS", 2, 0)]
)
def test_encode_takes_the_counter_modulo_16_into_the_alive_nibble(
    name: str, byte: int, shift: int
) -> None:
    """ALIVE is the low nibble of byte 1 (CRC-8 profile) or byte 2 (CRC-16 profile); a
    counter of 16 or 33 is the counter 0 or 1 and touches no other bit."""
    for counter, alive in ((16, 0), (33, 1), (15, 15)):
        data, _ = CODEC.encode(name, {}, counter)
        assert data == CODEC.encode(name, {}, alive)[0]
        assert (data[byte] >> shift) & 0x0F == alive
        assert data == reference_frame(name, {}, alive)


# --------------------------------------------------------------------------- exact frames
def test_encoded_frames_are_the_hand_packed_frames() -> None:
    """Encoded bytes against frames packed by cantools from raw values computed by hand
    (phys / scale rounded, offset removed), sealed with the byte-wise CRC."""
    cases = [
        (
            "WHEEL_TORQUE_CMD",
            {"TQ_FL": 100.5, "TQ_FR": -0.5, "TQ_RL": -512.0, "TQ_RR": 511.5, "ECHO_CYCLE": 42},
            5,
            {"TQ_FL": 201, "TQ_FR": -1, "TQ_RL": -1024, "TQ_RR": 1023, "ECHO_CYCLE": 42},
        ),
        (
            "WHEEL_SPEEDS",
            {"WS_FL": -10.0, "WS_FR": 0.0, "WS_RL": 100.05, "WS_RR": 194.7},
            11,
            {"WS_FL": 0, "WS_FR": 100, "WS_RL": 1100, "WS_RR": 2047},
        ),
        (
            "DRIVER_INPUTS",
            {"SWA": -1000.0, "ACCEL_PEDAL": 100.0, "BRAKE_PEDAL": 0.1, "STAB_ENABLE": 1},
            15,
            {"SWA": -20000, "ACCEL_PEDAL": 1000, "BRAKE_PEDAL": 1, "STAB_ENABLE": 1},
        ),
    ]
    for name, values, counter, raw in cases:
        data, saturated = CODEC.encode(name, values, counter)
        assert saturated == ()
        assert data == reference_frame(name, raw, counter), name


def test_saturation_stops_at_the_limits_and_names_the_signals() -> None:
    data, saturated = CODEC.encode(
        "DRIVER_INPUTS", {"SWA": -1e9, "ACCEL_PEDAL": math.inf, "BRAKE_PEDAL": math.nan}, 2
    )
    assert saturated == ("SWA", "ACCEL_PEDAL", "BRAKE_PEDAL")
    assert data == reference_frame(
        "DRIVER_INPUTS", {"SWA": -20000, "ACCEL_PEDAL": 1000, "BRAKE_PEDAL": 0}, 2
    )


def test_codec_message_is_a_classical_11_bit_frame_that_decodes() -> None:
    msg = CODEC.message("SYNC", {"CYCLE": 7, "SIM_TIME": 0.07}, 3)
    assert (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_fd) == (
        0x10F,
        False,
        False,
        False,
    )
    result = CODEC.decode_message(msg)
    assert isinstance(result, Decoded)
    assert (result.name, result.values, result.counter) == (
        "SYNC",
        {"CYCLE": 7.0, "SIM_TIME": 0.07},
        3,
    )


# ------------------------------------------------------------------------- decode verdicts
@pytest.mark.parametrize(
    ("name", "signal", "raw", "accepted"),
    [
        ("DRIVER_INPUTS", "SWA", 20000, True),
        ("DRIVER_INPUTS", "SWA", 20001, False),
        ("DRIVER_INPUTS", "SWA", -20000, True),
        ("DRIVER_INPUTS", "SWA", -20001, False),
        ("DRIVER_INPUTS", "ACCEL_PEDAL", 1000, True),
        ("DRIVER_INPUTS", "ACCEL_PEDAL", 1001, False),
        ("MOTION_SENSORS", "AX", 8000, True),
        ("MOTION_SENSORS", "AX", 8001, False),
        ("MOTION_SENSORS", "AY", -8000, True),
        ("MOTION_SENSORS", "AY", -8001, False),
        ("VEHICLE_EST", "VX_EST", -6000, True),
        ("VEHICLE_EST", "VX_EST", -6001, False),
        ("VEHICLE_EST", "VX_EST", 24000, True),
        ("VEHICLE_EST", "VX_EST", 24001, False),
    ],
)
def test_one_raw_step_beyond_a_limit_is_out_of_range(
    name: str, signal: str, raw: int, accepted: bool
) -> None:
    """The DBC range is the acceptance range to the last raw step (a tolerance of 1e-9 of
    a unit, for the float arithmetic, not a step)."""
    result = CODEC.decode(CODEC.messages[name].frame_id, reference_frame(name, {signal: raw}, 4))
    if accepted:
        assert isinstance(result, Decoded) and result.counter == 4
        scale = DB.get_message_by_name(name).get_signal_by_name(signal).scale
        assert math.isclose(result.values[signal], raw * scale, abs_tol=1e-9)
    else:
        assert isinstance(result, Rejected) and result.reason is Rejection.OUT_OF_RANGE
        assert f".{signal} = " in result.detail


@pytest.mark.parametrize(
    ("name", "raw", "detail"),
    [
        # signed, sign bit set: -30000 · 0.05 deg
        ("DRIVER_INPUTS", {"SWA": -30000}, "DRIVER_INPUTS.SWA = -1500 outside [-1000, 1000] deg"),
        # signed, sign bit clear: 30000 · 0.05 deg
        ("DRIVER_INPUTS", {"SWA": 30000}, "DRIVER_INPUTS.SWA = 1500 outside [-1000, 1000] deg"),
        # signed, 14 bits: -8192 · 0.005 m/s² (the most negative raw value)
        ("MOTION_SENSORS", {"AX": -8192}, "MOTION_SENSORS.AX = -40.96 outside [-40, 40] m/s^2"),
        # unsigned with its top bit set: 1023 · 0.1 % (not a negative value)
        (
            "DRIVER_INPUTS",
            {"ACCEL_PEDAL": 1023},
            "DRIVER_INPUTS.ACCEL_PEDAL = 102.3 outside [0, 100] %",
        ),
        # the first signal out of range is named, the later ones not
        (
            "DRIVER_INPUTS",
            {"SWA": 1, "ACCEL_PEDAL": 1010, "BRAKE_PEDAL": 1020},
            "DRIVER_INPUTS.ACCEL_PEDAL = 101 outside [0, 100] %",
        ),
        (
            "VEHICLE_EST",
            {"VX_EST": 100, "VY_EST": -32768},
            "VEHICLE_EST.VY_EST = -65.536 outside [-40, 40] m/s",
        ),
    ],
)
def test_an_out_of_range_rejection_names_the_signal_its_physical_value_and_range(
    name: str, raw: dict[str, int], detail: str
) -> None:
    result = CODEC.decode(CODEC.messages[name].frame_id, reference_frame(name, raw, 9))
    assert isinstance(result, Rejected)
    assert (result.reason, result.frame_id, result.detail) == (
        Rejection.OUT_OF_RANGE,
        CODEC.messages[name].frame_id,
        detail,
    )


OFF_GRID = (
    ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n'
    ' SG_ X : 12|11@1- (0.3,5) [-95.1|105.1] "V" B\n'
    ' SG_ N : 23|8@1+ (1,0) [0|200] "" B\n'
)


def test_limits_off_the_raw_grid_encode_to_the_nearest_value_inside(tmp_path: Path) -> None:
    """X = raw · 0.3 + 5 V limited to [-95.1, 105.1] V: neither limit is on the grid. The
    encoder never makes a frame its own decoder rejects: at and beyond the limits it sends
    the grid value nearest inside, raw -333 (-94.9 V) and raw 333 (104.9 V)."""
    codec = Codec(dbc(tmp_path, OFF_GRID))
    message = codec.database.get_message_by_name("M")
    for phys, raw, expected in (
        (-95.1, -333, -94.9),
        (-1e9, -333, -94.9),
        (105.1, 333, 104.9),
        (math.inf, 333, 104.9),
        (5.0, 0, 5.0),
        (-94.9, -333, -94.9),
    ):
        data, _ = codec.encode("M", {"X": phys}, 1)
        assert message.decode(data, scaling=False, decode_choices=False)["X"] == raw, phys
        result = codec.decode(256, data)
        assert isinstance(result, Decoded), (phys, result)
        assert math.isclose(result.values["X"], expected, abs_tol=1e-9)


def test_an_out_of_range_value_with_an_offset_is_reported_in_physical_units(tmp_path: Path) -> None:
    codec = Codec(dbc(tmp_path, OFF_GRID))
    message = codec.database.get_message_by_name("M")
    for raw, phys in ((-1024, "-302.2"), (1023, "311.9"), (-334, "-95.2"), (334, "105.2")):
        data = bytearray(
            message.encode({"CRC8": 0, "ALIVE": 0, "X": raw, "N": 0}, scaling=False, strict=False)
        )
        data[0] = frame_crc(256, data)
        result = codec.decode(256, bytes(data))
        assert isinstance(result, Rejected) and result.reason is Rejection.OUT_OF_RANGE
        assert result.detail == f"M.X = {phys} outside [-95.1, 105.1] V"


def test_a_signal_without_a_unit_has_an_empty_unit(tmp_path: Path) -> None:
    codec = Codec(dbc(tmp_path, OFF_GRID))
    units = {s.name: s.unit for s in codec.messages["M"].signals}
    assert units == {"X": "V", "N": ""}
    for name, spec in CODEC.messages.items():
        for sig in spec.signals:
            assert sig.unit == (
                DB.get_message_by_name(name).get_signal_by_name(sig.name).unit or ""
            ), (name, sig.name)


def test_a_message_without_a_cycle_time_has_cycle_time_zero(tmp_path: Path) -> None:
    codec = Codec(dbc(tmp_path, OFF_GRID))
    assert codec.database.get_message_by_name("M").cycle_time is None
    assert codec.messages["M"].cycle_time_s == 0.0


def test_every_message_of_the_dbc_is_a_control_or_a_diagnostic_frame() -> None:
    """Diagnostic frames are set apart without ending the walk over the DBC's messages."""
    assert CODEC.diagnostic == {"DIAG_REQ_CTRL": 0x7E0, "DIAG_RESP_CTRL": 0x7E8}
    assert sorted([*CODEC.messages, *CODEC.diagnostic]) == sorted(m.name for m in DB.messages)


# ------------------------------------------------------------------------ early rejections
def test_the_reason_and_detail_of_an_early_rejection() -> None:
    good, _ = CODEC.encode("SYNC", {"CYCLE": 1}, 1)
    cases = [
        (CODEC.decode(0x7FF, good), Rejection.UNKNOWN_ID, "ID 0x7FF not in DBC"),
        (
            CODEC.decode(0x7E0, good),
            Rejection.UNKNOWN_ID,
            "ID 0x7E0: diagnostic frame (UDS over ISO-TP), no E2E",
        ),
        (
            CODEC.decode(0x7E8, good),
            Rejection.UNKNOWN_ID,
            "ID 0x7E8: diagnostic frame (UDS over ISO-TP), no E2E",
        ),
        (
            CODEC.decode(0x7E0, good, is_remote_frame=True),
            Rejection.NOT_DATA_FRAME,
            "not a classical data frame",
        ),
        (
            CODEC.decode(0x10F, good, is_error_frame=True),
            Rejection.NOT_DATA_FRAME,
            "not a classical data frame",
        ),
        (CODEC.decode(0x10F, good[:7]), Rejection.WRONG_LENGTH, "SYNC: 7 bytes, expected 8"),
    ]
    for result, reason, detail in cases:
        assert isinstance(result, Rejected)
        assert (result.reason, result.detail) == (reason, detail)


@pytest.mark.parametrize("flag", ["is_extended_id", "is_remote_frame", "is_error_frame", "is_fd"])
def test_decode_message_refuses_each_flag_on_its_own(flag: str) -> None:
    """A frame whose payload and CRC are right is still refused when any one of the four
    flags says it is not a classical 11-bit data frame."""
    good = CODEC.message("SYNC", {"CYCLE": 1}, 1)
    assert isinstance(CODEC.decode_message(good), Decoded)
    flags = {"is_extended_id": False, flag: True}
    msg = can.Message(arbitration_id=good.arbitration_id, data=good.data, **flags)
    result = CODEC.decode_message(msg)
    assert isinstance(result, Rejected) and result.reason is Rejection.NOT_DATA_FRAME
    assert isinstance(CODEC.decode(good.arbitration_id, good.data, **{flag: True}), Rejected)


def test_the_flags_of_decode_are_keyword_only() -> None:
    good, _ = CODEC.encode("SYNC", {"CYCLE": 1}, 1)
    with pytest.raises(TypeError):
        CODEC.decode(0x10F, good, True)  # type: ignore[misc]


def test_early_rejections_are_shared_up_to_the_cache_bound() -> None:
    """Every 11-bit ID under both early reasons (4096 keys) gets one shared object; a flood
    of further distinct IDs (extended ones) gets fresh objects and no cache entry."""
    codec = Codec()
    keys = [(fid, {"is_remote_frame": True}) for fid in range(0x800)] + [
        (fid, {}) for fid in range(0x800) if fid not in codec.by_id
    ]
    keys += [(0x800 + i, {"is_extended_id": True}) for i in range(2 * 0x800 - len(keys))]
    assert len(keys) == 4096
    first = [codec.decode(fid, b"", **flags) for fid, flags in keys]
    again = [codec.decode(fid, b"", **flags) for fid, flags in keys]
    assert all(a is b for a, b in zip(first, again, strict=True))
    beyond = [codec.decode(0x1000 + i, b"", is_extended_id=True) for i in range(3)]
    for i, rejected in enumerate(beyond):
        repeat = codec.decode(0x1000 + i, b"", is_extended_id=True)
        assert repeat is not rejected and repeat == rejected
    assert all(
        a is b for a, b in zip(first, [codec.decode(f, b"", **k) for f, k in keys], strict=True)
    )


# --------------------------------------------------------------------- the parse, the records
def test_the_dbc_is_parsed_once_per_file(tmp_path: Path) -> None:
    assert Codec().database is Codec().database
    copies = [tmp_path / f"c{i}.dbc" for i in range(9)]
    for path in copies:
        path.write_bytes(codec_module.default_dbc_path().read_bytes())
    codec_module._parse_dbc.cache_clear()
    first = [parsed_dbc(p) for p in copies[:8]]
    assert all(parsed_dbc(p) is db for p, db in zip(copies[:8], first, strict=True))
    parsed_dbc(copies[8])  # a ninth file: the least recently used one is parsed again
    assert parsed_dbc(copies[0]) is not first[0]
    assert parsed_dbc(copies[7]) is first[7]


def test_a_spec_without_a_profile_is_the_crc8_one() -> None:
    spec = MessageSpec(name="X", frame_id=1, length=8, cycle_time_s=0.01, senders=(), signals=())
    assert (spec.crc_bits, spec.counter_start) == (8, 8)


@pytest.mark.parametrize(
    "record",
    [
        CODEC.messages["SYNC"],
        CODEC.messages["SYNC"].signals[0],
        Decoded("SYNC", {}, 0),
        Rejected(Rejection.BAD_CRC, 1, "x"),
    ],
)
def test_the_records_have_a_fixed_set_of_fields(record: object) -> None:
    assert not hasattr(record, "__dict__")
    with pytest.raises((AttributeError, TypeError)):  # TypeError: a frozen one's __setattr__
        record.extra = 1  # type: ignore[attr-defined]


@pytest.mark.parametrize("spec", [CODEC.messages["SYNC"], CODEC.messages["SYNC"].signals[0]])
def test_the_specs_shared_by_every_user_of_a_codec_are_immutable(
    spec: MessageSpec | SignalSpec,
) -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.name = "OTHER"  # type: ignore[misc]
