"""Frame-level fault injection at a sender (harness option ``--fault KIND[:ARG][@T]``).

The plant and the controller each run a :class:`FaultInjector` on their own outgoing frames,
so every fault reaches the receiver through the real bus and the real rx validation. Faults
are seeded and driven by the sender's notion of time (simulated time in lockstep, monotonic
time in real time), so a lockstep run with faults is still reproducible.

Spec grammar: ``KIND[:ARG][@T]`` where ARG is ``AMOUNT[,MESSAGE]`` or ``SIGNAL`` and T is
the start time (``3s``, ``250ms``; default 0). Durations (``burst:200ms``) end the fault.

=================  ==========================================================================
kind               effect on the sender's frames
=================  ==========================================================================
loss:P%[,MSG]      each frame (of MSG, or every frame) dropped with probability P
burst:D[,MSG]      every frame (of MSG) dropped for D starting at T
delay:D[,MSG]      frames held back by D (SYNC and its authenticator are never delayed in
                   lockstep: they are the clock)
jitter:D[,MSG]     each frame held back by a uniform random 0..D (may reorder frames)
crc:P%[,MSG]       CRC byte of each frame inverted with probability P
counter-freeze:MSG alive counter of MSG frozen at its value at T (CRC recomputed: valid frame)
counter-jump:MSG   alive counter of MSG advances by 2 per frame from T (CRC recomputed)
stuck:SIGNAL       SIGNAL (e.g. YAW_RATE) frozen at its value at T (valid CRC and counter)
out-of-range:SIGNAL SIGNAL's raw value set beyond its DBC range from T (valid CRC and counter)
mac-flip:P%[,MSG]  one random MAC bit of each SecOC authenticator (of MSG) flipped with
                   probability P (CRC recomputed: only the MAC check can catch it)
payload-flip:P%[,MSG] one random signal bit of each SecOC-secured frame (of MSG) flipped
                   with probability P (CRC recomputed: E2E passes, only SecOC catches it)
=================  ==========================================================================

Where a fault acts with SecOC on: ``stuck``, ``out-of-range``, ``counter-freeze`` and
``counter-jump`` are faults of the sending node (its sensor, its E2E protection) and act
before it signs its frames (``apply(..., stage="sender")``, the plant does so); the others are
faults of the bus and act after (``stage="bus"``). A sender that applies every fault at once
(``stage="all"``, the controller process) changes already signed frames.

Process-level faults (``kill-controller``, ``kill-plant``, ``restart-controller``,
``restart-plant``, ``restart-bus``), ``flood:RATE`` and the rogue-node attacks
(``rogue-inject``, ``rogue-replay:D``, ``rogue-flood:RATE``, ``rogue-spoof``,
``rogue-sensor-replay:D``, harness/run/rogue.py) are carried
out by the harness (SIGKILL, then a fresh process where it says restart), not here.

Core faults are carried out inside the controller process (controller/runtime/core_fault.py):
``core-exception[:D][@T]`` makes the controller core's ``step``/``allocate_only`` raise from
simulated time T on (for D, or to the end of the run without D); the node's exception handler
then puts the controller into FAULT (controller/runtime/node.py).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import can
import numpy as np

from can_db.codec import COUNTER_MODULO, Codec
from can_db.secoc import SECURED

FRAME_KINDS = {"loss", "burst", "delay", "jitter", "crc", "counter-freeze", "counter-jump",
               "stuck", "out-of-range", "mac-flip", "payload-flip"}
HARNESS_KINDS = {"kill-controller", "kill-plant", "restart-controller", "restart-plant",
                 "restart-bus", "flood", "rogue-inject", "rogue-replay", "rogue-flood",
                 "rogue-spoof", "rogue-sensor-replay"}
CORE_KINDS = {"core-exception"}  # carried out inside the controller process
_AUTH_FRAMES = frozenset(SECURED.values())
_SECURED_FRAMES = frozenset(SECURED)
_CLOCK_FRAMES = frozenset({"SYNC", "SYNC_AUTH"})  # never held back in lockstep: the clock
# Faults of the sending node itself (its sensor or its E2E protection), not of the bus: with
# SecOC they happen before the frame is signed (stage "sender"), the rest after ("bus").
SENDER_KINDS = frozenset({"stuck", "out-of-range", "counter-freeze", "counter-jump"})


class FaultSpecError(ValueError):
    """A ``--fault`` spec that cannot be parsed."""


@dataclass(frozen=True)
class FaultSpec:
    """One parsed fault. Times in s, probabilities 0..1."""

    kind: str
    # probability (loss, crc), seconds (burst, delay, jitter, core-exception: inf = to the
    # end of the run), rate (flood)
    amount: float = 0.0
    target: str | None = None  # message name (frame faults) or signal name (stuck, range)
    at_s: float = 0.0
    text: str = ""

    @property
    def is_frame_fault(self) -> bool:
        """Applied by the sending process (else by the harness)."""
        return self.kind in FRAME_KINDS

    @property
    def is_core_fault(self) -> bool:
        """Carried out inside the controller process, on its core (not on frames)."""
        return self.kind in CORE_KINDS


def _duration_s(text: str) -> float:
    m = re.fullmatch(r"\s*([0-9.]+)\s*(ms|s)?\s*", text)
    if not m:
        raise FaultSpecError(f"bad duration {text!r} (use e.g. 200ms or 3s)")
    try:
        value = float(m.group(1))
    except ValueError:  # e.g. "1.2.3s"
        raise FaultSpecError(f"bad duration {text!r} (use e.g. 200ms or 3s)") from None
    return value / 1000.0 if m.group(2) == "ms" else value


def parse_fault(text: str) -> FaultSpec:
    """Parse ``KIND[:ARG][@T]``; raises FaultSpecError with the reason."""
    body, _, at = text.partition("@")
    kind, _, arg = body.partition(":")
    kind = kind.strip()
    known = FRAME_KINDS | HARNESS_KINDS | CORE_KINDS
    if kind not in known:
        raise FaultSpecError(f"unknown fault kind {kind!r}; known: {', '.join(sorted(known))}")
    at_s = _duration_s(at) if at else 0.0
    amount, target = 0.0, None
    parts = [p.strip() for p in arg.split(",")] if arg else []
    if kind in {"loss", "crc", "mac-flip", "payload-flip"}:
        if not parts or not parts[0].endswith("%"):
            raise FaultSpecError(f"{kind} needs a percentage, e.g. {kind}:10%")
        amount = float(parts[0][:-1]) / 100.0
        if not 0.0 <= amount <= 1.0:
            raise FaultSpecError(f"{kind}: percentage must be 0..100")
        target = parts[1] if len(parts) > 1 else None
    elif kind == "core-exception":  # optional duration; without one: to the end of the run
        if len(parts) > 1:
            raise FaultSpecError(f"{kind} takes at most a duration, e.g. {kind}:200ms@2s")
        amount = _duration_s(parts[0]) if parts else math.inf
        if amount <= 0.0:
            raise FaultSpecError(f"{kind}: duration must be > 0")
    elif kind in {"burst", "delay", "jitter", "rogue-replay", "rogue-sensor-replay"}:
        if not parts:
            if kind in {"rogue-replay", "rogue-sensor-replay"}:
                return FaultSpec(kind, 1.0, None, at_s, text)
            raise FaultSpecError(f"{kind} needs a duration, e.g. {kind}:200ms")
        amount = _duration_s(parts[0])
        target = parts[1] if len(parts) > 1 else None
    elif kind in {"counter-freeze", "counter-jump", "stuck", "out-of-range"}:
        if len(parts) != 1:
            raise FaultSpecError(f"{kind} needs one message/signal name")
        target = parts[0]
    elif kind in {"flood", "rogue-flood"}:
        try:
            amount = float(parts[0]) if parts else (5000.0 if kind == "flood" else 1000.0)
        except ValueError:
            raise FaultSpecError(f"{kind}: rate must be a number of frames/s") from None
    elif parts:
        raise FaultSpecError(f"{kind} takes no argument")
    return FaultSpec(kind, amount, target, at_s, text)


@dataclass
class _Held:
    release_s: float
    order: int
    msg: can.Message


@dataclass
class FaultInjector:
    """Applies frame faults to one sender's outgoing frames."""

    codec: Codec
    faults: list[FaultSpec]
    seed: int = 0
    lockstep: bool = True
    counts: dict[str, int] = field(default_factory=dict)
    _rng: np.random.Generator = field(init=False)
    _held: list[_Held] = field(default_factory=list)
    _order: int = 0
    _frozen_counter: dict[str, int] = field(default_factory=dict)
    _jump_counter: dict[str, int] = field(default_factory=dict)
    _stuck_raw: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self.faults = [f for f in self.faults if f.is_frame_fault]
        names = set(self.codec.messages)
        signals = {s.name for m in self.codec.messages.values() for s in m.signals}
        for f in self.faults:
            if f.kind in {"stuck", "out-of-range"} and f.target not in signals:
                raise FaultSpecError(f"{f.text}: unknown signal {f.target!r}")
            if f.kind not in {"stuck", "out-of-range"} and f.target and f.target not in names:
                raise FaultSpecError(f"{f.text}: unknown message {f.target!r}")
            if f.kind == "out-of-range" and _out_of_range_raw(self.codec, f.target) is None:
                raise FaultSpecError(f"{f.text}: {f.target}'s DBC range fills its raw range")

    def _count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def apply(self, frames: list[can.Message], now_s: float,
              stage: str = "all") -> list[can.Message]:
        """Frames to put on the bus now (held frames whose time has come, in order).
        ``stage``: ``sender`` applies only SENDER_KINDS (before a SecOC sender signs the
        frames), ``bus`` only the others (after), ``all`` every fault."""
        out: list[can.Message] = []
        for msg in frames:
            kept = self._transform(msg, now_s, stage)
            if kept is not None:
                out.append(kept)
        if self._held and stage != "sender":
            due = [h for h in self._held if h.release_s <= now_s + 1e-9]
            if due:
                self._held = [h for h in self._held if h.release_s > now_s + 1e-9]
                due.sort(key=lambda h: (h.release_s, h.order))
                out.extend(h.msg for h in due)
        return out

    def _transform(self, msg: can.Message, now_s: float,
                   stage: str = "all") -> can.Message | None:
        spec = self.codec.by_id.get(msg.arbitration_id)
        name = spec.name if spec is not None else ""
        data = bytearray(msg.data)
        delay = 0.0
        for f in self.faults:
            if now_s + 1e-9 < f.at_s or (f.target and f.kind not in {"stuck", "out-of-range"}
                                         and f.target != name):
                continue
            if stage != "all" and (f.kind in SENDER_KINDS) != (stage == "sender"):
                continue
            kind = f.kind
            if kind == "loss" and self._rng.random() < f.amount:
                self._count("loss")
                return None
            if kind == "burst" and now_s < f.at_s + f.amount:
                self._count("burst")
                return None
            if kind == "crc" and self._rng.random() < f.amount:
                data[0] ^= 0xFF
                self._count("crc")
            elif kind == "counter-freeze":
                cb = spec.counter_start // 8 if spec is not None else 1  # ALIVE's byte
                frozen = self._frozen_counter.setdefault(name, data[cb] & 0x0F)
                data[cb] = (data[cb] & 0xF0) | frozen
                self.codec.seal(msg.arbitration_id, data)
                self._count("counter-freeze")
            elif kind == "counter-jump":
                cb = spec.counter_start // 8 if spec is not None else 1  # ALIVE's byte
                k = self._jump_counter.get(name, data[cb] & 0x0F)
                self._jump_counter[name] = (k + 2) % COUNTER_MODULO
                data[cb] = (data[cb] & 0xF0) | k
                self.codec.seal(msg.arbitration_id, data)
                self._count("counter-jump")
            elif kind in {"mac-flip", "payload-flip"}:
                targets = _AUTH_FRAMES if kind == "mac-flip" else _SECURED_FRAMES
                if (f.target is None and name not in targets) \
                        or self._rng.random() >= f.amount:
                    continue
                # MAC: bits 32..63 of an authenticator; payload: the signal bits after
                # the CRC and the alive counter (from bit 12 or, CRC16 profile, bit 20)
                first = spec.counter_start + 4 if spec is not None else 12
                bit = int(self._rng.integers(32, 64) if kind == "mac-flip"
                          else self._rng.integers(first, 64))
                data[bit // 8] ^= 1 << (bit % 8)
                self.codec.seal(msg.arbitration_id, data)
                self._count(kind)
            elif kind in {"stuck", "out-of-range"} and spec is not None:
                sig = next((s for s in spec.signals if s.name == f.target), None)
                if sig is None:
                    continue
                word = int.from_bytes(data, "little")
                if kind == "stuck":
                    raw = self._stuck_raw.setdefault(f.target or "", (word >> sig.start)
                                                     & sig.mask)
                else:
                    raw = _out_of_range_raw(self.codec, sig.name) or 0
                word = (word & ~(sig.mask << sig.start)) | ((raw & sig.mask) << sig.start)
                data[:] = word.to_bytes(len(data), "little")
                self.codec.seal(msg.arbitration_id, data)
                self._count(kind)
            elif kind == "delay" and not (self.lockstep and name in _CLOCK_FRAMES):
                delay = max(delay, f.amount)
            elif kind == "jitter" and not (self.lockstep and name in _CLOCK_FRAMES):
                delay = max(delay, float(self._rng.uniform(0.0, f.amount)))
        out = can.Message(arbitration_id=msg.arbitration_id, data=bytes(data),
                          is_extended_id=msg.is_extended_id)
        if delay > 0.0:
            self._count("delayed")
            self._order += 1
            self._held.append(_Held(now_s + delay, self._order, out))
            return None
        return out


def _out_of_range_raw(codec: Codec, signal: str | None) -> int | None:
    """A raw value one LSB beyond the signal's DBC range, or None if none is encodable."""
    for spec in codec.messages.values():
        for sig in spec.signals:
            if sig.name != signal:
                continue
            top = (sig.mask >> 1) if sig.signed else sig.mask
            bottom = -(top + 1) if sig.signed else 0
            if sig.raw_max + 1 <= top:
                return sig.raw_max + 1
            if sig.raw_min - 1 >= bottom:
                return sig.raw_min - 1
            return None
    return None


def parse_faults(texts: list[str]) -> list[FaultSpec]:
    """Parse every ``--fault`` option (errors name the offending spec)."""
    return [parse_fault(t) for t in texts]


