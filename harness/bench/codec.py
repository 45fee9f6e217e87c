"""`rhonn-bench codec`: encode + decode + validate one frame, µs per frame (p50/p99).

``--messages A,B``: only these messages, each reported on its own as well (encode =
``Transmitter.message``: pack, alive counter, E2E CRC; validate = ``RxMonitor.process``:
E2E CRC check, unpack, range and counter checks).
"""

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
    parser.add_argument("--messages", default=None,
                        help="comma-separated message names (default: every message)")
    parser.add_argument("--json", default=None, help="write results to this file")
    args = parser.parse_args(argv)

    codec = Codec()
    tx = Transmitter(codec)
    monitor = RxMonitor(codec, codec.messages)
    names = list(codec.messages)
    if args.messages:
        names = [n.strip() for n in args.messages.split(",") if n.strip()]
        unknown = [n for n in names if n not in codec.messages]
        if unknown:
            parser.error(f"unknown message(s) {', '.join(unknown)}")
    samples = []
    per: dict[str, tuple[list[int], list[int]]] = {n: ([], []) for n in names}
    clock = time.perf_counter_ns
    for k in range(args.frames):
        name = names[k % len(names)]
        values = {sig.name: 0.3 * sig.maximum * math.sin(0.01 * k)
                  for sig in codec.messages[name].signals}
        start = clock()
        msg: can.Message = tx.message(name, values)
        mid = clock()
        result = monitor.process(msg, now_s=k * 0.001)
        end = clock()
        samples.append(end - start)
        per[name][0].append(mid - start)
        per[name][1].append(end - mid)
        if result is None or not hasattr(result, "values"):
            raise SystemExit(f"frame {k} rejected: {result}")
    stats = summarize_us(samples)
    print(f"codec: encode+decode+validate per frame over {args.frames} frames of "
          f"{len(names)} messages: p50 {stats['p50_us']:.1f} µs, p99 {stats['p99_us']:.1f} µs")
    by_message = {}
    if args.messages:
        for name, (enc, dec) in per.items():
            e, d = summarize_us(enc), summarize_us(dec)
            by_message[name] = {"encode": e, "validate": d}
            crc = getattr(codec.messages[name], "crc_bits", 8)
            print(f"  {name:<18} CRC{crc:<3} encode p50 "
                  f"{e['p50_us']:.2f} µs, validate p50 {d['p50_us']:.2f} µs")
    write_json(args.json, {**stats, "by_message": by_message} if by_message else stats)
    return 0
