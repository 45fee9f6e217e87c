"""Bus flood: frames with IDs that are not in the DBC, at a fixed rate (fault ``flood:RATE``).

Run by the harness as its own OS process: ``python -m harness.run.flood --bus SPEC --rate 5000``.
Paced in 1 ms batches on the monotonic clock; stops on SIGTERM/SIGINT. Note: 5000 frames/s
of 8-byte frames is more than a real 500 kbit/s CAN bus carries (~3900 frames/s at best);
the loopback server has no such limit, so this is a software stress test, not a bus-load one.
"""

from __future__ import annotations

import argparse
import time

import can

from can_db.process.stopflag import StopFlag
from can_db.transport.bus import BusDisconnected, open_bus

FLOOD_IDS = (0x050, 0x3A0, 0x6F0, 0x7E0)  # not in the DBC; 0x050 outranks our frames


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.run.flood", description=__doc__)
    parser.add_argument("--bus", required=True)
    parser.add_argument("--rate", type=float, default=5000.0, help="frames per second")
    args = parser.parse_args(argv)
    stop = StopFlag()
    bus = open_bus(args.bus, reconnect_s=5.0)
    print("ready flood", flush=True)
    sent, start = 0, time.monotonic()
    try:
        while not stop():
            due = int((time.monotonic() - start) * args.rate)
            while sent < due:
                bus.send(can.Message(arbitration_id=FLOOD_IDS[sent % len(FLOOD_IDS)],
                                     data=sent.to_bytes(8, "little"), is_extended_id=False))
                sent += 1
            time.sleep(0.001)
    except BusDisconnected:
        pass
    finally:
        bus.shutdown()
    elapsed = time.monotonic() - start
    print(f"flood sent {sent} frames in {elapsed:.1f} s ({sent / max(elapsed, 1e-9):.0f}/s)",
          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
