"""The local bus's wire format and its channel files, without python-can.

What the hub (:mod:`can_db.transport.hub`) and its nodes (:mod:`can_db.transport.localbus`)
share: the packet layout, the control opcodes, the channel names and where a channel's socket
and lock live. The hub forwards bytes and never builds a ``can.Message``, so its process
imports this module and not python-can (whose package import loads every log format it
knows, MF4 with asammdf and pandas among them: most of a hub's start).

Wire format: a packet holds 1–64 frame records; a record is ``<IBBB`` = arbitration ID,
flags, DLC, number of data bytes, then the data bytes. Flags: 0x01 extended ID, 0x02 remote,
0x04 error frame, 0x08 FD, 0x10 bit-rate switch, 0x20 error-state indicator; 0x80 marks a
control packet (node ↔ hub, never delivered).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import struct
from pathlib import Path
from typing import Any

INTERFACE = "rhonncan"
HEADER = struct.Struct("<IBBB")  # ID, flags, DLC, number of data bytes that follow
FLAG_EXT, FLAG_RTR, FLAG_ERR, FLAG_FD, FLAG_BRS, FLAG_ESI = 0x01, 0x02, 0x04, 0x08, 0x10, 0x20
FLAG_CONTROL = 0x80
CTRL_HELLO = 1  # node → hub, first packet of a connection: JSON {"name": str, "own": bool}
CTRL_WELCOME = 2  # hub → node once it is a member: frames sent from then on reach it
DEFAULT_QUEUE_KIB = 4096  # per node: ~5 000 small packets; the kernel caps it at wmem_max
MAX_BATCH = 64  # frames per packet at most (send_many)
MAX_PACKET = MAX_BATCH * (HEADER.size + 64)
CHANNEL_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
CAN_DLC_TO_LEN = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


class ChannelError(ValueError):
    """A bad channel name or an unsafe runtime directory."""


def check_channel(channel: str) -> str:
    """Return ``channel`` if it is a valid channel name (1–64 of ``A-Za-z0-9_.-``)."""
    if not isinstance(channel, str) or not CHANNEL_RE.match(channel):
        raise ChannelError(f"bad {INTERFACE} channel {channel!r}: use 1-64 characters "
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
        raise ChannelError(f"runtime dir {path} is not a directory")
    if info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise ChannelError(f"runtime dir {path} must be owned by uid {os.getuid()} "
                           "with mode 0700")
    return path


def socket_path(channel: str) -> Path:
    """Where the hub of ``channel`` listens."""
    return runtime_dir() / f"{check_channel(channel)}.sock"


def lock_path(channel: str) -> Path:
    """The hub's lock file: held (``flock``) while the hub of ``channel`` runs."""
    return runtime_dir() / f"{check_channel(channel)}.lock"


def count_records(packet: bytes) -> int:
    """Number of frame records in a wire packet."""
    end, offset, count = len(packet), 0, 0
    while offset + HEADER.size <= end:
        offset += HEADER.size + packet[offset + 6]
        count += 1
    return count


def control_packet(opcode: int, payload: dict[str, Any]) -> bytes:
    """A control packet between two nodes (never delivered as a frame)."""
    body = json.dumps(payload).encode()[:255]
    return HEADER.pack(opcode, FLAG_CONTROL, 0, len(body)) + body
