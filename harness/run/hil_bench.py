"""The bench: a bus, a plant process and a controller process that carry out runs.

A **warm** bench keeps them alive across runs, the way a HIL bench keeps its plant model and
ECU powered between test cases: after a run the controller is reset over the bus with UDS
ECUReset (ISO 14229 service 0x11 on DIAG_REQ_CTRL, harness/run/uds_tester.py) — a soft reset
when the next run uses the same controller coding or only another configuration of the same
controller (written first with WriteDataByIdentifier), a coding write and a hard reset for
another controller — and the plant (``rhonn-plant --serve``) loads the next run's scenario over its
control channel (stdin). A **fresh** bench starts the processes for one run and stops them
after it; ``rhonn-harness run`` uses one, so both paths are the same code.

Per run: its own directory, bus recorder, truth trace, controller timing and summary, and the
run's lines of the plant and controller logs. Process-level faults act on the bench's
processes during a run; a process a fault killed or restarted is replaced before the next run.
A process that dies unexpectedly (no fault asked for it) is replaced and the run is retried
once; ``metrics["bench"]`` counts it.

Order of a run: (re)start or reset what is needed → recorder → rogue nodes timed at 0 s → the
plant's run command → wait for the plant's ``done`` line (faults, signals, progress, time-out)
→ reset (warm; the recorder stops at its response) or stop (fresh; the recorder drains
until the bus is idle) the controller → move the controller's files into the run
directory → stop the recorder.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from can_db.codec import Codec
from can_db.faults import FaultSpec, FaultSpecError, parse_fault, parse_faults
from can_db.process.cpu import allowed_cpus, choose_cpu, pin_all_threads
from can_db.process.rowlog import SUFFIX as ROWS_SUFFIX
from can_db.process.rowlog import finish_all, finish_rows
from can_db.secoc_keys import TEST_KEY_SOURCE, resolve_key_source
from can_db.transport.bus import resolve_bus
from can_db.transport.hub import LocalHub
from can_db.transport.server import BusServer, BusServerError
from harness.run import signals
from harness.run.bus_logger import BusRecorder
from harness.run.controller_config import config_file
from harness.run.procs import Child, ChildStartError
from harness.run.spec import RunSpec
from harness.run.uds_tester import UdsError, UdsTester
from plant_sim.scenario import scenario_label

log = logging.getLogger("harness.run")

# After SIGINT/SIGTERM: how long each child gets to exit after its SIGTERM before SIGKILL, and
# how long the recorder waits for the last frames, wall s (the harness stops within ~2 s).
INTERRUPT_GRACE_S = 1.0
INTERRUPT_DRAIN_S = 0.1
# How long a plant or controller process may take to report ready, wall s. A first start after
# an install compiles the plant's numba kernel; a process that exits is reported at once.
START_TIMEOUT_S = 300.0
# what a user waits for at a first start: Python writes the bytecode caches of numpy, scipy,
# python-can and the project, numba compiles the plant's vehicle step (cached after)
FIRST_START_NOTE = "a first start after install writes caches: up to about a minute"
RESET_TIMEOUT_S = 10.0  # wall s for a UDS reset's response (a hard reset: until ready again)
LOAD_TIMEOUT_S = 60.0  # wall s for the plant to load a run (its set-up, not the run)
DIAG_REQ_ID, DIAG_RESP_ID = (Codec().diagnostic[n]
                             for n in ("DIAG_REQ_CTRL", "DIAG_RESP_CTRL"))
DIAG_IDS = frozenset({DIAG_REQ_ID, DIAG_RESP_ID})
# the soft reset's positive response as an ISO-TP single frame (length 2, 51 03): the
# controller's last frame of a run; the session and security responses before it are not
SOFT_RESET_RESPONSE = bytes((0x02, 0x51, 0x03))
BARRIER_TIMEOUT_S = 2.0  # wall s for the reset response to reach the recorder
CONTROLLER_FILES = ("controller_timing", "controller_summary")
ROGUE_ATTACKS = {"rogue-inject": "inject", "rogue-replay": "replay", "rogue-flood": "flood",
                 "rogue-spoof": "spoof", "rogue-sensor-replay": "sensor-replay"}
# --target m4f: the process that runs the controller node as firmware on QEMU and bridges it
# to the bus (started by module name, as the plant is: the run layer imports no bench code)
PIL_NODE_MODULE = "harness.bench.mcu.pil_node"
TARGETS = ("host", "m4f")
# --target m4f, lockstep: the plant's wait for each cycle's answer when the run does not set
# one, ms. The firmware's cycle is about 1e6 instructions (OSQP in double), which QEMU with
# the counting plugin executes in a few ms, plus four SLCAN hops through Python threads; a
# loaded machine can stretch that 100-fold, and a wait that runs out costs a held command.
PIL_WAIT_MS = 5000.0
PROCESS_FAULTS_ON = {"kill-controller": "controller", "restart-controller": "controller",
                     "kill-plant": "plant", "restart-plant": "plant"}


class BusTap(Protocol):
    """What a live view needs from a run: every recorded frame, and a call now and then."""

    def tap(self, msg: Any) -> None: ...

    def poll(self) -> None: ...


class BenchError(RuntimeError):
    """A run the bench cannot carry out (its bus, CPU or timing layout differs)."""


@dataclass
class BenchCounters:
    """What a bench did over its life (``metrics["bench"]`` holds a run's share)."""

    runs: int = 0
    soft_resets: int = 0
    hard_resets: int = 0
    controller_starts: int = 0
    plant_starts: int = 0
    replaced: int = 0  # processes a fault or a failure left dead or dirty, started anew
    retries: int = 0  # runs carried out a second time after a process died unexpectedly
    reset_failures: int = 0  # UDS resets without a positive response (the process replaced)
    recodings: int = 0  # codings that kept the controller, applied by a soft reset


@dataclass
class RunOutcome:
    """What the processes did in one run (the analysis reads the files in the run dir)."""

    reason: str
    interrupted: bool
    plant_code: int | None
    controller_code: int | None
    controller_lost_at_s: float | None
    fault_events: list[dict[str, Any]]
    frames_recorded: int
    released_early: int
    log_time_base: str | None
    sim_time_s: float
    bus_spec: str
    own_cpu: int | None
    bench: dict[str, Any] = field(default_factory=dict)
    # frames the kernel dropped for the recorder's socket (SocketCAN), None elsewhere
    recorder_rx_dropped: int | None = None
    # run files that could not be written (disk full), by name: the error
    files_not_written: dict[str, str] = field(default_factory=dict)


def route_frame_faults(faults: list[FaultSpec], codec: Codec, lockstep: bool
                       ) -> tuple[list[str], list[str]]:
    """Split frame faults between the plant and the controller (each injects on its own
    frames): a fault naming a message or signal goes to that frame's sender, an untargeted
    one (e.g. ``loss:10%``) to both. Core faults (``core-exception``) go to the controller,
    which carries them out on its core."""
    signal_owner = {s.name: m for m in codec.messages.values() for s in m.signals}
    plant, ctrl = [], []
    for f in faults:
        if f.is_core_fault:
            ctrl.append(f.text)
            continue
        if not f.is_frame_fault:
            continue
        spec = codec.messages.get(f.target or "") or signal_owner.get(f.target or "")
        senders = set(spec.senders) if spec is not None else {"PLANT", "CTRL"}
        if lockstep and f.kind in {"delay", "jitter"}:
            # In lockstep the torque frame must echo the cycle it answers; a held-back answer
            # can only mean a missed cycle. Delays act on the plant's frames (stale data).
            senders.discard("CTRL")
            if not senders:
                raise FaultSpecError(f"{f.text}: delaying controller frames needs "
                                     "--mode realtime")
        if "PLANT" in senders:
            plant.append(f.text)
        if "CTRL" in senders:
            ctrl.append(f.text)
    return plant, ctrl


def run_faults(spec: RunSpec) -> list[FaultSpec]:
    """The run's faults, checked (FaultSpecError names a bad one)."""
    faults = parse_faults(list(spec.faults))
    if spec.kill_controller_at_s is not None:
        faults.append(parse_fault(f"kill-controller@{spec.kill_controller_at_s}s"))
    return faults


def plant_run_args(spec: RunSpec, out: Path, plant_faults: list[str]) -> list[str]:
    """The plant's per-run arguments (``rhonn-plant`` without ``--bus``): the same for a
    served run and a one-shot plant."""
    args = ["--scenario", spec.scenario, "--mode", spec.mode,
            "--trace", str(out / "truth.csv"), "--summary", str(out / "plant_summary.json"),
            "--seed", str(spec.seed)]
    if spec.mu is not None:
        args += ["--mu", str(spec.mu)]
    if spec.speed_kmh is not None:
        args += ["--speed", str(spec.speed_kmh)]
    if spec.duration_s is not None:
        args += ["--duration", str(spec.duration_s)]
    for key, value in spec.params:
        text = json.dumps(_plain(value)) if isinstance(value, list | tuple) else value
        args += ["--param", f"{key}={text}"]
    for key, value in spec.vehicle:
        args += ["--vehicle", f"{key}={value}"]
    if spec.secoc:
        # no --secoc-state: the plant advances the trip counter of its state directory
        # ($RHONN_STATE_DIR/plant), so every run — on this bench, a later bench, after a
        # restart-plant — has a trip above every earlier one and recordings of earlier runs
        # are stale in it (a counter kept in the run's folder started at 1 in every run)
        args += ["--secoc", "--secoc-keys", resolve_key_source(spec.secoc_keys)]
    else:  # the plant authenticates by default
        args.append("--no-secoc")
    if spec.lockstep_wait_ms is not None:
        args += ["--wait-ms", str(spec.lockstep_wait_ms)]
    elif spec.target == "m4f":
        args += ["--wait-ms", str(PIL_WAIT_MS)]
    if spec.command_hold_ms is not None:
        args += ["--command-hold-ms", str(spec.command_hold_ms)]
    for text in plant_faults:
        args += ["--fault", text]
    return args + list(spec.plant_extra_args)


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, list | tuple) else value


def controller_coding(spec: RunSpec, ctrl_faults: list[str], config_dir: Path
                      ) -> dict[str, Any]:
    """What the controller runs, as written with UDS WriteDataByIdentifier 0xFD10 (takes
    effect at the next reset: a soft one when it keeps the controller, else a hard one); a
    configuration with overrides is written into ``config_dir`` first."""
    config = config_file(spec.controller_config, dict(spec.controller_overrides), config_dir)
    return {"controller": spec.controller, "config": config,
            "faults": list(ctrl_faults), "fault_seed": 2}


def controller_setup(spec: RunSpec) -> tuple[Any, ...]:
    """The controller process's settings that a coding cannot change (a change starts a new
    process): its schedule, SecOC, CPU layout and extra arguments."""
    return (spec.controller_mode, spec.secoc,
            resolve_key_source(spec.secoc_keys) if spec.secoc else None,
            spec.rt, spec.controller_cpu, tuple(spec.controller_extra_args), spec.target)


def check_target(spec: RunSpec) -> None:
    """ValueError when the run asks for a target it cannot run on: an unknown one, or the
    firmware (m4f) with what it does not have (SecOC, the free-running schedule, faults
    injected by the controller)."""
    if spec.target not in TARGETS:
        raise ValueError(f"target must be one of {', '.join(TARGETS)}, not {spec.target!r}")
    if spec.target != "m4f":
        return
    if spec.controller == "passive":
        raise ValueError("--target m4f runs an MPC controller's node, not passive")
    if spec.secoc and resolve_key_source(spec.secoc_keys) != TEST_KEY_SOURCE:
        raise ValueError("--target m4f: SecOC with the public CI test key only (the keys are "
                         "compiled into the firmware image): --secoc-keys ci-test-key, or "
                         "--no-secoc")
    if spec.controller_mode != "lockstep":
        raise ValueError("--target m4f answers SYNC frames only: --controller-mode lockstep")
    _, ctrl_faults = route_frame_faults(run_faults(spec), Codec(),
                                        lockstep=spec.mode == "lockstep")
    if ctrl_faults:
        raise ValueError(f"--target m4f injects no faults in the controller: "
                         f"{', '.join(ctrl_faults)}")


class Bench:
    """Bus, plant and controller processes for runs; see the module docstring.

    ``work_dir``: the bench's own files (its process logs, the controller's file paths); a
    temporary directory when None. ``warm``: keep the processes across runs (False: they
    are started for each run, in the run's directory, and stopped after it).
    """

    def __init__(self, work_dir: Path | None = None, *, bus: str = "auto", rt: bool = False,
                 controller_cpu: str | None = None, warm: bool = True,
                 bus_start_timeout_s: float = 10.0) -> None:
        self.warm = warm
        self.bus_start_timeout_s = bus_start_timeout_s  # wall s, for a hub or server it starts
        self._tmp = None if work_dir is not None else tempfile.mkdtemp(prefix="rhonn-bench-")
        self.work_dir = Path(work_dir if work_dir is not None else self._tmp)
        self.bus_request, self.rt, self.controller_cpu_request = bus, rt, controller_cpu
        self.bus_spec: str | None = None
        self.server: LocalHub | BusServer | None = None
        self.controller: Child | None = None
        self.plant: Child | None = None
        self.coding: dict[str, Any] | None = None
        self.setup: tuple[Any, ...] | None = None
        self.counters = BenchCounters()
        self.own_cpu: int | None = None
        self._harness_cpus = allowed_cpus()
        self._dirty: set[str] = set()  # processes a fault touched: replaced before a next run
        self._ctrl_dir = self.work_dir / "controller"
        # per run (set in run())
        self._extras: list[Child] = []
        self._events: list[dict[str, Any]] = []
        self._pending: list[FaultSpec] = []
        self._restarts = {"controller": 0, "plant": 0}
        self._unwritten: dict[str, str] = {}  # per run: files finish_all could not write
        # processes launched and not yet seen ready (_await_starts)
        self._starting: list[tuple[str, Child]] = []

    # ------------------------------------------------------------------ life
    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, grace_s: float = 5.0) -> None:
        """Stop every process of the bench (plant first), then the bus."""
        with signals.shielded():
            self._stop_plant(grace_s)
            self._stop_controller(grace_s)
            if self.server is not None:
                self.server.stop()
                self.server = None
            if self.own_cpu is not None:
                pin_all_threads(self._harness_cpus)
                self.own_cpu = None
            if self._tmp is not None:
                shutil.rmtree(self._tmp, ignore_errors=True)
                self._tmp = None

    def _stop_plant(self, grace_s: float) -> int | None:
        code = self.plant.stop(grace_s) if self.plant is not None else None
        self._forget_start(self.plant)
        self.plant = None
        return code

    def _stop_controller(self, grace_s: float) -> int | None:
        code = self.controller.stop(grace_s) if self.controller is not None else None
        self._forget_start(self.controller)
        self.controller = self.coding = self.setup = None
        return code

    def _forget_start(self, child: Child | None) -> None:
        """A stopped process is no longer awaited (a launch that a failed start left in
        :attr:`_starting` would fail the next run's start)."""
        self._starting = [(n, c) for n, c in self._starting if c is not child]

    def _ensure_bus(self, stats_path: Path | None) -> None:
        if self.server is not None and self.server.alive():
            return
        if self.server is not None:  # a dead hub: the processes on it go with it
            self._stop_plant(1.0)
            self._stop_controller(1.0)
            self.counters.replaced += 1
        log.info("starting the bus (%s) ...", self.bus_request)
        self.bus_spec, self.server = resolve_bus(self.bus_request, stats_path=stats_path,
                                                 rt=self.rt,
                                                 start_timeout_s=self.bus_start_timeout_s)

    def _ensure_cpu(self) -> None:
        if self.controller_cpu_request is None or self.own_cpu is not None:
            return
        self.own_cpu = choose_cpu(self.controller_cpu_request)
        pin_all_threads(self._harness_cpus - {self.own_cpu})  # children inherit the rest

    # ------------------------------------------------------------------ processes
    def _controller_paths(self, out: Path) -> Path:
        return out if not self.warm else self._ctrl_dir

    def _start_controller(self, spec: RunSpec, coding: dict[str, Any], out: Path,
                          suffix: str = "", wait: bool = True) -> Child:
        """The controller process, ready (``wait`` False: launched; :meth:`_await_starts`
        waits for it)."""
        files = self._controller_paths(out) if not suffix else out
        files.mkdir(parents=True, exist_ok=True)
        if spec.target == "m4f":
            return self._start_firmware(spec, coding, out, files, suffix, wait)
        args = ["-m", "controller.runtime.process", "--bus", str(self.bus_spec),
                "--controller", coding["controller"], "--mode", spec.controller_mode,
                "--bench", "--timing", str(files / f"controller_timing{suffix}.csv"),
                "--summary", str(files / f"controller_summary{suffix}.json")]
        if coding.get("config"):
            args += ["--config", coding["config"]]
        for text in coding.get("faults", []):
            args += ["--fault", text]
        if spec.rt:
            args.append("--rt")
        if self.own_cpu is not None:
            args += ["--cpu", str(self.own_cpu), "--keep-cpu-awake"]
        if spec.secoc:
            args += ["--secoc", "--secoc-keys", resolve_key_source(spec.secoc_keys)]
        else:  # the controller authenticates by default
            args.append("--no-secoc")
        log_path = (out / f"controller{suffix}.log") if not self.warm or suffix \
            else self.work_dir / "controller.log"
        log.info("starting controller %s (imports and the compiled core; %s) ...",
                 coding["controller"], FIRST_START_NOTE)
        child = Child("controller", args + list(spec.controller_extra_args), log_path).launch()
        self._starting.append(("controller", child))
        if wait:
            self._await_starts()
        return child

    def _start_firmware(self, spec: RunSpec, coding: dict[str, Any], out: Path, files: Path,
                        suffix: str, wait: bool) -> Child:
        """--target m4f: the firmware's process (build if needed, QEMU, bridge), ready."""
        args = ["-m", PIL_NODE_MODULE, "--bus", str(self.bus_spec),
                "--controller", coding["controller"],
                "--summary", str(files / f"controller_summary{suffix}.json"),
                "--work-dir", str(files)]
        if coding.get("config"):
            args += ["--config", coding["config"]]
        if spec.secoc:
            args.append("--secoc")
        log_path = (out / f"controller{suffix}.log") if not self.warm or suffix \
            else self.work_dir / "controller.log"
        log.info("starting controller %s as Cortex-M4F firmware on QEMU (a first start "
                 "builds it) ...", coding["controller"])
        # controller_extra_args: the firmware process's own options (e.g. --osqp float)
        child = Child("controller", args + list(spec.controller_extra_args), log_path).launch()
        self._starting.append(("controller", child))
        if wait:
            self._await_starts()
        return child

    def _start_plant(self, out: Path, wait: bool = True) -> Child:
        """The plant process, ready (``wait`` False: launched, as :meth:`_start_controller`)."""
        args = ["-m", "plant_sim.process", "--bus", str(self.bus_spec), "--serve"]
        if self.rt:
            args.append("--rt")
        log_path = out / "plant.log" if not self.warm else self.work_dir / "plant.log"
        log.info("starting plant (imports and the vehicle model; %s) ...", FIRST_START_NOTE)
        child = Child("plant", args, log_path, stdin=True).launch()
        self._starting.append(("plant", child))
        if wait:
            self._await_starts()
        return child

    def _await_starts(self) -> None:
        """Wait for every launched process's ready line (each from its own launch). The
        controller and the plant import side by side: neither needs the other to start,
        and a fresh run's start is the longer of the two instead of their sum. A process
        that does not become ready is stopped and forgotten (ChildStartError)."""
        starting, self._starting = self._starting, []
        for i, (name, child) in enumerate(starting):
            try:
                child.wait_ready(START_TIMEOUT_S)
            except BaseException:
                for attr, other in (("controller", self.controller), ("plant", self.plant)):
                    if other is child:
                        setattr(self, attr, None)
                self._starting = starting[i + 1:]  # still to be seen ready before any use
                raise
            log.info("%s ready in %.1f s", name, time.monotonic() - child.started_at)
            if name == "controller":
                self.counters.controller_starts += 1
            else:
                self.counters.plant_starts += 1

    def _prepare_controller(self, spec: RunSpec, coding: dict[str, Any], out: Path) -> None:
        """A controller listening with ``coding`` and in its start state: started, or reset
        (soft: same coding; coding write + hard reset: another one)."""
        setup = controller_setup(spec)
        alive = self.controller is not None and self.controller.poll() is None
        if alive and ("controller" in self._dirty or setup != self.setup):
            self._stop_controller(5.0)
            self.counters.replaced += 1
            alive = False
        elif not alive and self.controller is not None:
            self._stop_controller(1.0)  # died in the last run: replaced
            self.counters.replaced += 1
        self._dirty.discard("controller")
        if not alive:
            self._clear_controller_files()
            # launched only: the plant may start beside it (run() awaits both)
            self.controller = self._start_controller(spec, coding, out, wait=False)
            self.coding, self.setup = coding, setup
            return
        if self.coding is not None and coding != self.coding:
            if coding["controller"] == self.coding["controller"]:
                self._recode(coding, "soft")  # configuration or faults: applied in place
            else:
                self._recode(coding, "hard")  # another controller: a new start
        # the same coding: the run before ended with a soft reset (start state already)
        self._clear_controller_files()  # what a reset wrote between the runs

    def _recode(self, coding: dict[str, Any], kind: str) -> None:
        """Write the coding, then reset: ``kind`` "soft" applies it in place (the same
        controller), "hard" restarts the process with it (and waits for its ready line)."""
        assert self.controller is not None and self.bus_spec is not None
        since = len(self.controller.lines)
        try:
            with UdsTester(self.bus_spec, timeout_s=RESET_TIMEOUT_S) as tester:
                tester.unlock()
                tester.write_coding(coding)
                tester.ecu_reset(kind)
        except UdsError as exc:
            self._reset_failed(f"coding and {kind} reset: {exc}")
            raise ChildStartError(f"controller coding and {kind} reset failed: {exc}") from exc
        if kind == "hard" and self.controller.wait_line(
                ("ready",), since, START_TIMEOUT_S, signals.check) is None:
            self._reset_failed("no ready line after the hard reset")
            raise ChildStartError("controller did not come back after a hard reset")
        self.coding = coding
        if kind == "hard":
            self.counters.hard_resets += 1
        else:
            self.counters.soft_resets += 1
            self.counters.recodings += 1

    def _soft_reset(self) -> bool:
        """Soft-reset the controller (its run files are finished when it answers)."""
        assert self.controller is not None and self.bus_spec is not None
        try:
            with UdsTester(self.bus_spec, timeout_s=RESET_TIMEOUT_S) as tester:
                tester.unlock()
                tester.ecu_reset("soft")
        except UdsError as exc:
            self._reset_failed(f"soft reset: {exc}")
            return False
        self.counters.soft_resets += 1
        return True

    def _reset_failed(self, why: str) -> None:
        log.warning("controller reset failed (%s): the process is replaced", why)
        self.counters.reset_failures += 1
        self._dirty.add("controller")

    def _clear_controller_files(self) -> None:
        if not self.warm:
            return
        self._ctrl_dir.mkdir(parents=True, exist_ok=True)
        for path in self._ctrl_dir.iterdir():
            if path.name.startswith(CONTROLLER_FILES):
                path.unlink(missing_ok=True)

    def _collect_controller_files(self, out: Path) -> None:
        """The controller's files of this run (CSV, summary, or the rows of a killed one) into
        the run directory."""
        if not self.warm or not self._ctrl_dir.is_dir():
            return
        for path in self._ctrl_dir.iterdir():
            if path.name.startswith(CONTROLLER_FILES):
                shutil.move(str(path), str(out / path.name))

    def _prepare_plant(self, out: Path) -> None:
        alive = self.plant is not None and self.plant.poll() is None
        if self.plant is not None and (not alive or "plant" in self._dirty):
            self._stop_plant(2.0)
            self.counters.replaced += 1
            alive = False
        self._dirty.discard("plant")
        if not alive:
            self.plant = self._start_plant(out, wait=False)

    # ------------------------------------------------------------------ one run
    def check(self, spec: RunSpec) -> None:
        """BenchError if ``spec`` needs another bus, CPU layout or scheduling class."""
        if self.warm and (spec.bus, spec.rt, spec.controller_cpu) != (
                self.bus_request, self.rt, self.controller_cpu_request):
            raise BenchError(f"this bench runs on bus={self.bus_request} rt={self.rt} "
                             f"controller_cpu={self.controller_cpu_request}; the run asks for "
                             f"bus={spec.bus} rt={spec.rt} controller_cpu={spec.controller_cpu}")

    def run(self, spec: RunSpec, progress: Callable[[float], None] | None = None,
            tap: BusTap | None = None) -> RunOutcome:
        """Carry out one run into ``spec.out_dir``; retried once if a process died that no
        fault asked to die (counted in the outcome's ``bench``)."""
        self.check(spec)
        before = BenchCounters(**vars(self.counters))
        outcome = self._attempt(spec, progress, tap)
        first_reason = first_dir = None
        if self._died_unexpectedly(outcome) and not outcome.interrupted:
            first_reason = _failure_of(outcome)
            out = Path(spec.out_dir or ".")
            first_dir = _keep_attempt_files(out, FIRST_ATTEMPT_DIR)
            log.warning("run %s: %s; processes replaced, retrying once (the first attempt's "
                        "files are in %s)", spec.out_dir, first_reason, first_dir)
            self.counters.retries += 1
            self._dirty.update({"plant", "controller"})
            outcome = self._attempt(spec, progress, tap)
        self.counters.runs += 1
        outcome.bench = {"warm": self.warm, "first_attempt_reason": first_reason,
                         "first_attempt_dir": first_dir,
                         **{k: v - getattr(before, k) for k, v in vars(self.counters).items()}}
        return outcome

    def _died_unexpectedly(self, outcome: RunOutcome) -> bool:
        faulted = {PROCESS_FAULTS_ON[e["fault"].split("@")[0].split(":")[0]]
                   for e in outcome.fault_events
                   if e["fault"].split("@")[0].split(":")[0] in PROCESS_FAULTS_ON}
        if outcome.reason.startswith("start failed"):
            return True
        plant_died = outcome.reason.startswith("plant exited") and "plant" not in faulted
        ctrl_died = outcome.controller_lost_at_s is not None and "controller" not in faulted
        return plant_died or ctrl_died

    def _attempt(self, spec: RunSpec, progress: Callable[[float], None] | None,
                 tap: BusTap | None) -> RunOutcome:
        out = Path(spec.out_dir or ".")
        out.mkdir(parents=True, exist_ok=True)
        faults = run_faults(spec)
        plant_faults, ctrl_faults = route_frame_faults(faults, Codec(),
                                                       lockstep=spec.mode == "lockstep")
        self._pending = sorted((f for f in faults if not f.is_frame_fault
                                and not f.is_core_fault), key=lambda f: f.at_s)
        self._events, self._extras = [], []
        self._restarts = {"controller": 0, "plant": 0}
        self._unwritten = {}
        coding = controller_coding(spec, ctrl_faults, self.work_dir / "configs")
        recorder: BusRecorder | None = None
        reason, interrupted = "not started", False
        plant_code = controller_code = None
        controller_lost_at: float | None = None
        wall_start = last_progress = last_tap = time.monotonic()
        run_lines = {"plant": 0, "controller": 0}
        own_cpu: int | None = None
        try:
            self._ensure_cpu()
            own_cpu = self.own_cpu  # (a fresh bench lets its CPU go when the run ends)
            self._ensure_bus(out / "bus_hub_stats.json" if not self.warm else None)
            self._prepare_controller(spec, coding, out)
            self._prepare_plant(out)
            self._await_starts()
            assert self.plant is not None and self.controller is not None
            run_lines = {"plant": len(self.plant.lines),
                         "controller": len(self.controller.lines)}
            recorder = BusRecorder(str(self.bus_spec), out / f"bus.{spec.log_format}",
                                   stamp="sim" if spec.mode == "lockstep" else "wall",
                                   tap=tap.tap if tap is not None else None, rt=spec.rt).start()
            for fault in [f for f in self._pending if f.kind in ROGUE_ATTACKS
                          and f.at_s <= 1e-9]:  # a rogue at 0 s is on the bus before the plant
                self._pending.remove(fault)
                self._apply_fault(fault, out, 0.0)
            self._send_run(spec, out, plant_faults)
            signals.check()
            reason = "running"
            while True:
                assert self.plant is not None and self.controller is not None
                line = self.plant.wait_line(("done", "error"), run_lines["plant"], 0.02)
                if line is not None or self.plant.poll() is not None:
                    reason, interrupted = self._plant_end(line, out)
                    break
                if self.controller.poll() is not None and controller_lost_at is None:
                    controller_lost_at = recorder.sim_time_s
                for fault in self._due(recorder.sim_time_s):
                    self._apply_fault(fault, out, recorder.sim_time_s, spec, plant_faults)
                if tap is not None and time.monotonic() - last_tap > 0.2:
                    tap.poll()
                    last_tap = time.monotonic()
                if progress is not None and time.monotonic() - last_progress > 0.5:
                    progress(recorder.sim_time_s)
                    last_progress = time.monotonic()
                if time.monotonic() - wall_start > spec.wall_timeout_s:
                    reason = f"wall timeout after {spec.wall_timeout_s:.0f} s"
                    self._dirty.add("plant")  # mid-run: only a new process starts clean
                    break
                signals.check()
        except (ChildStartError, BusServerError) as exc:
            reason = f"start failed: {exc}"
        except KeyboardInterrupt:  # SIGINT or SIGTERM (harness/run/signals.py)
            reason, interrupted = "interrupted", True
        finally:
            with signals.shielded():  # a further signal must not cut the cleanup short
                plant_code, controller_code = self._end_run(
                    out, recorder, interrupted, reason, run_lines)
        return RunOutcome(
            reason=reason, interrupted=interrupted, plant_code=plant_code,
            controller_code=controller_code, controller_lost_at_s=controller_lost_at,
            fault_events=self._events,
            frames_recorded=recorder.frames if recorder is not None else 0,
            released_early=recorder.released_early if recorder is not None else 0,
            log_time_base=recorder.time_base if recorder is not None else None,
            sim_time_s=float(recorder.sim_time_s) if recorder is not None else 0.0,
            bus_spec=str(self.bus_spec or spec.bus), own_cpu=own_cpu,
            recorder_rx_dropped=recorder.rx_dropped if recorder is not None else None,
            files_not_written=dict(self._unwritten))

    def _send_run(self, spec: RunSpec, out: Path, plant_faults: list[str]) -> None:
        """The run command on the plant's control channel; waits until it is loaded."""
        assert self.plant is not None
        since = len(self.plant.lines)
        log.info("loading %s into the plant ...", scenario_label(spec.scenario))
        self.plant.send(json.dumps({"run": plant_run_args(spec, out, plant_faults)}))
        line = self.plant.wait_line(("loaded", "error", "done"), since, LOAD_TIMEOUT_S,
                                    signals.check)
        if line is None:
            raise ChildStartError("plant did not load the run:\n"
                                  + "\n".join(self.plant.lines[since:][-10:]))
        if line.startswith("error"):
            raise ChildStartError(f"plant refused the run: {line[len('error'):].strip()}")

    def _plant_end(self, line: str | None, out: Path) -> tuple[str, bool]:
        """The run's end reason from the plant's ``done`` line (or its exit)."""
        if line is None or not line.startswith("done"):
            assert self.plant is not None
            code = self.plant.poll()
            self._dirty.add("plant")
            if line is not None and line.startswith("error"):
                return f"plant error: {line[len('error'):].strip()}", False
            return f"plant exited with code {code}", False
        summary = read_json(out / "plant_summary.json")
        if summary.get("reason") == "stopped by signal":
            # a stop signal reached the plant, not this process (a run in a pool worker,
            # whose process group got the terminal's Ctrl-C)
            self._dirty.add("plant")
            return "interrupted", True
        if summary.get("reason") == "bus lost":
            self._dirty.add("plant")
            return "plant exited with code 3", False
        return "finished", False

    def _end_run(self, out: Path, recorder: BusRecorder | None, interrupted: bool,
                 reason: str, run_lines: dict[str, int]) -> tuple[int | None, int | None]:
        plant_code = controller_code = None
        grace = INTERRUPT_GRACE_S if interrupted else 5.0
        if interrupted or reason.startswith(("wall timeout", "start failed")):
            self._dirty.add("plant")
        if self.plant is not None and ("plant" in self._dirty or not self.warm):
            plant_code = self._stop_plant(grace)  # a run still going ends here
        elif self.plant is not None:
            plant_code = 0
        warm_reset = (self.warm and not interrupted and self.controller is not None
                      and self.controller.poll() is None and "controller" not in self._dirty
                      and (self.setup is None or self.setup[-1] == "host"))  # firmware: no UDS
        if recorder is not None and warm_reset:
            # the reset's response is the controller's last frame after the run's: once the
            # recorder has it, the log is complete (no idle wait); the diagnostics stay out
            recorder.arm_barrier(DIAG_IDS, DIAG_RESP_ID, SOFT_RESET_RESPONSE)
        elif recorder is not None:
            recorder.drain(INTERRUPT_DRAIN_S if interrupted else 0.3)
        for child in self._extras:
            child.stop(grace)
        ctrl_child = self.controller
        if self.controller is not None:
            lines_end = len(self.controller.lines)
            if warm_reset and self._soft_reset():
                controller_code = 0  # reset: its files of this run are finished
                lines_end = len(self.controller.lines)
                if recorder is not None and not recorder.wait_barrier(BARRIER_TIMEOUT_S):
                    recorder.drain(0.3)
            elif self.warm and self.controller.poll() is None:
                if recorder is not None and warm_reset:
                    recorder.drain(0.3)  # no reset response: the idle wait instead
                lines_end = len(self.controller.lines)
                controller_code = self._stop_controller(grace)  # it writes its files now
                self.counters.replaced += 1
            else:
                controller_code = self.controller.poll()
                if controller_code is None:
                    controller_code = self._stop_controller(grace)
                else:
                    self._dirty.add("controller")
            if self.warm and ctrl_child is not None:
                _write_lines(out / "controller.log",
                             ctrl_child.lines[run_lines["controller"]:lines_end])
        if self.warm and self.plant is not None:
            _write_lines(out / "plant.log", self.plant.lines[run_lines["plant"]:])
        self._collect_controller_files(out)
        # the row logs of a killed plant or controller -> CSV; one that cannot be written
        # (disk full) keeps its row file and is named in the run's metrics
        finish_all(out, failed=self._unwritten)
        for name, why in self._unwritten.items():
            log.warning("%s could not be written (%s): its rows stay in %s%s", name, why,
                        name, ROWS_SUFFIX)
        if recorder is not None:
            recorder.stop()
        if not self.warm:
            self.close(grace)
        return plant_code, controller_code

    # ------------------------------------------------------------------ faults
    def _due(self, sim_time_s: float) -> list[FaultSpec]:
        """Process-level faults whose time (simulated s) has come."""
        out = [f for f in self._pending if f.at_s <= sim_time_s + 1e-9]
        self._pending = [f for f in self._pending if f.at_s > sim_time_s + 1e-9]
        return out

    def _apply_fault(self, fault: FaultSpec, out: Path, sim_time_s: float,
                     spec: RunSpec | None = None, plant_faults: list[str] | None = None
                     ) -> None:
        """Carry out a process-level fault on the bench's processes."""
        event: dict[str, Any] = {"fault": fault.text, "sim_time_s": sim_time_s}
        if fault.kind == "kill-controller" and self.controller is not None:
            self.controller.kill()
            self._dirty.add("controller")
        elif fault.kind == "kill-plant" and self.plant is not None:
            self.plant.kill()
            self._dirty.add("plant")
        elif fault.kind == "restart-controller" and self.controller is not None:
            assert spec is not None and self.coding is not None
            self.controller.kill()
            self._restarts["controller"] += 1
            keep = self.controller  # the killed one's log lines belong to the run
            self.controller = self._start_controller(
                spec, self.coding, out, suffix=f".{self._restarts['controller']}")
            self._extras.append(keep)
            self._dirty.add("controller")  # its files are in the run dir: not for a next run
        elif fault.kind == "restart-plant" and self.plant is not None:
            assert spec is not None
            self.plant.kill()
            self._restarts["plant"] += 1
            _keep_killed_plant_files(out, self._restarts["plant"])
            self.plant = self._start_plant(out)
            self._send_run(spec, out, plant_faults or [])
            self._dirty.add("plant")
        elif fault.kind == "restart-bus":
            if self.server is None:
                event["skipped"] = "no bus server to restart (SocketCAN bus)"
            else:
                self.server.restart()
        elif fault.kind == "flood":
            self._extras.append(Child("flood", [
                "-m", "harness.run.flood", "--bus", str(self.bus_spec), "--rate",
                str(fault.amount or 5000.0)], out / "flood.log").start())
        elif fault.kind in ROGUE_ATTACKS:
            n = sum(1 for c in self._extras if c.name == "rogue")
            args = ["-m", "harness.run.rogue", "--bus", str(self.bus_spec),
                    "--attack", ROGUE_ATTACKS[fault.kind],
                    "--summary", str(out / f"rogue{n}_summary.json")]
            if fault.kind == "rogue-flood":
                args += ["--rate", str(fault.amount)]
            elif fault.kind in {"rogue-replay", "rogue-sensor-replay"}:
                args += ["--record-s", str(fault.amount)]
            self._extras.append(Child("rogue", args, out / f"rogue{n}.log").start())
        self._events.append(event)


def _keep_killed_plant_files(out: Path, n: int) -> None:
    """The restarted plant starts the scenario again and owns the canonical files (the run's
    KPIs are its); the killed one's files are kept as ``*.runN``."""
    finish_rows(out / "truth.csv")  # the killed plant's rows, before the new plant's
    for name in ("truth.csv", "plant_summary.json"):
        stem, dot, ext = name.partition(".")
        if (out / name).exists():
            (out / name).rename(out / f"{stem}.run{n}{dot}{ext}")


FIRST_ATTEMPT_DIR = "attempt1"  # a retried run's first attempt: its files, kept


def _failure_of(outcome: RunOutcome) -> str:
    """What went wrong in an attempt that is retried: the plant's end, or the controller's
    death (the plant may well have "finished" the run without it)."""
    if outcome.controller_lost_at_s is not None and not outcome.reason.startswith(
            ("plant exited", "start failed")):
        code = outcome.controller_code
        return (f"the controller process died at {outcome.controller_lost_at_s:.2f} s "
                f"simulated (exit code {code if code is not None else 'unknown'}); the plant "
                f"ended: {outcome.reason}")
    return outcome.reason


def _keep_attempt_files(out: Path, name: str) -> str:
    """Move a failed attempt's files into ``out/name`` (replacing an older such folder)
    before the retry writes its own; returns ``name``."""
    keep = out / name
    if keep.exists():
        shutil.rmtree(keep)
    keep.mkdir(parents=True)
    paths = [out / n for n in ("truth.csv", "truth.csv.rows", "plant_summary.json",
                               "controller.log", "plant.log")]
    paths += [*out.glob("controller_*"), *out.glob("bus.*"), *out.glob("rogue*.log")]
    for path in paths:
        if path.exists():
            path.rename(keep / path.name)
    return name


def _write_lines(path: Path, lines: list[str]) -> None:
    with path.open("a") as f:
        f.writelines(ln + "\n" for ln in lines)


def read_json(path: Path) -> dict[str, Any]:
    """A summary file, or {} if it is missing or unreadable (a killed process)."""
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return {}

