"""Plots: the figures hold the run's data (series read back from the matplotlib figures:
axes, labels, series count, values), and the PNGs on disk are those figures (pixel size,
the data colour present, the "no data" case blank of it)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

import harness.viz.plots as plots
from harness.analysis.kpi import beta_rate
from harness.analysis.run_data import RunData, load_run
from harness.viz.plots import OVERLAY_NAMES, PLOT_NAMES, write_overlay_plots, write_plots
from tests.test_harness_kpi import DM_A, make_run_dir

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DEG = 180.0 / math.pi
N = 300
COURSE = [np.column_stack([np.linspace(0, 60, 13), np.full(13, 1.5)]),
          np.column_stack([np.linspace(0, 60, 13), np.full(13, -1.5)])]
REF = np.column_stack([np.linspace(0, 80, 9), np.zeros(9)])
CONES = np.vstack([c[::4] for c in COURSE])
TAB_BLUE = np.array(to_rgb("tab:blue"))
SIZES_IN = {"torques.png": (12.0, 6.5),
            "phase_plane.png": (10.0, 5.5), "overlay_phase_plane.png": (6.5, 5.5),
            "overlay_swa.png": (11.0, 4.5), "overlay_delta_m.png": (11.0, 4.5),
            "overlay_yaw_rate.png": (11.0, 4.5), "overlay_beta.png": (11.0, 4.5)}
#: Top views: 13 in wide, the height follows the true-scale panels.
TRUE_SCALE = ("trajectory.png", "overlay_trajectory.png")


def _capture(monkeypatch: pytest.MonkeyPatch) -> dict[str, Figure]:
    """File name → the Figure the plotting code saved under it."""
    saved: dict[str, Figure] = {}
    real = plots._save

    def save(fig: Figure, path: Path) -> Path:
        saved[Path(path).name] = fig
        return real(fig, path)

    monkeypatch.setattr(plots, "_save", save)
    return saved


def _lines(fig: Figure, ax: int = 0) -> dict[str, np.ndarray]:
    """Label → (n, 2) data of every labelled line on axis ``ax``."""
    return {ln.get_label(): np.asarray(ln.get_xydata())
            for ln in fig.axes[ax].get_lines() if not ln.get_label().startswith("_")}


def _texts(fig: Figure) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.texts]


def _blue_pixels(path: Path) -> int:
    img = mpimg.imread(path)
    return int(np.all(np.abs(img[..., :3] - TAB_BLUE) < 0.02, axis=-1).sum())


def _check_files(paths: list[Path], names: tuple[str, ...], out: Path) -> None:
    assert [p.name for p in paths] == list(names)
    for p in paths:
        assert p.parent == out and p.read_bytes().startswith(PNG_MAGIC)
        shape = mpimg.imread(p).shape[:2]
        if p.name in TRUE_SCALE:
            assert shape[1] == round(13.0 * plots.DPI), p.name
            continue
        w_in, h_in = SIZES_IN.get(p.name, (9.0, 4.5))
        assert shape == (round(h_in * plots.DPI), round(w_in * plots.DPI)), p.name


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> RunData:
    return load_run(make_run_dir(tmp_path_factory.mktemp("run"), N),
                    meta={"controller": "nmpc-rhonn"})


def test_single_run_plots_hold_the_runs_series(run: RunData, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    figs = _capture(monkeypatch)
    out = tmp_path / "plots"
    _check_files(write_plots(run, COURSE, REF, out, cones=CONES), PLOT_NAMES, out)
    t = run.truth_col("t_s")

    traj = figs["trajectory.png"]
    ax = traj.axes[0]
    assert ax.get_xlabel() == "X [m]" and ax.get_ylabel().startswith("Y [m] (+ left")
    # true scale in the overview and the zoom panel (axes[1] holds the legend)
    assert ax.get_aspect() == 1.0 and traj.axes[2].get_aspect() == 1.0
    lines = _lines(traj)
    assert set(lines) == {"course boundaries", "cones", "reference path",
                          "vehicle CG (nmpc-rhonn)"}
    np.testing.assert_array_equal(lines["vehicle CG (nmpc-rhonn)"],
                                  np.column_stack([run.truth_col("x_m"), run.truth_col("y_m")]))
    np.testing.assert_array_equal(lines["cones"], CONES)
    np.testing.assert_array_equal(lines["reference path"], REF)
    drawn = [np.asarray(ln.get_xydata()) for ln in ax.get_lines()]
    for want in COURSE:  # every course boundary is drawn exactly, once
        assert sum(d.shape == want.shape and np.array_equal(d, want) for d in drawn) == 1
    assert _blue_pixels(out / "trajectory.png") > 500

    for name, col in (("yaw_rate.png", "yaw_rate_radps"), ("beta.png", "beta_rad")):
        lines = _lines(figs[name])
        assert set(lines) == {"actual (truth)", "reference (CTRL_REFS)"}, name
        np.testing.assert_allclose(lines["actual (truth)"],
                                   np.column_stack([t, run.truth_col(col) * DEG]))
        assert len(lines["reference (CTRL_REFS)"]) == N
        assert figs[name].axes[0].get_xlabel() == "time [s]"

    dm = _lines(figs["delta_m.png"])["ΔM commanded (CTRL_REFS)"]
    assert len(dm) == N and np.max(np.abs(dm[:, 1])) == DM_A
    np.testing.assert_array_equal(dm[:, 1], run.bus["CTRL_REFS"]["DELTA_M"])

    torques = figs["torques.png"]
    assert [a.get_title().split(":")[0] for a in torques.axes] == [
        "Wheel FL", "Wheel FR", "Wheel RL", "Wheel RR"]
    tau, _, _ = plots.motor_lag()
    for i, w in enumerate(("fl", "fr", "rl", "rr")):
        ys = {k: v[:, 1] for k, v in _lines(torques, i).items()}
        lag_label = f"command through the {tau * 1e3:.0f} ms motor lag"
        assert set(ys) == {"commanded (applied frame)", "motor actual", lag_label,
                           "motor limit ±450 N·m"}, w
        np.testing.assert_array_equal(ys["commanded (applied frame)"],
                                      run.truth_col(f"tcmd_{w}"))
        np.testing.assert_array_equal(ys["motor actual"], run.truth_col(f"tact_{w}"))
        act = run.truth_col(f"tact_{w}")
        resid = np.max(np.abs(act - ys[lag_label]))
        assert torques.axes[i].get_title().endswith(f"{resid:.1f} N·m"), w

    phase = figs["phase_plane.png"]
    lines = _lines(phase)
    (label, xy), = ((k, v) for k, v in lines.items() if k.startswith("nmpc-rhonn"))
    assert label.startswith("nmpc-rhonn: hull area")
    beta = run.truth_col("beta_rad")
    np.testing.assert_allclose(xy, np.column_stack([beta * DEG, beta_rate(beta, t) * DEG]))
    assert (phase.axes[0].get_xlabel(), phase.axes[0].get_ylabel()) == ("β [deg]",
                                                                        "β̇ [deg/s]")

    swa = _lines(figs["swa.png"])["steering-wheel angle"]
    np.testing.assert_allclose(swa[:, 1], run.truth_col("swa_rad") * DEG)
    assert not any("no data" in s for f in figs.values() for s in _texts(f))


def test_a_run_without_truth_data_gets_no_plots(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    figs = _capture(monkeypatch)
    out = tmp_path / "empty"
    assert write_plots(load_run(tmp_path / "nothing"), [], np.zeros((0, 2)), out,
                       cones=CONES) == []
    assert figs == {} and not out.exists()


def test_overlay_has_one_series_per_run_with_data(run: RunData, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    figs = _capture(monkeypatch)
    out = tmp_path / "overlay"
    shifted = load_run(make_run_dir(tmp_path / "run2", N // 2), meta={"controller": "lmpc"})
    runs = {"nmpc-rhonn": run, "lmpc": shifted, "passive": load_run(tmp_path / "nothing")}
    _check_files(write_overlay_plots(runs, COURSE, None, out, cones=CONES), OVERLAY_NAMES,
                 out)
    traj = {k.split(",")[0]: v for k, v in _lines(figs["overlay_trajectory.png"]).items()}
    assert {"nmpc-rhonn", "lmpc"} <= set(traj) and "passive" not in traj
    assert len(traj["lmpc"]) == N // 2 and len(traj["nmpc-rhonn"]) == N
    for name, col in (("overlay_yaw_rate.png", "yaw_rate_radps"),
                      ("overlay_beta.png", "beta_rad"), ("overlay_swa.png", "swa_rad")):
        lines = _lines(figs[name])
        assert list(lines) == ["nmpc-rhonn", "lmpc"], name
        np.testing.assert_allclose(lines["nmpc-rhonn"][:, 1], run.truth_col(col) * DEG)
    dm = _lines(figs["overlay_delta_m.png"])
    assert list(dm) == ["nmpc-rhonn", "lmpc", "ΔM box ±1800 N·m"]
    np.testing.assert_array_equal(dm["nmpc-rhonn"][:, 1], run.bus["CTRL_REFS"]["DELTA_M"])
    phase = _lines(figs["overlay_phase_plane.png"])
    assert [k.split(":")[0] for k in phase] == ["nmpc-rhonn", "lmpc"]
    legend = figs["overlay_yaw_rate.png"].axes[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["nmpc-rhonn", "lmpc"]
