"""PNG plots of one run and overlays of several controllers (paper Figs 7 and 9 style).

Uses matplotlib's object API (``Figure`` + Agg canvas, never pyplot) so it runs headless and
leaves no global state behind.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from harness.analysis.footprint import Footprint, packaged_footprint, struck_cones
from harness.analysis.kpi import beta_rate, phase_area
from harness.analysis.run_data import RunData

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
    from controller.core.params import load_vehicle_params

    return float(load_vehicle_params().peak_torque_nm)


def delta_m_box_nm() -> float:
    """|ΔM| the four motors can give at zero pedal torque below base speed, N·m:
    2·min(C_L, C_R) with C = 2 × peak torque (allocation.delta_m_capacity)."""
    return 4.0 * motor_limit_nm()


def _style(label: str, i: int) -> dict[str, object]:
    return dict(CONTROLLER_STYLE.get(label, {"color": _EXTRA_COLOURS[i % 4], "lw": 1.2}))

#: File names written by :func:`write_plots` (in this order).
PLOT_NAMES = ("trajectory.png", "yaw_rate.png", "beta.png", "delta_m.png", "torques.png",
              "phase_plane.png", "swa.png")
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
    ax.set_title(title)
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m] (+ left; scale stretched)")
    ax.grid(True, alpha=0.3)


def _series(run: RunData, message: str, signal: str) -> tuple[np.ndarray, np.ndarray]:
    """(sim time, values) of a bus signal, frames with unknown sim time dropped."""
    t = run.bus_sig(message, "sim_time_s").astype(float)
    v = run.bus_sig(message, signal).astype(float)
    if t.size != v.size:
        return np.zeros(0), np.zeros(0)
    ok = np.isfinite(t)
    return t[ok], v[ok]


def _plot_traj(ax: Axes, run: RunData, label: str, **kw: object) -> bool:
    x, y = run.truth_col("x_m"), run.truth_col("y_m")
    if x.size == 0 or x.size != y.size:
        return False
    ax.plot(x, y, label=label, **kw)
    return True


def _struck(run: RunData, cones: np.ndarray | None, fp: Footprint) -> np.ndarray | None:
    """Mask of the cones this run's footprint covered (None without a trace or cones)."""
    x, y, yaw = run.truth_col("x_m"), run.truth_col("y_m"), run.truth_col("yaw_rad")
    if cones is None or not np.asarray(cones).size or x.size == 0 \
            or not x.size == y.size == yaw.size:
        return None
    return struck_cones(x, y, yaw, cones, fp)


def _draw_footprints(ax: Axes, run: RunData, fp: Footprint, color: str = "tab:blue") -> None:
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
                       f"{FOOTPRINT_EVERY_S:g} s (overhangs assumed)") if n == 0 else None)


def _course_limits(ax: Axes, course: Sequence[np.ndarray], cones: np.ndarray | None,
                   ref_path: np.ndarray | None, margin_x_m: float = 4.0,
                   margin_y_m: float = 1.5) -> None:
    """Bound the top view to the course (cones, boundaries, reference path). The lateral
    scale is stretched (a 190 m × 6 m lane change would be a thin strip at equal scale);
    the footprints are drawn in data coordinates, so cone clearances stay true."""
    parts = [np.asarray(c, dtype=float).reshape(-1, 2) for c in course]
    for extra in (cones, ref_path):
        if extra is not None and np.asarray(extra).size:
            parts.append(np.asarray(extra, dtype=float).reshape(-1, 2))
    pts = np.concatenate(parts) if parts else np.zeros((0, 2))
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.size:
        ax.set_xlim(pts[:, 0].min() - margin_x_m, pts[:, 0].max() + margin_x_m)
        ax.set_ylim(pts[:, 1].min() - margin_y_m, pts[:, 1].max() + margin_y_m)


def _applied_delta_m(run: RunData) -> tuple[np.ndarray, np.ndarray] | None:
    """(t s, ΔM N·m) from the motors' actual torques, ΔM = T_FR + T_RR − T_FL − T_RL (the
    DBC's yaw-moment lever)."""
    t = run.truth_col("t_s")
    cols = {w: run.truth_col(f"tact_{w}") for w in WHEELS}
    if t.size == 0 or any(c.size != t.size for c in cols.values()):
        return None
    return t, cols["fr"] + cols["rr"] - cols["fl"] - cols["rl"]


def _style_phase_plane(ax: Axes) -> None:
    """Title, axis labels, grid and legend of a β–β̇ phase-plane axis."""
    ax.set_title("β–β̇ phase plane")
    ax.set_xlabel("β [deg]")
    ax.set_ylabel("β̇ [deg/s]")
    ax.grid(True, alpha=0.3)
    _legend(ax)


def write_plots(run: RunData, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                out_dir: str | Path, *, cones: np.ndarray | None = None) -> list[Path]:
    """Write the single-run plots (:data:`PLOT_NAMES`) into ``out_dir``; returns their paths.

    ``course``: boundary polylines, each (N, 2) m, drawn as lines; ``cones``: (M, 2) m cone
    positions drawn as markers only (an unordered cone list drawn as a line would zigzag);
    ``ref_path``: (N, 2) m. Missing data draws an annotated empty axis rather than failing.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = str(run.meta.get("controller", run.meta.get("name", "run")))
    t = run.truth_col("t_s")
    paths: list[Path] = []

    fp = packaged_footprint()
    fig = _new((13.0, 5.0))
    ax = fig.add_subplot()
    struck = _struck(run, cones, fp)
    _draw_course(ax, course, ref_path, cones, struck)
    _draw_footprints(ax, run, fp)
    if not _plot_traj(ax, run, f"vehicle CG ({name})", color="tab:blue", lw=1.5):
        _no_data(ax)
    _course_limits(ax, course, cones, ref_path)
    n_struck = "" if struck is None else f": {int(struck.sum())} of {struck.size} cones struck"
    _traj_axes(ax, f"Trajectory and course{n_struck}")
    _legend(ax)
    paths.append(_save(fig, out / "trajectory.png"))

    for fname, title, ylabel, col, sig in (
            ("yaw_rate.png", "Yaw rate vs reference", "yaw rate [deg/s]", "yaw_rate_radps",
             "YAW_RATE_REF"),
            ("beta.png", "Sideslip angle β vs reference", "β [deg]", "beta_rad", "BETA_REF")):
        fig = _new()
        ax = fig.add_subplot()
        actual = run.truth_col(col)
        if actual.size and actual.size == t.size:
            ax.plot(t, actual * DEG, color="tab:blue", label="actual (truth)")
        tr, ref = _series(run, "CTRL_REFS", sig)
        if tr.size:
            ax.plot(tr, ref, color="tab:red", ls="--", label="reference (CTRL_REFS)")
        if not (actual.size or tr.size):
            _no_data(ax)
        _time_axes(ax, f"{title} ({name})", ylabel)
        _legend(ax)
        paths.append(_save(fig, out / fname))

    fig = _new()
    ax = fig.add_subplot()
    tr, dM = _series(run, "CTRL_REFS", "DELTA_M")
    if tr.size:
        ax.plot(tr, dM, color="tab:purple", label="ΔM commanded (CTRL_REFS)")
        applied = _applied_delta_m(run)
        if applied is not None:
            ax.plot(applied[0], applied[1], color="black", lw=0.8, ls="--",
                    label="ΔM applied (motor torques)")
        box = delta_m_box_nm()
        ax.axhline(box, **LIMIT_STYLE, label=f"ΔM box ±{box:.0f} N·m (motor capacity)")
        ax.axhline(-box, **LIMIT_STYLE)
    else:
        _no_data(ax)
    _time_axes(ax, f"Direct yaw moment ΔM ({name})", "ΔM [N·m]")
    _legend(ax)
    paths.append(_save(fig, out / "delta_m.png"))

    fig = _new((12.0, 6.5))
    axes = fig.subplots(2, 2, sharex=True, sharey=True)
    limit = motor_limit_nm()
    for i, (ax, w) in enumerate(zip(axes.flat, WHEELS, strict=True)):
        cmd, act = run.truth_col(f"tcmd_{w}"), run.truth_col(f"tact_{w}")
        lag = ""
        if cmd.size == t.size and t.size:
            ax.plot(t, cmd, color="tab:orange", lw=3.5, alpha=0.45, drawstyle="steps-post",
                    label="commanded (applied frame)")
        if act.size == t.size and t.size:
            ax.plot(t, act, color="black", lw=0.9, label="motor actual")
            if cmd.size == act.size:
                lag = f" — max |actual − cmd| {np.nanmax(np.abs(act - cmd)):.0f} N·m"
        if not t.size:
            _no_data(ax)
        ax.axhline(limit, **LIMIT_STYLE, label=f"motor limit ±{limit:.0f} N·m")
        ax.axhline(-limit, **LIMIT_STYLE)
        _time_axes(ax, f"wheel {w.upper()}{lag}", "torque [N·m]")
        if i == 1:
            _legend(ax)
    fig.suptitle(f"In-wheel motor torques ({name})")
    paths.append(_save(fig, out / "torques.png"))

    fig = _new((6.5, 5.5))
    ax = fig.add_subplot()
    beta = run.truth_col("beta_rad")
    if beta.size >= 3 and beta.size == t.size:
        area = phase_area(beta, t) * DEG * DEG
        ax.plot(beta * DEG, beta_rate(beta, t) * DEG, color="tab:blue",
                label=f"{name}: hull area {area:.4g} deg²/s ({area / DEG / DEG:.4g} rad²/s)")
    else:
        _no_data(ax)
    _style_phase_plane(ax)
    paths.append(_save(fig, out / "phase_plane.png"))

    fig = _new()
    ax = fig.add_subplot()
    swa = run.truth_col("swa_rad")
    if swa.size and swa.size == t.size:
        ax.plot(t, swa * DEG, color="tab:blue", label="steering-wheel angle")
    else:
        _no_data(ax)
    _time_axes(ax, f"Driver steering-wheel angle ({name})", "δsw [deg]")
    _legend(ax)
    paths.append(_save(fig, out / "swa.png"))
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
                        cones: np.ndarray | None = None) -> list[Path]:
    """Overlay several runs (label -> run) like the paper's Figs 7 and 9.

    ``course``/``cones``/``ref_path`` as in :func:`write_plots`.
    Writes :data:`OVERLAY_NAMES` into ``out_dir``; yaw rate and β are the truth of each run
    (the reference of each controller differs, so it is not overlaid).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    fp = packaged_footprint()
    fig = _new((13.0, 5.0))
    ax = fig.add_subplot()
    struck_by: dict[str, int] = {}
    any_struck = None
    for label, run in runs.items():
        hit = _struck(run, cones, fp)
        if hit is not None:
            struck_by[label] = int(hit.sum())
            if label not in UNCONTROLLED:
                any_struck = hit if any_struck is None else (any_struck | hit)
    _draw_course(ax, course, ref_path, cones, any_struck)
    for i, (label, run) in enumerate(runs.items()):
        n = f", {struck_by[label]} cones struck" if label in struck_by else ""
        _plot_traj(ax, run, f"{label}{n}", **_style(label, i))
    _course_limits(ax, course, cones, ref_path)
    _traj_axes(ax, "Trajectories (CG) in the course; red crosses: cones struck by a "
                   "controlled run")
    _legend(ax)
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
