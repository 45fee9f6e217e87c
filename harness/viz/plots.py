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

from harness.analysis.kpi import beta_rate, phase_area
from harness.analysis.run_data import RunData

DEG = 180.0 / math.pi
WHEELS = ("fl", "fr", "rl", "rr")
DPI = 120

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


def _legend(ax: Axes) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")


def _no_data(ax: Axes) -> None:
    ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center",
            color="gray")


def _draw_course(ax: Axes, course: Sequence[np.ndarray], ref_path: np.ndarray | None,
                 cones: np.ndarray | None = None) -> None:
    """Boundary polylines (orange lines, vertices marked), cones (markers only), ref dashed."""
    for i, line in enumerate(course):
        pts = np.asarray(line, dtype=float).reshape(-1, 2)
        if pts.size:
            ax.plot(pts[:, 0], pts[:, 1], color="tab:orange", lw=1.0, marker=".", ms=3,
                    label="course boundaries" if i == 0 else None)
    pts = np.asarray(cones if cones is not None else np.zeros((0, 2)), dtype=float)
    if pts.size:
        pts = pts.reshape(-1, 2)
        ax.plot(pts[:, 0], pts[:, 1], ls="none", color="tab:orange", marker="^", ms=5,
                label="cones")
    ref = np.asarray(ref_path if ref_path is not None else np.zeros((0, 2)), dtype=float)
    if ref.size:
        ref = ref.reshape(-1, 2)
        ax.plot(ref[:, 0], ref[:, 1], "k--", lw=0.8, label="reference path")


def _traj_axes(ax: Axes, title: str) -> None:
    ax.set_title(title)
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m] (+ left)")
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

    fig = _new((11.0, 4.5))
    ax = fig.add_subplot()
    _draw_course(ax, course, ref_path, cones)
    if not _plot_traj(ax, run, f"vehicle CG ({name})", color="tab:blue", lw=1.5):
        _no_data(ax)
    _traj_axes(ax, "Trajectory and course")
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
        ax.plot(tr, dM, color="tab:purple", label="ΔM commanded")
    else:
        _no_data(ax)
    _time_axes(ax, f"Direct yaw moment ΔM ({name})", "ΔM [N·m]")
    _legend(ax)
    paths.append(_save(fig, out / "delta_m.png"))

    fig = _new((10.0, 6.0))
    axes = fig.subplots(2, 2, sharex=True)
    for i, (ax, w) in enumerate(zip(axes.flat, WHEELS, strict=True)):
        cmd, act = run.truth_col(f"tcmd_{w}"), run.truth_col(f"tact_{w}")
        if cmd.size == t.size and t.size:
            ax.plot(t, cmd, color="tab:blue", label="command applied")
        if act.size == t.size and t.size:
            ax.plot(t, act, color="tab:green", ls="--", lw=1.0, label="motor actual")
        if not t.size:
            _no_data(ax)
        _time_axes(ax, f"wheel {w.upper()}", "torque [N·m]")
        if i == 0:
            _legend(ax)
    fig.suptitle(f"In-wheel motor torques ({name})")
    paths.append(_save(fig, out / "torques.png"))

    fig = _new((6.5, 5.5))
    ax = fig.add_subplot()
    beta = run.truth_col("beta_rad")
    if beta.size >= 3 and beta.size == t.size:
        area = phase_area(beta, t)
        ax.plot(beta * DEG, beta_rate(beta, t) * DEG, color="tab:blue",
                label=f"{name}: hull area {area:.4g} rad²/s")
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


def _overlay_time(runs: Mapping[str, RunData], path: Path, title: str, ylabel: str,
                  get: Callable[[RunData], tuple[np.ndarray, np.ndarray]]) -> Path:
    fig = _new()
    ax = fig.add_subplot()
    drawn = False
    for label, run in runs.items():
        t, v = get(run)
        if t.size and t.size == v.size:
            ax.plot(t, v, label=label)
            drawn = True
    if not drawn:
        _no_data(ax)
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

    fig = _new((11.0, 4.5))
    ax = fig.add_subplot()
    _draw_course(ax, course, ref_path, cones)
    for label, run in runs.items():
        _plot_traj(ax, run, label, lw=1.3)
    _traj_axes(ax, "Trajectories")
    _legend(ax)
    paths.append(_save(fig, out / "overlay_trajectory.png"))

    paths.append(_overlay_time(runs, out / "overlay_swa.png", "Steering-wheel angle",
                               "δsw [deg]", _truth_deg("swa_rad")))

    fig = _new((6.5, 5.5))
    ax = fig.add_subplot()
    drawn = False
    for label, run in runs.items():
        t, beta = run.truth_col("t_s"), run.truth_col("beta_rad")
        if beta.size >= 3 and beta.size == t.size:
            ax.plot(beta * DEG, beta_rate(beta, t) * DEG,
                    label=f"{label} (area {phase_area(beta, t):.3g} rad²/s)")
            drawn = True
    if not drawn:
        _no_data(ax)
    _style_phase_plane(ax)
    paths.append(_save(fig, out / "overlay_phase_plane.png"))

    paths.append(_overlay_time(runs, out / "overlay_delta_m.png", "Direct yaw moment ΔM",
                               "ΔM [N·m]", lambda r: _series(r, "CTRL_REFS", "DELTA_M")))
    paths.append(_overlay_time(runs, out / "overlay_yaw_rate.png", "Yaw rate",
                               "yaw rate [deg/s]", _truth_deg("yaw_rate_radps")))
    paths.append(_overlay_time(runs, out / "overlay_beta.png", "Sideslip angle β", "β [deg]",
                               _truth_deg("beta_rad")))
    return paths
