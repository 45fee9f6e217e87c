"""The model-fidelity figure of one run (paper Figs 5–6): truth against the three estimators.

matplotlib object API only (headless, no global state). The numbers come from
harness/analysis/fidelity.py; this module draws them and writes the PNG next to them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from harness.analysis.fidelity import FidelityResult, evaluate_run

DEG = 180.0 / math.pi
DPI = 110


def fidelity_figure(res: FidelityResult, path: Path, title: str = "") -> Path:
    """Truth vs the three estimators (paper set-up): Vx, Vy km/h and ωr deg/s over time s."""
    fig = Figure(figsize=(10.0, 7.5), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    scale = (3.6, 3.6, DEG)
    labels = ("Vx [km/h]", "Vy [km/h]", "ωr [deg/s]")
    style = {"rhonn": "-", "7dof-li": "--", "7dof-mf": ":"}
    for i, ax in enumerate(axes):
        ax.plot(res.t_grid, res.truth_grid[:, i] * scale[i], color="0.6", lw=3.0,
                label="truth (plant)")
        for name, s in res.series.items():
            ax.plot(res.t_grid, s[:, i] * scale[i], style.get(name, "-"), lw=1.2,
                    label=name)
        ax.set_ylabel(labels[i])
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or "Model fidelity")
    fig.savefig(path, dpi=DPI)
    return path


def fidelity_of_run(run_dir: str | Path, ts_s: float = 0.05, horizon: int = 3,
                    plot_path: str | Path | None = None, title: str = "") -> dict[str, Any]:
    """Evaluate a run's model fidelity (ts_s: model period, s; horizon: steps of ts_s) and,
    with ``plot_path``, draw its figure there; returns the numbers of
    :func:`harness.analysis.fidelity.evaluate_run` (plus ``plot``, the figure's file name)."""
    res, out = evaluate_run(run_dir, ts_s, horizon)
    if plot_path is not None:
        fidelity_figure(res, Path(plot_path), title)
        out["plot"] = Path(plot_path).name
    return out
