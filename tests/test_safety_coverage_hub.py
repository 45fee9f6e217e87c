"""The local bus hub's queues and error paths: one hub per channel, per-node drop counts
when a node's queue is full, spurious wake-ups, failed welcomes, and the managed child
process (start failure, stop of a hung hub)."""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import stat
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from can_db.transport import hub as hub_mod
from can_db.transport.hub import Hub, HubBusyError, LocalHub, LocalHubError, _Node, _node_stats
from can_db.transport.localbus import (
    CTRL_HELLO,
    CTRL_WELCOME,
    HEADER,
    control_packet,
    lock_path,
    socket_path,
)


@pytest.fixture()
def can_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private runtime directory for this test's channels (children inherit it)."""
    d = tmp_path / "can"
    d.mkdir(mode=0o700)
    monkeypatch.setenv("RHONN_CAN_DIR", str(d))
    return d


@pytest.fixture()
def hub(can_dir: Path) -> Iterator[Hub]:
    h = Hub("cov-hub", queue_kib=4)
    yield h
    h.close()


def frame(can_id: int = 0x123, data: bytes = b"\x01\x02") -> bytes:
    return HEADER.pack(can_id, 0, len(data), len(data)) + data


class ScriptedPoll:
    """Stands in for the hub's poll object: returns (or raises) the scripted results, then
    stops the hub."""

    def __init__(self, hub: Hub, script: list[object]) -> None:
        self.hub, self.script, self.calls = hub, list(script), 0

    def poll(self, _timeout: int) -> object:
        self.calls += 1
        item = self.script.pop(0)
        if not self.script:
            self.hub._stop = True
        if isinstance(item, BaseException):
            raise item
        return item

    def register(self, *_: object) -> None:
        pass

    def unregister(self, *_: object) -> None:
        pass


def test_one_hub_per_channel(hub: Hub) -> None:
    with pytest.raises(HubBusyError, match="already has a hub"):
        Hub("cov-hub")
    assert hub.queue_bytes == 4 * 1024
    assert Hub("cov-hub-2", queue_kib=1).queue_bytes == 4 * 1024   # at least 4 KiB


def test_the_hub_process_refuses_a_busy_channel(hub: Hub,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert hub_mod.main(["--channel", "cov-hub"]) == 4
    assert "already has a hub" in capsys.readouterr().err


def test_the_hub_process_reports_a_channel_it_cannot_serve(
        can_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    socket_path("cov-blocked").mkdir()          # a directory where the socket goes
    assert hub_mod.main(["--channel", "cov-blocked"]) == 3
    assert "cannot serve channel 'cov-blocked'" in capsys.readouterr().err


def test_the_hub_process_reports_a_bad_channel_name_in_one_line(
        can_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert hub_mod.main(["--channel", "bad/name"]) == 3
    err = capsys.readouterr().err
    assert "cannot serve channel 'bad/name'" in err and "Traceback" not in err


def test_accept_without_a_pending_connection_does_nothing(hub: Hub) -> None:
    hub._accept()
    assert hub.nodes == {}


def test_dropping_an_unknown_node_does_nothing(hub: Hub) -> None:
    hub._drop_node(12345)
    assert hub.left == []


def test_a_node_that_cannot_take_the_welcome_is_not_a_member(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    b.close()
    node = _Node(a)
    hub.nodes[a.fileno()] = node
    hub._control(node, control_packet(CTRL_HELLO, {"name": "gone", "own": True}))
    assert node.name == "gone" and node.own and node not in hub._order
    a.close()


def test_a_hello_makes_a_member_once(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    node = _Node(a)
    hub._control(node, control_packet(CTRL_HELLO, {"name": "n1"}))
    hub._control(node, control_packet(CTRL_HELLO, {"name": "n1"}))
    assert hub._order == (node,) and not node.own
    assert HEADER.unpack_from(b.recv(64))[0] == CTRL_WELCOME
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    bad = _Node(c)
    hub._control(bad, HEADER.pack(CTRL_HELLO, 0x80, 0, 3) + b"{x]")   # unparsable hello
    assert bad.name == "?" and hub._order == (node, bad)
    for s in (a, b, c, d):
        s.close()


def test_a_full_queue_drops_and_counts_per_node(hub: Hub) -> None:
    src_a, src_b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    dst_a, dst_b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    dst_a.setblocking(False)
    dst_a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    src, dst = _Node(src_a, "src"), _Node(dst_a, "dst")
    hub._order = (src, dst)
    sent = 0
    while dst.dropped == 0:
        hub._forward(src, frame())
        sent += 1
        assert sent < 100_000
    assert src.frames_in == sent == hub.frames
    assert dst.frames_out + dst.dropped == sent and hub.dropped == dst.dropped
    assert src.frames_out == 0                    # not its own frames (own=False)
    # the receiver reads one packet: room again, the next frame is delivered
    dst_b.recv(64)
    before = dst.frames_out
    hub._forward(src, frame())
    assert dst.frames_out == before + 1
    for s in (src_a, src_b, dst_a, dst_b):
        s.close()


def test_a_lossless_node_is_waited_for_then_given_up_when_it_stops_reading(hub: Hub) -> None:
    """A lossless node (the lockstep recorder) whose queue is full gets the packet as soon
    as it reads; one that does not read within the bounded wait is lossy from then on."""
    src_a, src_b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    dst_a, dst_b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    dst_a.setblocking(False)
    dst_a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    src, dst = _Node(src_a, "src"), _Node(dst_a, "rec")
    hub._control(dst, control_packet(CTRL_HELLO, {"name": "rec", "lossless": True}))
    dst_b.recv(64)                                # the welcome
    assert dst.lossless and hub._order == (dst,)
    hub._order = (src, dst)
    backlog = 0
    while True:                                   # a full queue: the recorder fell behind
        try:
            dst_a.send(frame())
        except BlockingIOError:
            break
        backlog += 1
    received: list[bytes] = []

    def read_after_a_while() -> None:  # the recorder catches up 20 ms later
        time.sleep(0.02)
        dst_b.settimeout(0.5)
        with contextlib.suppress(TimeoutError):
            while True:
                received.append(dst_b.recv(64))
    reader = threading.Thread(target=read_after_a_while)
    reader.start()
    hub._forward(src, frame())                    # waits for room, then delivers
    assert 0.0 < dst.waited_s < hub_mod.LOSSLESS_WAIT_S and dst.frames_out == 1
    sent = 1
    for _ in range(200):                          # the reader keeps up: nothing is lost
        hub._forward(src, frame())
        sent += 1
    reader.join()
    assert dst.dropped == 0 and hub.dropped == 0
    assert dst.frames_out == sent == len(received) - backlog
    assert _node_stats(dst)["lossless"] is True and _node_stats(dst)["waited_s"] > 0.0
    # nobody reads any more: one bounded wait, then drops are counted as for any node
    sent = 0
    while dst.dropped == 0:
        hub._forward(src, frame())
        sent += 1
        assert sent < 100_000
    assert not dst.lossless and dst.gave_up and hub.dropped == dst.dropped
    assert _node_stats(dst)["lossless"] is False
    waited = dst.waited_s
    hub._forward(src, frame())                    # no second wait for a node given up on
    assert dst.waited_s == waited and dst.dropped == 2
    for s in (src_a, src_b, dst_a, dst_b):
        s.close()


def test_a_dead_node_is_dropped_while_forwarding(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    d.close()
    src, dead = _Node(a, "src", own=True), _Node(c, "dead")
    hub.nodes = {a.fileno(): src, c.fileno(): dead}
    hub._order = (src, dead)
    hub._forward(src, frame())
    assert src.frames_out == 1                    # own=True: its own frames come back
    assert dead not in hub._order and hub.nodes[c.fileno()] is dead  # no more frames to it
    hub._poll = ScriptedPoll(hub, [[(c.fileno(), select.POLLIN)]])  # type: ignore[assignment]
    hub.run()                                     # its end of stream drops it
    assert c.fileno() == -1 and dead not in hub.nodes.values()
    assert hub.left == [{"name": "dead", "frames_in": 0, "frames_out": 0, "dropped": 0}]
    a.close()
    b.close()


def test_the_loop_survives_an_interrupted_poll_and_a_spurious_wake_up(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    a.setblocking(False)
    node = _Node(a, "quiet")
    hub.nodes[a.fileno()] = node
    hub._order = (node,)
    script = ScriptedPoll(hub, [InterruptedError(), [(a.fileno(), select.POLLIN)], []])
    hub._poll = script  # type: ignore[assignment]
    hub.run()
    assert script.calls == 3
    assert hub.nodes == {a.fileno(): node} and hub.frames == 0   # nothing read, still there
    a.close()
    b.close()


def test_stats_list_connected_and_departed_nodes(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    hub.nodes[a.fileno()] = _Node(a, "here", frames_in=2)
    hub.left.append({"name": "gone", "frames_in": 1, "frames_out": 0, "dropped": 0})
    s = hub.stats()
    assert s["channel"] == "cov-hub" and s["queue_bytes"] == 4096
    assert [n["name"] for n in s["nodes"]] == ["here", "gone"]
    b.close()


def test_close_removes_socket_and_lock(can_dir: Path) -> None:
    h = Hub("cov-close")
    assert socket_path("cov-close").exists() and lock_path("cov-close").exists()
    h.close()
    assert not socket_path("cov-close").exists() and not lock_path("cov-close").exists()
    Hub("cov-close").close()                      # the channel is free again


# ------------------------------------------------------------------ the managed process
def test_a_hub_child_that_cannot_start_raises_with_its_error(
        hub: Hub, monkeypatch: pytest.MonkeyPatch) -> None:
    child = LocalHub("cov-hub")                   # busy: the child exits with its error
    real_select = select.select

    def select_then_reap(r: list, w: list, x: list, t: float) -> tuple:
        ready = real_select(r, w, x, t)
        assert child.process is not None
        child.process.wait(timeout=30)            # its error is complete once it exited
        return ready

    monkeypatch.setattr(hub_mod.select, "select", select_then_reap)
    with pytest.raises(LocalHubError, match=r"did not start: .*already has a hub"):
        child.start(timeout_s=30)
    assert child.process is None


def test_stopping_a_hub_that_was_never_started_does_nothing() -> None:
    h = LocalHub()
    h.stop()
    h.kill()
    assert h.process is None and not h.alive()
    assert h.spec == f"local:{h.channel}"


def test_a_hub_that_ignores_sigterm_is_killed(can_dir: Path) -> None:
    h = LocalHub("cov-hung").start()
    proc = h.process
    assert proc is not None and h.alive()
    os.kill(proc.pid, signal.SIGSTOP)             # a hung hub: SIGTERM stays pending
    h.stop(timeout_s=0.5)
    assert proc.returncode == -signal.SIGKILL and h.process is None


def test_a_hub_restarts_on_its_channel(can_dir: Path, tmp_path: Path) -> None:
    stats = tmp_path / "stats.json"
    with LocalHub("cov-restart", stats_path=stats, queue_kib=8, rt=True) as h:
        first = h.process
        h.restart()
        assert h.alive() and h.process is not first
        assert isinstance(first, subprocess.Popen) and first.returncode == 0
    assert stats.exists()


def test_only_the_owner_may_connect_to_the_hub(hub: Hub) -> None:
    """The socket file is 0600: another user's process cannot join the bus and inject
    frames (the runtime directory is private too, this is the second wall)."""
    assert stat.S_IMODE(os.stat(socket_path("cov-hub")).st_mode) == 0o600


def test_the_hub_process_writes_its_counts_for_a_reader_and_leaves_nothing_behind(
        can_dir: Path, tmp_path: Path) -> None:
    stats = tmp_path / "hub.json"
    assert hub_mod.main(["--channel", "cov-stats", "--idle-exit", "0",
                         "--stats", str(stats)]) == 0
    text = stats.read_text()
    counts = json.loads(text)
    assert counts == {"channel": "cov-stats", "frames": 0, "dropped": 0,
                      "queue_bytes": 4 * 1024 * 1024, "nodes": []}  # 4 MiB default
    # for a person reading it: one field per line, indented by two
    assert text == json.dumps(counts, indent=2) + "\n"
    assert '\n  "frames": 0,\n' in text
    assert not socket_path("cov-stats").exists() and not lock_path("cov-stats").exists()


def test_one_wake_up_serves_a_new_connection_and_a_ready_node_alike(hub: Hub) -> None:
    """A poll that reports the listener and a node's packet at once handles both: the new
    connection does not delay the frame (nobody would wake the hub again for it if the
    sender then waited for an answer)."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    src, dst = _Node(a, "src"), _Node(c, "dst")
    hub.nodes = {a.fileno(): src, c.fileno(): dst}
    hub._order = (src, dst)
    newcomer = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    newcomer.connect(str(hub.path))
    b.send(frame())
    hub._poll = ScriptedPoll(hub, [[(hub.listener.fileno(), select.POLLIN),  # type: ignore[assignment]
                                    (a.fileno(), select.POLLIN)]])
    hub.run()
    assert len(hub.nodes) == 3                    # the newcomer was accepted
    assert hub.frames == 1 and d.recv(64) == frame()
    for s in (a, b, c, d, newcomer):
        s.close()


class FakeClock:
    """monotonic() for the hub's bounded wait; the poller moves it."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now


class SleepingPoller:
    """A select.poll stand-in on which nothing ever becomes writable: each poll returns
    after its full timeout, or earlier (a spurious wake-up) by the scripted amounts, s."""

    def __init__(self, clock: FakeClock, early: list[float], timeouts: list[int]) -> None:
        self.clock, self.early, self.timeouts = clock, early, timeouts

    def register(self, *_: object) -> None:
        pass

    def poll(self, timeout_ms: int) -> list[tuple[int, int]]:
        self.timeouts.append(timeout_ms)
        assert len(self.timeouts) < 1000, "the wait does not end"
        self.clock.now += self.early.pop(0) if self.early else timeout_ms / 1000.0
        return []


class FullSocket:
    """A node connection whose queue never has room."""

    def fileno(self) -> int:
        return 99

    def send(self, _packet: bytes) -> int:
        raise BlockingIOError


@pytest.mark.parametrize("early", [[], [0.040005]])
def test_the_bounded_wait_sleeps_in_whole_ms_until_its_end_and_no_longer(
        hub: Hub, monkeypatch: pytest.MonkeyPatch, early: list[float]) -> None:
    """The wait for a lossless node's queue, on a simulated clock: each poll asks for the
    time left in whole ms (at least 1 ms, never a busy poll(0), never past the end), a wait
    nobody interrupts is one poll, and the node is given up only once LOSSLESS_WAIT_S has
    passed."""
    clock, timeouts = FakeClock(), []
    poller = SleepingPoller(clock, list(early), timeouts)
    monkeypatch.setattr(hub_mod, "time", clock)
    monkeypatch.setattr(hub_mod, "select", type("Select", (), {
        "poll": staticmethod(lambda: poller), "POLLOUT": select.POLLOUT}))
    node = _Node(FullSocket(), "rec", lossless=True)  # type: ignore[arg-type]
    assert hub._send_when_room(node, frame()) is False
    assert node.gave_up and not node.lossless
    wait_ms = hub_mod.LOSSLESS_WAIT_S * 1000.0
    assert min(timeouts) >= 1
    if not early:
        assert timeouts == [round(wait_ms)] and node.waited_s == hub_mod.LOSSLESS_WAIT_S
    else:  # woken after 40.005 ms: 9.995 ms left, so 9 ms, then the last (at least 1) ms
        assert timeouts == [round(wait_ms), 9, 1]
        assert hub_mod.LOSSLESS_WAIT_S <= node.waited_s < hub_mod.LOSSLESS_WAIT_S + 0.001


def test_a_hub_started_without_unbuffered_output_still_reports_ready(
        can_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The ready line is flushed: a parent whose environment does not force unbuffered
    output (every production one) must see it while the hub runs."""
    monkeypatch.delenv("PYTHONUNBUFFERED", raising=False)
    with LocalHub("cov-buffered", start_timeout_s=30.0) as h:
        assert h.alive()


def test_the_start_timeout_is_the_callers_else_the_hubs(can_dir: Path) -> None:
    with pytest.raises(LocalHubError, match=r"no ready line within 1e-06 s"):
        LocalHub("cov-slow", start_timeout_s=1e-6).start()
    h = LocalHub("cov-slow", start_timeout_s=1e-6).start(timeout_s=30.0)
    assert h.alive()
    h.stop()


def test_a_hub_without_a_channel_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        hub_mod.main([])
    assert exc.value.code == 2 and "--channel" in capsys.readouterr().err


def test_the_managed_hubs_options_are_keyword_only(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        LocalHub("cov-kw", tmp_path / "stats.json")  # type: ignore[misc]


def test_a_burst_is_counted_frame_by_frame(hub: Hub) -> None:
    """A packet of three frame records (``send_many``) counts three frames in and out."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    src, dst = _Node(a, "src"), _Node(c, "dst")
    hub._order = (src, dst)
    burst = frame(0x101, b"\x01") + frame(0x102, b"\x02\x03\x04") + frame(0x103, b"")
    hub._forward(src, burst)
    hub._forward(src, frame())
    assert d.recv(64) == burst and d.recv(64) == frame()
    assert src.frames_in == dst.frames_out == hub.frames == 4
    for s in (a, b, c, d):
        s.close()


def test_the_hub_asks_for_real_time_scheduling_only_when_told(can_dir: Path) -> None:
    with LocalHub("cov-rt-default") as h:
        assert h.process is not None and "--rt" not in list(h.process.args)  # type: ignore[arg-type]
    for rt in (False, True):
        with LocalHub(f"cov-rt-{int(rt)}", rt=rt, queue_kib=8) as h:
            assert h.process is not None
            args = list(h.process.args)  # type: ignore[arg-type]
            assert ("--rt" in args) is rt
            assert args[args.index("--queue-kib") + 1] == "8" and "--stats" not in args


def test_a_burst_led_by_a_remote_frame_is_counted_by_its_records(hub: Hub) -> None:
    """The one-frame shortcut reads the record's byte count, not its DLC: a remote frame
    has DLC 8 and no data bytes, so a burst of it and a 1-byte frame is 7 + 8 bytes long."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    src, dst = _Node(a, "src"), _Node(c, "dst")
    hub._order = (src, dst)
    remote = HEADER.pack(0x100, 0, 8, 0)
    burst = remote + frame(0x101, b"\x01")
    assert len(burst) == HEADER.size + 8
    hub._forward(src, burst)
    hub._forward(src, remote)
    assert d.recv(64) == burst and d.recv(64) == remote
    assert src.frames_in == dst.frames_out == hub.frames == 3
    for s in (a, b, c, d):
        s.close()


class IdlePoll:
    """The hub's poll with no node and nothing to read: each call times out, advancing the
    simulated clock by its timeout."""

    def __init__(self, hub: Hub, clock: FakeClock) -> None:
        self.hub, self.clock, self.calls = hub, clock, 0

    def poll(self, timeout_ms: int) -> list[tuple[int, int]]:
        self.calls += 1
        assert self.calls < 100, "the idle hub does not leave"
        self.clock.now += timeout_ms / 1000.0
        return []

    def register(self, *_: object) -> None:
        pass


@pytest.mark.parametrize(("start_s", "idle_exit_s"), [(0.0, 0.4), (1000.0, 0.5)])
def test_an_idle_hub_leaves_only_once_idle_for_longer_than_asked(
        hub: Hub, monkeypatch: pytest.MonkeyPatch, start_s: float, idle_exit_s: float) -> None:
    """Polls of 200 ms: idle 0.2, 0.4 (not yet longer than 0.4), 0.6 s; the clock's origin
    (monotonic time is arbitrary) does not matter."""
    clock = FakeClock()
    clock.now = start_s
    monkeypatch.setattr(hub_mod, "time", clock)
    poll = IdlePoll(hub, clock)
    hub._poll = poll  # type: ignore[assignment]
    hub.run(idle_exit_s=idle_exit_s)
    assert poll.calls == 3


def test_the_hub_process_asks_for_real_time_only_with_rt(
        can_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[str] = []
    monkeypatch.setattr(hub_mod, "make_realtime", asked.append)
    assert hub_mod.main(["--channel", "cov-rt", "--idle-exit", "0"]) == 0
    assert asked == []
    assert hub_mod.main(["--channel", "cov-rt", "--idle-exit", "0", "--rt"]) == 0
    assert asked == ["can_db.transport.hub"]


def test_a_stopped_hub_leaves_no_open_pipe(can_dir: Path) -> None:
    h = LocalHub("cov-pipes").start()
    proc = h.process
    assert proc is not None and proc.stdout is not None and proc.stderr is not None
    h.stop()
    assert proc.stdout.closed and proc.stderr.closed


class BrokenSocket:
    """A node connection whose read fails (the peer reset it)."""

    closed = False

    def fileno(self) -> int:
        return 98

    def recv(self, _size: int) -> bytes:
        raise ConnectionResetError

    def close(self) -> None:
        self.closed = True


class ResetOnceSocket(BrokenSocket):
    """A node that left with frames for it unread: one reset, then its last packet."""

    def __init__(self) -> None:
        self.reads = [ConnectionResetError(), frame(), b""]

    def recv(self, _size: int) -> bytes:
        got = self.reads.pop(0)
        if isinstance(got, Exception):
            raise got
        return got


def test_a_reset_node_s_last_packet_is_still_forwarded(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    leaving, healthy = ResetOnceSocket(), _Node(a, "healthy")
    hub.nodes = {98: _Node(leaving, "leaving"), a.fileno(): healthy}  # type: ignore[arg-type]
    hub._order = (hub.nodes[98], healthy)
    hub._poll = ScriptedPoll(hub, [[(98, select.POLLIN)],  # type: ignore[assignment]
                                   [(98, select.POLLIN)]])
    hub.run()
    assert b.recv(64) == frame() and healthy.frames_out == 1
    assert leaving.closed and [n["name"] for n in hub.left] == ["leaving"]
    a.close()
    b.close()


def test_a_failed_read_drops_that_node_and_the_hub_keeps_running(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    broken, healthy = BrokenSocket(), _Node(a, "healthy")
    hub.nodes = {98: _Node(broken, "reset"), a.fileno(): healthy}  # type: ignore[arg-type]
    hub._order = (hub.nodes[98], healthy)
    script = ScriptedPoll(hub, [[(98, select.POLLIN)], []])
    hub._poll = script  # type: ignore[assignment]
    hub.run()
    assert script.calls == 2                      # the loop went on after the failed read
    assert broken.closed and hub.nodes == {a.fileno(): healthy} and hub._order == (healthy,)
    assert [n["name"] for n in hub.left] == ["reset"]
    a.close()
    b.close()


def test_a_spurious_wake_up_of_one_node_does_not_delay_anothers_packet(hub: Hub) -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    e, f = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (a, c):
        s.setblocking(False)
    quiet, src, dst = _Node(a, "quiet"), _Node(c, "src"), _Node(e, "dst")
    hub.nodes = {a.fileno(): quiet, c.fileno(): src, e.fileno(): dst}
    hub._order = (quiet, src, dst)
    d.send(frame())
    hub._poll = ScriptedPoll(hub, [[(a.fileno(), select.POLLIN),  # type: ignore[assignment]
                                    (c.fileno(), select.POLLIN)]])
    hub.run()
    assert hub.frames == 1 and f.recv(64) == frame()
    for s in (a, b, c, d, e, f):
        s.close()


def test_the_wait_is_reported_to_a_tenth_of_a_millisecond() -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    node = _Node(a, "rec", lossless=True, waited_s=0.0123456)
    assert _node_stats(node)["waited_s"] == 0.0123
    a.close()
    b.close()


def test_a_hello_without_a_body_still_makes_a_member(hub: Hub) -> None:
    """The smallest control packet is a bare header; a hello without its JSON keeps the
    defaults (name "?", lossy) and is welcomed like any other."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    node = _Node(a)
    bare = HEADER.pack(CTRL_HELLO, 0x80, 0, 0)
    assert len(bare) == HEADER.size
    hub._handle(a.fileno(), node, bare)
    assert hub._order == (node,) and node.name == "?" and not node.lossless
    assert HEADER.unpack_from(b.recv(64))[0] == CTRL_WELCOME
    a.close()
    b.close()


class SlowSocket:
    """A lossless node's connection whose queue is full once, then has room again."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []
        self.full = True

    def fileno(self) -> int:
        return 97

    def send(self, packet: bytes) -> int:
        if self.full:
            self.full = False
            raise BlockingIOError
        self.sent.append(packet)
        return len(packet)


def test_a_waited_for_node_does_not_end_the_delivery_to_the_others(
        hub: Hub, monkeypatch: pytest.MonkeyPatch) -> None:
    clock, timeouts = FakeClock(), []
    poller = SleepingPoller(clock, [0.001], timeouts)  # the recorder reads after 1 ms
    monkeypatch.setattr(hub_mod, "time", clock)
    monkeypatch.setattr(hub_mod, "select", type("Select", (), {
        "poll": staticmethod(lambda: poller), "POLLOUT": select.POLLOUT}))
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    c, d = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    slow = SlowSocket()
    src, rec, other = (_Node(a, "src"), _Node(slow, "rec", lossless=True),  # type: ignore[arg-type]
                       _Node(c, "other"))
    hub._order = (src, rec, other)
    d.setblocking(False)                          # nothing delivered: an error, not a hang
    hub._forward(src, frame())
    assert slow.sent == [frame()] and rec.frames_out == 1 and rec.dropped == 0
    assert d.recv(64) == frame() and other.frames_out == 1
    for s in (a, b, c, d):
        s.close()


def test_closing_the_hub_disconnects_and_counts_every_node(can_dir: Path) -> None:
    h = Hub("cov-close-nodes")
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    h.nodes[a.fileno()] = _Node(a, "here", frames_in=5)
    h.close()
    assert a.fileno() == -1 and b.recv(64) == b""      # the node sees the end of stream
    assert h.nodes == {} and [n["name"] for n in h.left] == ["here"]
    b.close()


def test_a_runt_packet_is_ignored(hub: Hub) -> None:
    """Shorter than a header: neither a frame nor a control packet, whatever its bytes."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    b.setblocking(False)
    node = _Node(a)
    hub.nodes[a.fileno()] = node
    for runt in (b"\x01", b"\x01\x02\x03", bytes((CTRL_HELLO, 0, 0, 0, 0x80, 0))):
        hub._handle(a.fileno(), node, runt)
    assert hub._order == () and hub.nodes == {a.fileno(): node}
    with pytest.raises(BlockingIOError):          # no welcome
        b.recv(64)
    a.close()
    b.close()
