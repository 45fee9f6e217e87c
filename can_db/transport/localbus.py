"""A local virtual CAN bus over Unix sockets: python-can interface ``rhonncan``.

Behaves like a Linux ``vcan`` interface for processes on one machine: every frame a node
sends reaches every other node on the same channel (and the sender itself only with
``receive_own_messages=True``), all nodes see the frames in one order, and an answer is never
seen before the frame it answers. The nodes talk to one small hub process per channel
(:mod:`can_db.transport.hub`, the channel's single point of order, like the kernel for a ``vcan``)
over ``SOCK_SEQPACKET`` Unix sockets in a private runtime directory (mode 0700, see
:func:`runtime_dir`); nothing is bound to a network interface.

* **Join/leave at any time**: a node connects to the hub and is a member from then on; a
  node that leaves or dies is dropped by the hub once the frames it sent before have been
  forwarded.
* **Bounded queues, counted drops**: the hub writes to each node without blocking; a node's
  queue is its connection's kernel send buffer (default 4 MiB, some thousands of frames). A node
  that does not read loses its own frames once that is full (counted per node by the hub)
  and never slows the writers.
* **SIGKILL leaves nothing harmful**: a killed node is a closed connection; a killed hub
  leaves a socket file that the next hub replaces (its lock is an ``flock``, released by the
  kernel). With ``reconnect_s`` > 0 nodes ride out a hub restart.
* Classical CAN and CAN FD frames (up to 64 data bytes, BRS/ESI flags), remote and error
  frames, 11- and 29-bit IDs. Receive timestamps are ``time.time()`` at reception, s.
* ``send_many`` sends a burst as one packet: each receiver wakes once per burst.

Open it by name, like any python-can interface (the first node of a channel starts its hub,
which exits a few seconds after the last node left; the harness starts and owns its own)::

    bus = can.Bus(interface="rhonncan", channel="demo")
    python -m can.logger -i rhonncan -c demo
    python -m can.player -i rhonncan -c demo log.asc

The wire format, the channel names and the channel files are in
:mod:`can_db.transport.wire` (shared with the hub, which does not import python-can).
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import socket
import struct
import subprocess
import sys
import termios
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from can_db.process.errors import error_text
from can_db.transport import wire
from can_db.transport.wire import (
    CAN_DLC_TO_LEN,
    CHANNEL_RE,
    CTRL_HELLO,
    CTRL_WELCOME,
    DEFAULT_QUEUE_KIB,
    FLAG_BRS,
    FLAG_CONTROL,
    FLAG_ERR,
    FLAG_ESI,
    FLAG_EXT,
    FLAG_FD,
    FLAG_RTR,
    HEADER,
    INTERFACE,
    MAX_BATCH,
    MAX_PACKET,
    ChannelError,
    control_packet,
    count_records,
)

__all__ = ["CAN_DLC_TO_LEN", "CHANNEL_RE", "CTRL_HELLO", "CTRL_WELCOME", "DEFAULT_QUEUE_KIB",
           "FLAG_BRS", "FLAG_CONTROL", "FLAG_ERR", "FLAG_ESI", "FLAG_EXT", "FLAG_FD",
           "FLAG_RTR", "HEADER", "INTERFACE", "JOIN_TIMEOUT_S", "MAX_BATCH", "MAX_PACKET",
           "BusDisconnected", "LocalBus", "LocalBusError", "check_channel", "control_packet",
           "count_records", "decode_frame", "encode_frame", "lock_path", "runtime_dir",
           "socket_path", "start_detached_hub"]

JOIN_TIMEOUT_S = 5.0


class BusDisconnected(can.CanError):
    """The bus (or the loopback bus server behind it) is gone."""


class LocalBusError(can.CanInitializationError, ChannelError):
    """The local bus could not be opened (bad channel name, unsafe runtime dir, no hub)."""


# The channel helpers of :mod:`can_db.transport.wire`, raising the python-can error a
# python-can interface raises (LocalBusError) instead of wire's ValueError.
def check_channel(channel: str) -> str:
    """Return ``channel`` if it is a valid channel name (1–64 of ``A-Za-z0-9_.-``)."""
    try:
        return wire.check_channel(channel)
    except ChannelError as exc:
        raise LocalBusError(str(exc)) from None


def runtime_dir() -> Path:
    """The private directory of the channels' sockets and locks (see :func:`wire.runtime_dir`)."""
    try:
        return wire.runtime_dir()
    except ChannelError as exc:
        raise LocalBusError(str(exc)) from None


def socket_path(channel: str) -> Path:
    """Where the hub of ``channel`` listens."""
    return runtime_dir() / f"{check_channel(channel)}.sock"


def lock_path(channel: str) -> Path:
    """The hub's lock file: held (``flock``) while the hub of ``channel`` runs."""
    return runtime_dir() / f"{check_channel(channel)}.lock"


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
    if not flags:  # the common case: a classical data frame with an 11-bit ID; positional
        # (timestamp, arbitration_id, is_extended_id, is_remote_frame, is_error_frame,
        # channel, dlc, data): keyword passing is measurably slower
        return can.Message(time.time() if timestamp is None else timestamp, arb, False,
                           False, False, channel, dlc, data)
    return can.Message(
        timestamp=time.time() if timestamp is None else timestamp, arbitration_id=arb,
        is_extended_id=bool(flags & FLAG_EXT), is_remote_frame=bool(flags & FLAG_RTR),
        is_error_frame=bool(flags & FLAG_ERR), is_fd=bool(flags & FLAG_FD),
        bitrate_switch=bool(flags & FLAG_BRS), error_state_indicator=bool(flags & FLAG_ESI),
        dlc=dlc, data=data, channel=channel, is_rx=True)


def start_detached_hub(channel: str, idle_exit_s: float = 3.0) -> None:
    """Start a hub for ``channel`` in its own session; it exits ``idle_exit_s`` after the
    last node left. A second hub started at the same time finds the lock held and exits."""
    subprocess.Popen([sys.executable, "-m", "can_db.transport.hub", "--channel", channel,
                      "--idle-exit", str(idle_exit_s)],
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)


class LocalBus(can.BusABC):
    """python-can bus on a local channel (see the module docstring).

    ``channel``: channel name (1–64 of ``A-Za-z0-9_.-``); ``receive_own_messages``: also
    return the frames this node sends; ``node_name``: how the hub names this node in its
    counts; ``autostart``: start a hub when the channel has none (default True, so python-can's
    tools work by name; the harness passes False and owns its hub); ``reconnect_s`` > 0: a
    lost hub is not fatal at once: while it is away ``recv`` returns None after its timeout,
    ``send`` drops the frame (counted in ``dropped_while_disconnected``) and the node
    reconnects every 50 ms; only a hub away for longer raises BusDisconnected.
    ``lossless``: when this node's queue is full the hub waits (briefly) for it to read
    instead of dropping its frames; for a lockstep recorder, never for a real-time node.
    """

    def __init__(self, channel: Any = "rhonn", *, receive_own_messages: bool = False,
                 reconnect_s: float = 0.0, autostart: bool = True,
                 connect_timeout_s: float = 5.0, node_name: str | None = None,
                 lossless: bool = False, **kwargs: Any) -> None:
        self.channel_name = check_channel(str(channel))
        self.channel_info = f"{INTERFACE} channel {self.channel_name}"
        self.receive_own_messages = bool(receive_own_messages)
        self.reconnect_s = float(reconnect_s)
        self.autostart = bool(autostart)
        self.lossless = bool(lossless)
        self.node_name = (node_name or f"{Path(sys.argv[0]).name or 'python'}:{os.getpid()}"
                          )[:100]
        self.sent = 0
        self.reconnects = 0
        self.dropped_while_disconnected = 0
        self._path = str(socket_path(self.channel_name))
        self._sock: socket.socket | None = None
        self._poll = select.poll()
        self._rx: deque[tuple[bytes, int]] = deque()  # (packet, offset of a frame record)
        self._lost_at: float | None = None
        self._next_try = 0.0
        self._connect(connect_timeout_s)
        super().__init__(channel=self.channel_name, **kwargs)

    # -- connection ----------------------------------------------------------------------
    def _try_connect_once(self) -> bool:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.connect(self._path)
        except (FileNotFoundError, ConnectionRefusedError):
            sock.close()
            return False
        hello: dict[str, Any] = {"own": self.receive_own_messages, "name": self.node_name}
        if self.lossless:
            hello["lossless"] = True
        sock.send(control_packet(CTRL_HELLO, hello))
        # A member once the hub says so: every frame sent after this reaches us.
        sock.settimeout(JOIN_TIMEOUT_S)
        try:
            welcome = sock.recv(MAX_PACKET)
        except OSError:
            welcome = b""
        if len(welcome) < HEADER.size or HEADER.unpack_from(welcome)[:2] != (CTRL_WELCOME,
                                                                            FLAG_CONTROL):
            sock.close()
            return False
        sock.setblocking(False)
        # room for thousands of packets to the hub: a hub that is descheduled for a while (a
        # loaded machine) does not make send() wait
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, DEFAULT_QUEUE_KIB * 1024)
        self._sock = sock
        self._poll = select.poll()
        self._poll.register(sock.fileno(), select.POLLIN)
        return True

    def _connect(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        started = False
        while not self._try_connect_once():
            if not self.autostart:
                raise LocalBusError(f"no hub on {INTERFACE} channel {self.channel_name} "
                                    f"({self._path}); start one with "
                                    "`python -m can_db.transport.hub --channel "
                                    f"{self.channel_name}`")
            if not started:
                start_detached_hub(self.channel_name)
                started = True
            if time.monotonic() > deadline:
                raise LocalBusError(f"hub of {INTERFACE} channel {self.channel_name} did not "
                                    f"come up within {timeout_s:g} s")
            time.sleep(0.02)

    def _lost(self, exc: BaseException | None) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        if self.reconnect_s <= 0.0:
            raise BusDisconnected(f"hub of {INTERFACE} channel {self.channel_name} lost"
                                  + (f": {error_text(exc)}" if exc else "")) from exc
        if self._lost_at is None:
            self._lost_at = time.monotonic()

    def _try_reconnect(self) -> bool:
        now = time.monotonic()
        if self._lost_at is None or now - self._lost_at > self.reconnect_s:
            raise BusDisconnected(f"hub of {INTERFACE} channel {self.channel_name} gone for "
                                  f"more than {self.reconnect_s:.1f} s")
        if now < self._next_try:
            return False
        self._next_try = now + 0.05
        if not self._try_connect_once():
            return False
        self._lost_at = None
        self.reconnects += 1
        return True

    @property
    def connected(self) -> bool:
        """False while the hub is away (reconnecting)."""
        return self._sock is not None

    # -- python-can API ------------------------------------------------------------------
    def recv(self, timeout: float | None = None) -> can.Message | None:
        """python-can's ``recv`` (same semantics); without filters the rest of a burst
        already read (one packet holds a whole burst) is returned at once, without a system
        call, and a frame that is there on the first try skips BusABC's timeout loop."""
        if self._filters is not None:
            return super().recv(timeout)
        if self._rx:
            packet, offset = self._rx.popleft()
            return decode_frame(packet, self.channel_name, None, offset)
        # no filters: BusABC.recv's loop only for the rest of a timeout not used up yet
        start = time.monotonic()
        msg, _ = self._recv_internal(timeout)
        if msg is not None or (timeout is not None and timeout <= 0.0):
            return msg
        remaining = None if timeout is None else timeout - (time.monotonic() - start)
        if remaining is not None and remaining <= 0.0:
            return None
        return super().recv(remaining)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        rx = self._rx
        if not rx:
            sock = self._sock
            if sock is None:
                if not self._try_reconnect():
                    time.sleep(min(timeout if timeout is not None else 0.05, 0.05))
                    return None, False
                sock = self._sock
                assert sock is not None
            # Whole milliseconds only: BusABC.recv calls again for the rest of its timeout,
            # so a sub-millisecond remainder becomes a short spin, not a late wake-up.
            if not self._poll.poll(-1 if timeout is None else int(timeout * 1000.0)):
                return None, False
            try:
                packet = sock.recv(MAX_PACKET)
            except (BlockingIOError, InterruptedError):
                return None, False
            except OSError as exc:
                self._lost(exc)
                return None, False
            if not packet:  # the hub went away
                self._lost(None)
                return None, False
            end = len(packet)
            if end < HEADER.size or packet[4] & FLAG_CONTROL:
                return None, False
            offset = 0
            while offset + HEADER.size <= end:
                rx.append((packet, offset))
                offset += HEADER.size + packet[offset + 6]
        packet, offset = rx.popleft()
        return decode_frame(packet, self.channel_name, None, offset), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame. Waits at most ``timeout`` s (None: 1 s) for room in the queue to
        the hub (it is only full when the hub is stalled), then raises CanOperationError."""
        try:
            packet = encode_frame(msg)
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from exc
        self._send_packet(packet, 1, timeout)

    def send_many(self, msgs: Sequence[can.Message], timeout: float | None = None) -> None:
        """Send a burst in order as one packet (up to MAX_BATCH frames each): every receiver
        wakes once per burst instead of once per frame."""
        try:
            records = [encode_frame(m) for m in msgs]
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from exc
        for first in range(0, len(records), MAX_BATCH):
            chunk = records[first:first + MAX_BATCH]
            self._send_packet(b"".join(chunk), len(chunk), timeout)

    def _send_packet(self, packet: bytes, frames: int, timeout: float | None) -> None:
        if self._sock is None and not self._try_reconnect():
            self.dropped_while_disconnected += frames
            return
        assert self._sock is not None
        try:
            self._sock.send(packet)
        except BlockingIOError:
            self._send_waiting(packet, frames, 1.0 if timeout is None else timeout)
            return
        except OSError as exc:
            self._lost(exc)
            self.dropped_while_disconnected += frames
            return
        self.sent += frames

    def _send_waiting(self, packet: bytes, frames: int, timeout: float) -> None:
        assert self._sock is not None
        out = select.poll()
        out.register(self._sock.fileno(), select.POLLOUT)
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0 or not out.poll(int(remaining * 1000.0) + 1):
                raise can.CanOperationError(f"{INTERFACE} {self.channel_name}: transmit "
                                            "queue full", error_code=errno.ENOBUFS)
            try:
                self._sock.send(packet)
            except BlockingIOError:
                continue
            except OSError as exc:
                self._lost(exc)
                self.dropped_while_disconnected += frames
                return
            self.sent += frames
            return

    def stats(self) -> dict[str, Any]:
        """Frames sent, and frames dropped because the hub was away (receiver-queue drops
        are counted by the hub)."""
        return {"sent": self.sent, "reconnects": self.reconnects,
                "dropped_while_disconnected": self.dropped_while_disconnected}

    def unread_by_hub(self) -> int:
        """Bytes this node sent that the hub has not read yet (0 when disconnected)."""
        if self._sock is None:
            return 0
        try:  # SIOCOUTQ: a Unix socket's send memory is held until the peer has read it
            return struct.unpack("i", fcntl.ioctl(self._sock.fileno(), termios.TIOCOUTQ,
                                                  b"\0" * 4))[0]
        except OSError:
            return 0

    def wait_read_by_hub(self, timeout_s: float) -> bool:
        """Wait (polling every 5 ms, at most ``timeout_s`` s) until the hub has read every
        frame this node sent; True when it has. A node about to exit calls it so that a frame
        another node sends after the exit is forwarded after all of this node's."""
        deadline = time.monotonic() + timeout_s
        while self.unread_by_hub() > 0:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)
        return True

    def fileno(self) -> int:
        return self._sock.fileno() if self._sock is not None else -1

    def shutdown(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        try:
            names = sorted(p.stem for p in runtime_dir().glob("*.sock"))
        except (OSError, LocalBusError):
            return []
        return [{"interface": INTERFACE, "channel": name} for name in names]
