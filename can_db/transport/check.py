"""Bus argument check run before anything starts: the spec parses and the bus is there
(SocketCAN interface present, loopback server answering), with a hint when it is not."""

from __future__ import annotations

import socket
from urllib.parse import urlparse

from can_db.process.argcheck import UsageError
from can_db.transport.bus import BusSpecError, parse_spec
from can_db.transport.server import vcan_available

SOCKETCAN_HINT = ("load the virtual CAN driver and create the interface "
                  "(sudo modprobe vcan && sudo ip link add dev {iface} type vcan && "
                  "sudo ip link set up {iface}), or use this machine's local bus: --bus "
                  "local:NAME (the first program on a channel starts its hub; rhonn-harness "
                  "--bus auto starts one of its own)")


def socketcan_supported() -> bool:
    """True when this kernel lets a process open a raw CAN socket (CONFIG_CAN, CAN_RAW)."""
    if not hasattr(socket, "AF_CAN"):
        return False
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        return False
    return True


def check_bus(spec: str, connect_timeout_s: float = 1.0, *, allow_auto: bool = True) -> None:
    """Raise :class:`UsageError` unless ``spec`` names a bus that is there now.

    ``auto`` passes when ``allow_auto`` (the harness falls back to a new loopback server).
    ``socketcan:IFACE`` needs the kernel's CAN support and the interface up; ``remote:ws://127.0.0.1:PORT/``
    needs a server accepting TCP connections on that port. ``virtual:NAME`` is refused: every
    caller is a program whose peers are other processes, and python-can's virtual bus never
    leaves the process that opened it. ``local:NAME`` passes (its hub starts on demand).
    """
    try:
        kind, channel = parse_spec(spec)
    except BusSpecError as exc:
        raise UsageError(str(exc)) from None
    if kind == "auto" and not allow_auto:
        raise UsageError("--bus auto is resolved by rhonn-harness; name the bus here "
                         "(local:NAME, socketcan:IFACE or remote:ws://127.0.0.1:PORT/ from "
                         "`rhonn-bus serve`)")
    if kind == "virtual":
        raise UsageError(f"bus {spec}: python-can's virtual bus stays inside one process, so "
                         f"the other programs would never see its frames; use local:{channel} "
                         "(this machine's local bus) or socketcan:vcan0")
    if kind == "socketcan":
        if not socketcan_supported():
            raise UsageError(f"bus {spec}: this kernel has no SocketCAN support; "
                             + SOCKETCAN_HINT.format(iface=channel))
        if not vcan_available(channel):
            raise UsageError(f"bus {spec}: no SocketCAN interface {channel!r} is up; "
                             + SOCKETCAN_HINT.format(iface=channel))
    elif kind == "remote":
        url = urlparse(channel)
        try:
            port = url.port
        except ValueError:
            port = None
        if url.scheme != "ws" or url.hostname is None or port is None:
            raise UsageError(f"bus {spec}: expected remote:ws://127.0.0.1:PORT/")
        try:
            with socket.create_connection((url.hostname, port), timeout=connect_timeout_s):
                pass
        except OSError as exc:
            raise UsageError(
                f"bus {spec}: no loopback bus server answers on {url.hostname}:{port} "
                f"({exc.strerror or exc}); start one with `rhonn-bus serve`, or let "
                "rhonn-harness start its own with --bus auto") from None
