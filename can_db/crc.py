"""CRC8 SAE J1850 (poly 0x1D, init 0xFF, final XOR 0xFF), table-driven.

This is the checksum of AUTOSAR E2E profile 1 and of many OEM CAN matrices. The check value
of the ASCII string "123456789" is 0x4B.
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
