"""`rhonn-bench`: one entry point for every benchmark; each lives in its own module.

Each benchmark module exposes ``main(argv: list[str]) -> int`` and accepts ``--json FILE``.
Timings are medians and p99 over many repetitions; nothing here asserts a threshold.
"""

from __future__ import annotations

import importlib
import sys

BENCHMARKS: dict[str, tuple[str, str]] = {
    "codec": ("harness.bench.codec", "encode + decode + validate one frame (µs)"),
    "e2e": ("harness.bench.e2e", "random acceptance of the E2E check per frame type"),
    "bus": ("harness.bench.bus", "round trip between two OS processes over the bus (µs)"),
    "plant": ("harness.bench.plant", "standalone plant model speed (simulated s per wall s)"),
    "controller": ("harness.bench.controller_step", "controller step time per controller (µs)"),
    "ranges": ("harness.bench.ranges", "signal ranges, Q-formats and float32 equivalence"),
    "mpc-update": ("harness.bench.mpc_update",
                   "MPC update time inside the controller process, shared vs own CPU"),
    "loop": ("harness.bench.loop", "closed-loop lockstep speed and rx→tx turnaround"),
    "secoc": ("harness.bench.secoc", "SecOC MAC generate + verify per frame (µs), loop impact"),
    "soak": ("harness.bench.soak", "long real-time 100 Hz loop under flood and loss"),
    "flood": ("harness.bench.flood",
              "RSS and SYNC-answer latency of controller and plant under a valid-ID flood"),
    "fuzz": ("harness.fuzz.cli", "adversarial fuzzing of decoder, monitor, node, controllers"),
    "mcu": ("harness.bench.mcu", "C core on a Cortex-M4F (QEMU): flash, RAM, stack, instr/step"),
    "deploy": ("harness.bench.deploy",
               "core-only install: size, start → ready, RSS after 10 000 steps"),
}


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``rhonn-bench NAME [options]`` to the benchmark module."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] not in BENCHMARKS and args[0] not in {"-h", "--help"}:
        print(f"rhonn-bench: error: unknown benchmark {args[0]!r}; choose from "
              f"{', '.join(BENCHMARKS)} (see rhonn-bench --help)", file=sys.stderr)
        return 2
    if not args or args[0] in {"-h", "--help"}:
        print("usage: rhonn-bench {" + ",".join(BENCHMARKS) + "} [--json FILE] [options]\n"
              "       rhonn-bench NAME --help   options of one benchmark")
        for name, (_, what) in BENCHMARKS.items():
            print(f"  {name:<11} {what}")
        if not args:
            print("rhonn-bench: error: name a benchmark", file=sys.stderr)
        return 0 if args else 2
    from can_db.process.argcheck import UsageError, check_extra

    try:
        check_extra(("tqdm",))
    except UsageError as exc:
        print(f"rhonn-bench: error: {exc}", file=sys.stderr)
        return 2
    module = importlib.import_module(BENCHMARKS[args[0]][0])
    return int(module.main(args[1:]))


if __name__ == "__main__":
    raise SystemExit(main())
