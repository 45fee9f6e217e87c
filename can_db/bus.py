"""Open a python-can bus from one spec string.

Specs:
  ``socketcan:vcan0``               SocketCAN interface (real ``can0`` or a ``vcan``)
  ``remote:ws://127.0.0.1:PORT/``   the loopback bus server (python-can-remote)
  ``virtual:NAME``                  python-can's in-process virtual bus (unit tests only)
  ``auto``                          ``socketcan:vcan0`` if that interface is up, else a new
                                    loopback bus server (see :func:`resolve_auto`)

A remote client whose server goes away raises :class:`BusDisconnected` (a ``can.CanError``)
from ``recv``/``send`` instead of hanging or leaking a websocket exception.
"""

from __future__ import annotations

import contextlib
from typing import Any

import can

from can_db.server import BusServer, vcan_available


class BusDisconnected(can.CanError):
    """The bus (or the loopback bus server behind it) is gone."""


class BusSpecError(ValueError):
    """A bus spec string that cannot be parsed."""


def parse_spec(spec: str) -> tuple[str, str]:
    """Split ``kind:channel``; raises BusSpecError for anything else."""
    kind, sep, channel = spec.partition(":")
    if kind == "auto" and not sep:
        return "auto", ""
    if not sep or not channel or kind not in {"socketcan", "remote", "virtual"}:
        raise BusSpecError(
            f"bad bus spec {spec!r}: use socketcan:IFACE, remote:ws://127.0.0.1:PORT/, "
            "virtual:NAME or auto")
    if kind == "remote" and not channel.startswith(("ws://127.", "ws://localhost",
                                                    "ws://[::1]")):
        raise BusSpecError(f"remote bus {channel!r}: only loopback servers are allowed")
    return kind, channel


def resolve_auto(vcan: str = "vcan0") -> tuple[str, BusServer | None]:
    """Resolve ``auto``: the SocketCAN interface if up, else a started loopback server.

    The caller owns the returned server and must stop it.
    """
    if vcan_available(vcan):
        return f"socketcan:{vcan}", None
    server = BusServer().start()
    return server.spec, server


class _SafeRemoteBus(can.BusABC):
    """Wraps python-can-remote's client so a dead server raises BusDisconnected."""

    def __init__(self, url: str, **kwargs: Any) -> None:
        try:
            self._inner = can.Bus(channel=url, interface="remote", **kwargs)
        except (OSError, can.CanError) as exc:
            raise BusDisconnected(f"cannot connect to loopback bus server {url}: {exc}") \
                from exc
        self.channel_info = self._inner.channel_info
        super().__init__(channel=url)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._inner.recv(timeout), False
        except Exception as exc:  # websocket closed, socket errors: the server is gone
            raise BusDisconnected(f"loopback bus server lost: {exc!r}") from exc

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        try:
            self._inner.send(msg, timeout)
        except Exception as exc:
            raise BusDisconnected(f"loopback bus server lost: {exc!r}") from exc

    def fileno(self) -> int:
        return self._inner.fileno()

    def shutdown(self) -> None:
        # The library's own shutdown loops until the server answers the close handshake,
        # which never ends if the server hangs: send the close frame and drop the socket.
        with contextlib.suppress(Exception):
            self._inner.remote_protocol.close()
        with contextlib.suppress(Exception):
            self._inner.socket.close()
        can.BusABC.shutdown(self._inner)
        super().shutdown()


def open_bus(spec: str, **kwargs: Any) -> can.BusABC:
    """Open a python-can bus from ``spec`` (``auto`` is not accepted here: resolve it first)."""
    kind, channel = parse_spec(spec)
    if kind == "auto":
        raise BusSpecError("resolve 'auto' with resolve_auto() first; it may start a server")
    if kind == "remote":
        return _SafeRemoteBus(channel, **kwargs)
    if kind == "virtual":
        return can.Bus(channel=channel, interface="virtual", **kwargs)
    return can.Bus(channel=channel, interface="socketcan", **kwargs)
