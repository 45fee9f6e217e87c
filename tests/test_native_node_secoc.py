"""Back-to-back tests of the node's C AES-128-CMAC and SecOC (controller/native/node:
node_cmac, node_secoc) against NIST's example vectors, the ``cryptography`` package and the
Python SecOC (can_db/secoc.py).

* CMAC: NIST SP 800-38B, Appendix D.1 (AES-128, key 2b7e1516 28aed2a6 abf71588 09cf4f3c, the
  four examples of 0, 16, 40 and 64 bytes), then seeded random keys and messages of every
  length 0..80 against ``cryptography``'s CMAC (and single AES blocks against its ECB).
* SecOC: freshness, reconstruction and MAC equal to can_db.secoc on random frames; the
  authenticator frames equal SecOcSender's byte for byte; and recorded sequences of genuine,
  forged, corrupted, dropped, delayed and replayed frames give the same verdicts, counts and
  released frames as SecOcReceiver (the plant's receiver of the controller's frames, and the
  controller's receiver of SYNC across plant restarts); the early verdict on a deferred
  stream's authenticator before its SYNC equals SecOcReceiver._verify_early's.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from cryptography.hazmat.primitives.cmac import CMAC

from can_db.codec import Codec, Transmitter
from can_db.secoc import (
    CTRL_SECURED,
    HISTORY,
    PLANT_DATA_SECURED,
    PLANT_SECURED,
    SECURED,
    MacEngine,
    SecOcReceiver,
    SecOcSender,
    freshness,
    reconstruct,
)
from tests.native_node_frames import FrameLayer, build_frame_layer

NIST_KEY = bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")
NIST_MESSAGE = bytes.fromhex(
    "6bc1bee22e409f96e93d7e117393172a"
    "ae2d8a571e03ac9c9eb76fac45af8e51"
    "30c81c46a35ce411e5fbc1191a0a52ef"
    "f69f2445df4f9b17ad2b417be66c3710"
)
# NIST SP 800-38B, Appendix D.1 (AES-128): Mlen in bytes -> T
NIST_EXAMPLES = {
    0: "bb1d6929e95937287fa37d129b756746",
    16: "070a16b46b4d4144f79bdd9dd04a287c",
    40: "dfa66747de9ae63030ca32611497c827",
    64: "51f0bebf7e3b9d92fc49741779363cfe",
}


@pytest.fixture(scope="module")
def layer(tmp_path_factory: pytest.TempPathFactory) -> FrameLayer:
    return build_frame_layer(tmp_path_factory.mktemp("node_secoc"))


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def _key(layer: FrameLayer, key: bytes) -> object:
    ctx = layer.ffi.new("rh_node_cmac_key_t *")
    layer.lib.rh_node_cmac_init(ctx, layer.ffi.new("uint8_t[16]", key))
    return ctx


def _cmac(layer: FrameLayer, key: bytes, message: bytes) -> bytes:
    ffi = layer.ffi
    tag = ffi.new("uint8_t[16]")
    layer.lib.rh_node_cmac_compute(
        _key(layer, key), ffi.new("uint8_t[]", message or b"\0"), len(message), tag
    )
    return bytes(tag)


@pytest.mark.parametrize("length", sorted(NIST_EXAMPLES))
def test_cmac_nist_sp800_38b_appendix_d1(layer: FrameLayer, length: int) -> None:
    assert _cmac(layer, NIST_KEY, NIST_MESSAGE[:length]).hex() == NIST_EXAMPLES[length]


def test_cmac_and_aes_match_cryptography_on_random_inputs(layer: FrameLayer) -> None:
    rng = random.Random("cmac")
    ffi, lib = layer.ffi, layer.lib
    for length in range(81):
        for _ in range(6):
            key, message = rng.randbytes(16), rng.randbytes(length)
            ref = CMAC(algorithms.AES(key))
            ref.update(message)
            assert _cmac(layer, key, message) == ref.finalize()
    for _ in range(300):
        key, block = rng.randbytes(16), rng.randbytes(16)
        round_keys = ffi.new("uint32_t[44]")
        lib.rh_node_cmac_aes_expand(ffi.new("uint8_t[16]", key), round_keys)
        out = ffi.new("uint8_t[16]")
        lib.rh_node_cmac_aes_encrypt(round_keys, ffi.new("uint8_t[16]", block), out)
        enc = Cipher(algorithms.AES(key), modes.ECB()).encryptor()
        assert bytes(out) == enc.update(block) + enc.finalize()


def test_freshness_reconstruct_and_mac_match_python(layer: FrameLayer) -> None:
    rng = random.Random("secoc-mac")
    ffi, lib = layer.ffi, layer.lib
    key = rng.randbytes(16)
    ctx, engine = _key(layer, key), MacEngine(key)
    for _ in range(3000):
        trip, cycle, sub = rng.randrange(1 << 21), rng.randrange(1 << 25), rng.randrange(300)
        fv = freshness(trip, cycle, sub)
        assert lib.rh_node_secoc_freshness(trip, cycle, sub) == fv
        fv_lo = rng.randrange(1 << 20)
        upper = rng.choice((fv, rng.randrange(1 << 20), rng.randrange(1 << 52)))
        assert lib.rh_node_secoc_reconstruct(fv_lo, upper) == reconstruct(fv_lo, upper)
        frame_id = rng.randrange(0x800)
        payload = rng.randbytes(8)
        assert lib.rh_node_secoc_mac(
            ctx, frame_id, ffi.new("uint8_t[8]", payload), 8, fv
        ) == engine.mac(frame_id, payload, fv)


def test_authenticator_frames_match_the_python_sender(layer: FrameLayer, codec: Codec) -> None:
    """Every secured frame, cycles repeating (sub > 0) and advancing, trips changing: the
    authenticator's bytes (FV_LO or TRIP, MAC, CRC, its own alive counter) are equal."""
    rng = random.Random("secoc-tx")
    ffi, lib = layer.ffi, layer.lib
    key = rng.randbytes(16)
    ctx = _key(layer, key)
    sender = SecOcSender(codec, key, SECURED)
    tx = Transmitter(codec)
    states = {name: ffi.new("rh_node_secoc_tx_t *") for name in SECURED}
    for state in states.values():
        lib.rh_node_secoc_tx_init(state)
    trip, cycle = 5, 4090
    for _ in range(3000):
        cycle += rng.choice((0, 0, 1, 1, 2, 300))
        trip += rng.random() < 0.01
        name = rng.choice(tuple(SECURED))
        spec = codec.messages[name]
        msg = tx.message(name, {s.name: rng.uniform(s.minimum, s.maximum) for s in spec.signals})
        expected = sender.authenticator(name, msg, trip, cycle)
        out = ffi.new("uint8_t[8]")
        auth = lib.rh_node_secoc_authenticator(
            states[name],
            ctx,
            layer.message_index[name],
            ffi.new("uint8_t[8]", bytes(msg.data)),
            trip,
            cycle,
            out,
        )
        assert auth == layer.message_index[SECURED[name]]
        assert bytes(out) == bytes(expected.data), (name, trip, cycle)
    out = ffi.new("uint8_t[8]")
    assert (
        lib.rh_node_secoc_authenticator(
            states["SYNC"], ctx, layer.message_index["CTRL_REFS"], ffi.new("uint8_t[8]"), 1, 1, out
        )
        == -1
    )


# ------------------------------------------------------------------------ recorded sequences
@dataclass
class Delivery:
    """One frame on the wire and the receiver's cycle when it arrives."""

    msg: can.Message
    cycle: int


def _reseal(codec: Codec, msg: can.Message, flip_byte: int, flip_bit: int) -> can.Message:
    data = bytearray(msg.data)
    data[flip_byte] ^= 1 << flip_bit
    codec.seal(msg.arbitration_id, data)
    return can.Message(arbitration_id=msg.arbitration_id, data=bytes(data), is_extended_id=False)


def _corrupt(msg: can.Message, rng: random.Random) -> can.Message:
    data = bytearray(msg.data)
    data[rng.randrange(8)] ^= 1 << rng.randrange(8)
    return can.Message(arbitration_id=msg.arbitration_id, data=bytes(data), is_extended_id=False)


def _ctrl_sequence(codec: Codec, key: bytes, rng: random.Random, trip: int) -> Iterator[Delivery]:
    """The controller's secured frames as the plant receives them: genuine pairs, and
    forged, corrupted, dropped, delayed and replayed ones (seeded)."""
    sender = SecOcSender(codec, key, CTRL_SECURED)
    rogue = SecOcSender(codec, key, CTRL_SECURED)  # right key, wrong trip (old recording)
    tx = Transmitter(codec)
    recorded: list[list[can.Message]] = []
    delayed: list[tuple[int, list[can.Message]]] = []
    for cycle in range(1, 700):
        for due, pair in [d for d in delayed if d[0] == cycle]:
            delayed.remove((due, pair))
            yield from (Delivery(m, cycle) for m in pair)
        names = list(CTRL_SECURED) + (["WHEEL_TORQUE_CMD"] if rng.random() < 0.1 else [])
        for name in names:
            spec = codec.messages[name]
            data = tx.message(
                name, {s.name: rng.uniform(s.minimum, s.maximum) for s in spec.signals}
            )
            pair = [data, sender.authenticator(name, data, trip, cycle)]
            recorded.append(pair)
            event = rng.random()
            if event < 0.55:
                out = pair
            elif event < 0.60:  # authenticator lost: the data frame stays pending
                out = [data]
            elif event < 0.63:  # data frame lost: an orphan authenticator
                out = [pair[1]]
            elif event < 0.68:  # forged MAC with a valid CRC
                out = [data, _reseal(codec, pair[1], rng.randrange(4, 8), rng.randrange(8))]
            elif event < 0.71:  # forged payload with a valid CRC, genuine authenticator
                out = [_reseal(codec, data, rng.randrange(2, 8), rng.randrange(8)), pair[1]]
            elif event < 0.74:  # corrupted authenticator (bad CRC)
                out = [data, _corrupt(pair[1], rng)]
            elif event < 0.80:  # held back: arrives late (within or beyond the window)
                delayed.append((cycle + rng.choice((2, 9, 12, 40)), pair))
                out = []
            elif event < 0.90 and recorded:  # a replay of an earlier pair
                old = rng.choice(recorded[-rng.choice((3, 50, 400)) :])
                out = [pair[0], pair[1], *old]
            elif event < 0.93:  # a recording of an earlier trip
                old = rogue.authenticator(name, data, trip - 1, cycle)
                out = [data, old]
            elif event < 0.96:  # authenticator first, then its data frame
                out = [pair[1], data]
            else:  # unsecured frame in between
                out = [tx.message("CTRL_REFS", {}), *pair]
            # the plant's cycle when they arrive: mostly the same, sometimes ahead (at and
            # just beyond the forward window) or one behind
            lag = rng.choice((0, 0, 0, 0, 0, 0, 0, 1, -1, 10, 11))
            yield from (Delivery(m, max(cycle + lag, 0)) for m in out)


def _sync_sequence(codec: Codec, key: bytes, rng: random.Random) -> Iterator[Delivery]:
    """SYNC frames of a plant that restarts (new trip), with replays and old recordings."""
    tx = Transmitter(codec)
    trip = 3
    sender = SecOcSender(codec, key, ("SYNC",))
    recorded: list[list[can.Message]] = []
    cycle = 0
    for _ in range(900):
        if rng.random() < 0.01:  # plant restart: higher trip, cycle from 0
            trip += 1
            cycle = 0
            sender = SecOcSender(codec, key, ("SYNC",))
        cycle += 1
        sync = tx.message("SYNC", {"CYCLE": float(cycle), "SIM_TIME": cycle * 0.01})
        pair = [sync, sender.authenticator("SYNC", sync, trip, cycle)]
        recorded.append(pair)
        event = rng.random()
        if event < 0.7:
            out = pair
        elif event < 0.8 and recorded:
            out = list(rng.choice(recorded[-rng.choice((2, 30, 600)) :]))
        elif event < 0.85:
            out = [sync]
        elif event < 0.9:
            out = [sync, _reseal(codec, pair[1], rng.randrange(4, 8), rng.randrange(8))]
        elif event < 0.95:
            out = [_corrupt(sync, rng), pair[1]]
        else:
            out = [pair[1]]
        yield from (Delivery(m, 0) for m in out)


def _compare(
    layer: FrameLayer,
    codec: Codec,
    receiver: SecOcReceiver,
    key: bytes,
    deliveries: Iterator[Delivery],
    plant_trip: int | None,
) -> dict[str, int]:
    """Feed ``deliveries`` to the Python receiver and to the C streams; per frame, the
    verdict counts and the released frame must be equal, and at the end the streams'
    counts. Returns the verdict totals."""
    ffi, lib = layer.ffi, layer.lib
    assert lib.RH_NODE_SECOC_HISTORY == HISTORY  # both remember as many accepted pairs
    ctx = _key(layer, key)
    rx = ffi.new("rh_node_secoc_rx_t *")
    rx.has_trip, rx.trip = plant_trip is not None, plant_trip or 0
    rx.max_age_cycles = receiver.max_age_cycles
    streams = {}
    for fid in receiver.data_ids:
        streams[fid] = ffi.new("rh_node_secoc_stream_t *")
        lib.rh_node_secoc_stream_init(streams[fid])
    totals: dict[str, int] = {}
    for delivery in deliveries:
        msg = delivery.msg
        fid = msg.arbitration_id
        receiver.cycle = rx.cycle = delivery.cycle
        before = dict(receiver.counts)
        released = receiver.feed(msg)
        expected = {k: v - before[k] for k, v in receiver.counts.items() if v != before[k]}
        got: dict[str, int] = {}
        got_released: bytes | None = None
        data = ffi.new("uint8_t[]", bytes(msg.data) or b"\0")
        if fid in receiver.data_ids:
            if lib.rh_node_secoc_hold(streams[fid], data, len(msg.data)):
                got["unauthenticated"] = 1
        elif fid in receiver.auth_ids:
            data_id = receiver.auth_ids[fid]
            out = ffi.new("rh_node_secoc_result_t *")
            lib.rh_node_secoc_check_auth(
                rx,
                streams[data_id],
                ctx,
                layer.message_index[receiver.data_ids[data_id]],
                data,
                len(msg.data),
                0,
                out,
            )
            verdict = ffi.string(lib.rh_node_secoc_verdict_name(out.verdict)).decode()
            if verdict == "accepted":
                got_released = bytes(out.data)[: out.data_len]
            else:
                got[verdict] = 1
            if out.unauthenticated:
                got["unauthenticated"] = got.get("unauthenticated", 0) + out.unauthenticated
            totals[verdict] = totals.get(verdict, 0) + 1
        else:
            got_released = bytes(msg.data)
        assert got == expected, (hex(fid), bytes(msg.data).hex(), delivery.cycle)
        assert got_released == (bytes(released.data) if released is not None else None)
        if receiver.trip is not None:
            assert rx.has_trip and rx.trip == receiver.trip
    for fid, stream in streams.items():
        py = receiver.streams[fid]
        assert stream.pending_count == len(py.pending)
        assert stream.history_count == len(py.history)
        assert (stream.last_fv if stream.has_last_fv else -1) == py.last_fv
    return totals


def test_plant_receiver_verdicts_match_python(layer: FrameLayer, codec: Codec) -> None:
    rng = random.Random("secoc-plant")
    key = rng.randbytes(16)
    trip = 77
    receiver = SecOcReceiver(codec, key, CTRL_SECURED)
    receiver.trip = trip
    totals = _compare(layer, codec, receiver, key, _ctrl_sequence(codec, key, rng, trip), trip)
    assert set(totals) == {"accepted", "bad_mac", "replay", "stale_freshness", "orphan_auth"}
    assert min(totals.values()) >= 10, totals
    assert receiver.counts["unauthenticated"] > 10


def test_sync_receiver_verdicts_match_python(layer: FrameLayer, codec: Codec) -> None:
    rng = random.Random("secoc-sync")
    key = rng.randbytes(16)
    receiver = SecOcReceiver(codec, key, ("SYNC",))
    totals = _compare(layer, codec, receiver, key, _sync_sequence(codec, key, rng), None)
    assert set(totals) == {"accepted", "bad_mac", "replay", "stale_freshness", "orphan_auth"}
    assert min(totals.values()) >= 10, totals
    assert receiver.resyncs >= 3  # plant restarts were followed


def test_a_short_history_only_turns_old_replays_stale(tmp_path: Path, codec: Codec) -> None:
    """With RH_NODE_SECOC_HISTORY 8 the replay of a pair older than the last 8 accepted is
    STALE_FRESHNESS (rejected all the same); a recent replay is still REPLAY."""
    small = build_frame_layer(tmp_path, ("RH_NODE_SECOC_HISTORY=8u",))
    ffi, lib = small.ffi, small.lib
    key = bytes(range(16))
    ctx = _key(small, key)
    sender, tx = SecOcSender(codec, key, CTRL_SECURED), Transmitter(codec)
    rx = ffi.new("rh_node_secoc_rx_t *")
    rx.has_trip, rx.trip, rx.max_age_cycles = 1, 9, 10
    stream = ffi.new("rh_node_secoc_stream_t *")
    lib.rh_node_secoc_stream_init(stream)
    index = small.message_index["WHEEL_TORQUE_CMD"]
    pairs = []

    def feed(pair: list[can.Message]) -> str:
        lib.rh_node_secoc_hold(stream, ffi.new("uint8_t[8]", bytes(pair[0].data)), 8)
        out = ffi.new("rh_node_secoc_result_t *")
        lib.rh_node_secoc_check_auth(
            rx, stream, ctx, index, ffi.new("uint8_t[8]", bytes(pair[1].data)), 8, 0, out
        )
        return ffi.string(lib.rh_node_secoc_verdict_name(out.verdict)).decode()

    for cycle in range(1, 21):
        rx.cycle = cycle
        data = tx.message("WHEEL_TORQUE_CMD", {})
        pairs.append([data, sender.authenticator("WHEEL_TORQUE_CMD", data, 9, cycle)])
        assert feed(pairs[-1]) == "accepted"
    assert feed(pairs[-3]) == "replay"
    assert feed(pairs[-15]) == "stale_freshness"


def test_early_verification_of_a_deferred_stream_matches_python(
    layer: FrameLayer, codec: Codec
) -> None:
    """A driver-input stream before its burst's SYNC, trip known: genuine pairs at and around
    the receiver's cycle (beyond the forward window too), lost authenticators, orphan and
    forged ones, replays and an old trip's recording. Per authenticator, the C early verdict
    (which held data frame, accepted / replay / stale, or none: held) equals the Python
    receiver's feed; the FV memory ends the same."""
    ffi, lib = layer.ffi, layer.lib
    rng = random.Random("secoc-early")
    key = rng.randbytes(16)
    ctx = _key(layer, key)
    name = "DRIVER_INPUTS"
    data_id = codec.messages[name].frame_id
    totals: dict[str, int] = {}
    for _ in range(60):
        trip, base = 5, rng.randrange(20, 5000)
        receiver = SecOcReceiver(codec, key, PLANT_SECURED, deferred=PLANT_DATA_SECURED)
        receiver.trip, receiver.cycle = trip, base
        rx = ffi.new("rh_node_secoc_rx_t *")
        rx.has_trip, rx.trip, rx.cycle = 1, trip, base
        rx.max_age_cycles = receiver.max_age_cycles
        stream = ffi.new("rh_node_secoc_stream_t *")
        lib.rh_node_secoc_stream_init(stream)
        sender = SecOcSender(codec, key, PLANT_SECURED)
        tx = Transmitter(codec)
        held: list[can.Message] = []  # the data frames the Python receiver holds
        recorded: list[list[can.Message]] = []
        for step in range(10):  # at most 3 frames a step: the Python hold (32) never fills
            cycle = base + rng.choice((-15, -3, 0, 0, 1, step, 9, 10, 11))
            spec = codec.messages[name]
            data = tx.message(
                name, {s.name: rng.uniform(s.minimum, s.maximum) for s in spec.signals}
            )
            pair = [data, sender.authenticator(name, data, trip, cycle)]
            event = rng.random()
            if event < 0.45:
                out = pair
            elif event < 0.55:
                out = [data]
            elif event < 0.62:
                out = [pair[1]]
            elif event < 0.75:
                out = [data, _reseal(codec, pair[1], rng.randrange(4, 8), rng.randrange(8))]
            elif event < 0.9 and recorded:
                out = list(rng.choice(recorded))
            else:
                out = [
                    data,
                    SecOcSender(codec, key, PLANT_SECURED).authenticator(
                        name, data, trip - 1, cycle
                    ),
                ]
            recorded.append(pair)
            for msg in out:
                before = dict(receiver.counts)
                released = receiver.feed(msg)
                delta = {k: v - before[k] for k, v in receiver.counts.items() if v != before[k]}
                if msg.arbitration_id == data_id:
                    held.append(msg)
                    assert released is None and delta == {}
                    continue
                cand = [ffi.new("uint8_t[8]", bytes(m.data)) for m in held]
                res = ffi.new("rh_node_secoc_result_t *")
                hit = lib.rh_node_secoc_verify_early(
                    rx,
                    stream,
                    ctx,
                    layer.message_index[name],
                    ffi.new("uint8_t[8]", bytes(msg.data)),
                    len(msg.data),
                    ffi.new("const uint8_t *[]", cand or [ffi.NULL]),
                    ffi.new("size_t[]", [len(m.data) for m in held] or [0]),
                    len(held),
                    res,
                )
                verdict = ffi.string(lib.rh_node_secoc_verdict_name(res.verdict)).decode()
                if hit < 0:
                    assert released is None and delta == {}  # held for the SYNC
                    verdict = "held"
                elif verdict == "accepted":
                    assert released is not None and delta == {}
                    assert bytes(released.data) == bytes(held[hit].data)
                    assert bytes(res.data)[: res.data_len] == bytes(held[hit].data)
                    del held[hit]
                else:
                    assert released is None and delta == {verdict: 1}
                    del held[hit]
                totals[verdict] = totals.get(verdict, 0) + 1
        py = receiver.streams[data_id]
        assert stream.history_count == len(py.history)
        assert (stream.last_fv if stream.has_last_fv else -1) == py.last_fv
    assert set(totals) == {"accepted", "held", "replay", "stale_freshness"}
    assert min(totals.values()) >= 10, totals
