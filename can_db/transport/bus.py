"""Open a python-can bus from one spec string.

Specs:
  ``socketcan:vcan0``               SocketCAN interface (real ``can0`` or a ``vcan``)
  ``local:NAME``                    the local virtual CAN bus over Unix sockets (python-can
                                    interface ``rhonncan``, see :mod:`can_db.transport.localbus`)
  ``remote:ws://127.0.0.1:PORT/``   the websocket bus server (python-can-remote), for a bus
                                    that must span machines
  ``virtual:NAME``                  python-can's in-process virtual bus (unit tests only)
  ``auto``                          ``socketcan:vcan0`` if that interface is up, else a new
                                    local bus channel with its hub (see :func:`resolve_auto`)
  ``remote:new``                    a new websocket bus server (see :func:`resolve_bus`)

A remote client whose server goes away raises :class:`BusDisconnected` (a ``can.CanError``)
from ``recv``/``send`` instead of hanging or leaking a websocket exception.
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Any

import can

from can_db.process.errors import error_text
from can_db.transport.hub import START_TIMEOUT_S as HUB_START_TIMEOUT_S
from can_db.transport.hub import LocalHub, LocalHubError
from can_db.transport.localbus import BusDisconnected, LocalBus, LocalBusError, check_channel
from can_db.transport.server import BusServer, vcan_available
from can_db.transport.socketcan import RCVBUF_BYTES, CountingSocketcanBus

__all__ = ["BusDisconnected", "BusSpecError", "open_bus", "parse_spec", "resolve_auto",
           "resolve_bus", "send_all"]


def send_all(bus: can.BusABC, frames: list[can.Message]) -> None:
    """Send a burst in order: as one batch where the bus supports it (the local bus wakes
    each receiver once per burst), else frame by frame."""
    send_many = getattr(bus, "send_many", None)
    if send_many is not None:
        send_many(frames)
        return
    for frame in frames:
        bus.send(frame)


class BusSpecError(ValueError):
    """A bus spec string that cannot be parsed."""


def parse_spec(spec: str) -> tuple[str, str]:
    """Split ``kind:channel``; raises BusSpecError for anything else."""
    kind, sep, channel = spec.partition(":")
    if kind == "auto" and not sep:
        return "auto", ""
    if not sep or not channel or kind not in {"socketcan", "remote", "virtual", "local"}:
        raise BusSpecError(
            f"bad bus spec {spec!r}: use local:NAME, socketcan:IFACE or "
            "remote:ws://127.0.0.1:PORT/ (rhonn-harness also: auto, remote:new)")
    if kind == "local":
        try:
            check_channel(channel)
        except LocalBusError as exc:
            raise BusSpecError(str(exc)) from exc
    if kind == "remote" and channel != "new" and not channel.startswith(
            ("ws://127.", "ws://localhost", "ws://[::1]")):
        raise BusSpecError(f"remote bus {channel!r}: only loopback servers are allowed")
    return kind, channel


def resolve_auto(vcan: str = "vcan0", *, stats_path: Path | None = None,
                 rt: bool = False, start_timeout_s: float = HUB_START_TIMEOUT_S
                 ) -> tuple[str, LocalHub | BusServer | None]:
    """Resolve ``auto``: ``socketcan:VCAN`` if that interface is up, else a started hub on a
    fresh local channel (``stats_path``: the hub writes its per-node frame and drop counts
    there when stopped; ``rt``: the hub asks for SCHED_FIFO; ``start_timeout_s``: how long
    a started hub or server may take to come up, wall s).

    The caller owns the returned hub and must stop it.
    """
    if vcan_available(vcan):
        return f"socketcan:{vcan}", None
    try:
        hub = LocalHub(stats_path=stats_path, rt=rt, start_timeout_s=start_timeout_s).start()
    except LocalHubError as exc:  # no SEQPACKET Unix sockets (macOS): the websocket server
        print(f"local bus unavailable ({exc}); using the websocket bus server",
              file=sys.stderr)
        server = BusServer(start_timeout_s=start_timeout_s).start()
        return server.spec, server
    return hub.spec, hub


def resolve_bus(spec: str, *, stats_path: Path | None = None, rt: bool = False,
                start_timeout_s: float = HUB_START_TIMEOUT_S
                ) -> tuple[str, LocalHub | BusServer | None]:
    """Resolve the specs that pick or start something: ``auto`` (see :func:`resolve_auto`)
    and ``remote:new`` (starts a websocket bus server); any other spec is returned as it is.
    ``start_timeout_s``: how long a started hub or server may take to come up, wall s.

    The caller owns a returned hub or server (both have ``spec``, ``restart`` and ``stop``)
    and must stop it.
    """
    if spec == "auto":
        return resolve_auto(stats_path=stats_path, rt=rt, start_timeout_s=start_timeout_s)
    if spec == "remote:new":
        server = BusServer(start_timeout_s=start_timeout_s).start()
        return server.spec, server
    parse_spec(spec)
    return spec, None


class _SafeRemoteBus(can.BusABC):
    """Wraps python-can-remote's client so a dead server raises BusDisconnected.

    With ``reconnect_s`` > 0 a lost server is not fatal at once: while disconnected,
    ``recv`` waits out its timeout and returns None, ``send`` drops the frame (counted in
    ``dropped_while_disconnected``), and the client retries every 0.2 s; only when the
    server stays away for ``reconnect_s`` does it raise BusDisconnected.
    """

    def __init__(self, url: str, reconnect_s: float = 0.0, **kwargs: Any) -> None:
        self._url, self._kwargs, self.reconnect_s = url, kwargs, reconnect_s
        self._inner: Any = None
        self._lost_at: float | None = None
        self._next_try = 0.0
        self.reconnects = 0
        self.dropped_while_disconnected = 0
        try:
            self._inner = can.Bus(channel=url, interface="remote", **kwargs)
        except (OSError, can.CanError) as exc:
            raise BusDisconnected(f"cannot connect to loopback bus server {url}: {exc}") \
                from exc
        self.channel_info = self._inner.channel_info
        super().__init__(channel=url)

    @property
    def connected(self) -> bool:
        """False while the server is away (reconnecting)."""
        return self._inner is not None

    def _lost(self, exc: BaseException) -> None:
        self._close_inner()
        if self.reconnect_s <= 0.0:
            raise BusDisconnected(f"loopback bus server lost: {error_text(exc)}") from exc
        if self._lost_at is None:
            self._lost_at = time.monotonic()

    def _try_reconnect(self) -> bool:
        now = time.monotonic()
        if self._lost_at is None or now - self._lost_at > self.reconnect_s:
            raise BusDisconnected(f"loopback bus server {self._url} gone for more than "
                                  f"{self.reconnect_s:.1f} s")
        if now < self._next_try:
            return False
        self._next_try = now + 0.2
        try:
            self._inner = can.Bus(channel=self._url, interface="remote", **self._kwargs)
        except (OSError, can.CanError):
            return False
        self._lost_at = None
        self.reconnects += 1
        return True

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._inner is None and not self._try_reconnect():
            time.sleep(min(timeout if timeout is not None else 0.2, 0.2))
            return None, False
        try:
            return self._inner.recv(timeout), False
        except Exception as exc:  # websocket closed, socket errors: the server is gone
            self._lost(exc)
            return None, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._inner is None and not self._try_reconnect():
            self.dropped_while_disconnected += 1
            return
        try:
            self._inner.send(msg, timeout)
        except Exception as exc:
            self._lost(exc)
            self.dropped_while_disconnected += 1

    def fileno(self) -> int:
        return self._inner.fileno() if self._inner is not None else -1

    def _close_inner(self) -> None:
        inner, self._inner = self._inner, None
        if inner is None:
            return
        # The library's own shutdown loops until the server answers the close handshake,
        # which never ends if the server hangs: send the close frame and drop the socket.
        with contextlib.suppress(Exception):
            inner.remote_protocol.close()
        with contextlib.suppress(Exception):
            inner.socket.close()
        can.BusABC.shutdown(inner)

    def shutdown(self) -> None:
        self._close_inner()
        super().shutdown()


def open_bus_for_process(spec: str, prog: str, reconnect_s: float) -> can.BusABC | None:
    """``open_bus`` for a process's main: on failure print ``prog: cannot open bus …`` to
    stderr and return None (the caller exits with code 3)."""
    try:
        return open_bus(spec, reconnect_s=reconnect_s)
    except (BusDisconnected, OSError, ValueError) as exc:
        print(f"{prog}: cannot open bus {spec}: {exc}", file=sys.stderr)
        return None


def open_bus(spec: str, *, reconnect_s: float = 0.0, autostart: bool = True,
             rcvbuf_bytes: int | None = None, **kwargs: Any) -> can.BusABC:
    """Open a python-can bus from ``spec`` (``auto`` is not accepted here: resolve it first).

    ``reconnect_s``: for the loopback server, how long a lost server may stay away before
    the client gives up (0: at once). SocketCAN interfaces do not go away this way.
    ``autostart``: a ``local:NAME`` channel without a hub gets one (the same rule as
    python-can's ``rhonncan`` interface: the first node of a channel starts its hub, which
    exits 3 s after the last node left); False: no hub is an error.
    ``rcvbuf_bytes``: a SocketCAN socket's receive buffer (None: ``RCVBUF_BYTES``, the loop
    nodes' size; can_db/transport/socketcan.py); other buses ignore it.
    """
    kind, channel = parse_spec(spec)
    if kind == "auto" or spec == "remote:new":
        raise BusSpecError(f"resolve {spec!r} with resolve_bus() first")
    if kind == "local":
        try:
            return LocalBus(channel, reconnect_s=reconnect_s, autostart=autostart, **kwargs)
        except (LocalBusError, OSError) as exc:
            raise BusDisconnected(f"cannot connect to local bus {channel}: {exc}") from exc
    if kind == "remote":
        return _SafeRemoteBus(channel, reconnect_s=reconnect_s, **kwargs)
    if kind == "virtual":
        return can.Bus(channel=channel, interface="virtual", **kwargs)
    return CountingSocketcanBus(channel, rcvbuf_bytes=rcvbuf_bytes or RCVBUF_BYTES, **kwargs)
