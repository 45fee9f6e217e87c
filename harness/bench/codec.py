"""`rhonn-bench codec`: encode + decode + validate one frame, µs per frame (p50/p99)."""

from __future__ import annotations

import math
import time

import can

from can_db.codec import Codec, Transmitter
from can_db.monitor import RxMonitor
from can_db.process.argcheck import OneLineParser, number
from harness.bench.stats import summarize_us, write_json


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench codec", description=__doc__)
    parser.add_argument("--frames", type=number(int, lo=1), default=50_000, help="frames to time")
    parser.add_argument("--json", default=None, help="write results to this file")
    args = parser.parse_args(argv)

    codec = Codec()
    tx = Transmitter(codec)
    monitor = RxMonitor(codec, codec.messages)
    names = list(codec.messages)
    samples = []
    clock = time.perf_counter_ns
    for k in range(args.frames):
        name = names[k % len(names)]
        values = {sig.name: 0.3 * sig.maximum * math.sin(0.01 * k)
                  for sig in codec.messages[name].signals}
        start = clock()
        msg: can.Message = tx.message(name, values)
        result = monitor.process(msg, now_s=k * 0.001)
        samples.append(clock() - start)
        if result is None or not hasattr(result, "values"):
            raise SystemExit(f"frame {k} rejected: {result}")
    stats = summarize_us(samples)
    print(f"codec: encode+decode+validate per frame over {args.frames} frames of "
          f"{len(names)} messages: p50 {stats['p50_us']:.1f} µs, p99 {stats['p99_us']:.1f} µs")
    write_json(args.json, stats)
    return 0
