"""`rhonn-controller`: the stability controller as a standalone process on a CAN bus.

  rhonn-controller --bus SPEC --controller NAME [--config FILE] [--mode lockstep|freerun]
                   [--timing FILE] [--rerun FILE] [--checkpoint FILE [--checkpoint-every N]]
                   [--secoc [--secoc-keys env|ci-test-key|KEYFILE]]
                   [--rt] [--cpu CPU|auto [--keep-cpu-awake]]

Lockstep answers every SYNC frame with a torque frame echoing its cycle; free-running runs on
its own 10 ms schedule on the monotonic clock. SIGINT/SIGTERM stop it cleanly (logs flushed);
a malformed frame never stops it. Exit codes: 0 clean stop, 2 bad arguments, 3 bus lost.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import psutil

from can_db.codec import Codec
from can_db.faults import FaultInjector, FaultSpecError, parse_faults
from can_db.process.argcheck import (
    OneLineParser,
    UsageError,
    check_out_file,
    number,
)
from can_db.process.cpu import CpuChoiceError, KeepAwake, allowed_cpus, choose_cpu, pin_all_threads
from can_db.process.logsetup import (
    add_logging_options,
    logging_args,
    process_age_s,
    setup_logging,
)
from can_db.process.rowlog import RowLog
from can_db.process.rt import GcWatch, freeze_heap, make_realtime
from can_db.process.stall import StallWatch
from can_db.process.stopflag import StopFlag
from can_db.secoc import ControllerSecOc
from can_db.secoc_keys import SecOcKeyError, load_keys
from can_db.transport.bus import BusDisconnected, open_bus_for_process, send_all
from can_db.transport.check import check_bus
from controller.core.config_schema import CONFIG_LOAD_ERRORS, config_error_line
from controller.core.interfaces import Controller
from controller.core.params import load_vehicle_params
from controller.registry import CONTROLLER_NAMES, make_controller
from controller.runtime.checkpoint import CheckpointManager, config_hash
from controller.runtime.core_fault import FaultyCore, core_faults
from controller.runtime.node import ControllerNode

TIMING_COLUMNS = ("cycle", "sim_time_s", "step_us", "turnaround_us", "period_us",
                  "mpc_update", "qp_iterations", "qp_status", "mode", "deadline_miss")


TIMING_FORMATS = ("%d", "%.3f", "%.1f", "%.1f", "%.1f", "%d", "%d", "%d", "%d", "%d")


class TimingLog:
    """Per-cycle timing rows: one packed row per cycle during the run (can_db/process/rowlog.py:
    one write(2), a killed process leaves every finished row), the CSV ``path`` on close
    (the formatting is off the cycle; ≈ 6 µs a lockstep cycle measured in situ).

    Also samples the process's resident memory every ``RSS_EVERY`` cycles (after the frames
    of that cycle are sent) so long runs can show memory growth.
    """

    RSS_EVERY = 1000

    def __init__(self, path: str | None) -> None:
        self._log = RowLog(path, TIMING_COLUMNS, TIMING_FORMATS) if path else None
        self.rows = 0
        self.rss_samples_kb: list[int] = []
        self._proc = psutil.Process()

    def write(self, node: ControllerNode, turnaround_ns: int, period_ns: int,
              deadline_miss: bool) -> None:
        if self.rows % self.RSS_EVERY == 0:
            self.rss_samples_kb.append(self._proc.memory_info().rss // 1024)
        self.rows += 1
        if self._log is None:
            return
        rec, out = node.record, node.record.outputs
        self._log.write((rec.cycle, rec.sim_time_s, rec.step_ns / 1000,
                         turnaround_ns / 1000, period_ns / 1000, rec.mpc_update,
                         out.qp_iterations, out.qp_status, int(rec.mode), deadline_miss))

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None


def _parser() -> OneLineParser:
    parser = OneLineParser(prog="rhonn-controller", description=__doc__)
    parser.add_argument("--bus", required=True,
                        help="local:NAME | socketcan:IFACE | remote:ws://127.0.0.1:PORT/ | "
                             "virtual:NAME")
    parser.add_argument("--controller", required=True, choices=CONTROLLER_NAMES,
                        help="which controller runs")
    parser.add_argument("--config", default=None,
                        help="controller TOML file or packaged name such as 100hz "
                             "(default: the packaged default.toml, 20 Hz MPC)")
    parser.add_argument("--mode", choices=("lockstep", "freerun"), default="lockstep",
                        help="lockstep: answer each SYNC; freerun: own 10 ms schedule")
    parser.add_argument("--period-ms", type=number(lo=0.0, hi=1000.0, lo_open=True, unit="ms"),
                        default=10.0, help="communication cycle, ms (free-running schedule)")
    parser.add_argument("--timing", default=None, help="write the per-cycle timing CSV here")
    parser.add_argument("--rerun", default=None, help="write a rerun recording (.rrd) here")
    parser.add_argument("--summary", default=None, help="write the counters as JSON at exit")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND[:ARG][@T]",
                        help="inject a frame fault on the controller's frames, or "
                             "core-exception[:D][@T] (the core raises from T, for D), "
                             "repeatable (see can_db/faults.py)")
    parser.add_argument("--reconnect-s", type=number(lo=0.0, unit="s"), default=5.0,
                        help="loopback bus: how long a lost server may stay away, s")
    parser.add_argument("--fault-seed", type=number(int, lo=0), default=2,
                        help="seed of the fault injector's randomness")
    parser.add_argument("--checkpoint", default=None,
                        help="learned-state file (.npz): restored at start if it matches, "
                             "saved periodically and at a clean stop")
    parser.add_argument("--rt", action="store_true",
                        help="SCHED_FIFO (and $RHONN_RT_CPUS affinity) where permitted")
    parser.add_argument("--cpu", default=None, metavar="CPU|auto",
                        help="run on this CPU alone (auto: the highest one); the caller keeps "
                             "other processes off it (rhonn-harness run --controller-cpu)")
    parser.add_argument("--keep-cpu-awake", action="store_true",
                        help="with --cpu: a SCHED_IDLE spinner keeps that CPU from going "
                             "idle, so its caches stay warm (can_db/process/cpu.py)")
    parser.add_argument("--checkpoint-every", type=number(int, lo=1), default=None,
                        help="MPC steps between checkpoint saves (default: 1 s)")
    parser.add_argument("--secoc", action="store_true",
                        help="verify SYNC and authenticate torque/status frames (SecOC)")
    parser.add_argument("--secoc-keys", default="env",
                        help="SecOC keys: env | ci-test-key | KEYFILE (mode 600)")
    add_logging_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    log = setup_logging("rhonn-controller", *logging_args(args))
    try:  # every argument is checked before the bus is opened or a file written
        faults = parse_faults(args.fault)
        injector = FaultInjector(Codec(), faults, seed=args.fault_seed,
                                 lockstep=args.mode == "lockstep") if args.fault else None
        controller = _make_controller(args.controller, args.config)
        for path, what in ((args.timing, "--timing"), (args.rerun, "--rerun"),
                           (args.summary, "--summary"), (args.checkpoint, "--checkpoint")):
            if path:
                check_out_file(path, what)
        if args.rerun and importlib.util.find_spec("rerun") is None:
            raise UsageError("--rerun needs rerun-sdk: pip install 'rhonn-tv[harness]'")
        check_bus(args.bus, allow_auto=False)
        cpu = _own_cpu(args.cpu, args.keep_cpu_awake)
    except (UsageError, FaultSpecError) as exc:
        parser.error(str(exc))
    # the imports (numpy, scipy, the compiled core; a first start also writes their bytecode
    # caches) are the slow part of a start: the line says how long they took
    log.info("starting controller %s (%s) on %s, %s; %.1f s since the process started",
             args.controller, _backend_line(controller), args.bus, args.mode, process_age_s())

    secoc = None
    if args.secoc:
        try:
            secoc = ControllerSecOc(Codec(), load_keys(args.secoc_keys))
        except SecOcKeyError as exc:
            parser.error(str(exc))
    params = load_vehicle_params()
    ckpt = None
    if args.checkpoint:  # restore before the first cycle; a bad file means a cold start
        ckpt = CheckpointManager(args.checkpoint, controller,
                                 config_hash(args.controller, args.config),
                                 every_steps=args.checkpoint_every,
                                 report=lambda m: print(m, file=sys.stderr, flush=True))
        ckpt.restore()
    # --fault core-exception: the node steps a core that raises inside the injected window
    # (controller/runtime/core_fault.py); checkpoints and the summary keep the real core
    faulty = FaultyCore(controller, core_faults(faults)) if core_faults(faults) else None
    node = ControllerNode(faulty or controller, params, comm_period_s=args.period_ms / 1000.0,
                          clock_ns=time.perf_counter_ns, secoc=secoc)
    if faulty is not None:
        faulty.bind(lambda: node.record.sim_time_s)  # SIM_TIME of the SYNC being answered
    if ckpt is not None:  # a latched core fault may have left the state half-updated
        ckpt.blocked_by = lambda: "core fault latched" if node.core_fault_latched else None
    timing = TimingLog(args.timing)
    sink = None
    if args.rerun:
        from controller.runtime.rerun_sink import RerunSink  # optional: imports rerun only if asked
        sink = RerunSink(args.rerun, args.controller)

    stop = StopFlag()
    if args.rt:
        make_realtime("rhonn-controller")
    if cpu is not None:  # after make_realtime: --cpu wins over $RHONN_RT_CPUS
        try:
            pin_all_threads({cpu})
        except OSError as exc:  # e.g. a CPU outside this container's cpuset
            parser.error(f"--cpu {cpu}: {exc.strerror}")
    freeze_heap()  # set-up garbage collected once; later gen-2 passes skip it (< 1 ms)
    # (before the bus opens: frames cannot pile up during the collection)
    bus = open_bus_for_process(args.bus, "rhonn-controller", args.reconnect_s)
    if bus is None:
        return 3
    awake = KeepAwake(cpu) if cpu is not None and args.keep_cpu_awake else None
    gc_watch = GcWatch()
    stall = StallWatch()
    print(f"ready {args.controller} on {args.bus} ({args.mode}, {_backend_line(controller)})",
          flush=True)
    log.info("controller ready in %.1f s", process_age_s())
    code = 0
    try:
        if args.mode == "lockstep":
            _run_lockstep(bus, node, timing, sink, stop, injector, ckpt, stall)
        else:
            _run_freerun(bus, node, timing, sink, stop, args.period_ms / 1000.0,
                         injector, ckpt, stall)
        if ckpt is not None:
            ckpt.save()  # clean stop (not after an unexpected exception)
    except BusDisconnected as exc:
        print(f"rhonn-controller: error: bus lost: {exc}", file=sys.stderr)
        code = 3
        if ckpt is not None:
            ckpt.save()
    finally:
        timing.close()
        if sink is not None:
            sink.close()
        bus.shutdown()
        if awake is not None:
            awake.stop()
    summary = {
        "controller": args.controller, "mode_changes": node.mode_changes,
        "backend": getattr(controller, "backend", "numpy"),
        "core_exceptions": node.controller_exceptions, "plant_restarts": node.plant_restarts,
        "frozen_signal_detections": node.frozen.detections,
        "rejections": node.monitor.rejection_counts(),
        # frames dropped by a bounded rx queue, by reason (docs/safety/queues.md)
        "rx_drops": node.rx_drop_counts(), "rx_overload_cycles": node.rx_overload_cycles,
        "saturations": dict(node.tx.saturations),
        "injected": {**(injector.counts if injector else {}),
                     **({"core-exception": faulty.raised} if faulty is not None else {})},
        "bus_reconnects": getattr(bus, "reconnects", 0),
        "cycles_answered": timing.rows,
        "rss_samples_kb": timing.rss_samples_kb,
        "gc": gc_watch.summary(),
        "stalls": stall.summary(),
        "bus_stats": bus.stats() if hasattr(bus, "stats") else None,
        "envelope": asdict(node.envelope.counters),
        "checkpoint": ckpt.summary() if ckpt is not None else None,
        "secoc": secoc.summary() if secoc is not None else {"enabled": False},
        "cpu": {"affinity": sorted(allowed_cpus()),
                "keep_awake_pid": awake.pid if awake is not None else None},
    }
    if args.summary:
        Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")
    print(f"stopped: {json.dumps(summary)}", flush=True)
    return code


def _own_cpu(text: str | None, keep_awake: bool) -> int | None:
    """The CPU of ``--cpu`` (None: not pinned), or a one-line UsageError."""
    if text is None:
        if keep_awake:
            raise UsageError("--keep-cpu-awake needs --cpu")
        return None
    try:  # the caller (e.g. the harness) may have kept this process off that CPU so far
        return choose_cpu(text, allowed=allowed_cpus() if text == "auto"
                          else set(range(os.cpu_count() or 1)), leave_one=False)
    except CpuChoiceError as exc:
        raise UsageError(f"--cpu: {exc}") from None


def _backend_line(controller: Controller) -> str:
    """Which implementation steps: "C core float64" or "numpy reference float32"."""
    dtype = np.dtype(getattr(controller, "dtype", np.float64)).name
    if getattr(controller, "backend", "numpy") == "native":
        return f"C core {dtype}"
    return f"numpy reference {dtype}"


def _make_controller(name: str, config: str | None) -> Controller:
    """The controller, or a one-line UsageError for a missing, malformed or wrong config."""
    try:
        return make_controller(name, config)
    except CONFIG_LOAD_ERRORS as exc:
        raise UsageError(config_error_line(config, exc)) from None


def _send(bus, frames, node: ControllerNode, injector: FaultInjector | None) -> None:
    if injector is not None:
        frames = injector.apply(frames, node.record.sim_time_s)
    send_all(bus, frames)


def _run_lockstep(bus, node: ControllerNode, timing: TimingLog, sink, stopped,
                  injector: FaultInjector | None = None,
                  ckpt: CheckpointManager | None = None,
                  stall: StallWatch | None = None) -> None:
    """Answer every SYNC; turnaround = SYNC received → last frame sent. A cycle whose
    turnaround plus logging takes longer than the stall threshold goes to ``stall``."""
    clock = time.perf_counter_ns
    last_sync_ns = 0
    period_ns = int(node.comm_period_s * 1e9)
    stall = stall or StallWatch()
    # the frames that can release an answer: SYNC, or its authenticator with SecOC
    release = {node.codec.messages["SYNC_AUTH" if node.secoc else "SYNC"].frame_id}
    while not stopped():
        msg = bus.recv(timeout=0.1)
        if msg is None:
            continue
        rx_ns = clock()
        if msg.arbitration_id in release:
            stall.begin(rx_ns)
        frames = node.on_frame_lockstep(msg)
        if frames is None:
            continue
        stall.mark("node")  # validation, controller step, envelope, encoding, SecOC
        _send(bus, frames, node, injector)
        stall.mark("send")
        turnaround = clock() - rx_ns
        timing.write(node, turnaround, rx_ns - last_sync_ns if last_sync_ns else 0,
                     turnaround > period_ns)
        stall.mark("log")
        if sink is not None:
            sink.log(node)
        if ckpt is not None:  # after the frames are sent: outside the timed step
            ckpt.after_cycle(node.record.mpc_update)
        stall.mark("after")
        stall.end(node.record.cycle, step_us=round(node.record.step_ns / 1e3, 1),
                  since_last_sync_ms=round((rx_ns - last_sync_ns) / 1e6, 3)
                  if last_sync_ns else None)
        last_sync_ns = rx_ns


def _run_freerun(bus, node: ControllerNode, timing: TimingLog, sink, stopped,
                 period_s: float, injector: FaultInjector | None = None,
                 ckpt: CheckpointManager | None = None,
                 stall: StallWatch | None = None) -> None:
    """Own fixed-step schedule on the monotonic clock; frames validated as they arrive
    (a tick later than the stall threshold, or one that takes longer, goes to ``stall``)."""
    clock = time.perf_counter_ns
    stall = stall or StallWatch()
    period_ns = int(period_s * 1e9)
    next_tick = clock() + period_ns
    last_tick = 0
    while not stopped():
        remaining = (next_tick - clock()) / 1e9
        msg = bus.recv(timeout=max(0.0, remaining)) if remaining > 0 else None
        if msg is not None:
            node.on_frame(msg, time.monotonic())
            continue
        now = clock()
        if now < next_tick:
            continue
        late = now - next_tick
        stall.begin(next_tick)
        stall.mark("wakeup")  # how late the tick began
        _send(bus, node.tick(time.monotonic()), node, injector)
        done = clock()
        stall.mark("tick")
        timing.write(node, done - now, now - last_tick if last_tick else 0,
                     late > period_ns)
        last_tick = now
        next_tick += period_ns
        if next_tick < done:  # overran a whole period: skip, do not burst to catch up
            next_tick = done + period_ns - (done - next_tick) % period_ns
        if sink is not None:
            sink.log(node)
        if ckpt is not None:  # after the frames are sent: outside the timed step
            ckpt.after_cycle(node.record.mpc_update)
        stall.mark("after")
        stall.end(node.record.cycle, step_us=round(node.record.step_ns / 1e3, 1))


if __name__ == "__main__":
    raise SystemExit(main())
