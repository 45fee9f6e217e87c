"""Encode and decode our frames from the DBC, with E2E protection and value validation.

The DBC (``rhonn_tv.dbc``) is parsed with cantools once; the per-frame hot path then packs
and unpacks the little-endian signals itself (all our signals are Intel byte order), which is
several times faster than a generic decoder. Tests cross-check every message against
cantools' own encode/decode.

Two E2E profiles, chosen per message by the DBC: a message with a ``CRC8`` signal (byte 0,
ALIVE in the low nibble of byte 1) uses CRC-8 SAE J1850, one with a ``CRC16`` signal (bytes
0-1, low byte first, ALIVE in the low nibble of byte 2) uses CRC-16/CCITT-FALSE (can_db/crc.py);
both cover the ID as data ID. The rx monitor applies the matching counter check
(can_db/monitor.py).
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from importlib import resources
from pathlib import Path

import can
import cantools

from can_db.codegen import make_decoder, make_encoder
from can_db.crc import frame_crc, frame_crc16, id_seed, id_seed16, word_crc, word_crc16

CRC_SIGNAL = "CRC8"
CRC16_SIGNAL = "CRC16"
CRC_SIGNALS = (CRC_SIGNAL, CRC16_SIGNAL)
COUNTER_SIGNAL = "ALIVE"
COUNTER_MODULO = 16
FRAME_LENGTH = 8
REJECTION_CACHE_SIZE = 4096  # shared Rejected objects for unknown IDs (all 2048 11-bit IDs)


def default_dbc_path() -> Path:
    """Path of the packaged DBC file."""
    return Path(str(resources.files("can_db").joinpath("rhonn_tv.dbc")))


def parsed_dbc(path: Path) -> cantools.database.can.Database:
    """The parsed DBC at ``path``, parsed once per process and file content: a process
    builds several codecs (node, injector, SecOC, recorder, tester, each reset), and the
    parse is most of a codec's construction. Callers only read the database."""
    return _parse_dbc(str(path), hashlib.sha256(path.read_bytes()).hexdigest())


@functools.lru_cache(maxsize=8)
def _parse_dbc(path: str, digest: str) -> cantools.database.can.Database:
    """``digest`` (of the file's bytes) is part of the key: an edited file is parsed again."""
    return cantools.database.load_file(path)


class Rejection(StrEnum):
    """Why a received frame (or a message stream) was not accepted."""

    UNKNOWN_ID = "unknown_id"
    NOT_DATA_FRAME = "not_data_frame"  # remote, error, extended-ID or CAN FD frame
    WRONG_LENGTH = "wrong_length"
    BAD_CRC = "bad_crc"
    OUT_OF_RANGE = "out_of_range"
    COUNTER_FROZEN = "counter_frozen"  # same alive counter as the previous frame: stale data
    COUNTER_JUMP = "counter_jump"  # frames missed; accepted while faults stay below the limit
    COUNTER_FAULT = "counter_fault"  # too many counter faults: frame rejected, message invalid
    # CRC16 profile only: counter delta outside 1..MAX_DELTA_COUNTER (frames lost or
    # inserted): frame rejected, the receiver resynchronises on its counter
    WRONG_SEQUENCE = "wrong_sequence"
    TIMEOUT = "timeout"  # no valid frame within the message timeout (a stream event)


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """One scaled-integer signal: phys = raw * scale + offset, valid in [minimum, maximum]."""

    name: str
    start: int
    length: int
    signed: bool
    scale: float
    offset: float
    minimum: float
    maximum: float
    unit: str
    raw_min: int  # smallest raw value whose physical value is >= minimum
    raw_max: int  # largest raw value whose physical value is <= maximum

    @property
    def mask(self) -> int:
        """Bit mask of the raw value."""
        return (1 << self.length) - 1


@dataclass(frozen=True, slots=True)
class MessageSpec:
    """A frame of the matrix; ``signals`` excludes the CRC and the alive counter."""

    name: str
    frame_id: int
    length: int
    cycle_time_s: float
    senders: tuple[str, ...]
    signals: tuple[SignalSpec, ...]
    crc_bits: int = 8  # E2E profile: 8 (CRC8 signal) or 16 (CRC16 signal)

    @property
    def counter_start(self) -> int:
        """Start bit of the ALIVE counter (right after the CRC)."""
        return self.crc_bits


@dataclass(slots=True)
class Decoded:
    """A validated frame: physical values keyed by signal name, and its alive counter."""

    name: str
    values: dict[str, float]
    counter: int


@dataclass(slots=True)
class Rejected:
    """A frame that failed validation, with the reason and a human-readable detail."""

    reason: Rejection
    frame_id: int
    detail: str


class Codec:
    """Stateless encoder/decoder for every message of the DBC."""

    def __init__(self, dbc_path: str | Path | None = None) -> None:
        self.dbc_path = Path(dbc_path) if dbc_path is not None else default_dbc_path()
        self.database = parsed_dbc(self.dbc_path)
        self.messages: dict[str, MessageSpec] = {}
        self.by_id: dict[int, MessageSpec] = {}
        self._rejections: dict[tuple[Rejection, int], Rejected] = {}
        # diagnostic frames (DiagRequest/DiagResponse in the DBC: ISO-TP, no E2E, no
        # cycle) are not control frames: name -> ID here, outside ``messages``
        self.diagnostic: dict[str, int] = {}
        for message in self.database.messages:
            if is_diagnostic(message):
                self.diagnostic[message.name] = message.frame_id
                continue
            spec = _message_spec(message)
            self.messages[spec.name] = spec
            self.by_id[spec.frame_id] = spec
        # Precomputed packing tables of the hot path: one flat tuple per signal, so a frame
        # is packed or unpacked without attribute look-ups (same arithmetic as the specs).
        self._pack = {spec.name: (spec.frame_id, tuple(
            (g.name, g.minimum, g.maximum, g.offset, g.scale, g.raw_min, g.raw_max, g.mask,
             g.start, min(max(0.0, g.minimum), g.maximum)) for g in spec.signals))
            for spec in self.messages.values()}
        self._unpack = {spec.frame_id: tuple(
            (g.name, g.start, g.mask, (1 << (g.length - 1)) if g.signed else 0,
             1 << g.length, g.scale, g.offset, g.minimum - 1e-9, g.maximum + 1e-9)
            for g in spec.signals) for spec in self.messages.values()}
        # ... and the same arithmetic as one straight-line function per message
        # (can_db/codegen.py): about half the time of the loops over the tables
        self._encoders = {name: (frame_id, make_encoder(table), id_seed(frame_id))
                          for name, (frame_id, table) in self._pack.items()}
        self._decoders = {fid: make_decoder(table) for fid, table in self._unpack.items()}
        # CRC16 profile: (ALIVE start bit, CRC of the packed word from its ID seed, seed)
        # per message name; a CRC8 message has no entry (the path above)
        self._e2e16 = {spec.name: (spec.counter_start, word_crc16, id_seed16(spec.frame_id))
                       for spec in self.messages.values() if spec.crc_bits == 16}
        self._crc16_ids = frozenset(fid for fid, spec in self.by_id.items()
                                    if spec.crc_bits == 16)
        self._seed16 = {fid: id_seed16(fid) for fid in self._crc16_ids}

    def encode(self, name: str, values: Mapping[str, float], counter: int
               ) -> tuple[bytes, tuple[str, ...]]:
        """Pack physical ``values`` into an 8-byte payload with counter and CRC.

        Missing signals encode as 0 (clamped into range). Values outside [min, max] saturate at
        the DBC limit (never wrap); NaN encodes as the in-range value nearest 0. Returns the
        payload and the names of signals that were saturated or non-finite.
        """
        _, encoder, seed = self._encoders[name]
        e2e16 = self._e2e16.get(name)
        if e2e16 is not None:
            shift, crc16, seed16 = e2e16
            word, saturated = encoder(values, (counter % COUNTER_MODULO) << shift)
            return (word | crc16(seed16, word)).to_bytes(FRAME_LENGTH, "little"), saturated
        word, saturated = encoder(values, (counter % COUNTER_MODULO) << 8)
        return (word | word_crc(seed, word)).to_bytes(FRAME_LENGTH, "little"), saturated

    def e2e_crc(self, frame_id: int, data: bytes | bytearray) -> int:
        """The E2E CRC the frame ``data`` of ``frame_id`` must carry (its profile from the
        DBC: CRC-16 for a CRC16 message, else CRC-8)."""
        if frame_id in self._crc16_ids:
            return frame_crc16(frame_id, data)
        return frame_crc(frame_id, data)

    def seal(self, frame_id: int, data: bytearray) -> None:
        """Write the correct E2E CRC into ``data`` in place (after a deliberate change to
        the payload, e.g. an injected fault that must pass the CRC check)."""
        crc = self.e2e_crc(frame_id, data)
        data[0] = crc & 0xFF
        if frame_id in self._crc16_ids:
            data[1] = crc >> 8

    def message(self, name: str, values: Mapping[str, float], counter: int) -> can.Message:
        """Encode into a python-can Message (11-bit ID, classical CAN)."""
        data, _ = self.encode(name, values, counter)
        return can.Message(arbitration_id=self.messages[name].frame_id, data=data,
                           is_extended_id=False)

    def decode(self, frame_id: int, data: bytes | bytearray, *, is_extended_id: bool = False,
               is_remote_frame: bool = False, is_error_frame: bool = False,
               is_fd: bool = False) -> Decoded | Rejected:
        """Validate and decode one frame. Never raises for any input bytes or ID."""
        if is_remote_frame or is_error_frame or is_extended_id or is_fd:
            return self._early_rejection(Rejection.NOT_DATA_FRAME, frame_id)
        spec = self.by_id.get(frame_id)
        if spec is None:
            return self._early_rejection(Rejection.UNKNOWN_ID, frame_id)
        if len(data) != spec.length:
            return Rejected(Rejection.WRONG_LENGTH, frame_id,
                            f"{spec.name}: {len(data)} bytes, expected {spec.length}")
        word = int.from_bytes(data, "little")
        seed16 = self._seed16.get(frame_id)
        if seed16 is not None:  # CRC16 profile: from the payload integer (word_crc16)
            if word_crc16(seed16, word) != word & 0xFFFF:
                return Rejected(Rejection.BAD_CRC, frame_id, f"{spec.name}: CRC mismatch")
        elif frame_crc(frame_id, data) != data[0]:
            return Rejected(Rejection.BAD_CRC, frame_id, f"{spec.name}: CRC mismatch")
        values = self._decoders[frame_id](word)
        if values.__class__ is int:  # the index of the first signal out of range
            sig = spec.signals[values]
            raw = (word >> sig.start) & sig.mask
            if sig.signed and raw & (1 << (sig.length - 1)):
                raw -= 1 << sig.length
            phys = raw * sig.scale + sig.offset
            return Rejected(Rejection.OUT_OF_RANGE, frame_id,
                            f"{spec.name}.{sig.name} = {phys:g} outside "
                            f"[{sig.minimum:g}, {sig.maximum:g}] {sig.unit}")
        return Decoded(spec.name, values, (word >> spec.crc_bits) & 0x0F)

    def _early_rejection(self, reason: Rejection, frame_id: int) -> Rejected:
        """The Rejected for a frame refused before its payload is read: one shared object
        per (reason, ID), so a flood of such frames allocates nothing per frame (treat it
        as read-only). The cache is bounded; beyond it a fresh object is made."""
        key = (reason, frame_id)
        rejected = self._rejections.get(key)
        if rejected is None:
            detail = (f"ID 0x{frame_id:X} not in DBC" if reason is Rejection.UNKNOWN_ID
                      else "not a classical data frame")
            if reason is Rejection.UNKNOWN_ID and frame_id in self.diagnostic.values():
                detail = f"ID 0x{frame_id:X}: diagnostic frame (UDS over ISO-TP), no E2E"
            rejected = Rejected(reason, frame_id, detail)
            if len(self._rejections) < REJECTION_CACHE_SIZE:
                self._rejections[key] = rejected
        return rejected

    def decode_message(self, msg: can.Message) -> Decoded | Rejected:
        """Decode a python-can Message (flags checked)."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            return self._early_rejection(Rejection.NOT_DATA_FRAME, msg.arbitration_id)
        return self.decode(msg.arbitration_id, msg.data)


class Transmitter:
    """Encodes outgoing frames for one node, keeping an alive counter per message."""

    def __init__(self, codec: Codec) -> None:
        self.codec = codec
        self._encoders = codec._encoders
        self._e2e16 = codec._e2e16
        self._counters: dict[str, int] = {}
        self.saturations: dict[str, int] = {}

    def message(self, name: str, values: Mapping[str, float]) -> can.Message:
        """Encode the next frame of ``name``; saturated signals are counted per signal.
        (Codec.encode inlined: this runs for every frame a node sends.)"""
        counters = self._counters
        counter = counters.get(name, 0)
        counters[name] = (counter + 1) % COUNTER_MODULO
        frame_id, encoder, seed = self._encoders[name]
        e2e16 = self._e2e16.get(name)
        if e2e16 is None:
            word, saturated = encoder(values, counter << 8)
            word |= word_crc(seed, word)
        else:
            word, saturated = encoder(values, counter << e2e16[0])
            word |= e2e16[1](e2e16[2], word)
        if saturated:
            for sig in saturated:
                key = f"{name}.{sig}"
                self.saturations[key] = self.saturations.get(key, 0) + 1
        # positional: timestamp, arbitration_id, is_extended_id, is_remote_frame,
        # is_error_frame, channel, dlc, data (keyword passing is measurably slower)
        return can.Message(0.0, frame_id, False, False, False, None, None,
                           word.to_bytes(FRAME_LENGTH, "little"))


def is_diagnostic(message: cantools.database.can.Message) -> bool:
    """True for a diagnostic frame (DBC attribute DiagRequest or DiagResponse = Yes): UDS
    over ISO-TP (docs/diagnostics.md), outside the E2E-protected control frames."""
    attributes = message.dbc.attributes if message.dbc is not None else {}
    return any(name in attributes and attributes[name].value == 1
               for name in ("DiagRequest", "DiagResponse"))


def _message_spec(message: cantools.database.can.Message) -> MessageSpec:
    signals = []
    names = {sig.name for sig in message.signals}
    crcs = [name for name in CRC_SIGNALS if name in names]
    if len(crcs) != 1 or COUNTER_SIGNAL not in names:
        raise ValueError(f"{message.name}: every frame needs one of {CRC_SIGNALS} and "
                         f"{COUNTER_SIGNAL}")
    crc_bits = 16 if crcs[0] == CRC16_SIGNAL else 8
    by_name = {sig.name: sig for sig in message.signals}
    crc_sig, alive = by_name[crcs[0]], by_name[COUNTER_SIGNAL]
    if (crc_sig.start, crc_sig.length, alive.start, alive.length) != (0, crc_bits,
                                                                        crc_bits, 4):
        raise ValueError(f"{message.name}: {crcs[0]} must be bits 0..{crc_bits - 1} and "
                         f"{COUNTER_SIGNAL} the 4 bits after it")
    for sig in message.signals:
        if sig.byte_order != "little_endian":
            raise ValueError(f"{message.name}.{sig.name}: only Intel byte order is supported")
        if sig.name in (*CRC_SIGNALS, COUNTER_SIGNAL):
            continue
        signals.append(SignalSpec(
            name=sig.name, start=sig.start, length=sig.length, signed=sig.is_signed,
            scale=float(sig.scale), offset=float(sig.offset),
            minimum=float(sig.minimum), maximum=float(sig.maximum), unit=sig.unit or "",
            raw_min=math.ceil((sig.minimum - sig.offset) / sig.scale - 1e-9),
            raw_max=math.floor((sig.maximum - sig.offset) / sig.scale + 1e-9)))
    cycle_ms = message.cycle_time or 0
    return MessageSpec(name=message.name, frame_id=message.frame_id, length=message.length,
                       cycle_time_s=cycle_ms / 1000.0, senders=tuple(message.senders),
                       signals=tuple(signals), crc_bits=crc_bits)
