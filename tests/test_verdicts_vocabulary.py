"""One verdict vocabulary (paper rule, course rule (cones), stable) with the same numbers in
metrics.json, the KPI table and the plots; honest lockstep timing; the truth trace's first
row carries the road's μ.

A synthetic drive through the dlc-paper course at a fixed lateral offset strikes a known set
of cones (computed here from the cone layout alone, not by the code under test); a short real
run over the bus checks the files a user gets."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

import harness.viz.plots as plots
from harness.analysis.course import course_geometry
from harness.analysis.footprint import packaged_footprint
from harness.analysis.kpi import compute_kpis, course_end_time_s
from harness.analysis.run_data import RunData, load_run
from harness.analysis.verdicts import VERDICT_NAMES, verdict_block, verdict_summary
from harness.cli import print_table
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation
from tests.test_harness_kpi import TRUTH_COLUMNS, make_run_dir, write_truth

OFFSET_M = 1.0   # lateral offset of the straight drive, m (+ left)
SPEED_MPS = 18.0
CONTRACT_KEYS = {"paper_rule": {"passed", "rule"},
                 "course_rule": {"passed", "cones_struck", "gate_exits", "rule"},
                 "stable": {"passed", "rule"}}


def _straight_drive(root: Path, t_end_s: float) -> RunData:
    """Truth of a car driving straight at y = OFFSET_M from x = −20 m (the course start)
    at SPEED_MPS, no sideslip, no yaw; arc length and deviation projected on the dlc-paper
    reference path as the plant does."""
    t = np.arange(0.0, t_end_s + 1e-9, 0.01)
    x = -20.0 + SPEED_MPS * t
    path = load_scenario("dlc-paper").path
    path.reset()
    s, dev = np.array([path.project(float(xi), OFFSET_M) for xi in x]).T
    sig = {c: np.zeros(t.size) for c in TRUTH_COLUMNS}
    sig.update(t_s=t, cycle=np.arange(t.size, dtype=float), x_m=x, y_m=np.full(t.size, OFFSET_M),
               vx_mps=np.full(t.size, SPEED_MPS), path_s_m=s, cmd_valid=np.ones(t.size),
               lateral_dev_m=dev)
    root.mkdir(parents=True, exist_ok=True)
    write_truth(root / "truth.csv", sig)
    return load_run(root, meta={"controller": "lmpc", "scenario_end_s": float(t[-1])})


def _expected_struck(cones: np.ndarray, x_max: float) -> np.ndarray:
    """Cones a straight body at y = OFFSET_M covers: |y_cone − OFFSET_M| ≤ half the body
    width, and the body reached the cone's x."""
    fp = packaged_footprint()
    return (np.abs(cones[:, 1] - OFFSET_M) <= fp.width_m / 2) & (cones[:, 0] <= x_max)


def _capture(monkeypatch: pytest.MonkeyPatch) -> dict[str, Figure]:
    """File name → the Figure write_plots made for it (not rendered: the PNGs themselves
    are checked in test_harness_plots.py and the bus run below)."""
    saved: dict[str, Figure] = {}

    def save(fig: Figure, path: Path) -> Path:
        saved[Path(path).name] = fig
        return Path(path)

    monkeypatch.setattr(plots, "_save", save)
    return saved


def _table(capsys: pytest.CaptureFixture[str], rows: dict[str, dict]) -> dict[str, str]:
    """The KPI table as label → the first run's cell."""
    print_table(rows)
    out = {}
    for line in capsys.readouterr().out.splitlines()[1:]:
        label, _, cell = line.rpartition("  ")
        out[label.strip()] = cell.strip()
    return out


def test_struck_cones_are_one_number_in_metrics_table_and_trajectory_plot(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    sc = load_scenario("dlc-paper")
    geo = course_geometry(sc)
    run = _straight_drive(tmp_path / "run", 12.0)  # 196 m: course end + 2 s covered
    block = verdict_block(run, cones=geo.cones, lanes=geo.lanes,
                          course_end_arc_m=geo.course_end_arc_m,
                          planned_end_s=run.meta["scenario_end_s"])
    assert {k: set(v) for k, v in block.items()} == CONTRACT_KEYS
    want = _expected_struck(geo.cones, float(run.truth_col("x_m")[-1]))
    assert want.sum() == 6  # the gate-1 and gate-3 cones on the left line
    course = block["course_rule"]
    assert course["passed"] is False and course["cones_struck"] == int(want.sum())
    assert course["gate_exits"] > 0  # the body's left corners are outside gate 1
    # 1 m off the lane centre everywhere and 2.5 m below the offset lane: the paper rule
    # fails; no sideslip and no rotation: stable
    assert block["paper_rule"]["passed"] is False and block["stable"]["passed"] is True
    # the paper rule of the block is the passed_dlc KPI the paper study reads
    end = course_end_time_s(run, geo.course_end_arc_m)
    assert compute_kpis(run, course_end_s=end)["passed_dlc"] is False

    metrics = {"verdicts": block, "mode": "lockstep"}
    rows = _table(capsys, {"lmpc": metrics})
    assert rows["paper rule"] == "FAIL" and rows["stable"] == "pass"
    assert rows["course rule (cones)"] == f"FAIL ({int(want.sum())} struck)"

    figs = _capture(monkeypatch)
    plots.write_plots(run, geo.boundaries, geo.ref_path, tmp_path / "plots", cones=geo.cones,
                      lanes=geo.lanes, course_end_arc_m=geo.course_end_arc_m, metrics=metrics)
    traj = figs["trajectory.png"]
    title = traj.get_suptitle()
    assert verdict_summary(block) in title and f"({int(want.sum())} cones struck)" in title
    for word in ("paper rule: FAIL", "course rule (cones): FAIL", "stable: pass"):
        assert word in title
    crosses = {ln.get_label(): np.asarray(ln.get_xydata()) for ln in traj.axes[0].get_lines()}
    np.testing.assert_array_equal(crosses[f"cones struck ({int(want.sum())})"], geo.cones[want])
    assert "stable: pass" in figs["phase_plane.png"].axes[0].get_title()


def test_a_trace_short_of_the_window_is_not_judged_unless_it_already_failed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    geo = course_geometry(load_scenario("dlc-paper"))
    kw = {"cones": geo.cones, "lanes": geo.lanes, "course_end_arc_m": geo.course_end_arc_m}
    # 0.8 s: the car has not reached the first cone yet, nothing failed so far
    early = verdict_block(_straight_drive(tmp_path / "early", 0.8), **kw)
    assert [early[k]["passed"] for k in VERDICT_NAMES] == [None, None, None]
    assert early["stable"]["rule"].startswith("not judged")
    assert _table(capsys, {"lmpc": {"verdicts": early}})["course rule (cones)"] == "– (0 struck)"
    # 2 s: the gate-1 cones are already struck and the deviation is over 1 m: final
    mid = verdict_block(_straight_drive(tmp_path / "mid", 2.0), **kw)
    assert mid["course_rule"]["passed"] is False and mid["course_rule"]["cones_struck"] == 3
    assert mid["stable"]["passed"] is None
    # a scenario without cones has no paper or course rule
    sine = course_geometry(load_scenario("sine-with-dwell"))
    none = verdict_block(_straight_drive(tmp_path / "sine", 2.0), cones=sine.cones,
                         lanes=sine.lanes, course_end_arc_m=None, planned_end_s=2.0)
    assert none["paper_rule"]["passed"] is None and none["course_rule"]["cones_struck"] is None
    assert none["stable"]["passed"] is True


def test_partial_run_titles_every_plot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    geo = course_geometry(load_scenario("dlc-paper"))
    run = _straight_drive(tmp_path / "run", 3.0)
    figs = _capture(monkeypatch)
    metrics = {"interrupted": True, "sim_time_reached_s": 3.0, "duration_planned_s": 18.0}
    paths = plots.write_plots(run, geo.boundaries, geo.ref_path, tmp_path / "plots",
                              cones=geo.cones, lanes=geo.lanes,
                              course_end_arc_m=geo.course_end_arc_m, metrics=metrics)
    assert [p.name for p in paths] == list(plots.PLOT_NAMES)
    note = "PARTIAL RUN — interrupted at 3.0 s of 18.0 s"
    for name, fig in figs.items():
        titles = [fig.get_suptitle(), *(ax.get_title() for ax in fig.axes)]
        assert any(note in t for t in titles), name


def test_lockstep_has_no_wall_clock_jitter_and_says_what_its_timing_is(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = make_run_dir(tmp_path / "run", 200)
    realtime = compute_kpis(load_run(root, meta={"mode": "realtime"}))
    lockstep = compute_kpis(load_run(root, meta={"mode": "lockstep"}))
    assert realtime["period_jitter_us_p99"] == pytest.approx(50.0)
    assert lockstep["period_jitter_us_p99"] is None
    # the compute figures stay, identical in both modes
    for key in ("step_us_p50", "step_us_p99", "turnaround_us_p50", "turnaround_us_p99"):
        assert lockstep[key] == realtime[key] is not None
    rows = _table(capsys, {"lmpc": {**lockstep, "mode": "lockstep"}})
    assert rows["period jitter p99 µs"] == "n/a lockstep"
    assert "turnaround > 10 ms (wall)" in rows and "deadline misses" not in rows
    assert rows["step compute p50/p99 µs (wall)"] == (
        f"{lockstep['step_us_p50']:.0f} / {lockstep['step_us_p99']:.0f}")
    rows = _table(capsys, {"lmpc": {**realtime, "mode": "realtime"}})
    assert rows["period jitter p99 µs"] == "50" and "deadline misses" in rows
    # firmware on QEMU has no clock for CTRL_STATUS.COMPUTE_TIME: no step time of 0 µs
    rows = _table(capsys, {"m4f": {**lockstep, "mode": "lockstep", "target": "m4f"}})
    assert rows["step compute p50/p99 µs (wall)"] == "n/a (firmware)"


def test_the_torque_plot_lag_model_is_the_plants_motor_lag() -> None:
    # step commands well inside the motor envelope: what is left of actual − lagged command
    # must be round-off, while the raw actual − command shows the lag at every step
    sim = Simulation(load_scenario("dlc-paper"))
    rows = [sim.truth_row()]
    for k in range(60):
        level = 200.0 if (k // 6) % 2 == 0 else -150.0
        sim.step_comm([level, -level, 0.5 * level, -0.5 * level])
        rows.append(sim.truth_row())
    tau, _, cycle = plots.motor_lag()
    for w in ("fl", "fr", "rl", "rr"):
        cmd = np.array([r[f"tcmd_{w}"] for r in rows])
        act = np.array([r[f"tact_{w}"] for r in rows])
        model = plots.lagged_command(cmd, float(act[0]), tau, cycle)
        assert np.max(np.abs(act - cmd)) > 50.0, w
        assert np.max(np.abs(act - model)) < 1e-6, w


@pytest.mark.parametrize("name", ["dlc-paper", "slippery-curve", "split-mu-braking"])
def test_truth_row_zero_carries_the_road_friction(name: str) -> None:
    sc = load_scenario(name)
    sim = Simulation(sc)
    row0 = sim.truth_row()
    sim.step_comm(None)
    row1 = sim.truth_row()
    mus = [row0[f"mu_{w}"] for w in ("fl", "fr", "rl", "rr")]
    assert mus == [row1[f"mu_{w}"] for w in ("fl", "fr", "rl", "rr")]
    if sc.friction.at_time(0.0).uniform is not None:
        assert mus == [pytest.approx(sc.mu)] * 4


def test_bus_run_writes_the_verdict_block_plots_and_true_first_row(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "run", "dlc-paper", "--controller", "lmpc",
         "--duration", "3", "--no-rrd", "--out", str(out)],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert "analysis_error" not in m, m["analysis_error"]
    assert {k: set(v) for k, v in m["verdicts"].items()} == CONTRACT_KEYS
    # 3 s of an 18 s course: the window is not covered; a failure would already be final
    for key in VERDICT_NAMES:
        assert m["verdicts"][key]["passed"] in (None, False)
    assert m["mode"] == "lockstep" and m["period_jitter_us_p99"] is None
    assert m["plots"] == list(plots.PLOT_NAMES)
    assert all((out / p).is_file() for p in m["plots"])
    table = dict(line.rsplit(None, 1) for line in proc.stdout.splitlines()
                 if line.startswith(("paper rule", "stable ")))
    assert table["paper rule"] == ("–" if m["verdicts"]["paper_rule"]["passed"] is None
                                   else "FAIL")
    header = (out / "truth.csv").read_text().splitlines()[:2]
    row0 = dict(zip(header[0].split(","), header[1].split(","), strict=True))
    assert math.isclose(float(row0["mu_fl"]), load_scenario("dlc-paper").mu)
