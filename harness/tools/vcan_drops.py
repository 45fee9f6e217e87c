"""The SocketCAN check's flood step: a node that does not read while another floods the
interface, then reads what its socket kept. The kernel's drop count for that socket
(can_db/transport/socketcan.py) must be every frame it did not get.

Usage (inside the Linux with vcan0): ``python -m harness.tools.vcan_drops --bus
socketcan:vcan0 --frames 20000 --out drops.json``; vcan_check.py judges the JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import can

from can_db.transport.bus import open_bus

FLOOD_ID = 0x7FE  # not in the DBC: the loop's receivers reject it (unknown ID)
SEND_RETRY_S = 0.001  # the sender's own queue full (ENOBUFS): wait and resend
READ_IDLE_S = 0.5  # wall s without a frame that ends the read-back


def flood_and_count(spec: str, frames: int) -> dict[str, int]:
    """Flood ``frames`` frames while a second node does not read, then read back what its
    socket kept; its counters beside what was sent."""
    reader = open_bus(spec)
    sender = open_bus(spec)
    try:
        for i in range(frames):
            msg = can.Message(arbitration_id=FLOOD_ID, data=i.to_bytes(4, "little"),
                              is_extended_id=False)
            while True:
                try:
                    sender.send(msg)
                    break
                except can.CanOperationError:
                    time.sleep(SEND_RETRY_S)
        received = 0
        while reader.recv(timeout=READ_IDLE_S) is not None:
            received += 1
        stats = reader.stats()
        return {"sent": frames, "received": received,
                "rx_dropped": int(stats.get("rx_dropped", -1)),
                "rcvbuf_bytes": int(getattr(reader, "rcvbuf_bytes", -1))}
    finally:
        reader.shutdown()
        sender.shutdown()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vcan_drops", description=__doc__.split("\n")[0])
    parser.add_argument("--bus", default="socketcan:vcan0")
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    result = flood_and_count(args.bus, args.frames)
    args.out.write_text(json.dumps(result) + "\n")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
