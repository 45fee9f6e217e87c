"""`rhonn-bench e2e`: random acceptance of the E2E check, per frame type, measured.

For every message a receiver acts on (default: the controller's DRIVER_INPUTS,
MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST, SYNC; ``--messages all`` adds the rest), random
8-byte payloads on that ID go through a fresh ``RxMonitor`` in sequence and every one it
returns as data (``Decoded``) counts as accepted. Two streams per ID:

* ``random``: only random payloads, one after the other;
* ``interleaved``: genuine frame, random payload, genuine frame, ... (a corrupted or forged
  frame between the sender's own, the counter state the genuine frames keep fresh).

Reported per ID and stream: accepted / payloads, the rate and its one-sided 95 %
Clopper-Pearson upper bound (what the sample supports when few or none are accepted).
``--dbc FILE`` measures another matrix (e.g. the CRC-8 layout from git history:
``git show REV:can_db/rhonn_tv.dbc > old.dbc``).

``--fast``: the payloads whose CRC cannot match are rejected by a vectorised CRC (numpy, the
codec's tables) instead of one by one; only the CRC-passing ones go through the monitor. A
frame with a bad CRC leaves the monitor's stream state untouched (it returns before the
counter check), so the count is the same as the full path's; the test suite checks the
vectorised CRC against the codec. Without ``--fast`` every payload takes the full path
(≈ 1-2 µs each: 2·10⁶ payloads per ID and stream take about a minute for five IDs).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import can
import numpy as np
from scipy.stats import beta

from can_db.codec import Codec, Decoded
from can_db.crc import INIT, INIT16, TABLE, TABLE16, XOR_OUT, XOR_OUT16
from can_db.monitor import RxMonitor
from can_db.process.argcheck import OneLineParser, number
from harness.bench.stats import write_json
from harness.viz.progress import Bar

ACTED_ON = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")
STREAMS = ("random", "interleaved")
CONFIDENCE = 0.95
SETTLE = 6  # genuine frames before a random one (fast interleaved): fault level back at 0


def upper_bound(accepted: int, trials: int, confidence: float = CONFIDENCE) -> float:
    """One-sided Clopper-Pearson upper confidence bound of a binomial rate."""
    if trials <= 0:
        return 1.0
    if accepted >= trials:
        return 1.0
    return float(beta.ppf(confidence, accepted + 1, trials - accepted))


@dataclass
class Result:
    """Accepted random payloads of one ID and stream."""

    name: str
    stream: str
    profile: str  # "CRC8" or "CRC16"
    payloads: int
    accepted: int
    crc_passed: int  # payloads whose CRC matched (full path: counted from the rejections)
    seconds: float

    @property
    def rate(self) -> float:
        """Accepted per random payload."""
        return self.accepted / self.payloads if self.payloads else 0.0

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary, with the 95 % upper bound of the rate."""
        return {"message": self.name, "stream": self.stream, "profile": self.profile,
                "payloads": self.payloads, "accepted": self.accepted,
                "crc_passed": self.crc_passed, "rate": self.rate,
                "upper95": upper_bound(self.accepted, self.payloads),
                "one_in": (self.payloads / self.accepted) if self.accepted else None,
                "seconds": round(self.seconds, 3)}


def crc_pass_mask(codec: Codec, frame_id: int, payloads: np.ndarray) -> np.ndarray:
    """Vectorised E2E CRC check of ``payloads`` (uint8 array, n × 8) on ``frame_id``: True
    where the payload carries the CRC its profile (the DBC's CRC8/CRC16 signal) requires."""
    data = payloads.astype(np.uint32)
    if codec.by_id[frame_id].crc_bits == 16:
        table = np.asarray(TABLE16, dtype=np.uint32)
        crc = np.full(len(data), INIT16, dtype=np.uint32)
        for byte in (frame_id >> 8, frame_id & 0xFF):
            crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
        for col in range(2, 8):
            crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ data[:, col]]
        return (crc ^ XOR_OUT16) == (data[:, 0] | (data[:, 1] << 8))
    table8 = np.asarray(TABLE, dtype=np.uint32)
    crc = np.full(len(data), INIT, dtype=np.uint32)
    for byte in (frame_id >> 8, frame_id & 0xFF):
        crc = table8[crc ^ byte]
    for col in range(1, 8):
        crc = table8[crc ^ data[:, col]]
    return (crc ^ XOR_OUT) == data[:, 0]


def _msg(frame_id: int, payload: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=payload, is_extended_id=False)


def _genuine(codec: Codec, name: str, k: int) -> can.Message:
    """The sender's k-th frame (mid-range values, alive counter k mod 16)."""
    values = {s.name: min(max(0.0, s.minimum), s.maximum) for s in codec.messages[name].signals}
    return codec.message(name, values, k % 16)


def random_payloads(codec: Codec, name: str, stream: str, payloads: int,
                    seed: int) -> np.ndarray:
    """The seeded random payloads (n × 8 uint8) of one ID and stream."""
    rng = np.random.default_rng([seed, codec.messages[name].frame_id, STREAMS.index(stream)])
    return rng.integers(0, 256, size=(payloads, 8), dtype=np.uint8)


def measure(codec: Codec, name: str, stream: str, payloads: int, seed: int,
            fast: bool = False, data: np.ndarray | None = None) -> Result:
    """Random payloads on ``name``'s ID through a fresh RxMonitor (see the module doc);
    ``data``: these payloads (n × 8 uint8) instead of the seeded random ones."""
    spec = codec.messages[name]
    if data is None:
        data = random_payloads(codec, name, stream, payloads, seed)
    payloads = len(data)
    start = time.perf_counter()
    accepted = crc_passed = 0
    if fast:
        hits = np.flatnonzero(crc_pass_mask(codec, spec.frame_id, data))
        crc_passed = len(hits)
        if stream == "random":
            monitor = RxMonitor(codec, [name])
            for i in hits:  # the rejected rest leaves the stream state as it is
                got = monitor.process(_msg(spec.frame_id, bytes(data[i])), i * spec.cycle_time_s)
                accepted += isinstance(got, Decoded)
        else:
            for i in hits:  # genuine frames 0..i, then random payload i: the state before
                monitor = RxMonitor(codec, [name])  # it is that of the last SETTLE frames
                for k in range(max(0, i - SETTLE + 1), i + 1):
                    monitor.process(_genuine(codec, name, k), k * spec.cycle_time_s)
                got = monitor.process(_msg(spec.frame_id, bytes(data[i])),
                                      i * spec.cycle_time_s)
                accepted += isinstance(got, Decoded)
        return Result(name, stream, f"CRC{spec.crc_bits}", payloads, accepted, crc_passed,
                      time.perf_counter() - start)
    monitor = RxMonitor(codec, [name])
    dt = spec.cycle_time_s
    for i in range(payloads):
        if stream == "interleaved":
            monitor.process(_genuine(codec, name, i), i * dt)
        got = monitor.process(_msg(spec.frame_id, data[i].tobytes()), i * dt)
        accepted += isinstance(got, Decoded)
    crc_passed = payloads - monitor.counts["bad_crc"]
    return Result(name, stream, f"CRC{spec.crc_bits}", payloads, accepted, crc_passed,
                  time.perf_counter() - start)


def run(codec: Codec, names: Iterable[str], payloads: int, seed: int, fast: bool,
        streams: Iterable[str] = STREAMS, progress: Bar | None = None) -> list[Result]:
    """Every (message, stream) measurement; ``progress`` counts them (one per pair)."""
    out = []
    for n in names:
        for s in streams:
            out.append(measure(codec, n, s, payloads, seed, fast))
            if progress is not None:
                progress.set(len(out), note=f"{n} {s}")
    return out


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench e2e", description=__doc__)
    parser.add_argument("--payloads", type=number(int, lo=1), default=2_000_000,
                        help="random payloads per ID and stream")
    parser.add_argument("--messages", default="acted-on",
                        help="acted-on (default) | all | comma-separated message names")
    parser.add_argument("--streams", default="random,interleaved",
                        help="random, interleaved or both (comma-separated)")
    parser.add_argument("--dbc", default=None, help="measure this DBC (default: the packaged)")
    parser.add_argument("--seed", type=number(int, lo=0), default=1)
    parser.add_argument("--fast", action="store_true",
                        help="vectorised CRC pre-filter (same counts, see --help text)")
    parser.add_argument("--json", default=None, help="write the results to this file")
    args = parser.parse_args(argv)
    codec = Codec(args.dbc)
    if args.messages == "acted-on":
        names = [n for n in ACTED_ON if n in codec.messages]
    elif args.messages == "all":
        names = sorted(codec.messages)
    else:
        names = [n.strip() for n in args.messages.split(",") if n.strip()]
        unknown = [n for n in names if n not in codec.messages]
        if unknown:
            parser.error(f"unknown message(s) {', '.join(unknown)}; choose from "
                         f"{', '.join(sorted(codec.messages))}")
    streams = [s.strip() for s in args.streams.split(",") if s.strip()]
    if not streams or any(s not in STREAMS for s in streams):
        parser.error(f"--streams: choose from {', '.join(STREAMS)}")
    # each pair takes seconds (the full rx path: ~5 s per 2 M payloads): progress on stderr
    bar = Bar("e2e", total=len(names) * len(streams), unit="ID × stream", line_every_s=5.0)
    try:
        results = run(codec, names, args.payloads, args.seed, args.fast, streams, bar)
    finally:
        bar.close()
    print(f"e2e random acceptance, {args.payloads} random payloads per ID and stream "
          f"({'vectorised CRC pre-filter' if args.fast else 'full rx path'}), DBC "
          f"{codec.dbc_path.name}:")
    print(f"  {'message':<16} {'profile':<6} {'stream':<12} {'CRC ok':>8} {'accepted':>9} "
          f"{'rate':>10} {'95% upper':>10}")
    for r in results:
        d = r.as_dict()
        print(f"  {r.name:<16} {r.profile:<6} {r.stream:<12} {r.crc_passed:>8} "
              f"{r.accepted:>9} {r.rate:>10.2e} {d['upper95']:>10.2e}")
    total_n = sum(r.payloads for r in results)
    total_k = sum(r.accepted for r in results)
    print(f"  all: {total_k} of {total_n} accepted, rate {total_k / total_n:.2e}, 95 % upper "
          f"bound {upper_bound(total_k, total_n):.2e}")
    write_json(args.json, {"payloads_per_id_and_stream": args.payloads, "fast": args.fast,
                           "dbc": str(codec.dbc_path), "seed": args.seed,
                           "results": [r.as_dict() for r in results],
                           "total": {"payloads": total_n, "accepted": total_k,
                                     "upper95": upper_bound(total_k, total_n)}})
    return 0
