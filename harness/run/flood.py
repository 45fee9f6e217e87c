"""Bus flood at a fixed rate (fault ``flood:RATE``; ``rhonn-bench flood``; the queue tests).

Run as its own OS process: ``python -m harness.run.flood --bus SPEC --rate 5000``.
Paced in 1 ms batches on the monotonic clock; stops on SIGTERM/SIGINT or after
``--duration`` s, then prints ``flood sent N frames in T s (R/s; U refused by a full queue, L
lost while disconnected)``; N counts only frames handed to the bus. Note: 5000 frames/s
of 8-byte frames is more than a real 500 kbit/s CAN bus carries (~3900 frames/s at best);
the local bus has no such limit, so this is a software stress test, not a bus-load one.

What is sent (``--kind``):

* ``unknown`` (default): 8-byte frames on IDs that are not in the DBC;
* ``short``: 3-byte frames on the DBC IDs of ``--message`` (rejected ``wrong_length``);
* ``valid``: well-formed frames of ``--message`` (every signal 0, correct E2E CRC and alive
  counter): what a babbling node of that ID sends; a receiver must bound how many it keeps.
"""

from __future__ import annotations

import argparse
import sys
import time

import can

from can_db.codec import Codec, Transmitter
from can_db.process.stopflag import StopFlag
from can_db.transport.bus import BusDisconnected, open_bus

FLOOD_IDS = (0x050, 0x3A0, 0x6F0, 0x7E0)  # not in the DBC; 0x050 outranks our frames
END_MARKER_ID = 0x7FF  # not in the DBC: --end-marker frames, after the last flood frame
END_MARKERS = 10  # sent 20 ms apart: one is enough, the others cover a node's lost frames
READ_BY_HUB_WAIT_S = 30.0  # a hub starved by a loaded machine still reads within this
KINDS = ("unknown", "short", "valid")


def frame_source(kind: str, messages: list[str]):
    """A function ``n -> can.Message`` giving the n-th flood frame of ``kind``."""
    if kind == "unknown":
        return lambda n: can.Message(arbitration_id=FLOOD_IDS[n % len(FLOOD_IDS)],
                                     data=n.to_bytes(8, "little"), is_extended_id=False)
    codec = Codec()
    specs = [codec.messages[m] for m in messages]
    if kind == "short":
        return lambda n: can.Message(arbitration_id=specs[n % len(specs)].frame_id,
                                     data=(n & 0xFFFFFF).to_bytes(3, "little"),
                                     is_extended_id=False)
    tx = Transmitter(codec)
    zeros = {s.name: {sig.name: 0.0 for sig in s.signals} for s in specs}
    return lambda n: tx.message(specs[n % len(specs)].name, zeros[specs[n % len(specs)].name])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.run.flood", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bus", required=True)
    parser.add_argument("--rate", type=float, default=5000.0, help="frames per second")
    parser.add_argument("--kind", choices=KINDS, default="unknown", help="what is sent")
    parser.add_argument("--message", action="append", default=[],
                        help="DBC message flooded by --kind short|valid, repeatable")
    parser.add_argument("--duration", type=float, default=None,
                        help="stop after this many wall seconds (default: at SIGTERM)")
    parser.add_argument("--end-marker", action="store_true",
                        help=f"then send {END_MARKERS} empty frames on 0x{END_MARKER_ID:03X}: the "
                             "hub forwards a sender's frames in order, so a node that has "
                             "received one has been sent every flood frame")
    args = parser.parse_args(argv)
    if args.kind != "unknown":
        known = Codec().messages
        if not args.message or any(m not in known for m in args.message):
            parser.error(f"--kind {args.kind} needs --message NAME (one of "
                         f"{', '.join(known)})")
    make = frame_source(args.kind, args.message)
    stop = StopFlag()
    bus = open_bus(args.bus, reconnect_s=5.0)
    print("ready flood", flush=True)
    sent, unsent, lost, start = 0, 0, 0, time.monotonic()
    try:
        while not stop():
            elapsed = time.monotonic() - start
            if args.duration is not None and elapsed >= args.duration:
                break
            due = int(elapsed * args.rate)
            while sent < due:
                try:
                    bus.send(make(sent))
                except can.CanOperationError:  # our queue to the hub stayed full for 1 s
                    unsent += 1
                sent += 1
            time.sleep(0.001)
        # frames the bus node dropped while its hub connection was away (a local bus node
        # reconnects instead of raising): not sent either
        stats = getattr(bus, "stats", None)
        lost = int(stats().get("dropped_while_disconnected", 0)) if callable(stats) else 0
        if args.end_marker:
            marker = can.Message(arbitration_id=END_MARKER_ID, data=b"", is_extended_id=False)
            for _ in range(END_MARKERS):
                bus.send(marker)
                time.sleep(0.02)
        # exit only once the hub has read every frame: a frame another node sends after this
        # process ended then follows every flood frame (the hub reads its nodes in turn)
        wait_read = getattr(bus, "wait_read_by_hub", None)
        if callable(wait_read) and not wait_read(READ_BY_HUB_WAIT_S):
            print(f"flood: the hub had not read every frame after {READ_BY_HUB_WAIT_S:.0f} s",
                  file=sys.stderr, flush=True)
    except BusDisconnected:
        pass
    finally:
        bus.shutdown()
    elapsed = time.monotonic() - start
    sent -= unsent + lost
    print(f"flood sent {sent} frames in {elapsed:.1f} s ({sent / max(elapsed, 1e-9):.0f}/s; "
          f"{unsent} refused by a full queue, {lost} lost while disconnected)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
