"""`rhonn-plant`: the vehicle simulator as a process on the CAN bus.

  rhonn-plant --bus SPEC --scenario NAME|FILE.toml [--mode lockstep|realtime] [--trace FILE]
              [--summary FILE] [--mu X] [--speed KMH] [--seed N] [--param KEY=VALUE ...]
              [--vehicle KEY=VALUE ...]
              [--no-secoc] [--secoc-keys env|ci-test-key|KEYFILE] [--secoc-state FILE]
  rhonn-plant --bus SPEC --serve [--no-secoc] [--secoc-keys SRC] [--rt] [--reconnect-s S]

Every 10 ms communication cycle it publishes DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS,
VEHICLE_EST and ends the burst with SYNC. Lockstep: it then waits for the WHEEL_TORQUE_CMD that
echoes the cycle (a wall-clock timeout: no fresh command this cycle, counted; after
``--lost-after`` consecutive timeouts it stops waiting until torque frames reappear, so a dead
controller does not slow the run to a crawl). Real-time: it paces on the monotonic clock.
One command-loss policy in both modes (:meth:`PlantNode.advance`): a cycle without a fresh
torque command holds the last accepted one for ``--command-hold-ms`` (default 30 ms, the
DBC's rx timeout of 3 cycles; simulated time in lockstep, wall time in real time), counted as
held cycles; after that, or with the torque stream's counter faulted, the car drives as one
without the stability function: the driver's torque split evenly (a fallback cycle).

SecOC (``--secoc``, see can_db/secoc.py): SYNC and the driver and sensor frames are each
followed by their authenticator (faults of the plant's own sensors and E2E protection are
injected before signing, bus faults after); torque and status frames are used only after
their authenticator verifies, so a rejected (forged, replayed, corrupted) command is handled
exactly as a missing one.

The truth trace is ``FILE.rows`` during the run (one packed row per cycle, readable after a
kill, can_db/process/rowlog.py) and the CSV ``FILE`` from when the plant stops; the summary
JSON holds the counters (fallback cycles, rejected torque frames by reason, saturations, overruns).

A loop that does not hold is said: once more than 2 % of the cycles (``FALLBACK_SHARE_MAX``,
the harness's limit for a ``degraded`` run) ran on the fallback, the plant logs a warning
(once, after the first 0.5 s); a one-shot run that reaches its end so (no ``--fault``) ends
with ``rhonn-plant: degraded: the plant fell back in N% of its cycles ...`` on stderr, exit 4.

Serve mode (``--serve``, a warm HIL bench): the bus is opened once and ``ready serve on SPEC``
printed; then one JSON command a line on stdin:

* ``{"run": [ARGS...]}`` — ARGS are the per-run options above (everything but ``--bus``,
  ``--serve``, ``--rt``, ``--reconnect-s`` and the logging options; ``--secoc`` and
  ``--secoc-keys`` given at start are every run's defaults), checked by the same parser. A bad
  run: one line ``error MESSAGE``, no file written, the next command is read. Otherwise the
  frames queued on the bus are dropped (a previous run's late answers), ``loaded SCENARIO``
  is printed, the run runs exactly as a one-shot plant's (same truth bytes, same frames; a
  run's ``--secoc-state`` is its own file, so a fresh path is trip 1), its trace and summary
  are written and ``done SUMMARY-JSON`` (one line) is printed. Bus counters in the summary
  are the run's own.
* ``{"quit": true}`` or end of input: exit 0.

SIGTERM/SIGINT during a run ends it as in the one-shot plant ("stopped by signal": files
written, ``done`` printed), then the process exits 0; between runs it exits 0 at once. A run
that raises (a bug, not a bad argument) writes its files with reason ``error: ...``, prints
``error run failed: ...`` and the process exits 1: its state is suspect, a bench replaces it.
A lost bus ends the run with reason "bus lost", ``done``, exit 3.
"""

from __future__ import annotations

from can_db.process.launch import refuse_unused

if __name__ == "__main__":  # before the imports below: packages the plant never uses
    refuse_unused("rhonn-plant")

import argparse
import gc
import json
import os
import select
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from can_db.codec import Codec, Decoded
from can_db.faults import FaultInjector, FaultSpecError, parse_faults
from can_db.process.argcheck import (
    OneLineParser,
    UsageError,
    check_out_file,
    number,
)
from can_db.process.logsetup import (
    add_logging_options,
    logging_args,
    process_age_s,
    setup_logging,
)
from can_db.process.rowlog import RowLog
from can_db.process.rt import freeze_heap, make_realtime
from can_db.process.stall import StallWatch
from can_db.process.stopflag import StopFlag
from can_db.secoc import MAX_AGE_CYCLES, PlantSecOc
from can_db.secoc_keys import (
    SecOcKeyError,
    SecOcKeys,
    TripCounter,
    load_keys,
    resolve_key_source,
    secoc_state_text,
)
from can_db.transport.bus import BusDisconnected, open_bus_for_process, send_all
from can_db.transport.check import check_bus
from plant_sim.node import (
    FALLBACK_HINT,
    TORQUE_FRAME,
    PlantNode,
    fallback_passed,
    fallback_text,
)
from plant_sim.overrides import parse_key_values
from plant_sim.run_options import check_scenario, parse_params, scenario_arg
from plant_sim.scenario import (
    list_scenarios,
)
from plant_sim.scenario_schema import DURATION_MAX_S, MU_MAX, SPEED_MAX_KMH
from plant_sim.simulation import Simulation

# Lockstep: frames read after the cycle's deadline at most (one full send_many packet). The
# wait for the answer then ends even when frames keep arriving; without this limit a flood
# faster than the plant reads would hold it in one cycle's wait for ever.
LATE_READS_MAX = 64
# a run that reached its end on the fallback in more than FALLBACK_SHARE_MAX of its cycles
# (plant_sim/node.py), no fault injected: the harness's exit code for a degraded run
EXIT_DEGRADED = 4




class TraceWriter:
    """Truth trace (every value ``%.9g``): one packed row per cycle during the run
    (can_db/process/rowlog.py: one write(2), a SIGKILLed plant loses no finished cycle), turned into
    the CSV ``path`` on close — the same bytes a line-per-cycle CSV writer gives, ≈ 15 µs a
    lockstep cycle cheaper. (Buffering for 0.2 wall seconds lost ~1 s of simulated time in
    lockstep.)"""

    def __init__(self, path: str | None, columns: list[str]) -> None:
        self.columns = columns
        self._log = RowLog(path, columns, ["%.9g"] * len(columns)) if path else None

    def write_values(self, values: tuple[float, ...]) -> None:
        """One row of values in column order (``Simulation.truth_values``)."""
        if self._log is not None:
            self._log.write(values)

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None


COMMAND_HOLD_MS = 30.0  # the last torque command's hold without a fresh one, ms (3 cycles)
# Options of the process, not of a run: given once at start (serve mode: the runs share them).
PROCESS_OPTIONS = ("bus", "serve", "reconnect_s", "rt", "verbose", "quiet")
# Per-run options that serve mode takes at start as every run's default.
SERVE_DEFAULTS = ("secoc", "secoc_keys")
# Serve mode: how often the wait for the next command looks at the stop flag, ms (a SIGTERM
# does not interrupt a blocking read: Python retries it after the handler, PEP 475).
COMMAND_POLL_MS = 100
COMMAND_MAX_BYTES = 1 << 20  # one command line, bytes (a run's arguments are a few hundred)
# Serve mode loads the compiled vehicle step and path projection (numba's cache, ~0.2 s) with
# a throw-away simulation of this scenario before ``ready``: the first run loads as fast as the
# next ones.
WARM_UP_SCENARIO = "dlc-paper"
# At most this many queued frames are dropped before a run, frames (a node's hub queue holds
# ~5 000 packets, can_db/transport/wire.py): a flood still sending cannot hold the start for ever.
DRAIN_MAX_FRAMES = 100_000


def _add_run_options(parser: argparse.ArgumentParser, *, scenario_required: bool) -> None:
    """The options of one run (the one-shot command line, or a served run's line)."""
    parser.add_argument("--scenario", required=scenario_required, type=scenario_arg,
                        metavar="NAME|FILE",
                        help="a packaged scenario (" + ", ".join(list_scenarios())
                             + ") or a scenario TOML file (docs/scenarios.md)")
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                        help="lockstep: wait for each cycle's answer; realtime: pace on the "
                             "monotonic clock")
    parser.add_argument("--trace", default=None, help="write the truth trace CSV here")
    parser.add_argument("--summary", default=None, help="write the counters as JSON at exit")
    parser.add_argument("--mu", type=number(lo=0.0, hi=MU_MAX, lo_open=True), default=None,
                        metavar="MU",
                        help="road friction coefficient override, 0 < mu <= "
                             f"{MU_MAX:g} (default: the scenario's)")
    parser.add_argument("--speed", type=number(lo=0.0, hi=SPEED_MAX_KMH, unit="km/h"),
                        default=None, metavar="KMH", help="initial speed override, km/h, 0 .. "
                                           f"{SPEED_MAX_KMH:g} (default: the scenario's)")
    parser.add_argument("--seed", type=number(int, lo=0), default=0, metavar="N",
                        help="sensor-noise seed, >= 0")
    parser.add_argument("--duration", type=number(lo=0.0, hi=DURATION_MAX_S, lo_open=True,
                                                  unit="s"), default=None, metavar="S",
                        help="stop after this much simulated time, s (default: the "
                             "scenario's)")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="scenario parameter override, repeatable")
    parser.add_argument("--vehicle", action="append", default=[], metavar="KEY=VALUE",
                        help="plant parameter override, repeatable (plant_sim/overrides.py), "
                             "e.g. mass_scale=1.15")
    parser.add_argument("--wait-ms", type=number(lo=0.0, hi=60_000.0, lo_open=True, unit="ms"),
                        default=200.0,
                        help="lockstep: wall-clock wait for the echoing torque frame, ms")
    parser.add_argument("--command-hold-ms", type=number(lo=0.0, hi=1000.0, unit="ms"),
                        default=COMMAND_HOLD_MS, metavar="MS",
                        help="a cycle without a fresh torque command holds the last accepted "
                             "one this long, then falls back to the driver's torques, ms "
                             f"(both modes; default {COMMAND_HOLD_MS:g}, the DBC's rx timeout "
                             "of 3 cycles)")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND[:ARG][@T]",
                        help="inject a frame fault on the plant's frames, repeatable "
                             "(see can_db/faults.py)")
    parser.add_argument("--fault-seed", type=number(int, lo=0), default=1,
                        help="seed of the fault injector's randomness")
    parser.add_argument("--secoc", action=argparse.BooleanOptionalAction, default=True,
                        help="authenticate SYNC, verify torque/status frames (SecOC; on by "
                             "default, --no-secoc turns it off)")
    parser.add_argument("--secoc-keys", default=None,
                        help="SecOC keys: env | ci-test-key | KEYFILE (mode 600); default: env "
                             "when the RHONN_SECOC_KEY_* variables are set (both; one alone "
                             "is an error), else the public test key (simulation only)")
    parser.add_argument("--secoc-state", default=None,
                        help="SecOC trip-counter file (+1 at every start; needed so a "
                             "restarted plant is accepted again)")
    parser.add_argument("--secoc-max-age", type=number(int, lo=1), default=MAX_AGE_CYCLES,
                        help="SecOC forward window: oldest acceptable answered cycle, cycles")
    parser.add_argument("--lost-after", type=number(int, lo=1), default=3,
                        help="lockstep: consecutive timeouts before the controller is "
                             "considered lost (no more waiting until it answers again)")


def _parser() -> OneLineParser:
    parser = OneLineParser(prog="rhonn-plant", description=__doc__)
    parser.add_argument("--bus", required=True,
                        help="local:NAME | socketcan:IFACE | remote:ws://127.0.0.1:PORT/")
    parser.add_argument("--serve", action="store_true",
                        help="warm bench: keep the bus open and run the runs read as JSON "
                             "lines on stdin (see above); the run options come with each run")
    _add_run_options(parser, scenario_required=False)  # required in one-shot mode (main)
    parser.add_argument("--reconnect-s", type=number(lo=0.0, unit="s"), default=5.0,
                        help="loopback bus: how long a lost server may stay away, s")
    parser.add_argument("--rt", action="store_true",
                        help="SCHED_FIFO (and $RHONN_RT_CPUS affinity) where permitted")
    add_logging_options(parser)
    return parser


class _RunLineParser(OneLineParser):
    """The parser of a served run's arguments: an error is a UsageError (the process goes on
    serving), never an exit; no ``--help`` (stdout is the control channel)."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        raise UsageError(message)

    def exit(self, status: int = 0, message: str | None = None) -> Any:  # type: ignore[override]
        raise UsageError(message or f"exit {status}")


def _run_parser(process_args: argparse.Namespace) -> _RunLineParser:
    """Parser of one served run; the process's options are in every run's namespace."""
    parser = _RunLineParser(prog="rhonn-plant run", add_help=False)
    _add_run_options(parser, scenario_required=True)
    parser.set_defaults(**{name: getattr(process_args, name)
                           for name in (*PROCESS_OPTIONS, *SERVE_DEFAULTS)})
    return parser


class PlantRun:
    """One run, its arguments checked and its simulation built; nothing written yet.

    ``start()`` writes: it counts the SecOC trip (``--secoc-state``) and opens the trace."""

    def __init__(self, args: argparse.Namespace, codec: Codec) -> None:
        """Check every argument of the run (UsageError, FaultSpecError, SecOcKeyError)."""
        try:
            vehicle = parse_key_values(args.vehicle)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        self.args, self.codec = args, codec
        self.sim = check_scenario(args.scenario, args.mu, args.speed, parse_params(args.param),
                                  args.seed, vehicle)
        self.injector = FaultInjector(codec, parse_faults(args.fault), seed=args.fault_seed,
                                      lockstep=args.mode == "lockstep") if args.fault else None
        for path, what in ((args.trace, "--trace"), (args.summary, "--summary")):
            if path is not None:  # "--trace=" is refused, not taken as "no trace"
                check_out_file(path, what)
        if not args.secoc and args.secoc_keys is not None:
            raise UsageError("--secoc-keys is given with --no-secoc (no keys are used)")
        self.keys: SecOcKeys | None = \
            load_keys(resolve_key_source(args.secoc_keys)) if args.secoc else None

    def start(self) -> tuple[PlantNode, TraceWriter]:
        """The run's node (SecOC trip counted: SecOcKeyError if its file is unreadable) and
        its truth trace (file opened)."""
        args = self.args
        secoc = None
        if self.keys is not None:
            secoc = PlantSecOc(self.codec, self.keys, TripCounter(args.secoc_state).next_trip(),
                               max_age_cycles=args.secoc_max_age)
        node = PlantNode(self.sim, codec=self.codec, injector=self.injector, secoc=secoc,
                         command_hold_s=args.command_hold_ms / 1000.0)
        return node, TraceWriter(args.trace, list(self.sim.trace_columns))


def _bus_counts(bus: can.BusABC) -> dict[str, Any] | None:
    """The bus's own counters (frames sent, reconnects, ...), None when it keeps none."""
    stats = getattr(bus, "stats", None)
    return dict(stats()) if callable(stats) else None


def _since(before: dict[str, Any] | None, after: dict[str, Any] | None
           ) -> dict[str, Any] | None:
    """Counters of ``after`` minus those of ``before`` (a run's share of a process's bus)."""
    if after is None:
        return None
    base = before or {}
    return {k: v - base.get(k, 0) if isinstance(v, int | float) and not isinstance(v, bool)
            else v for k, v in after.items()}


def _drain(bus: can.BusABC) -> int:
    """Drop the frames already queued for this node (a previous run's late answers, a
    tester's diagnostic frames); returns how many."""
    count = 0
    while count < DRAIN_MAX_FRAMES and bus.recv(timeout=0.0) is not None:
        count += 1
    return count


def run_one(bus: can.BusABC, run: PlantRun, node: PlantNode, trace: TraceWriter,
            stop: Callable[[], bool], announce: str) -> tuple[int, dict[str, Any]]:
    """Run one run on an open bus, write its trace and summary; returns (exit code, summary).

    Exit code 0, 3 when the bus is lost, 1 when the run raised (reason ``error: ...``).
    ``announce`` is printed once the run is set up, just before its first burst."""
    args, sim, injector = run.args, node.sim, node.injector
    stats: dict[str, Any] = {"scenario": args.scenario, "mode": args.mode, "cycles": 0,
                             "lockstep_timeouts": 0, "overruns": 0, "waits_cut_by_flood": 0,
                             "reason": "running"}
    # a previous run's garbage (serve mode); the process's own heap (imports, compiled code)
    # is frozen once before the first run, so this and the run's gen-2 collections are short
    gc.collect()
    stats["drained_frames"] = _drain(bus)
    counts_before = _bus_counts(bus)
    print(announce, flush=True)
    code = 0
    try:
        trace.write_values(sim.truth_values())
        loop = _run_lockstep if args.mode == "lockstep" else _run_realtime
        loop_start = time.monotonic()
        try:
            stats["reason"] = loop(bus, node, trace, args, stats, stop)
        finally:
            stats["loop_wall_s"] = time.monotonic() - loop_start
    except BusDisconnected as exc:
        print(f"rhonn-plant: error: bus lost: {exc}", file=sys.stderr)
        stats["reason"], code = "bus lost", 3
    except OSError as exc:  # the run's files cannot be written (disk full): not a bug
        stats["reason"], code = f"error: {_write_error(exc)}", 1
        print(f"rhonn-plant: {stats['reason']}", file=sys.stderr)
    except Exception as exc:  # a bug: its files are still written, the caller ends
        traceback.print_exc(file=sys.stderr)
        what = " ".join(f"{type(exc).__name__}: {exc}".split())  # one line
        stats["reason"], code = f"error: {what}", 1
    finally:
        try:
            trace.close()
        except OSError as exc:  # the rows stay in the row file; the reason says so
            if code == 0:
                stats["reason"], code = f"error: {_write_error(exc)}", 1
            print(f"rhonn-plant: error: {_write_error(exc)}", file=sys.stderr)
        stats.update(cycles=sim.cycle, sim_time_s=sim.time_s, spun=bool(sim.spun),
                     fallback_cycles=node.fallback_cycles,
                     commanded_cycles=node.commanded_cycles,
                     held_cycles=node.held_cycles,
                     torque_rejections=node.monitor.rejection_counts(),
                     # frames dropped by a bounded rx queue (docs/safety/queues.md)
                     rx_drops=node.rx_drop_counts(),
                     injected=dict(injector.counts) if injector else {},
                     secoc=node.secoc.summary() if node.secoc is not None
                     else {"enabled": False},
                     saturations=dict(getattr(sim, "saturations", {}) or {}),
                     bus_stats=_since(counts_before, _bus_counts(bus)),
                     cpu_affinity=sorted(os.sched_getaffinity(0))
                     if hasattr(os, "sched_getaffinity") else None)
        if args.summary:
            try:
                Path(args.summary).write_text(json.dumps(stats, indent=2) + "\n")
            except OSError as exc:  # the serve loop's "done"/"error" line still says it
                print(f"rhonn-plant: error: {_write_error(exc)} ({args.summary})",
                      file=sys.stderr)
    return code, stats


def _write_error(exc: OSError) -> str:
    """One line for a file the plant could not write (disk full, file too large)."""
    where = f" ({exc.filename})" if exc.filename else ""
    return f"cannot write the run's files: {exc.strerror or exc}{where}"


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    log = setup_logging("rhonn-plant", *logging_args(args))
    if args.serve:
        given = [f"--{name.replace('_', '-')}" for name in vars(args)
                 if name not in (*PROCESS_OPTIONS, *SERVE_DEFAULTS)
                 and getattr(args, name) != parser.get_default(name)]
        if given:
            parser.error(f"--serve: give {', '.join(given)} with each run on stdin, "
                         "not at start")
        try:
            check_bus(args.bus, allow_auto=False)
            if args.secoc:
                load_keys(resolve_key_source(args.secoc_keys))
        except (UsageError, SecOcKeyError) as exc:
            parser.error(str(exc))
        return _serve(args, log)
    if args.scenario is None:
        parser.error("the following arguments are required: --scenario")
    codec = Codec()  # stateless: one DBC parse for the node, the injector and SecOC
    try:  # every argument is checked before the bus is opened or a file written
        run = PlantRun(args, codec)
        check_bus(args.bus, allow_auto=False)
        node, trace = run.start()
    except (UsageError, FaultSpecError, SecOcKeyError) as exc:
        parser.error(str(exc))
    # the imports and the first scenario set-up (numba compiles the vehicle step on a first
    # start, cached after) are the slow part of a start: the line says how long they took
    log.info("starting plant %s on %s, %s; %.1f s since the process started",
             args.scenario, args.bus, args.mode, process_age_s())
    stop = StopFlag()
    if args.rt:
        make_realtime("rhonn-plant")
    freeze_heap()  # everything alive after set-up: out of reach of later gen-2 collections
    # (before the bus opens: frames cannot pile up during the collection)
    bus = open_bus_for_process(args.bus, "rhonn-plant", args.reconnect_s)
    if bus is None:
        trace.close()
        return 3
    try:
        code, stats = run_one(bus, run, node, trace, stop,
                              f"ready {args.scenario} on {args.bus} ({args.mode}, "
                              f"{secoc_state_text(run.keys)})")
    finally:
        bus.shutdown()
    print(f"stopped: {stats['reason']} after {node.sim.cycle} cycles, "
          f"{node.fallback_cycles} fallback cycles", flush=True)
    if code == 0 and stats["reason"] == "finished" and not args.fault \
            and fallback_passed(node.fallback_cycles, node.sim.cycle):
        # the run reached its end but was not a closed loop: as the harness's "degraded"
        print(f"rhonn-plant: degraded: {fallback_text(node.fallback_cycles, node.sim.cycle)}: "
              f"{FALLBACK_HINT}", file=sys.stderr, flush=True)
        return EXIT_DEGRADED
    return code


class _CommandLines:
    """Lines of the control channel (a file descriptor), read so that a stop signal ends the
    wait for the next one within COMMAND_POLL_MS."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._buffer = b""
        self._eof = False
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN | select.POLLHUP)

    def next(self, stop: Callable[[], bool]) -> bytes | None:
        """The next line (without its newline); None at end of input or on a stop signal."""
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                line, self._buffer = self._buffer[:end], self._buffer[end + 1:]
                return line
            if self._eof or stop():
                line, self._buffer = self._buffer, b""
                return line if line.strip() and not stop() else None
            if len(self._buffer) > COMMAND_MAX_BYTES:
                self._buffer = b""  # no newline in sight: not a command; keep reading
                return b"<too long>"
            if self._poll.poll(COMMAND_POLL_MS):
                chunk = os.read(self._fd, 65536)
                self._eof = not chunk
                self._buffer += chunk


def _command_run_args(line: bytes) -> list[str] | None:
    """The run arguments of a command line; None for ``{"quit": true}``; UsageError else."""
    try:
        command = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        text = line[:80].decode(errors="replace")
        raise UsageError(f"not a JSON command: {text!r}") from None
    if isinstance(command, dict) and command.get("quit") is True and len(command) == 1:
        return None
    if not isinstance(command, dict) or set(command) != {"run"}:
        raise UsageError('a command is {"run": [ARGS...]} or {"quit": true}')
    argv = command["run"]
    if not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        raise UsageError('"run" takes a list of argument strings')
    return argv


def _serve(args: argparse.Namespace, log: Any) -> int:
    """Serve mode (see the module docstring); the process's exit code."""
    codec = Codec()
    run_parser = _run_parser(args)
    warm_up = check_scenario(WARM_UP_SCENARIO, None, None, {})
    warm_up.step_comm(None)  # its own objects and RNGs: no run sees them
    del warm_up
    stop = StopFlag()
    if args.rt:
        make_realtime("rhonn-plant")
    # the heap of every run (imports, compiled code): frozen once; a run's own objects are
    # not, so the next run's collection frees them
    freeze_heap()
    bus = open_bus_for_process(args.bus, "rhonn-plant", args.reconnect_s)
    if bus is None:
        return 3
    commands = _CommandLines(sys.stdin.fileno())
    print(f"ready serve on {args.bus}", flush=True)
    log.info("plant ready to serve in %.1f s", process_age_s())
    runs = 0
    try:
        while not stop():
            line = commands.next(stop)
            if line is None:
                break
            if not line.strip():
                continue
            started = time.monotonic()
            try:
                argv = _command_run_args(line)
                if argv is None:
                    break
                run = PlantRun(run_parser.parse_args(argv), codec)
                node, trace = run.start()
            except (UsageError, FaultSpecError, SecOcKeyError) as exc:
                print(f"error {' '.join(str(exc).split())}", flush=True)
                continue
            runs += 1
            log.info("run %d: %s set up in %.3f s", runs, run.args.scenario,
                     time.monotonic() - started)
            code, stats = run_one(bus, run, node, trace, stop, f"loaded {run.args.scenario}")
            if code == 1:  # a bug: the summary holds "error: WHAT"
                print(f"error run failed: {stats['reason'].removeprefix('error: ')}",
                      flush=True)
                return 1
            print("done " + json.dumps(stats, separators=(",", ":")), flush=True)
            if code != 0:
                return code
        return 0
    finally:
        bus.shutdown()


def _done(sim: Simulation, args: argparse.Namespace) -> bool:
    return sim.finished or (args.duration is not None and sim.time_s >= args.duration - 1e-9)


def _run_lockstep(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                  args: argparse.Namespace, stats: dict[str, Any], stopped) -> str:
    sim = node.sim
    wait_s = args.wait_ms / 1000.0
    sync_id = node.codec.messages["SYNC"].frame_id
    sync_auth_id = node.codec.messages["SYNC_AUTH"].frame_id
    consecutive_timeouts = 0
    reconnects_seen = getattr(bus, "reconnects", 0)
    resync_until = 0.0  # wall clock, s: wait for the controller again until then
    while not stopped():
        if _done(sim, args):
            return "finished"
        if getattr(bus, "reconnects", 0) != reconnects_seen:
            # Our bus came back after an outage: every client is reconnecting too, so wait
            # for the controller (each cycle up to wait_ms) for as long as a client may take
            # to reconnect, instead of racing through the outage at machine speed.
            reconnects_seen = getattr(bus, "reconnects", 0)
            resync_until = time.monotonic() + args.reconnect_s
        frames = node.burst()
        send_all(bus, frames)
        now_sim = sim.time_s
        echo = sim.cycle % 256
        command = None
        # No answer can come when our own SYNC was dropped by an injected fault, and none is
        # waited for once the controller is considered lost.
        sync_sent = any(f.arbitration_id == sync_id for f in frames) and (
            node.secoc is None  # SecOC: a SYNC without its authenticator is not answered
            or any(f.arbitration_id == sync_auth_id for f in frames))
        lost = consecutive_timeouts >= args.lost_after and time.monotonic() > resync_until
        deadline = time.monotonic() + (wait_s if sync_sent and not lost else 0.0)
        answered = late_answer = False
        late_reads = 0  # frames read after the deadline
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                if late_reads >= LATE_READS_MAX:
                    # frames keep coming past the deadline (a flood): the cycle ends here,
                    # the rest waits in the bounded hub queue for the next cycle's reads
                    stats["waits_cut_by_flood"] += 1
                    break
                late_reads += 1
            msg = bus.recv(timeout=max(0.0, remaining))
            if msg is None:
                break
            got = node.receive(msg, now_sim)
            if got is None:
                continue
            if int(got.values["ECHO_CYCLE"]) != echo:
                late_answer = True  # a valid answer to an earlier cycle: controller alive
                continue
            if got.name == TORQUE_FRAME:
                command = got
                break
            answered = True  # status of cycle k seen: its torque frame was lost on the way
            break
        if command is None and not answered and sync_sent:
            stats["lockstep_timeouts"] += 1
            # torque frames reappeared (late): wait for the answers again from the next cycle;
            # while our own bus is down (a restarting bus server) the SYNC went nowhere:
            # that is no sign of a lost controller, so the lockstep keeps waiting.
            if late_answer:
                consecutive_timeouts = 0
            elif getattr(bus, "connected", True):
                consecutive_timeouts += 1
        elif command is not None or answered:
            consecutive_timeouts = 0
        node.advance(command, now_sim)
        trace.write_values(sim.truth_values())
    return "stopped by signal"


def _run_realtime(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                  args: argparse.Namespace, stats: dict[str, Any], stopped) -> str:
    sim = node.sim
    start = time.monotonic()
    # from the cycle's deadline to its burst sent; longer than the threshold: a stall
    stall = StallWatch(clock=time.monotonic_ns)
    stats["stalls"] = stall.ring  # (the summary is written at exit)
    watching = False
    try:
        while not stopped():
            if _done(sim, args):
                return "finished"
            burst = node.burst()
            if watching:
                stall.mark("burst")
            send_all(bus, burst)
            if watching:
                stall.mark("send")
                stall.end(sim.cycle)
            _realtime_cycle(bus, node, trace, stats, stall, start)
            watching = True
        return "stopped by signal"
    finally:
        stats["stalls"] = stall.summary()


def _realtime_cycle(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                    stats: dict[str, Any], stall: StallWatch, start: float) -> None:
    """Receive until the next cycle's deadline, then integrate it (the command in force:
    :meth:`PlantNode.advance`)."""
    sim = node.sim
    period = sim.comm_period_s
    next_cycle = start + (sim.cycle + 1) * period
    fresh: Decoded | None = None  # the newest torque command accepted in this cycle
    while True:
        remaining = next_cycle - time.monotonic()
        if remaining <= 0:
            break
        msg = bus.recv(timeout=remaining)
        if msg is not None:
            got = node.receive(msg, time.monotonic())
            if got is not None and got.name == TORQUE_FRAME:
                fresh = got
    stall.begin(round(next_cycle * 1e9))
    stall.mark("wakeup")  # how late the wait loop saw the deadline
    if -remaining > period:
        stats["overruns"] += 1
    node.advance(fresh, time.monotonic())
    stall.mark("advance")
    trace.write_values(sim.truth_values())
    stall.mark("trace")


if __name__ == "__main__":
    raise SystemExit(main())


