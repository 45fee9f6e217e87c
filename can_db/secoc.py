"""SecOC-style authentication of safety-relevant frames (AUTOSAR SecOC profile, simplified).

Threat: the E2E CRC + alive counter catch faults, not attacks. Any node on the bus can send a
WHEEL_TORQUE_CMD — or a sensor frame the controller acts on — with a correct CRC and counter.
With SecOC on, the receiver uses a secured frame only after its *authenticator frame*
verifies. Secured: the torque command and the status (controller → plant), SYNC and the
plant's driver and sensor frames (plant → controller).

Framing (classical CAN, 8-byte frames, see ``rhonn_tv.dbc``): each secured data frame is
followed by a companion authenticator frame (ID = data ID + 1 for the controller's frames,
0x110 for SYNC, 0x111-0x114 for DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST)
carrying the usual CRC8 + alive counter, 20 bits of freshness and a 32-bit
MAC (AES-128-CMAC truncated to its 32 most significant bits, RFC 4493 / SP 800-38B) over::

    data ID (2 bytes, big endian) || data payload (8 bytes) || full freshness value (8 bytes BE)

Freshness value (FV, 64 bit, never the clock): ``trip << 32 | cycle << 8 | sub`` where
``trip`` is the plant's trip counter (persisted, +1 per plant start; the plant is the
freshness master), ``cycle`` the plant's SYNC cycle the frame belongs to (24 bit) and ``sub``
the index of the frame within that cycle for its ID (0 in lockstep). A lockstep run therefore
produces the same MACs run after run.

* SYNC_AUTH (plant → controller) carries the full ``trip`` (TRIP, 20 bit); the cycle is in
  SYNC itself, so the controller knows the full FV: it accepts a SYNC only if the MAC verifies
  and the FV is larger than the last accepted one. A restarted plant starts a higher trip: the
  authenticated SYNC is the resynchronisation (a restarted controller needs no state at all).
* WHEEL_TORQUE_AUTH / CTRL_STATUS_AUTH (controller → plant) carry FV_LO, the low 20 bits of the
  FV (12 bits of cycle, 8 of sub). The plant reconstructs the full FV as the largest value not
  above ``trip << 32 | current cycle << 8 | 0xFF`` with those low bits, verifies the MAC, and
  accepts only a FV above the last accepted one and no older than ``max_age_cycles``
  (the forward window, 10 cycles = 100 ms: it bounds how long a held-back genuine frame stays
  usable; 3 cycles proved too tight for a free-running controller on a loaded machine; a
  4096-cycle reconstruction range classifies older frames).

* DRIVER_INPUTS_AUTH ... VEHICLE_EST_AUTH (plant → controller) carry FV_LO like the
  controller's authenticators; the frames of a burst precede the SYNC that ends it, so the
  controller holds them (data and authenticator frames, in arrival order, per ID) until that
  SYNC is authenticated and then verifies them with the SYNC's trip and cycle: the same
  freshness rules (above the last accepted, within ``max_age_cycles``). As a shortcut, once
  a trip is known, an authenticator is checked on arrival against the held frames of its ID
  with the freshness reconstructed up to ``max_age_cycles`` cycles ahead of the last
  authentic SYNC: a frame that verifies (its MAC covers the full freshness value, trip
  included) is released at once, so the work is not in the SYNC's turnaround; anything else
  waits for the SYNC (the first burst, a new trip after a plant restart, a forgery). A held
  frame that no authenticator verifies is dropped (``unauthenticated``). A frame that fails
  its E2E CRC or length is not held: it goes to the E2E layer at once, which rejects and
  counts it as the fault it is (its authenticator then finds no frame: ``orphan_auth``).

Rejections are counted by reason (:class:`SecRejection`), in total and per secured frame. A
rejected frame never reaches the E2E rx monitor, so it cannot disturb the alive-counter
supervision either; the receiver then behaves exactly as for a missing frame.

Every verdict counts the frames it is about, and each frame is counted once: ``bad_mac``,
``orphan_auth`` and ``unchecked_auth`` count authenticator frames, ``unauthenticated`` data
frames, and ``replay`` / ``stale_freshness`` an authentic pair (a data frame with its
authenticator) once, as ``accepted`` does. So, per secured data frame (the summaries' keys)::

    received                = accepted + replay + stale_freshness + unauthenticated
                              + pending + to_e2e
    authenticators_received = accepted + replay + stale_freshness + bad_mac + orphan_auth
                              + unchecked_auth + pending_authenticators

A SYNC whose authenticator fails (a wrong key) is therefore counted twice in ``rejected``,
once per frame: its authenticator ``bad_mac`` at once, the SYNC itself ``unauthenticated``
when newer SYNCs push it out of the 16 held (the last 16 stay ``pending``). ``to_e2e``: data
frames of a deferred ID passed on unheld because they fail their E2E CRC or length (counted
by the E2E layer).

Keys and the persisted trip counter: can_db/secoc_keys.py.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum

import can
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from can_db.codec import Codec, Decoded, Transmitter
from can_db.secoc_keys import TEST_KEY_SOURCE, TRIP_BITS, SecOcKeys

#: secured data frame -> its authenticator frame
SECURED: dict[str, str] = {
    "WHEEL_TORQUE_CMD": "WHEEL_TORQUE_AUTH",
    "CTRL_STATUS": "CTRL_STATUS_AUTH",
    "SYNC": "SYNC_AUTH",
    "DRIVER_INPUTS": "DRIVER_INPUTS_AUTH",
    "MOTION_SENSORS": "MOTION_SENSORS_AUTH",
    "WHEEL_SPEEDS": "WHEEL_SPEEDS_AUTH",
    "VEHICLE_EST": "VEHICLE_EST_AUTH",
}
CTRL_SECURED = ("WHEEL_TORQUE_CMD", "CTRL_STATUS")  # key ctrl_to_plant
#: the plant's secured frames other than SYNC: verified once their burst's SYNC verifies
PLANT_DATA_SECURED = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")
PLANT_SECURED = ("SYNC", *PLANT_DATA_SECURED)  # key plant_to_ctrl
MAC_BITS = 32
FV_LO_BITS = 20
SUB_BITS = 8
CYCLE_BITS = 24
HISTORY = 4096  # accepted FVs remembered per ID, to tell a replay from a merely stale FV
MAX_AGE_CYCLES = 10  # forward window: oldest answered cycle accepted, cycles of 10 ms
PENDING = 16  # unverified data frames kept per ID while their authenticator is awaited
HELD = 2 * PENDING  # held frames (data + authenticator) per deferred ID until the SYNC



log = logging.getLogger(__name__)


class SecRejection(StrEnum):
    """Why a secured frame was not accepted."""

    BAD_MAC = "bad_mac"  # authenticator does not verify against any pending data frame
    STALE_FRESHNESS = "stale_freshness"  # authentic, but FV not above the last / too old
    REPLAY = "replay"  # authentic, and this FV was already accepted
    UNAUTHENTICATED = "unauthenticated"  # data frame dropped without a valid authenticator
    ORPHAN_AUTH = "orphan_auth"  # authenticator with no data frame to check it against
    UNCHECKED_AUTH = "unchecked_auth"  # held authenticator pushed out before its SYNC verified


#: what the first rejection of a kind most likely means, for its log line
REJECTION_HINT: dict[str, str] = {
    "bad_mac": "the MAC does not verify: the two sides use different keys",
    "stale_freshness": "authentic but not fresh: an old or delayed frame, or a restarted "
                       "sender without its trip-counter file",
    "replay": "authentic and already accepted once: a replayed frame",
    "unauthenticated": "no valid authenticator came with it: the sender does not use SecOC "
                       "(--no-secoc on one side only?) or its authenticator was lost",
    "orphan_auth": "an authenticator with no data frame to check: a lost or rogue frame",
    "unchecked_auth": "an authenticator held for its burst's SYNC was pushed out unchecked: "
                      "no SYNC verifies (the two sides use different keys?) or a flood",
}


# ------------------------------------------------------------------------------- freshness
def freshness(trip: int, cycle: int, sub: int = 0) -> int:
    """Full freshness value: ``trip << 32 | cycle << 8 | sub`` (all masked to their width)."""
    return ((trip & ((1 << TRIP_BITS) - 1)) << 32) | ((cycle & ((1 << CYCLE_BITS) - 1)) << 8) \
        | (sub & ((1 << SUB_BITS) - 1))


def fv_cycle(fv: int) -> int:
    """The cycle field of a freshness value."""
    return (fv >> 8) & ((1 << CYCLE_BITS) - 1)


def reconstruct(fv_lo: int, upper: int) -> int:
    """Largest FV ≤ ``upper`` whose low FV_LO_BITS bits are ``fv_lo`` (may be negative when
    there is none: then it is older than anything acceptable)."""
    return upper - ((upper - fv_lo) % (1 << FV_LO_BITS))


# ---------------------------------------------------------------------------------------- MAC
class MacEngine:
    """AES-128-CMAC truncated to MAC_BITS, keyed once (the per-frame work is a copy)."""

    def __init__(self, key: bytes) -> None:
        self._base = CMAC(algorithms.AES(key))

    def mac(self, frame_id: int, payload: bytes, fv: int) -> int:
        """Truncated MAC (most significant MAC_BITS of the CMAC) over ID, payload, full FV."""
        c = self._base.copy()
        c.update(frame_id.to_bytes(2, "big") + bytes(payload) + fv.to_bytes(8, "big"))
        return int.from_bytes(c.finalize()[: MAC_BITS // 8], "big")


# ------------------------------------------------------------------------------ sender side
class SecOcSender:
    """Builds the authenticator frames of one node's secured frames."""

    def __init__(self, codec: Codec, key: bytes, secured: Iterable[str]) -> None:
        self.codec = codec
        self.engine = MacEngine(key)
        self.tx = Transmitter(codec)
        self.ids = {codec.messages[n].frame_id: n for n in secured}
        self._last: dict[int, tuple[int, int]] = {}  # id -> (cycle, sub) last used
        self.sent = 0

    def protect(self, frames: list[can.Message], trip: int, cycle: int) -> list[can.Message]:
        """``frames`` with an authenticator inserted after every secured frame."""
        out: list[can.Message] = []
        for msg in frames:
            out.append(msg)
            name = self.ids.get(msg.arbitration_id)
            if name is not None:
                out.append(self.authenticator(name, msg, trip, cycle))
        return out

    def authenticator(self, name: str, msg: can.Message, trip: int, cycle: int
                      ) -> can.Message:
        """The authenticator frame of ``msg`` for (trip, cycle); sub counts frames of the
        same ID within one cycle so a FV is never used twice."""
        frame_id = msg.arbitration_id
        last = self._last.get(frame_id)
        sub = last[1] + 1 if last is not None and last[0] == cycle else 0
        self._last[frame_id] = (cycle, sub)
        fv = freshness(trip, cycle, sub)
        tag = self.engine.mac(frame_id, bytes(msg.data), fv)
        self.sent += 1
        auth = SECURED[name]
        if name == "SYNC":
            values = {"TRIP": float(trip & ((1 << TRIP_BITS) - 1)), "MAC": float(tag)}
        else:
            values = {"FV_LO": float(fv & ((1 << FV_LO_BITS) - 1)), "MAC": float(tag)}
        return self.tx.message(auth, values)


# ---------------------------------------------------------------------------- receiver side
@dataclass
class _Stream:
    """Receiver state of one secured data ID."""

    pending: deque[can.Message] = field(default_factory=lambda: deque(maxlen=PENDING))
    last_fv: int = -1
    history: deque[int] = field(default_factory=lambda: deque(maxlen=HISTORY))
    seen: set[int] = field(default_factory=set)

    def remember(self, fv: int) -> None:
        if len(self.history) == self.history.maxlen:
            self.seen.discard(self.history[0])
        self.history.append(fv)
        self.seen.add(fv)
        self.last_fv = fv


class SecOcReceiver:
    """Verifies secured frames before anything else sees them.

    ``feed(msg)`` returns the frame(s) the node may go on to process: unsecured frames at
    once, a secured data frame only when its authenticator has verified (returned when the
    authenticator arrives), nothing for authenticator frames themselves.
    """

    def __init__(self, codec: Codec, key: bytes, secured: Iterable[str], *,
                 max_age_cycles: int = MAX_AGE_CYCLES, deferred: Iterable[str] = ()) -> None:
        secured = tuple(secured)
        self.codec = codec
        self.engine = MacEngine(key)
        self.max_age_cycles = max_age_cycles
        self.data_ids = {codec.messages[n].frame_id: n for n in secured}
        self.auth_ids = {codec.messages[SECURED[n]].frame_id: codec.messages[n].frame_id
                         for n in secured}
        self.streams = {fid: _Stream() for fid in self.data_ids}
        self.counts: dict[str, int] = {r.value: 0 for r in SecRejection}
        self.rejected_by_frame: dict[str, dict[str, int]] = {n: {} for n in secured}
        # deferred data IDs (verified when the SYNC of their burst verifies), and their
        # data and authenticator frames held in arrival order per data ID
        order = tuple(codec.messages[n].frame_id for n in deferred)  # release order
        self.deferred_ids = frozenset(order)
        self._held_of = {fid: data_id for data_id in order
                         for fid in (data_id, codec.messages[SECURED[self.data_ids[data_id]]]
                                     .frame_id)}
        self._held: dict[int, deque[can.Message]] = {fid: deque(maxlen=HELD) for fid in order}
        # the deferred data frames released with the SYNC ``feed`` has just released
        self.released_data: list[can.Message] = []
        self.accepted = 0
        self.accepted_by_frame: dict[str, int] = {n: 0 for n in self.data_ids.values()}
        # secured data frames and authenticators received, per data frame: with the
        # accepted, rejected and still pending ones they account for every such frame
        self.received_by_frame: dict[str, int] = {n: 0 for n in self.data_ids.values()}
        self.auth_received_by_frame: dict[str, int] = {n: 0 for n in self.data_ids.values()}
        # data frames of a deferred ID passed on unheld to the E2E layer (CRC, length)
        self.to_e2e_by_frame: dict[str, int] = {n: 0 for n in self.data_ids.values()}
        self.resyncs = 0
        self.evicted = 0  # pending data frames pushed out by newer ones (flood) unverified
        self.trip: int | None = None  # known trip (own for the plant, learnt for the controller)
        # the decoded SYNC that ``feed`` has just released (decoded for its freshness): the
        # caller need not decode it again; None after any other frame
        self.released_sync: Decoded | None = None
        self.cycle = 0  # the freshest cycle the sender can have answered (plant's own cycle)

    def _count(self, reason: SecRejection, n: int = 1, data_id: int | None = None) -> None:
        name = self.data_ids.get(data_id) if data_id is not None else None
        if not self.counts[reason.value]:  # the first of a kind is logged, the rest counted
            log.warning("SecOC: first rejected %s frame (%s): %s", name or "secured",
                        reason.value, REJECTION_HINT[reason.value])
        self.counts[reason.value] += n
        if name is not None:
            per = self.rejected_by_frame[name]
            per[reason.value] = per.get(reason.value, 0) + n

    def rejections_by_frame(self) -> dict[str, dict[str, int]]:
        """Rejection counts per secured data frame (frames with none left out)."""
        return {k: dict(v) for k, v in self.rejected_by_frame.items() if v}

    def rejection_counts(self) -> dict[str, int]:
        """Non-zero rejection counts by reason."""
        return {k: v for k, v in self.counts.items() if v}

    def is_secured(self, frame_id: int) -> bool:
        """True for a secured data ID or an authenticator ID."""
        return frame_id in self.data_ids or frame_id in self.auth_ids

    def feed(self, msg: can.Message) -> can.Message | None:
        """Process one received frame (see class doc); returns the frame to pass on, if any."""
        self.released_sync = None
        if self.released_data:
            self.released_data = []
        fid = msg.arbitration_id
        held = self._held_of.get(fid)
        if held is not None:  # a deferred frame: kept until its burst's SYNC verifies
            if msg.is_remote_frame or msg.is_error_frame or msg.is_extended_id:
                return msg if fid == held else None  # the E2E layer rejects and counts it
            name = self.data_ids[held]
            if fid == held:
                self.received_by_frame[name] += 1
            else:
                self.auth_received_by_frame[name] += 1
            if fid == held and not self._e2e_intact(msg):
                self.to_e2e_by_frame[name] += 1
                return msg  # corrupted (CRC, length): the E2E layer rejects it as the fault
            if fid != held and self.trip is not None:
                early = self._verify_early(held, msg)
                if early is not None:
                    return early if early is not msg else None
            queue = self._held[held]
            if len(queue) == queue.maxlen:  # the oldest goes: a data frame or authenticator
                self._count(SecRejection.UNAUTHENTICATED if queue[0].arbitration_id == held
                            else SecRejection.UNCHECKED_AUTH, data_id=held)
                self.evicted += 1
            queue.append(msg)
            return None
        if fid in self.data_ids:
            if msg.is_remote_frame or msg.is_error_frame or msg.is_extended_id:
                return msg  # not a data frame: the E2E layer rejects and counts it
            self.received_by_frame[self.data_ids[fid]] += 1
            self._hold_pending(fid, msg)
            return None
        data_id = self.auth_ids.get(fid)
        if data_id is None:
            return msg
        self.auth_received_by_frame[self.data_ids[data_id]] += 1
        return self._check_auth(data_id, msg)

    def pending_by_frame(self) -> dict[str, int]:
        """Data frames neither accepted nor rejected yet, per data frame: waiting for their
        authenticator or, of a deferred ID, held for their burst's SYNC."""
        return {name: len(self.streams[fid].pending)
                + sum(m.arbitration_id == fid for m in self._held.get(fid, ()))
                for fid, name in self.data_ids.items()}

    def pending_auth_by_frame(self) -> dict[str, int]:
        """Authenticators neither accepted nor rejected yet, per data frame: those of a
        deferred ID held for their burst's SYNC (any other is judged on arrival)."""
        return {name: sum(m.arbitration_id != fid for m in self._held.get(fid, ()))
                for fid, name in self.data_ids.items()}

    def frame_accounts(self) -> dict[str, object]:
        """The summaries' per-frame counters, which add up (module doc): received,
        authenticators received, pending data and authenticators, passed to E2E."""
        return {"received": dict(self.received_by_frame),
                "authenticators_received": dict(self.auth_received_by_frame),
                "pending": self.pending_by_frame(),
                "pending_authenticators": self.pending_auth_by_frame(),
                "to_e2e": dict(self.to_e2e_by_frame)}

    def _verify_early(self, data_id: int, auth_msg: can.Message) -> can.Message | None:
        """Verify a deferred frame when its authenticator arrives, with the trip learnt from
        the last authentic SYNC and the freshness reconstructed up to ``max_age_cycles``
        cycles ahead of that SYNC (the burst's own SYNC has not arrived yet). Returns the
        data frame that verified (released now, outside the SYNC's turnaround),
        ``auth_msg`` itself when the verdict is final without a release (authentic but
        replayed or stale: counted), or None when nothing verified: the authenticator is
        then held and judged once the SYNC verifies (a new trip after a plant restart, or a
        forgery)."""
        queue = self._held[data_id]
        if not queue:
            return None
        auth = self.codec.decode_message(auth_msg)
        if not isinstance(auth, Decoded):
            return None
        upper = freshness(self.trip or 0, self.cycle + self.max_age_cycles,
                          (1 << SUB_BITS) - 1)
        fv = reconstruct(int(auth.values["FV_LO"]), upper)
        if fv < 0:
            return None
        tag = int(auth.values["MAC"])
        for msg in queue:
            if msg.arbitration_id != data_id or self.engine.mac(data_id, bytes(msg.data),
                                                                fv) != tag:
                continue
            queue.remove(msg)  # authentic: the verdict is final
            stream = self.streams[data_id]
            if fv in stream.seen:
                self._count(SecRejection.REPLAY, data_id=data_id)
                return auth_msg
            if fv <= stream.last_fv or fv_cycle(fv) + self.max_age_cycles < self.cycle:
                self._count(SecRejection.STALE_FRESHNESS, data_id=data_id)
                return auth_msg
            stream.remember(fv)
            self.accepted += 1
            self.accepted_by_frame[self.data_ids[data_id]] += 1
            return msg
        return None

    def _e2e_intact(self, msg: can.Message) -> bool:
        """True when ``msg`` has its length and its E2E CRC: a frame without them is never
        used, so it goes to the E2E layer at once and is counted there as the fault it is
        (``bad_crc``, ``wrong_length``) rather than waiting to fail its MAC."""
        data = msg.data
        spec = self.codec.by_id[msg.arbitration_id]
        if len(data) != spec.length:
            return False
        width = spec.crc_bits // 8
        return self.codec.e2e_crc(msg.arbitration_id, data) \
            == int.from_bytes(data[:width], "little")

    def _hold_pending(self, data_id: int, msg: can.Message) -> None:
        """Keep a data frame until its authenticator arrives (oldest pushed out, counted)."""
        stream = self.streams[data_id]
        if len(stream.pending) == stream.pending.maxlen:
            self._count(SecRejection.UNAUTHENTICATED, data_id=data_id)
            self.evicted += 1
        stream.pending.append(msg)

    def _check_auth(self, data_id: int, msg: can.Message) -> can.Message | None:
        """Decode an authenticator frame and verify the pending frames of ``data_id``."""
        auth = self.codec.decode_message(msg)
        if not isinstance(auth, Decoded):
            # a corrupted authenticator cannot verify
            self._count(SecRejection.BAD_MAC, data_id=data_id)
            return None
        return self._verify(data_id, auth)

    def _release_held(self) -> list[can.Message]:
        """After an authentic SYNC (``self.trip``, ``self.cycle`` set from it): replay the
        held deferred frames of each ID in arrival order through the usual pending /
        verify steps; returns the frames that verified. Frames left unverified are dropped
        (their burst is over), counted ``unauthenticated``."""
        out: list[can.Message] = []
        for data_id, queue in self._held.items():
            if not queue:
                continue
            for msg in queue:
                if msg.arbitration_id == data_id:
                    self._hold_pending(data_id, msg)
                else:
                    released = self._check_auth(data_id, msg)
                    if released is not None:
                        out.append(released)
            queue.clear()
            stream = self.streams[data_id]
            if stream.pending:
                self._count(SecRejection.UNAUTHENTICATED, len(stream.pending), data_id)
                stream.pending.clear()
        return out

    def _verify(self, data_id: int, auth: Decoded) -> can.Message | None:
        stream = self.streams[data_id]
        if not stream.pending:
            self._count(SecRejection.ORPHAN_AUTH, data_id=data_id)
            return None
        tag = int(auth.values["MAC"])
        name = self.data_ids[data_id]
        new_trip = False
        sync = None
        for msg in stream.pending:
            data = bytes(msg.data)
            if name == "SYNC":
                sync = self.codec.decode(data_id, data)
                if not isinstance(sync, Decoded):
                    continue
                trip = int(auth.values["TRIP"])
                fv = freshness(trip, int(sync.values["CYCLE"]))
            else:
                if self.trip is None:
                    continue
                upper = freshness(self.trip, self.cycle, (1 << SUB_BITS) - 1)
                fv = reconstruct(int(auth.values["FV_LO"]), upper)
                if fv < 0:
                    continue
            if self.engine.mac(data_id, data, fv) != tag:
                continue
            # authentic: now judge its freshness
            stream.pending.remove(msg)
            if fv in stream.seen:
                self._count(SecRejection.REPLAY, data_id=data_id)
                return None
            too_old = name != "SYNC" and fv_cycle(fv) + self.max_age_cycles < self.cycle
            if fv <= stream.last_fv or too_old:
                self._count(SecRejection.STALE_FRESHNESS, data_id=data_id)
                return None
            if name == "SYNC":
                new_trip = self.trip is not None and fv >> 32 != self.trip
                self.trip = fv >> 32
                self.resyncs += int(new_trip)
            if stream.pending:
                self._count(SecRejection.UNAUTHENTICATED, len(stream.pending), data_id)
                stream.pending.clear()
            stream.remember(fv)
            self.accepted += 1
            self.accepted_by_frame[name] += 1
            if name == "SYNC" and self.deferred_ids:
                self.cycle = fv_cycle(fv)
                self.released_data = self._release_held()
            self.released_sync = sync
            return msg
        self._count(SecRejection.BAD_MAC, data_id=data_id)
        return None


# --------------------------------------------------------------------------- node endpoints
class PlantSecOc:
    """The plant's SecOC: freshness master (trip), signs SYNC, verifies torque and status."""

    def __init__(self, codec: Codec, keys: SecOcKeys, trip: int, *,
                 max_age_cycles: int = MAX_AGE_CYCLES) -> None:
        self.keys_source = keys.source
        self.sender = SecOcSender(codec, keys.plant_to_ctrl, PLANT_SECURED)
        self.receiver = SecOcReceiver(codec, keys.ctrl_to_plant, CTRL_SECURED,
                                      max_age_cycles=max_age_cycles)
        self.trip = trip
        self.receiver.trip = trip

    def protect(self, frames: list[can.Message], cycle: int) -> list[can.Message]:
        """Append SYNC_AUTH after SYNC (cycle = the SYNC's cycle)."""
        return self.sender.protect(frames, self.trip, cycle)

    def feed(self, msg: can.Message, cycle: int) -> can.Message | None:
        """Verify a received frame against the plant's current ``cycle``."""
        self.receiver.cycle = cycle
        return self.receiver.feed(msg)

    def summary(self) -> dict[str, object]:
        """Counters for the plant's summary JSON (never any key material)."""
        return {"enabled": True, "trip": self.trip, "keys": _key_label(self.keys_source),
                "accepted": dict(self.receiver.accepted_by_frame),
                "rejected": self.receiver.rejection_counts(),
                "rejected_by_frame": self.receiver.rejections_by_frame(),
                "evicted_unverified": self.receiver.evicted,
                **self.receiver.frame_accounts(),
                "authenticators_sent": self.sender.sent}


class ControllerSecOc:
    """The controller's SecOC: verifies SYNC (learning the trip), signs torque and status."""

    def __init__(self, codec: Codec, keys: SecOcKeys) -> None:
        self.keys_source = keys.source
        self.sender = SecOcSender(codec, keys.ctrl_to_plant, CTRL_SECURED)
        self.receiver = SecOcReceiver(codec, keys.plant_to_ctrl, PLANT_SECURED,
                                      deferred=PLANT_DATA_SECURED)

    @property
    def trip(self) -> int:
        """The plant's trip, learnt from the last authentic SYNC (0 before the first)."""
        return self.receiver.trip or 0

    def feed(self, msg: can.Message) -> can.Message | None:
        """Verify a received frame; returns the frame to process, if any. When it returns
        an authenticated SYNC, ``released_data`` holds the driver and sensor frames of its
        burst that verified (in the order of PLANT_DATA_SECURED, to be processed first)."""
        return self.receiver.feed(msg)

    @property
    def released_data(self) -> list[can.Message]:
        """The burst's verified driver and sensor frames released with the last SYNC."""
        return self.receiver.released_data

    def protect(self, frames: list[can.Message], cycle: int) -> list[can.Message]:
        """Insert the authenticators of the torque and status frames answering ``cycle``."""
        return self.sender.protect(frames, self.trip, max(cycle, 0))

    def summary(self) -> dict[str, object]:
        """Counters for the controller's summary JSON (never any key material)."""
        return {"enabled": True, "trip": self.trip, "keys": _key_label(self.keys_source),
                "accepted": dict(self.receiver.accepted_by_frame), "resyncs": self.receiver.resyncs,
                "rejected": self.receiver.rejection_counts(),
                "rejected_by_frame": self.receiver.rejections_by_frame(),
                "evicted_unverified": self.receiver.evicted,
                **self.receiver.frame_accounts(),
                "authenticators_sent": self.sender.sent}


def _key_label(source: str) -> str:
    """Where the keys came from, for logs (a path, ``env`` or the test-key marker)."""
    return "ci-test-key (PUBLIC, simulation only)" if source == TEST_KEY_SOURCE else source


class SecOcObserver:
    """A passive bus observer holding both keys (``rhonn-bus dump``, offline replay): follows
    the authentic SYNC frames for trip and cycle and verifies the controller's frames as the
    plant would. ``observe`` returns a label for the frame and the data frame an authenticator
    released (None otherwise)."""

    def __init__(self, codec: Codec, keys: SecOcKeys, *,
                 max_age_cycles: int = MAX_AGE_CYCLES) -> None:
        self.codec = codec
        self.sync = SecOcReceiver(codec, keys.plant_to_ctrl, PLANT_SECURED,
                                  deferred=PLANT_DATA_SECURED)
        self.ctrl = SecOcReceiver(codec, keys.ctrl_to_plant, CTRL_SECURED,
                                  max_age_cycles=max_age_cycles)
        self.sync_id = codec.messages["SYNC"].frame_id

    def observe(self, msg: can.Message) -> tuple[str, can.Message | None]:
        """Label: ``unsecured``, ``pending`` (secured data frame awaiting its authenticator;
        also the plant's driver and sensor authenticators, verified with their SYNC or, once
        the trip is known, on arrival: then the data frame they verified is returned),
        ``authenticated 0xID`` or ``REJECTED <reason>`` (for an authenticator)."""
        fid = msg.arbitration_id
        rx = self.sync if self.sync.is_secured(fid) else self.ctrl \
            if self.ctrl.is_secured(fid) else None
        if rx is None:
            return "unsecured", None
        if fid in rx.data_ids or fid in rx._held_of:
            # a deferred authenticator may verify its held data frame at once (the trip is
            # known): that frame is released, the authenticator itself stays "pending"
            released = rx.feed(msg)
            return "pending", released if released is not msg else None
        before = dict(rx.counts)
        released = rx.feed(msg)
        if released is not None:
            if released.arbitration_id == self.sync_id:
                self.ctrl.trip = self.sync.trip
                sync = self.codec.decode_message(released)
                if isinstance(sync, Decoded):
                    self.ctrl.cycle = int(sync.values["CYCLE"])
            return f"authenticated 0x{released.arbitration_id:03X}", released
        reasons = [k for k, v in rx.counts.items() if v > before.get(k, 0)
                   and k != SecRejection.UNAUTHENTICATED.value]
        return f"REJECTED {','.join(reasons) or 'unknown'}", None
