"""A local virtual CAN bus over Unix sockets: python-can interface ``rhonncan``.

Behaves like a Linux ``vcan`` interface for processes on one machine: every frame a node
sends reaches every other node on the same channel (and the sender itself only with
``receive_own_messages=True``), in the order that node sent them. There is no server: the
nodes of a channel form a mesh of ``SOCK_SEQPACKET`` Unix-socket connections in a private
runtime directory (mode 0700, see :func:`runtime_dir`), so a frame costs one kernel copy per
receiver and a single process wake-up; nothing is bound to a network interface.

* **Join/leave at any time**: a joining node takes the channel's lock, connects to every node
  listening in the channel directory, and only then publishes its own socket there; nodes
  accept newcomers whenever they send or receive. A node that leaves (or dies) is dropped
  by its peers at their next read or write.
* **Bounded queues, counted drops**: each connection's kernel send buffer (``queue_kib``,
  default 1 MiB ≈ 1 500 small frames) is the receiver's queue. A send never blocks: a frame
  that does not fit is dropped for that receiver only and counted in :meth:`LocalBus.stats`.
* **SIGKILL leaves nothing harmful**: a dead node's socket file refuses connections; the next
  joiner removes it. The lock is an ``flock``, released by the kernel with the process.
* Classical CAN and CAN FD frames (up to 64 data bytes, BRS/ESI flags), remote and error
  frames, 11- and 29-bit IDs. Receive timestamps are ``time.time()`` at reception, s.

Open it by name, like any python-can interface::

    bus = can.Bus(interface="rhonncan", channel="demo")
    python -m can.logger -i rhonncan -c demo
    python -m can.player -i rhonncan -c demo log.asc

Wire format: a packet holds 1–64 frame records (``send_many`` batches a burst); a record is
``<IBBB`` = arbitration ID, flags, DLC, number of data bytes, then the data bytes.
Flags: 0x01 extended ID, 0x02 remote, 0x04 error frame, 0x08 FD, 0x10 bit-rate switch,
0x20 error-state indicator; 0x80 marks a control packet (node ↔ node, never delivered).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import secrets
import select
import socket
import stat
import struct
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

INTERFACE = "rhonncan"
HEADER = struct.Struct("<IBBB")  # ID, flags, DLC, number of data bytes that follow
FLAG_EXT, FLAG_RTR, FLAG_ERR, FLAG_FD, FLAG_BRS, FLAG_ESI = 0x01, 0x02, 0x04, 0x08, 0x10, 0x20
FLAG_CONTROL = 0x80
CTRL_HELLO = 1  # joiner → peer, first packet of a connection: JSON {"name": str}
DEFAULT_QUEUE_KIB = 1024
MAX_BATCH = 64  # frames per packet at most (send_many)
MAX_PACKET = MAX_BATCH * (HEADER.size + 64)
CHANNEL_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
CAN_DLC_TO_LEN = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


class BusDisconnected(can.CanError):
    """The bus (or the loopback bus server behind it) is gone."""


class LocalBusError(can.CanInitializationError):
    """The local bus could not be opened (bad channel name, unsafe runtime dir)."""


def check_channel(channel: str) -> str:
    """Return ``channel`` if it is a valid channel name (1–64 of ``A-Za-z0-9_.-``)."""
    if not isinstance(channel, str) or not CHANNEL_RE.match(channel):
        raise LocalBusError(f"bad {INTERFACE} channel {channel!r}: use 1-64 characters "
                            "of A-Z a-z 0-9 _ . -")
    return channel


def runtime_dir() -> Path:
    """The private directory holding the channels' sockets and locks (created 0700).

    ``$RHONN_CAN_DIR`` if set, else ``$XDG_RUNTIME_DIR/rhonn-can``, else
    ``/tmp/rhonn-can-UID``. Refuses a directory that is a symlink, owned by another user or
    open to group/others (another user could then listen on our channels).
    """
    env = os.environ.get("RHONN_CAN_DIR")
    if env:
        path = Path(env)
    elif os.environ.get("XDG_RUNTIME_DIR"):
        path = Path(os.environ["XDG_RUNTIME_DIR"]) / "rhonn-can"
    else:
        path = Path("/tmp") / f"rhonn-can-{os.getuid()}"
    with contextlib.suppress(FileExistsError):
        path.mkdir(mode=0o700, parents=True)
    info = os.lstat(path)
    if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
        raise LocalBusError(f"runtime dir {path} is not a directory")
    if info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise LocalBusError(f"runtime dir {path} must be owned by uid {os.getuid()} "
                            "with mode 0700")
    return path


def channel_dir(channel: str) -> Path:
    """The directory holding the listening sockets of the nodes of ``channel``."""
    path = runtime_dir() / check_channel(channel)
    with contextlib.suppress(FileExistsError):
        path.mkdir(mode=0o700)
    return path


def encode_frame(msg: can.Message) -> bytes:
    """One wire packet for ``msg``; raises ValueError for data that no CAN frame holds."""
    data = bytes(msg.data) if msg.data is not None else b""
    limit = 64 if msg.is_fd else 8
    if len(data) > limit:
        raise ValueError(f"{len(data)} data bytes do not fit a "
                         f"{'CAN FD' if msg.is_fd else 'classical CAN'} frame")
    if msg.is_fd and len(data) not in CAN_DLC_TO_LEN:
        raise ValueError(f"{len(data)} bytes is not a valid CAN FD length")
    flags = ((FLAG_EXT if msg.is_extended_id else 0) | (FLAG_RTR if msg.is_remote_frame else 0)
             | (FLAG_ERR if msg.is_error_frame else 0) | (FLAG_FD if msg.is_fd else 0)
             | (FLAG_BRS if msg.bitrate_switch else 0)
             | (FLAG_ESI if msg.error_state_indicator else 0))
    return HEADER.pack(msg.arbitration_id & 0x1FFFFFFF, flags, msg.dlc & 0xFF, len(data)) + data


def decode_frame(packet: bytes, channel: str | None = None,
                 timestamp: float | None = None, offset: int = 0) -> can.Message:
    """The python-can Message of the frame record at ``offset`` of a wire packet
    (``timestamp`` in s, default now)."""
    arb, flags, dlc, size = HEADER.unpack_from(packet, offset)
    start = offset + HEADER.size
    data = packet[start:start + size]
    if not flags:  # the common case: a classical data frame with an 11-bit ID
        return can.Message(timestamp=time.time() if timestamp is None else timestamp,
                           arbitration_id=arb, is_extended_id=False, dlc=dlc,
                           data=data, channel=channel, is_rx=True)
    return can.Message(
        timestamp=time.time() if timestamp is None else timestamp, arbitration_id=arb,
        is_extended_id=bool(flags & FLAG_EXT), is_remote_frame=bool(flags & FLAG_RTR),
        is_error_frame=bool(flags & FLAG_ERR), is_fd=bool(flags & FLAG_FD),
        bitrate_switch=bool(flags & FLAG_BRS), error_state_indicator=bool(flags & FLAG_ESI),
        dlc=dlc, data=data, channel=channel, is_rx=True)


def control_packet(opcode: int, payload: dict[str, Any]) -> bytes:
    """A control packet between two nodes (never delivered as a frame)."""
    body = json.dumps(payload).encode()[:255]
    return HEADER.pack(opcode, FLAG_CONTROL, 0, len(body)) + body


def _read_hello(conn: socket.socket, timeout_s: float = 0.1) -> str:
    """The name in a newcomer's hello (its first packet, sent right after its connect), or
    "?" when it does not come within ``timeout_s``; anything else stays queued."""
    waiter = select.poll()
    waiter.register(conn.fileno(), select.POLLIN)
    if not waiter.poll(int(timeout_s * 1000)):
        return "?"
    try:
        packet = conn.recv(MAX_PACKET, socket.MSG_PEEK)
    except OSError:
        return "?"
    if len(packet) < HEADER.size or not packet[4] & FLAG_CONTROL:
        return "?"
    conn.recv(MAX_PACKET)
    try:
        return str(json.loads(packet[HEADER.size:]).get("name", "?"))
    except ValueError:
        return "?"


@dataclass
class _Peer:
    """One connection to another node of the channel."""

    sock: socket.socket
    name: str = "?"
    dropped: int = 0  # our frames that did not fit this peer's queue


class LocalBus(can.BusABC):
    """python-can bus on a local channel (see the module docstring).

    ``channel``: channel name (1–64 of ``A-Za-z0-9_.-``); ``receive_own_messages``: also
    return the frames this node sends; ``queue_kib``: per-receiver queue, KiB;
    ``node_name``: how peers name this node in their drop counts.
    """

    def __init__(self, channel: Any = "rhonn", *, receive_own_messages: bool = False,
                 queue_kib: int = DEFAULT_QUEUE_KIB, node_name: str | None = None,
                 **kwargs: Any) -> None:
        self.channel_name = check_channel(str(channel))
        self.channel_info = f"{INTERFACE} channel {self.channel_name}"
        self.receive_own_messages = bool(receive_own_messages)
        self.node_name = node_name or f"{Path(sys.argv[0]).name or 'python'}:{os.getpid()}"
        self.queue_bytes = max(4, int(queue_kib)) * 1024
        self.sent = 0
        self.reconnects = 0  # API parity with the remote client: a mesh never reconnects
        self._peers: dict[int, _Peer] = {}
        self._departed_drops: dict[str, int] = {}  # drops counted for peers that left
        self._peer_list: tuple[_Peer, ...] = ()
        self._rx: deque[tuple[bytes, int]] = deque()  # (packet, offset of a frame record)
        self._poll = select.poll()
        self._listen_poll = select.poll()  # newcomers waiting (poll(0) is cheaper than a
        self._listener, self._path = self._join()  # failed accept with its exception)
        self._listen_poll.register(self._listener.fileno(), select.POLLIN)
        super().__init__(channel=self.channel_name, **kwargs)

    # -- membership ---------------------------------------------------------------------
    def _join(self) -> tuple[socket.socket, Path]:
        for _attempt in range(5):  # the directory may vanish under us (last node leaving)
            try:
                return self._join_once()
            except FileNotFoundError:
                time.sleep(0.01)
        raise LocalBusError(f"cannot join {INTERFACE} channel {self.channel_name}")

    def _join_once(self) -> tuple[socket.socket, Path]:
        directory = channel_dir(self.channel_name)
        ident = f"{os.getpid()}-{secrets.token_hex(4)}"
        final = directory / f"{ident}.sock"
        tmp = directory / f".{ident}.tmp"
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            listener.bind(str(tmp))
            listener.listen(128)
            listener.setblocking(False)
            dir_fd = os.open(directory, os.O_RDONLY)
            try:
                fcntl.flock(dir_fd, fcntl.LOCK_EX)  # joins are serialised per channel
                for path in sorted(directory.glob("*.sock")):
                    self._connect_peer(path)
                os.rename(tmp, final)  # only now can later joiners find us
            finally:
                os.close(dir_fd)  # releases the lock
        except BaseException:
            listener.close()
            for fd in list(self._peers):
                self._remove_peer(fd)
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        self._poll.register(listener.fileno(), select.POLLIN)
        return listener, final

    def _connect_peer(self, path: Path) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.settimeout(1.0)
        try:
            sock.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            sock.close()  # a node that died without leaving: its socket is garbage
            with contextlib.suppress(OSError):
                path.unlink()
            return
        except OSError:
            sock.close()
            return
        sock.send(control_packet(CTRL_HELLO, {"name": self.node_name}))
        self._add_peer(sock, path.stem)

    def _add_peer(self, sock: socket.socket, name: str) -> None:
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.queue_bytes)
        self._peers[sock.fileno()] = _Peer(sock, name)
        self._peer_list = tuple(self._peers.values())
        self._poll.register(sock.fileno(), select.POLLIN)

    def _remove_peer(self, fd: int) -> None:
        peer = self._peers.pop(fd, None)
        if peer is None:
            return
        with contextlib.suppress(KeyError, ValueError):
            self._poll.unregister(fd)
        peer.sock.close()
        if peer.dropped:
            self._departed_drops[peer.name] = (self._departed_drops.get(peer.name, 0)
                                               + peer.dropped)
        self._peer_list = tuple(self._peers.values())

    def _accept(self) -> None:
        while self._listen_poll.poll(0):
            try:
                conn, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            self._add_peer(conn, _read_hello(conn))

    # -- python-can API -----------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        rx = self._rx
        if not rx:
            # Whole milliseconds only: BusABC.recv calls again for the rest of its timeout,
            # so a sub-millisecond remainder becomes a short spin, not a late wake-up.
            wait_ms = -1 if timeout is None else int(timeout * 1000.0)
            for fd, _ in self._poll.poll(wait_ms):
                if fd == self._listener.fileno():
                    self._accept()
                else:
                    self._drain(fd)
            if not rx:
                return None, False
        packet, offset = rx.popleft()
        return decode_frame(packet, self.channel_name, None, offset), False

    def _drain(self, fd: int) -> None:
        """Read one packet of a peer that poll found readable (poll is level-triggered: the
        next call sees the rest; reading until EAGAIN would cost an exception per wake-up)
        and queue its frame records."""
        peer = self._peers.get(fd)
        if peer is None:
            return
        try:
            packet = peer.sock.recv(MAX_PACKET)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._remove_peer(fd)
            return
        if not packet:  # the peer left (or died)
            self._remove_peer(fd)
            return
        end = len(packet)
        if end < HEADER.size:
            return
        if packet[4] & FLAG_CONTROL:
            self._control(peer, packet)
            return
        rx = self._rx
        offset = 0
        while offset + HEADER.size <= end:
            rx.append((packet, offset))
            offset += HEADER.size + packet[offset + 6]

    @staticmethod
    def _control(peer: _Peer, packet: bytes) -> None:
        if HEADER.unpack_from(packet)[0] == CTRL_HELLO:
            with contextlib.suppress(ValueError):
                peer.name = str(json.loads(packet[HEADER.size:]).get("name", "?"))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to every other node; never blocks (``timeout`` is ignored): a
        receiver whose queue is full loses this frame, counted in :meth:`stats`."""
        try:
            packet = encode_frame(msg)
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from exc
        self._send_packet(packet, 1)

    def send_many(self, msgs: Sequence[can.Message]) -> None:
        """Send a burst of frames in order, as one packet per receiver (up to MAX_BATCH
        frames each): the receivers wake once per burst instead of once per frame. A
        receiver whose queue is full loses the whole packet (counted per frame)."""
        try:
            records = [encode_frame(m) for m in msgs]
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from exc
        for first in range(0, len(records), MAX_BATCH):
            chunk = records[first:first + MAX_BATCH]
            self._send_packet(b"".join(chunk), len(chunk))

    def _send_packet(self, packet: bytes, frames: int) -> None:
        self._accept()  # newcomers get every frame sent after they joined
        dead = None
        for peer in self._peer_list:
            try:
                peer.sock.send(packet)
            except BlockingIOError:
                peer.dropped += frames
            except OSError:
                dead = [*(dead or []), peer.sock.fileno()]
        if dead:
            for fd in dead:
                self._remove_peer(fd)
        self.sent += frames
        if self.receive_own_messages:
            end, offset = len(packet), 0
            while offset < end:
                self._rx.append((packet, offset))
                offset += HEADER.size + packet[offset + 6]

    def stats(self) -> dict[str, Any]:
        """Frames sent, and frames dropped because a receiver's queue was full (per peer
        name, including peers that have left)."""
        by_peer = dict(self._departed_drops)
        for p in self._peers.values():
            if p.dropped:
                by_peer[p.name] = by_peer.get(p.name, 0) + p.dropped
        return {"sent": self.sent, "peers": len(self._peers),
                "dropped": sum(by_peer.values()), "dropped_by_peer": by_peer}

    def fileno(self) -> int:
        return self._listener.fileno()

    def shutdown(self) -> None:
        if self._listener is not None and self._listener.fileno() >= 0:
            for fd in list(self._peers):
                self._remove_peer(fd)
            self._listener.close()
            with contextlib.suppress(OSError):
                self._path.unlink()
            with contextlib.suppress(OSError):
                self._path.parent.rmdir()  # only when it is empty: the last node left
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        try:
            names = sorted(p.name for p in runtime_dir().iterdir()
                           if p.is_dir() and any(p.glob("*.sock")))
        except (OSError, LocalBusError):
            return []
        return [{"interface": INTERFACE, "channel": name} for name in names]
