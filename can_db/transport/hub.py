"""The hub of a local CAN channel (:mod:`can_db.transport.localbus`) and its manager.

  python -m can_db.transport.hub --channel NAME [--queue-kib K] [--idle-exit S]
                                 [--stats FILE] [--rt]

One process per channel; it is the channel's single point of order, as the kernel is for a
``vcan``: every packet (one frame, or a burst sent with ``send_many``) goes to every other
node in the order the hub read it, so a frame that answers another is never seen before it by
a third node (the bus recorder relies on that). The hub holds ``NAME.lock`` (``flock``) while
it runs: a second hub for the channel refuses to start, and a hub killed with SIGKILL leaves
only a socket file, which the next hub replaces (the kernel dropped the lock). Writes never
block: each node's queue is its connection's kernel send buffer (``--queue-kib``, default
4 MiB, some thousands of frames); a packet that does not fit is dropped and its frames
counted for that node. The one exception is a node that joined as *lossless* (the lockstep
bus recorder): when its queue is full the hub waits for room, at most ``LOSSLESS_WAIT_S`` per
packet, so a slow recorder slows the loop instead of losing frames (a lockstep loop's result
does not depend on wall time); a node that lets that wait run out is treated as lossy from
then on and the hub stops waiting for it. SIGTERM/SIGINT stop it cleanly; ``--stats`` then
holds per-node frame, drop and wait counts.

:class:`LocalHub` runs a hub as a managed child process (start, restart, stop) for the
harness, like :class:`can_db.transport.server.BusServer` does for the websocket server.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import itertools
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

from can_db.process.parent import die_with_parent
from can_db.process.rt import freeze_heap, make_realtime

# the wire format only: the hub forwards bytes, so its process never imports python-can
from can_db.transport.wire import (
    CTRL_HELLO,
    CTRL_WELCOME,
    DEFAULT_QUEUE_KIB,
    FLAG_CONTROL,
    HEADER,
    MAX_PACKET,
    check_channel,
    control_packet,
    count_records,
    lock_path,
    socket_path,
)

_counter = itertools.count()
LOSSLESS_WAIT_S = 0.05  # longest wait for room in a lossless node's queue, per packet, wall s


class HubBusyError(RuntimeError):
    """Another hub already serves this channel."""


@dataclass(eq=False)
class _Node:
    sock: socket.socket
    name: str = "?"
    own: bool = False
    frames_in: int = 0  # frames this node sent
    frames_out: int = 0  # frames delivered to this node
    dropped: int = 0  # frames for this node that did not fit its queue
    lossless: bool = False  # the hub waits (bounded) for room in its queue instead of dropping
    waited_s: float = 0.0  # wall time the hub spent waiting for room in its queue, s
    gave_up: bool = False  # a wait ran out: lossy from then on


class Hub:
    """The forwarding loop of one channel (runs in the hub process)."""

    def __init__(self, channel: str, queue_kib: int = DEFAULT_QUEUE_KIB) -> None:
        self.channel = check_channel(channel)
        self.queue_bytes = max(4, queue_kib) * 1024
        self._lock_fh = open(lock_path(channel), "a+")  # noqa: SIM115 - held for our lifetime
        try:
            fcntl.flock(self._lock_fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            self._lock_fh.close()
            raise HubBusyError(f"channel {channel} already has a hub") from exc
        self.path = socket_path(channel)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()  # left behind by a hub that was killed
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.listener.bind(str(self.path))
        os.chmod(self.path, 0o600)
        self.listener.listen(128)
        self.listener.setblocking(False)
        self.nodes: dict[int, _Node] = {}
        self._order: tuple[_Node, ...] = ()
        self.left: list[dict[str, Any]] = []
        self.frames = 0
        self.dropped = 0
        self._poll = select.poll()
        self._poll.register(self.listener.fileno(), select.POLLIN)
        self._stop = False

    def stop(self, *_: object) -> None:
        """Signal handler: leave the loop at its next wake-up."""
        self._stop = True

    def _accept(self) -> None:
        try:
            conn, _ = self.listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        conn.setblocking(False)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.queue_bytes)
        self.nodes[conn.fileno()] = _Node(conn)  # a member (gets frames) after its hello
        self._poll.register(conn.fileno(), select.POLLIN)

    def _drop_node(self, fd: int) -> None:
        node = self.nodes.pop(fd, None)
        if node is None:
            return
        self._order = tuple(n for n in self._order if n is not node)
        with contextlib.suppress(KeyError, ValueError):
            self._poll.unregister(fd)
        node.sock.close()
        self.left.append(_node_stats(node))

    def _control(self, node: _Node, packet: bytes) -> None:
        if HEADER.unpack_from(packet)[0] == CTRL_HELLO:
            with contextlib.suppress(ValueError):
                hello = json.loads(packet[HEADER.size:])
                node.name, node.own = str(hello.get("name", "?")), bool(hello.get("own"))
                node.lossless = bool(hello.get("lossless"))
            try:  # the welcome first, then the frames: a member from now on
                node.sock.send(control_packet(CTRL_WELCOME, {}))
            except OSError:
                return
            if node not in self._order:
                self._order = (*self._order, node)

    def _forward(self, src: _Node, packet: bytes) -> None:
        # one frame (the common case) without walking the records
        frames = 1 if len(packet) == HEADER.size + packet[6] else count_records(packet)
        src.frames_in += frames
        self.frames += frames
        dead = None
        for node in self._order:
            if node is src and not node.own:
                continue
            try:
                node.sock.send(packet)
                node.frames_out += frames
            except BlockingIOError:
                try:
                    if node.lossless and self._send_when_room(node, packet):
                        node.frames_out += frames
                        continue
                except OSError:  # the lossless node left while the hub waited for it
                    dead = [*(dead or []), node]
                    continue
                node.dropped += frames
                self.dropped += frames
            except OSError:
                dead = [*(dead or []), node]
        if dead:
            self._stop_sending(dead)

    def _stop_sending(self, gone: list[_Node]) -> None:
        """Nodes whose connection failed on a write get no more frames; each is dropped at
        its end of stream, after the packets it sent before it left have been read and
        forwarded (a node that closes with frames for it unread would otherwise lose its
        last frames)."""
        self._order = tuple(n for n in self._order if n not in gone)
        for node in gone:
            with contextlib.suppress(OSError):  # the node, if alive, sees the hub leave
                node.sock.shutdown(socket.SHUT_WR)

    def _send_when_room(self, node: _Node, packet: bytes) -> bool:
        """A lossless node's queue is full: wait (at most LOSSLESS_WAIT_S) until it takes
        ``packet``. False when the wait ran out (the node is lossy from then on)."""
        start = time.monotonic()
        waiter = select.poll()
        waiter.register(node.sock.fileno(), select.POLLOUT)
        try:
            while True:
                left_ms = (LOSSLESS_WAIT_S - (time.monotonic() - start)) * 1000.0
                if left_ms <= 0.0:
                    node.lossless, node.gave_up = False, True
                    return False
                waiter.poll(max(1, int(left_ms)))
                try:
                    node.sock.send(packet)
                    return True
                except (BlockingIOError, InterruptedError):
                    continue
        finally:
            node.waited_s += time.monotonic() - start

    def _handle(self, fd: int, node: _Node, packet: bytes) -> None:
        """A packet that is not a data packet: end of stream (empty: the node left or
        failed), a runt (ignored) or a control packet. The forwarding loop reads one packet
        per readable node per wake-up (level-triggered: the next poll sees the rest;
        reading until EAGAIN would cost an exception per wake-up)."""
        if not packet:
            self._drop_node(fd)
        elif len(packet) >= HEADER.size and packet[4] & FLAG_CONTROL:
            self._control(node, packet)

    def run(self, idle_exit_s: float | None = None) -> None:
        """Forward until stopped (or idle for ``idle_exit_s`` s with no node connected)."""
        listen_fd = self.listener.fileno()
        idle_since = time.monotonic()
        poll = self._poll.poll
        nodes = self.nodes
        while not self._stop:
            try:
                events = poll(200)
            except InterruptedError:
                continue
            for fd, _ in events:
                if fd == listen_fd:
                    self._accept()
                    continue
                node = nodes.get(fd)  # the common case inline: one data packet
                if node is not None:
                    try:
                        packet = node.sock.recv(MAX_PACKET)
                    except (BlockingIOError, InterruptedError):
                        continue
                    except ConnectionResetError:
                        packet = _read_after_reset(node.sock)
                    except OSError:
                        packet = b""
                    if len(packet) >= HEADER.size and not packet[4] & FLAG_CONTROL:
                        self._forward(node, packet)
                    else:
                        self._handle(fd, node, packet)
            if idle_exit_s is not None:
                if self.nodes:
                    idle_since = time.monotonic()
                elif time.monotonic() - idle_since > idle_exit_s:
                    return

    def stats(self) -> dict[str, Any]:
        """Frame and drop counts, per node (connected and departed)."""
        return {"channel": self.channel, "frames": self.frames, "dropped": self.dropped,
                "queue_bytes": self.queue_bytes,
                "nodes": [_node_stats(n) for n in self.nodes.values()] + self.left}

    def close(self) -> None:
        """Disconnect every node, remove the socket file, release the lock."""
        for fd in list(self.nodes):
            self._drop_node(fd)
        self.listener.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        with contextlib.suppress(FileNotFoundError):  # a clean exit leaves no file behind
            lock_path(self.channel).unlink()  # still held here: a hub starting now refuses
        self._lock_fh.close()


def _read_after_reset(sock: socket.socket) -> bytes:
    """The node closed with frames for it unread: the kernel reports that once, before the
    packets it sent; those are still read and forwarded (then its end of stream drops it),
    as a vcan forwards every frame a node sent before it left. b"" when nothing follows."""
    try:
        return sock.recv(MAX_PACKET)
    except OSError:
        return b""


def _node_stats(node: _Node) -> dict[str, Any]:
    stats: dict[str, Any] = {"name": node.name, "frames_in": node.frames_in,
                             "frames_out": node.frames_out, "dropped": node.dropped}
    if node.lossless or node.gave_up:
        stats.update(lossless=not node.gave_up, waited_s=round(node.waited_s, 4))
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m can_db.transport.hub", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--channel", required=True)
    parser.add_argument("--queue-kib", type=int, default=DEFAULT_QUEUE_KIB,
                        help="per-node queue (kernel send buffer), KiB")
    parser.add_argument("--idle-exit", type=float, default=None,
                        help="exit after S s without any node (auto-started hubs)")
    parser.add_argument("--stats", default=None, help="write frame/drop counts here at exit")
    parser.add_argument("--rt", action="store_true",
                        help="SCHED_FIFO (and $RHONN_RT_CPUS affinity) where permitted")
    args = parser.parse_args(argv)
    try:
        hub = Hub(args.channel, args.queue_kib)
    except HubBusyError as exc:
        print(f"can_db.transport.hub: {exc}", file=sys.stderr)
        return 4
    except (OSError, ValueError) as exc:  # ValueError: ChannelError, a bad channel name
        print(f"can_db.transport.hub: cannot serve channel {args.channel!r}: {exc}",
              file=sys.stderr)
        return 3
    signal.signal(signal.SIGTERM, hub.stop)
    signal.signal(signal.SIGINT, hub.stop)
    if args.rt:
        make_realtime("can_db.transport.hub")
    freeze_heap()
    print(f"ready {args.channel} {hub.path}", flush=True)
    try:
        hub.run(args.idle_exit)
    finally:
        stats = hub.stats()
        hub.close()
        if args.stats:
            Path(args.stats).write_text(json.dumps(stats, indent=2) + "\n")
    return 0


START_TIMEOUT_S = 10.0  # default wait for a started hub's ready line, wall s


class LocalHubError(RuntimeError):
    """The hub child process could not be started."""


class LocalHub:
    """A hub for a (fresh) channel as a managed child process that dies with its parent.
    ``queue_kib`` None: ``$RHONN_HUB_QUEUE_KIB`` if set, else the default (4 MiB).
    ``start_timeout_s``: how long :meth:`start` (and :meth:`restart`) wait for the hub's
    ready line, wall s (a slow emulator or a loaded CI machine needs more than the default)."""

    def __init__(self, channel: str | None = None, *, stats_path: Path | None = None,
                 rt: bool = False, queue_kib: int | None = None,
                 start_timeout_s: float = START_TIMEOUT_S) -> None:
        self.channel = check_channel(channel or f"rhonn-{os.getpid()}-{next(_counter)}")
        self.stats_path = stats_path
        if queue_kib is None:
            queue_kib = int(os.environ.get("RHONN_HUB_QUEUE_KIB") or DEFAULT_QUEUE_KIB)
        self.queue_kib = queue_kib
        self.rt = rt
        self.start_timeout_s = start_timeout_s
        self.process: subprocess.Popen[str] | None = None

    @property
    def spec(self) -> str:
        """Bus spec string for :func:`can_db.transport.bus.open_bus`."""
        return f"local:{self.channel}"

    def start(self, timeout_s: float | None = None) -> LocalHub:
        """Start the hub and wait for its ready line (``timeout_s`` None: the hub's
        ``start_timeout_s``)."""
        timeout_s = self.start_timeout_s if timeout_s is None else timeout_s
        cmd = [sys.executable, "-m", "can_db.transport.hub", "--channel", self.channel,
               "--queue-kib", str(self.queue_kib)]
        if self.stats_path is not None:
            cmd += ["--stats", str(self.stats_path)]
        if self.rt:
            cmd.append("--rt")
        self.process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        text=True, preexec_fn=die_with_parent)
        assert self.process.stdout is not None
        ready, _, _ = select.select([self.process.stdout], [], [], timeout_s)
        line = self.process.stdout.readline() if ready else ""
        if not line.startswith("ready"):
            err = ""
            if self.process.poll() is not None and self.process.stderr is not None:
                err = self.process.stderr.read().strip()
            self.stop()
            raise LocalHubError(f"hub for channel {self.channel} did not start: "
                                f"{err or f'no ready line within {timeout_s:g} s'}")
        return self

    def alive(self) -> bool:
        """True while the hub process runs."""
        return self.process is not None and self.process.poll() is None

    def restart(self) -> LocalHub:
        """Stop the hub and start a new one on the same channel (nodes reconnect)."""
        self.stop()
        return self.start()

    def stop(self, timeout_s: float = 3.0) -> None:
        """SIGTERM (then SIGKILL) and reap the hub."""
        proc, self.process = self.process, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=timeout_s)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()

    def kill(self) -> None:
        """SIGKILL the hub (what a crash leaves behind)."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(timeout=5.0)

    def __enter__(self) -> LocalHub:
        return self.start() if self.process is None else self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


if __name__ == "__main__":
    raise SystemExit(main())
