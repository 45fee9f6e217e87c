"""One closed-loop run: bus (server if needed), controller process, plant process, recorder.

Order: resolve the bus → start the bus recorder → start the controller (it must be listening
before the first SYNC) → start the plant → wait for the plant to finish → drain the bus →
SIGTERM the controller → stop the recorder and the server. Anything that goes wrong (a child
dies, Ctrl-C, a timeout) still stops every child and still writes ``metrics.json`` with the
reason. Afterwards: KPIs, PNG plots and one rerun recording from the files in DIR.

SecOC is on by default (``secoc=False`` turns it off): both processes get ``--secoc`` and the
key source (``secoc_keys``; default: the RHONN_SECOC_KEY_* variables when set, else the public
CI test key, which is fine for a simulation). The plant's trip counter lives in
``DIR/secoc_trip``; it is removed at the start of a run (each run is a new vehicle, so a
lockstep run gives the same frames, MACs included, every time) and kept across a
``restart-plant`` inside the run.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from can_db.codec import Codec
from can_db.faults import (
    FaultInjector,
    FaultSpec,
    FaultSpecError,
    parse_fault,
    parse_faults,
)
from can_db.process.cpu import allowed_cpus, choose_cpu, pin_all_threads
from can_db.process.rowlog import finish_all, finish_rows
from can_db.secoc_keys import TEST_KEY_SOURCE, load_keys, resolve_key_source
from can_db.transport.bus import resolve_bus
from can_db.transport.hub import LocalHub
from can_db.transport.server import BusServer, BusServerError
from harness.run import marker, signals
from harness.run.bus_logger import BusRecorder
from harness.run.procs import Child, ChildStartError
from plant_sim.scenario import is_scenario_file, scenario_label

# After SIGINT/SIGTERM: how long each child gets to exit after its SIGTERM before SIGKILL, and
# how long the recorder waits for the last frames, wall s (the harness stops within ~2 s).
INTERRUPT_GRACE_S = 1.0
INTERRUPT_DRAIN_S = 0.1
# What the analysis of an interrupted run (KPIs, plots, recording of the data up to the signal)
# may take, wall s after the signal; the rest is skipped and metrics.json says so.
INTERRUPT_ANALYSIS_S = 1.5
# How long a live plant or controller process may take to report ready, s. The first run
# after an install compiles the plant's numba kernel (plant_sim/kernel.py, when numba is
# installed); a process that exits is reported at once, not after this.
START_TIMEOUT_S = 300.0
# what a user waits for at a first start: Python writes the bytecode caches of numpy, scipy,
# python-can and the project, numba compiles the plant's vehicle step (cached after)
FIRST_START_NOTE = "a first start after install writes caches: up to about a minute"
log = logging.getLogger("harness.run")


def software_version() -> str:
    """Installed rhonn-tv version (or 'dev')."""
    try:
        return version("rhonn-tv")
    except PackageNotFoundError:
        return "dev"


@dataclass
class RunConfig:
    """What to run. Speeds in km/h, friction dimensionless, durations in s."""

    scenario: str
    controller: str
    out_dir: Path
    bus: str = "auto"
    mode: str = "lockstep"  # lockstep | realtime
    controller_mode: str = "lockstep"  # lockstep (sync-driven) | freerun
    controller_config: str | None = None
    mu: float | None = None
    speed_kmh: float | None = None
    seed: int = 0
    duration_s: float | None = None
    params: dict[str, Any] = field(default_factory=dict)
    vehicle: dict[str, float] = field(default_factory=dict)  # plant_sim/overrides.py
    wall_timeout_s: float = 600.0
    kill_controller_at_s: float | None = None  # simulated s (same as fault kill-controller@T)
    faults: list[str] = field(default_factory=list)  # --fault specs, see can_db/faults.py
    controller_extra_args: list[str] = field(default_factory=list)
    plant_extra_args: list[str] = field(default_factory=list)  # e.g. ["--lost-after", "100"]
    make_plots: bool = True
    make_rrd: bool = True
    rt: bool = False  # plant, controller, hub and recorder ask for SCHED_FIFO (process/rt.py)
    log_format: str = "blf"  # bus log: blf | asc | mf4 (see harness/run/bus_logger.py)
    rerun_live: bool = False  # stream to a rerun web viewer on 127.0.0.1 during the run
    rerun_port: int = 9090  # web viewer port of --rerun-live
    secoc: bool = True  # authenticated SYNC/torque/status frames (can_db/secoc.py)
    secoc_keys: str | None = None  # env | ci-test-key | KEYFILE; None: env if set, else test key
    # HIL layout: the controller alone on this CPU ("auto": the highest), kept awake
    # (can_db/process/cpu.py); harness, recorder, hub and plant on the others. None: all share.
    controller_cpu: str | None = None


@dataclass
class RunResult:
    """Where things are and what happened."""

    out_dir: Path
    metrics: dict[str, Any]
    reason: str
    plant_code: int | None
    controller_code: int | None
    live: Any = None  # the live rerun view (harness.viz.rerun_live.LiveRerun) if one ran


def recording_name(cfg: RunConfig) -> str:
    """``SCENARIO-CONTROLLER-muX-vY-sN`` with the friction and speed the run really used
    (the scenario's own when not overridden)."""
    mu, speed = cfg.mu, cfg.speed_kmh
    if mu is None or speed is None:
        try:
            from plant_sim.scenario import load_scenario

            params = {k: _number(v) for k, v in cfg.params.items()}
            scen = load_scenario(cfg.scenario, mu=cfg.mu, speed_kmh=cfg.speed_kmh, **params)
            mu = scen.mu if mu is None else mu
            speed = scen.speed_kmh if speed is None else speed
        except (KeyError, ValueError, TypeError):
            pass
    mu_s = "?" if mu is None else f"{mu:g}"
    v_s = "?" if speed is None else f"{speed:g}"
    return f"{scenario_label(cfg.scenario)}-{cfg.controller}-mu{mu_s}-v{v_s}-s{cfg.seed}"


def planned_duration_s(cfg: RunConfig) -> float | None:
    """Simulated seconds the run is meant to last: the scenario's, cut at ``duration_s`` (the
    plant stops at the earlier of the two)."""
    try:
        from plant_sim.scenario import load_scenario

        params = {k: _number(v) for k, v in cfg.params.items()}
        own = float(load_scenario(cfg.scenario, mu=cfg.mu, speed_kmh=cfg.speed_kmh,
                                  **params).duration_s)
    except (KeyError, ValueError, TypeError):
        return None if cfg.duration_s is None else float(cfg.duration_s)
    return own if cfg.duration_s is None else min(own, float(cfg.duration_s))


def _number(value: Any) -> Any:
    try:
        return float(value)
    except (TypeError, ValueError):
        return value


def _start_live(cfg: RunConfig) -> Any:
    """The live rerun view (None, with a note on stderr, if it cannot start)."""
    try:
        from harness.analysis.course import course_geometry, scenario_for
        from harness.viz.rerun_live import LiveRerun

        geo = course_geometry(scenario_for(cfg.scenario, cfg.mu, cfg.speed_kmh, cfg.params),
                              cfg.duration_s)
        live = LiveRerun(cfg.out_dir, recording_name(cfg), geo.boundaries, geo.ref_path,
                         geo.cones, web_port=cfg.rerun_port)
    except Exception as exc:  # the run goes on without its live view
        log.warning("live rerun view not started: %s", exc)
        return None
    print(f"live rerun view: {live.url}", flush=True)
    return live


SECOC_TRIP_FILE = "secoc_trip"
ROGUE_ATTACKS = {"rogue-inject": "inject", "rogue-replay": "replay", "rogue-flood": "flood",
                 "rogue-spoof": "spoof", "rogue-sensor-replay": "sensor-replay"}


_TEST_KEY_NOTED = []


def _note_test_key() -> None:
    """Say once per process that the public CI test key is in use."""
    if not _TEST_KEY_NOTED:
        _TEST_KEY_NOTED.append(True)
        log.info("SecOC: using the public CI test key (simulation only)")


def _plant_args(cfg: RunConfig, spec: str) -> list[str]:
    args = ["-m", "plant_sim.process", "--bus", spec, "--scenario", cfg.scenario,
            "--mode", cfg.mode, "--trace", str(cfg.out_dir / "truth.csv"),
            "--summary", str(cfg.out_dir / "plant_summary.json"), "--seed", str(cfg.seed)]
    if cfg.mu is not None:
        args += ["--mu", str(cfg.mu)]
    if cfg.speed_kmh is not None:
        args += ["--speed", str(cfg.speed_kmh)]
    if cfg.duration_s is not None:
        args += ["--duration", str(cfg.duration_s)]
    for key, value in cfg.params.items():
        text = json.dumps(value) if isinstance(value, list | tuple) else value
        args += ["--param", f"{key}={text}"]
    for key, value in cfg.vehicle.items():
        args += ["--vehicle", f"{key}={value}"]
    if cfg.rt:
        args.append("--rt")
    if cfg.secoc:
        args += ["--secoc", "--secoc-keys", resolve_key_source(cfg.secoc_keys),
                 "--secoc-state", str(cfg.out_dir / SECOC_TRIP_FILE)]
    return args + list(cfg.plant_extra_args)


def _controller_args(cfg: RunConfig, spec: str) -> list[str]:
    args = ["-m", "controller.runtime.process", "--bus", spec, "--controller", cfg.controller,
            "--mode", cfg.controller_mode, "--timing",
            str(cfg.out_dir / "controller_timing.csv"),
            "--summary", str(cfg.out_dir / "controller_summary.json")]
    if cfg.controller_config:
        args += ["--config", cfg.controller_config]
    if cfg.rt:
        args.append("--rt")
    if cfg.controller_cpu is not None:
        # a CPU number: run_closed_loop resolves "auto" before any child starts
        args += ["--cpu", cfg.controller_cpu, "--keep-cpu-awake"]
    if cfg.secoc:
        args += ["--secoc", "--secoc-keys", resolve_key_source(cfg.secoc_keys)]
    return args


def _route_frame_faults(faults: list[FaultSpec], codec: Codec, lockstep: bool
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


class _Orchestra:
    """The children of one run and the process-level faults applied to them."""

    def __init__(self, cfg: RunConfig, spec: str, faults: list[FaultSpec]) -> None:
        self.cfg, self.spec = cfg, spec
        self.pending = sorted((f for f in faults
                               if not f.is_frame_fault and not f.is_core_fault),
                              key=lambda f: f.at_s)
        self.plant_faults, self.ctrl_faults = _route_frame_faults(
            faults, Codec(), lockstep=cfg.mode == "lockstep")
        self.events: list[dict[str, Any]] = []
        self.controller: Child | None = None
        self.plant: Child | None = None
        self.flood: Child | None = None
        self.rogues: list[Child] = []
        self.controller_starts = 0
        self.plant_starts = 0

    def start_controller(self) -> None:
        args = _controller_args(self.cfg, self.spec)
        for text in self.ctrl_faults:
            args += ["--fault", text]
        suffix = f".{self.controller_starts}" if self.controller_starts else ""
        if suffix:  # a restarted controller keeps its predecessor's files
            args[args.index("--timing") + 1] = str(self.cfg.out_dir /
                                                   f"controller_timing{suffix}.csv")
            args[args.index("--summary") + 1] = str(self.cfg.out_dir /
                                                    f"controller_summary{suffix}.json")
        log.info("starting controller %s (imports and the compiled core; %s) ...",
                 self.cfg.controller, FIRST_START_NOTE)
        started = time.monotonic()
        self.controller = Child("controller", args + list(self.cfg.controller_extra_args),
                                self.cfg.out_dir / f"controller{suffix}.log"
                                ).start(timeout_s=START_TIMEOUT_S)
        log.info("controller ready in %.1f s", time.monotonic() - started)
        self.controller_starts += 1

    def start_plant(self) -> None:
        args = _plant_args(self.cfg, self.spec)
        for text in self.plant_faults:
            args += ["--fault", text]
        if self.plant_starts:
            # The restarted plant starts the scenario again and owns the canonical files
            # (the run's KPIs are its); the killed one's files are kept as *.runN.
            out = self.cfg.out_dir
            finish_rows(out / "truth.csv")  # the killed plant's rows, before the new plant's
            for name in ("truth.csv", "plant_summary.json", "plant.log"):
                stem, dot, ext = name.partition(".")
                if (out / name).exists():
                    (out / name).rename(out / f"{stem}.run{self.plant_starts}{dot}{ext}")
        log.info("starting plant %s (imports and the vehicle model; %s) ...",
                 scenario_label(self.cfg.scenario), FIRST_START_NOTE)
        started = time.monotonic()
        self.plant = Child("plant", args, self.cfg.out_dir / "plant.log"
                           ).start(timeout_s=START_TIMEOUT_S)
        log.info("plant ready in %.1f s", time.monotonic() - started)
        self.plant_starts += 1

    def due(self, sim_time_s: float) -> list[FaultSpec]:
        """Process-level faults whose time (simulated s) has come."""
        out = [f for f in self.pending if f.at_s <= sim_time_s + 1e-9]
        self.pending = [f for f in self.pending if f.at_s > sim_time_s + 1e-9]
        return out

    def due_attacks_at_start(self) -> list[FaultSpec]:
        """Rogue-node attacks timed at 0 s (started before the plant's first frame)."""
        out = [f for f in self.pending if f.kind in ROGUE_ATTACKS and f.at_s <= 1e-9]
        self.pending = [f for f in self.pending if f not in out]
        return out

    def stop_all(self, grace_s: float = 5.0) -> tuple[int | None, int | None]:
        """SIGTERM every child (plant first: it ends the loop), SIGKILL after ``grace_s``."""
        plant_code = self.plant.stop(grace_s) if self.plant is not None else None
        controller_code = (self.controller.stop(grace_s) if self.controller is not None
                           else None)
        if self.flood is not None:
            self.flood.stop(grace_s)
        for rogue in self.rogues:
            rogue.stop(grace_s)
        return plant_code, controller_code


def run_closed_loop(cfg: RunConfig,
                    progress: Callable[[float], None] | None = None) -> RunResult:
    """Run the processes, then analyse; never leaves a child behind.

    ``progress``: called about every 0.5 s (wall) with the simulated time reached, s.
    """
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    faults = parse_faults(list(cfg.faults))  # bad specs raise FaultSpecError here, early
    if cfg.kill_controller_at_s is not None:
        faults.append(parse_fault(f"kill-controller@{cfg.kill_controller_at_s}s"))
    FaultInjector(Codec(), faults)  # validates message and signal names
    _route_frame_faults(faults, Codec(), lockstep=cfg.mode == "lockstep")
    (cfg.out_dir / SECOC_TRIP_FILE).unlink(missing_ok=True)  # a new vehicle: trip 1
    if cfg.secoc:
        load_keys(resolve_key_source(cfg.secoc_keys))  # bad keys raise SecOcKeyError here
    if cfg.secoc and resolve_key_source(cfg.secoc_keys) == TEST_KEY_SOURCE:
        _note_test_key()
    server: LocalHub | BusServer | None = None
    recorder: BusRecorder | None = None
    orch: _Orchestra | None = None
    reason = "not started"
    controller_lost_at: float | None = None
    spec = cfg.bus
    wall_start = last_progress = time.monotonic()
    plant_code = controller_code = None
    live = _start_live(cfg) if cfg.rerun_live else None
    last_live = time.monotonic()
    harness_cpus = allowed_cpus()
    own_cpu = choose_cpu(cfg.controller_cpu) if cfg.controller_cpu is not None else None
    if own_cpu is not None:  # children started from here on inherit the rest
        cfg = replace(cfg, controller_cpu=str(own_cpu))
        pin_all_threads(harness_cpus - {own_cpu})
    interrupted = False
    last_touch = time.monotonic()
    in_progress = marker.claim(cfg.out_dir)  # RunDirBusyError if a live harness writes there
    try:  # from here on every end (a signal too) writes metrics.json and releases the marker
        _clear_previous_outputs(cfg.out_dir)
        log.info("starting the bus (%s) and its recorder ...", cfg.bus)
        spec, server = resolve_bus(cfg.bus, stats_path=cfg.out_dir / "bus_hub_stats.json",
                                   rt=cfg.rt)
        orch = _Orchestra(cfg, spec, faults)
        recorder = BusRecorder(spec, cfg.out_dir / f"bus.{cfg.log_format}",
                               stamp="sim" if cfg.mode == "lockstep" else "wall",
                               tap=live.tap if live is not None else None,
                               rt=cfg.rt).start()
        orch.start_controller()
        for fault in orch.due_attacks_at_start():  # a rogue at 0 s is on the bus before the plant
            server = _apply_process_fault(fault, orch, server, 0.0)
        orch.start_plant()
        signals.check()
        reason = "running"
        while True:
            assert orch.plant is not None and orch.controller is not None
            code = orch.plant.poll()
            if code is not None:
                reason = "finished" if code == 0 else f"plant exited with code {code}"
                if code == 0 and _read_json(cfg.out_dir / "plant_summary.json").get(
                        "reason") == "stopped by signal":
                    # a stop signal reached the plant, not this process (a run in a pool
                    # worker, whose process group got the terminal's Ctrl-C)
                    reason, interrupted = "interrupted", True
                break
            if orch.controller.poll() is not None and controller_lost_at is None:
                controller_lost_at = recorder.sim_time_s
            for fault in orch.due(recorder.sim_time_s):
                server = _apply_process_fault(fault, orch, server, recorder.sim_time_s)
            if live is not None and time.monotonic() - last_live > 0.2:
                live.poll()
                last_live = time.monotonic()
            if progress is not None and time.monotonic() - last_progress > 0.5:
                progress(recorder.sim_time_s)
                last_progress = time.monotonic()
            if time.monotonic() - wall_start > cfg.wall_timeout_s:
                reason = f"wall timeout after {cfg.wall_timeout_s:.0f} s"
                break
            if time.monotonic() - last_touch > marker.TOUCH_EVERY_S:
                marker.touch(in_progress)
                last_touch = time.monotonic()
            signals.check()
            time.sleep(0.02)
    except (ChildStartError, BusServerError) as exc:
        reason = f"start failed: {exc}"
    except KeyboardInterrupt:  # SIGINT or SIGTERM (harness/run/signals.py)
        reason, interrupted = "interrupted", True
    finally:
        with signals.shielded():  # a further signal must not cut the cleanup short
            if interrupted and orch is not None:
                # the plant is still running: stop it first, the last answers follow
                plant_code, controller_code = orch.stop_all(INTERRUPT_GRACE_S)
            if recorder is not None:
                recorder.drain(INTERRUPT_DRAIN_S if interrupted else 0.3)
            if orch is not None and not interrupted:
                plant_code, controller_code = orch.stop_all()
            finish_all(cfg.out_dir)  # the row logs of a killed plant or controller -> CSV
            if recorder is not None:
                recorder.stop()
            if server is not None:
                server.stop()
            if own_cpu is not None:
                pin_all_threads(harness_cpus)
    meta = {
        "scenario": cfg.scenario, "controller": cfg.controller,
        # a scenario file: its stem, and where it is (metrics "scenario" is as given)
        "scenario_name": scenario_label(cfg.scenario),
        "scenario_file": str(Path(cfg.scenario).absolute())
        if is_scenario_file(cfg.scenario) else None,
        "bus": spec.split(":")[0] if spec else cfg.bus, "bus_spec": cfg.bus, "mode": cfg.mode,
        "controller_mode": cfg.controller_mode, "mu": cfg.mu, "speed_kmh": cfg.speed_kmh,
        "seed": cfg.seed, "software_version": software_version(), "reason": reason,
        "params": dict(cfg.params),
        "secoc": cfg.secoc,
        "controller_cpu": own_cpu,
        "faults": list(cfg.faults), "fault_events": orch.events if orch else [],
        "plant_exit_code": plant_code, "controller_exit_code": controller_code,
        "controller_lost_at_sim_s": controller_lost_at,
        "wall_time_s": time.monotonic() - wall_start,
        "bus_frames_recorded": recorder.frames if recorder is not None else 0,
        "bus_log_released_early": recorder.released_early if recorder is not None else 0,
        "bus_hub": _read_json(cfg.out_dir / "bus_hub_stats.json") or None,
        "bus_log": f"bus.{cfg.log_format}",
        "bus_log_time_base": recorder.time_base if recorder is not None else None,
        "interrupted": interrupted,
        "sim_time_reached_s": _sim_time_reached_s(cfg.out_dir, recorder),
        "duration_planned_s": planned_duration_s(cfg),
    }
    log.info("run %s after %.1f s; analysing (KPIs, plots, recording) ...", reason,
             meta["wall_time_s"])
    try:
        metrics = analyse_run(cfg, meta, live)
    finally:
        marker.release(in_progress)
    return RunResult(cfg.out_dir, metrics, metrics["reason"], plant_code, controller_code,
                     live)


def _apply_process_fault(fault: FaultSpec, orch: _Orchestra,
                         server: LocalHub | BusServer | None,
                         sim_time_s: float) -> LocalHub | BusServer | None:
    """Carry out a process-level fault; returns the (possibly new) bus server."""
    event: dict[str, Any] = {"fault": fault.text, "sim_time_s": sim_time_s}
    if fault.kind == "kill-controller" and orch.controller is not None:
        orch.controller.kill()
    elif fault.kind == "kill-plant" and orch.plant is not None:
        orch.plant.kill()
    elif fault.kind == "restart-controller" and orch.controller is not None:
        orch.controller.kill()
        orch.start_controller()
    elif fault.kind == "restart-plant" and orch.plant is not None:
        orch.plant.kill()
        orch.start_plant()
    elif fault.kind == "restart-bus":
        if server is None:
            event["skipped"] = "no bus server to restart (SocketCAN bus)"
        else:
            server.restart()
    elif fault.kind == "flood":
        orch.flood = Child("flood", ["-m", "harness.run.flood", "--bus", orch.spec, "--rate",
                                     str(fault.amount or 5000.0)],
                           orch.cfg.out_dir / "flood.log").start()
    elif fault.kind in ROGUE_ATTACKS:
        n = len(orch.rogues)
        args = ["-m", "harness.run.rogue", "--bus", orch.spec,
                "--attack", ROGUE_ATTACKS[fault.kind],
                "--summary", str(orch.cfg.out_dir / f"rogue{n}_summary.json")]
        if fault.kind == "rogue-flood":
            args += ["--rate", str(fault.amount)]
        elif fault.kind in {"rogue-replay", "rogue-sensor-replay"}:
            args += ["--record-s", str(fault.amount)]
        orch.rogues.append(Child("rogue", args, orch.cfg.out_dir / f"rogue{n}.log").start())
    orch.events.append(event)
    return server


def _scenario_end_s(plant_summary: dict[str, Any], duration_s: float) -> float:
    """Where a complete run ends, s: the plant's own end when it finished normally (the
    duration, or earlier at the end of the course), else the scenario duration."""
    if plant_summary.get("reason") == "finished" and "sim_time_s" in plant_summary:
        return min(float(plant_summary["sim_time_s"]), duration_s)
    return duration_s


def _secoc_rejected(*summaries: dict[str, Any]) -> dict[str, int]:
    """SecOC rejections of the plant and the controller, merged by reason."""
    out: dict[str, int] = {}
    for summary in summaries:
        for reason, n in (summary.get("secoc") or {}).get("rejected", {}).items():
            out[reason] = out.get(reason, 0) + int(n)
    return dict(sorted(out.items()))


def _rx_drops(plant: dict[str, Any], controller: dict[str, Any],
              hub: dict[str, Any] | None) -> dict[str, Any]:
    """Frames dropped by a bounded rx queue (docs/safety/queues.md): the controller's and
    the plant's by reason, and the hub's per node that lost any (a node that does not read,
    such as a flood process, loses its own)."""
    nodes = (hub or {}).get("nodes", [])
    return {"controller": controller.get("rx_drops", {}), "plant": plant.get("rx_drops", {}),
            "hub": {n["name"]: n["dropped"] for n in nodes if n.get("dropped")}}


def _whole_plots(out: Path) -> list[str]:
    """The plots in ``out`` written to their end (a PNG ends with its IEND chunk); one that
    a stop cut in the middle is removed. (Earlier runs' plots are cleared at the start.)"""
    try:
        from harness.viz.plots import PLOT_NAMES
    except ImportError:
        return []
    whole = []
    for name in PLOT_NAMES:
        path = out / name
        try:
            with path.open("rb") as f:
                f.seek(max(0, path.stat().st_size - 12))
                complete = b"IEND" in f.read()
        except OSError:
            continue
        if complete:
            whole.append(name)
        else:
            path.unlink(missing_ok=True)
    return whole


def _clear_previous_outputs(out: Path) -> None:
    """Remove the outputs of an earlier run in ``out`` that this run might not replace: the
    plots, recording and bus log its metrics.json lists (the bus log may be of another
    format), and metrics.json. A run that stops early must not sit beside the figures of a
    complete one. Nothing else in the directory is touched."""
    previous = _read_json(out / "metrics.json")
    names = [*(previous.get("plots") or []), previous.get("rrd"), previous.get("bus_log"),
             "run.rrd"]
    try:  # also plots whose writing a signal cut short (not listed anywhere)
        from harness.viz.plots import PLOT_NAMES

        names += list(PLOT_NAMES)
    except ImportError:  # the core install, without the harness extra: no plots to clear
        pass
    for name in names:
        if isinstance(name, str) and name and Path(name).name == name:  # a plain file name
            (out / name).unlink(missing_ok=True)
    (out / "metrics.json").unlink(missing_ok=True)


def _sim_time_reached_s(out: Path, recorder: BusRecorder | None) -> float:
    """Simulated s the plant reached: its summary's (written at its end, also on SIGTERM), else
    the last SYNC the recorder saw."""
    reached = _read_json(out / "plant_summary.json").get("sim_time_s")
    if isinstance(reached, int | float):
        return float(reached)
    return float(recorder.sim_time_s) if recorder is not None else 0.0


def _read_json(path: Path) -> dict[str, Any]:
    """A summary file, or {} if it is missing or unreadable (a killed process)."""
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError):
        return {}


def analyse_run(cfg: RunConfig, meta: dict[str, Any], live: Any = None) -> dict[str, Any]:
    """KPIs, plots and the rerun recording from the run directory; metrics.json always.
    ``live``: the live rerun view, given the whole run's events and KPIs at the end."""
    out = cfg.out_dir
    plant_summary = _read_json(out / "plant_summary.json")
    controller_summary = _read_json(out / "controller_summary.json")
    meta["plant_summary"] = plant_summary
    meta["controller_summary"] = controller_summary
    metrics: dict[str, Any] = dict(meta)
    metrics["secoc_rejected"] = _secoc_rejected(plant_summary, controller_summary)
    metrics["rx_drops"] = _rx_drops(plant_summary, controller_summary, meta.get("bus_hub"))
    metrics.setdefault("interrupted", False)
    # written first, so a signal or a kill during the analysis still leaves the run described
    _write_metrics(out, metrics)
    signalled_at = signals.received_at()
    budget = (metrics["interrupted"] and signalled_at is not None
              and signals.arm_deadline(signalled_at + INTERRUPT_ANALYSIS_S))
    try:
        if not metrics["interrupted"]:
            signals.check()  # a signal that came during the (shielded) cleanup stops here
        from harness.analysis.course import course_geometry, scenario_for
        from harness.analysis.kpi import compute_kpis, course_end_time_s
        from harness.analysis.run_data import load_run

        geo = course_geometry(scenario_for(cfg.scenario, cfg.mu, cfg.speed_kmh, cfg.params),
                              cfg.duration_s)
        run = load_run(out, meta={
            "rejections": {"plant": plant_summary.get("torque_rejections", {}),
                           "controller": controller_summary.get("rejections", {})},
            "scenario_end_s": _scenario_end_s(plant_summary, geo.duration_s),
            "comm_period_s": 0.01,
            "controller": cfg.controller,
            "mode": cfg.mode,  # lockstep: no wall-clock period jitter (kpi.py)
            "log_time": "sim" if cfg.mode == "lockstep" else "wall"})
        course_end_s = None
        if geo.course_end_arc_m > 0:
            course_end_s = course_end_time_s(run, geo.course_end_arc_m)
            course_end_s = math.inf if course_end_s is None else course_end_s
        run.meta["course_end_s"] = course_end_s
        metrics.update(compute_kpis(run, course_end_s=course_end_s))
        metrics.update(meta)
        _note_partial(metrics, run)
        from harness.analysis.verdicts import verdict_block
        course_end_arc = geo.course_end_arc_m if geo.course_end_arc_m > 0 else None
        metrics["verdicts"] = verdict_block(run, cones=geo.cones, lanes=geo.lanes,
                                            course_end_arc_m=course_end_arc,
                                            planned_end_s=run.meta["scenario_end_s"])
        if not run.truth_col("t_s").size:  # no row reached the trace: nothing to draw
            metrics["plots"] = []
        elif cfg.make_plots:
            from harness.viz.plots import write_plots
            metrics["plots"] = [p.name for p in write_plots(
                run, geo.boundaries, geo.ref_path, out, cones=geo.cones, lanes=geo.lanes,
                course_end_arc_m=course_end_arc, metrics=metrics)]
        if live is not None:
            live.finish(run, metrics)
        if cfg.make_rrd and run.truth_col("t_s").size:
            from harness.viz.rerun_log import write_rrd
            name = recording_name(cfg)
            rrd = write_rrd(run, geo.boundaries, geo.ref_path, out / "run.rrd",
                            recording_name=name, cones=geo.cones, metrics=metrics)
            metrics["rrd"] = rrd.name
    except signals.DeadlineReached:
        metrics["analysis_cut"] = (f"the analysis of the partial run stopped "
                                   f"{INTERRUPT_ANALYSIS_S:g} s after the signal")
        metrics["plots"] = _whole_plots(out)
    except KeyboardInterrupt as exc:  # SIGINT/SIGTERM during the analysis: stop it here
        metrics.update(interrupted=True, reason="interrupted",
                       analysis_cut=f"the analysis stopped at {exc or 'SIGINT'}")
    except Exception as exc:  # analysis must not lose the run: say why in metrics.json
        metrics["analysis_error"] = repr(exc)
    with signals.shielded():
        if budget:
            signals.disarm_deadline()
        _write_metrics(out, metrics)
    return metrics


def _write_metrics(out: Path, metrics: dict[str, Any]) -> None:
    """``out/metrics.json``, replaced whole (a reader never sees half a file)."""
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=2, default=str) + "\n")
    tmp.replace(out / "metrics.json")


def _note_partial(metrics: dict[str, Any], run: Any) -> None:
    """For an interrupted run: the simulated time the truth trace reached (the plant's own
    record, s), and the run's metadata carries the interrupt for the plots and rerun."""
    if not metrics.get("interrupted"):
        return
    t = run.truth_col("t_s")
    if t.size:
        metrics["sim_time_reached_s"] = float(t[-1])
    for key in ("interrupted", "sim_time_reached_s", "duration_planned_s"):
        run.meta[key] = metrics.get(key)



