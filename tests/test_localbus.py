"""The local virtual CAN bus (python-can interface ``rhonncan``): vcan-like semantics, by name,
across real OS processes; python-can's own logger and player on it."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from can_db.bus import BusSpecError, open_bus, parse_spec, resolve_auto
from can_db.localbus import INTERFACE, LocalBus, LocalBusError, channel_dir, runtime_dir
from tests.helpers_proc import live_children, spawn


@pytest.fixture
def private_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fresh runtime dir for each test (children inherit it through the environment)."""
    path = tmp_path / "rt"
    monkeypatch.setenv("RHONN_CAN_DIR", str(path))
    yield path


def _frame(k: int, **kw: object) -> can.Message:
    return can.Message(arbitration_id=0x100 + k % 0x600, data=k.to_bytes(4, "little"),
                       is_extended_id=False, **kw)  # type: ignore[arg-type]


def _members(channel: str) -> int:
    return len(list(channel_dir(channel).glob("*.sock")))


def _wait_members(channel: str, count: int, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while _members(channel) < count:
        assert time.monotonic() < deadline, f"{count} nodes did not join {channel}"
        time.sleep(0.02)


def test_every_other_node_gets_every_frame_and_own_only_on_request(private_dir: Path) -> None:
    a = can.Bus(interface=INTERFACE, channel="unit")
    b = can.Bus(interface=INTERFACE, channel="unit")
    c = can.Bus(interface=INTERFACE, channel="unit", receive_own_messages=True)
    try:
        frames = [_frame(1), can.Message(arbitration_id=0x1ABCDEF0, data=bytes(range(64)),
                                         is_extended_id=True, is_fd=True, bitrate_switch=True,
                                         error_state_indicator=True),
                  can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=3,
                              is_extended_id=False)]
        for f in frames:
            a.send(f)
        for bus in (b, c):
            got = [bus.recv(1.0) for _ in frames]
            for sent, rx in zip(frames, got, strict=True):
                assert rx is not None and rx.equals(sent, timestamp_delta=None,
                                                    check_direction=False, check_channel=False)
        assert a.recv(0.05) is None  # not its own
        c.send(_frame(7))
        assert c.recv(1.0).arbitration_id == _frame(7).arbitration_id  # own, on request
        assert a.recv(1.0).data == _frame(7).data and b.recv(1.0).data == _frame(7).data
    finally:
        for bus in (a, b, c):
            bus.shutdown()
    assert not (runtime_dir() / "unit").exists()  # the last node to leave removes the dir


def test_frames_that_no_can_frame_holds_are_refused(private_dir: Path) -> None:
    with LocalBus("unit") as bus:
        with pytest.raises(can.CanOperationError, match="classical CAN"):
            bus.send(can.Message(arbitration_id=1, data=bytes(9)))
        with pytest.raises(can.CanOperationError, match="CAN FD length"):
            bus.send(can.Message(arbitration_id=1, data=bytes(9), is_fd=True))


def test_bad_names_and_an_unsafe_runtime_dir_are_clear_errors(private_dir: Path) -> None:
    for bad in ("", "a/b", "../x", "x" * 65, "sp ace"):
        with pytest.raises(LocalBusError, match="bad rhonncan channel"):
            LocalBus(bad)
        with pytest.raises(BusSpecError):
            parse_spec(f"local:{bad}")
    runtime_dir()
    os.chmod(private_dir, 0o755)  # another user could reach our sockets
    with pytest.raises(LocalBusError, match="mode 0700"):
        LocalBus("unit")


def test_a_slow_reader_loses_its_own_frames_counted_and_never_blocks_others(
        private_dir: Path) -> None:
    sender = LocalBus("unit", queue_kib=16, node_name="sender")
    sleeper = LocalBus("unit", node_name="sleeper")  # never reads
    reader = LocalBus("unit", node_name="reader")
    try:
        received = 0
        start = time.monotonic()
        for k in range(5000):
            sender.send(_frame(k))
            if k % 10 == 9:  # the reader keeps up
                while reader.recv(0.0 if received < k - 9 else 0.5) is not None:
                    received += 1
                    if received == k + 1:
                        break
        while received < 5000 and reader.recv(0.5) is not None:
            received += 1
        elapsed = time.monotonic() - start
        stats = sender.stats()
    finally:
        for bus in (sender, sleeper, reader):
            bus.shutdown()
    assert received == 5000  # nothing lost for the node that reads
    by_peer = stats["dropped_by_peer"]
    assert set(by_peer) == {"sleeper"} and 4000 < by_peer["sleeper"] < 5000
    assert stats["dropped"] == by_peer["sleeper"] and stats["sent"] == 5000
    assert elapsed < 60.0  # the sender was never blocked by the full queue (no wait-out)


def test_nodes_join_and_leave_at_any_time(private_dir: Path) -> None:
    a = LocalBus("unit")
    a.send(_frame(0))  # nobody there: goes nowhere, no error
    b = LocalBus("unit")
    a.send(_frame(1))
    assert b.recv(1.0).data == _frame(1).data and b.recv(0.05) is None  # only after joining
    b.shutdown()
    a.send(_frame(2))  # a left peer is dropped silently
    c = LocalBus("unit")
    c.send(_frame(3))
    assert a.recv(1.0).data == _frame(3).data
    a.shutdown()
    c.shutdown()


def test_a_sigkilled_node_leaves_nothing_that_breaks_the_next_run(private_dir: Path) -> None:
    child = spawn("-c", "import can, time; b = can.Bus(interface='rhonncan', channel='unit');"
                  "print('joined', flush=True); time.sleep(60)", stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().startswith("joined")
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        assert _members("unit") == 1  # its socket file stays behind ...
        a = LocalBus("unit")  # ... and the next node removes it while joining
        b = LocalBus("unit")
        assert _members("unit") == 2
        a.send(_frame(5))
        assert b.recv(1.0).data == _frame(5).data
        a.shutdown()
        b.shutdown()
    finally:
        if child.poll() is None:
            child.kill()
    assert not live_children()


def test_python_can_logger_records_by_name_across_processes(private_dir: Path,
                                                            tmp_path: Path) -> None:
    log = tmp_path / "log.asc"
    logger = spawn("-m", "can.logger", "-i", INTERFACE, "-c", "tools", "-f", str(log),
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_members("tools", 1)
        frames = [_frame(k) for k in range(200)] + [
            can.Message(arbitration_id=0x18DAF110, data=bytes(range(12)), is_fd=True,
                        is_extended_id=True)]
        with LocalBus("tools") as bus:
            for f in frames:
                bus.send(f)
            time.sleep(1.0)  # let the logger write them
        logger.send_signal(signal.SIGINT)
        assert logger.wait(timeout=20) == 0, logger.stderr.read() if logger.stderr else ""
    finally:
        if logger.poll() is None:
            logger.kill()
    got = list(can.LogReader(str(log)))
    assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in got] == \
        [(m.arbitration_id, bytes(m.data), m.is_fd) for m in frames]


def test_python_can_player_replays_by_name_across_processes(private_dir: Path,
                                                            tmp_path: Path) -> None:
    log = tmp_path / "replay.asc"
    frames = [can.Message(timestamp=1.0 + 0.001 * k, arbitration_id=0x200 + k,
                          data=bytes([k, 0xAA]), is_extended_id=False) for k in range(50)]
    with can.ASCWriter(str(log)) as writer:
        for f in frames:
            writer.on_message_received(f)
    with LocalBus("tools") as bus:
        player = spawn("-m", "can.player", "-i", INTERFACE, "-c", "tools", str(log),
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            got = []
            while len(got) < len(frames):
                msg = bus.recv(20.0)
                assert msg is not None, f"player sent {len(got)} of {len(frames)}"
                got.append(msg)
            assert player.wait(timeout=20) == 0
        finally:
            if player.poll() is None:
                player.kill()
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == \
        [(m.arbitration_id, bytes(m.data)) for m in frames]


def test_auto_picks_the_local_bus_without_socketcan(private_dir: Path) -> None:
    spec, server = resolve_auto(vcan="rhonn_no_such_if")
    assert server is None and parse_spec(spec)[0] == "local"
    with open_bus(spec) as a, open_bus(spec) as b:
        a.send(_frame(9))
        assert b.recv(1.0).data == _frame(9).data

