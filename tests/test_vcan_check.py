"""The SocketCAN check (harness/tools/vcan_check.py, docs/vcan.md).

Where ``vcan0`` is up (a user's Linux machine), the whole set runs on it and every
comparison with the local bus must pass. Everywhere, the comparisons themselves are shown
to catch what they are for: a frame stamped into the wrong cycle, a frame the capture
missed, a torque answer that differs."""

from __future__ import annotations

import shutil
from pathlib import Path

import can
import pytest

from can_db.codec import Codec
from can_db.transport.server import vcan_available
from harness.run.bus_logger import SimTimeStamper
from harness.tools import vcan_check
from tests.test_bus_log_frame_order import atomic_order, secoc_cycles

CYCLES = 30


def _write_log(frames: list[can.Message], path: Path) -> list[can.Message]:
    """``frames`` stamped as the harness's recorder does (simulated time), written to BLF."""
    stamper = SimTimeStamper(Codec(), epoch_s=1000.0)
    out: list[can.Message] = []
    for f in frames:
        out += stamper.feed(can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                        is_extended_id=False))
    out += stamper.flush()
    with can.BLFWriter(str(path)) as writer:
        for m in out:
            writer.on_message_received(m)
    return out


@pytest.fixture(scope="module")
def frames() -> list[can.Message]:
    return atomic_order(secoc_cycles(CYCLES))


def test_equal_logs_pass_cycle_by_cycle(frames: list[can.Message], tmp_path: Path) -> None:
    _write_log(frames, tmp_path / "a.blf")
    _write_log(frames, tmp_path / "b.blf")
    check = vcan_check.compare_logs("log", tmp_path / "a.blf", tmp_path / "b.blf")
    assert check.ok, check.detail
    assert f"{CYCLES} cycles" in check.detail


def test_a_frame_in_the_next_cycle_fails_and_names_the_cycle(frames: list[can.Message],
                                                             tmp_path: Path) -> None:
    stamped = _write_log(frames, tmp_path / "a.blf")
    moved = [can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id, data=m.data,
                         is_extended_id=False)
             for m in stamped]
    status_auth = Codec().messages["CTRL_STATUS_AUTH"].frame_id
    k = [i for i, m in enumerate(moved) if m.arbitration_id == status_auth][7]
    moved[k].timestamp += vcan_check.PERIOD_S  # what the recorder did on SocketCAN
    with can.BLFWriter(str(tmp_path / "b.blf")) as writer:
        for m in sorted(moved, key=lambda m: m.timestamp):
            writer.on_message_received(m)
    check = vcan_check.compare_logs("log", tmp_path / "b.blf", tmp_path / "a.blf")
    assert not check.ok
    assert "2 of" in check.detail and "first cycle 7" in check.detail


def test_a_capture_missing_one_frame_fails(frames: list[can.Message]) -> None:
    assert vcan_check.capture_complete("cap", frames, frames).ok
    check = vcan_check.capture_complete("cap", frames[:-1], frames)
    assert not check.ok and "1 missing" in check.detail


def test_candump_lines_are_read_back(tmp_path: Path) -> None:
    (tmp_path / "c.log").write_text("(1700000000.000100) vcan0 10F#0011223344556677\n"
                                    "(1700000000.000200) vcan0 110#\n")
    got = vcan_check.read_frames(tmp_path / "c.log")
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [
        (0x10F, bytes.fromhex("0011223344556677")), (0x110, b"")]


def test_the_plant_slice_ends_with_a_whole_cycle(frames: list[can.Message],
                                                 tmp_path: Path) -> None:
    codec = Codec()
    _write_log(frames, tmp_path / "main.blf")
    n = vcan_check.write_plant_slice(tmp_path / "main.blf", tmp_path / "slice.blf", codec)
    got = vcan_check.read_frames(tmp_path / "slice.blf")
    assert n == len(got) > 0
    sync = codec.messages["SYNC"].frame_id
    assert sum(m.arbitration_id == sync for m in got) == CYCLES  # fewer than SLICE_CYCLES
    assert got[-1].arbitration_id == codec.messages["SYNC_AUTH"].frame_id
    slice_ids = {codec.messages[x].frame_id for x in vcan_check.SLICE_NAMES}
    assert {m.arbitration_id for m in got} <= slice_ids


def test_kernel_choice_is_explicit_and_skips_rt_images(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("vmlinuz-6.1.0-9-amd64", "vmlinuz-6.1.0-56-amd64", "vmlinuz-6.1.0-56-rt-amd64"):
        (tmp_path / name).write_text("")
    monkeypatch.setattr(vcan_check.glob, "glob",
                        lambda pattern: [str(p) for p in tmp_path.glob(Path(pattern).name)])
    assert vcan_check.pick_kernel().name == "vmlinuz-6.1.0-56-amd64"
    assert vcan_check.pick_kernel(rt=True).name == "vmlinuz-6.1.0-56-rt-amd64"


@pytest.mark.skipif(not vcan_available("vcan0"), reason="vcan0 is not up (docs/vcan.md)")
@pytest.mark.skipif(shutil.which("candump") is None, reason="no candump (can-utils)")
@pytest.mark.timeout(1800)
def test_the_socketcan_set_on_vcan0_equals_the_local_bus(tmp_path: Path) -> None:
    assert vcan_check.main(["--here", "--work", str(tmp_path)]) == 0


def test_only_the_measured_compute_time_is_left_out_of_the_log_comparison() -> None:
    """CTRL_STATUS carries the controller's measured compute time (and its authenticator a
    MAC over it): never equal in two runs; everything else in them must be."""
    from can_db.codec import Transmitter

    codec = Codec()

    def status(compute_us: float, mode: int) -> can.Message:
        return Transmitter(codec).message("CTRL_STATUS", {
            "MODE": mode, "FAULT_BITS": 0, "QP_STATUS": 1, "QP_ITER": 7,
            "COMPUTE_TIME": compute_us, "ECHO_CYCLE": 3, "CONTROLLER_ID": 1})

    base = vcan_check.comparable(status(120.0, 1), codec)
    assert vcan_check.comparable(status(480.0, 1), codec) == base
    assert vcan_check.comparable(status(120.0, 2), codec) != base
    torque = Transmitter(codec).message("WHEEL_TORQUE_CMD", {"TQ_FL": 1.0, "TQ_FR": 1.0,
                                                             "TQ_RL": 1.0, "TQ_RR": 1.0,
                                                             "ECHO_CYCLE": 3})
    assert vcan_check.comparable(torque, codec) == bytes(torque.data).hex()


def test_drops_pass_only_when_the_kernel_counted_every_lost_frame(tmp_path: Path) -> None:
    import json
    path = tmp_path / "drops.json"
    assert not vcan_check.drops_counted(path).ok  # no result: the step did not run
    path.write_text(json.dumps({"sent": 20000, "received": 1450, "rx_dropped": 18550,
                                "rcvbuf_bytes": 2097152}))
    assert vcan_check.drops_counted(path).ok
    path.write_text(json.dumps({"sent": 20000, "received": 1450, "rx_dropped": -1,
                                "rcvbuf_bytes": 2097152}))  # no count from the kernel
    assert not vcan_check.drops_counted(path).ok
    path.write_text(json.dumps({"sent": 100, "received": 100, "rx_dropped": 0,
                                "rcvbuf_bytes": 2097152}))  # the flood did not overflow
    assert not vcan_check.drops_counted(path).ok


def test_a_socketcan_run_is_healthy_only_with_every_nodes_drops_counted_and_zero(
        tmp_path: Path) -> None:
    import json
    (tmp_path / "plant_summary.json").write_text(json.dumps({"lockstep_timeouts": 0}))

    def health(socket: dict | None) -> bool:
        drops = {} if socket is None else {"socket": socket}
        (tmp_path / "metrics.json").write_text(json.dumps(
            {"fallback_events": 0, "bus": "socketcan", "rx_drops": drops}))
        return vcan_check.run_health("run", tmp_path, "socketcan").ok

    assert health({"controller": 0, "plant": 0, "bus-recorder": 0})
    assert not health({"controller": 0, "plant": 2, "bus-recorder": 0})
    assert not health(None)  # not counted
