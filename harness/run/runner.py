"""One closed-loop run on a bench: what it ran and what the processes did, in ``metrics.json``.

:func:`run_closed_loop` checks the run, claims its directory, carries the run out on a bench
(harness/run/hil_bench.py: a warm one given by the caller, or one started for this run and stopped
after it) and writes ``metrics.json`` with the run's description and its processes' end. It
analyses nothing: KPIs and verdicts (harness/analysis/run_metrics.py), plots and the rerun
recording (harness/report/run_report.py) are separate steps after it. Anything that goes wrong
(a child dies, Ctrl-C, a time-out) still stops the run's children and still writes
``metrics.json`` with the reason.

SecOC is on by default (``secoc=False`` turns it off): both processes get ``--secoc`` and the
key source (``secoc_keys``; default: the RHONN_SECOC_KEY_* variables when set, else the public
CI test key, which is fine for a simulation). The plant's SecOC trip counter is the one in
its state directory (``$RHONN_STATE_DIR/plant/secoc_trip``, can_db/secoc_keys.py): +1 at
every run's start and at a ``restart-plant``, never reset, so a recording of an earlier run
is stale in every later one (a lockstep run's data frames are the same run after run; its
authenticators' MACs and SYNC_AUTH.TRIP differ with the trip).
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from can_db.codec import Codec
from can_db.faults import FaultInjector
from can_db.process.errors import error_text
from can_db.secoc_keys import TEST_KEY_SOURCE, load_keys, resolve_key_source
from harness.run import marker
from harness.run.hil_bench import (
    Bench,
    BusTap,
    RunOutcome,
    check_target,
    read_json,
    route_frame_faults,
    run_faults,
)
from harness.run.spec import RunSpec
from plant_sim.scenario import ScenarioError, is_scenario_file, load_scenario, scenario_label

log = logging.getLogger("harness.run")


def software_version() -> str:
    """Installed rhonn-tv version (or 'dev')."""
    try:
        return version("rhonn-tv")
    except PackageNotFoundError:
        return "dev"


@dataclass
class RunResult:
    """Where things are and what happened."""

    out_dir: Path
    metrics: dict[str, Any]
    reason: str
    plant_code: int | None
    controller_code: int | None
    live: Any = None  # the live rerun view (harness.viz.rerun_live.LiveRerun) if one ran
    marker: Path | None = None  # the run directory's marker, when the caller holds it


def _scenario_of(spec: RunSpec) -> Any:
    params = {k: _number(v) for k, v in spec.params}
    return load_scenario(spec.scenario, mu=spec.mu, speed_kmh=spec.speed_kmh, **params)


def recording_name(spec: RunSpec) -> str:
    """``SCENARIO-CONTROLLER-muX-vY-sN`` with the friction and speed the run really used
    (the scenario's own when not overridden)."""
    mu, speed = spec.mu, spec.speed_kmh
    if mu is None or speed is None:
        try:
            scen = _scenario_of(spec)
            mu = scen.mu if mu is None else mu
            speed = scen.speed_kmh if speed is None else speed
        except (KeyError, ValueError, TypeError, ScenarioError):
            pass
    mu_s = "?" if mu is None else f"{mu:g}"
    v_s = "?" if speed is None else f"{speed:g}"
    return f"{scenario_label(spec.scenario)}-{spec.controller}-mu{mu_s}-v{v_s}-s{spec.seed}"


def planned_duration_s(spec: RunSpec) -> float | None:
    """Simulated seconds the run is meant to last: the scenario's, cut at ``duration_s`` (the
    plant stops at the earlier of the two)."""
    try:
        own = float(_scenario_of(spec).duration_s)
    except (KeyError, ValueError, TypeError, ScenarioError):
        return None if spec.duration_s is None else float(spec.duration_s)
    return own if spec.duration_s is None else min(own, float(spec.duration_s))


def _number(value: Any) -> Any:
    try:
        return float(value)
    except (TypeError, ValueError):
        return value


_TEST_KEY_NOTED: list[bool] = []


def _note_test_key() -> None:
    """Say once per process that the public CI test key is in use."""
    if not _TEST_KEY_NOTED:
        _TEST_KEY_NOTED.append(True)
        log.info("SecOC on (key: public test key; simulation only)")


def check_run(spec: RunSpec) -> None:
    """What can be checked without starting anything: the faults (FaultSpecError), the
    target (ValueError) and the SecOC keys (SecOcKeyError)."""
    faults = run_faults(spec)
    FaultInjector(Codec(), faults)  # validates message and signal names
    route_frame_faults(faults, Codec(), lockstep=spec.mode == "lockstep")
    check_target(spec)  # ValueError: a target the run cannot use
    if spec.secoc:
        load_keys(resolve_key_source(spec.secoc_keys))
        if resolve_key_source(spec.secoc_keys) == TEST_KEY_SOURCE:
            _note_test_key()


def run_closed_loop(spec: RunSpec, progress: Callable[[float], None] | None = None,
                    tap: BusTap | None = None, bench: Bench | None = None,
                    hold_marker: bool = False, clear_also: tuple[str, ...] = ()
                    ) -> RunResult:
    """Carry out one run into ``spec.out_dir`` and write its ``metrics.json`` (no analysis).

    ``progress``: called about every 0.5 s (wall) with the simulated time reached, s.
    ``tap``: a live view fed every recorded frame. ``bench``: a warm bench to run on (None:
    processes of this run's own). ``hold_marker``: leave the run directory's marker for the
    caller to release after its analysis (``marker.release(result.marker)``).
    ``clear_also``: file names of an earlier run's outputs to remove with the rest.
    """
    if spec.out_dir is None:
        raise ValueError("RunSpec.out_dir: a run needs its directory")
    out = spec.out_dir
    out.mkdir(parents=True, exist_ok=True)
    check_run(spec)
    wall_start = time.monotonic()
    in_progress = marker.claim(out)  # RunDirBusyError if a live harness writes there
    try:
        clear_previous_outputs(out, also=clear_also)
        own = bench is None
        bench = bench or Bench(out, bus=spec.bus, rt=spec.rt,
                               controller_cpu=spec.controller_cpu, warm=False,
                               bus_start_timeout_s=spec.bus_start_timeout_s)
        try:
            outcome = bench.run(spec, _heartbeat(in_progress, progress), tap)
        except KeyboardInterrupt:  # a signal between a failed attempt and its retry
            if own:
                bench.close(1.0)
            outcome = RunOutcome("interrupted", True, None, None, None, [], 0, 0, None, 0.0,
                                 spec.bus, None)
        metrics = run_meta(spec, outcome, time.monotonic() - wall_start)
        write_metrics(out, metrics)
        log.info("run %s after %.1f s", outcome.reason, metrics["wall_time_s"])
        first = (outcome.bench or {}).get("first_attempt_reason")
        if first:
            log.warning("this run is a second attempt: the first one failed (%s); its files "
                        "are in %s", first, out / str(outcome.bench.get("first_attempt_dir")))
    finally:
        if not hold_marker:
            marker.release(in_progress)
    return RunResult(out, metrics, outcome.reason, outcome.plant_code,
                     outcome.controller_code, marker=in_progress if hold_marker else None)


def _heartbeat(in_progress: Path, progress: Callable[[float], None] | None
               ) -> Callable[[float], None]:
    """The bench's progress call (every 0.5 s wall): the marker says the harness is alive,
    then the caller's own ``progress``."""
    def beat(sim_time_s: float) -> None:
        marker.touch(in_progress)
        if progress is not None:
            progress(sim_time_s)
    return beat


def run_meta(spec: RunSpec, outcome: RunOutcome, wall_s: float) -> dict[str, Any]:
    """The description of a run and of what its processes did (the first part of
    ``metrics.json``; the analysis adds the KPIs)."""
    out = Path(spec.out_dir or ".")
    plant_summary = read_json(out / "plant_summary.json")
    return {
        "scenario": spec.scenario, "controller": spec.controller,
        # a scenario file: its stem, and where it is (metrics "scenario" is as given)
        "scenario_name": scenario_label(spec.scenario),
        "scenario_file": str(Path(spec.scenario).absolute())
        if is_scenario_file(spec.scenario) else None,
        "bus": outcome.bus_spec.split(":")[0], "bus_spec": spec.bus, "mode": spec.mode,
        "controller_mode": spec.controller_mode, "mu": spec.mu, "speed_kmh": spec.speed_kmh,
        "seed": spec.seed, "software_version": software_version(), "reason": outcome.reason,
        "params": {k: v for k, v in spec.params}, "run_key": spec.key(),
        # the controller's configuration: what the analysis reads again (its MPC period)
        "controller_config": _config_as_given(spec.controller_config),
        "controller_overrides": {k: v for k, v in spec.controller_overrides},
        "duration_s": spec.duration_s,
        "secoc": spec.secoc,
        "target": spec.target,
        "controller_cpu": outcome.own_cpu,
        "faults": list(spec.faults), "fault_events": outcome.fault_events,
        "plant_exit_code": outcome.plant_code, "controller_exit_code": outcome.controller_code,
        "controller_lost_at_sim_s": outcome.controller_lost_at_s,
        "wall_time_s": wall_s,
        "loop_wall_s": plant_summary.get("loop_wall_s"),
        # cycles without a fresh command that held the last one (PlantNode, plant_sim/node.py)
        "command_held_cycles": plant_summary.get("held_cycles"),
        "bus_frames_recorded": outcome.frames_recorded,
        "bus_log_released_early": outcome.released_early,
        "bus_hub": read_json(out / "bus_hub_stats.json") or None,
        "bus_recorder_rx_dropped": outcome.recorder_rx_dropped,
        "files_not_written": outcome.files_not_written,
        "bus_log": f"bus.{spec.log_format}",
        "bus_log_time_base": outcome.log_time_base,
        "interrupted": outcome.interrupted,
        "sim_time_reached_s": _sim_time_reached_s(plant_summary, outcome),
        "duration_planned_s": planned_duration_s(spec),
        "bench": outcome.bench,
    }


def _config_as_given(config: str | None) -> str | None:
    """A controller configuration file as an absolute path (the run directory is read again
    from elsewhere); a packaged name as it is."""
    if config and Path(config).is_file():
        return str(Path(config).absolute())
    return config


def spec_of_run(out_dir: Path, meta: dict[str, Any]) -> RunSpec:
    """The spec of the run whose ``metrics.json`` is ``meta``, as far as the analysis of its
    directory needs it (scenario, friction, speed, duration, controller and its
    configuration, mode, faults). A run directory written before the controller's
    configuration was recorded reads as one with the default configuration."""
    def _opt_float(key: str) -> float | None:
        value = meta.get(key)
        return float(value) if isinstance(value, int | float) else None

    duration = _opt_float("duration_s")
    # a scenario file: where it is (metrics "scenario" is the path as given, maybe relative
    # to where the run started)
    scenario = meta.get("scenario_file") or meta["scenario"]
    return RunSpec(scenario=str(scenario), controller=str(meta["controller"]),
                   out_dir=Path(out_dir), seed=int(meta.get("seed") or 0),
                   mu=_opt_float("mu"), speed_kmh=_opt_float("speed_kmh"),
                   duration_s=duration if duration is not None
                   else _opt_float("duration_planned_s"),
                   params=dict(meta.get("params") or {}),
                   faults=tuple(meta.get("faults") or ()),
                   controller_config=meta.get("controller_config"),
                   controller_overrides=dict(meta.get("controller_overrides") or {}),
                   mode=str(meta.get("mode") or "lockstep"),
                   controller_mode=str(meta.get("controller_mode") or "lockstep"),
                   secoc=bool(meta.get("secoc", True)),
                   log_format=str(meta.get("bus_log") or "bus.blf").rsplit(".", 1)[-1])


def clear_previous_outputs(out: Path, also: tuple[str, ...] = ()) -> None:
    """Remove the outputs of an earlier run in ``out`` that this run might not replace: the
    plots, recording and bus log its metrics.json lists (the bus log may be of another
    format), ``also``, and metrics.json. A run that stops early must not sit beside the
    figures of a complete one. Nothing else in the directory is touched."""
    previous = read_json(out / "metrics.json")
    names = [*(previous.get("plots") or []), previous.get("rrd"), previous.get("bus_log"),
             "run.rrd", *also]
    for name in names:
        if isinstance(name, str) and name and Path(name).name == name:  # a plain file name
            (out / name).unlink(missing_ok=True)
    (out / "metrics.json").unlink(missing_ok=True)


def _sim_time_reached_s(plant_summary: dict[str, Any], outcome: RunOutcome) -> float:
    """Simulated s the plant reached: its summary's (written at its end, also on SIGTERM),
    else the last SYNC the recorder saw."""
    reached = plant_summary.get("sim_time_s")
    if isinstance(reached, int | float):
        return float(reached)
    return float(outcome.sim_time_s)


def write_metrics(out: Path, metrics: dict[str, Any]) -> bool:
    """``out/metrics.json``, replaced whole (a reader never sees half a file). On a write
    error (disk full) the previous metrics.json, if any, stays, the error is logged with the
    run's reason and ``metrics["metrics_not_written"]`` says why; returns False."""
    tmp = out / "metrics.json.tmp"
    try:
        tmp.write_text(json.dumps(metrics, indent=2, default=str) + "\n")
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        why = error_text(exc)
        metrics["metrics_not_written"] = why
        log.error("cannot write %s/metrics.json (%s); the run's reason: %s", out, why,
                  metrics.get("reason"))
        return False
    tmp.replace(out / "metrics.json")
    return True
