"""A run's report: KPIs and verdicts, PNG plots and the rerun recording, after the run.

:func:`report_run` analyses a finished run (harness/analysis/run_metrics.py), draws its plots
(harness/viz/plots.py) and writes its rerun recording (harness/viz/rerun_log.py) as the run's
description asks, and always writes ``metrics.json``. :func:`run_and_report` is
``rhonn-harness run``: the run (harness/run/runner.py), then its report.

An interrupted run's report gets ``INTERRUPT_ANALYSIS_S`` wall seconds after the signal;
whatever does not fit is named in ``analysis_cut`` and a plot cut in the middle is removed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from can_db.process.errors import error_text
from harness.analysis.course import course_geometry, scenario_for
from harness.analysis.run_metrics import analyse_run, with_summaries
from harness.run import marker, signals
from harness.run.hil_bench import Bench
from harness.run.runner import (
    RunResult,
    recording_name,
    run_closed_loop,
    write_metrics,
)
from harness.run.spec import RunSpec
from harness.viz.plots import PLOT_NAMES, write_plots
from harness.viz.rerun_live import LiveRerun
from harness.viz.rerun_log import write_rrd

# What the analysis of an interrupted run (KPIs, plots, recording of the data up to the signal)
# may take, wall s after the signal; the rest is skipped and metrics.json says so.
INTERRUPT_ANALYSIS_S = 1.5
log = logging.getLogger("harness.run")


def start_live(spec: RunSpec) -> LiveRerun | None:
    """The live rerun view (None, with a note on stderr, if it cannot start)."""
    try:
        geo = course_geometry(scenario_for(spec.scenario, spec.mu, spec.speed_kmh,
                                           dict(spec.params)), spec.duration_s)
        live = LiveRerun(Path(spec.out_dir or "."), recording_name(spec), geo.boundaries,
                         geo.ref_path, geo.cones, web_port=spec.rerun_port)
    except Exception as exc:  # the run goes on without its live view
        log.warning("live rerun view not started: %s", exc)
        return None
    print(f"live rerun view: {live.url}", flush=True)
    return live


def run_and_report(spec: RunSpec, progress: Callable[[float], None] | None = None,
                   bench: Bench | None = None) -> RunResult:
    """Run (on ``bench``, or processes of its own), then KPIs, plots and recording as the
    spec asks; the run directory's marker is held until the report is written."""
    Path(spec.out_dir or ".").mkdir(parents=True, exist_ok=True)
    live = start_live(spec) if spec.rerun_live else None
    result = run_closed_loop(spec, progress, tap=live, bench=bench, hold_marker=True,
                             clear_also=PLOT_NAMES)
    try:
        log.info("analysing (KPIs, plots, recording) ...")
        result.metrics = report_run(spec, result.metrics, live)
    finally:
        if result.marker is not None:
            marker.release(result.marker)
    result.reason, result.live = result.metrics["reason"], live
    return result


def report_run(spec: RunSpec, meta: dict[str, Any], live: Any = None) -> dict[str, Any]:
    """KPIs, plots and the rerun recording from the run directory; metrics.json always.
    ``live``: the live rerun view, given the whole run's events and KPIs at the end."""
    out = Path(spec.out_dir or ".")
    metrics = with_summaries(out, meta)
    # written first, so a signal or a kill during the analysis still leaves the run described
    write_metrics(out, metrics)
    if metrics.get("bus_log_frames_lost"):
        log.warning("the bus log lost %d frames: the recorder fell behind (a storm, or a "
                    "busy machine in real time); the log of this run is incomplete",
                    metrics["bus_log_frames_lost"])
    signalled_at = signals.received_at()
    try:  # the one-shot deadline can land outside _analyse_and_draw's handlers: here
        if metrics["interrupted"] and signalled_at is not None:
            signals.arm_deadline(signalled_at + INTERRUPT_ANALYSIS_S)
        metrics = _analyse_and_draw(spec, meta, metrics, out, live)
        signals.disarm_deadline()
    except signals.DeadlineReached:
        metrics.update(_cut_at_deadline(out))
    with signals.shielded():
        signals.disarm_deadline()
        write_metrics(out, metrics)
    return metrics


def _analyse_and_draw(spec: RunSpec, meta: dict[str, Any], metrics: dict[str, Any], out: Path,
                      live: Any) -> dict[str, Any]:
    """KPIs, plots and recording; ``metrics`` (the run's summaries) extended with the KPIs, or
    with what stopped the analysis."""
    try:
        if not metrics["interrupted"]:
            signals.check()  # a signal that came during the (shielded) cleanup stops here
        analysis = analyse_run(spec, meta)
        metrics = analysis.metrics
        run, geo = analysis.run, analysis.geometry
        if not run.truth_col("t_s").size:  # no row reached the trace: nothing to draw
            metrics["plots"] = []
        elif spec.make_plots:
            metrics["plots"] = [p.name for p in write_plots(
                run, geo.boundaries, geo.ref_path, out, cones=geo.cones, lanes=geo.lanes,
                course_end_arc_m=analysis.course_end_arc_m, metrics=metrics)]
        if live is not None:
            live.finish(run, metrics)
        if spec.make_rrd and run.truth_col("t_s").size:
            rrd = write_rrd(run, geo.boundaries, geo.ref_path, out / "run.rrd",
                            recording_name=recording_name(spec), cones=geo.cones,
                            metrics=metrics)
            metrics["rrd"] = rrd.name
    except signals.DeadlineReached:
        metrics.update(_cut_at_deadline(out))
    except KeyboardInterrupt as exc:  # SIGINT/SIGTERM during the analysis: stop it here
        metrics.update(interrupted=True, reason="interrupted",
                       analysis_cut=f"the analysis stopped at {exc or 'SIGINT'}")
    except Exception as exc:  # analysis must not lose the run: say why in metrics.json
        metrics["analysis_error"] = error_text(exc)
    return metrics


def _cut_at_deadline(out: Path) -> dict[str, Any]:
    """What metrics.json says of an analysis the deadline after a signal stopped."""
    return {"analysis_cut": (f"the analysis of the partial run stopped "
                             f"{INTERRUPT_ANALYSIS_S:g} s after the signal"),
            "plots": whole_plots(out)}


def whole_plots(out: Path) -> list[str]:
    """The plots in ``out`` written to their end (a PNG ends with its IEND chunk); one that
    a stop cut in the middle is removed. (Earlier runs' plots are cleared at the start.)"""
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
