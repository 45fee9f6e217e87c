"""Receiver-side supervision of message streams (opendbc/panda style).

Per monitored message: a timeout (default 3 x the DBC cycle time), alive-counter continuity
with a tolerance (each counter fault raises a fault level by one, each good frame lowers it by
one; at ``counter_fault_limit`` the message is invalid and its frames are rejected until the
level decays), a ``valid`` flag, and counts of every rejection by reason. Time is passed in by
the caller (simulated or monotonic seconds), so the monitor itself never reads a clock.

The counter check follows the message's E2E profile (the DBC's CRC signal): a CRC8 message
accepts any counter jump (counted) while its fault level stays below the limit; a CRC16
message applies a counter-delta window (AUTOSAR E2E profile 5's MaxDeltaCounter =
``MAX_DELTA_COUNTER`` = 3, the rx timeout in cycles): delta 1 is good, delta 2 or 3 is
accepted as one or two frames lost (``counter_jump``), delta 0 is a repetition
(``counter_frozen``) and any other delta a wrong sequence (``wrong_sequence``), rejected; the
stored counter is the received one, so the next frame resynchronises.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import can

from can_db.codec import COUNTER_MODULO, Codec, Decoded, Rejected, Rejection

# CRC16 profile: largest counter delta accepted. 3 = the rx timeout in cycles: two frames
# lost in a row cost no third (at 10 % loss 97 % of the cycles stay ACTIVE with SecOC on, 95 %
# with 2), and a random frame still passes at ≤ 2^-16 · 3/16 = 2.9e-6 (docs/safety/e2e.md).
MAX_DELTA_COUNTER = 3


@dataclass(slots=True)
class StreamState:
    """Supervision state of one message stream."""

    timeout_s: float
    window: bool = False  # CRC16 profile: counter-delta window (see the module doc)
    last_rx_s: float | None = None
    last_counter: int | None = None
    counter_fault_level: int = 0
    timed_out_reported: bool = False
    latest: Decoded | None = None
    received: int = 0
    accepted: int = 0
    rejections: dict[str, int] = field(default_factory=dict)


class RxMonitor:
    """Validates received frames for one node and tracks per-message validity."""

    def __init__(self, codec: Codec, monitored: Iterable[str], *, timeout_factor: float = 3.0,
                 counter_fault_limit: int = 5,
                 timeouts_s: dict[str, float] | None = None) -> None:
        self.codec = codec
        self.counter_fault_limit = counter_fault_limit
        self.streams: dict[str, StreamState] = {}
        for name in monitored:
            spec = codec.messages[name]
            timeout = (timeouts_s or {}).get(name, timeout_factor * spec.cycle_time_s)
            self.streams[name] = StreamState(timeout_s=timeout, window=spec.crc_bits == 16)
        self.counts: dict[str, int] = {reason.value: 0 for reason in Rejection}
        self.ignored = 0  # valid frames of known messages this node does not monitor

    def process(self, msg: can.Message, now_s: float,
                decoded: Decoded | Rejected | None = None) -> Decoded | Rejected | None:
        """Validate one received frame at time ``now_s`` (s).

        Returns the decoded frame when accepted, a Rejected with the reason otherwise, and
        None for a well-formed frame of a message this node does not monitor. ``decoded``:
        ``codec.decode_message(msg)`` when the caller already has it (not decoded twice).
        """
        result = self.codec.decode_message(msg) if decoded is None else decoded
        if isinstance(result, Rejected):
            self._count(result.reason, self._stream_of(result.frame_id))
            return result
        stream = self.streams.get(result.name)
        if stream is None:
            self.ignored += 1
            return None
        stream.received += 1
        verdict = self._check_counter(stream, result.counter)
        if verdict is not None:
            self._count(verdict, stream)
            if verdict is not Rejection.COUNTER_JUMP:
                return Rejected(verdict, msg.arbitration_id,
                                f"{result.name}: alive counter {result.counter}")
        stream.last_rx_s = now_s
        stream.timed_out_reported = False
        stream.latest = result
        stream.accepted += 1
        return result

    def _check_counter(self, stream: StreamState, counter: int) -> Rejection | None:
        """The alive-counter check of both profiles (module doc): delta 1 lowers the fault
        level, any other delta raises it; below the limit a repeated counter is stale, and a
        jump is accepted (counted) unless the CRC16 window rejects it."""
        previous = stream.last_counter
        stream.last_counter = counter
        if previous is None:
            return None
        delta = (counter - previous) % COUNTER_MODULO
        limit = self.counter_fault_limit
        if delta == 1:
            stream.counter_fault_level = max(0, stream.counter_fault_level - 1)
            return None if stream.counter_fault_level < limit else Rejection.COUNTER_FAULT
        stream.counter_fault_level = min(limit, stream.counter_fault_level + 1)
        if stream.counter_fault_level >= limit:
            return Rejection.COUNTER_FAULT
        if delta == 0:
            return Rejection.COUNTER_FROZEN
        if stream.window and delta > MAX_DELTA_COUNTER:
            return Rejection.WRONG_SEQUENCE
        return Rejection.COUNTER_JUMP

    def valid(self, name: str, now_s: float) -> bool:
        """True when ``name`` has a fresh, accepted frame and its counter is healthy."""
        stream = self.streams[name]
        if stream.last_rx_s is None or stream.counter_fault_level >= self.counter_fault_limit:
            return False
        # written as "not <=" so a NaN time (a caller's bug) counts as timed out, never valid
        if not now_s - stream.last_rx_s <= stream.timeout_s + 1e-9:  # + float rounding
            if not stream.timed_out_reported:
                stream.timed_out_reported = True
                self._count(Rejection.TIMEOUT, stream)
            return False
        return True

    def all_valid(self, names: Iterable[str], now_s: float) -> bool:
        """True when every message in ``names`` is valid (each one is checked and counted)."""
        ok = True
        for name in names:
            ok = self.valid(name, now_s) and ok
        return ok

    def latest(self, name: str) -> Decoded | None:
        """Most recent accepted frame of ``name`` (may be stale: check ``valid``)."""
        return self.streams[name].latest

    def _stream_of(self, frame_id: int) -> StreamState | None:
        spec = self.codec.by_id.get(frame_id)
        return self.streams.get(spec.name) if spec is not None else None

    def _count(self, reason: Rejection, stream: StreamState | None) -> None:
        self.counts[reason.value] += 1
        if stream is not None:
            stream.rejections[reason.value] = stream.rejections.get(reason.value, 0) + 1

    def rejection_counts(self) -> dict[str, int]:
        """Non-zero rejection counts by reason."""
        return {k: v for k, v in self.counts.items() if v}
