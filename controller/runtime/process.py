"""`rhonn-controller`: the stability controller as a standalone process on a CAN bus.

  rhonn-controller --bus SPEC --controller NAME [--config FILE] [--mode lockstep|freerun]
                   [--timing FILE] [--rerun FILE] [--checkpoint FILE [--checkpoint-every N]]
                   [--no-secoc] [--secoc-keys env|ci-test-key|KEYFILE]
                   [--rt] [--cpu CPU|auto [--keep-cpu-awake]] [--bench]

Lockstep answers every SYNC frame with a torque frame echoing its cycle; free-running runs on
its own 10 ms schedule on the monotonic clock. SIGINT/SIGTERM stop it cleanly (logs flushed);
a malformed frame never stops it. Exit codes: 0 clean stop, 2 bad arguments, 3 bus lost.

Diagnostics: a UDS (ISO 14229) server on DIAG_REQ_CTRL / DIAG_RESP_CTRL (docs/diagnostics.md):
ECUReset soft (everything per-run rebuilt in place as at a start) or hard (the process
re-executes itself with the coding written by WriteDataByIdentifier 0xFD10); the per-run
files (--timing, --summary) are written whole at each reset and opened again by the next run.
"""

from __future__ import annotations

from can_db.process.launch import refuse_unused

if __name__ == "__main__":  # before the imports below: packages the controller never uses
    refuse_unused("rhonn-controller")

import argparse
import importlib.util
import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import can
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
from can_db.secoc_keys import (
    SecOcKeyError,
    SecOcKeys,
    load_keys,
    resolve_key_source,
    secoc_state_text,
)
from can_db.transport.bus import BusDisconnected, open_bus_for_process, send_all
from can_db.transport.check import check_bus
from controller.core.config_schema import CONFIG_LOAD_ERRORS, config_error_line
from controller.core.interfaces import Controller
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.registry import load_controller_config
from controller.registry import CONTROLLER_NAMES, make_controller
from controller.runtime.checkpoint import CheckpointManager, StateLimits, config_hash
from controller.runtime.core_fault import FaultyCore, core_faults
from controller.runtime.isotp import IsoTpEndpoint
from controller.runtime.node import ControllerNode
from controller.runtime.rerun_sink import RerunSink
from controller.runtime.uds import (
    MOVING_KMH,
    Action,
    UdsReply,
    UdsSecretError,
    UdsServer,
    load_uds_secret,
)

_log = logging.getLogger("rhonn-controller")

# model_err_rms: the learned model's filtered RMS one-step yaw-rate error after the cycle,
# rad/s (its confidence gate's signal; NaN without a learned model), read by the benchmark
TIMING_COLUMNS = ("cycle", "sim_time_s", "step_us", "turnaround_us", "period_us",
                  "mpc_update", "qp_iterations", "qp_status", "mode", "deadline_miss",
                  "model_err_rms")


TIMING_FORMATS = ("%d", "%.3f", "%.1f", "%.1f", "%.1f", "%d", "%d", "%d", "%d", "%d", "%.17g")


class TimingLog:
    """Per-cycle timing rows: one packed row per cycle during the run (can_db/process/rowlog.py:
    one write(2), a killed process leaves every finished row), the CSV ``path`` on close
    (the formatting is off the cycle; ≈ 6 µs a lockstep cycle measured in situ).

    The file is opened at the first row (or at close, for a run without a cycle), not at
    construction: between a reset's response and the next run's first frame the bench moves
    the previous run's CSV away without racing a new one.

    Also samples the process's resident memory every ``RSS_EVERY`` cycles (after the frames
    of that cycle are sent) so long runs can show memory growth.
    """

    RSS_EVERY = 1000

    def __init__(self, path: str | None) -> None:
        self._path = path
        self._log: RowLog | None = None
        self.rows = 0
        self.write_error: str | None = None  # the first failed write (disk full), if any
        self.rss_samples_kb: list[int] = []
        self._proc = psutil.Process()

    def _open(self) -> RowLog:
        assert self._path is not None
        self._log = RowLog(self._path, TIMING_COLUMNS, TIMING_FORMATS)
        return self._log

    def write(self, node: ControllerNode, turnaround_ns: int, period_ns: int,
              deadline_miss: bool) -> None:
        if self.rows % self.RSS_EVERY == 0:
            self.rss_samples_kb.append(self._proc.memory_info().rss // 1024)
        self.rows += 1
        if self._path is None or self.write_error is not None:
            return
        rec, out = node.record, node.record.outputs
        try:
            log = self._log or self._open()
            log.write((rec.cycle, rec.sim_time_s, rec.step_ns / 1000,
                       turnaround_ns / 1000, period_ns / 1000, rec.mpc_update,
                       out.qp_iterations, out.qp_status, int(rec.mode), deadline_miss,
                       np.sqrt(model.err_ms) if hasattr(model := getattr(
                           node.controller, "model", None), "err_ms") else np.nan))
        except OSError as exc:  # disk full: the log stops, control goes on
            self.write_error = f"{type(exc).__name__}: {exc}"
            _log.error("the timing log %s cannot be written (%s): no more rows this run; "
                       "control goes on", self._path, self.write_error)

    def close(self) -> None:
        """Write the CSV (idempotent); a run without a cycle still leaves its header. A CSV
        that cannot be written leaves its row file (the harness names it in the metrics)."""
        if self._path is None:
            return
        try:
            log = self._log or self._open()
            log.close()
        except OSError as exc:
            self.write_error = self.write_error or f"{type(exc).__name__}: {exc}"
            _log.error("the timing log %s cannot be written (%s)", self._path, exc)
        self._path = None


@dataclass
class PerRun:
    """Every object whose state belongs to one run: built by :func:`build_run` at process
    start and again at a soft reset, so a reset starts exactly as a new process does."""

    controller: Controller
    faults: list
    injector: FaultInjector | None
    faulty: FaultyCore | None
    secoc: ControllerSecOc | None
    node: ControllerNode
    ckpt: CheckpointManager | None
    timing: TimingLog


def build_run(args: argparse.Namespace, params: VehicleParams, codec: Codec,
              keys: SecOcKeys | None = None, controller: Controller | None = None) -> PerRun:
    """The per-run objects from the parsed arguments ``args`` (controller core, fault
    injector and its RNG, SecOC receiver/transmitter with ``keys``, node with its monitors,
    checkpoint restored, timing log not yet opened). ``controller``: one made already from
    the same arguments (the start checks make it). Raises UsageError / FaultSpecError."""
    faults = parse_faults(args.fault)
    injector = FaultInjector(codec, faults, seed=args.fault_seed,
                             lockstep=args.mode == "lockstep") if args.fault else None
    if controller is None:
        controller = _make_controller(args.controller, args.config)
    secoc = ControllerSecOc(codec, keys) if args.secoc else None
    ckpt = None
    if args.checkpoint:  # restore before the first cycle; a bad file means a cold start
        ckpt = CheckpointManager(args.checkpoint, controller,
                                 config_hash(args.controller, args.config),
                                 every_steps=args.checkpoint_every,
                                 report=lambda m: print(m, file=sys.stderr, flush=True),
                                 limits=StateLimits.of(load_controller_config(args.config)))
        ckpt.restore()
    # --fault core-exception: the node steps a core that raises inside the injected window
    # (controller/runtime/core_fault.py); checkpoints and the summary keep the real core
    faulty = FaultyCore(controller, core_faults(faults)) if core_faults(faults) else None
    node = ControllerNode(faulty or controller, params, codec=codec,
                          comm_period_s=args.period_ms / 1000.0,
                          clock_ns=time.perf_counter_ns, secoc=secoc)
    if faulty is not None:
        faulty.bind(lambda: node.record.sim_time_s)  # SIM_TIME of the SYNC being answered
    if ckpt is not None:  # a latched core fault may have left the state half-updated
        ckpt.blocked_by = lambda: "core fault latched" if node.core_fault_latched else None
    return PerRun(controller, faults, injector, faulty, secoc, node, ckpt,
                  TimingLog(args.timing))


def _parser() -> OneLineParser:
    parser = OneLineParser(prog="rhonn-controller", description=__doc__)
    parser.add_argument("--bus", required=True,
                        help="local:NAME | socketcan:IFACE | remote:ws://127.0.0.1:PORT/")
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
                             "repeatable (see can_db/faults.py); needs --bench")
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
    parser.add_argument("--secoc", action=argparse.BooleanOptionalAction, default=True,
                        help="verify SYNC and authenticate torque/status frames (SecOC; on "
                             "by default, --no-secoc turns it off)")
    parser.add_argument("--bench", action="store_true",
                        help="the harness runs this controller on a bench: UDS resets and "
                             "coding writes are accepted while the vehicle moves "
                             "(docs/diagnostics.md)")
    parser.add_argument("--uds-secret", default="env", metavar="env|public|FILE",
                        help="diagnostic secret of SecurityAccess (hex): env = "
                             "$RHONN_UDS_SECRET, else the public test secret "
                             "(docs/diagnostics.md)")
    parser.add_argument("--secoc-keys", default=None,
                        help="SecOC keys: env | ci-test-key | KEYFILE (mode 600); default: env "
                             "when the RHONN_SECOC_KEY_* variables are set (both; one alone "
                             "is an error), else the public test key (simulation only)")
    add_logging_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser()
    args = parser.parse_args(argv)
    log = setup_logging("rhonn-controller", *logging_args(args))
    codec = Codec()
    if args.fault and not args.bench:   # a production controller injects no faults
        parser.error("--fault: fault injection only on a bench controller (add --bench)")
    try:  # every argument is checked before the bus is opened or a file written
        # the fault kinds, and the messages and signals they name
        FaultInjector(codec, parse_faults(args.fault))
        if not args.secoc and args.secoc_keys is not None:
            raise UsageError("--secoc-keys is given with --no-secoc (no keys are used)")
        controller = _make_controller(args.controller, args.config)
        for path, what in ((args.timing, "--timing"), (args.rerun, "--rerun"),
                           (args.summary, "--summary"), (args.checkpoint, "--checkpoint")):
            if path is not None:  # "--timing=" is refused, not taken as "no timing log"
                check_out_file(path, what)
        if args.rerun and importlib.util.find_spec("rerun") is None:
            raise UsageError("--rerun needs rerun-sdk: pip install 'rhonn-tv[harness]'")
        check_bus(args.bus, allow_auto=False)
        cpu = _own_cpu(args.cpu, args.keep_cpu_awake)
        keys = load_keys(resolve_key_source(args.secoc_keys)) if args.secoc else None
        uds_secret, uds_secret_source = load_uds_secret(args.uds_secret)
    except (UsageError, FaultSpecError, SecOcKeyError, UdsSecretError) as exc:
        parser.error(str(exc))
    # the imports (numpy, scipy, the compiled core; a first start also writes their bytecode
    # caches) are the slow part of a start: the line says how long they took
    log.info("starting controller %s (%s) on %s, %s; %.1f s since the process started",
             args.controller, _backend_line(controller), args.bus, args.mode, process_age_s())
    params = load_vehicle_params()
    run = build_run(args, params, codec, keys, controller)  # its arguments are checked above
    boot_count = _boot_count()
    uds = UdsServer(coding_of(args), boot_count=boot_count,
                    check_coding=lambda coding: _coding_problem(coding, codec),
                    bench=args.bench, secret=uds_secret)
    sink = None
    if args.rerun:
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
    diag = DiagLink(codec, uds, params.wheel_radius_m)
    print(f"ready {args.controller} on {args.bus} ({args.mode}, {_backend_line(controller)}, "
          f"{secoc_state_text(keys)}; diagnostics: {uds_secret_source})", flush=True)
    log.info("controller ready in %.1f s", process_age_s())
    code = 0
    action = Action.NONE
    try:
        while True:
            if args.mode == "lockstep":
                action = _run_lockstep(bus, run.node, run.timing, sink, stop, run.injector,
                                       run.ckpt, stall, diag)
            else:
                action = _run_freerun(bus, run.node, run.timing, sink, stop,
                                      args.period_ms / 1000.0, run.injector, run.ckpt,
                                      stall, diag)
            if action is Action.NONE:
                break
            # a reset: the finished run's files whole, then (soft) everything per-run
            # rebuilt as at a start before the response, or (hard) the response, then exec
            _finish_run(args, run, bus, gc_watch, stall, awake, uds)
            if action is Action.HARD_RESET:
                break
            if uds.pending is not None and \
                    uds.pending.get("controller") == uds.coding.get("controller"):
                # a written coding that keeps the controller (its configuration, faults)
                # becomes active at this reset; another controller needs the hard reset
                argv = apply_coding(argv, uds.pending)
                args = parser.parse_args(argv)
                uds.coding, uds.pending = uds.pending, None
            run = build_run(args, params, codec, keys)
            uds.soft_reset_done()
            diag.respond_pending(bus)
            log.info("soft reset %d done", uds.soft_resets)
        if action is Action.NONE and run.ckpt is not None:
            run.ckpt.save()  # clean stop (not after an unexpected exception)
    except BusDisconnected as exc:
        print(f"rhonn-controller: error: bus lost: {exc}", file=sys.stderr)
        code = 3
        if run.ckpt is not None:
            run.ckpt.save()
    finally:
        if action is Action.HARD_RESET:
            diag.respond_pending(bus)
        run.timing.close()
        if sink is not None:
            sink.close()
        bus.shutdown()
        if awake is not None:
            awake.stop()
    if action is Action.HARD_RESET and code == 0:
        new_argv = apply_coding(argv, uds.next_coding())
        log.info("hard reset: exec with %s", " ".join(new_argv))
        sys.stdout.flush()
        sys.stderr.flush()
        # the environment only for the new image: an in-process caller's stays untouched
        os.execve(sys.executable, [sys.executable, "-m", "controller.runtime.process",
                                   *new_argv], {**os.environ, BOOT_COUNT_ENV: str(boot_count)})
    summary = _summary(args, run, bus, gc_watch, stall, awake, uds)
    if args.summary:
        _write_summary(args.summary, summary)
    print(stopped_line(summary, args.summary), flush=True)
    return code


def stopped_line(summary: dict, summary_path: str | None) -> str:
    """The run's end in one line a person reads (the whole summary is the --summary JSON)."""
    sec = summary.get("secoc") or {}
    if sec.get("enabled"):
        rej = sec.get("rejected") or {}
        secoc = ("SecOC on, rejected " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items()))
                 if rej else "SecOC on, nothing rejected")
    elif sec.get("authenticators_ignored"):
        secoc = (f"SecOC off, but {sec['authenticators_ignored']} authenticators of a plant "
                 "with SecOC seen (it rejects these answers)")
    else:
        secoc = "SecOC off"
    rejected = sum(int(v) for v in (summary.get("rejections") or {}).values()
                   if isinstance(v, (int, float)))
    where = f"; whole summary in {summary_path}" if summary_path else \
        "; the whole summary: --summary FILE"
    return (f"stopped: {summary['controller']} ({summary['backend']} core), "
            f"{summary['cycles_answered']} cycles answered, {rejected} frames rejected by "
            f"the monitor, {summary['core_exceptions']} core exceptions, {secoc}{where}")


def _finish_run(args: argparse.Namespace, run: PerRun, bus, gc_watch: GcWatch, stall: StallWatch,
                awake: KeepAwake | None, uds: UdsServer) -> None:
    """A run ends at a reset: timing CSV and summary JSON written whole, checkpoint saved."""
    if run.ckpt is not None:
        run.ckpt.save()
    run.timing.close()
    if args.summary:
        _write_summary(args.summary, _summary(args, run, bus, gc_watch, stall, awake, uds))


def _write_summary(path: str, summary: dict) -> None:
    """The summary JSON; a write error (disk full) is logged, never ends the controller."""
    try:
        Path(path).write_text(json.dumps(summary, indent=2) + "\n")
    except OSError as exc:
        _log.error("the summary %s cannot be written (%s)", path, exc)


def _summary(args: argparse.Namespace, run: PerRun, bus, gc_watch: GcWatch, stall: StallWatch,
             awake: KeepAwake | None, uds: UdsServer) -> dict:
    """The counters of a run (and of the process: bus, gc, stalls, CPU) as JSON data."""
    node, injector, faulty, secoc = run.node, run.injector, run.faulty, run.secoc
    return {
        "controller": args.controller, "mode_changes": node.mode_changes,
        "backend": getattr(run.controller, "backend", "numpy"),
        "core_exceptions": node.controller_exceptions, "plant_restarts": node.plant_restarts,
        "frozen_signal_detections": node.frozen.detections,
        "rejections": node.monitor.rejection_counts(),
        # frames dropped by a bounded rx queue, by reason (docs/safety/queues.md)
        "rx_drops": node.rx_drop_counts(), "rx_overload_cycles": node.rx_overload_cycles,
        "saturations": dict(node.tx.saturations),
        "injected": {**(injector.counts if injector else {}),
                     **({"core-exception": faulty.raised} if faulty is not None else {})},
        "bus_reconnects": getattr(bus, "reconnects", 0),
        "cycles_answered": run.timing.rows,
        "timing_log_error": run.timing.write_error,
        "rss_samples_kb": run.timing.rss_samples_kb,
        "gc": gc_watch.summary(),
        "stalls": stall.summary(),
        "bus_stats": bus.stats() if hasattr(bus, "stats") else None,
        "envelope": asdict(node.envelope.counters),
        "checkpoint": run.ckpt.summary() if run.ckpt is not None else None,
        "secoc": secoc.summary() if secoc is not None else {
            "enabled": False, "authenticators_ignored": node.authenticators_ignored},
        "uds": {**uds.counts, "refused": dict(uds.refused)},
        "cpu": {"affinity": sorted(allowed_cpus()),
                "keep_awake_pid": awake.pid if awake is not None else None},
    }


# ---------------------------------------------------------------- diagnostics (UDS)
BOOT_COUNT_ENV = "RHONN_BOOT_COUNT"  # carried across a hard reset's exec


def _boot_count() -> int:
    """This start's boot counter: the environment's + 1 (a hard reset's exec passes its
    own count there; a process started otherwise counts 1)."""
    try:
        return max(0, int(os.environ.get(BOOT_COUNT_ENV, "0"))) + 1
    except ValueError:
        return 1


def coding_of(args: argparse.Namespace) -> dict:
    """The controller coding (DID 0xFD10) of the parsed arguments."""
    return {"controller": args.controller, "config": args.config,
            "faults": list(args.fault), "fault_seed": args.fault_seed}


def _coding_problem(coding: dict, codec: Codec) -> str | None:
    """Why ``coding`` cannot run (unknown controller, config that does not load, bad fault
    spec, or one naming a message or signal ``codec`` does not know), or None."""
    if coding.get("controller") not in CONTROLLER_NAMES:
        return f"unknown controller {coding.get('controller')!r}"
    try:
        load_controller_config(coding.get("config"))
        FaultInjector(codec, parse_faults(list(coding.get("faults", []))))
    except (*CONFIG_LOAD_ERRORS, FaultSpecError, OSError) as exc:   # OSError: e.g. /proc
        return str(exc)
    return None


_CODED_OPTIONS = {"--controller": "controller", "--config": "config", "--fault": "faults",
                  "--fault-seed": "fault_seed"}


def apply_coding(argv: list[str], coding: dict) -> list[str]:
    """``argv`` with the coded options (--controller, --config, --fault, --fault-seed)
    replaced by the values of ``coding``; every other argument kept in order."""
    out: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
            continue
        name = arg.split("=", 1)[0]
        if name in _CODED_OPTIONS:
            skip = "=" not in arg
            continue
        out.append(arg)
    out += ["--controller", str(coding["controller"])]
    if coding.get("config") is not None:
        out += ["--config", str(coding["config"])]
    for spec in coding.get("faults", []):
        out.append(f"--fault={spec}")  # a spec may start with "-"
    out += ["--fault-seed", str(int(coding.get("fault_seed", 2)))]
    return out


WHEEL_SIGNALS = ("WS_FL", "WS_FR", "WS_RL", "WS_RR")


class DiagLink:
    """The controller's diagnostic channel: DIAG_REQ_CTRL frames into an ISO-TP endpoint
    (controller/runtime/isotp.py), complete requests to the UDS server
    (controller/runtime/uds.py), responses back as DIAG_RESP_CTRL frames. Never touches the
    node's cycle: a diagnostic frame is handled between cycles and is not a control frame.

    ``wheel_radius_m``: rolling radius, m, for the wheel speeds' vehicle speed."""

    def __init__(self, codec: Codec, server: UdsServer, wheel_radius_m: float,
                 clock=time.monotonic) -> None:
        self.req_id = codec.diagnostic["DIAG_REQ_CTRL"]
        self.resp_id = codec.diagnostic["DIAG_RESP_CTRL"]
        self.server = server
        self.isotp = IsoTpEndpoint()
        self._radius_m = wheel_radius_m
        self._clock = clock
        self._pending: UdsReply | None = None

    def timeout(self, wait_s: float) -> float:
        """How long the caller may wait on its bus, s: ``wait_s`` or less when a frame
        (STmin-spaced) or a timeout is due earlier."""
        due = self.isotp.next_release_s
        if due is None:
            return wait_s
        return max(0.0, min(wait_s, due - self._clock()))

    def poll(self, bus) -> None:
        """Timeouts applied and due frames sent (call when the bus is idle)."""
        self.isotp.poll(self._clock())
        self._flush(bus)

    def moving(self, node: ControllerNode) -> bool:
        """The vehicle moves: the last accepted VEHICLE_EST says > 0.5 km/h (VX_EST m/s), or
        a wheel of the last accepted WHEEL_SPEEDS (rad/s) turns faster than that. Fails
        closed: until both frames have been accepted the vehicle counts as moving."""
        est = node.monitor.latest("VEHICLE_EST")
        whl = node.monitor.latest("WHEEL_SPEEDS")
        if est is None or whl is None:
            return True
        if abs(est.values["VX_EST"]) * 3.6 > MOVING_KMH:
            return True
        return max(abs(whl.values[w]) for w in WHEEL_SIGNALS) * self._radius_m * 3.6 \
            > MOVING_KMH

    def on_frame(self, bus, msg: can.Message, node: ControllerNode) -> Action:
        """Take one DIAG_REQ_CTRL frame; returns the reset to perform (its response is held
        by :meth:`respond_pending` until the reset's work is done)."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
            return Action.NONE
        request = self.isotp.feed(msg.data, self._clock())
        if request is None:
            self._flush(bus)
            return Action.NONE
        reply = self.server.handle(request, self.moving(node), self._clock())
        self._log_refusal(request, reply)
        if reply.action is Action.NONE:
            if reply.response is not None:
                self.isotp.send(reply.response, self._clock())
            self._flush(bus)
            return Action.NONE
        self._pending = reply
        return reply.action

    def _log_refusal(self, request: bytes, reply: UdsReply) -> None:
        """A refused request is logged: the first of each service and NRC as a warning (a
        storm of them cannot flood the log), every one at debug level."""
        r = reply.response
        if r is None or len(r) < 3 or r[0] != 0x7F:
            return
        key = f"{r[1]:02X}/{r[2]:02X}"
        level = logging.WARNING if self.server.refused.get(key) == 1 else logging.DEBUG
        _log.log(level, "UDS request %s refused: NRC 0x%02X (%d so far)",
                 request[:3].hex(" "), r[2], self.server.refused[key])

    def respond_pending(self, bus) -> None:
        """Send the held response of a reset (none when suppressed)."""
        reply, self._pending = self._pending, None
        if reply is not None and reply.response is not None:
            self.isotp.send(reply.response, self._clock())
            self._flush(bus)

    def _flush(self, bus) -> None:
        frames = self.isotp.due(self._clock())
        if frames:
            send_all(bus, [can.Message(arbitration_id=self.resp_id, data=f,
                                       is_extended_id=False) for f in frames])


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
                  stall: StallWatch | None = None,
                  diag: DiagLink | None = None) -> Action:
    """Answer every SYNC; turnaround = SYNC received → last frame sent. A cycle whose
    turnaround plus logging takes longer than the stall threshold goes to ``stall``.
    Diagnostic requests are answered between cycles; returns the reset one asks for
    (Action.NONE: stopped)."""
    clock = time.perf_counter_ns
    last_sync_ns = 0
    period_ns = int(node.comm_period_s * 1e9)
    stall = stall or StallWatch()
    # the frames that can release an answer: SYNC, or its authenticator with SecOC
    release = {node.codec.messages["SYNC_AUTH" if node.secoc else "SYNC"].frame_id}
    diag_id = diag.req_id if diag is not None else -1
    while not stopped():
        msg = bus.recv(timeout=diag.timeout(0.1) if diag is not None else 0.1)
        if msg is None:
            if diag is not None:
                diag.poll(bus)
            continue
        if msg.arbitration_id == diag_id:  # not a control frame: never reaches the node
            action = diag.on_frame(bus, msg, node)
            if action is not Action.NONE:
                return action
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
    return Action.NONE


def _run_freerun(bus, node: ControllerNode, timing: TimingLog, sink, stopped,
                 period_s: float, injector: FaultInjector | None = None,
                 ckpt: CheckpointManager | None = None,
                 stall: StallWatch | None = None,
                 diag: DiagLink | None = None) -> Action:
    """Own fixed-step schedule on the monotonic clock; frames validated as they arrive
    (a tick later than the stall threshold, or one that takes longer, goes to ``stall``).
    Diagnostic requests are answered between ticks; returns the reset one asks for
    (Action.NONE: stopped)."""
    clock = time.perf_counter_ns
    stall = stall or StallWatch()
    period_ns = int(period_s * 1e9)
    next_tick = clock() + period_ns
    last_tick = 0
    diag_id = diag.req_id if diag is not None else -1
    while not stopped():
        remaining = (next_tick - clock()) / 1e9
        if diag is not None:
            remaining = diag.timeout(remaining)
        msg = bus.recv(timeout=max(0.0, remaining)) if remaining > 0 else None
        if msg is not None:
            if msg.arbitration_id == diag_id:  # not a control frame: never reaches the node
                action = diag.on_frame(bus, msg, node)
                if action is not Action.NONE:
                    return action
                continue
            node.on_frame(msg, time.monotonic())
            continue
        if diag is not None:
            diag.poll(bus)
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
    return Action.NONE


if __name__ == "__main__":
    raise SystemExit(main())
