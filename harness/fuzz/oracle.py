"""Independent oracles of the CAN input path, for the fuzzers (docs/safety/fuzz.md).

Nothing here runs ``can_db`` code (only the packaged DBC file is located through it): the
expected verdict for a frame comes from other sources than the code under test, so a check
missing from the codec or the rx monitor shows up as a disagreement instead of being
reproduced by the oracle.

* **Signals** — the DBC parsed by cantools (``Message.decode`` with scaling, choices off);
  range validity against the signal minimum/maximum as cantools reads them.
* **E2E CRC** — the ``crcmod`` package, configured from the parameters in
  :data:`E2E_PROFILES` (the DBC's stated algorithm); which profile a message uses is read
  from the DBC (the name of its CRC signal), and where the CRC and the alive counter sit
  from the signals' start bits and lengths.
* **Alive counter** — the documented receiver rules, written out here again
  (:class:`MonitorOracle`).
* **Timeouts** — the DBC cycle time (``GenMsgCycleTime``, cantools ``Message.cycle_time``)
  × :data:`TIMEOUT_CYCLES`, the documented factor; never the monitor's own ``timeout_s``.

Verdict reasons are the documented rejection names (docs/can-matrix.md, "E2E protection"):
``not_data_frame``, ``unknown_id``, ``wrong_length``, ``bad_crc``, ``out_of_range``, then the
receiver's ``counter_frozen``, ``counter_fault``, ``wrong_sequence`` and ``timeout``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import cantools
import crcmod

# ----------------------------------------------------------------- documented constants
# Receiver supervision as documented (docs/can-matrix.md "E2E protection", can_db/monitor.py
# docstring):
TIMEOUT_CYCLES = 3.0        # a message times out after 3 × its DBC cycle time without a frame
COUNTER_FAULT_LIMIT = 5     # at counter fault level 5 the message is invalid (both profiles)
COUNTER_SIGNAL = "ALIVE"    # the 4-bit alive counter of every frame
COUNTER_MODULO = 16
TIME_BAND_S = 1e-6          # |elapsed - timeout| below this: float rounding, not judged
RANGE_BAND_LSB = 1e-6       # a value this close (in LSBs) to a limit counts as inside


@dataclass(frozen=True)
class E2EProfile:
    """One E2E protection profile: CRC algorithm (Rocksoft model, not reflected) and the
    receiver's alive-counter window."""

    crc_signal: str     # name of the CRC signal that marks a message as using this profile
    width: int          # CRC bits
    poly: int           # generator polynomial without its top bit
    init: int           # initial register value
    xor_out: int        # final XOR
    check: int          # CRC of b"123456789" (the catalogue's check value)
    max_delta: int      # largest counter delta accepted (15: any jump)


# Source: the DBC's general comment (CM_ "rhonn-tv CAN matrix: ... E2E on every frame, one of
# two profiles named by the frame's CRC signal ..."), which states each profile's CRC
# algorithm, the covered bytes ([ID >> 8, ID & 0xFF], then the payload bytes after the CRC
# field) and the receiver's counter rule. Both rules share the fault level of the rx monitor
# (can_db/monitor.py docstring, docs/can-matrix.md "E2E protection"): delta 1 lowers it by
# one, any other delta raises it by one, and at COUNTER_FAULT_LIMIT every frame is rejected as
# counter_fault until it decays.
#   CRC8:  CRC-8 SAE J1850 (poly 0x1D, init 0xFF, no reflection, final XOR 0xFF; check 0x4B);
#          any counter jump is accepted (counted as counter_jump), delta 0 rejected
#          (counter_frozen).
#   CRC16: CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, final XOR 0x0000;
#          check 0x29B1); counter-delta window: delta 1..3 accepted (2, 3 counted as
#          counter_jump), delta 0 rejected (counter_frozen), any other delta rejected
#          (wrong_sequence); the receiver resynchronises on the rejected frame's counter.
E2E_PROFILES: dict[str, E2EProfile] = {
    "CRC8": E2EProfile("CRC8", 8, 0x1D, 0xFF, 0xFF, 0x4B, 15),
    "CRC16": E2EProfile("CRC16", 16, 0x1021, 0xFFFF, 0x0000, 0x29B1, 3),
}

def crc_function(profile: E2EProfile) -> Callable[[bytes], int]:
    """The profile's CRC as a crcmod function (crcmod takes the polynomial with its top bit
    and an initial value already XORed with the final XOR)."""
    return crcmod.mkCrcFun((1 << profile.width) | profile.poly,
                           initCrc=profile.init ^ profile.xor_out, rev=False,
                           xorOut=profile.xor_out)


def default_dbc_path() -> Path:
    """The packaged DBC (located here, not through the codec)."""
    return Path(str(resources.files("can_db").joinpath("rhonn_tv.dbc")))


@dataclass(frozen=True)
class SignalInfo:
    """A data signal as cantools reads it, with the raw bounds the generators use."""

    name: str
    minimum: float
    maximum: float
    band: float          # RANGE_BAND_LSB in physical units
    raw_lo: int          # smallest representable raw value
    raw_hi: int          # largest representable raw value
    valid_lo: int        # smallest raw value inside [minimum, maximum]
    valid_hi: int        # largest raw value inside [minimum, maximum]


@dataclass(frozen=True)
class MessageInfo:
    """One message of the DBC as the oracle sees it."""

    name: str
    frame_id: int
    length: int
    cycle_s: float
    profile: E2EProfile
    crc_bytes: tuple[int, int]        # [first, end) byte indices of the CRC field
    covered: tuple[int, ...]          # payload bytes under the CRC
    signals: tuple[SignalInfo, ...]   # data signals (no CRC, no counter)
    message: Any = field(repr=False, compare=False)  # the cantools Message


@dataclass(slots=True)
class Verdict:
    """The oracle's expectation for one frame: accepted (values, counter) or a reason;
    ``ignored`` for a good frame of a message the receiver does not monitor."""

    accepted: bool
    reason: str | None = None
    name: str | None = None
    values: dict[str, float] | None = None
    counter: int | None = None
    jump: bool = False
    ignored: bool = False


def _raw_bounds(sig: Any) -> tuple[int, int, int, int]:
    lo, hi = (-(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1) if sig.is_signed \
        else (0, (1 << sig.length) - 1)
    scale, offset = float(sig.scale), float(sig.offset)
    vlo = max(lo, math.ceil((sig.minimum - offset) / scale - 1e-9))
    vhi = min(hi, math.floor((sig.maximum - offset) / scale + 1e-9))
    return lo, hi, vlo, vhi


def _message_info(message: Any) -> MessageInfo:
    by_name = {s.name: s for s in message.signals}
    crc_names = [n for n in E2E_PROFILES if n in by_name]
    if len(crc_names) != 1 or COUNTER_SIGNAL not in by_name:
        raise ValueError(f"{message.name}: needs one CRC signal of {list(E2E_PROFILES)} "
                         f"and {COUNTER_SIGNAL}")
    profile = E2E_PROFILES[crc_names[0]]
    crc = by_name[profile.crc_signal]
    if crc.byte_order != "little_endian" or crc.start % 8 or crc.length != profile.width:
        raise ValueError(f"{message.name}.{crc.name}: not a byte-aligned {profile.width}-bit "
                         "Intel field")
    first = crc.start // 8
    end = first + profile.width // 8
    signals = []
    for sig in message.signals:
        if sig.name in (profile.crc_signal, COUNTER_SIGNAL):
            continue
        lo, hi, vlo, vhi = _raw_bounds(sig)
        signals.append(SignalInfo(sig.name, float(sig.minimum), float(sig.maximum),
                                  RANGE_BAND_LSB * abs(float(sig.scale)), lo, hi, vlo, vhi))
    return MessageInfo(
        name=message.name, frame_id=message.frame_id, length=message.length,
        cycle_s=(message.cycle_time or 0) / 1000.0, profile=profile,
        crc_bytes=(first, end),
        covered=tuple(i for i in range(message.length) if not first <= i < end),
        signals=tuple(signals), message=message)


class FrameOracle:
    """Stateless expectation for one frame, and a generator of correctly protected frames
    (cantools encodes, crcmod protects)."""

    def __init__(self, dbc_path: str | Path | None = None) -> None:
        self.database = cantools.database.load_file(
            str(dbc_path if dbc_path is not None else default_dbc_path()))
        self.messages: dict[str, MessageInfo] = {}
        self.by_id: dict[int, MessageInfo] = {}
        for message in self.database.messages:
            attributes = message.dbc.attributes if message.dbc is not None else {}
            if any(attributes[a].value == 1 for a in ("DiagRequest", "DiagResponse")
                   if a in attributes):
                continue  # UDS over ISO-TP (docs/diagnostics.md): no E2E to check
            info = _message_info(message)
            self.messages[info.name] = info
            self.by_id[info.frame_id] = info
        self._crc = {name: crc_function(p) for name, p in E2E_PROFILES.items()}

    # ------------------------------------------------------------------ E2E
    def crc(self, info: MessageInfo, frame_id: int, data: bytes | bytearray) -> int:
        """The profile's CRC of ``data`` sent on ``frame_id``."""
        body = bytes((frame_id >> 8 & 0xFF, frame_id & 0xFF, *(data[i] for i in info.covered)))
        return self._crc[info.profile.crc_signal](body)

    def stored_crc(self, info: MessageInfo, data: bytes | bytearray) -> int:
        """The CRC field of ``data`` (Intel byte order)."""
        first, end = info.crc_bytes
        return int.from_bytes(bytes(data[first:end]), "little")

    def protect(self, info: MessageInfo, data: bytes | bytearray,
                frame_id: int | None = None) -> bytes:
        """``data`` with its CRC field set for ``frame_id`` (default: the message's ID)."""
        out = bytearray(data)
        first, end = info.crc_bytes
        fid = info.frame_id if frame_id is None else frame_id
        out[first:end] = self.crc(info, fid, out).to_bytes(end - first, "little")
        return bytes(out)

    def encode(self, name: str, raw: Mapping[str, int], counter: int) -> bytes:
        """A correctly protected frame of ``name`` from raw signal values (missing = 0)."""
        info = self.messages[name]
        values = {s.name: int(raw.get(s.name, 0)) for s in info.signals}
        values[COUNTER_SIGNAL] = counter % COUNTER_MODULO
        values[info.profile.crc_signal] = 0
        data = info.message.encode(values, scaling=False, strict=False)
        return self.protect(info, data)

    # -------------------------------------------------------------- verdict
    def verdict(self, frame_id: int, data: bytes | bytearray, is_extended_id: bool = False,
                is_remote_frame: bool = False, is_error_frame: bool = False,
                is_fd: bool = False) -> Verdict:
        """Expected decoder verdict, checks in the documented order."""
        if is_extended_id or is_remote_frame or is_error_frame or is_fd:
            return Verdict(False, "not_data_frame")
        info = self.by_id.get(frame_id)
        if info is None:
            return Verdict(False, "unknown_id")
        if len(data) != info.length:
            return Verdict(False, "wrong_length", info.name)
        if self.stored_crc(info, data) != self.crc(info, frame_id, data):
            return Verdict(False, "bad_crc", info.name)
        decoded = info.message.decode(bytes(data), decode_choices=False, scaling=True)
        values = {}
        for sig in info.signals:
            v = float(decoded[sig.name])
            if not sig.minimum - sig.band <= v <= sig.maximum + sig.band:
                return Verdict(False, "out_of_range", info.name)
            values[sig.name] = v
        return Verdict(True, None, info.name, values, int(decoded[COUNTER_SIGNAL]))


@dataclass(slots=True)
class _Stream:
    timeout_s: float
    max_delta: int
    last_counter: int | None = None
    level: int = 0
    last_rx_s: float | None = None


class MonitorOracle:
    """Expected rx-monitor behaviour over a sequence of frames and validity probes."""

    def __init__(self, frames: FrameOracle, monitored: Iterable[str]) -> None:
        self.frames = frames
        self.streams: dict[str, _Stream] = {}
        for name in monitored:
            info = frames.messages[name]
            self.streams[name] = _Stream(TIMEOUT_CYCLES * info.cycle_s, info.profile.max_delta)

    def process(self, frame_id: int, data: bytes | bytearray, now_s: float,
                is_extended_id: bool = False, is_remote_frame: bool = False,
                is_error_frame: bool = False, is_fd: bool = False) -> Verdict:
        """Expected verdict of ``RxMonitor.process`` for one frame received at ``now_s``."""
        v = self.frames.verdict(frame_id, data, is_extended_id, is_remote_frame,
                                is_error_frame, is_fd)
        if not v.accepted:
            return v
        stream = self.streams.get(v.name or "")
        if stream is None:
            v.ignored = True
            return v
        reason, v.jump = self._counter(stream, int(v.counter or 0))
        if reason is not None:
            v.accepted, v.reason = False, reason
            return v
        stream.last_rx_s = now_s
        return v

    @staticmethod
    def _counter(s: _Stream, counter: int) -> tuple[str | None, bool]:
        """(rejection reason or None, accepted with frames lost) for the next counter."""
        previous, s.last_counter = s.last_counter, counter  # resynchronise on every frame
        if previous is None:
            return None, False
        delta = (counter - previous) % COUNTER_MODULO
        if delta == 1:
            s.level = max(0, s.level - 1)
            return (None if s.level < COUNTER_FAULT_LIMIT else "counter_fault"), False
        s.level = min(COUNTER_FAULT_LIMIT, s.level + 1)
        if s.level >= COUNTER_FAULT_LIMIT:
            return "counter_fault", False
        if delta == 0:
            return "counter_frozen", False
        if delta > s.max_delta:
            return "wrong_sequence", False
        return None, True

    def valid(self, name: str, now_s: float) -> bool | None:
        """Expected ``RxMonitor.valid``: an accepted frame no older than the DBC timeout and
        a healthy counter. None when ``now_s`` is within TIME_BAND_S of the deadline."""
        s = self.streams[name]
        if s.last_rx_s is None or s.level >= COUNTER_FAULT_LIMIT:
            return False
        elapsed = now_s - s.last_rx_s
        if math.isnan(elapsed):
            return False
        if abs(elapsed - s.timeout_s) <= TIME_BAND_S:
            return None
        return elapsed <= s.timeout_s


def compare(expected: Verdict, accepted: bool, reason: str | None, ignored: bool,
            name: str | None = None, values: Mapping[str, float] | None = None,
            counter: int | None = None) -> str | None:
    """The mismatch kind between the oracle's verdict and the code's, or None.

    ``missed:R`` — the code accepted a frame the oracle rejects for R (a missing check);
    ``false_reject:R`` — the code rejected (R) a frame the oracle accepts;
    ``reason:R->S`` — both reject, for different reasons; ``value:SIG`` / ``counter`` /
    ``name`` — accepted with other contents than cantools decodes; ``ignored`` — ignored
    against the oracle.
    """
    if expected.accepted or expected.ignored:
        if not accepted and not ignored:
            return f"false_reject:{reason}"
        if ignored != expected.ignored:
            return "ignored"
        if ignored:
            return None
        if name != expected.name:
            return "name"
        if counter != expected.counter:
            return "counter"
        exp = expected.values or {}
        got = values or {}
        if set(got) != set(exp):
            return "value:signal set"
        for sig, v in exp.items():
            w = got[sig]
            if not (w == v or abs(w - v) <= 1e-9 * max(1.0, abs(v))):
                return f"value:{sig}"
        return None
    if accepted or ignored:
        return f"missed:{expected.reason}"
    if reason != expected.reason:
        return f"reason:{expected.reason}->{reason}"
    return None
