"""Write one run as a rerun (0.41) recording file with a saved blueprint.

Only the SDK's file sink is used (``RecordingStream.save``): no viewer, no network. Time series
go through ``send_columns`` (one call per entity, columnar), so a 20 s run (2000 cycles) is
written in a fraction of a second. Timelines: ``sim_time`` (duration, s) and ``cycle``
(sequence, the plant's SYNC cycle).

Entity tree::

    /plant/...        truth states (velocity, yaw_rate, beta, accel, swa, torque, …)
    /plant/trajectory 2-D top view: course lines/cones, reference path, driven path, vehicle
    /controller/...   ΔM, yaw_rate/{ref,actual}, beta/{ref,actual}, status/*, torque_cmd/*
    /bus/...          timing/* (period, jitter, step, turnaround, compute time), frame_age_ms,
                      deadline_misses (cumulative), rejections/<reason> (cumulative)
    /log              TextLog of mode changes, faults, spin, invalid-command periods, misses
    /summary          TextDocument with the run's KPIs

rerun's 2-D view draws +y downwards (image convention); the top view is therefore logged in
display coordinates (X, −Y) so that "left" (+Y, ISO 8855) appears up. Numeric values of Y are
in the truth trace and in /plant scalars, unchanged.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from harness.analysis.kpi import compute_kpis
from harness.analysis.run_data import REJECTED_KEY, RunData

APPLICATION_ID = "rhonn_tv"
DEG = 180.0 / math.pi
WHEELS = ("fl", "fr", "rl", "rr")
DEFAULT_PERIOD_S = 0.01
INFO, WARN, ERROR = "INFO", "WARN", "ERROR"  # rerun TextLog levels
#: CTRL_STATUS.FAULT_BITS meaning, bit 0 first (from the DBC comment).
FAULT_BIT_NAMES = ("sensor frames invalid/timed out", "driver frame invalid/timed out",
                   "sync lost", "solver fallback", "non-finite input rejected",
                   "learning reset", "torque envelope clipped", "rx overload")

HOW_TO_OPEN = (
    "Open a run's recording with the rerun viewer of the same version as the SDK "
    "(rerun-sdk 0.41, installed with the project): first run `rerun analytics disable` once "
    "(the viewer otherwise sends anonymous usage data), then `rerun DIR/run.rrd` opens the "
    "native viewer with the saved layout (trajectory as a band on top; event log and KPIs "
    "below on the left; tabs "
    "'Vehicle & control', 'Plant states' and 'Timing & bus' on the right; pick the `sim_time` "
    "or `cycle` timeline at the bottom). Several runs can be compared by opening their files "
    "together (`rerun a/run.rrd b/run.rrd`). On a machine without a display, serve the web "
    "viewer on the loopback interface only: `rerun --serve-web --bind 127.0.0.1 DIR/run.rrd` "
    "and browse to the printed http://127.0.0.1 address (tunnel it with `ssh -L` if remote); "
    "never bind to all interfaces. If the layout was changed by hand, 'Reset blueprint' "
    "restores it."
)


@functools.lru_cache(maxsize=1)
def _choices() -> dict[str, dict[int, str]]:
    """Value tables of CTRL_STATUS (MODE, QP_STATUS, CONTROLLER_ID) from the DBC."""
    from can_db.codec import Codec

    msg = Codec().database.get_message_by_name("CTRL_STATUS")
    out: dict[str, dict[int, str]] = {}
    for sig in msg.signals:
        if sig.choices:
            out[sig.name] = {int(k): str(v) for k, v in sig.choices.items()}
    return out


class _Writer:
    """Columnar scalar logging on the two timelines, skipping rows without a valid time."""

    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rec = rec

    def scalars(self, path: str, t: np.ndarray, cycle: np.ndarray, values: np.ndarray,
                label: str, color: Sequence[int] | None = None) -> int:
        t = np.asarray(t, dtype=float)
        cycle = np.asarray(cycle, dtype=float)
        values = np.asarray(values, dtype=float)
        if not (t.size == cycle.size == values.size) or values.size == 0:
            return 0
        ok = np.isfinite(t) & np.isfinite(cycle) & (cycle >= 0) & np.isfinite(values)
        if not ok.any():
            return 0
        self.rec.log(path, rr.SeriesLines(names=label, colors=color), static=True)
        self.rec.send_columns(path, indexes=self.index(t[ok], cycle[ok]),
                              columns=rr.Scalars.columns(scalars=values[ok]))
        return int(ok.sum())

    @staticmethod
    def index(t: np.ndarray, cycle: np.ndarray) -> list[rr.TimeColumn]:
        return [rr.TimeColumn("sim_time", duration=np.asarray(t, dtype=float)),
                rr.TimeColumn("cycle", sequence=np.asarray(cycle, dtype=np.int64))]


_BLUE, _RED, _GREEN, _ORANGE, _PURPLE, _GRAY = (
    (31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189),
    (127, 127, 127))
_WHEEL_COLORS = (_BLUE, _ORANGE, _GREEN, _RED)


def _bus(run: RunData, msg: str) -> tuple[np.ndarray, np.ndarray]:
    return (run.bus_sig(msg, "sim_time_s").astype(float), run.bus_sig(msg, "cycle").astype(float))


def _log_plant(w: _Writer, run: RunData) -> None:
    t, c = run.truth_col("t_s"), run.truth_col("cycle")
    tc = run.truth_col
    w.scalars("/plant/velocity/vx", t, c, tc("vx_mps"), "vx [m/s]", _BLUE)
    w.scalars("/plant/velocity/vy", t, c, tc("vy_mps"), "vy [m/s]", _ORANGE)
    w.scalars("/plant/yaw_rate", t, c, tc("yaw_rate_radps") * DEG, "yaw rate [deg/s]", _BLUE)
    w.scalars("/plant/beta", t, c, tc("beta_rad") * DEG, "β [deg]", _BLUE)
    w.scalars("/plant/accel/ax", t, c, tc("ax_mps2"), "ax [m/s²]", _BLUE)
    w.scalars("/plant/accel/ay", t, c, tc("ay_mps2"), "ay [m/s²]", _ORANGE)
    w.scalars("/plant/swa", t, c, tc("swa_rad") * DEG, "steering-wheel angle [deg]", _BLUE)
    w.scalars("/plant/lateral_dev", t, c, tc("lateral_dev_m"), "lateral deviation [m]", _BLUE)
    w.scalars("/plant/spun", t, c, tc("spun"), "spun (0/1)", _RED)
    w.scalars("/plant/cmd_valid", t, c, tc("cmd_valid"), "command valid (0/1)", _GREEN)
    w.scalars("/plant/stab_enable", t, c, tc("stab_enable"), "stab. enable (0/1)", _GRAY)
    for wheel, color in zip(WHEELS, _WHEEL_COLORS, strict=True):
        w.scalars(f"/plant/torque/{wheel}", t, c, tc(f"tcmd_{wheel}"),
                  f"T applied {wheel.upper()} [N·m]", color)
        w.scalars(f"/plant/torque_actual/{wheel}", t, c, tc(f"tact_{wheel}"),
                  f"T motor {wheel.upper()} [N·m]", color)


def _log_controller(w: _Writer, run: RunData) -> None:
    t, c = run.truth_col("t_s"), run.truth_col("cycle")
    tr, cr = _bus(run, "CTRL_REFS")
    w.scalars("/controller/delta_m", tr, cr, run.bus_sig("CTRL_REFS", "DELTA_M"),
              "ΔM [N·m]", _PURPLE)
    w.scalars("/controller/yaw_rate/ref", tr, cr, run.bus_sig("CTRL_REFS", "YAW_RATE_REF"),
              "yaw-rate ref [deg/s]", _RED)
    w.scalars("/controller/yaw_rate/actual", t, c, run.truth_col("yaw_rate_radps") * DEG,
              "yaw rate actual [deg/s]", _BLUE)
    w.scalars("/controller/beta/ref", tr, cr, run.bus_sig("CTRL_REFS", "BETA_REF"),
              "β ref [deg]", _RED)
    w.scalars("/controller/beta/actual", t, c, run.truth_col("beta_rad") * DEG,
              "β actual [deg]", _BLUE)
    ts, cs = _bus(run, "CTRL_STATUS")
    for sig, path, label, color in (("MODE", "mode", "mode", _BLUE),
                                    ("QP_ITER", "qp_iter", "QP iterations", _ORANGE),
                                    ("QP_STATUS", "qp_status", "QP status", _RED),
                                    ("FAULT_BITS", "fault_bits", "fault bits", _GRAY)):
        w.scalars(f"/controller/status/{path}", ts, cs, run.bus_sig("CTRL_STATUS", sig),
                  label, color)
    tt, ct = _bus(run, "WHEEL_TORQUE_CMD")
    for wheel, color in zip(WHEELS, _WHEEL_COLORS, strict=True):
        w.scalars(f"/controller/torque_cmd/{wheel}", tt, ct,
                  run.bus_sig("WHEEL_TORQUE_CMD", f"TQ_{wheel.upper()}"),
                  f"T cmd {wheel.upper()} [N·m]", color)
    w.scalars("/controller/status/mpc_update", run.timing_col("sim_time_s"),
              run.timing_col("cycle"), run.timing_col("mpc_update"), "MPC step ran (0/1)",
              _GREEN)


def _log_bus(w: _Writer, run: RunData) -> None:
    nominal_us = float(run.meta.get("comm_period_s", DEFAULT_PERIOD_S)) * 1e6
    t, c = run.timing_col("sim_time_s"), run.timing_col("cycle")
    period = run.timing_col("period_us")
    w.scalars("/bus/timing/period_us", t, c, period, "sync period [µs]", _BLUE)
    jitter = period - nominal_us
    if jitter.size:
        jitter[0] = math.nan  # first row has no previous sync
    w.scalars("/bus/timing/jitter_us", t, c, jitter, "period − nominal [µs]", _ORANGE)
    w.scalars("/bus/timing/step_us", t, c, run.timing_col("step_us"),
              "controller step [µs]", _GREEN)
    w.scalars("/bus/timing/turnaround_us", t, c, run.timing_col("turnaround_us"),
              "sync → torque frame [µs]", _RED)
    ts, cs = _bus(run, "CTRL_STATUS")
    w.scalars("/bus/timing/compute_time_us", ts, cs, run.bus_sig("CTRL_STATUS", "COMPUTE_TIME"),
              "COMPUTE_TIME (CTRL_STATUS) [µs]", _PURPLE)
    miss = run.timing_col("deadline_miss")
    w.scalars("/bus/deadline_misses", t, c, np.cumsum(np.nan_to_num(miss) > 0.5),
              "deadline misses (cumulative)", _RED)

    # Frame age on the bus: torque frame log time − log time of the SYNC it answers. A
    # lockstep log is stamped in simulated time (bus_logger.py): no wall-clock age in it.
    if run.meta.get("log_time") == "sim":
        return _log_rejections(w, run)
    sync_c = run.bus_sig("SYNC", "cycle")
    sync_t = run.bus_sig("SYNC", "t_log").astype(float)
    sync_at = dict(zip(sync_c.tolist(), sync_t.tolist(), strict=True))
    tt, ct = _bus(run, "WHEEL_TORQUE_CMD")
    tlog = run.bus_sig("WHEEL_TORQUE_CMD", "t_log").astype(float)
    age = np.array([(tl - sync_at[int(k)]) * 1e3 if int(k) in sync_at else math.nan
                    for k, tl in zip(ct.tolist(), tlog.tolist(), strict=True)])
    w.scalars("/bus/frame_age_ms", tt, ct, age, "torque frame age vs SYNC [ms]", _BLUE)
    _log_rejections(w, run)


def _log_rejections(w: _Writer, run: RunData) -> None:
    rej = run.bus.get(REJECTED_KEY, {})
    reasons = np.asarray(rej.get("reason", np.zeros(0)), dtype=object)
    for i, reason in enumerate(sorted(set(reasons.tolist()))):
        sel = reasons == reason
        w.scalars(f"/bus/rejections/{reason}", rej["sim_time_s"][sel], rej["cycle"][sel],
                  np.arange(1, int(sel.sum()) + 1), f"rejected: {reason} (cumulative)",
                  _WHEEL_COLORS[i % 4])


def _events(run: RunData) -> list[tuple[float, int, str, str]]:
    """(sim time, cycle, level, text) of everything worth a line in the event log."""
    ev: list[tuple[float, int, str, str]] = []
    choices = _choices()
    ts, cs = _bus(run, "CTRL_STATUS")
    mode = run.bus_sig("CTRL_STATUS", "MODE")
    faults = run.bus_sig("CTRL_STATUS", "FAULT_BITS")
    qp = run.bus_sig("CTRL_STATUS", "QP_STATUS")
    mode_names = choices.get("MODE", {})
    prev_mode, prev_fault, prev_qp = None, 0, None
    for k in range(mode.size):
        t, cyc = float(ts[k]), int(cs[k])
        m, f, q = int(mode[k]), int(faults[k]), int(qp[k])
        if m != prev_mode:
            old = "" if prev_mode is None else f"{mode_names.get(prev_mode, prev_mode)} → "
            level = WARN if m >= 3 else INFO
            ev.append((t, cyc, level, f"controller mode {old}{mode_names.get(m, m)}"))
            prev_mode = m
        if f != prev_fault:
            for bit, name in enumerate(FAULT_BIT_NAMES):
                was, now = prev_fault >> bit & 1, f >> bit & 1
                if now and not was:
                    ev.append((t, cyc, WARN, f"fault set: bit{bit} {name}"))
                elif was and not now:
                    ev.append((t, cyc, INFO, f"fault cleared: bit{bit} {name}"))
            prev_fault = f
        if q == 5 and prev_qp != 5:
            ev.append((t, cyc, WARN, "controller solver fallback (QP_STATUS)"))
        prev_qp = q

    t, c = run.truth_col("t_s"), run.truth_col("cycle")
    spun = run.truth_col("spun")
    if spun.size == t.size and spun.size:
        onset = np.flatnonzero((spun > 0.5) & ~np.r_[False, spun[:-1] > 0.5])
        ev += [(float(t[i]), int(c[i]), ERROR, "vehicle spun") for i in onset]
    valid = run.truth_col("cmd_valid")
    if valid.size == t.size and valid.size > 1:
        bad = valid < 0.5
        bad[0] = False  # no command can exist before the first answer
        start = None
        for i in range(1, bad.size):
            if bad[i] and not bad[i - 1]:
                start = i
                ev.append((float(t[i]), int(c[i]), WARN,
                           "plant: no valid command (fallback) — period starts"))
            elif not bad[i] and bad[i - 1] and start is not None:
                ev.append((float(t[i]), int(c[i]), INFO,
                           f"plant: valid command again after {i - start} cycles"))
    stab = run.truth_col("stab_enable")
    if stab.size == t.size and stab.size:
        change = np.flatnonzero(np.diff(stab) != 0) + 1
        ev += [(float(t[i]), int(c[i]), INFO,
                f"stabilisation {'enabled' if stab[i] > 0.5 else 'disabled'} by the scenario")
               for i in change]

    tm, cm = run.timing_col("sim_time_s"), run.timing_col("cycle")
    miss, turn = run.timing_col("deadline_miss"), run.timing_col("turnaround_us")
    if miss.size == tm.size:
        for i in np.flatnonzero(miss > 0.5):
            extra = f" (turnaround {turn[i]:.0f} µs)" if turn.size == miss.size else ""
            ev.append((float(tm[i]), int(cm[i]), WARN,
                       f"controller deadline miss{extra}"))

    rej = run.bus.get(REJECTED_KEY, {})
    for tr, cr, fid, reason in zip(rej.get("sim_time_s", ()), rej.get("cycle", ()),
                                   rej.get("frame_id", ()), rej.get("reason", ()), strict=True):
        ev.append((float(tr), int(cr), WARN,
                   f"frame 0x{int(fid):03X} rejected: {reason}"))
    ev = [e for e in ev if math.isfinite(e[0]) and e[1] >= 0]
    ev.sort(key=lambda e: (e[0], e[1]))
    return ev


def _log_events(rec: rr.RecordingStream, run: RunData) -> int:
    ev = _events(run)
    if not ev:
        return 0
    rec.send_columns("/log", indexes=_Writer.index(np.array([e[0] for e in ev]),
                                                   np.array([e[1] for e in ev])),
                     columns=rr.TextLog.columns(text=[e[3] for e in ev],
                                                level=[e[2] for e in ev]))
    return len(ev)


_FLIP = np.array([1.0, -1.0])  # display coordinates, see module docstring


def course_bounds(course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                  cones: np.ndarray | None, margin_m: float = 3.0
                  ) -> tuple[float, float, float, float] | None:
    """(x_min, x_max, y_min, y_max) in display coordinates, m, that the trajectory view
    opens on: the cones (the course proper, without lead-in and run-out) with a margin, or
    the boundaries and reference path of a course without cones; None without geometry."""
    if cones is not None and np.asarray(cones).size:
        parts = [np.asarray(cones, dtype=float).reshape(-1, 2)]
    else:
        parts = [np.asarray(p, dtype=float).reshape(-1, 2) for p in course]
        if ref_path is not None and np.asarray(ref_path).size:
            parts.append(np.asarray(ref_path, dtype=float).reshape(-1, 2))
    pts = np.concatenate(parts) * _FLIP if parts else np.zeros((0, 2))
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not pts.size:
        return None
    return (float(pts[:, 0].min() - margin_m), float(pts[:, 0].max() + margin_m),
            float(pts[:, 1].min() - margin_m), float(pts[:, 1].max() + margin_m))


def log_course(rec: rr.RecordingStream, course: Sequence[np.ndarray],
               ref_path: np.ndarray | None, cones: np.ndarray | None) -> None:
    """Static course lines, cones and reference path under /plant/trajectory."""
    strips = [np.asarray(p, dtype=float).reshape(-1, 2) * _FLIP for p in course]
    strips = [s for s in strips if s.size]
    if strips:
        rec.log("/plant/trajectory/course/lines",
                rr.LineStrips2D(strips, colors=_GRAY, radii=0.05), static=True)
    if cones is not None and np.asarray(cones).size:
        rec.log("/plant/trajectory/course/cones",
                rr.Points2D(np.asarray(cones, dtype=float).reshape(-1, 2) * _FLIP,
                            colors=_ORANGE, radii=0.15), static=True)
    if ref_path is not None and np.asarray(ref_path).size:
        rec.log("/plant/trajectory/ref_path",
                rr.LineStrips2D([np.asarray(ref_path, dtype=float).reshape(-1, 2) * _FLIP],
                                colors=_GRAY, radii=0.03), static=True)


def log_driven_path(rec: rr.RecordingStream, xy: np.ndarray) -> None:
    """The CG path driven so far (display coordinates, m) as one static line."""
    rec.log("/plant/trajectory/driven_path", rr.LineStrips2D([xy], colors=_BLUE, radii=0.04),
            static=True)


def log_vehicle(rec: rr.RecordingStream, run: RunData) -> np.ndarray | None:
    """The vehicle's position and heading on the timelines; returns the CG points logged
    (display coordinates, m) or None."""
    t, c = run.truth_col("t_s"), run.truth_col("cycle")
    x, y, yaw = run.truth_col("x_m"), run.truth_col("y_m"), run.truth_col("yaw_rad")
    if not (x.size and x.size == y.size == t.size == c.size):
        return None
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(t) & np.isfinite(c) & (c >= 0)
    xy = np.column_stack([x[ok], -y[ok]])
    if not xy.size:
        return None
    index = _Writer.index(t[ok], c[ok])
    rec.log("/plant/trajectory/vehicle", rr.Points2D.from_fields(colors=_RED, radii=0.4),
            static=True)
    rec.send_columns("/plant/trajectory/vehicle", indexes=index,
                     columns=rr.Points2D.columns(positions=xy))
    if yaw.size == x.size:
        heading = 2.5 * np.column_stack([np.cos(yaw[ok]), -np.sin(yaw[ok])])  # 2.5 m arrow
        rec.log("/plant/trajectory/heading", rr.Arrows2D.from_fields(colors=_RED), static=True)
        rec.send_columns("/plant/trajectory/heading", indexes=index,
                         columns=rr.Arrows2D.columns(origins=xy, vectors=heading))
    return xy


def _log_trajectory(rec: rr.RecordingStream, run: RunData, course: Sequence[np.ndarray],
                    ref_path: np.ndarray | None, cones: np.ndarray | None) -> None:
    log_course(rec, course, ref_path, cones)
    xy = log_vehicle(rec, run)
    if xy is not None:
        log_driven_path(rec, xy)


def log_time_series(w: _Writer, run: RunData) -> None:
    """Every scalar series (plant, controller, bus timing) of ``run``."""
    _log_plant(w, run)
    _log_controller(w, run)
    _log_bus(w, run)


def log_events(rec: rr.RecordingStream, run: RunData) -> int:
    """The event log (/log) of the whole run; returns the number of events."""
    return _log_events(rec, run)


def log_summary(rec: rr.RecordingStream, run: RunData, recording_name: str) -> None:
    """The KPI summary document (/summary)."""
    rec.log("/summary", rr.TextDocument(_summary(run, recording_name),
                                        media_type=rr.MediaType.MARKDOWN), static=True)


def _summary(run: RunData, recording_name: str) -> str:
    try:
        kpis = compute_kpis(run, course_end_s=run.meta.get("course_end_s"))
    except Exception as exc:  # the recording must not depend on the KPI code working
        kpis = {"error": repr(exc)}
    meta = {k: v for k, v in run.meta.items() if isinstance(v, str | int | float | bool)}
    lines = [f"# {recording_name}", "", "| KPI | value |", "|---|---|"]
    lines += [f"| {k} | {json.dumps(v)} |" for k, v in kpis.items()]
    lines += ["", "| meta | value |", "|---|---|"]
    lines += [f"| {k} | {json.dumps(v)} |" for k, v in sorted(meta.items())]
    return "\n".join(lines)


#: Legend corner of the time-series views: top left, where a run that starts at rest has no
#: data (the default corner covered the negative peaks).
LEGEND = rrb.PlotLegend(corner=rrb.components.Corner2D.LeftTop)


def _ts(origin: str, name: str, **kw: Any) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(origin=origin, name=name, plot_legend=LEGEND, **kw)


def build_blueprint(bounds: tuple[float, float, float, float] | None = None,
                    active_tab: int | None = None) -> rrb.Blueprint:
    """Layout: the trajectory as a full-width band on top; events and KPIs on the left below,
    tabs of time-series grids on the right.

    ``bounds``: the trajectory view's visible box (x_min, x_max, y_min, y_max), display m
    (see :func:`course_bounds`); None lets the viewer fit everything. ``active_tab``: the
    right-hand tab shown first (0 'Vehicle & control', 1 'Plant states', 2 'Timing & bus').
    """
    control = rrb.Grid(
        _ts("/controller/yaw_rate", "Yaw rate: ref vs actual [deg/s]"),
        _ts("/controller/beta", "β: ref vs actual [deg]"),
        _ts("/controller/delta_m", "ΔM [N·m]"),
        _ts("/plant/torque", "Applied wheel torques [N·m]"),
        _ts("/plant/swa", "Steering-wheel angle [deg]"),
        _ts("/plant/velocity", "Velocity [m/s]"),
        name="Vehicle & control")
    plant = rrb.Grid(
        _ts("/plant/accel", "Acceleration [m/s²]"),
        _ts("/plant/lateral_dev", "Lateral deviation [m]"),
        _ts("/plant/torque_actual", "Motor torques [N·m]"),
        _ts("/controller/torque_cmd", "Torque commands on the bus [N·m]"),
        _ts("/plant", "Flags (spun, cmd valid, stab. enable)",
            contents=["/plant/spun", "/plant/cmd_valid", "/plant/stab_enable"]),
        _ts("/controller/status", "Controller status (mode, QP iter/status, faults)"),
        name="Plant states")
    timing = rrb.Grid(
        _ts("/bus/timing", "Sync period [µs]", contents=["/bus/timing/period_us"]),
        _ts("/bus/timing", "Period jitter [µs]", contents=["/bus/timing/jitter_us"]),
        _ts("/bus/timing", "Compute time & turnaround [µs]", contents=[
            "/bus/timing/step_us", "/bus/timing/turnaround_us", "/bus/timing/compute_time_us"]),
        _ts("/bus/frame_age_ms", "Torque frame age [ms]"),
        _ts("/bus/deadline_misses", "Deadline misses (cumulative)"),
        _ts("/bus/rejections", "Rejected frames (cumulative)"),
        name="Timing & bus")
    trajectory = rrb.Spatial2DView(
        origin="/plant/trajectory", name="Trajectory (top view, +Y left up)",
        visual_bounds=None if bounds is None else rrb.VisualBounds2D(x_range=bounds[:2],
                                                                     y_range=bounds[2:]))
    side = rrb.Vertical(rrb.TextLogView(origin="/log", name="Events"),
                        rrb.TextDocumentView(origin="/summary", name="KPIs"),
                        row_shares=[1, 1])
    # The course is long and narrow (a DLC is ≈ 190 m × 10 m): the top view gets the full
    # width as a band on top, the rest below.
    return rrb.Blueprint(
        rrb.Vertical(trajectory,
                     rrb.Horizontal(side, rrb.Tabs(control, plant, timing,
                                                   active_tab=active_tab),
                                    column_shares=[1, 3]),
                     row_shares=[1, 3]),
        rrb.TimePanel(timeline="sim_time"))


def write_rrd(run: RunData, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
              path: str | Path, *, recording_name: str, cones: np.ndarray | None = None
              ) -> Path:
    """Write ``run`` to the rerun file ``path`` (one recording + its blueprint); returns it.

    ``course``: boundary polylines (N, 2) m; ``cones``: (M, 2) m cone positions (points);
    ``ref_path``: (N, 2) m. ``recording_name`` is shown in the viewer and is also the
    recording id, so give every run a distinct name (files with the same id are merged into
    one recording when opened together). The KPI summary uses ``run.meta["course_end_s"]``.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(application_id=APPLICATION_ID, recording_id=recording_name)
    rec.save(out, default_blueprint=build_blueprint(course_bounds(course, ref_path, cones)))
    try:
        rec.send_recording_name(recording_name)
        log_time_series(_Writer(rec), run)
        _log_trajectory(rec, run, course, ref_path, cones)
        log_events(rec, run)
        log_summary(rec, run, recording_name)
    finally:
        rec.flush()
        rec.disconnect()
    return out


def read_scalars(path: str | Path) -> dict[str, dict[str, Any]]:
    """Read back the scalar series of an .rrd (for tests/tools): entity -> columns.

    Each entry has ``values`` (float array), ``sim_time`` (s) and ``cycle`` arrays, sorted by
    cycle. Uses ``rerun.chunk.RrdReader`` (0.41).
    """
    from rerun.chunk import RrdReader

    acc: dict[str, dict[str, list[Any]]] = {}
    for chunk in RrdReader(str(path)).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if "Scalars:scalars" not in names:
            continue
        d = acc.setdefault(chunk.entity_path, {"values": [], "sim_time": [], "cycle": []})
        d["values"].append(np.asarray(batch.column("Scalars:scalars").flatten(), dtype=float))
        d["sim_time"].append(batch.column("sim_time").cast("int64").to_numpy() * 1e-9)
        d["cycle"].append(batch.column("cycle").to_numpy())
    out: dict[str, dict[str, Any]] = {}
    for ent, d in acc.items():
        cols = {k: np.concatenate(v) for k, v in d.items()}
        order = np.argsort(cols["cycle"], kind="stable")
        out[ent] = {k: v[order] for k, v in cols.items()}
    return out

