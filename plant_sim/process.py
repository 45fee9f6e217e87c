"""`rhonn-plant`: the vehicle simulator as a process on the CAN bus.

  rhonn-plant --bus SPEC --scenario NAME|FILE.toml [--mode lockstep|realtime] [--trace FILE]
              [--summary FILE] [--mu X] [--speed KMH] [--seed N] [--param KEY=VALUE ...]
              [--vehicle KEY=VALUE ...]
              [--secoc [--secoc-keys env|ci-test-key|KEYFILE] [--secoc-state FILE]]

Every 10 ms communication cycle it publishes DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS,
VEHICLE_EST and ends the burst with SYNC. Lockstep: it then waits for the WHEEL_TORQUE_CMD that
echoes the cycle (wall-clock timeout → the cycle falls back, counted; after
``--lost-after`` consecutive timeouts it stops waiting until torque frames reappear, so a dead
controller does not slow the run to a crawl). Real-time: it paces on the monotonic clock and
applies the latest valid command (rx monitor timeout 3 cycles). Without a valid command the
car drives as one without the stability function: the driver's torque split evenly.

SecOC (``--secoc``, see can_db/secoc.py): SYNC and the driver and sensor frames are each
followed by their authenticator (faults of the plant's own sensors and E2E protection are
injected before signing, bus faults after); torque and status frames are used only after
their authenticator verifies, so a rejected (forged, replayed, corrupted) command is handled
exactly as a missing one.

The truth trace is ``FILE.rows`` during the run (one packed row per cycle, readable after a
kill, can_db/process/rowlog.py) and the CSV ``FILE`` from when the plant stops; the summary
JSON holds the counters (fallback cycles, rejected torque frames by reason, saturations, overruns).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import can

from can_db.codec import Codec, Decoded, Transmitter
from can_db.faults import FaultInjector, FaultSpecError, parse_faults
from can_db.monitor import RxMonitor
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
from can_db.secoc_keys import SecOcKeyError, TripCounter, load_keys
from can_db.transport.bus import BusDisconnected, open_bus_for_process, send_all
from can_db.transport.check import check_bus
from plant_sim.overrides import apply_vehicle_overrides, parse_key_values
from plant_sim.params import load_vehicle_params
from plant_sim.scenario import (
    ScenarioError,
    check_scenario_ref,
    list_scenarios,
    load_scenario,
    scenario_source,
)
from plant_sim.scenario_schema import DURATION_MAX_S, MU_MAX, SPEED_MAX_KMH
from plant_sim.simulation import Simulation

TORQUE_FRAME = "WHEEL_TORQUE_CMD"
WHEELS = ("FL", "FR", "RL", "RR")
# Lockstep: frames read after the cycle's deadline at most (one full send_many packet). The
# wait for the answer then ends even when frames keep arriving; without this limit a flood
# faster than the plant reads would hold it in one cycle's wait for ever.
LATE_READS_MAX = 64




class TraceWriter:
    """Truth trace (every value ``%.9g``): one packed row per cycle during the run
    (can_db/process/rowlog.py: one write(2), a SIGKILLed plant loses no finished cycle), turned into
    the CSV ``path`` on close — the same bytes a line-per-cycle CSV writer gives, ≈ 15 µs a
    lockstep cycle cheaper. (Buffering for 0.2 wall seconds lost ~1 s of simulated time in
    lockstep.)"""

    def __init__(self, path: str | None, columns: list[str]) -> None:
        self.columns = columns
        self._log = RowLog(path, columns, ["%.9g"] * len(columns)) if path else None

    def write(self, row: dict[str, float]) -> None:
        """One row keyed by column."""
        self.write_values(tuple([row[c] for c in self.columns]))

    def write_values(self, values: tuple[float, ...]) -> None:
        """One row of values in column order (``Simulation.truth_values``)."""
        if self._log is not None:
            self._log.write(values)

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None


class PlantNode:
    """Frames out of the simulation, torque commands into it (no sockets, no clocks)."""

    def __init__(self, sim: Simulation, codec: Codec | None = None,
                 injector: FaultInjector | None = None,
                 secoc: PlantSecOc | None = None) -> None:
        self.sim = sim
        self.secoc = secoc  # SecOC hook: None = frames are not authenticated
        self.codec = codec or Codec()
        self.injector = injector
        self.tx = Transmitter(self.codec)
        self.monitor = RxMonitor(self.codec, (TORQUE_FRAME, "CTRL_STATUS", "CTRL_REFS"))
        self.torque_id = self.codec.messages[TORQUE_FRAME].frame_id
        self.fallback_cycles = 0
        self.commanded_cycles = 0

    def burst(self) -> list[can.Message]:
        """The frames of the current cycle, SYNC last (after fault injection, if any)."""
        frames = self._clean_burst()
        if self.secoc is not None:  # SecOC hook: authenticators after SYNC and the data frames
            if self.injector is not None:  # faults of the plant's own sensors and E2E first:
                frames = self.injector.apply(frames, self.sim.time_s, stage="sender")  # signed
                return self.injector.apply(self.secoc.protect(frames, self.sim.cycle),
                                           self.sim.time_s, stage="bus")
            frames = self.secoc.protect(frames, self.sim.cycle)
        if self.injector is None:
            return frames
        return self.injector.apply(frames, self.sim.time_s)

    def _clean_burst(self) -> list[can.Message]:
        s = self.sim.sensors()
        ws = s.wheel_speeds_radps
        return [
            self.tx.message("DRIVER_INPUTS", {
                "SWA": s.swa_deg, "ACCEL_PEDAL": 100.0 * s.accel_pedal,
                "BRAKE_PEDAL": 100.0 * s.brake_pedal, "STAB_ENABLE": float(s.stab_enable)}),
            self.tx.message("MOTION_SENSORS", {"YAW_RATE": s.yaw_rate_degps, "AX": s.ax_mps2,
                                               "AY": s.ay_mps2}),
            self.tx.message("WHEEL_SPEEDS", {f"WS_{w}": ws[i] for i, w in enumerate(WHEELS)}),
            self.tx.message("VEHICLE_EST", {"VX_EST": s.vx_est_mps, "VY_EST": s.vy_est_mps}),
            self.tx.message("SYNC", {"CYCLE": self.sim.cycle, "SIM_TIME": self.sim.time_s}),
        ]

    def receive(self, msg: can.Message, now_s: float) -> Decoded | None:
        """Validate a frame; return it when it is an accepted torque command or status."""
        if self.secoc is not None:  # SecOC hook: verified before the E2E monitor sees it
            verified = self.secoc.feed(msg, self.sim.cycle)
            if verified is None:
                return None
            msg = verified
        result = self.monitor.process(msg, now_s)
        if isinstance(result, Decoded) and result.name in (TORQUE_FRAME, "CTRL_STATUS"):
            return result
        return None

    def rx_drop_counts(self) -> dict[str, int]:
        """Frames dropped by the plant's bounded rx queues, by reason: the SecOC receiver's
        pending frames (``secoc_pending_full``); the plant buffers nothing else."""
        if self.secoc is None:
            return {}
        return {"secoc_pending_full": int(getattr(self.secoc.receiver, "evicted", 0))}

    def advance(self, command: Decoded | None) -> None:
        """Integrate one cycle with the command's torques, or the driver fallback."""
        if command is None:
            self.fallback_cycles += 1
            self.sim.step_comm(None)
        else:
            self.commanded_cycles += 1
            v = command.values
            self.sim.step_comm([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])


def parse_params(items: list[str]) -> dict[str, Any]:
    """``--param KEY=VALUE`` items as a dict (numbers as float, a value in brackets as a JSON
    list, e.g. ``steps=[[8,0.3]]``); UsageError if malformed."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--param needs KEY=VALUE, got {item!r}")
        if value.strip().startswith("["):
            try:
                out[key.strip()] = json.loads(value)
            except ValueError:
                raise UsageError(f"--param {key.strip()}: not a JSON list: {value!r}") from None
            continue
        try:
            out[key.strip()] = float(value)
        except ValueError:
            out[key.strip()] = value
    return out


def scenario_arg(text: str) -> str:
    """``argparse`` type of a scenario: a packaged name, or a path to a scenario file
    (anything containing '/' or ending in .toml; child processes inherit the working
    directory, so a relative path names the same file). The file's content is checked by
    :func:`check_scenario`, so its errors name the file as the user wrote it."""
    try:
        check_scenario_ref(text)
    except ScenarioError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def check_scenario(name: str, mu: float | None, speed_kmh: float | None,
                   params: dict[str, Any], seed: int = 0,
                   vehicle: dict[str, float] | None = None) -> Simulation:
    """Load the scenario (a packaged name or a file) with its overrides, apply the plant
    overrides and build the simulation once (nothing runs); any problem is a one-line
    UsageError naming the file or option, the key and the problem."""
    try:
        scenario = load_scenario(name, mu=mu, speed_kmh=speed_kmh, **params)
    except ScenarioError as exc:
        raise UsageError(str(exc)) from None
    try:
        car = apply_vehicle_overrides(load_vehicle_params(), vehicle or {})
    except ValueError as exc:
        raise UsageError(f"--vehicle: {exc}") from None
    try:
        return Simulation(scenario, params=car, seed=seed)
    except (KeyError, ValueError, TypeError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        raise UsageError(f"{scenario_source(name)}: {msg}") from None


def _parser() -> OneLineParser:
    parser = OneLineParser(prog="rhonn-plant", description=__doc__)
    parser.add_argument("--bus", required=True,
                        help="socketcan:IFACE | remote:ws://127.0.0.1:PORT/ | virtual:NAME")
    parser.add_argument("--scenario", required=True, type=scenario_arg, metavar="NAME|FILE",
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
    parser.add_argument("--fault", action="append", default=[], metavar="KIND[:ARG][@T]",
                        help="inject a frame fault on the plant's frames, repeatable "
                             "(see can_db/faults.py)")
    parser.add_argument("--reconnect-s", type=number(lo=0.0, unit="s"), default=5.0,
                        help="loopback bus: how long a lost server may stay away, s")
    parser.add_argument("--fault-seed", type=number(int, lo=0), default=1,
                        help="seed of the fault injector's randomness")
    parser.add_argument("--rt", action="store_true",
                        help="SCHED_FIFO (and $RHONN_RT_CPUS affinity) where permitted")
    parser.add_argument("--secoc", action="store_true",
                        help="authenticate SYNC, verify torque/status frames (SecOC)")
    parser.add_argument("--secoc-keys", default="env",
                        help="SecOC keys: env | ci-test-key | KEYFILE (mode 600)")
    parser.add_argument("--secoc-state", default=None,
                        help="SecOC trip-counter file (+1 at every start; needed so a "
                             "restarted plant is accepted again)")
    parser.add_argument("--secoc-max-age", type=number(int, lo=1), default=MAX_AGE_CYCLES,
                        help="SecOC forward window: oldest acceptable answered cycle, cycles")
    parser.add_argument("--lost-after", type=number(int, lo=1), default=3,
                        help="lockstep: consecutive timeouts before the controller is "
                             "considered lost (no more waiting until it answers again)")
    add_logging_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    log = setup_logging("rhonn-plant", *logging_args(args))
    try:  # every argument is checked before the bus is opened or a file written
        try:
            vehicle = parse_key_values(args.vehicle)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        sim = check_scenario(args.scenario, args.mu, args.speed, parse_params(args.param),
                             args.seed, vehicle)
        faults = parse_faults(args.fault)
        injector = FaultInjector(Codec(), faults, seed=args.fault_seed,
                                 lockstep=args.mode == "lockstep") if args.fault else None
        for path, what in ((args.trace, "--trace"), (args.summary, "--summary")):
            if path:
                check_out_file(path, what)
        check_bus(args.bus, allow_auto=False)
    except (UsageError, FaultSpecError) as exc:
        parser.error(str(exc))
    # the imports and the first scenario set-up (numba compiles the vehicle step on a first
    # start, cached after) are the slow part of a start: the line says how long they took
    log.info("starting plant %s on %s, %s; %.1f s since the process started",
             args.scenario, args.bus, args.mode, process_age_s())
    secoc = None
    if args.secoc:
        try:
            secoc = PlantSecOc(Codec(), load_keys(args.secoc_keys),
                               TripCounter(args.secoc_state).next_trip(),
                               max_age_cycles=args.secoc_max_age)
        except SecOcKeyError as exc:
            parser.error(str(exc))
    node = PlantNode(sim, injector=injector, secoc=secoc)
    trace = TraceWriter(args.trace, list(sim.trace_columns))
    stats: dict[str, Any] = {"scenario": args.scenario, "mode": args.mode, "cycles": 0,
                             "lockstep_timeouts": 0, "overruns": 0, "waits_cut_by_flood": 0,
                             "reason": "running"}
    stop = StopFlag()
    if args.rt:
        make_realtime("rhonn-plant")
    freeze_heap()  # everything alive after set-up: out of reach of later gen-2 collections
    # (before the bus opens: frames cannot pile up during the collection)
    bus = open_bus_for_process(args.bus, "rhonn-plant", args.reconnect_s)
    if bus is None:
        return 3
    print(f"ready {args.scenario} on {args.bus} ({args.mode})", flush=True)
    log.info("plant ready in %.1f s", process_age_s())
    code = 0
    try:
        trace.write_values(sim.truth_values())
        run = _run_lockstep if args.mode == "lockstep" else _run_realtime
        loop_start = time.monotonic()
        try:
            stats["reason"] = run(bus, node, trace, args, stats, stop)
        finally:
            stats["loop_wall_s"] = time.monotonic() - loop_start
    except BusDisconnected as exc:
        print(f"rhonn-plant: error: bus lost: {exc}", file=sys.stderr)
        stats["reason"], code = "bus lost", 3
    finally:
        trace.close()
        bus.shutdown()
        stats.update(cycles=sim.cycle, sim_time_s=sim.time_s, spun=bool(sim.spun),
                     fallback_cycles=node.fallback_cycles,
                     commanded_cycles=node.commanded_cycles,
                     torque_rejections=node.monitor.rejection_counts(),
                     # frames dropped by a bounded rx queue (docs/safety/queues.md)
                     rx_drops=node.rx_drop_counts(),
                     injected=dict(injector.counts) if injector else {},
                     secoc=secoc.summary() if secoc is not None else {"enabled": False},
                     saturations=dict(getattr(sim, "saturations", {}) or {}),
                     bus_stats=bus.stats() if hasattr(bus, "stats") else None,
                     cpu_affinity=sorted(os.sched_getaffinity(0))
                     if hasattr(os, "sched_getaffinity") else None)
        if args.summary:
            Path(args.summary).write_text(json.dumps(stats, indent=2) + "\n")
    print(f"stopped: {stats['reason']} after {sim.cycle} cycles, "
          f"{node.fallback_cycles} fallback cycles", flush=True)
    return code


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
        node.advance(command)
        trace.write_values(sim.truth_values())
    return "stopped by signal"


def _run_realtime(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                  args: argparse.Namespace, stats: dict[str, Any], stopped) -> str:
    sim = node.sim
    start = time.monotonic()
    latest: Decoded | None = None
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
            latest = _realtime_cycle(bus, node, trace, stats, stall, start, latest)
            watching = True
        return "stopped by signal"
    finally:
        stats["stalls"] = stall.summary()


def _realtime_cycle(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                    stats: dict[str, Any], stall: StallWatch, start: float,
                    latest: Decoded | None) -> Decoded | None:
    """Receive until the next cycle's deadline, then integrate it; returns the latest
    accepted torque command."""
    sim = node.sim
    period = sim.comm_period_s
    next_cycle = start + (sim.cycle + 1) * period
    while True:
        remaining = next_cycle - time.monotonic()
        if remaining <= 0:
            break
        msg = bus.recv(timeout=remaining)
        if msg is not None:
            got = node.receive(msg, time.monotonic())
            if got is not None and got.name == TORQUE_FRAME:
                latest = got
    stall.begin(round(next_cycle * 1e9))
    stall.mark("wakeup")  # how late the wait loop saw the deadline
    if -remaining > period:
        stats["overruns"] += 1
    now = time.monotonic()
    valid = latest is not None and node.monitor.valid(TORQUE_FRAME, now)
    node.advance(latest if valid else None)
    stall.mark("advance")
    trace.write_values(sim.truth_values())
    stall.mark("trace")
    return latest


if __name__ == "__main__":
    raise SystemExit(main())


