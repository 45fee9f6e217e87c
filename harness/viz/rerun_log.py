"""Write one run as a rerun (0.41) recording file with a saved blueprint.

Only the SDK's file sink is used (``RecordingStream.save``): no viewer, no network. Time series
go through ``send_columns`` (one call per entity, columnar), so a 20 s run (2000 cycles) is
written in a fraction of a second. Timelines: ``sim_time`` (duration, s) and ``cycle``
(sequence, the plant's SYNC cycle).

Entity tree::

    /plant/...        truth states (velocity, yaw_rate, beta, accel, swa, torque, …)
    /plant/state/*    discrete plant states as StateChange (command, stabilisation, spin)
    /plant/trajectory 2-D top view: course lines/cones, reference path, driven path, vehicle
                      (CG point and a true-size body outline)
    /controller/...   ΔM, yaw_rate/{ref,actual}, beta/{ref,actual}, status/*, torque_cmd/*,
                      torque_rate/* (|dT/dt| of the commanded torques, N·m/s)
    /controller/state/* discrete controller states as StateChange (mode, QP status, faults)
    /bus/...          timing/* (period, jitter, step, turnaround, compute time), frame_age_ms,
                      deadline_misses (cumulative), rejections/<reason> (cumulative)
    /log              TextLog of mode changes, faults, spin, invalid-command periods, misses
    /summary          TextDocument: partial-run label, verdicts, rounded KPIs with units

A lockstep run is scheduled in simulated time: its wall-clock period, jitter and frame age
say nothing about the schedule and are not written; step and turnaround are labelled as
wall-clock compute times. The blueprint holds only views that have data in the recording,
with each plot's value axis set from its data (plus a margin) so that no peak is clipped, except
the compute and turnaround views: a few values far above the rest (a start-up or scheduling
spike of a millisecond among 10 µs steps) would flatten them, so their axes end at the top of
the bulk (:func:`axis_top`) and each value above is a line in the event log.

rerun's 2-D view draws +y downwards (image convention); the top view is therefore logged in
display coordinates (X, −Y) so that "left" (+Y, ISO 8855) appears up. Numeric values of Y are
in the truth trace and in /plant scalars, unchanged.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from can_db.codec import Codec
from can_db.process.errors import error_text
from harness.analysis.kpi import compute_kpis
from harness.analysis.run_data import REJECTED_KEY, RunData
from harness.analysis.smoothness import frame_rates

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
    "native viewer with the saved layout (top view as a band on top; verdicts and KPIs "
    "below on the left; tabs 'Vehicle & control', 'States & QP' (with the event log), 'Plant' and "
    "'Timing & bus' on the right; the time panel at the bottom is collapsed: expand it to "
    "scrub or to pick the `cycle` timeline). Several runs can be compared by opening their files "
    "together (`rerun a/run.rrd b/run.rrd`). On a machine without a display, serve the web "
    "viewer on the loopback interface only: `rerun --serve-web --bind 127.0.0.1 DIR/run.rrd` "
    "and browse to the printed http://127.0.0.1 address (tunnel it with `ssh -L` if remote); "
    "never bind to all interfaces. If the layout was changed by hand, 'Reset blueprint' "
    "restores it."
)


@functools.lru_cache(maxsize=1)
def _choices() -> dict[str, dict[int, str]]:
    """Value tables of CTRL_STATUS (MODE, QP_STATUS, CONTROLLER_ID) from the DBC."""
    msg = Codec().database.get_message_by_name("CTRL_STATUS")
    out: dict[str, dict[int, str]] = {}
    for sig in msg.signals:
        if sig.choices:
            out[sig.name] = {int(k): str(v) for k, v in sig.choices.items()}
    return out


#: A value is a peak above the axis when it exceeds p99 by more than this many times the
#: spread p99 − p50 (at least 10 % of p99); fewer than PEAK_MIN_VALUES values: no peaks.
PEAK_SPREADS = 3.0
PEAK_MIN_VALUES = 20


def peak_fence(values: np.ndarray) -> float | None:
    """The value above which a timing value is a peak off the axis (see PEAK_SPREADS); None
    for too few values."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < PEAK_MIN_VALUES:
        return None
    p50, p99 = (float(x) for x in np.percentile(v, [50, 99], method="lower"))
    return p99 + PEAK_SPREADS * max(p99 - p50, 0.1 * abs(p99))


def axis_top(values: np.ndarray) -> float | None:
    """The largest value at or below :func:`peak_fence` when some values lie above it (the
    view's axis then ends there, plus its margin), else None (the axis holds every value).
    A single 1.4 ms start-up step among 10 µs steps no longer flattens the step-time plot."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    fence = peak_fence(v)
    if fence is None or not (v > fence).any():
        return None
    return float(v[v <= fence].max())


class _Writer:
    """Columnar scalar and state logging on the two timelines, skipping rows without a valid
    time. Records the value range of every entity written (``ranges``, for the blueprint's
    axes) and the state entities written (``states``). Without a stream (``rec=None``) it
    only records: a dry pass that sizes the blueprint before the file is opened."""

    def __init__(self, rec: rr.RecordingStream | None) -> None:
        self.rec = rec
        self.ranges: dict[str, tuple[float, float]] = {}
        #: entity of PEAK_PATHS -> top of its axis without its peaks (see axis_top)
        self.tops: dict[str, float] = {}
        self.states: set[str] = set()
        self._last_state: dict[str, str] = {}

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
        lo, hi = float(values[ok].min()), float(values[ok].max())
        old = self.ranges.get(path)
        self.ranges[path] = (lo, hi) if old is None else (min(old[0], lo), max(old[1], hi))
        top = axis_top(values[ok]) if path in PEAK_PATHS else None
        if top is not None:
            self.tops[path] = top
        if self.rec is None:
            return int(ok.sum())
        # Min and max per pixel column: a zoomed-out plot keeps every peak (the viewer's
        # default, averaging, washes single-cycle peaks out).
        self.rec.log(path, rr.SeriesLines(names=label, colors=color,
                                          aggregation_policy="MinMax"), static=True)
        self.rec.send_columns(path, indexes=self.index(t[ok], cycle[ok]),
                              columns=rr.Scalars.columns(scalars=values[ok]))
        return int(ok.sum())

    def states_of(self, path: str, t: np.ndarray, cycle: np.ndarray,
                  labels: Sequence[str]) -> int:
        """A discrete state per row, written as StateChange rows where it changes (the
        first row and every change; a state repeated across calls is not written again)."""
        t = np.asarray(t, dtype=float)
        cycle = np.asarray(cycle, dtype=float)
        if not (t.size == cycle.size == len(labels)) or t.size == 0:
            return 0
        ok = np.isfinite(t) & np.isfinite(cycle) & (cycle >= 0)
        rows, prev = [], self._last_state.get(path)
        for i in np.flatnonzero(ok):
            if labels[i] != prev:
                rows.append(i)
                prev = labels[i]
        if not ok.any():
            return 0
        self.states.add(path)
        self._last_state[path] = prev if prev is not None else ""
        if self.rec is None or not rows:
            return len(rows)
        idx = np.asarray(rows)
        self.rec.send_columns(path, indexes=self.index(t[idx], cycle[idx]),
                              columns=rr.StateChange.columns(state=[labels[i] for i in rows]))
        return len(rows)

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
    for col, path, yes, no in (("cmd_valid", "command", "valid", "invalid (fallback)"),
                               ("stab_enable", "stabilisation", "enabled", "disabled"),
                               ("spun", "spin", "SPUN", "no spin")):
        flag = tc(col)
        if flag.size == t.size:
            w.states_of(f"/plant/state/{path}", t, c,
                        [yes if v > 0.5 else no for v in np.nan_to_num(flag).tolist()])
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
    choices = _choices()
    for sig, path in (("MODE", "mode"), ("QP_STATUS", "qp_status")):
        vals = run.bus_sig("CTRL_STATUS", sig).astype(float)
        if vals.size == ts.size:
            names = choices.get(sig, {})
            w.states_of(f"/controller/state/{path}", ts, cs,
                        [names.get(int(v), str(int(v))) if math.isfinite(v) else ""
                         for v in vals.tolist()])
    bits = run.bus_sig("CTRL_STATUS", "FAULT_BITS").astype(float)
    if bits.size == ts.size:
        w.states_of("/controller/state/faults", ts, cs,
                    [fault_text(int(v)) if math.isfinite(v) else "" for v in bits.tolist()])
    tt, ct = _bus(run, "WHEEL_TORQUE_CMD")
    for wheel, color in zip(WHEELS, _WHEEL_COLORS, strict=True):
        w.scalars(f"/controller/torque_cmd/{wheel}", tt, ct,
                  run.bus_sig("WHEEL_TORQUE_CMD", f"TQ_{wheel.upper()}"),
                  f"T cmd {wheel.upper()} [N·m]", color)
        _log_torque_rate(w, run, wheel, color)
    solved = run.timing_col("mpc_update") > 0.5
    qp_iter = run.timing_col("qp_iterations")
    if qp_iter.size == solved.size and solved.any():
        w.scalars("/controller/qp_iterations", run.timing_col("sim_time_s")[solved],
                  run.timing_col("cycle")[solved], qp_iter[solved], "QP iterations per solve",
                  _ORANGE)
    w.scalars("/controller/status/mpc_update", run.timing_col("sim_time_s"),
              run.timing_col("cycle"), run.timing_col("mpc_update"), "MPC step ran (0/1)",
              _GREEN)


def _log_torque_rate(w: _Writer, run: RunData, wheel: str, color: Sequence[int]
                     ) -> None:
    """/controller/torque_rate/<wheel>: |T(k) − T(k−1)| / cycle of the commanded torque
    (N·m/s, harness/analysis/smoothness.py: the quantity of the wheel_torque_rate KPIs), at
    the frames whose previous cycle has a frame."""
    tt, ct = _bus(run, "WHEEL_TORQUE_CMD")
    tq = run.bus_sig("WHEEL_TORQUE_CMD", f"TQ_{wheel.upper()}").astype(float)
    if tq.size < 2 or tq.size != ct.size:
        return
    rate = frame_rates(ct, tq, float(run.meta.get("comm_period_s", DEFAULT_PERIOD_S)))
    w.scalars(f"/controller/torque_rate/{wheel}", tt, ct, rate,  # NaN rows are left out
              f"|dT/dt| cmd {wheel.upper()} [N·m/s]", color)


def is_lockstep(run: RunData) -> bool:
    """True for a run scheduled in simulated time (its bus log is stamped in sim time)."""
    return run.meta.get("log_time") == "sim" or run.meta.get("mode") == "lockstep"


def _log_bus(w: _Writer, run: RunData) -> None:
    nominal_us = float(run.meta.get("comm_period_s", DEFAULT_PERIOD_S)) * 1e6
    t, c = run.timing_col("sim_time_s"), run.timing_col("cycle")
    lockstep = is_lockstep(run)
    wall = " (wall-clock compute)" if lockstep else ""
    if not lockstep:  # a lockstep period is the wall time between simulated steps
        period = run.timing_col("period_us")
        w.scalars("/bus/timing/period_us", t, c, period, "sync period [µs]", _BLUE)
        jitter = period - nominal_us
        if jitter.size:
            jitter[0] = math.nan  # first row has no previous sync
        w.scalars("/bus/timing/jitter_us", t, c, jitter, "period − nominal [µs]", _ORANGE)
    w.scalars("/bus/timing/step_us", t, c, run.timing_col("step_us"),
              f"controller step [µs]{wall}", _GREEN)
    w.scalars("/bus/timing/turnaround_us", t, c, run.timing_col("turnaround_us"),
              f"sync → torque frame [µs]{wall}", _RED)
    ts, cs = _bus(run, "CTRL_STATUS")
    w.scalars("/bus/timing/compute_time_us", ts, cs, run.bus_sig("CTRL_STATUS", "COMPUTE_TIME"),
              f"COMPUTE_TIME (CTRL_STATUS) [µs]{wall}", _PURPLE)
    miss = run.timing_col("deadline_miss")
    w.scalars("/bus/deadline_misses", t, c, np.cumsum(np.nan_to_num(miss) > 0.5),
              "deadline misses (cumulative)", _RED)

    # Frame age on the bus: torque frame log time − log time of the SYNC it answers. A
    # lockstep log is stamped in simulated time (bus_logger.py): no wall-clock age in it.
    if lockstep:
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


def fault_text(bits: int) -> str:
    """CTRL_STATUS.FAULT_BITS as words: "none" or "bit3 solver fallback + …"."""
    set_bits = [f"bit{b} {n}" for b, n in enumerate(FAULT_BIT_NAMES) if bits >> b & 1]
    return " + ".join(set_bits) if set_bits else "none"


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

    for col, what, view in (("step_us", "controller step", "compute"),
                            ("turnaround_us", "turnaround", "turnaround")):
        values = run.timing_col(col)
        fence = peak_fence(values) if values.size == tm.size else None
        if fence is None:
            continue
        top = axis_top(values)
        for i in np.flatnonzero(np.nan_to_num(values) > fence):
            ev.append((float(tm[i]), int(cm[i]), INFO,
                       f"{what} {values[i]:.0f} µs: above the {view} view's axis "
                       f"(which ends at {top:.0f} µs)"))

    rej = run.bus.get(REJECTED_KEY, {})
    for tr, cr, fid, reason in zip(rej.get("sim_time_s", ()), rej.get("cycle", ()),
                                   rej.get("frame_id", ()), rej.get("reason", ()), strict=True):
        ev.append((float(tr), int(cr), WARN,
                   f"frame 0x{int(fid):03X} rejected: {reason}"))
    ev = [e for e in ev if math.isfinite(e[0]) and e[1] >= 0]
    ev.sort(key=lambda e: (e[0], e[1]))
    return ev


def _log_events(rec: rr.RecordingStream, run: RunData,
                metrics: Mapping[str, Any] | None = None) -> int:
    ev = _events(run)
    label = partial_label(metrics or run.meta)
    if label is not None:
        reached = _num((metrics or run.meta).get("sim_time_reached_s"))
        t_end = reached if reached is not None else float(
            np.nanmax(run.truth_col("t_s"))) if run.truth_col("t_s").size else 0.0
        cycles = run.truth_col("cycle")
        c_end = int(np.nanmax(cycles)) if cycles.size else 0
        ev.append((t_end, c_end, ERROR, label))
    if not ev:
        return 0
    rec.send_columns("/log", indexes=_Writer.index(np.array([e[0] for e in ev]),
                                                   np.array([e[1] for e in ev])),
                     columns=rr.TextLog.columns(text=[e[3] for e in ev],
                                                level=[e[2] for e in ev]))
    return len(ev)


_FLIP = np.array([1.0, -1.0])  # display coordinates, see module docstring


def course_bounds(course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                  cones: np.ndarray | None, margin_m: float = 3.0,
                  driven: np.ndarray | None = None
                  ) -> tuple[float, float, float, float] | None:
    """(x_min, x_max, y_min, y_max) in display coordinates, m, that the trajectory view
    opens on: the cones (the course proper, without lead-in and run-out) with a margin, or
    the boundaries and reference path of a course without cones, widened to hold the
    ``driven`` CG path ((N, 2), display m) so the car is in view at every time; None
    without geometry. The 2-D view keeps equal scales on both axes (letterboxing)."""
    if cones is not None and np.asarray(cones).size:
        parts = [np.asarray(cones, dtype=float).reshape(-1, 2)]
    else:
        parts = [np.asarray(p, dtype=float).reshape(-1, 2) for p in course]
        if ref_path is not None and np.asarray(ref_path).size:
            parts.append(np.asarray(ref_path, dtype=float).reshape(-1, 2))
    pts = np.concatenate(parts) * _FLIP if parts else np.zeros((0, 2))
    if driven is not None and np.asarray(driven).size:
        pts = np.concatenate([pts, np.asarray(driven, dtype=float).reshape(-1, 2)])
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


#: Body outline drawn in the top view, m (a mid-size car; the plant's track is 1.6 m).
BODY_LENGTH_M, BODY_WIDTH_M = 4.6, 1.85


def body_outline(xy: np.ndarray, yaw_display: np.ndarray) -> np.ndarray:
    """(N, 5, 2) closed body outlines at CG points ``xy`` (display m), heading
    ``yaw_display`` (rad, display coordinates: the negated ISO yaw)."""
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1], [1, 1]], dtype=float) * [
        BODY_LENGTH_M / 2, BODY_WIDTH_M / 2]
    cos, sin = np.cos(yaw_display)[:, None], np.sin(yaw_display)[:, None]
    x = half[None, :, 0] * cos - half[None, :, 1] * sin
    y = half[None, :, 0] * sin + half[None, :, 1] * cos
    return np.stack([x, y], axis=-1) + np.asarray(xy, dtype=float)[:, None, :]


def log_vehicle(rec: rr.RecordingStream, run: RunData) -> np.ndarray | None:
    """The vehicle's CG and true-size body outline on the timelines; returns the CG points
    logged (display coordinates, m) or None."""
    t, c = run.truth_col("t_s"), run.truth_col("cycle")
    x, y, yaw = run.truth_col("x_m"), run.truth_col("y_m"), run.truth_col("yaw_rad")
    if not (x.size and x.size == y.size == t.size == c.size):
        return None
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(t) & np.isfinite(c) & (c >= 0)
    xy = np.column_stack([x[ok], -y[ok]])
    if not xy.size:
        return None
    index = _Writer.index(t[ok], c[ok])
    rec.log("/plant/trajectory/vehicle", rr.Points2D.from_fields(colors=_RED, radii=0.3),
            static=True)
    rec.send_columns("/plant/trajectory/vehicle", indexes=index,
                     columns=rr.Points2D.columns(positions=xy))
    if yaw.size == x.size:
        heading = np.nan_to_num(-yaw[ok])
        rec.log("/plant/trajectory/body", rr.LineStrips2D.from_fields(colors=_RED, radii=0.08),
                static=True)
        rec.send_columns("/plant/trajectory/body", indexes=index,
                         columns=rr.LineStrips2D.columns(strips=list(body_outline(xy, heading))))
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


def log_events(rec: rr.RecordingStream, run: RunData,
               metrics: Mapping[str, Any] | None = None) -> int:
    """The event log (/log) of the whole run; returns the number of events. A partial run
    (``metrics["interrupted"]``) gets its label as the last event."""
    return _log_events(rec, run, metrics)


def log_summary(rec: rr.RecordingStream, run: RunData, recording_name: str,
                metrics: Mapping[str, Any] | None = None) -> None:
    """The summary document (/summary): partial-run label, verdicts, KPIs, run settings.
    ``metrics``: the run's metrics.json content when known (verdicts, interrupted, …)."""
    rec.log("/summary", rr.TextDocument(summary_text(run, recording_name, metrics),
                                        media_type=rr.MediaType.MARKDOWN), static=True)


def _num(v: Any) -> float | None:
    """``v`` as a finite float, else None."""
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def partial_label(metrics: Mapping[str, Any]) -> str | None:
    """"PARTIAL RUN — interrupted at X.X s of Y.Y s" for an interrupted run, else None.
    Y is ``duration_planned_s`` (or the scenario's end when that is all there is)."""
    if metrics.get("interrupted") is not True:
        return None
    reached = _num(metrics.get("sim_time_reached_s"))
    planned = _num(metrics.get("duration_planned_s"))
    if planned is None:
        planned = _num(metrics.get("scenario_end_s"))
    at = "?" if reached is None else f"{reached:.1f} s"
    return f"PARTIAL RUN — interrupted at {at}" + ("" if planned is None
                                                     else f" of {planned:.1f} s")


#: The verdict words (the only ones shown) and the metrics.json "verdicts" keys.
VERDICTS = (("paper_rule", "paper rule"), ("course_rule", "course rule (cones)"),
            ("stable", "stable"))


def verdict_lines(metrics: Mapping[str, Any]) -> list[str]:
    """Markdown lines for the metrics.json "verdicts" block; a line saying it is absent
    when the run has none."""
    block = metrics.get("verdicts")
    if not isinstance(block, Mapping):
        return ["verdicts: not in this run's metrics"]
    lines = []
    for key, word in VERDICTS:
        v = block.get(key)
        v = v if isinstance(v, Mapping) else {}
        passed = v.get("passed")
        # None: no such rule in the scenario, or not judged (the rule text says which).
        result = "not judged" if passed is None else ("PASS" if passed else "FAIL")
        extra = []
        if key == "course_rule" and passed is not None:
            for k, what in (("cones_struck", "cones struck"), ("gate_exits", "gate exits")):
                if isinstance(v.get(k), int):
                    extra.append(f"{v[k]} {what}")
        detail = f" ({', '.join(extra)})" if extra else ""
        text = v.get("rule") if isinstance(v.get("rule"), str) else ""
        rule = f" — {text.removeprefix('not judged: ')}" if text else ""
        lines.append(f"* **{word}: {result}**{detail}{rule}")
    return lines


#: KPI rows of the summary: label, metrics key(s), unit, format (units in the label column
#: so the value column stays narrow).
KPI_ROWS: tuple[tuple[str, str | tuple[str, ...], str, str], ...] = (
    ("completed", "completed", "", "{}"),
    ("spun", "spun", "", "{}"),
    ("max \\|β\\|", "max_abs_beta_deg", "deg", "{:.2f}"),
    ("max \\|lateral dev.\\|", "max_abs_lateral_dev_m", "m", "{:.3f}"),
    ("rms lateral dev.", "rms_lateral_dev_m", "m", "{:.3f}"),
    ("phase-plane area", "phase_area", "rad²/s", "{:.4f}"),
    ("max \\|steering-wheel angle\\|", "max_abs_swa_deg", "deg", "{:.1f}"),
    ("steering effort", "steering_effort_deg", "deg", "{:.0f}"),
    ("max \\|ΔM\\|", "max_abs_dM_Nm", "N·m", "{:.0f}"),
    ("ΔM total variation", "dM_total_variation_Nm", "N·m", "{:.0f}"),
    ("ΔM total variation per second", "dM_tv_per_s_Nm_per_s", "N·m/s", "{:.0f}"),
    ("largest ΔM change per MPC period", "dM_max_change_per_period_Nm", "N·m", "{:.0f}"),
    ("wheel-torque rate max / p99", ("wheel_torque_rate_max_Nm_per_s",
                                     "wheel_torque_rate_p99_Nm_per_s"), "N·m/s",
     "{:.0f} / {:.0f}"),
    ("ΔM chatter (increment sign reversals)", "dM_chatter_per_s", "1/s", "{:.1f}"),
    ("yaw-rate tracking rms error", "yaw_rate_rmse_degps", "deg/s", "{:.2f}"),
    ("β tracking rms error", "beta_rmse_deg", "deg", "{:.2f}"),
    ("controller step p50 / p99", ("step_us_p50", "step_us_p99"), "µs", "{:.0f} / {:.0f}"),
    ("sync → torque p50 / p99", ("turnaround_us_p50", "turnaround_us_p99"), "µs",
     "{:.0f} / {:.0f}"),
    ("period jitter p99", "period_jitter_us_p99", "µs", "{:.0f}"),
    ("deadline misses", "deadline_misses", "", "{}"),
    ("fallback events", "fallback_events", "", "{}"),
    ("frames rejected", "frames_rejected", "", "{}"),
)
#: Compute-time rows: wall-clock figures, also in lockstep (labelled so there).
_COMPUTE_ROWS = ("controller step p50 / p99", "sync → torque p50 / p99")


def format_kpi(value: Any, fmt: str) -> str:
    """One KPI cell: rounded numbers, "–" for none, a dict as "k: n, …" ("none" if empty)."""
    values = value if isinstance(value, tuple) else (value,)
    if any(v is None for v in values):
        return "–"
    if len(values) == 1 and isinstance(values[0], Mapping):
        return ", ".join(f"{k}: {n}" for k, n in values[0].items()) or "none"
    if any(isinstance(v, float) and not math.isfinite(v) for v in values):
        return " / ".join(str(v) for v in values)
    try:
        return fmt.format(*values)
    except (TypeError, ValueError):
        return str(values[0] if len(values) == 1 else values)


def _kpi_table(kpis: Mapping[str, Any], lockstep: bool) -> list[str]:
    lines = ["| KPI | value |", "|---|---|"]
    for label, key, unit, fmt in KPI_ROWS:
        keys = key if isinstance(key, tuple) else (key,)
        if not any(k in kpis for k in keys):
            continue
        value = tuple(kpis.get(k) for k in keys) if len(keys) > 1 else kpis.get(keys[0])
        if label == "period jitter p99" and lockstep:
            continue  # a lockstep period is not a schedule figure
        name = f"{label} [{unit}]" if unit else label
        if lockstep and label in _COMPUTE_ROWS:
            name += " (wall-clock compute)"
        lines.append(f"| {name} | {format_kpi(value, fmt)} |")
    return lines


def summary_text(run: RunData, recording_name: str,
                 metrics: Mapping[str, Any] | None = None) -> str:
    """The /summary document (Markdown): partial-run label, verdicts, KPIs, settings."""
    info: dict[str, Any] = {**run.meta, **(metrics or {})}
    try:
        kpis = compute_kpis(run, course_end_s=run.meta.get("course_end_s"))
    except Exception as exc:  # the recording must not depend on the KPI code working
        kpis = {}
        info["kpi_error"] = error_text(exc)
    lines = [f"## {recording_name}", ""]
    label = partial_label(info)
    if label is not None:
        lines += [f"**{label}**", ""]
    lines += ["### Verdicts", "", *verdict_lines(info), "", "### KPIs", ""]
    lines += _kpi_table(kpis, is_lockstep(run) or info.get("mode") == "lockstep")
    if "kpi_error" in info:
        lines.append(f"\nKPIs could not be computed: {info['kpi_error']}")
    lines += ["", "### Run", "", "| setting | value |", "|---|---|"]
    for key in ("scenario", "controller", "mode", "controller_mode", "bus", "mu",
                "speed_kmh", "seed", "duration_planned_s", "sim_time_reached_s", "reason",
                "secoc", "software_version", "wall_time_s"):
        v = info.get(key)
        if v is None or isinstance(v, dict | list):
            continue
        text = f"{v:.4g}" if isinstance(v, float) else str(v)
        lines.append(f"| {key} | {text} |")
    return "\n".join(lines)


#: Legends are hidden: a legend box sits on top of the data whatever its corner. Each
#: view's title names its series and their colours instead (hover shows the values).
NO_LEGEND = rrb.PlotLegend(visible=False)
#: Head and foot room of a value axis, as a fraction of the data's span.
AXIS_MARGIN = 0.08
#: Wheel torques in two views, front and rear: left and right of one axle differ by the yaw
#: moment, while a left front and a left rear torque are often equal and would hide one
#: another in one view (and four colours did not fit a title).
_AXLES = (("Front", ("fl", "fr"), "FL blue, FR orange"),
          ("Rear", ("rl", "rr"), "RL green, RR red"))
#: The controller's own compute (µs) and the turnaround through the bus (up to ms) in
#: separate views: on one axis the turnaround's spikes flatten the step time.
_STEP_PATHS = ("/bus/timing/step_us", "/bus/timing/compute_time_us")
_TURNAROUND_PATHS = ("/bus/timing/turnaround_us",)
#: The entities of these two views: their value axes end at the top of the bulk of the data
#: (:func:`axis_top`), so that one spike does not flatten them.
PEAK_PATHS = _STEP_PATHS + _TURNAROUND_PATHS
#: Entities of the state-timeline view (discrete states, named).
STATE_PATHS = ("/controller/state/mode", "/controller/state/qp_status",
               "/controller/state/faults", "/plant/state/command",
               "/plant/state/stabilisation", "/plant/state/spin")
TAB_NAMES = ("Vehicle & control", "States & QP", "Plant", "Timing & bus")


#: Event log columns: sim time, level, text (the entity path is always /log).
EVENT_COLUMNS = rrb.archetypes.TextLogColumns(
    timeline_columns=[rrb.encodings.TimelineColumn("sim_time"),
                      rrb.encodings.TimelineColumn("cycle", visible=False)],
    text_log_columns=[rrb.encodings.TextLogColumn("LogLevel"),
                      rrb.encodings.TextLogColumn("Body"),
                      rrb.encodings.TextLogColumn("EntityPath", visible=False)])


def axis_range(lo: float, hi: float, margin: float = AXIS_MARGIN) -> tuple[float, float]:
    """A value-axis range that holds [lo, hi] with ``margin`` of the span either side (a
    flat signal gets ±10 % of its value, at least ±0.5)."""
    span = hi - lo
    pad = margin * span if span > 0 else max(0.5, 0.1 * abs(hi))
    return (lo - pad, hi + pad)


class _Views:
    """Builds the time-series views of one blueprint. With ``ranges`` (entity -> value range
    of the data written), a view whose entities have no data is left out and its value axis
    spans its data; without (a live view, data still to come) every view is made with an
    automatic axis."""

    def __init__(self, ranges: Mapping[str, tuple[float, float]] | None,
                 tops: Mapping[str, float] | None = None) -> None:
        self.ranges = ranges
        self.tops = tops or {}

    def _data(self, paths: Sequence[str], peaks: bool = False) -> list[tuple[float, float]]:
        """Value ranges of the entities under ``paths``; ``peaks``: an entity's range ends
        at its :func:`axis_top` where it has one."""
        assert self.ranges is not None
        return [(r[0], self.tops.get(p, r[1]) if peaks else r[1])
                for p, r in self.ranges.items()
                if any(p == q or p.startswith(q.rstrip("/") + "/") for q in paths)]

    def ts(self, name: str, paths: Sequence[str], *, live: bool = True,
           legend: bool = False, count: bool = False,
           peaks: bool = False) -> rrb.TimeSeriesView | None:
        """A time-series view of ``paths`` (entities or subtrees); None when it would be
        empty (``live=False``: never fed in a live view). ``count``: a count, whose axis
        starts at 0. ``peaks``: the axis ends at the top of the bulk of the data, the peaks
        above it leave the view (:func:`axis_top`)."""
        axis = None
        if self.ranges is None:
            if not live:
                return None
        else:
            data = self._data(paths, peaks)
            if not data:
                return None
            lo, hi = axis_range(min(r[0] for r in data), max(r[1] for r in data))
            if count:
                lo, hi = -0.05 * max(hi, 1.0), max(hi, 1.0)
            axis = rrb.ScalarAxis(range=(lo, hi))
        legend_bp = rrb.PlotLegend(corner=rrb.components.Corner2D.LeftTop) if legend \
            else NO_LEGEND
        return rrb.TimeSeriesView(origin="/", contents=[f"+ {p}/**" if not p.endswith("**")
                                                        else f"+ {p}" for p in paths],
                                  name=name, plot_legend=legend_bp, axis_y=axis)


#: Characters of a title a grid cell of four columns shows (1600 px wide viewer).
TITLE_SHOWN = 25


def _axle_views(v: _Views, title: str, root: str, unit: str = "N·m", kind: str = ""
                ) -> list[rrb.TimeSeriesView | None]:
    """``title`` [unit] of the wheels under ``root``, one view per axle (see _AXLES). A grid
    cell shows the first :data:`TITLE_SHOWN` characters of a title: the colour key comes
    first, after ``kind`` (at most 5 characters) where a tab has several per-wheel
    quantities, so that the views of one tab still differ in what is shown (the colour key
    names the axle there)."""
    return [v.ts(f"{kind}: {colours} — {title} [{unit}]" if kind
                 else f"{colours} — {axle} {title} [{unit}]", [f"{root}/{w}" for w in wheels])
            for axle, wheels, colours in _AXLES]


def _grid(name: str, *views: rrb.View | None) -> rrb.Grid | None:
    kept = [v for v in views if v is not None]
    return rrb.Grid(*kept, name=name) if kept else None


def build_blueprint(bounds: tuple[float, float, float, float] | None = None,
                    active_tab: int | None = None, *,
                    ranges: Mapping[str, tuple[float, float]] | None = None,
                    states: Sequence[str] | None = None,
                    note: str | None = None,
                    tops: Mapping[str, float] | None = None) -> rrb.Blueprint:
    """Layout: the trajectory as a full-width band on top (true aspect, opened on the
    course); the summary (verdicts, KPIs) on the left below; tabs of time-series grids,
    the state timeline and the event log on the right. The viewer's own side panels are
    hidden or collapsed so the views get the width.

    ``bounds``: the trajectory view's visible box (x_min, x_max, y_min, y_max), display m
    (see :func:`course_bounds`); None lets the viewer fit everything. ``active_tab``: the
    right-hand tab shown first (index into :data:`TAB_NAMES`). ``ranges``: value range of
    every scalar entity in the recording (``_Writer.ranges``): views without data are left
    out and each value axis spans its data with a margin; None (a live view) makes every
    view with automatic axes. ``states``: the state entities in the recording (None: all of
    :data:`STATE_PATHS`). ``note``: shown in the trajectory view's title (e.g. the
    partial-run label). ``tops``: entity -> top of its axis without its peaks
    (``_Writer.tops``): the compute and turnaround views end their axes there.
    """
    v = _Views(ranges, tops)
    control = _grid(
        TAB_NAMES[0],
        v.ts("Yaw rate [deg/s] — ref red, actual blue", ["/controller/yaw_rate"]),
        v.ts("β [deg] — ref red, actual blue", ["/controller/beta"]),
        v.ts("ΔM [N·m]", ["/controller/delta_m"]),
        *_axle_views(v, "wheels, applied", "/plant/torque"),
        v.ts("Steering-wheel angle [deg]", ["/plant/swa"]),
        v.ts("Velocity [m/s] — vx blue, vy orange", ["/plant/velocity"]))
    state_paths = [p for p in STATE_PATHS if states is None or p in states]
    state_view = rrb.StateTimelineView(
        origin="/", contents=[f"+ {p}" for p in state_paths],
        name="States: controller mode, QP status, faults; plant command, stabilisation, "
             "spin") if state_paths else None
    qp = (v.ts("QP iterations per MPC solve", ["/controller/qp_iterations"])
          or v.ts("QP iterations (CTRL_STATUS; 0: no solve in that step)",
                  ["/controller/status/qp_iter"]))
    events = rrb.TextLogView(origin="/log", name="Events", columns=EVENT_COLUMNS)
    parts = [x for x in (state_view, qp) if x is not None] + [events]
    states_tab = rrb.Vertical(*parts, name=TAB_NAMES[1], row_shares=[3, 2, 2][-len(parts):])
    plant = _grid(
        TAB_NAMES[2],
        v.ts("Acceleration [m/s²] — ax blue, ay orange", ["/plant/accel"]),
        v.ts("Lateral deviation from the reference path [m]", ["/plant/lateral_dev"]),
        *_axle_views(v, "motor output", "/plant/torque_actual", kind="Motor"),
        *_axle_views(v, "commands on the bus", "/controller/torque_cmd", kind="Bus"),
        *_axle_views(v, "command |dT/dt|", "/controller/torque_rate", "N·m/s", kind="Rate"))
    compute = "Compute time [µs] — step green, COMPUTE_TIME violet"
    turnaround = "Turnaround SYNC → torque frame [µs] (red)"
    if ranges is not None and "/bus/timing/period_us" not in ranges:
        # lockstep: wall-clock figures of a simulated schedule
        compute = compute.replace("Compute time [µs]", "Compute [µs, wall]")
        turnaround = turnaround.replace("[µs]", "[µs, wall]")
    timing = _grid(
        TAB_NAMES[3],
        v.ts("Sync period [µs]", ["/bus/timing/period_us"]),
        v.ts("Period − nominal [µs]", ["/bus/timing/jitter_us"]),
        v.ts(compute, list(_STEP_PATHS), peaks=True),
        v.ts(turnaround, list(_TURNAROUND_PATHS), peaks=True),
        v.ts("Torque frame age vs its SYNC [ms]", ["/bus/frame_age_ms"]),
        v.ts("Deadline misses (cumulative)", ["/bus/deadline_misses"], count=True),
        v.ts("Rejected frames (cumulative, by reason)", ["/bus/rejections"], live=False,
             legend=True, count=True))
    tabs = [x for x in (control, states_tab, plant, timing) if x is not None]
    if active_tab is not None:
        wanted = TAB_NAMES[active_tab]
        active_tab = next((i for i, t in enumerate(tabs) if t.name == wanted), 0)
    title = "Top view [m] (+Y left is up)" + (f" — {note}" if note else "")
    trajectory = rrb.Spatial2DView(
        origin="/plant/trajectory", name=title,
        visual_bounds=None if bounds is None else rrb.VisualBounds2D(x_range=bounds[:2],
                                                                     y_range=bounds[2:]))
    side = rrb.TextDocumentView(origin="/summary", name="Verdicts & KPIs (events: tab "
                                                       "'States & QP')")
    right = rrb.Tabs(*tabs, active_tab=active_tab) if tabs else rrb.Tabs()
    # The course is long and narrow (a DLC is ≈ 190 m × 10 m): the top view gets the full
    # width as a band on top, the rest below.
    return rrb.Blueprint(
        rrb.Vertical(trajectory,
                     rrb.Horizontal(side, right, column_shares=[1, 3]),
                     row_shares=[1, 3]),
        rrb.BlueprintPanel(state="hidden"),
        rrb.SelectionPanel(state="hidden"),
        # Following: the time cursor sits at the latest data (the run's end once loaded)
        # instead of playing from the start.
        rrb.TimePanel(state="collapsed", timeline="sim_time", play_state="following"))


def blueprint_for(run: RunData, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                  cones: np.ndarray | None, metrics: Mapping[str, Any] | None = None,
                  active_tab: int | None = None) -> rrb.Blueprint:
    """The blueprint :func:`write_rrd` saves with ``run`` (a dry pass over its series)."""
    dry = _Writer(None)
    log_time_series(dry, run)
    x, y = run.truth_col("x_m"), run.truth_col("y_m")
    driven = np.column_stack([x, -y]) if x.size == y.size else None
    if driven is not None:
        driven = driven[np.isfinite(driven).all(axis=1)]
    return build_blueprint(course_bounds(course, ref_path, cones, driven=driven), active_tab,
                           ranges=dry.ranges, states=sorted(dry.states), tops=dry.tops,
                           note=partial_label({**run.meta, **(metrics or {})}))


def recording_layout(path: str | Path) -> dict[str, Any]:
    """What :func:`build_blueprint` needs, read back from an .rrd written by
    :func:`write_rrd`: ``ranges`` (scalar entity -> value range), ``tops`` (entity of
    :data:`PEAK_PATHS` -> top of its axis without its peaks), ``states`` (state entities)
    and ``driven`` ((N, 2) CG points, display m)."""
    from rerun.chunk import RrdReader

    ranges: dict[str, tuple[float, float]] = {}
    peak_values: dict[str, list[np.ndarray]] = {}
    states: set[str] = set()
    driven: list[np.ndarray] = []
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        ent = chunk.entity_path
        if "StateChange:state" in names:
            states.add(ent)
        if chunk.is_static:
            continue
        if "Scalars:scalars" in names:
            v = np.asarray(batch.column("Scalars:scalars").flatten(), dtype=float)
            v = v[np.isfinite(v)]
            if ent in PEAK_PATHS:
                peak_values.setdefault(ent, []).append(v)
            if v.size:
                lo, hi = float(v.min()), float(v.max())
                old = ranges.get(ent)
                ranges[ent] = (lo, hi) if old is None else (min(old[0], lo), max(old[1], hi))
        if ent == "/plant/trajectory/vehicle" and "Points2D:positions" in names:
            pts = batch.column("Points2D:positions").flatten().to_numpy(zero_copy_only=False)
            driven.append(np.stack(pts).astype(float).reshape(-1, 2))
    tops = {ent: top for ent, parts in peak_values.items()
            if (top := axis_top(np.concatenate(parts))) is not None}
    return {"ranges": ranges, "tops": tops, "states": sorted(states),
            "driven": np.concatenate(driven) if driven else None}


def write_rrd(run: RunData, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
              path: str | Path, *, recording_name: str, cones: np.ndarray | None = None,
              metrics: Mapping[str, Any] | None = None) -> Path:
    """Write ``run`` to the rerun file ``path`` (one recording + its blueprint); returns it.

    ``course``: boundary polylines (N, 2) m; ``cones``: (M, 2) m cone positions (points);
    ``ref_path``: (N, 2) m. ``recording_name`` is shown in the viewer and is also the
    recording id, so give every run a distinct name (files with the same id are merged into
    one recording when opened together). The KPI summary uses ``run.meta["course_end_s"]``.
    ``metrics``: the run's metrics (metrics.json content): its "verdicts" block and
    "interrupted"/"sim_time_reached_s"/"duration_planned_s" are shown when present.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(application_id=APPLICATION_ID, recording_id=recording_name)
    rec.save(out, default_blueprint=blueprint_for(run, course, ref_path, cones, metrics))
    try:
        rec.send_recording_name(recording_name)
        log_time_series(_Writer(rec), run)
        _log_trajectory(rec, run, course, ref_path, cones)
        log_events(rec, run, metrics)
        log_summary(rec, run, recording_name, metrics)
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

