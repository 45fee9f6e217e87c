"""Plots are written as non-empty PNGs with the expected names (also for missing data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.run_data import load_run
from harness.viz.plots import OVERLAY_NAMES, PLOT_NAMES, write_overlay_plots, write_plots
from tests.test_harness_kpi import make_run_dir

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
COURSE = [np.column_stack([np.linspace(0, 60, 13), np.full(13, 1.5)]),
          np.column_stack([np.linspace(0, 60, 13), np.full(13, -1.5)])]
REF = np.column_stack([np.linspace(0, 80, 9), np.zeros(9)])


def _check(paths: list[Path], names: tuple[str, ...], out: Path) -> None:
    assert [p.name for p in paths] == list(names)
    for p in paths:
        assert p.parent == out
        data = p.read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5000, p


def test_single_and_overlay_plots(tmp_path: Path) -> None:
    run = load_run(make_run_dir(tmp_path / "run", 300), meta={"controller": "nmpc-rhonn"})
    empty = load_run(tmp_path / "nothing")
    cones = np.vstack([c[::4] for c in COURSE])
    _check(write_plots(run, COURSE, REF, tmp_path / "plots", cones=cones), PLOT_NAMES,
           tmp_path / "plots")
    _check(write_plots(empty, [], np.zeros((0, 2)), tmp_path / "empty"), PLOT_NAMES,
           tmp_path / "empty")
    out = tmp_path / "overlay"
    _check(write_overlay_plots({"nmpc-rhonn": run, "passive": empty}, COURSE, None, out,
                               cones=cones), OVERLAY_NAMES, out)
