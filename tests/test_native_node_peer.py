"""End to end across processes: a miniature controller node built on the C frame layer
(tests/native_node_peer.c, its own process) talks to the Python plant side through pipes.

The Python side sends DRIVER_INPUTS and authenticated SYNC frames (can_db.codec, can_db.secoc)
with faults spliced in (a bad CRC, a repeated alive counter, a forged SYNC authenticator, a
replayed SYNC pair); the C node answers every authentic SYNC with WHEEL_TORQUE_CMD and its
authenticator. Checked: the C node's verdict on every frame equals the Python receivers'
(RxMonitor, SecOcReceiver), and the plant's SecOC receiver accepts every answer, whose bytes
equal what the Python codec and SecOC sender make of the same values.
"""

from __future__ import annotations

import random
import subprocess
from pathlib import Path

import can
import pytest

from can_db.codec import Codec, Decoded, Rejected, Transmitter
from can_db.monitor import RxMonitor
from can_db.secoc import CTRL_SECURED, SecOcReceiver, SecOcSender
from controller.native.build_tools import CFLAGS, find_compiler
from controller.native.node.dbc_gen import NODE_DIR, frame_layer_sources

PEER_SOURCE = Path(__file__).resolve().parent / "native_node_peer.c"
CYCLES = 80
TRIP = 12


@pytest.fixture(scope="module")
def peer(tmp_path_factory: pytest.TempPathFactory) -> Path:
    build = tmp_path_factory.mktemp("node_peer")
    gen = build / "generated"
    sources = [*frame_layer_sources(gen), PEER_SOURCE]
    exe = build / "node_peer"
    cmd = [
        find_compiler(),
        *CFLAGS,
        f"-I{NODE_DIR}",
        f"-I{gen}",
        *map(str, sources),
        "-o",
        str(exe),
        "-lm",
    ]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return exe


def _line(msg: can.Message) -> str:
    return f"{msg.arbitration_id:03X} {bytes(msg.data).hex() or '-'}"


def _flip_resealed(codec: Codec, msg: can.Message, byte: int) -> can.Message:
    data = bytearray(msg.data)
    data[byte] ^= 0x10
    codec.seal(msg.arbitration_id, data)
    return can.Message(arbitration_id=msg.arbitration_id, data=bytes(data), is_extended_id=False)


def _plant_frames(codec: Codec, key: bytes, rng: random.Random) -> list[can.Message]:
    """The plant's bursts: DRIVER_INPUTS then SYNC and SYNC_AUTH, faults at fixed cycles."""
    tx = Transmitter(codec)
    sender = SecOcSender(codec, key, ("SYNC",))
    frames: list[can.Message] = []
    previous_pair: list[can.Message] = []
    for cycle in range(1, CYCLES + 1):
        driver = tx.message("DRIVER_INPUTS", {"ACCEL_PEDAL": rng.uniform(0.0, 100.0)})
        if cycle == 10:  # a bit flip on the wire: bad CRC
            data = bytearray(driver.data)
            data[5] ^= 0x04
            driver = can.Message(
                arbitration_id=driver.arbitration_id, data=bytes(data), is_extended_id=False
            )
        frames.append(driver)
        if cycle == 40:  # the same frame twice: a frozen alive counter
            frames.append(driver)
        sync = tx.message("SYNC", {"CYCLE": float(cycle), "SIM_TIME": cycle * 0.01})
        pair = [sync, sender.authenticator("SYNC", sync, TRIP, cycle)]
        if cycle == 20:  # a forged MAC with a valid CRC: no answer this cycle
            pair[1] = _flip_resealed(codec, pair[1], 6)
        frames += pair
        if cycle == 30:  # the previous cycle's pair again: a replay
            frames += previous_pair
        previous_pair = pair
    return frames


def _python_verdicts(codec: Codec, key: bytes, frames: list[can.Message]) -> list[str]:
    """What the Python controller side says of each frame (the C node's vocabulary)."""
    secoc = SecOcReceiver(codec, key, ("SYNC",))
    monitor = RxMonitor(codec, ["DRIVER_INPUTS"])
    verdicts = []
    for msg in frames:
        if msg.arbitration_id in secoc.data_ids:
            assert secoc.feed(msg) is None
            verdicts.append("held")
        elif msg.arbitration_id in secoc.auth_ids:
            before = dict(secoc.counts)
            released = secoc.feed(msg)
            grew = [k for k, v in secoc.counts.items() if v > before[k] and k != "unauthenticated"]
            verdicts.append("accepted" if released is not None else ",".join(grew))
        else:
            jumps = monitor.counts["counter_jump"]
            result = monitor.process(msg, 0.0)
            if isinstance(result, Rejected):
                verdicts.append(result.reason.value)
            else:
                verdicts.append("counter_jump" if monitor.counts["counter_jump"] > jumps else "ok")
    return verdicts


def test_c_node_answers_the_python_plant_across_processes(peer: Path) -> None:
    codec = Codec()
    rng = random.Random("peer")
    key_p2c, key_c2p = rng.randbytes(16), rng.randbytes(16)
    frames = _plant_frames(codec, key_p2c, rng)
    proc = subprocess.run(
        [str(peer), key_p2c.hex(), key_c2p.hex()],
        input="".join(_line(m) + "\n" for m in frames),
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    lines = proc.stdout.splitlines()
    rx = [line.split() for line in lines if line.startswith("RX ")]
    sent = [line.split() for line in lines if line.startswith("TX ")]

    # the C node's verdict on every frame is the Python receivers'
    assert [int(r[1], 16) for r in rx] == [m.arbitration_id for m in frames]
    expected = _python_verdicts(codec, key_p2c, frames)
    assert [r[2] for r in rx] == expected
    assert {"bad_crc", "counter_frozen", "bad_mac", "replay"} <= set(expected)

    # every answer verifies at the plant, and is the bytes the Python side would send
    plant = SecOcReceiver(codec, key_c2p, CTRL_SECURED)
    plant.trip = TRIP
    sender = SecOcSender(codec, key_c2p, CTRL_SECURED)
    tx = Transmitter(codec)
    monitor = RxMonitor(codec, ["DRIVER_INPUTS"])
    answered = []
    pedal = 0.0
    secoc = SecOcReceiver(codec, key_p2c, ("SYNC",))
    for msg in frames:  # replay the controller's view to know each answer's inputs
        if msg.arbitration_id == codec.messages["DRIVER_INPUTS"].frame_id:
            result = monitor.process(msg, 0.0)
            if isinstance(result, Decoded):
                pedal = result.values["ACCEL_PEDAL"]
            continue
        released = secoc.feed(msg)
        if released is not None and released.arbitration_id == codec.messages["SYNC"].frame_id:
            cycle = int(secoc.released_sync.values["CYCLE"])
            torque = tx.message(
                "WHEEL_TORQUE_CMD",
                {
                    **{f"TQ_{w}": pedal * 4.0 for w in ("FL", "FR", "RL", "RR")},
                    "ECHO_CYCLE": float(cycle % 256),
                },
            )
            answered.append(
                (cycle, torque, sender.authenticator("WHEEL_TORQUE_CMD", torque, TRIP, cycle))
            )
    assert len(answered) == CYCLES - 1  # every cycle but the forged one
    assert len(sent) == 2 * len(answered)
    for k, (cycle, torque, auth) in enumerate(answered):
        data, auth_data = bytes.fromhex(sent[2 * k][2]), bytes.fromhex(sent[2 * k + 1][2])
        assert (data, auth_data) == (bytes(torque.data), bytes(auth.data))
        plant.cycle = cycle
        assert (
            plant.feed(
                can.Message(arbitration_id=int(sent[2 * k][1], 16), data=data, is_extended_id=False)
            )
            is None
        )
        released = plant.feed(
            can.Message(
                arbitration_id=int(sent[2 * k + 1][1], 16), data=auth_data, is_extended_id=False
            )
        )
        assert released is not None and bytes(released.data) == data
        decoded = codec.decode(released.arbitration_id, released.data)
        assert isinstance(decoded, Decoded) and decoded.values["ECHO_CYCLE"] == cycle % 256
    assert plant.rejection_counts() == {}
