"""The closed loop across real OS processes: plant ⇄ loopback bus ⇄ controller, via the harness."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from harness.analysis.run_data import load_run
from harness.run.replay import replay_log
from harness.run.runner import RunConfig, run_closed_loop
from tests.helpers_proc import live_children

REQUIRED_METRICS = (
    "completed", "spun", "max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m",
    "phase_area", "max_abs_swa_deg", "max_abs_dM_Nm", "step_us_p50", "step_us_p99",
    "turnaround_us_p50", "turnaround_us_p99", "deadline_misses", "frames_rejected",
    "fallback_events", "scenario", "controller", "bus", "mode", "software_version")


@pytest.fixture(scope="module")
def lockstep_dlc(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("dlc-rhonn")
    run_closed_loop(RunConfig(scenario="dlc-paper", controller="nmpc-rhonn", out_dir=out,
                              duration_s=8.0, make_plots=True, make_rrd=True))
    return out


def test_lockstep_dlc_with_nmpc_rhonn_completes_with_bounded_sideslip(lockstep_dlc: Path
                                                                      ) -> None:
    metrics = json.loads((lockstep_dlc / "metrics.json").read_text())
    assert "analysis_error" not in metrics, metrics.get("analysis_error")
    for key in REQUIRED_METRICS:
        assert key in metrics, key
    assert metrics["reason"] == "finished" and metrics["completed"] is True
    assert metrics["spun"] is False and metrics["max_abs_beta_deg"] < 8.0
    assert metrics["fallback_events"] == 0 and metrics["frames_rejected"] == {}
    assert metrics["plant_summary"]["lockstep_timeouts"] == 0
    # The controller was really in the loop: it answered every cycle and moved ΔM.
    run = load_run(lockstep_dlc)
    assert run.n_cycles >= 790 and np.all(run.truth_col("cmd_valid")[1:] == 1)
    assert metrics["max_abs_dM_Nm"] > 0.0
    for name in ("bus.blf", "truth.csv", "run.rrd", "controller_timing.csv",
                 "trajectory.png", "phase_plane.png"):
        assert (lockstep_dlc / name).stat().st_size > 0, name
    assert not live_children()


def test_replay_of_a_lockstep_log_is_bit_identical(lockstep_dlc: Path) -> None:
    result = replay_log(lockstep_dlc / "bus.blf", "nmpc-rhonn")
    assert result.recorded >= 790
    assert result.bit_identical, result


def test_replay_with_another_controller_is_detected_as_different(lockstep_dlc: Path) -> None:
    result = replay_log(lockstep_dlc / "bus.blf", "passive")
    assert not result.bit_identical and result.first_mismatch is not None


def test_realtime_run_reports_deadline_misses_and_jitter(tmp_path: Path) -> None:
    result = run_closed_loop(RunConfig(scenario="dlc-paper", controller="nmpc-rhonn",
                                       out_dir=tmp_path, mode="realtime", duration_s=2.0,
                                       make_plots=False, make_rrd=False))
    m = result.metrics
    assert result.reason == "finished", m
    assert isinstance(m["deadline_misses"], int) and m["deadline_misses"] >= 0
    assert m["period_jitter_us_p99"] is not None and m["period_jitter_us_p99"] >= 0.0
    assert m["turnaround_us_p50"] is not None and m["turnaround_us_p99"] >= m["turnaround_us_p50"]
    assert 190 <= m["plant_summary"]["cycles"] <= 201
    assert not live_children()


def test_killed_controller_makes_the_plant_fall_back_within_its_timeout(tmp_path: Path) -> None:
    result = run_closed_loop(RunConfig(scenario="dlc-paper", controller="nmpc-rhonn",
                                       out_dir=tmp_path, mode="realtime", duration_s=3.0,
                                       kill_controller_at_s=1.2, make_plots=False,
                                       make_rrd=False))
    m = result.metrics
    assert result.reason == "finished"  # the plant survived its peer's death
    assert m["controller_lost_at_sim_s"] is not None and result.controller_code != 0
    run = load_run(tmp_path)
    valid = run.truth_col("cmd_valid")
    cycles = run.truth_col("cycle")
    last_answer = int(np.max(run.bus["WHEEL_TORQUE_CMD"]["cycle"]))
    # (a late answer on a loaded machine can cost a real-time cycle before the kill too;
    # what matters is what happens after the last answer)
    first_fallback = int(cycles[np.flatnonzero((valid == 0) & (cycles > last_answer))[0]])
    # rx monitor timeout = 3 cycles: the command stays valid at most 3 cycles after the
    # last torque frame, then the driver's torque split takes over for good.
    assert first_fallback <= last_answer + 4
    assert np.all(valid[cycles >= first_fallback] == 0)
    assert m["fallback_events"] >= 100 and m["plant_summary"]["fallback_cycles"] >= 100
    assert not math.isnan(run.truth_col("vx_mps")[-1])
    assert not live_children()
