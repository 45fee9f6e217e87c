"""The local virtual CAN bus (python-can interface ``rhonncan``) and its hub: vcan-like
semantics, by name, across real OS processes; python-can's own logger and player on it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from can_db.transport import wire
from can_db.transport.bus import BusSpecError, open_bus, parse_spec, resolve_auto
from can_db.transport.hub import LocalHub
from can_db.transport.localbus import (
    INTERFACE,
    BusDisconnected,
    LocalBus,
    LocalBusError,
    runtime_dir,
)
from tests.helpers_proc import interrupt_and_wait, live_children, spawn


@pytest.fixture
def private_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fresh runtime dir for each test (children inherit it through the environment)."""
    path = tmp_path / "rt"
    monkeypatch.setenv("RHONN_CAN_DIR", str(path))
    yield path


def _frame(k: int, **kw: object) -> can.Message:
    return can.Message(arbitration_id=0x100 + k % 0x600, data=k.to_bytes(4, "little"),
                       is_extended_id=False, **kw)  # type: ignore[arg-type]


@pytest.fixture
def hub(private_dir: Path, tmp_path: Path) -> Iterator[LocalHub]:
    """A managed hub on channel "unit" that writes its counts to tmp_path/hub.json."""
    with LocalHub("unit", stats_path=tmp_path / "hub.json") as running:
        yield running


def _hub_nodes(path: Path) -> dict[str, dict]:
    return {n["name"]: n for n in json.loads(path.read_text())["nodes"]}


def _wait_for_hub(channel: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not (runtime_dir() / f"{channel}.sock").exists():
        assert time.monotonic() < deadline, f"no hub on {channel}"
        time.sleep(0.02)


def test_every_other_node_gets_every_frame_and_own_only_on_request(hub: LocalHub) -> None:
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


def test_frames_that_no_can_frame_holds_are_refused(hub: LocalHub) -> None:
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
    with pytest.raises(LocalBusError, match="no hub"):
        LocalBus("unit", autostart=False)
    os.chmod(private_dir, 0o755)  # another user could reach our sockets
    with pytest.raises(LocalBusError, match="mode 0700"):
        LocalBus("unit")


def test_the_runtime_dir_follows_xdg_and_refuses_a_symlink_or_a_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RHONN_CAN_DIR", raising=False)
    xdg = tmp_path / "xdg"
    xdg.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(xdg))
    path = runtime_dir()
    assert path == xdg / "rhonn-can" and path.is_dir()
    assert path.stat().st_mode & 0o777 == 0o700
    # a symlink to a private directory of ours, or a plain file: another user could have
    # placed either, so neither is used
    link = tmp_path / "link"
    link.symlink_to(path, target_is_directory=True)
    plain = tmp_path / "plain"
    plain.write_bytes(b"")
    plain.chmod(0o600)
    for bad in (link, plain):
        monkeypatch.setenv("RHONN_CAN_DIR", str(bad))
        with pytest.raises(wire.ChannelError, match="is not a directory"):
            wire.socket_path("unit")  # the hub's side (no python-can)
        with pytest.raises(LocalBusError, match="is not a directory"):
            LocalBus("unit")
    assert not list(path.iterdir())  # nothing created through the link


def test_a_slow_reader_loses_its_own_frames_counted_and_never_blocks_others(
        private_dir: Path, tmp_path: Path) -> None:
    stats = tmp_path / "hub.json"
    with LocalHub("unit", stats_path=stats, queue_kib=64):
        sender = LocalBus("unit", node_name="sender", autostart=False)
        sleeper = LocalBus("unit", node_name="sleeper", autostart=False)  # never reads
        reader = LocalBus("unit", node_name="reader", autostart=False)
        try:
            received = 0
            for k in range(5000):
                sender.send(_frame(k))
                if k % 10 == 9:  # the reader keeps up; the sleeper's queue overflows
                    while received <= k:
                        msg = reader.recv(5.0)
                        assert msg is not None, f"reader lost frame {received}"
                        assert int.from_bytes(msg.data, "little") == received
                        received += 1
        finally:
            for bus in (sender, sleeper, reader):
                bus.shutdown()
    nodes = _hub_nodes(stats)
    assert received == 5000  # nothing lost, in order, for the node that reads
    assert nodes["reader"]["dropped"] == 0 and nodes["reader"]["frames_out"] == 5000
    assert 1000 < nodes["sleeper"]["dropped"] < 5000  # its bounded queue took the rest
    assert nodes["sleeper"]["dropped"] + nodes["sleeper"]["frames_out"] == 5000
    assert nodes["sender"]["frames_in"] == 5000 and sender.stats()["sent"] == 5000


def test_a_burst_arrives_whole_and_in_order(hub: LocalHub) -> None:
    with LocalBus("unit") as a, LocalBus("unit") as b:
        a.send_many([_frame(k) for k in range(150)])  # more than one packet's worth
        got = [b.recv(1.0) for _ in range(150)]
        assert [int.from_bytes(m.data, "little") for m in got] == list(range(150))
        assert b.recv(0.05) is None


def test_nodes_join_and_leave_at_any_time(hub: LocalHub) -> None:
    a = LocalBus("unit")
    a.send(_frame(0))  # nobody else there: goes nowhere, no error
    time.sleep(0.2)  # frame 0 has been forwarded (to nobody)
    b = LocalBus("unit")  # a member when the constructor returns
    a.send(_frame(1))
    assert b.recv(1.0).data == _frame(1).data and b.recv(0.05) is None  # only after joining
    b.shutdown()
    a.send(_frame(2))  # a node that left is dropped silently
    c = LocalBus("unit")
    c.send(_frame(3))
    assert a.recv(1.0).data == _frame(3).data
    a.shutdown()
    c.shutdown()


def test_a_node_that_leaves_still_has_every_frame_it_sent_forwarded(
        private_dir: Path, tmp_path: Path) -> None:
    """A node closes with a frame for it unread while the hub (paused: a starved process)
    has not read its last 2 000 frames yet: the kernel reports the close to the hub before
    those frames, and the hub still forwards every one, in order, then drops the node."""
    stats = tmp_path / "hub.json"
    with LocalHub("unit", stats_path=stats) as hub:
        assert hub.process is not None
        sender = LocalBus("unit", node_name="sender", autostart=False)
        reader = LocalBus("unit", node_name="reader", autostart=False)
        try:
            reader.send(_frame(9999))
            time.sleep(0.2)  # forwarded to the sender, which never reads it
            os.kill(hub.process.pid, signal.SIGSTOP)
            try:
                sender.send_many([_frame(k) for k in range(2000)])
                assert sender.unread_by_hub() > 0 and not sender.wait_read_by_hub(0.05)
                sender.shutdown()
            finally:
                os.kill(hub.process.pid, signal.SIGCONT)
            got = []
            while (msg := reader.recv(5.0)) is not None and len(got) < 2000:
                got.append(int.from_bytes(msg.data, "little"))
            assert got == list(range(2000))
        finally:
            sender.shutdown()
            reader.shutdown()
    nodes = _hub_nodes(stats)
    assert nodes["sender"]["frames_in"] == 2000 and nodes["reader"]["frames_out"] == 2000


def test_a_node_waits_until_the_hub_has_read_what_it_sent(hub: LocalHub) -> None:
    """``wait_read_by_hub``: False while the hub is paused, True once it has read."""
    assert hub.process is not None
    with LocalBus("unit") as a, LocalBus("unit") as b:
        os.kill(hub.process.pid, signal.SIGSTOP)
        try:
            a.send_many([_frame(k) for k in range(300)])
            assert a.unread_by_hub() > 0 and not a.wait_read_by_hub(0.1)
        finally:
            os.kill(hub.process.pid, signal.SIGCONT)
        assert a.wait_read_by_hub(10.0) and a.unread_by_hub() == 0
        assert [int.from_bytes(b.recv(5.0).data, "little") for _ in range(300)] == list(
            range(300))


def test_an_answer_is_never_seen_before_the_frame_it_answers(hub: LocalHub) -> None:
    """vcan order: a third node (the recorder) sees every echo after its request."""
    echo = spawn("-m", "harness.bench.bus", "--echo", "local:unit")
    try:
        with LocalBus("unit") as pinger, LocalBus("unit") as recorder:
            assert pinger.recv(20.0).arbitration_id == 0x7F0  # the echo node is ready
            for k in range(300):
                pinger.send(can.Message(arbitration_id=0x700, data=k.to_bytes(8, "little"),
                                        is_extended_id=False))
                assert pinger.recv(5.0).arbitration_id == 0x701
            pinger.send(can.Message(arbitration_id=0x7F0, is_extended_id=False))
            seen = []
            while (msg := recorder.recv(1.0)) is not None:
                seen.append((msg.arbitration_id, bytes(msg.data)))
        assert echo.wait(timeout=20) == 0
    finally:
        if echo.poll() is None:
            echo.kill()
    order = [(i, int.from_bytes(d, "little")) for i, d in seen if i in (0x700, 0x701)]
    assert order == [(i, k) for k in range(300) for i in (0x700, 0x701)]


def test_sigkill_of_a_node_or_of_the_hub_leaves_nothing_that_breaks_the_next_run(
        private_dir: Path) -> None:
    hub = LocalHub("unit").start()
    child = spawn("-c", "import can, time; b = can.Bus(interface='rhonncan', channel='unit');"
                  "print('joined', flush=True); time.sleep(60)", stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().startswith("joined")
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        a = LocalBus("unit", reconnect_s=5.0, autostart=False)
        b = LocalBus("unit", autostart=False)
        a.send(_frame(5))  # the dead node's closed connection costs nothing
        assert b.recv(1.0).data == _frame(5).data
        hub.kill()  # SIGKILL: the socket file stays, the lock goes with the process
        assert (runtime_dir() / "unit.sock").exists()
        with pytest.raises(BusDisconnected):
            b.recv(1.0)  # no reconnect allowed: a clear error, not a hang
        hub.start()  # the next hub replaces the stale socket
        deadline = time.monotonic() + 5.0
        while a.reconnects == 0 and time.monotonic() < deadline:
            a.recv(0.05)  # a rides it out and reconnects
        c = LocalBus("unit", autostart=False)
        c.send(_frame(6))
        assert a.reconnects == 1 and a.recv(1.0).data == _frame(6).data
        for bus in (a, b, c):
            bus.shutdown()
    finally:
        hub.stop()
        if child.poll() is None:
            child.kill()
    assert not hub.alive() and child.poll() is not None


def test_python_can_logger_records_by_name_across_processes(private_dir: Path,
                                                            tmp_path: Path) -> None:
    log = tmp_path / "log.asc"
    err = tmp_path / "logger.err"
    logger = spawn("-m", "can.logger", "-i", INTERFACE, "-c", "tools", "-f", str(log),
                   stdout=subprocess.DEVNULL, stderr=err.open("w"),
                   env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    try:
        _wait_for_hub("tools")  # the logger started the channel's hub
        time.sleep(0.5)  # and has joined it
        frames = [_frame(k) for k in range(200)] + [
            can.Message(arbitration_id=0x18DAF110, data=bytes(range(12)), is_fd=True,
                        is_extended_id=True)]
        with LocalBus("tools") as bus:
            for f in frames:
                bus.send(f)
            time.sleep(1.0)  # let the logger write them
        assert interrupt_and_wait(logger, 60, err) == 0, err.read_text()
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
    # The hub the first node started exits its idle time (3 s) after the last node left.
    deadline = time.monotonic() + 15.0
    while live_children() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not live_children()


def test_auto_picks_the_local_bus_without_socketcan(private_dir: Path) -> None:
    spec, hub = resolve_auto(vcan="rhonn_no_such_if")
    try:
        assert hub is not None and hub.alive() and parse_spec(spec) == ("local", hub.channel)
        with open_bus(spec) as a, open_bus(spec) as b:
            a.send(_frame(9))
            assert b.recv(1.0).data == _frame(9).data
    finally:
        if hub is not None:
            hub.stop()
    assert hub is not None and not hub.alive()

