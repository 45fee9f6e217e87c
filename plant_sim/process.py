"""`rhonn-plant`: the vehicle simulator as a process on the CAN bus.

  rhonn-plant --bus SPEC --scenario NAME [--mode lockstep|realtime] [--trace FILE]
              [--summary FILE] [--mu X] [--speed KMH] [--seed N] [--param KEY=VALUE ...]
              [--secoc [--secoc-keys env|ci-test-key|KEYFILE] [--secoc-state FILE]]

Every 10 ms communication cycle it publishes DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS,
VEHICLE_EST and ends the burst with SYNC. Lockstep: it then waits for the WHEEL_TORQUE_CMD that
echoes the cycle (wall-clock timeout → the cycle falls back, counted; after
``--lost-after`` consecutive timeouts it stops waiting until torque frames reappear, so a dead
controller does not slow the run to a crawl). Real-time: it paces on the monotonic clock and
applies the latest valid command (rx monitor timeout 3 cycles). Without a valid command the
car drives as one without the stability function: the driver's torque split evenly.

SecOC (``--secoc``, see can_db/secoc.py): SYNC is followed by its authenticator; torque and
status frames are used only after their authenticator verifies, so a rejected (forged,
replayed, corrupted) command is handled exactly as a missing one.

The truth trace is CSV written line by line (readable after a kill); the summary JSON holds
the counters (fallback cycles, rejected torque frames by reason, saturations, overruns).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import can

from can_db.bus import BusDisconnected, open_bus_for_process
from can_db.codec import Codec, Decoded, Transmitter
from can_db.faults import FaultInjector, FaultSpecError, parse_faults
from can_db.monitor import RxMonitor
from can_db.secoc import MAX_AGE_CYCLES, PlantSecOc
from can_db.secoc_keys import SecOcKeyError, TripCounter, load_keys
from can_db.stopflag import StopFlag
from plant_sim.scenario import list_scenarios, load_scenario
from plant_sim.simulation import Simulation

TORQUE_FRAME = "WHEEL_TORQUE_CMD"
WHEELS = ("FL", "FR", "RL", "RR")


class TraceWriter:
    """Truth trace as CSV, one flushed line per cycle."""

    def __init__(self, path: str | None, columns: list[str]) -> None:
        self.columns = columns
        self._fh: TextIO | None = None
        if path:
            self._fh = open(path, "w", buffering=1)  # noqa: SIM115 - closed in close()
            self._fh.write(",".join(columns) + "\n")

    def write(self, row: dict[str, float]) -> None:
        if self._fh is not None:
            self._fh.write(",".join(f"{row[c]:.9g}" for c in self.columns) + "\n")

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


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
        if self.secoc is not None:  # SecOC hook: SYNC_AUTH after SYNC
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

    def advance(self, command: Decoded | None) -> None:
        """Integrate one cycle with the command's torques, or the driver fallback."""
        if command is None:
            self.fallback_cycles += 1
            self.sim.step_comm(None)
        else:
            self.commanded_cycles += 1
            v = command.values
            self.sim.step_comm([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])


def _parse_params(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--param needs KEY=VALUE, got {item!r}")
        try:
            out[key] = float(value)
        except ValueError:
            out[key] = value
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rhonn-plant", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bus", required=True)
    parser.add_argument("--scenario", required=True, help=", ".join(list_scenarios()))
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--trace", default=None, help="truth trace CSV")
    parser.add_argument("--summary", default=None, help="counters as JSON at exit")
    parser.add_argument("--mu", type=float, default=None, help="override road friction")
    parser.add_argument("--speed", type=float, default=None, help="override speed, km/h")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=None, help="stop after S sim s")
    parser.add_argument("--param", action="append", default=[], help="scenario KEY=VALUE")
    parser.add_argument("--wait-ms", type=float, default=200.0,
                        help="lockstep: wall-clock wait for the echoing torque frame")
    parser.add_argument("--fault", action="append", default=[],
                        help="inject a frame fault on the plant's frames: KIND[:ARG][@T] "
                             "(see can_db/faults.py)")
    parser.add_argument("--reconnect-s", type=float, default=5.0,
                        help="loopback bus: how long a lost server may stay away, s")
    parser.add_argument("--fault-seed", type=int, default=1)
    parser.add_argument("--secoc", action="store_true",
                        help="authenticate SYNC, verify torque/status frames (SecOC)")
    parser.add_argument("--secoc-keys", default="env",
                        help="SecOC keys: env | ci-test-key | KEYFILE (mode 600)")
    parser.add_argument("--secoc-state", default=None,
                        help="SecOC trip-counter file (+1 at every start; needed so a "
                             "restarted plant is accepted again)")
    parser.add_argument("--secoc-max-age", type=int, default=MAX_AGE_CYCLES,
                        help="SecOC forward window: oldest acceptable answered cycle, cycles")
    parser.add_argument("--lost-after", type=int, default=3,
                        help="lockstep: consecutive timeouts before the controller is "
                             "considered lost (no more waiting until it answers again)")
    args = parser.parse_args(argv)

    scenario = load_scenario(args.scenario, mu=args.mu, speed_kmh=args.speed,
                             **_parse_params(args.param))
    sim = Simulation(scenario, seed=args.seed)
    try:
        faults = parse_faults(args.fault)
        injector = FaultInjector(Codec(), faults, seed=args.fault_seed,
                                 lockstep=args.mode == "lockstep") if args.fault else None
    except FaultSpecError as exc:
        parser.error(str(exc))
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
                             "lockstep_timeouts": 0, "overruns": 0, "reason": "running"}
    stop = StopFlag()
    bus = open_bus_for_process(args.bus, "rhonn-plant", args.reconnect_s)
    if bus is None:
        return 3
    print(f"ready {args.scenario} on {args.bus} ({args.mode})", flush=True)
    code = 0
    try:
        trace.write(sim.truth_row())
        run = _run_lockstep if args.mode == "lockstep" else _run_realtime
        loop_start = time.monotonic()
        try:
            stats["reason"] = run(bus, node, trace, args, stats, stop)
        finally:
            stats["loop_wall_s"] = time.monotonic() - loop_start
    except BusDisconnected as exc:
        print(f"rhonn-plant: bus lost: {exc}", file=sys.stderr)
        stats["reason"], code = "bus lost", 3
    finally:
        trace.close()
        bus.shutdown()
        stats.update(cycles=sim.cycle, sim_time_s=sim.time_s, spun=bool(sim.spun),
                     fallback_cycles=node.fallback_cycles,
                     commanded_cycles=node.commanded_cycles,
                     torque_rejections=node.monitor.rejection_counts(),
                     injected=dict(injector.counts) if injector else {},
                     secoc=secoc.summary() if secoc is not None else {"enabled": False},
                     saturations=dict(getattr(sim, "saturations", {}) or {}))
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
    while not stopped():
        if _done(sim, args):
            return "finished"
        frames = node.burst()
        for frame in frames:
            bus.send(frame)
        now_sim = sim.time_s
        echo = sim.cycle % 256
        command = None
        # No answer can come when our own SYNC was dropped by an injected fault, and none is
        # waited for once the controller is considered lost.
        sync_sent = any(f.arbitration_id == sync_id for f in frames) and (
            node.secoc is None  # SecOC: a SYNC without its authenticator is not answered
            or any(f.arbitration_id == sync_auth_id for f in frames))
        lost = consecutive_timeouts >= args.lost_after
        deadline = time.monotonic() + (wait_s if sync_sent and not lost else 0.0)
        answered = late_answer = False
        while True:
            remaining = deadline - time.monotonic()
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
            # torque frames reappeared (late): wait for the answers again from the next cycle
            consecutive_timeouts = 0 if late_answer else consecutive_timeouts + 1
        elif command is not None or answered:
            consecutive_timeouts = 0
        node.advance(command)
        trace.write(sim.truth_row())
    return "stopped by signal"


def _run_realtime(bus: can.BusABC, node: PlantNode, trace: TraceWriter,
                  args: argparse.Namespace, stats: dict[str, Any], stopped) -> str:
    sim = node.sim
    period = sim.comm_period_s
    start = time.monotonic()
    latest: Decoded | None = None
    while not stopped():
        if _done(sim, args):
            return "finished"
        for frame in node.burst():
            bus.send(frame)
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
        if -remaining > period:
            stats["overruns"] += 1
        now = time.monotonic()
        valid = latest is not None and node.monitor.valid(TORQUE_FRAME, now)
        node.advance(latest if valid else None)
        trace.write(sim.truth_row())
    return "stopped by signal"


if __name__ == "__main__":
    raise SystemExit(main())


