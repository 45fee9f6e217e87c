"""SocketCAN with the receive side a loop node needs: a sized receive buffer and the
kernel's count of the frames it dropped for this node.

A SocketCAN reader that falls behind loses frames in the kernel: its socket's receive buffer
fills and the kernel drops what follows, counting each drop on the socket (``sk_drops``, the
count ``SO_RXQ_OVFL`` would attach to every received frame). python-can's SocketCAN reader
accepts only the time stamp as ancillary data, so the count is read with
``getsockopt(SO_MEMINFO)`` instead: the same counter, read when asked, nothing added to the
receive path.

The receive buffer: Linux's default (``net.core.rmem_default``, 208 KiB on Debian) holds a
few hundred CAN frames (each queued frame costs its socket-buffer overhead, not 16 bytes).
``RCVBUF_BYTES`` asks for 1 MiB: about 2,700 frames on vcan0 (measured: ≈ 770 B each, the
kernel reporting twice the size asked), 1.8 s of the loop's 1,500 frames/s (15 a cycle at
100 Hz), so a reader stalled that long loses nothing. As root ``SO_RCVBUFFORCE`` sets it past
``net.core.rmem_max``; otherwise the kernel caps it there and ``rcvbuf_bytes`` says what it
got.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

from can.interfaces.socketcan import SocketcanBus

RCVBUF_BYTES = 1 << 20  # requested receive buffer of a loop node, bytes (module doc)
# a capture tool (rhonn-bus dump) is not in the loop and may be slower than it (printing
# every frame): 16 MiB hold about 44 000 frames (16 × the 2,700 measured for 1 MiB), more than
# a whole main job's 16 950
CAPTURE_RCVBUF_BYTES = 16 << 20
# <asm-generic/socket.h> and <linux/sock_diag.h>: not in Python's socket module
SO_MEMINFO = 55
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
SK_MEMINFO_DROPS = 8  # index of the drop count in SO_MEMINFO's u32 array (Linux ≥ 4.14)
_MEMINFO_BYTES = 4 * (SK_MEMINFO_DROPS + 1)


def socket_drops(sock: socket.socket) -> int | None:
    """Frames (datagrams) the kernel dropped for ``sock`` because its receive buffer was
    full, since the socket was opened; None where the kernel does not report it."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, _MEMINFO_BYTES)
    except OSError:
        return None
    if len(raw) < _MEMINFO_BYTES:
        return None
    return int(struct.unpack_from("=I", raw, 4 * SK_MEMINFO_DROPS)[0])


def rx_dropped(bus: object) -> int | None:
    """Frames the kernel dropped for ``bus``'s socket (a :class:`CountingSocketcanBus`'s
    ``stats()``); None for a bus that keeps no such count (the local hub counts its own)."""
    stats = getattr(bus, "stats", None)
    value = stats().get("rx_dropped") if callable(stats) else None
    return value if isinstance(value, int) else None


def size_receive_buffer(sock: socket.socket, wanted_bytes: int) -> int:
    """Ask for a ``wanted_bytes`` receive buffer (forced past rmem_max where permitted);
    returns the size the kernel reports (bytes, its doubled bookkeeping value)."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, wanted_bytes)
    except OSError:  # not CAP_NET_ADMIN: capped at net.core.rmem_max
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, wanted_bytes)
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


class CountingSocketcanBus(SocketcanBus):
    """python-can's SocketCAN bus with a ``rcvbuf_bytes`` receive buffer and ``stats()``:
    ``rx_dropped``, the frames the kernel dropped for this node (see the module doc)."""

    def __init__(self, channel: str, *, rcvbuf_bytes: int = RCVBUF_BYTES,
                 **kwargs: Any) -> None:
        self._drops_at_shutdown: int | None = None
        self._closed = False  # (set first: python-can's __del__ may call shutdown)
        super().__init__(channel=channel, **kwargs)
        self.rcvbuf_bytes = size_receive_buffer(self.socket, rcvbuf_bytes)

    def stats(self) -> dict[str, int]:
        """Counters for a node's summary: ``rx_dropped`` (after ``shutdown``: the count at
        that moment; absent where the kernel does not report it)."""
        drops = self._drops_at_shutdown if self._closed else socket_drops(self.socket)
        return {} if drops is None else {"rx_dropped": drops}

    def shutdown(self) -> None:
        if not self._closed:  # the count dies with the socket: keep it for the summary
            self._drops_at_shutdown = socket_drops(self.socket)
            self._closed = True
        super().shutdown()
