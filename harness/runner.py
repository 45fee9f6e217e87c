"""One closed-loop run: bus (server if needed), controller process, plant process, recorder.

Order: resolve the bus → start the bus recorder → start the controller (it must be listening
before the first SYNC) → start the plant → wait for the plant to finish → drain the bus →
SIGTERM the controller → stop the recorder and the server. Anything that goes wrong (a child
dies, Ctrl-C, a timeout) still stops every child and still writes ``metrics.json`` with the
reason. Afterwards: KPIs, PNG plots and one rerun recording from the files in DIR.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from can_db.bus import resolve_auto
from can_db.server import BusServer
from harness.bus_logger import BusRecorder
from harness.procs import Child, ChildStartError


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
    wall_timeout_s: float = 600.0
    kill_controller_at_s: float | None = None  # wall seconds after the plant starts
    make_plots: bool = True
    make_rrd: bool = True


@dataclass
class RunResult:
    """Where things are and what happened."""

    out_dir: Path
    metrics: dict[str, Any]
    reason: str
    plant_code: int | None
    controller_code: int | None


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
        args += ["--param", f"{key}={value}"]
    return args


def _controller_args(cfg: RunConfig, spec: str) -> list[str]:
    args = ["-m", "controller.process", "--bus", spec, "--controller", cfg.controller,
            "--mode", cfg.controller_mode, "--timing",
            str(cfg.out_dir / "controller_timing.csv")]
    if cfg.controller_config:
        args += ["--config", cfg.controller_config]
    return args


def run_closed_loop(cfg: RunConfig) -> RunResult:
    """Run the processes, then analyse; never leaves a child behind."""
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    server: BusServer | None = None
    recorder: BusRecorder | None = None
    controller = plant = None
    reason = "not started"
    controller_lost_at: float | None = None
    spec = cfg.bus
    wall_start = time.monotonic()
    try:
        if cfg.bus == "auto":
            spec, server = resolve_auto()
        recorder = BusRecorder(spec, cfg.out_dir / "bus.blf").start()
        controller = Child("controller", _controller_args(cfg, spec),
                           cfg.out_dir / "controller.log").start()
        plant = Child("plant", _plant_args(cfg, spec), cfg.out_dir / "plant.log").start()
        plant_started = time.monotonic()
        reason = "running"
        while True:
            code = plant.poll()
            if code is not None:
                reason = "finished" if code == 0 else f"plant exited with code {code}"
                break
            if controller.poll() is not None and controller_lost_at is None:
                controller_lost_at = time.monotonic() - plant_started
            if (cfg.kill_controller_at_s is not None and controller_lost_at is None
                    and time.monotonic() - plant_started >= cfg.kill_controller_at_s):
                controller.kill()
            if time.monotonic() - wall_start > cfg.wall_timeout_s:
                reason = f"wall timeout after {cfg.wall_timeout_s:.0f} s"
                break
            time.sleep(0.05)
    except ChildStartError as exc:
        reason = f"start failed: {exc}"
    except KeyboardInterrupt:
        reason = "interrupted"
    finally:
        if recorder is not None:
            recorder.drain()
        plant_code = plant.stop() if plant is not None else None
        controller_code = controller.stop() if controller is not None else None
        if recorder is not None:
            recorder.stop()
        if server is not None:
            server.stop()
    meta = {
        "scenario": cfg.scenario, "controller": cfg.controller,
        "bus": spec.split(":")[0] if spec else cfg.bus, "bus_spec": cfg.bus, "mode": cfg.mode,
        "controller_mode": cfg.controller_mode, "mu": cfg.mu, "speed_kmh": cfg.speed_kmh,
        "seed": cfg.seed, "software_version": software_version(), "reason": reason,
        "plant_exit_code": plant_code, "controller_exit_code": controller_code,
        "controller_lost_at_wall_s": controller_lost_at,
        "wall_time_s": time.monotonic() - wall_start,
        "bus_frames_recorded": recorder.frames if recorder is not None else 0,
    }
    metrics = analyse_run(cfg, meta)
    return RunResult(cfg.out_dir, metrics, reason, plant_code, controller_code)


def _scenario_end_s(plant_summary: dict[str, Any], duration_s: float) -> float:
    """Where a complete run ends, s: the plant's own end when it finished normally (the
    duration, or earlier at the end of the course), else the scenario duration."""
    if plant_summary.get("reason") == "finished" and "sim_time_s" in plant_summary:
        return min(float(plant_summary["sim_time_s"]), duration_s)
    return duration_s


def analyse_run(cfg: RunConfig, meta: dict[str, Any]) -> dict[str, Any]:
    """KPIs, plots and the rerun recording from the run directory; metrics.json always."""
    out = cfg.out_dir
    summary_path = out / "plant_summary.json"
    plant_summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    meta["plant_summary"] = plant_summary
    metrics: dict[str, Any] = dict(meta)
    try:
        from harness.course import course_geometry, scenario_for
        from harness.kpi import compute_kpis, course_end_time_s
        from harness.run_data import load_run

        geo = course_geometry(scenario_for(cfg.scenario, cfg.mu, cfg.speed_kmh, cfg.params),
                              cfg.duration_s)
        run = load_run(out, meta={
            "rejections": {"plant": plant_summary.get("torque_rejections", {})},
            "scenario_end_s": _scenario_end_s(plant_summary, geo.duration_s),
            "comm_period_s": 0.01,
            "controller": cfg.controller})
        course_end_s = None
        if geo.course_end_arc_m > 0:
            course_end_s = course_end_time_s(run, geo.course_end_arc_m)
            course_end_s = math.inf if course_end_s is None else course_end_s
        run.meta["course_end_s"] = course_end_s
        metrics.update(compute_kpis(run, course_end_s=course_end_s))
        metrics.update(meta)
        if cfg.make_plots:
            from harness.plots import write_plots
            metrics["plots"] = [p.name for p in write_plots(
                run, geo.boundaries, geo.ref_path, out, cones=geo.cones)]
        if cfg.make_rrd:
            from harness.rerun_log import write_rrd
            name = f"{cfg.scenario}-{cfg.controller}-mu{cfg.mu}-v{cfg.speed_kmh}-s{cfg.seed}"
            rrd = write_rrd(run, geo.boundaries, geo.ref_path, out / "run.rrd",
                            recording_name=name, cones=geo.cones)
            metrics["rrd"] = rrd.name
    except Exception as exc:  # analysis must not lose the run: say why in metrics.json
        metrics["analysis_error"] = repr(exc)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str) + "\n")
    return metrics



