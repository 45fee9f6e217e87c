"""Figures of the paper reproduction (Figs 8/10 tracking, Table 4 probes, FMVSS 126 yaw-rate
ratios; the fidelity figure of Figs 5–6 is harness/viz/fidelity_plot.py). matplotlib object API
only (headless, no global state)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from harness.analysis.run_data import RunData

DEG = 180.0 / math.pi
DPI = 110


def _fig(w: float, h: float) -> Figure:
    fig = Figure(figsize=(w, h), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _series(run: RunData, message: str, signal: str) -> tuple[np.ndarray, np.ndarray]:
    t = run.bus_sig(message, "sim_time_s").astype(float)
    v = run.bus_sig(message, signal).astype(float)
    ok = np.isfinite(t) & np.isfinite(v)
    return t[ok], v[ok]


def tracking_figure(runs: Mapping[str, RunData], path: Path, title: str) -> Path:
    """Paper Figs 8/10: per controller, yaw rate and β (truth) vs its CTRL_REFS references."""
    names = list(runs)
    fig = _fig(11.0, 2.6 * max(1, len(names)))
    axes = np.atleast_2d(fig.subplots(max(1, len(names)), 2, sharex=True, squeeze=False))
    for row, name in enumerate(names):
        run = runs[name]
        t = run.truth_col("t_s")
        for col, (truth, sig, lab) in enumerate((("yaw_rate_radps", "YAW_RATE_REF",
                                                   "yaw rate [deg/s]"),
                                                  ("beta_rad", "BETA_REF", "β [deg]"))):
            ax = axes[row, col]
            ax.plot(t, run.truth_col(truth) * DEG, label="actual", lw=1.3)
            tr, ref = _series(run, "CTRL_REFS", sig)
            if tr.size:
                ax.plot(tr, ref, "--", label="reference", lw=1.1)
            ax.set_title(f"{name}: {lab.split(' [')[0]}", fontsize="medium")
            ax.set_ylabel(lab)
            ax.grid(True, alpha=0.3)
            if row == 0:
                ax.legend(loc="best", fontsize="small")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(title)
    fig.savefig(path, dpi=DPI)
    return path


def vmax_figure(vmax: Mapping[str, Mapping[str, Any]], path: Path) -> Path:
    """Every probed DLC entry speed per controller: max |β| and max |dev|, pass/fail."""
    fig = _fig(11.0, 4.2)
    ax_b, ax_d = fig.subplots(1, 2)
    for name, res in vmax.items():
        probes = sorted(res.get("probes", []), key=lambda p: p["speed_kmh"])
        if not probes:
            continue
        v = [p["speed_kmh"] for p in probes]
        b = [p.get("max_abs_beta_deg") or math.nan for p in probes]
        dv = [p.get("max_abs_lateral_dev_m") or math.nan for p in probes]
        line = ax_b.plot(v, b, "-", lw=0.8, label=name)[0]
        ax_d.plot(v, dv, "-", lw=0.8, color=line.get_color(), label=name)
        for vi, bi, di, p in zip(v, b, dv, probes, strict=True):
            mk = "o" if p.get("passed") else "x"
            ax_b.plot(vi, bi, mk, color=line.get_color())
            ax_d.plot(vi, di, mk, color=line.get_color())
    ax_b.axhline(8.0, color="k", lw=0.8, ls="--")
    ax_d.axhline(1.0, color="k", lw=0.8, ls="--")
    ax_b.set(xlabel="entry speed [km/h]", ylabel="max |β| [deg] (window)",
             title="DLC probes: max |β| (o pass, x fail)")
    ax_d.set(xlabel="entry speed [km/h]", ylabel="max |lateral dev| [m]",
             title="DLC probes: max |deviation|")
    ax_b.set_yscale("log")
    ax_d.set_yscale("log")
    for ax in (ax_b, ax_d):
        ax.grid(True, alpha=0.3, which="both")
        ax.legend(loc="best", fontsize="small")
    fig.savefig(path, dpi=DPI)
    return path


def fmvss_figure(runs: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Yaw-rate ratios at COS+1 s and COS+1.75 s vs amplitude, per controller/direction."""
    fig = _fig(11.0, 4.2)
    ax1, ax2 = fig.subplots(1, 2, sharex=True)
    keys = sorted({(r["controller"], r["direction"]) for r in runs})
    for ctrl, direction in keys:
        sel = sorted((r for r in runs if r["controller"] == ctrl
                      and r["direction"] == direction and r.get("yrr_1s") is not None),
                     key=lambda r: r["amplitude_deg"])
        if not sel:
            continue
        a = [r["amplitude_deg"] for r in sel]
        ls = "-" if direction == "left" else "--"
        line = ax1.plot(a, [r["yrr_1s"] * 100 for r in sel], ls, marker=".",
                        label=f"{ctrl} {direction}")[0]
        ax2.plot(a, [r["yrr_175s"] * 100 for r in sel], ls, marker=".",
                 color=line.get_color(), label=f"{ctrl} {direction}")
    ax1.axhline(35.0, color="k", lw=0.8)
    ax2.axhline(20.0, color="k", lw=0.8)
    ax1.set(xlabel="amplitude [deg]", ylabel="yaw-rate ratio [%]", title="COS + 1.00 s (≤ 35 %)")
    ax2.set(xlabel="amplitude [deg]", ylabel="yaw-rate ratio [%]", title="COS + 1.75 s (≤ 20 %)")
    for ax in (ax1, ax2):
        ax.set_ylim(-60, 160)
        ax.grid(True, alpha=0.3)
    ax2.legend(loc="best", fontsize="x-small", ncol=2)
    fig.savefig(path, dpi=DPI)
    return path
