"""`rhonn-bench bus`: round trip between two OS processes over the bus (default: local hub).

The echo process answers every frame on ID+1 with the same payload; this process measures
send → echo received with ``perf_counter_ns`` (µs, p50/p99) and counts lost frames.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can

from can_db.process.argcheck import OneLineParser, number
from can_db.process.parent import die_with_parent
from can_db.process.rt import make_realtime
from can_db.transport.bus import open_bus, resolve_bus
from harness.bench.stats import summarize_us, write_json

PING_ID = 0x700
READY_ID = 0x7F0


def _rt_cpus() -> set[int]:
    """Every process of the bench on the last CPU: a wake-up on the same CPU is much cheaper
    than one that needs an inter-processor interrupt on this VM."""
    return {max(os.sched_getaffinity(0))}


def echo(spec: str, rt: bool = False) -> int:
    """Child: answer every PING_ID frame with the same payload on PING_ID + 1."""
    if rt:
        make_realtime("bench-bus echo", cpus=_rt_cpus())
    bus = open_bus(spec)
    try:
        bus.send(can.Message(arbitration_id=READY_ID, data=b"", is_extended_id=False))
        while True:
            msg = bus.recv(timeout=5.0)
            if msg is None:
                return 0
            if msg.arbitration_id == PING_ID:
                bus.send(can.Message(arbitration_id=PING_ID + 1, data=msg.data,
                                     is_extended_id=False))
            elif msg.arbitration_id == READY_ID:
                return 0
    finally:
        bus.shutdown()


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench bus", description=__doc__)
    parser.add_argument("--frames", type=number(int, lo=1), default=5000,
                        help="round trips to time")
    parser.add_argument("--bus", default="auto",
                        help="bus spec: auto (default), local:NAME, remote:new, socketcan:IFACE")
    parser.add_argument("--json", default=None, help="write results to this file")
    parser.add_argument("--rt", action="store_true",
                        help="SCHED_FIFO, both processes on the last CPU (where permitted)")
    parser.add_argument("--echo", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error("--frames must be >= 1")
    if args.echo:
        return echo(args.echo, args.rt)
    if args.rt:  # the hub and the echo process inherit the CPU choice
        os.environ["RHONN_RT_CPUS"] = ",".join(str(c) for c in sorted(_rt_cpus()))
        make_realtime("bench-bus", cpus=_rt_cpus())

    hub_stats = Path(tempfile.mkdtemp(prefix="rhonn-bench-bus-")) / "hub.json"
    spec, server = resolve_bus(args.bus, rt=args.rt, stats_path=hub_stats)
    bus = open_bus(spec)
    child = subprocess.Popen([sys.executable, "-m", "harness.bench.bus", "--echo", spec,
                              *(["--rt"] if args.rt else [])], preexec_fn=die_with_parent)
    try:
        ready = bus.recv(timeout=20.0)
        if ready is None or ready.arbitration_id != READY_ID:
            raise SystemExit("echo process did not come up")
        samples, lost = [], 0
        clock = time.perf_counter_ns
        for k in range(args.frames):
            payload = k.to_bytes(8, "little")
            start = clock()
            bus.send(can.Message(arbitration_id=PING_ID, data=payload, is_extended_id=False))
            while True:
                msg = bus.recv(timeout=0.5)
                if msg is None:
                    lost += 1
                    break
                if msg.arbitration_id == PING_ID + 1 and bytes(msg.data) == payload:
                    samples.append(clock() - start)
                    break
        bus.send(can.Message(arbitration_id=READY_ID, data=b"", is_extended_id=False))
        child.wait(timeout=10)
    finally:
        bus.shutdown()
        if child.poll() is None:
            child.kill()
        if server is not None:
            server.stop()
    stats = summarize_us(samples) if samples else {"p50_us": float("nan"),
                                                   "p99_us": float("nan")}
    # "lost": no echo within 0.5 s; the hub (local bus) says whether a queue dropped it
    dropped = json.loads(hub_stats.read_text())["dropped"] if hub_stats.exists() else None
    shutil.rmtree(hub_stats.parent, ignore_errors=True)
    stats.update(frames=args.frames, lost=lost, hub_dropped=dropped, bus=spec.split(":")[0],
                 rt=args.rt)
    print(f"bus round trip ({stats['bus']}{', rt' if args.rt else ''}, two OS processes) "
          f"over {args.frames} frames: "
          f"p50 {stats['p50_us']:.0f} µs, p99 {stats['p99_us']:.0f} µs, lost {lost}"
          + (f" (dropped by the hub: {dropped})" if dropped is not None else ""))
    write_json(args.json, stats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
