"""The analysis of one finished run: KPIs and verdicts from the files in its directory.

Reads what the run left (truth trace, bus log, controller timing, the processes' summaries)
and the run's description in ``metrics.json`` (harness/run/runner.py), and returns the
metrics: the description plus the KPIs (harness/analysis/kpi.py) and the verdict block
(harness/analysis/verdicts.py). Plots and the rerun recording are drawn from the same
:class:`RunAnalysis` by harness/report/run_report.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.analysis.course import CourseGeometry, course_geometry, scenario_for
from harness.analysis.kpi import compute_kpis, course_end_time_s
from harness.analysis.loop_health import apply_loop_verdict
from harness.analysis.run_data import RunData, load_run
from harness.analysis.verdicts import verdict_block
from harness.run.bus_logger import RECORDER_NODE
from harness.run.controller_config import mpc_period_s
from harness.run.hil_bench import read_json
from harness.run.spec import RunSpec

COMM_PERIOD_S = 0.01  # the DBC's communication cycle, s


@dataclass
class RunAnalysis:
    """A run's data, its course and its metrics (the KPIs included)."""

    run: RunData
    geometry: CourseGeometry
    metrics: dict[str, Any]

    @property
    def course_end_arc_m(self) -> float | None:
        """Arc length where the course ends, m (None: a scenario without a course end)."""
        return self.geometry.course_end_arc_m if self.geometry.course_end_arc_m > 0 else None


def _scenario_end_s(plant_summary: dict[str, Any], duration_s: float) -> float:
    """Where a complete run ends, s: the plant's own end when it finished normally (the
    duration, or earlier at the end of the course), else the scenario duration."""
    if plant_summary.get("reason") == "finished" and "sim_time_s" in plant_summary:
        return min(float(plant_summary["sim_time_s"]), duration_s)
    return duration_s


def secoc_rejected(*summaries: dict[str, Any]) -> dict[str, int]:
    """SecOC rejections of the plant and the controller, merged by reason."""
    out: dict[str, int] = {}
    for summary in summaries:
        for reason, n in (summary.get("secoc") or {}).get("rejected", {}).items():
            out[reason] = out.get(reason, 0) + int(n)
    return dict(sorted(out.items()))


def rx_drops(plant: dict[str, Any], controller: dict[str, Any],
             hub: dict[str, Any] | None, recorder_socket: int | None = None
             ) -> dict[str, Any]:
    """Frames dropped by a bounded rx queue (docs/safety/queues.md): the controller's and
    the plant's by reason; the hub's per node that lost any (a node that does not read,
    such as a flood process, loses its own); on SocketCAN the kernel's per node socket
    (``socket``: controller, plant, bus-recorder; the controller's counts its process)."""
    nodes = (hub or {}).get("nodes", [])
    socket = {name: int(n) for name, n in (
        ("controller", _socket_drops(controller)), ("plant", _socket_drops(plant)),
        (RECORDER_NODE, recorder_socket)) if isinstance(n, int)}
    out = {"controller": controller.get("rx_drops", {}), "plant": plant.get("rx_drops", {}),
           "hub": {n["name"]: n["dropped"] for n in nodes if n.get("dropped")}}
    if socket:
        out["socket"] = socket
    return out


def _socket_drops(summary: dict[str, Any]) -> int | None:
    """The kernel's drop count of a process's SocketCAN socket (its summary's bus_stats)."""
    value = (summary.get("bus_stats") or {}).get("rx_dropped")
    return value if isinstance(value, int) else None


def bus_log_frames_lost(hub: dict[str, Any] | None,
                        recorder_socket: int | None = None) -> int | None:
    """Frames the bus recorder did not get: the local hub's drops for its node, or the
    kernel's for its SocketCAN socket (a real-time recorder that fell behind, a storm);
    None where the bus keeps no such count (the websocket server)."""
    nodes = [n for n in (hub or {}).get("nodes", []) if n.get("name") == RECORDER_NODE]
    if nodes:
        return sum(int(n.get("dropped", 0)) for n in nodes)
    return recorder_socket


def with_summaries(out: Path, meta: dict[str, Any]) -> dict[str, Any]:
    """The run's description plus its processes' summaries and what they counted (no KPI:
    cheap, written before the analysis so a stopped analysis still leaves them)."""
    plant_summary = read_json(out / "plant_summary.json")
    controller_summary = read_json(out / "controller_summary.json")
    metrics: dict[str, Any] = dict(meta)
    metrics["plant_summary"] = plant_summary
    metrics["controller_summary"] = controller_summary
    metrics["secoc_rejected"] = secoc_rejected(plant_summary, controller_summary)
    recorder_socket = meta.get("bus_recorder_rx_dropped")
    metrics["rx_drops"] = rx_drops(plant_summary, controller_summary, meta.get("bus_hub"),
                                   recorder_socket)
    metrics["bus_log_frames_lost"] = bus_log_frames_lost(meta.get("bus_hub"), recorder_socket)
    metrics.setdefault("interrupted", False)
    return metrics


def analyse_run(spec: RunSpec, meta: dict[str, Any]) -> RunAnalysis:
    """KPIs and verdicts of the run in ``spec.out_dir`` whose description is ``meta``."""
    out = Path(spec.out_dir or ".")
    metrics = with_summaries(out, meta)
    plant_summary = metrics["plant_summary"]
    controller_summary = metrics["controller_summary"]
    geo = course_geometry(scenario_for(spec.scenario, spec.mu, spec.speed_kmh,
                                       dict(spec.params)), spec.duration_s)
    run = load_run(out, meta={
        "rejections": {"plant": plant_summary.get("torque_rejections", {}),
                       "controller": controller_summary.get("rejections", {})},
        "scenario_end_s": _scenario_end_s(plant_summary, geo.duration_s),
        "comm_period_s": COMM_PERIOD_S,
        # the MPC period, s: the lag of dM_max_change_per_period_Nm (smoothness.py)
        "ctrl_period_s": mpc_period_s(spec.controller_config, dict(spec.controller_overrides)),
        "controller": spec.controller,
        "mode": spec.mode,  # lockstep: no wall-clock period jitter (kpi.py)
        "log_time": "sim" if spec.mode == "lockstep" else "wall"})
    course_end_s = None
    if geo.course_end_arc_m > 0:
        course_end_s = course_end_time_s(run, geo.course_end_arc_m)
        course_end_s = math.inf if course_end_s is None else course_end_s
    run.meta["course_end_s"] = course_end_s
    metrics.update(compute_kpis(run, course_end_s=course_end_s))
    metrics.update(meta)
    note_partial(metrics, run)
    analysis = RunAnalysis(run, geo, metrics)
    metrics["verdicts"] = verdict_block(run, cones=geo.cones, lanes=geo.lanes,
                                        course_end_arc_m=analysis.course_end_arc_m,
                                        planned_end_s=run.meta["scenario_end_s"])
    apply_loop_verdict(metrics, faults_injected=faults_injected(spec))
    return analysis


def faults_injected(spec: RunSpec) -> bool:
    """True when the run injects faults on purpose (frame or core faults, a killed
    controller, extra --fault arguments): its fallbacks and rejections are expected."""
    extra = (*spec.controller_extra_args, *spec.plant_extra_args)
    return bool(spec.faults) or spec.kill_controller_at_s is not None \
        or any(a == "--fault" or a.startswith("--fault=") for a in extra)


def note_partial(metrics: dict[str, Any], run: RunData) -> None:
    """For an interrupted run: the simulated time the truth trace reached (the plant's own
    record, s), and the run's metadata carries the interrupt for the plots and rerun."""
    if not metrics.get("interrupted"):
        return
    t = run.truth_col("t_s")
    if t.size:
        metrics["sim_time_reached_s"] = float(t[-1])
    for key in ("interrupted", "sim_time_reached_s", "duration_planned_s"):
        run.meta[key] = metrics.get(key)
