"""PNG plots of one run and overlays of several controllers (paper Figs 7 and 9 style).

Uses matplotlib's object API (``Figure`` + Agg canvas, never pyplot) so it runs headless and
leaves no global state behind.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from collections.abc import Callable, Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controller.core.params import load_vehicle_params as load_controller_vehicle
from harness.analysis.fmvss126 import G
from harness.analysis.footprint import Footprint, packaged_footprint
from harness.analysis.kpi import beta_rate, phase_area
from harness.analysis.run_data import RunData
from harness.analysis.run_status import partial_note
from harness.analysis.verdicts import (
    BETA_LIMIT_DEG,
    PAPER_DEV_M,
    verdict_block,
    verdict_summary,
    verdict_word,
    window_struck,
)
from plant_sim.params import load_vehicle_params as load_plant_vehicle

DEG = 180.0 / math.pi
WHEELS = ("fl", "fr", "rl", "rr")
DPI = 120
FOOTPRINT_EVERY_S = 0.4  # body outline drawn every this many simulated seconds
LIMIT_STYLE: dict[str, object] = {"color": "tab:red", "ls": ":", "lw": 1.0}
#: Fixed colour and line style per controller (never the cones' orange); the RHONN-NMPC is
#: drawn last and thickest so no other line hides it.
CONTROLLER_STYLE: dict[str, dict[str, object]] = {
    "nmpc-rhonn": {"color": "tab:blue", "lw": 2.0, "zorder": 5},
    "nmpc-mf": {"color": "tab:green", "lw": 1.4, "ls": "-.", "zorder": 4},
    "lmpc": {"color": "tab:purple", "lw": 1.4, "ls": "--", "zorder": 3},
    "passive": {"color": "tab:gray", "lw": 1.0, "zorder": 2},
}
_EXTRA_COLOURS = ("tab:brown", "tab:pink", "tab:olive", "tab:cyan")
UNCONTROLLED = ("passive",)


def motor_limit_nm() -> float:
    """Peak torque per motor, N·m (controller/config/vehicle.toml)."""
    return float(load_controller_vehicle().peak_torque_nm)


def delta_m_box_nm() -> float:
    """|ΔM| the four motors can give at zero pedal torque below base speed, N·m:
    2·min(C_L, C_R) with C = 2 × peak torque (allocation.delta_m_capacity)."""
    return 4.0 * motor_limit_nm()


def _style(label: str, i: int) -> dict[str, object]:
    return dict(CONTROLLER_STYLE.get(label, {"color": _EXTRA_COLOURS[i % 4], "lw": 1.2}))

#: File names written by :func:`write_plots` (in this order).
PLOT_NAMES = ("trajectory.png", "yaw_rate.png", "beta.png", "delta_m.png", "torques.png",
              "phase_plane.png", "swa.png", "vx.png", "ay.png", "lateral_deviation.png")
#: File names written by :func:`write_overlay_plots` (in this order).
OVERLAY_NAMES = ("overlay_trajectory.png", "overlay_swa.png", "overlay_phase_plane.png",
                 "overlay_delta_m.png", "overlay_yaw_rate.png", "overlay_beta.png")


def _new(figsize: tuple[float, float] = (9.0, 4.5)) -> Figure:
    fig = Figure(figsize=figsize, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    return path


def _time_axes(ax: Axes, title: str, ylabel: str) -> None:
    ax.set_title(title)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)


def _legend(ax: Axes, inside: bool = False) -> None:
    """Legend outside the axes on the right (it never covers data), or ``inside`` (upper
    right) where the data leaves room."""
    if ax.get_legend_handles_labels()[0]:
        if inside:
            ax.legend(loc="best", fontsize="small")
        else:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small",
                      borderaxespad=0.0)


def _no_data(ax: Axes) -> None:
    ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center",
            color="gray")


def _draw_course(ax: Axes, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                 cones: np.ndarray | None = None, struck: np.ndarray | None = None) -> None:
    """Boundary polylines (grey), cones (orange markers; struck ones red crosses), reference
    path dashed."""
    for i, line in enumerate(course):
        pts = np.asarray(line, dtype=float).reshape(-1, 2)
        if pts.size:
            ax.plot(pts[:, 0], pts[:, 1], color="0.55", lw=0.9,
                    label="course boundaries" if i == 0 else None)
    pts = np.asarray(cones if cones is not None else np.zeros((0, 2)), dtype=float)
    if pts.size:
        pts = pts.reshape(-1, 2)
        hit = (np.zeros(len(pts), dtype=bool) if struck is None
               else np.asarray(struck, dtype=bool))
        ax.plot(pts[~hit, 0], pts[~hit, 1], ls="none", color="tab:orange", marker="^", ms=6,
                label="cones", zorder=6)
        if hit.any():
            ax.plot(pts[hit, 0], pts[hit, 1], ls="none", color="red", marker="X", ms=9,
                    mec="black", mew=0.6, label=f"cones struck ({int(hit.sum())})", zorder=7)
    ref = np.asarray(ref_path if ref_path is not None else np.zeros((0, 2)), dtype=float)
    if ref.size:
        ref = ref.reshape(-1, 2)
        ax.plot(ref[:, 0], ref[:, 1], "k--", lw=0.8, label="reference path")


def _traj_axes(ax: Axes, title: str) -> None:
    """Top view at true scale: one metre is as long on both axes."""
    ax.set_title(title, fontsize="medium")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m] (+ left)")
    ax.set_aspect("equal", adjustable="box")
    ax.grid(True, alpha=0.3)


def _series(run: RunData, message: str, signal: str) -> tuple[np.ndarray, np.ndarray]:
    """(sim time, values) of a bus signal, frames with unknown sim time dropped."""
    t = run.bus_sig(message, "sim_time_s").astype(float)
    v = run.bus_sig(message, signal).astype(float)
    if t.size != v.size:
        return np.zeros(0), np.zeros(0)
    ok = np.isfinite(t)
    return t[ok], v[ok]


def _plot_traj(ax: Axes, run: RunData, label: str | None, **kw: object) -> bool:
    x, y = run.truth_col("x_m"), run.truth_col("y_m")
    if x.size == 0 or x.size != y.size:
        return False
    ax.plot(x, y, label=label, **kw)
    return True


def _draw_footprints(ax: Axes, run: RunData, fp: Footprint, color: str = "tab:blue",
                     label: bool = True) -> None:
    """Body outline every FOOTPRINT_EVERY_S along the run."""
    t = run.truth_col("t_s")
    x, y, yaw = run.truth_col("x_m"), run.truth_col("y_m"), run.truth_col("yaw_rad")
    if t.size < 2 or not t.size == x.size == y.size == yaw.size:
        return
    step = max(1, round(FOOTPRINT_EVERY_S / max(float(np.median(np.diff(t))), 1e-6)))
    for n, k in enumerate([*range(0, t.size, step), t.size - 1]):
        if not (np.isfinite(x[k]) and np.isfinite(y[k]) and np.isfinite(yaw[k])):
            continue
        c = fp.corners(float(x[k]), float(y[k]), float(yaw[k]))
        ax.fill(c[:, 0], c[:, 1], facecolor=color, alpha=0.12, edgecolor=color, lw=0.7,
                label=(f"body {fp.front_m + fp.rear_m:.2f} × {fp.width_m:.2f} m every "
                       f"{FOOTPRINT_EVERY_S:g} s (overhangs assumed)")
                if n == 0 and label else None)


def _draw_strikes(ax: Axes, run: RunData, cones: np.ndarray | None,
                  struck: np.ndarray | None, fp: Footprint, label: bool = True) -> None:
    """The body outline (red) at the first sample it covers each struck cone."""
    if struck is None or cones is None or not np.any(struck):
        return
    x, y, yaw = run.truth_col("x_m"), run.truth_col("y_m"), run.truth_col("yaw_rad")
    if x.size == 0 or not x.size == y.size == yaw.size:
        return
    first = True
    for cx, cy in np.asarray(cones, dtype=float).reshape(-1, 2)[np.asarray(struck, bool)]:
        dx, dy = cx - x, cy - y
        lon = np.cos(yaw) * dx + np.sin(yaw) * dy
        lat = -np.sin(yaw) * dx + np.cos(yaw) * dy
        inside = np.flatnonzero((lon <= fp.front_m) & (lon >= -fp.rear_m)
                                & (np.abs(lat) <= fp.width_m / 2))
        if not inside.size:
            continue
        c = fp.corners(float(x[inside[0]]), float(y[inside[0]]), float(yaw[inside[0]]))
        ax.plot(c[:, 0], c[:, 1], color="red", lw=1.2, zorder=6,
                label="body at a cone strike" if first and label else None)
        first = False


def _points(course: Sequence[np.ndarray], cones: np.ndarray | None,
            ref_path: np.ndarray | None, runs: Sequence[RunData] = ()) -> np.ndarray:
    """All finite (x, y) m of the course, its cones, the reference path and the runs' CG
    tracks, as (N, 2)."""
    parts = [np.asarray(c, dtype=float).reshape(-1, 2) for c in course]
    for extra in (cones, ref_path):
        if extra is not None and np.asarray(extra).size:
            parts.append(np.asarray(extra, dtype=float).reshape(-1, 2))
    for run in runs:
        x, y = run.truth_col("x_m"), run.truth_col("y_m")
        if x.size and x.size == y.size:
            parts.append(np.column_stack([x, y]))
    pts = np.concatenate(parts) if parts else np.zeros((0, 2))
    return pts[np.isfinite(pts).all(axis=1)]


def _limits(ax: Axes, pts: np.ndarray, x_range: tuple[float, float] | None = None,
            margin_m: float = 2.0) -> None:
    """Axis limits around ``pts`` (only those inside ``x_range`` m, if given)."""
    if x_range is not None and pts.size:
        pts = pts[(pts[:, 0] >= x_range[0]) & (pts[:, 0] <= x_range[1])]
    if not pts.size:
        return
    ax.set_xlim(*(x_range or (pts[:, 0].min() - margin_m, pts[:, 0].max() + margin_m)))
    ax.set_ylim(pts[:, 1].min() - margin_m, pts[:, 1].max() + margin_m)


def _zoom_ranges(lanes: Sequence[Any] | None, runs: Sequence[RunData]
                 ) -> list[tuple[float, float]]:
    """X ranges (m) of the zoom panels: from the exit of one gated lane to the end of the
    next (± 3 m), so each lane change and the gate it leads into are seen; without a course,
    ±25 m around the largest |β| of the first run."""
    if lanes:
        ordered = sorted(lanes, key=lambda ln: ln.x0)
        return [(float(a.x1) - 3.0, float(b.x1) + 3.0)
                for a, b in itertools.pairwise(ordered)][:2]
    for run in runs[:1]:
        x, beta = run.truth_col("x_m"), run.truth_col("beta_rad")
        if x.size and x.size == beta.size and np.isfinite(beta).any():
            xc = float(x[int(np.nanargmax(np.abs(beta)))])
            return [(xc - 25.0, xc + 25.0)]
    return []


def _applied_delta_m(run: RunData) -> tuple[np.ndarray, np.ndarray] | None:
    """(t s, ΔM N·m) from the motors' actual torques, ΔM = T_FR + T_RR − T_FL − T_RL (the
    DBC's yaw-moment lever)."""
    t = run.truth_col("t_s")
    cols = {w: run.truth_col(f"tact_{w}") for w in WHEELS}
    if t.size == 0 or any(c.size != t.size for c in cols.values()):
        return None
    return t, cols["fr"] + cols["rr"] - cols["fl"] - cols["rl"]


def motor_lag() -> tuple[float, float, float]:
    """(time constant τ s, integration step s, cycle s) of the plant's first-order motor lag
    (plant_sim/params/vehicle.toml [motors] time_constant_s; plant_sim/motor.py)."""
    p = load_plant_vehicle()
    return float(p.time_constant_s), float(p.step_s), float(p.comm_period_s)


def lagged_command(cmd_nm: np.ndarray, first_nm: float, tau_s: float, cycle_s: float
                   ) -> np.ndarray:
    """The command passed through the plant's motor lag, N·m.

    Truth row k holds the command applied over the cycle (t[k−1], t[k]] and the motor
    output at t[k]; the plant integrates T += (cmd − T)(1 − e^(−dt/τ)) each step, which over
    one cycle of constant command is exactly T[k] = cmd[k] + (T[k−1] − cmd[k]) e^(−cycle/τ).
    Row 0 starts from ``first_nm`` (the motor output the trace begins with). The power and
    regeneration envelope the plant applies after the lag is not modelled here: what remains
    of actual − lagged command is that envelope or a real fault.
    """
    cmd = np.asarray(cmd_nm, dtype=float)
    out = np.empty_like(cmd)
    if not cmd.size:
        return out
    a = math.exp(-cycle_s / tau_s) if tau_s > 0 else 0.0
    out[0] = first_nm
    for k in range(1, cmd.size):
        out[k] = cmd[k] + (out[k - 1] - cmd[k]) * a
    return out


def phase_bounds() -> dict[str, float]:
    """The phase-plane lines drawn on the β–β̇ plots, in deg and s.

    ``beta_limit_deg``: the stable verdict's |β| limit (harness/analysis/verdicts.py).
    ``guard_beta_deg`` and ``guard_lead_s``: the sideslip guard of the nmpc-rhonn references
    (controller/config/default.toml, controller/core/references/sideslip_guard.py) acts while
    |β + T·β̇| > β_g, i.e. outside the band |β̇ + β/T| ≤ β_g/T: the usual β–β̇ stability
    region with c = 1/T and d = β_g/T.
    """
    refs = tomllib.loads(resources.files("controller").joinpath("config/default.toml")
                        .read_text()).get("references", {})
    return {"beta_limit_deg": BETA_LIMIT_DEG,
            "guard_beta_deg": math.degrees(float(refs.get("guard_beta_rad", 0.0))),
            "guard_lead_s": float(refs.get("guard_lead_s", 0.0))}


def _draw_phase_bounds(ax: Axes, bx: np.ndarray, by: np.ndarray) -> None:
    """Stable-rule lines |β| = 8° and the guard's band |β + T·β̇| ≤ β_g, axes set to show
    the data and the bounds."""
    b = phase_bounds()
    lim_x = max(float(np.nanmax(np.abs(bx))) if bx.size else 0.0, b["beta_limit_deg"]) * 1.12
    band_y = b["guard_beta_deg"] / b["guard_lead_s"] if b["guard_lead_s"] > 0 else 0.0
    lim_y = max(float(np.nanmax(np.abs(by))) if by.size else 0.0, 1.5 * band_y, 1.0) * 1.12
    ax.set_xlim(-lim_x, lim_x)
    ax.set_ylim(-lim_y, lim_y)
    ax.axvline(b["beta_limit_deg"], **LIMIT_STYLE,
               label=f"stable rule |β| ≤ {b['beta_limit_deg']:g}°")
    ax.axvline(-b["beta_limit_deg"], **LIMIT_STYLE)
    if band_y > 0:
        xs = np.array([-lim_x, lim_x])
        for sign in (1.0, -1.0):
            ax.plot(xs, (sign * b["guard_beta_deg"] - xs) / b["guard_lead_s"], color="tab:green",
                    ls="--", lw=1.0,
                    label=(f"sideslip guard bound |β + {b['guard_lead_s']:g} s·β̇| = "
                           f"{b['guard_beta_deg']:.0f}° (nmpc-rhonn default.toml)")
                    if sign > 0 else None)


def _style_phase_plane(ax: Axes, title: str = "β–β̇ phase plane") -> None:
    """Title, axis labels, grid and legend of a β–β̇ phase-plane axis."""
    ax.set_title(title, fontsize="medium")
    ax.set_xlabel("β [deg]")
    ax.set_ylabel("β̇ [deg/s]")
    ax.grid(True, alpha=0.3)
    _legend(ax)


def _with_note(title: str, note: str | None) -> str:
    """``title`` with the partial-run note (harness/analysis/run_status.py) on a line of its
    own."""
    return f"{title}\n{note}" if note else title


def _panel_height_in(pts: np.ndarray, x_range: tuple[float, float] | None, width_in: float,
                     margin_m: float = 2.0) -> float:
    """Height (in) of an equal-aspect panel ``width_in`` wide over ``pts`` in ``x_range``."""
    if x_range is not None and pts.size:
        pts = pts[(pts[:, 0] >= x_range[0]) & (pts[:, 0] <= x_range[1])]
    if not pts.size:
        return 1.0
    dx = (x_range[1] - x_range[0]) if x_range else float(np.ptp(pts[:, 0])) + 2 * margin_m
    dy = float(np.ptp(pts[:, 1])) + 2 * margin_m
    return float(np.clip(width_in * dy / max(dx, 1e-6), 0.6, 6.0))


def _trajectory_figure(runs: Mapping[str, RunData], course: Sequence[np.ndarray],
                       ref_path: np.ndarray | None, cones: np.ndarray | None,
                       lanes: Sequence[Any] | None, struck: np.ndarray | None,
                       title: str, labels: Mapping[str, str], bodies: bool) -> Figure:
    """Top view at true scale (1 m is as long on both axes) over the whole course, the
    legend under it, and zoom panels at the same scale on each lane change (or, without a
    course, around the largest |β|) where the car bodies can be told apart."""
    run_list = list(runs.values())
    zooms = _zoom_ranges(lanes, run_list)
    pts = _points(course, cones, ref_path, run_list)
    width_in = 13.0
    h_over = _panel_height_in(pts, None, width_in - 1.0)
    h_zoom = max((_panel_height_in(pts, xr, (width_in - 1.0) / len(zooms) - 0.8)
                  for xr in zooms), default=0.0)
    heights = [h_over + 0.7, 0.6] + ([h_zoom + 0.8] if zooms else [])
    fig = _new((width_in, min(sum(heights) + 0.8, 11.0)))
    grid = fig.add_gridspec(len(heights), max(1, len(zooms)), height_ratios=heights)
    ax = fig.add_subplot(grid[0, :])
    leg_ax = fig.add_subplot(grid[1, :])
    leg_ax.set_axis_off()
    zaxes = [fig.add_subplot(grid[2, i]) for i in range(len(zooms))]
    for panel, (a, xr) in enumerate([(ax, None), *zip(zaxes, zooms, strict=True)]):
        _draw_course(a, course, ref_path, cones, struck)
        drawn = False
        for i, (label, run) in enumerate(runs.items()):
            style = _style(label, i)
            if bodies and i == 0:
                _draw_footprints(a, run, packaged_footprint(), str(style["color"]),
                                 label=panel == 0)
                _draw_strikes(a, run, cones, struck, packaged_footprint(), label=panel == 0)
            drawn |= _plot_traj(a, run, labels.get(label, label) if panel == 0 else None,
                                **style)
        if not drawn:
            _no_data(a)
        _limits(a, pts, xr)
        _traj_axes(a, "whole course, true scale" if xr is None else
                   f"zoom X {xr[0]:.0f} … {xr[1]:.0f} m, true scale")
    handles, texts = ax.get_legend_handles_labels()
    if handles:
        leg_ax.legend(handles, texts, loc="center", ncol=3, fontsize="small", frameon=False)
    fig.suptitle(title)
    return fig


def write_plots(run: RunData, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                out_dir: str | Path, *, cones: np.ndarray | None = None,
                lanes: Sequence[Any] | None = None, course_end_arc_m: float | None = None,
                metrics: Mapping[str, Any] | None = None) -> list[Path]:
    """Write the single-run plots (:data:`PLOT_NAMES`) into ``out_dir``; returns their paths.

    ``course``: boundary polylines, each (N, 2) m, drawn as lines; ``cones``: (M, 2) m cone
    positions drawn as markers only (an unordered cone list drawn as a line would zigzag);
    ``lanes``: the gated lane sections (zoom panels on the lane changes); ``ref_path``:
    (N, 2) m; ``course_end_arc_m``: arc length of the course end, m (verdict window).
    ``metrics``: the run's metrics.json dict: its ``verdicts`` block titles the trajectory
    and phase plots (computed here when absent), ``interrupted`` marks every title as a
    partial run. A run without truth data gets no plots at all (returns []).
    """
    t = run.truth_col("t_s")
    if t.size == 0:
        return []
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = dict(metrics or {})
    name = str(run.meta.get("controller", run.meta.get("name", "run")))
    note = partial_note(metrics) or partial_note(run.meta)
    verdicts = metrics.get("verdicts") or verdict_block(
        run, cones=cones, lanes=list(lanes or []), course_end_arc_m=course_end_arc_m,
        planned_end_s=run.meta.get("scenario_end_s"))
    # the crosses are the cones the block counts (none where the block has no course rule)
    has_rule = (verdicts.get("course_rule") or {}).get("cones_struck") is not None
    struck = window_struck(run, cones, course_end_arc_m) if has_rule else None
    paths: list[Path] = []

    fig = _trajectory_figure({name: run}, course, ref_path, cones, lanes, struck,
                             _with_note(f"Trajectory ({name}) — {verdict_summary(verdicts)}",
                                        note),
                             {name: f"vehicle CG ({name})"}, bodies=True)
    paths.append(_save(fig, out / "trajectory.png"))

    def time_plot(fname: str, title: str, ylabel: str,
                  series: Sequence[tuple[np.ndarray, np.ndarray, str, dict[str, object]]],
                  hlines: Sequence[tuple[float, str]] = ()) -> None:
        fig = _new()
        ax = fig.add_subplot()
        for tt, v, label, kw in series:
            if tt.size and tt.size == v.size:
                ax.plot(tt, v, label=label, **kw)
        for i, (y, label) in enumerate(hlines):
            ax.axhline(y, **LIMIT_STYLE, label=label if i % 2 == 0 else None)
        _time_axes(ax, _with_note(f"{title} ({name})", note), ylabel)
        _legend(ax)
        paths.append(_save(fig, out / fname))

    blue: dict[str, object] = {"color": "tab:blue"}
    ref_kw: dict[str, object] = {"color": "tab:red", "ls": "--"}
    for fname, title, ylabel, col, sig in (
            ("yaw_rate.png", "Yaw rate vs reference", "yaw rate [deg/s]", "yaw_rate_radps",
             "YAW_RATE_REF"),
            ("beta.png", "Sideslip angle β vs reference", "β [deg]", "beta_rad", "BETA_REF")):
        tr, ref = _series(run, "CTRL_REFS", sig)
        time_plot(fname, title, ylabel, [(t, run.truth_col(col) * DEG, "actual (truth)", blue),
                                         (tr, ref, "reference (CTRL_REFS)", ref_kw)])

    tr, dM = _series(run, "CTRL_REFS", "DELTA_M")
    applied = _applied_delta_m(run) or (np.zeros(0), np.zeros(0))
    box = delta_m_box_nm()
    time_plot("delta_m.png", "Direct yaw moment ΔM", "ΔM [N·m]",
              [(tr, dM, "ΔM commanded (CTRL_REFS)", {"color": "tab:purple"}),
               (applied[0], applied[1], "ΔM applied (motor torques)",
                {"color": "black", "lw": 0.8, "ls": "--"})],
              [(box, f"ΔM box ±{box:.0f} N·m (motor capacity)"), (-box, "")] if tr.size
              else ())

    tau, _, cycle = motor_lag()
    fig = _new((12.0, 6.5))
    axes = fig.subplots(2, 2, sharex=True, sharey=True)
    limit = motor_limit_nm()
    for i, (ax, w) in enumerate(zip(axes.flat, WHEELS, strict=True)):
        cmd, act = run.truth_col(f"tcmd_{w}"), run.truth_col(f"tact_{w}")
        resid = ""
        if cmd.size == t.size:
            # row k's command acts over (t[k−1], t[k]]: drawn as steps ending at t[k]
            ax.plot(t, cmd, color="tab:orange", lw=3.5, alpha=0.45, drawstyle="steps-pre",
                    label="commanded (applied frame)")
        if act.size == t.size:
            ax.plot(t, act, color="black", lw=0.9, label="motor actual")
            if cmd.size == act.size:
                model = lagged_command(cmd, float(act[0]), tau, cycle)
                ax.plot(t, model, color="tab:cyan", lw=0.9, ls="--",
                        label=f"command through the {tau * 1e3:.0f} ms motor lag")
                resid = (f": max |actual − lagged command| "
                         f"{np.nanmax(np.abs(act - model)):.1f} N·m")
        ax.axhline(limit, **LIMIT_STYLE, label=f"motor limit ±{limit:.0f} N·m")
        ax.axhline(-limit, **LIMIT_STYLE)
        _time_axes(ax, f"Wheel {w.upper()}{resid}", "torque [N·m]")
        ax.title.set_fontsize("medium")
        if i == 1:
            _legend(ax)
    fig.suptitle(_with_note(f"In-wheel motor torques ({name}); the residual is measured "
                            f"against the command through the plant's {tau * 1e3:.0f} ms "
                            "first-order lag", note), fontsize="medium")
    paths.append(_save(fig, out / "torques.png"))

    fig = _new((10.0, 5.5))
    ax = fig.add_subplot()
    beta = run.truth_col("beta_rad")
    bx = by = np.zeros(0)
    if beta.size >= 3 and beta.size == t.size:
        area = phase_area(beta, t) * DEG * DEG
        bx, by = beta * DEG, beta_rate(beta, t) * DEG
        ax.plot(bx, by, color="tab:blue",
                label=f"{name}: hull area {area:.4g} deg²/s ({area / DEG / DEG:.4g} rad²/s)")
        # start: an open ring, end: a filled square inside it (a run that ends at rest
        # ends where it started)
        ax.plot(bx[:1], by[:1], ls="none", marker="o", ms=13, mfc="none", mec="tab:green",
                mew=2.0, label=f"start t = {t[0]:.2f} s", zorder=6)
        ax.plot(bx[-1:], by[-1:], ls="none", marker="s", ms=6, color="tab:red",
                mec="black", label=f"end t = {t[-1]:.2f} s", zorder=7)
    _draw_phase_bounds(ax, bx, by)
    stable = (verdicts.get("stable") or {}).get("passed")
    _style_phase_plane(ax, _with_note(f"β–β̇ phase plane ({name}) — stable: "
                                      f"{verdict_word(stable)}", note))
    paths.append(_save(fig, out / "phase_plane.png"))

    time_plot("swa.png", "Driver steering-wheel angle", "δsw [deg]",
              [(t, run.truth_col("swa_rad") * DEG, "steering-wheel angle", blue)])
    time_plot("vx.png", "Longitudinal speed Vx", "Vx [km/h]",
              [(t, run.truth_col("vx_mps") * 3.6, "Vx (truth, body axes)", blue)])
    mu = np.nanmean(np.vstack([run.truth_col(f"mu_{w}") for w in WHEELS]), axis=0) \
        if all(run.truth_col(f"mu_{w}").size == t.size for w in WHEELS) else np.zeros(0)
    time_plot("ay.png", "Lateral acceleration ay", "ay [m/s²]",
              [(t, run.truth_col("ay_mps2"), "ay (truth, CG, body axes)", blue),
               (t, mu * G, "grip μ·g (mean of the four wheels' μ)", {**LIMIT_STYLE}),
               (t, -mu * G, "", {**LIMIT_STYLE})])

    fig = _new()
    ax = fig.add_subplot()
    s, dev = run.truth_col("path_s_m"), run.truth_col("lateral_dev_m")
    if s.size and s.size == dev.size:
        ax.plot(s, dev, color="tab:blue", label="lateral deviation of the CG (truth)")
    if cones is not None and np.asarray(cones).size:
        ax.axhline(PAPER_DEV_M, **LIMIT_STYLE, label=f"paper rule ±{PAPER_DEV_M:g} m")
        ax.axhline(-PAPER_DEV_M, **LIMIT_STYLE)
        if course_end_arc_m is not None:
            ax.axvline(course_end_arc_m, color="0.4", ls="-.", lw=0.9,
                       label=f"course end, station {course_end_arc_m:.1f} m")
    ax.set_title(_with_note(f"Lateral deviation from the reference path vs station ({name})",
                            note))
    ax.set_xlabel("station along the reference path [m]")
    ax.set_ylabel("lateral deviation [m] (+ left)")
    ax.grid(True, alpha=0.3)
    _legend(ax)
    paths.append(_save(fig, out / "lateral_deviation.png"))
    return paths


def _scale_to_controlled(ax: Axes, runs: Mapping[str, RunData], values: dict[str, np.ndarray],
                         axis: str = "y", margin: float = 0.12) -> None:
    """Set the ``axis`` range from the controlled runs only (an uncontrolled car that spins
    would squash them) and say in the axes which runs leave it."""
    controlled = [v[np.isfinite(v)] for k, v in values.items()
                  if k not in UNCONTROLLED and v.size]
    controlled = [v for v in controlled if v.size]
    if not controlled or len(controlled) == len(values):
        return
    lo = min(float(v.min()) for v in controlled)
    hi = max(float(v.max()) for v in controlled)
    pad = max(hi - lo, 1e-6) * margin
    lo, hi = lo - pad, hi + pad
    (ax.set_ylim if axis == "y" else ax.set_xlim)(lo, hi)
    out = [k for k, v in values.items() if k in UNCONTROLLED and v.size
           and (np.nanmin(v) < lo or np.nanmax(v) > hi)]
    if out:
        v = values[out[0]]
        ax.text(0.01, 0.02 if axis == "y" else 0.07,
                f"{axis} scaled to the controlled runs; {', '.join(out)} leaves it "
                f"(range {np.nanmin(v):.3g} … {np.nanmax(v):.3g})",
                transform=ax.transAxes, fontsize="x-small", color="0.35", va="bottom")


def _overlay_time(runs: Mapping[str, RunData], path: Path, title: str, ylabel: str,
                  get: Callable[[RunData], tuple[np.ndarray, np.ndarray]],
                  limit: float | None = None, limit_label: str = "") -> Path:
    fig = _new((11.0, 4.5))
    ax = fig.add_subplot()
    values: dict[str, np.ndarray] = {}
    times: dict[str, np.ndarray] = {}
    for i, (label, run) in enumerate(runs.items()):
        t, v = get(run)
        if t.size and t.size == v.size:
            ax.plot(t, v, label=label, **_style(label, i))
            values[label] = np.asarray(v, dtype=float)
            times[label] = np.asarray(t, dtype=float)
    if not values:
        _no_data(ax)
    if limit is not None:
        ax.axhline(limit, **LIMIT_STYLE, label=limit_label)
        ax.axhline(-limit, **LIMIT_STYLE)
    _scale_to_controlled(ax, runs, values)
    _scale_to_controlled(ax, runs, times, axis="x", margin=0.02)
    _time_axes(ax, title, ylabel)
    _legend(ax)
    return _save(fig, path)


def _truth_deg(col: str) -> Callable[[RunData], tuple[np.ndarray, np.ndarray]]:
    return lambda r: (r.truth_col("t_s"), r.truth_col(col) * DEG)


def write_overlay_plots(runs: Mapping[str, RunData], course: Sequence[np.ndarray],
                        ref_path: np.ndarray | None, out_dir: str | Path, *,
                        cones: np.ndarray | None = None, lanes: Sequence[Any] | None = None,
                        course_end_arc_m: float | None = None) -> list[Path]:
    """Overlay several runs (label -> run) like the paper's Figs 7 and 9.

    ``course``/``cones``/``lanes``/``ref_path``/``course_end_arc_m`` as in
    :func:`write_plots`.
    Writes :data:`OVERLAY_NAMES` into ``out_dir``; yaw rate and β are the truth of each run
    (the reference of each controller differs, so it is not overlaid).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    struck_by: dict[str, int] = {}
    any_struck = None
    for label, run in runs.items():
        hit = window_struck(run, cones, course_end_arc_m)
        if hit is not None:
            struck_by[label] = int(hit.sum())
            if label not in UNCONTROLLED:
                any_struck = hit if any_struck is None else (any_struck | hit)
    labels = {k: f"{k}, {struck_by[k]} cones struck" if k in struck_by else k for k in runs}
    fig = _trajectory_figure(runs, course, ref_path, cones, lanes, any_struck,
                             "Trajectories (CG); red crosses: cones struck by a controlled "
                             "run (course rule window)", labels, bodies=False)
    paths.append(_save(fig, out / "overlay_trajectory.png"))

    paths.append(_overlay_time(runs, out / "overlay_swa.png", "Steering-wheel angle",
                               "δsw [deg]", _truth_deg("swa_rad")))

    fig = _new((6.5, 5.5))
    ax = fig.add_subplot()
    bx: dict[str, np.ndarray] = {}
    by: dict[str, np.ndarray] = {}
    for i, (label, run) in enumerate(runs.items()):
        t, beta = run.truth_col("t_s"), run.truth_col("beta_rad")
        if beta.size >= 3 and beta.size == t.size:
            bx[label], by[label] = beta * DEG, beta_rate(beta, t) * DEG
            ax.plot(bx[label], by[label], **_style(label, i),
                    label=f"{label}: hull area {phase_area(beta, t) * DEG * DEG:.3g} deg²/s")
    if not bx:
        _no_data(ax)
    _scale_to_controlled(ax, runs, bx, axis="x")
    _scale_to_controlled(ax, runs, by, axis="y")
    _style_phase_plane(ax)
    paths.append(_save(fig, out / "overlay_phase_plane.png"))

    box = delta_m_box_nm()
    paths.append(_overlay_time(runs, out / "overlay_delta_m.png", "Direct yaw moment ΔM",
                               "ΔM [N·m]", lambda r: _series(r, "CTRL_REFS", "DELTA_M"),
                               limit=box, limit_label=f"ΔM box ±{box:.0f} N·m"))
    paths.append(_overlay_time(runs, out / "overlay_yaw_rate.png", "Yaw rate",
                               "yaw rate [deg/s]", _truth_deg("yaw_rate_radps")))
    paths.append(_overlay_time(runs, out / "overlay_beta.png", "Sideslip angle β", "β [deg]",
                               _truth_deg("beta_rad")))
    return paths
