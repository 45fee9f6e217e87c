"""E2E checksums against an independent bit-by-bit reference: every table entry, the check
values of the CRC catalogue, chaining, and the frame, word and seed helpers on random
frames of every length the code handles."""

from __future__ import annotations

import random

import pytest

from can_db import crc as C  # noqa: N812  (short: the tests read like the formulas)


def ref_crc8(data: bytes, init: int = 0xFF, xor_out: int = 0xFF) -> int:
    """CRC-8/SAE-J1850 bit by bit (poly 0x1D, no reflection)."""
    reg = init
    for b in data:
        reg ^= b
        for _ in range(8):
            reg = ((reg << 1) ^ 0x1D) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
    return reg ^ xor_out


def ref_crc16(data: bytes, init: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE bit by bit (poly 0x1021, no reflection, no final XOR)."""
    reg = init
    for b in data:
        reg ^= b << 8
        for _ in range(8):
            reg = ((reg << 1) ^ 0x1021) & 0xFFFF if reg & 0x8000 else (reg << 1) & 0xFFFF
    return reg


def id_bytes(frame_id: int) -> bytes:
    return bytes(((frame_id >> 8) & 0xFF, frame_id & 0xFF))


RNG = random.Random(20261124)
IDS = [0x000, 0x001, 0x0FF, 0x100, 0x123, 0x2A5, 0x3FF, 0x400, 0x5A5, 0x7FF] + [
    RNG.randrange(0x800) for _ in range(30)]
PAYLOADS = [bytes(RNG.randrange(256) for _ in range(8)) for _ in range(60)] + [
    bytes(8), b"\xff" * 8, bytes(range(8)), bytes(range(248, 256))]


def test_parameters_of_the_catalogue() -> None:
    assert (C.POLY, C.INIT, C.XOR_OUT) == (0x1D, 0xFF, 0xFF)
    assert (C.POLY16, C.INIT16, C.XOR_OUT16) == (0x1021, 0xFFFF, 0x0000)


def test_every_table_entry_matches_the_bitwise_reference() -> None:
    assert len(C.TABLE) == 256 and len(C.TABLE16) == 256
    for b in range(256):
        assert C.TABLE[b] == ref_crc8(bytes([b]), init=0, xor_out=0), b
        assert C.TABLE16[b] == ref_crc16(bytes([b]), init=0), b


def test_check_values() -> None:
    assert C.crc8_j1850(b"123456789") == 0x4B
    assert C.crc16_ccitt_false(b"123456789") == 0x29B1
    assert C.crc8_j1850(b"") == 0x00          # init 0xFF, final XOR 0xFF
    assert C.crc16_ccitt_false(b"") == 0xFFFF


@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 9, 64])
def test_crcs_of_random_data_match_the_reference(n: int) -> None:
    for _ in range(20):
        data = bytes(RNG.randrange(256) for _ in range(n))
        assert C.crc8_j1850(data) == ref_crc8(data)
        assert C.crc8_j1850(bytearray(data)) == ref_crc8(data)
        assert C.crc16_ccitt_false(data) == ref_crc16(data)


def test_chaining_continues_the_running_register() -> None:
    a, b = b"\x12\x34\x56", b"\xab\xcd\xef\x01"
    assert C.crc8_j1850(b, C.crc8_j1850(a) ^ C.XOR_OUT) == C.crc8_j1850(a + b)
    assert C.crc16_ccitt_false(b, C.crc16_ccitt_false(a) ^ C.XOR_OUT16) == \
        C.crc16_ccitt_false(a + b)


def test_frame_crc_covers_the_id_and_the_payload_without_byte_0() -> None:
    for fid in IDS:
        for p in PAYLOADS[:8]:
            want = ref_crc8(id_bytes(fid) + p[1:])
            assert C.frame_crc(fid, p) == want, (hex(fid), p.hex())
            assert C.frame_crc(fid, bytes([p[0] ^ 0xFF]) + p[1:]) == want  # byte 0 excluded


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7, 9, 12])
def test_frame_crc_of_payloads_that_are_not_eight_bytes(n: int) -> None:
    for fid in IDS[:12]:
        p = bytes(RNG.randrange(256) for _ in range(n))
        assert C.frame_crc(fid, p) == ref_crc8(id_bytes(fid) + p[1:])
        assert C.frame_crc(fid, bytearray(p)) == ref_crc8(id_bytes(fid) + p[1:])


def test_a_frame_copied_onto_another_id_fails_the_check() -> None:
    p = PAYLOADS[0]
    crcs = {C.frame_crc(fid, p) for fid in range(0x100, 0x110)}
    assert len(crcs) == 16   # the low ID byte enters the CRC
    crcs = {C.frame_crc(fid << 8, p) for fid in range(8)}
    assert len(crcs) == 8    # and the high ID bits


def test_id_seed_and_word_crc_equal_frame_crc() -> None:
    for fid in IDS:
        seed = C.id_seed(fid)
        assert seed == ref_crc8(id_bytes(fid), xor_out=0)
        for p in PAYLOADS:
            word = int.from_bytes(p, "little")
            assert C.word_crc(seed, word) == C.frame_crc(fid, p) == ref_crc8(id_bytes(fid)
                                                                            + p[1:])


def test_crc16_frame_helpers_equal_the_reference() -> None:
    for fid in IDS:
        seed = C.id_seed16(fid)
        assert seed == ref_crc16(id_bytes(fid))
        for p in PAYLOADS:
            want = ref_crc16(id_bytes(fid) + p[2:])
            assert C.frame_crc16(fid, p) == want, (hex(fid), p.hex())
            assert C.frame_crc16(fid, bytearray(p)) == want
            assert C.word_crc16(seed, int.from_bytes(p, "little")) == want
            # bytes 0-1 (the CRC itself) are excluded
            assert C.frame_crc16(fid, b"\x5a\xa5" + p[2:]) == want


def test_single_bit_flips_change_both_crcs() -> None:
    fid, p = 0x2A5, bytearray(PAYLOADS[1])
    base8, base16 = C.frame_crc(fid, p), C.frame_crc16(fid, p)
    for bit in range(16, 64):
        q = bytearray(p)
        q[bit // 8] ^= 1 << (bit % 8)
        assert C.frame_crc16(fid, q) != base16
        assert C.frame_crc(fid, q) != base8
