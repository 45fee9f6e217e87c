"""Run-directory loading and KPIs against closed-form references, on synthetic runs.

``make_run_dir`` (also used by the rerun and plot tests) writes a complete synthetic run:
truth.csv, a bus.blf encoded with the real codec, and controller_timing.csv.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import can
import numpy as np
import pytest

from can_db.codec import Codec, Transmitter
from harness.analysis.kpi import (
    KPI_KEYS,
    compute_kpis,
    course_end_time_s,
    model_fidelity,
    phase_area,
)
from harness.analysis.run_data import (
    REJECTED_KEY,
    load_bus_log,
    load_run,
    load_timing_csv,
    load_truth_csv,
)
from harness.analysis.smoothness import SMOOTHNESS_KEYS

DT = 0.01
BETA_A = 0.05  # rad
OMEGA = 2 * math.pi * 0.5  # rad/s
DEV_A = 0.5  # m
SWA_A = 0.5  # rad
DM_A = 300.0  # N·m, square wave flipping every DM_HALF cycles
DM_HALF = 50
YAW_OFFSET_DEG = 0.5  # reference − actual, deg/s
INVALID_CYCLES = (100, 101, 102)
FALLBACK_CYCLES = (200, 201)
MISS_ROWS = (30, 40)
WHEELS = ("fl", "fr", "rl", "rr")

TRUTH_COLUMNS = (
    ["t_s", "cycle", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps", "yaw_rate_radps", "beta_rad",
     "ax_mps2", "ay_mps2", "roll_rad", "pitch_rad", "swa_rad", "delta_f_rad", "accel_pedal",
     "brake_pedal", "stab_enable"]
    + [f"omega_{w}" for w in WHEELS] + [f"tcmd_{w}" for w in WHEELS]
    + [f"tact_{w}" for w in WHEELS] + [f"fz_{w}" for w in WHEELS] + [f"mu_{w}" for w in WHEELS]
    + ["lateral_dev_m", "path_s_m", "spun", "cmd_valid"])
TIMING_COLUMNS = ["cycle", "sim_time_s", "step_us", "turnaround_us", "period_us", "mpc_update",
                  "qp_iterations", "qp_status", "mode", "deadline_miss"]


def truth_signals(n: int) -> dict[str, np.ndarray]:
    """The synthetic truth trace: closed-form signals over n cycles."""
    t = np.arange(n) * DT
    z = np.zeros(n)
    sig = {c: z.copy() for c in TRUTH_COLUMNS}
    sig.update(t_s=t, cycle=np.arange(n, dtype=float), x_m=20.0 * t,
               y_m=DEV_A * np.sin(OMEGA * t), yaw_rad=0.05 * np.sin(OMEGA * t),
               vx_mps=z + 20.0, vy_mps=0.3 * np.sin(OMEGA * t),
               yaw_rate_radps=0.2 * np.sin(OMEGA * t), beta_rad=BETA_A * np.sin(OMEGA * t),
               swa_rad=SWA_A * np.sin(OMEGA * t), lateral_dev_m=DEV_A * np.sin(OMEGA * t),
               stab_enable=(t >= 1.0).astype(float), cmd_valid=z + 1.0, path_s_m=20.0 * t)
    sig["cmd_valid"][0] = 0.0  # no answer before the first cycle: not a fallback
    for k in INVALID_CYCLES:
        if k < n:
            sig["cmd_valid"][k] = 0.0
    for w in WHEELS:
        sig[f"tcmd_{w}"] = 50.0 * np.sin(OMEGA * t)
        sig[f"tact_{w}"] = 48.0 * np.sin(OMEGA * t)
    return sig


def delta_m(k: int) -> float:
    return DM_A if (k // DM_HALF) % 2 == 0 else -DM_A


def write_truth(path: Path, sig: dict[str, np.ndarray]) -> None:
    n = len(sig["t_s"])
    with path.open("w") as fh:
        fh.write(",".join(TRUTH_COLUMNS) + "\n")
        for k in range(n):
            fh.write(",".join(repr(float(sig[c][k])) for c in TRUTH_COLUMNS) + "\n")


def write_timing(path: Path, n: int) -> None:
    with path.open("w") as fh:
        fh.write(",".join(TIMING_COLUMNS) + "\n")
        for k in range(n):
            period = 0.0 if k == 0 else 10000.0 + (50.0 if k % 2 else -50.0)
            row = [k, k * DT, 100 + k % 100, 300 + k % 100, period, int(k % 5 == 0), 7, 0, 1,
                   int(k in MISS_ROWS)]
            fh.write(",".join(str(v) for v in row) + "\n")


def write_bus(path: Path, sig: dict[str, np.ndarray], *, late_cycles: tuple[int, ...] = (),
              bad_frames_at: tuple[int, ...] = ()) -> None:
    """One plant burst + SYNC + controller answer per cycle; ``late_cycles`` are answered after
    the next SYNC; ``bad_frames_at`` cycles add a bad-CRC and an unknown-ID frame."""
    codec = Codec()
    plant, ctrl = Transmitter(codec), Transmitter(codec)
    n = len(sig["t_s"])
    deg = 180.0 / math.pi
    t_log = 1000.0
    frames: list[can.Message] = []

    def emit(msg: can.Message, dt: float = 1e-4) -> None:
        nonlocal t_log
        t_log += dt
        msg.timestamp = t_log
        frames.append(msg)

    def answer(k: int) -> None:
        qp = 5 if k in FALLBACK_CYCLES else 0
        emit(ctrl.message("WHEEL_TORQUE_CMD", {f"TQ_{w.upper()}": sig[f"tcmd_{w}"][k]
                                               for w in WHEELS} | {"ECHO_CYCLE": k % 256}))
        emit(ctrl.message("CTRL_STATUS", {"MODE": 1, "QP_STATUS": qp, "QP_ITER": 7,
                                          "COMPUTE_TIME": 120, "ECHO_CYCLE": k % 256,
                                          "CONTROLLER_ID": 1}))
        emit(ctrl.message("CTRL_REFS", {
            "DELTA_M": delta_m(k),
            "YAW_RATE_REF": round(sig["yaw_rate_radps"][k] * deg / 0.005) * 0.005
            + YAW_OFFSET_DEG,
            "BETA_REF": round(sig["beta_rad"][k] * deg / 0.005) * 0.005,
            "ECHO_CYCLE": k % 256}))

    pending: list[int] = []
    for k in range(n):
        t_log = 1000.0 + k * DT
        emit(plant.message("DRIVER_INPUTS", {"SWA": sig["swa_rad"][k] * deg,
                                             "STAB_ENABLE": sig["stab_enable"][k]}))
        emit(plant.message("MOTION_SENSORS", {"YAW_RATE": sig["yaw_rate_radps"][k] * deg}))
        emit(plant.message("WHEEL_SPEEDS", {}))
        emit(plant.message("VEHICLE_EST", {"VX_EST": sig["vx_mps"][k]}))
        emit(plant.message("SYNC", {"CYCLE": k, "SIM_TIME": k * DT}))
        for j in pending:
            answer(j)
        pending.clear()
        if k in bad_frames_at:
            bad = codec.message("CTRL_REFS", {}, 0)
            bad.data = bytearray(bad.data)
            bad.data[0] ^= 0xFF
            emit(bad)
            emit(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))
        if k in late_cycles:
            pending.append(k)
        else:
            answer(k)
    with can.Logger(str(path)) as logger:
        for msg in frames:
            logger.on_message_received(msg)


def make_run_dir(root: Path, n: int = 600, *, late_cycles: tuple[int, ...] = (),
                 bad_frames_at: tuple[int, ...] = (), meta: dict | None = None) -> Path:
    """A complete synthetic run directory with n cycles."""
    root.mkdir(parents=True, exist_ok=True)
    sig = truth_signals(n)
    write_truth(root / "truth.csv", sig)
    write_timing(root / "controller_timing.csv", n)
    write_bus(root / "bus.blf", sig, late_cycles=late_cycles, bad_frames_at=bad_frames_at)
    if meta is not None:
        (root / "meta.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run_dir(tmp_path_factory.mktemp("run"), 600, late_cycles=(300, 301),
                        bad_frames_at=(10, 400))


# --- loading ---------------------------------------------------------------------------------

def test_load_run_shapes_and_alignment(run_dir: Path) -> None:
    run = load_run(run_dir, meta={"controller": "nmpc-rhonn"})
    assert run.n_cycles == 600
    assert run.meta["missing_files"] == []
    assert run.meta["controller"] == "nmpc-rhonn"
    for msg in ("SYNC", "DRIVER_INPUTS", "WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS"):
        assert len(run.bus[msg]["t_log"]) == 600
    assert run.bus["SYNC"]["cycle"].tolist() == list(range(600))
    # Plant frames belong to the SYNC that ends their burst.
    assert run.bus["DRIVER_INPUTS"]["cycle"].tolist() == list(range(600))
    # Controller echoes unwrap past 255 and late answers keep their cycle (incl. CTRL_REFS).
    for msg in ("WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS"):
        assert sorted(run.bus[msg]["cycle"].tolist()) == list(range(600)), msg
        np.testing.assert_allclose(run.bus[msg]["sim_time_s"], run.bus[msg]["cycle"] * DT,
                                   atol=1e-9)
    refs = run.bus["CTRL_REFS"]
    expected = [delta_m(int(c)) for c in refs["cycle"]]
    np.testing.assert_array_equal(refs["DELTA_M"], expected)
    assert run.rejections == {"bad_crc": 2, "unknown_id": 2}
    rej = run.bus[REJECTED_KEY]
    assert rej["cycle"].tolist() == [10, 10, 400, 400]
    np.testing.assert_allclose(rej["sim_time_s"], [0.1, 0.1, 4.0, 4.0])


def test_truncated_truth_and_timing(tmp_path: Path, run_dir: Path) -> None:
    text = (run_dir / "truth.csv").read_text()
    cut = tmp_path / "truth.csv"
    cut.write_text(text[: len(text) - 7])  # half of the last line
    truth = load_truth_csv(cut)
    assert len(truth["t_s"]) == 599
    assert set(truth) == set(TRUTH_COLUMNS)
    (tmp_path / "header_only.csv").write_text(",".join(TRUTH_COLUMNS))
    assert load_truth_csv(tmp_path / "header_only.csv") == {}
    (tmp_path / "header_nl.csv").write_text(",".join(TRUTH_COLUMNS) + "\n")
    assert all(v.size == 0 for v in load_truth_csv(tmp_path / "header_nl.csv").values())
    assert load_timing_csv(tmp_path / "missing.csv") == {}
    (tmp_path / "garbage.csv").write_bytes(b"a,b,c\n1,2,x\n3\n4,5,6,7\n,\xff,8\n9,10,11")
    garbage = load_timing_csv(tmp_path / "garbage.csv")
    np.testing.assert_array_equal(garbage["a"], [1.0, np.nan])
    np.testing.assert_array_equal(garbage["c"], [np.nan, 8.0])


@pytest.mark.parametrize("fraction", [0.0, 0.01, 0.3, 0.77, 0.999])
def test_truncated_blf_loads(tmp_path: Path, run_dir: Path, fraction: float) -> None:
    data = (run_dir / "bus.blf").read_bytes()
    cut = tmp_path / "bus.blf"
    cut.write_bytes(data[: int(len(data) * fraction)])
    bus, rejections = load_bus_log(cut)
    n_sync = len(bus.get("SYNC", {}).get("CYCLE", []))
    assert 0 <= n_sync <= 600
    assert isinstance(rejections, dict)


def test_empty_run_dir(tmp_path: Path) -> None:
    run = load_run(tmp_path)
    assert run.n_cycles == 0
    assert sorted(run.meta["missing_files"]) == ["bus.blf", "controller_timing.csv", "truth.csv"]
    k = compute_kpis(run)
    assert set(k) == set(KPI_KEYS)
    assert k["completed"] is False and k["passed_dlc"] is False
    assert k["max_abs_beta_deg"] is None and k["deadline_misses"] is None
    json.dumps(k, allow_nan=False)


# --- KPIs ------------------------------------------------------------------------------------

def test_kpis_closed_form(run_dir: Path) -> None:
    run = load_run(run_dir, meta={"rejections": {"plant": {"timeout": 2, "bad_crc": 1},
                                                 "controller": {"counter_jump": 3}}})
    k = compute_kpis(run)
    assert list(k) == list(KPI_KEYS)
    json.dumps(k, allow_nan=False)
    n = 600  # 6 s = 3 full periods of the 0.5 Hz signals
    t = np.arange(n) * DT
    assert k["completed"] is True and k["spun"] is False
    assert k["max_abs_beta_deg"] == pytest.approx(np.degrees(BETA_A), rel=1e-3)
    assert k["max_abs_lateral_dev_m"] == pytest.approx(DEV_A, rel=1e-3)
    assert k["rms_lateral_dev_m"] == pytest.approx(DEV_A / math.sqrt(2), rel=1e-3)
    # Ellipse β = a sin ωt, β̇ = aω cos ωt: area π·a·aω.
    assert k["phase_area"] == pytest.approx(math.pi * BETA_A * BETA_A * OMEGA, rel=5e-3)
    assert k["max_abs_swa_deg"] == pytest.approx(np.degrees(SWA_A), rel=1e-3)
    # ∫|dδ/dt| from 0 to 5.99 s = 3 · 4a minus the last 10 ms (samples hit every peak).
    tv = np.sum(np.abs(np.diff(np.degrees(SWA_A * np.sin(OMEGA * t)))))
    assert k["steering_effort_deg"] == pytest.approx(tv, rel=1e-9)
    closed = np.degrees(SWA_A) * (12 - math.sin(OMEGA * DT))
    assert k["steering_effort_deg"] == pytest.approx(closed, rel=1e-9)
    assert k["max_abs_dM_Nm"] == DM_A
    flips = (n - 1) // DM_HALF  # sign changes of the square wave
    assert k["dM_total_variation_Nm"] == pytest.approx(2 * DM_A * flips)
    # Smoothness of the same ΔM over the 6 s the frames span (MPC period 50 ms = 5 cycles):
    # every flip is a 2·DM_A change within one period, and the flips alternate in sign.
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(2 * DM_A * flips / (n * DT))
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(2 * DM_A)
    assert k["dM_chatter_per_s"] == pytest.approx((flips - 1) / (n * DT))
    # Commanded torques 50 sin(ωt) N·m in 0.5 N·m steps: the steepest step of the sine is
    # 50 · 2 sin(ω·DT/2) = 1.57 N·m per cycle, sent as 1.5 or 2.0 N·m.
    assert 150.0 <= k["wheel_torque_rate_max_Nm_per_s"] <= 200.0
    assert 100.0 <= k["wheel_torque_rate_p99_Nm_per_s"] <= k["wheel_torque_rate_max_Nm_per_s"]
    # References: yaw-rate ref = quantised actual + 0.5 deg/s; β ref = quantised actual.
    assert k["yaw_rate_rmse_degps"] == pytest.approx(YAW_OFFSET_DEG, abs=0.003)
    assert k["beta_rmse_deg"] < 0.003
    steps = 100 + np.arange(n) % 100
    assert k["step_us_p50"] == pytest.approx(np.percentile(steps, 50))
    assert k["step_us_p99"] == pytest.approx(np.percentile(steps, 99))
    assert k["turnaround_us_p50"] == pytest.approx(np.percentile(steps + 200, 50))
    assert k["period_jitter_us_p99"] == pytest.approx(50.0)
    assert k["deadline_misses"] == len(MISS_ROWS)
    assert k["frames_rejected"] == {"bad_crc": 3, "counter_jump": 3, "timeout": 2,
                                    "unknown_id": 2}
    assert k["fallback_events"] == len(INVALID_CYCLES) + len(FALLBACK_CYCLES)
    assert k["passed_dlc"] is True


def test_smoothness_reads_the_mpc_period_and_only_the_bus(run_dir: Path) -> None:
    """A 1 s MPC period spans a whole period of the square wave ΔM: no change over it. A
    run without bus log has no smoothness KPI (the truth's torques are not used)."""
    k = compute_kpis(load_run(run_dir, meta={"ctrl_period_s": 2 * DM_HALF * DT}))
    assert k["dM_max_change_per_period_Nm"] == 0.0
    truth_only = load_run(run_dir, meta={})
    truth_only.bus = {}
    k = compute_kpis(truth_only)
    assert all(k[key] is None for key in SMOOTHNESS_KEYS)


def test_dlc_window_and_completion(tmp_path: Path) -> None:
    n = 600
    sig = truth_signals(n)
    sig["lateral_dev_m"][550] = 1.5  # after course end + 2 s = 5.0 s
    sig["beta_rad"][560] = math.radians(9.0)
    write_truth(tmp_path / "truth.csv", sig)
    run = load_run(tmp_path, meta={"scenario_end_s": 5.99})
    assert compute_kpis(run)["passed_dlc"] is False
    assert compute_kpis(run, course_end_s=3.0)["passed_dlc"] is True
    assert compute_kpis(run, course_end_s=3.6)["passed_dlc"] is False  # window reaches 5.5 s
    assert compute_kpis(run, course_end_s=5.0)["passed_dlc"] is False  # trace ends before 7 s
    assert compute_kpis(run, pass_dev_m=2.0, pass_beta_deg=10.0)["passed_dlc"] is True
    assert compute_kpis(run, course_end_s=math.inf, pass_dev_m=9.0)["passed_dlc"] is False
    # path_s_m = 20 m/s · t: 60 m of arc is reached at 3.0 s; 500 m never.
    assert course_end_time_s(run, 60.0) == pytest.approx(3.0)
    assert course_end_time_s(run, 500.0) is None
    k = compute_kpis(run)
    assert k["completed"] is True
    assert k["max_abs_dM_Nm"] is None and k["yaw_rate_rmse_degps"] is None  # no bus log
    assert k["step_us_p50"] is None and k["frames_rejected"] == {}
    assert compute_kpis(load_run(tmp_path, meta={"scenario_end_s": 8.0}))["completed"] is False

    sig["spun"][400:] = 1.0
    write_truth(tmp_path / "truth.csv", sig)
    k = compute_kpis(load_run(tmp_path), course_end_s=1.0)
    assert k["spun"] is True and k["completed"] is False
    assert k["passed_dlc"] is True  # the spin happens after the evaluation window (3 s)
    assert compute_kpis(load_run(tmp_path), course_end_s=2.5)["passed_dlc"] is False


def test_phase_area_degenerate_and_sampling() -> None:
    t = np.arange(0, 2.0, DT)
    assert phase_area(np.zeros_like(t), t) == 0.0
    assert phase_area(np.array([0.1, 0.2]), np.array([0.0, 0.01])) == 0.0
    a, w = 0.02, 2 * math.pi * 1.0
    assert phase_area(a * np.sin(w * t), t) == pytest.approx(math.pi * a * a * w, rel=1e-2)
    beta = a * np.sin(w * t)
    beta[5] = math.nan  # a NaN sample is ignored, not propagated
    assert math.isfinite(phase_area(beta, t))


def test_model_fidelity() -> None:
    n = 100
    truth = np.column_stack([np.full(n, 20.0), np.zeros(n), np.zeros(n)])
    err = np.column_stack([np.linspace(-0.1, 0.1, n), np.full(n, 0.05),
                           np.full(n, math.radians(2.0))])
    est = truth + err
    est[3, 1] = math.nan
    f = model_fidelity(truth, est)
    assert f["vx_kmh"]["max"] == pytest.approx(0.36)
    assert f["vx_kmh"]["min"] == pytest.approx(0.36 / (n - 1), rel=1e-6)
    assert f["vy_kmh"]["rmse"] == pytest.approx(0.18)
    assert f["yaw_rate_degps"]["min"] == pytest.approx(2.0)
    assert f["yaw_rate_degps"]["rmse"] == pytest.approx(2.0)
    json.dumps(f, allow_nan=False)
    assert model_fidelity(np.zeros((0, 3)), np.zeros((0, 3)))["vx_kmh"]["rmse"] is None
