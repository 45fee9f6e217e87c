"""The fuzzers' oracles (harness/fuzz/oracle.py) against their sources: the CRC catalogue's
check values, the DBC's comment and signals, the documented receiver rules (docs/can-matrix.md), and
hand-written verdict sequences; and their agreement with the codec on correct frames."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from can_db.codec import Codec, Decoded
from harness.fuzz.oracle import (
    COUNTER_FAULT_LIMIT,
    E2E_PROFILES,
    TIMEOUT_CYCLES,
    FrameOracle,
    MonitorOracle,
    Verdict,
    compare,
    crc_function,
)

ORACLE = FrameOracle()
CAN_DOC = (Path(__file__).resolve().parents[1] / "docs" / "can-matrix.md").read_text()
PLANT_TO_CTRL = {"DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC"}


def test_crcmod_gives_the_catalogue_check_values() -> None:
    # reveng catalogue: CRC-8/SAE-J1850 check 0x4B, CRC-16/IBM-3740 (CCITT-FALSE) 0x29B1
    assert crc_function(E2E_PROFILES["CRC8"])(b"123456789") == 0x4B
    assert crc_function(E2E_PROFILES["CRC16"])(b"123456789") == 0x29B1
    for profile in E2E_PROFILES.values():
        assert crc_function(profile)(b"123456789") == profile.check


def test_the_profile_table_is_what_the_dbc_comment_states() -> None:
    text = (Path(__file__).resolve().parents[1] / "can_db" / "rhonn_tv.dbc").read_text()
    general = re.search(r'^CM_ "(.*?)";', text, re.M | re.S)
    assert general is not None
    used = {info.profile.crc_signal for info in ORACLE.messages.values()}
    assert used == {"CRC8", "CRC16"}
    for name in used:
        p, digits = E2E_PROFILES[name], E2E_PROFILES[name].width // 4
        section = general.group(1).split(f"Profile {name} ", 1)[1].split("Profile ", 1)[0]
        for part in (f"poly 0x{p.poly:0{digits}X}", f"init 0x{p.init:0{digits}X}",
                     f"final XOR 0x{p.xor_out:0{digits}X}", f"check 0x{p.check:0{digits}X}",
                     "no reflection", f"payload bytes {p.width // 8}..7"):
            assert part in section, (name, part)


def test_each_message_profile_and_crc_field_come_from_the_dbc() -> None:
    for name, info in ORACLE.messages.items():
        crc16 = name in PLANT_TO_CTRL
        assert info.profile is E2E_PROFILES["CRC16" if crc16 else "CRC8"], name
        assert info.crc_bytes == ((0, 2) if crc16 else (0, 1))
        assert info.covered == (tuple(range(2, 8)) if crc16 else tuple(range(1, 8)))
        alive = info.message.get_signal_by_name("ALIVE")
        assert (alive.start, alive.length) == ((16, 4) if crc16 else (8, 4))


def test_oracle_frames_and_codec_frames_agree() -> None:
    codec = Codec()
    for name, info in ORACLE.messages.items():
        raw = {s.name: (s.valid_lo + s.valid_hi) // 2 for s in info.signals}
        data = ORACLE.encode(name, raw, 7)
        got = codec.decode(info.frame_id, data)
        want = ORACLE.verdict(info.frame_id, data)
        assert isinstance(got, Decoded) and want.accepted, (name, got)
        assert compare(want, True, None, False, got.name, got.values, got.counter) is None
        # and the codec's own frame of the same values passes the oracle bit for bit
        assert codec.encode(name, want.values or {}, 7)[0] == data, name


def test_the_oracle_rejects_each_damage_for_its_reason() -> None:
    info = ORACLE.messages["WHEEL_SPEEDS"]
    good = ORACLE.encode("WHEEL_SPEEDS", {}, 3)
    assert ORACLE.verdict(info.frame_id, good).accepted
    flipped = bytearray(good)
    flipped[5] ^= 0x10
    assert ORACLE.verdict(info.frame_id, bytes(flipped)).reason == "bad_crc"
    assert ORACLE.verdict(info.frame_id, good[:7]).reason == "wrong_length"
    assert ORACLE.verdict(info.frame_id, good, is_remote_frame=True).reason == \
        "not_data_frame"
    assert ORACLE.verdict(0x7FF, good).reason == "unknown_id"
    # the same payload on another ID of the same profile: the data ID is under the CRC
    assert ORACLE.verdict(ORACLE.messages["MOTION_SENSORS"].frame_id, good).reason == \
        "bad_crc"
    pedal = ORACLE.messages["DRIVER_INPUTS"]
    acc = next(s for s in pedal.signals if s.name == "ACCEL_PEDAL")  # 0.1 %/bit, [0, 100]
    assert (acc.valid_lo, acc.valid_hi, acc.raw_hi) == (0, 1000, 1023)
    over = ORACLE.encode("DRIVER_INPUTS", {"ACCEL_PEDAL": 1001}, 0)
    assert ORACLE.verdict(pedal.frame_id, over).reason == "out_of_range"
    edge = ORACLE.encode("DRIVER_INPUTS", {"ACCEL_PEDAL": 1000}, 0)
    assert ORACLE.verdict(pedal.frame_id, edge).values["ACCEL_PEDAL"] == pytest.approx(100.0)


def _run(name: str, counters: list[int]) -> list[str]:
    mon = MonitorOracle(ORACLE, [name])
    info = ORACLE.messages[name]
    out = []
    for k, c in enumerate(counters):
        v = mon.process(info.frame_id, ORACLE.encode(name, {}, c), 0.01 * k)
        out.append("jump" if v.accepted and v.jump else "ok" if v.accepted else str(v.reason))
    return out


def test_counter_rule_of_the_crc8_profile() -> None:
    assert _run("WHEEL_TORQUE_CMD", [0, 1, 1, 3, 4, 15]) == [
        "ok", "ok", "counter_frozen", "jump", "ok", "jump"]


def test_counter_window_of_the_crc16_profile() -> None:
    # delta 2 and 3 accepted (frames lost), 0 repeated, 5 a wrong sequence, then
    # resynchronised
    assert _run("SYNC", [0, 1, 3, 4, 7, 7, 12, 13]) == [
        "ok", "ok", "jump", "ok", "jump", "counter_frozen", "wrong_sequence", "ok"]


def test_the_fault_level_rejects_at_the_documented_limit_and_decays() -> None:
    for name in ("SYNC", "WHEEL_TORQUE_CMD"):
        # five repeats: four rejected as frozen, the fifth reaches the limit; the next good
        # frame lowers the level to 4 and is accepted
        verdicts = _run(name, [0, *([0] * COUNTER_FAULT_LIMIT), 1, 2])
        assert verdicts[1:COUNTER_FAULT_LIMIT] == ["counter_frozen"] * (COUNTER_FAULT_LIMIT - 1)
        assert verdicts[COUNTER_FAULT_LIMIT:] == ["counter_fault", "ok", "ok"]
        mon = MonitorOracle(ORACLE, [name])
        fid = ORACLE.messages[name].frame_id
        for c in [0, *([0] * COUNTER_FAULT_LIMIT)]:
            mon.process(fid, ORACLE.encode(name, {}, c), 0.0)
        assert mon.valid(name, 0.0) is False  # fault level at the limit: invalid
        mon.process(fid, ORACLE.encode(name, {}, 1), 0.0)
        assert mon.valid(name, 0.0) is True


def test_timeouts_come_from_the_dbc_cycle_times() -> None:
    names = ["SYNC", "WHEEL_TORQUE_CMD", "DRIVER_INPUTS"]
    mon = MonitorOracle(ORACLE, names)
    for name in names:
        info = ORACLE.messages[name]
        assert info.cycle_s == info.message.cycle_time / 1000.0 == 0.01
        assert mon.streams[name].timeout_s == pytest.approx(TIMEOUT_CYCLES * info.cycle_s)
        assert mon.valid(name, 0.0) is False  # never received
        mon.process(info.frame_id, ORACLE.encode(name, {}, 0), 1.0)
        assert mon.valid(name, 1.0 + 0.029) is True
        assert mon.valid(name, 1.0 + 0.0300001) is None  # within the rounding band
        assert mon.valid(name, 1.0 + 0.031) is False
        assert mon.valid(name, float("nan")) is False


def test_the_documented_constants_are_the_readmes() -> None:
    assert TIMEOUT_CYCLES == 3 and "default 3 × cycle" in CAN_DOC
    assert COUNTER_FAULT_LIMIT == 5 and "at 5 the message is invalid" in CAN_DOC


def test_compare_names_each_disagreement() -> None:
    bad = Verdict(False, "bad_crc", "SYNC")
    good = Verdict(True, None, "SYNC", {"CYCLE": 1.0}, 2)
    assert compare(bad, True, None, False, "SYNC", {"CYCLE": 1.0}, 2) == "missed:bad_crc"
    assert compare(bad, False, "bad_crc", False) is None
    assert compare(bad, False, "out_of_range", False) == "reason:bad_crc->out_of_range"
    assert compare(good, False, "counter_frozen", False) == "false_reject:counter_frozen"
    assert compare(good, True, None, False, "SYNC", {"CYCLE": 2.0}, 2) == "value:CYCLE"
    assert compare(good, True, None, False, "SYNC", {"CYCLE": 1.0}, 3) == "counter"
    assert compare(good, True, None, False, "SYNC", {"CYCLE": 1.0}, 2) is None
    assert compare(good, False, None, True) == "ignored"
