"""The two E2E checksums of the matrix, table-driven.

* CRC-8 SAE J1850 (poly 0x1D, init 0xFF, final XOR 0xFF): the checksum of AUTOSAR E2E
  profile 1 and of many OEM CAN matrices; check value of the ASCII string "123456789" 0x4B.
  Byte 0 of a frame of the CRC8 profile.
* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, final XOR 0x0000): the
  polynomial and start value of AUTOSAR E2E profile 5; check value 0x29B1. Bytes 0-1 (low
  byte first) of a frame of the CRC16 profile.

Both run over the data ID (the 11-bit frame ID as two big-endian bytes) and then the payload
bytes after the CRC; which profile a message uses is the DBC's choice (can_db/codec.py).
"""

from __future__ import annotations

POLY = 0x1D
INIT = 0xFF
XOR_OUT = 0xFF


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


TABLE = _make_table()


def crc8_j1850(data: bytes | bytearray, crc: int = INIT) -> int:
    """CRC8 SAE J1850 of ``data``; ``crc`` is the running value before XOR_OUT (for chaining)."""
    for byte in data:
        crc = TABLE[crc ^ byte]
    return crc ^ XOR_OUT


def frame_crc(frame_id: int, payload: bytes | bytearray) -> int:
    """E2E CRC of one of our frames: over [ID high byte, ID low byte, payload[1:8]].

    Byte 0 of the payload is the CRC itself and is excluded; the 11-bit ID is included as two
    big-endian bytes so a frame copied onto another ID fails the check (the ID is the data ID).
    """
    t = TABLE
    crc = t[t[INIT ^ ((frame_id >> 8) & 0xFF)] ^ (frame_id & 0xFF)]
    if len(payload) == 8:  # every frame of the matrix: unrolled, same steps
        return t[t[t[t[t[t[t[crc ^ payload[1]] ^ payload[2]] ^ payload[3]] ^ payload[4]]
                         ^ payload[5]] ^ payload[6]] ^ payload[7]] ^ XOR_OUT
    for byte in payload[1:]:
        crc = t[crc ^ byte]
    return crc ^ XOR_OUT


def id_seed(frame_id: int) -> int:
    """The CRC register after the two ID bytes of ``frame_id`` (for :func:`word_crc`)."""
    return TABLE[TABLE[INIT ^ ((frame_id >> 8) & 0xFF)] ^ (frame_id & 0xFF)]


def word_crc(seed: int, word: int) -> int:
    """:func:`frame_crc` of the 8-byte frame whose little-endian payload is ``word`` (byte 0
    ignored), from its ID's :func:`id_seed`: the same steps on the bytes taken from the
    integer, so an encoder need not build the payload twice (≈ 0.3 µs a frame less)."""
    t = TABLE
    return t[t[t[t[t[t[t[seed ^ ((word >> 8) & 0xFF)] ^ ((word >> 16) & 0xFF)]
                       ^ ((word >> 24) & 0xFF)] ^ ((word >> 32) & 0xFF)]
                 ^ ((word >> 40) & 0xFF)] ^ ((word >> 48) & 0xFF)] ^ ((word >> 56) & 0xFF)] \
        ^ XOR_OUT


# ------------------------------------------------------------------ CRC-16/CCITT-FALSE
# The checksum of the 16-bit E2E profile (AUTOSAR E2E profile 5 uses the same polynomial,
# initial value and no reflection): poly 0x1021, init 0xFFFF, no input/output reflection,
# final XOR 0x0000. The check value of the ASCII string "123456789" is 0x29B1.
POLY16 = 0x1021
INIT16 = 0xFFFF
XOR_OUT16 = 0x0000


def _make_table16() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ POLY16) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table.append(crc)
    return tuple(table)


TABLE16 = _make_table16()


def crc16_ccitt_false(data: bytes | bytearray, crc: int = INIT16) -> int:
    """CRC-16/CCITT-FALSE of ``data``; ``crc`` is the running register (for chaining)."""
    t = TABLE16
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ byte]
    return crc ^ XOR_OUT16


def id_seed16(frame_id: int) -> int:
    """The CRC-16 register after the two data-ID bytes of ``frame_id`` (big endian)."""
    return crc16_ccitt_false(bytes(((frame_id >> 8) & 0xFF, frame_id & 0xFF))) ^ XOR_OUT16


def frame_crc16(frame_id: int, payload: bytes | bytearray) -> int:
    """E2E CRC-16 of a frame of the 16-bit profile: over [ID high byte, ID low byte,
    payload[2:8]]. Bytes 0-1 hold the CRC itself (low byte first, Intel order) and are
    excluded; the 11-bit ID is the data ID, so a frame copied onto another ID fails."""
    return crc16_ccitt_false(bytes(payload[2:]), id_seed16(frame_id))


def word_crc16(seed: int, word: int) -> int:
    """:func:`frame_crc16` of the 8-byte frame whose little-endian payload is ``word``
    (bytes 0-1 ignored), from its ID's :func:`id_seed16`, unrolled over bytes 2..7."""
    t = TABLE16
    crc = ((seed << 8) & 0xFFFF) ^ t[(seed >> 8) ^ ((word >> 16) & 0xFF)]
    crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ ((word >> 24) & 0xFF)]
    crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ ((word >> 32) & 0xFF)]
    crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ ((word >> 40) & 0xFF)]
    crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ ((word >> 48) & 0xFF)]
    crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ ((word >> 56) & 0xFF)]
    return crc ^ XOR_OUT16
