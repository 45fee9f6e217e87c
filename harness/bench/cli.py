"""`rhonn-bench`: one entry point for every benchmark; each lives in its own module.

Each benchmark module exposes ``main(argv: list[str]) -> int`` and accepts ``--json FILE``.
Timings are medians and p99 over many repetitions; nothing here asserts a threshold.

``rhonn-bench --version`` prints the versions; ``-v/--verbose`` and ``-q/--quiet`` (anywhere
on the line) set the diagnostics on stderr to DEBUG or WARNING (can_db/process/logsetup.py).
"""

from __future__ import annotations

import importlib
import itertools
import logging
import sys
import time

from can_db.process.argcheck import UsageError, check_extra, usage_exit
from can_db.process.logsetup import setup_logging, version_line

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
    "vcan": ("harness.tools.vcan_check",
             "the loop and its logs on SocketCAN vcan0 (a VM if needed) against the local bus"),
}


LOGGING_FLAGS = {"verbose": ["-v", "--verbose"], "quiet": ["-q", "--quiet"]}


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``rhonn-bench [-v|-q] NAME [options]`` to the benchmark module."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["--version"]:
        print(version_line("rhonn-bench"), flush=True)
        return 0
    verbose = any(a in LOGGING_FLAGS["verbose"] for a in args)
    quiet = any(a in LOGGING_FLAGS["quiet"] for a in args)
    if verbose and quiet:
        usage_exit("rhonn-bench", "-v/--verbose and -q/--quiet exclude each other "
                   "(see rhonn-bench --help)")
    args = [a for a in args if a not in LOGGING_FLAGS["verbose"] + LOGGING_FLAGS["quiet"]]
    if args and args[0] not in BENCHMARKS and args[0] not in {"-h", "--help"}:
        usage_exit("rhonn-bench", f"unknown benchmark {args[0]!r}; choose from "
                   f"{', '.join(BENCHMARKS)} (see rhonn-bench --help)")
    if not args or args[0] in {"-h", "--help"}:
        print("usage: rhonn-bench [-h] [--version] [-v | -q] {" + ",".join(BENCHMARKS)
              + "} [--json FILE] [options]\n"
              "       rhonn-bench NAME --help   options of one benchmark\n\n"
              "  -v, --verbose  diagnostics down to DEBUG on stderr\n"
              "  -q, --quiet    only warnings and errors on stderr (results still on stdout)\n"
              "  --version      print the program, package and backend versions and exit\n\n"
              "benchmarks:")
        for name, (_, what) in BENCHMARKS.items():
            print(f"  {name:<11} {what}")
        if not args:
            usage_exit("rhonn-bench", "name a benchmark (see rhonn-bench --help)")
        return 0
    if "--json=" in args or any(a == "--json" and not b for a, b in itertools.pairwise(args)):
        # every benchmark's --json FILE: an empty path would silently mean "no file"
        usage_exit(f"rhonn-bench {args[0]}", "--json: empty path (give a file)")
    log = setup_logging("rhonn-bench", verbose, quiet)
    try:
        check_extra(("tqdm",))
    except UsageError as exc:
        usage_exit("rhonn-bench", str(exc))
    log.debug("benchmark %s: %s (%s)", args[0], BENCHMARKS[args[0]][1], BENCHMARKS[args[0]][0])
    start = time.monotonic()
    module = importlib.import_module(BENCHMARKS[args[0]][0])
    code = int(module.main(args[1:]))  # a bad argument exits inside, with its one line
    # a failure has said so in its own line; the time of a finished benchmark is a diagnostic
    log.log(logging.INFO if code == 0 else logging.DEBUG, "benchmark %s done in %.1f s "
            "(exit code %d)", args[0], time.monotonic() - start, code)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
