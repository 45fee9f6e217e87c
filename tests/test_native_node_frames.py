"""Back-to-back tests of the node's C frame layer (controller/native/node: node_codec, node_e2e)
against the Python codec (can_db/codec.py, can_db/crc.py, can_db/monitor.py).

Every message of the DBC, seeded random physical values (in range, out of range, NaN,
infinities, rounding ties): the C encoder's bytes and saturated signals equal the Python
codec's. Random, sealed and corrupted frames (bad CRC, wrong length, unknown ID, not a data
frame, out-of-range raw values): the same verdict, and for an accepted frame the same float64
values (exact) and alive counter. Both builds (double and ``-DRH_FLOAT32``): the frame layer
computes in double in both, so both must give the identical results.
"""

from __future__ import annotations

import math
import random
from pathlib import Path

import can
import pytest

from can_db.codec import Codec, Decoded, Rejected
from can_db.crc import crc8_j1850, crc16_ccitt_false, frame_crc, frame_crc16
from can_db.monitor import RxMonitor
from controller.native.node.dbc_gen import generate_sources
from tests.native_node_frames import FrameLayer, build_frame_layer

CASES_PER_MESSAGE = 400
# python-can's frame kinds and the frame layer's flag macros (node_codec.h) that carry them
FLAG_MACROS = {
    "is_extended_id": "RH_NODE_CODEC_FLAG_EXTENDED",
    "is_remote_frame": "RH_NODE_CODEC_FLAG_REMOTE",
    "is_error_frame": "RH_NODE_CODEC_FLAG_ERROR",
    "is_fd": "RH_NODE_CODEC_FLAG_FD",
}


@pytest.fixture(scope="module", params=[(), ("RH_FLOAT32",)], ids=["double", "float32"])
def layer(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> FrameLayer:
    return build_frame_layer(tmp_path_factory.mktemp("node_frames"), request.param)


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec()


def _random_value(rng: random.Random, lo: float, hi: float, scale: float, offset: float) -> float:
    """A physical value of one of the kinds the encoder must treat like the Python codec."""
    kind = rng.randrange(8)
    span = hi - lo
    if kind == 0:
        return rng.uniform(lo, hi)
    if kind == 1:  # beyond the range: saturates
        return rng.choice((hi + rng.uniform(0.0, span + 1.0), lo - rng.uniform(0.0, span + 1.0)))
    if kind == 2:
        return rng.choice((math.nan, math.inf, -math.inf, -0.0, 0.0))
    if kind == 3:  # a rounding tie: (k + 0.5) steps, half to even in both
        k = rng.randrange(int(span / scale) + 1)
        return offset + (math.floor((lo - offset) / scale) + k + 0.5) * scale
    if kind == 4:  # exactly on a limit or one step inside / outside
        return rng.choice((lo, hi, lo + scale, hi - scale, lo - scale, hi + scale))
    if kind == 5:
        return rng.uniform(-1e12, 1e12)
    if kind == 6:  # an integer-valued float (raw counters, IDs)
        return float(rng.randrange(int(lo) - 2, int(hi) + 3))
    return rng.uniform(lo - 1e-9, lo + 1e-9)


def test_every_message_of_the_dbc_is_in_the_c_tables(layer: FrameLayer, codec: Codec) -> None:
    assert sorted(layer.message_index) == sorted(codec.messages)
    lib = layer.lib
    for name, index in layer.message_index.items():
        row = lib.rh_node_dbc_messages[index]
        spec = codec.messages[name]
        assert (row.frame_id, row.length, row.crc_bits, row.n_signals) == (
            spec.frame_id,
            spec.length,
            spec.crc_bits,
            len(spec.signals),
        )
        for k, sig in enumerate(spec.signals):
            c = row.signals[k]
            assert layer.ffi.string(c.name).decode() == sig.name
            assert (c.minimum, c.maximum, c.scale, c.offset, c.raw_min, c.raw_max) == (
                sig.minimum,
                sig.maximum,
                sig.scale,
                sig.offset,
                sig.raw_min,
                sig.raw_max,
            )


def _c_encode(
    layer: FrameLayer, index: int, values: list[float], counter: int
) -> tuple[bytes, int, int]:
    ffi = layer.ffi
    out = ffi.new("uint8_t[8]")
    sat = ffi.new("uint32_t *")
    arr = ffi.new("double[]", values or [0.0])
    status = layer.lib.rh_node_codec_encode(index, arr, counter, out, sat)
    return bytes(out), sat[0], status


@pytest.mark.parametrize("name", sorted(Codec().messages))
def test_encode_matches_python_codec(layer: FrameLayer, codec: Codec, name: str) -> None:
    spec = codec.messages[name]
    index = layer.message_index[name]
    rng = random.Random(f"encode-{name}")
    saturating = 0
    for _ in range(CASES_PER_MESSAGE):
        values = [_random_value(rng, s.minimum, s.maximum, s.scale, s.offset) for s in spec.signals]
        counter = rng.randrange(256)
        expected, saturated = codec.encode(
            name, dict(zip([s.name for s in spec.signals], values, strict=True)), counter
        )
        got, mask, status = _c_encode(layer, index, values, counter)
        assert status == 0
        assert got == expected, (name, values, counter)
        names = tuple(s.name for k, s in enumerate(spec.signals) if mask >> k & 1)
        assert names == saturated
        saturating += bool(saturated)
    assert saturating > CASES_PER_MESSAGE // 4  # the saturating paths were exercised


def test_encode_of_an_unknown_message_is_refused(layer: FrameLayer) -> None:
    out, mask, status = _c_encode(layer, 99, [1.0], 3)
    assert status == -1 and out == bytes(8) and mask == 0
    assert _c_encode(layer, -1, [1.0], 3)[2] == -1
    out = layer.ffi.new("uint8_t[8]", b"\xff" * 8)
    assert layer.lib.rh_node_codec_encode(0, layer.ffi.NULL, 3, out, layer.ffi.NULL) == -1
    assert bytes(out) == bytes(8)


def _c_decode(layer: FrameLayer, frame_id: int, data: bytes, flags: int = 0) -> tuple[str, object]:
    ffi, lib = layer.ffi, layer.lib
    out = ffi.new("rh_node_codec_decoded_t *")
    buf = ffi.new("uint8_t[]", data or b"\0")
    verdict = lib.rh_node_codec_decode(frame_id, buf, len(data), flags, out)
    name = ffi.string(lib.rh_node_e2e_rejection_name(verdict)).decode()
    if name == "ok":
        return name, (out.counter, [out.values[k] for k in range(out.n_values)])
    if name == "out_of_range":
        return name, out.bad_signal
    return name, None


def _flag_bits(layer: FrameLayer) -> dict[str, int]:
    """The flag bit of each python-can frame kind, as the frame layer's header defines it."""
    return {key: getattr(layer.lib, macro) for key, macro in FLAG_MACROS.items()}


def _py_decode(
    codec: Codec, bits: dict[str, int], frame_id: int, data: bytes, flags: int = 0
) -> tuple[str, object]:
    kinds = {key: bool(flags & bit) for key, bit in bits.items()}
    result = codec.decode(frame_id, data, **kinds)
    if isinstance(result, Decoded):
        spec = codec.by_id[frame_id]
        return "ok", (result.counter, [result.values[s.name] for s in spec.signals])
    assert isinstance(result, Rejected)
    if result.reason.value == "out_of_range":
        spec = codec.by_id[frame_id]
        bad = result.detail.split(" = ")[0].split(".")[1]
        return result.reason.value, [s.name for s in spec.signals].index(bad)
    return result.reason.value, None


def _frames(
    codec: Codec, bits: dict[str, int], rng: random.Random, count: int
) -> list[tuple[int, bytes, int]]:
    """Random frames of every kind: random bytes, sealed random bytes (good CRC, any raw
    value), valid encodings, single bit flips of them, wrong lengths, unknown IDs, flags
    (one of ``bits``)."""
    ids = [spec.frame_id for spec in codec.messages.values()]
    frames = []
    for _ in range(count):
        frame_id = rng.choice(ids)
        spec = codec.by_id[frame_id]
        kind = rng.randrange(7)
        data = bytearray(rng.randbytes(8))
        flags = 0
        if kind in (1, 2, 3):
            codec.seal(frame_id, data)
        if kind == 2:  # a valid frame from physical values
            values = {s.name: rng.uniform(s.minimum, s.maximum) for s in spec.signals}
            data = bytearray(codec.encode(spec.name, values, rng.randrange(16))[0])
        if kind == 3:  # one bit flipped after sealing: a bad CRC
            data[rng.randrange(8)] ^= 1 << rng.randrange(8)
        if kind == 4:
            data = data[: rng.choice((0, 1, 5, 7))] if rng.random() < 0.8 else data + b"\x00"
            codec.seal(frame_id, data) if len(data) == 8 else None
        if kind == 5:
            frame_id = rng.choice((rng.randrange(0x800), 0x7E0, 0x7E8, 0x1FFFFFFF))
        if kind == 6:
            codec.seal(frame_id, data)
            flags = rng.choice(tuple(bits.values()))
        frames.append((frame_id, bytes(data), flags))
    return frames


def test_decode_matches_python_codec(layer: FrameLayer, codec: Codec) -> None:
    rng = random.Random("decode")
    verdicts: dict[str, int] = {}
    bits = _flag_bits(layer)
    assert len(set(bits.values())) == len(bits)  # one bit of its own per kind
    assert all(b > 0 and b & (b - 1) == 0 for b in bits.values())
    for frame_id, data, flags in _frames(codec, bits, rng, 20000):
        expected = _py_decode(codec, bits, frame_id, data, flags)
        got = _c_decode(layer, frame_id, data, flags)
        assert got == expected, (hex(frame_id), data.hex(), flags)
        verdicts[expected[0]] = verdicts.get(expected[0], 0) + 1
    # every verdict of the codec was met, each many times
    assert set(verdicts) == {
        "ok",
        "bad_crc",
        "out_of_range",
        "wrong_length",
        "unknown_id",
        "not_data_frame",
    }
    assert min(verdicts.values()) > 200, verdicts


def test_decoded_values_are_the_encoded_values_exactly(layer: FrameLayer, codec: Codec) -> None:
    """Every raw value of every signal at its limits decodes to the Python float exactly."""
    for name, spec in codec.messages.items():
        for s in spec.signals:
            for phys in (s.minimum, s.maximum, s.minimum + s.scale, s.maximum - s.scale):
                values = {g.name: (phys if g is s else 0.0) for g in spec.signals}
                data, _ = codec.encode(name, values, 7)
                assert _c_decode(layer, spec.frame_id, data) == _py_decode(
                    codec, _flag_bits(layer), spec.frame_id, data
                )


def test_crc_check_values_and_frames(layer: FrameLayer) -> None:
    lib, ffi = layer.lib, layer.ffi
    check = ffi.new("uint8_t[]", b"123456789")
    assert lib.rh_node_e2e_crc8_bytes(check, 9) == 0x4B == crc8_j1850(b"123456789")
    assert lib.rh_node_e2e_crc16_bytes(check, 9) == 0x29B1 == crc16_ccitt_false(b"123456789")
    rng = random.Random("crc")
    for _ in range(2000):
        frame_id = rng.randrange(0x800)
        data = rng.randbytes(8)
        buf = ffi.new("uint8_t[8]", data)
        assert lib.rh_node_e2e_crc8(frame_id, buf) == frame_crc(frame_id, data)
        assert lib.rh_node_e2e_crc16(frame_id, buf) == frame_crc16(frame_id, data)
        raw = rng.randbytes(rng.randrange(20))
        assert lib.rh_node_e2e_crc8_bytes(
            ffi.new("uint8_t[]", raw or b"\0"), len(raw)
        ) == crc8_j1850(raw)


@pytest.mark.parametrize("name", ["DRIVER_INPUTS", "WHEEL_TORQUE_AUTH"])
def test_alive_counter_check_matches_rx_monitor(layer: FrameLayer, codec: Codec, name: str) -> None:
    """The counter verdicts of both profiles (CRC16 window, CRC8 jumps) on random counter
    sequences with repeats, jumps and runs, through the Python RxMonitor's process()."""
    ffi, lib = layer.ffi, layer.lib
    spec = codec.messages[name]
    rng = random.Random(f"counter-{name}")
    seen: set[str] = set()
    for _ in range(40):
        monitor = RxMonitor(codec, [name])
        state = ffi.new("rh_node_e2e_counter_t *")
        lib.rh_node_e2e_counter_init(state, spec.crc_bits == 16)
        counter = rng.randrange(16)
        for _ in range(60):
            step = rng.choice((1, 1, 1, 0, 2, 3, 4, rng.randrange(16)))
            counter = (counter + step) % 16
            data, _ = codec.encode(name, {}, counter)
            jumps = monitor.counts["counter_jump"]
            result = monitor.process(
                can.Message(arbitration_id=spec.frame_id, data=data, is_extended_id=False), 0.0
            )
            if isinstance(result, Rejected):
                expected = result.reason.value
            else:
                expected = "counter_jump" if monitor.counts["counter_jump"] > jumps else "ok"
            verdict = lib.rh_node_e2e_check_counter(state, counter, monitor.counter_fault_limit)
            got = ffi.string(lib.rh_node_e2e_rejection_name(verdict)).decode()
            assert got == expected
            seen.add(got)
    wanted = {"ok", "counter_jump", "counter_frozen", "counter_fault"}
    if spec.crc_bits == 16:
        wanted.add("wrong_sequence")
    assert seen == wanted


def test_generated_tables_are_not_committed() -> None:
    node = Path(__file__).resolve().parents[1] / "controller" / "native" / "node"
    assert not (node / "node_dbc.h").exists() and not (node / "rh_node_dbc_pack.c").exists()


def test_generation_is_reproducible(tmp_path: Path) -> None:
    """The same DBC gives the same generated bytes (cantools' time stamp is dropped)."""
    first = generate_sources(tmp_path / "a")
    second = generate_sources(tmp_path / "b")
    assert [p.name for p in first] == [p.name for p in second]
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(first, second, strict=True))
    assert b"cantools version" in first[0].read_bytes()  # cantools did generate it
