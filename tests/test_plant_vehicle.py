"""Physics validation of the plant against independent closed-form references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.analysis.fmvss126 import amplitude_schedule_deg, evaluate_sine_with_dwell, find_a_deg
from plant_sim.body import VehicleModel
from plant_sim.params import load_vehicle_params
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation, run_passive

P = load_vehicle_params()


def _axle_stiffness() -> tuple[float, float]:
    """Axle cornering stiffnesses (N/rad, positive) the plant's tyres give at static load."""
    front, rear = P.tyres()
    fzf, fzr = P.static_wheel_loads_n
    return -2.0 * front.cornering_stiffness(fzf), -2.0 * rear.cornering_stiffness(fzr)


def _moving_average(a: np.ndarray, n: int) -> np.ndarray:
    return np.convolve(a, np.ones(n) / n, mode="valid")


# Measured gain error vs the linear bicycle: -0.98 % at 60 km/h (docs/plant.md's figure) and
# -2.05 % at 80 km/h (a_y nearer 0.2 g, a little tyre nonlinearity); bound = |measured| +
# 0.5 percentage point.
@pytest.mark.parametrize(("speed_kmh", "rel"), [(60.0, 0.015), (80.0, 0.025)])
def test_linear_yaw_rate_gain_matches_bicycle(speed_kmh: float, rel: float) -> None:
    """Steady-state r/delta vs vx / (L + K vx^2) at a_y <= 0.2 g, mu = 1."""
    cf, cr = _axle_stiffness()
    L, m = P.wheelbase_m, P.mass_kg
    K = m / L * (P.lr_m / cf - P.lf_m / cr)  # understeer gradient, rad/(m/s^2)
    tr = run_passive(load_scenario("step-steer", speed_kmh=speed_kmh, amplitude_deg=8.0,
                                   duration_s=5.0))
    last = slice(-50, None)  # last 0.5 s, steady
    ay = np.mean(tr["ay_mps2"][last])
    assert 0.02 * 9.81 < ay <= 0.2 * 9.81
    vx = np.mean(tr["vx_mps"][last])
    gain = np.mean(tr["yaw_rate_radps"][last]) / np.mean(tr["delta_f_rad"][last])
    ref = vx / (L + K * vx * vx)
    assert gain == pytest.approx(ref, rel=rel)


@pytest.mark.parametrize("mu", [1.0, 0.35])
def test_max_steady_lateral_acceleration(mu: float) -> None:
    """Slowly increasing steer, coasting: the 1 s-average a_y peak is below mu g (no steady
    state beyond the friction limit) and at least 0.89 mu g. Measured 0.909 g at mu = 1 and
    0.342 g = 0.978 mu g at mu = 0.35 (docs/plant.md); the lower bound is the smaller with a 2 %
    margin (a check within 10 % either side would allow a physically impossible 1.1 mu g)."""
    tr = run_passive(load_scenario("slowly-increasing-steer", mu=mu, speed="coast",
                                   duration_s=14.0))
    ay_max = _moving_average(np.abs(tr["ay_mps2"]), 100).max()
    assert 0.89 * mu * P.gravity_mps2 <= ay_max <= mu * P.gravity_mps2


def test_coast_down_matches_drag_and_rolling_resistance() -> None:
    """Straight coast-down from 120 km/h vs the closed-form solution of
    (m + 4 Iw / r^2) dv/dt = -(f m g + 0.5 rho CdA v^2). Measured: speed loss -0.0055 %
    (docs/plant.md: -0.006 %), deceleration at 100 km/h +0.002 %; bound 0.01 % (about twice the
    claim)."""
    v0 = 120.0 / 3.6
    tr = run_passive(load_scenario("step-steer", speed_kmh=120.0, amplitude_deg=0.0,
                                   speed="coast", duration_s=20.0, length_m=800.0))
    assert tr["t_s"][-1] == pytest.approx(20.0)
    m_eff = P.mass_kg + 4.0 * P.wheel_inertia_kgm2 / P.wheel_radius_m**2
    a = P.rolling_resistance_coeff * P.mass_kg * P.gravity_mps2
    b = 0.5 * P.air_density_kgpm3 * P.drag_area_m2
    t = tr["t_s"]
    v_ref = math.sqrt(a / b) * np.tan(
        math.atan(v0 * math.sqrt(b / a)) - math.sqrt(a * b) * t / m_eff)
    dv_sim = v0 - tr["vx_mps"][-1]
    dv_ref = v0 - v_ref[-1]
    assert dv_sim == pytest.approx(dv_ref, rel=1e-4)
    # instantaneous deceleration at ~100 km/h
    i = int(np.argmin(np.abs(tr["vx_mps"] - 100.0 / 3.6)))
    decel_sim = -np.gradient(tr["vx_mps"], t)[i]
    v = tr["vx_mps"][i]
    assert decel_sim == pytest.approx((a + b * v * v) / m_eff, rel=1e-4)


def test_left_right_mirror_symmetry() -> None:
    left = run_passive(load_scenario("step-steer", amplitude_deg=60.0, direction="left"))
    right = run_passive(load_scenario("step-steer", amplitude_deg=60.0, direction="right"))
    for col in ("x_m", "vx_mps", "ax_mps2", "pitch_rad"):
        np.testing.assert_allclose(right[col], left[col], atol=1e-7)
    for col in ("y_m", "yaw_rad", "vy_mps", "yaw_rate_radps", "ay_mps2", "roll_rad", "swa_rad"):
        np.testing.assert_allclose(right[col], -left[col], atol=1e-7)
    for a, b in (("fl", "fr"), ("rl", "rr")):
        np.testing.assert_allclose(right[f"fz_{a}"], left[f"fz_{b}"], atol=1e-5)
        np.testing.assert_allclose(right[f"omega_{a}"], left[f"omega_{b}"], atol=1e-7)
    assert np.max(np.abs(left["ay_mps2"])) > 5.0  # well into the nonlinear range


def test_torque_difference_gives_expected_yaw_moment() -> None:
    """Delta M = T2 + T4 - T1 - T3 at low slip -> tyre yaw moment wB/(2r) * Delta M.
    Measured 0.992x (docs/plant.md); bound 1.5 %."""
    sim = Simulation(load_scenario("step-steer", speed_kmh=60.0, amplitude_deg=0.0,
                                   speed="coast", duration_s=5.0))
    dm = 400.0  # N·m in total, 100 N·m per wheel: about 0.3 % slip
    cmd = [-dm / 4.0, dm / 4.0, -dm / 4.0, dm / 4.0]
    for _ in range(20):
        sim.step_comm([0.0, 0.0, 0.0, 0.0])
    r0 = sim.vehicle.r
    moments = []
    for k in range(30):
        sim.step_comm(cmd)
        if k >= 10:  # after the motor lag and the longitudinal relaxation (~0.1 s)
            fx = sim.vehicle.fx
            moments.append(0.5 * P.track_m * (fx[1] + fx[3] - fx[0] - fx[2]))
    expected = P.track_m / (2.0 * P.wheel_radius_m) * dm
    assert np.mean(moments) == pytest.approx(expected, rel=0.015)
    assert sim.vehicle.r > r0  # Delta M > 0 turns the car left
    assert sim.truth_row()["delta_m_nm"] == pytest.approx(dm)


def test_uncontrolled_sine_with_dwell_on_low_mu_spins_safely() -> None:
    tr = run_passive(load_scenario("sine-with-dwell", mu=0.35, amplitude_deg=180.0,
                                   duration_s=8.0))
    for name, col in tr.items():
        assert np.all(np.isfinite(col)), name
    assert tr["spun"][-1] == 1.0
    assert np.max(np.abs(tr["beta_rad"])) > math.radians(45.0)


def test_passive_car_fails_fmvss126_on_high_mu() -> None:
    """The passive car passes the sine with dwell up to 3.0A and fails from 3.5A = 66.8 deg
    (mu = 1), as docs/plant.md states. Measured A = 19.07 deg; bound ±0.2 deg (a schedule step
    is 0.5A ≈ 9.5 deg, so the first failing amplitude stays 3.5A). Was 10 < A < 60 and
    "fails at some amplitude <= 270 deg"."""
    sis = run_passive(load_scenario("slowly-increasing-steer"))
    a_deg = find_a_deg(np.degrees(sis["swa_rad"]), sis["ay_mps2"])
    assert a_deg == pytest.approx(19.07, abs=0.2)
    results = []
    for amp in amplitude_schedule_deg(a_deg):
        tr = run_passive(load_scenario("sine-with-dwell", amplitude_deg=amp))
        res = evaluate_sine_with_dwell(tr["t_s"], np.degrees(tr["swa_rad"]),
                                       tr["yaw_rate_radps"], tr["x_m"], tr["y_m"],
                                       tr["yaw_rad"], amp, a_deg)
        results.append((amp, res.passed))
        if not res.passed:
            break
    assert [round(amp / a_deg, 2) for amp, _ in results] == [1.5, 2.0, 2.5, 3.0, 3.5]
    assert [ok for _, ok in results] == [True, True, True, True, False], results
    assert results[-1][0] == pytest.approx(66.8, abs=0.1)


def test_passive_car_completes_paper_dlc_at_50_kmh() -> None:
    sc = load_scenario("dlc-paper", speed_kmh=50.0)
    tr = run_passive(sc)
    assert tr["spun"][-1] == 0.0
    assert tr["path_s_m"][-1] >= sc.course_end_s  # got through the course
    for lane in sc.lanes:  # CG inside every gated lane
        inside = (tr["x_m"] >= lane.x0) & (tr["x_m"] <= lane.x1)
        assert inside.any()
        assert np.all(tr["y_m"][inside] > lane.y_right)
        assert np.all(tr["y_m"][inside] < lane.y_left)
    half_lane = 0.5 * min(ln.y_left - ln.y_right for ln in sc.lanes)
    assert np.max(np.abs(tr["lateral_dev_m"])) < half_lane


def test_deterministic_same_seed() -> None:
    def run(seed: int) -> tuple[list[dict[str, float]], list[object]]:
        sim = Simulation(load_scenario("dlc-paper-high-mu"), seed=seed)
        rows, frames = [], []
        for k in range(300):
            sim.step_comm(None if k % 7 == 0 else [50.0, -20.0, 30.0, 10.0])
            rows.append(sim.truth_row())
            frames.append(sim.sensors())
        return rows, frames

    rows_a, frames_a = run(3)
    rows_b, frames_b = run(3)
    rows_c, frames_c = run(4)
    assert rows_a == rows_b
    assert frames_a == frames_b
    assert rows_a == rows_c  # the seed only drives sensor noise
    assert frames_a != frames_c


@settings(max_examples=100, deadline=None)
@given(
    torques=st.lists(st.floats(-1e4, 1e4), min_size=4, max_size=4),
    swa_deg=st.floats(-1000.0, 1000.0),
    speed=st.floats(0.0, 60.0),
    mu=st.floats(0.05, 1.5),
)
def test_no_nan_under_extreme_inputs(torques: list[float], swa_deg: float, speed: float,
                                     mu: float) -> None:
    model = VehicleModel(P)
    model.reset(vx=speed)
    delta = math.radians(swa_deg) / P.steering_ratio
    for k in range(100):  # 1 s of raw (unsaturated) torques; the motor envelope still applies
        sign = 1.0 if (k // 25) % 2 == 0 else -1.0
        model.advance([sign * delta] * 10, [sign * t for t in torques], mu)
    state = [model.x, model.y, model.psi, model.vx, model.vy, model.r, model.phi, model.theta,
             *model.omega, *model.alpha_t, *model.kappa_t, *model.torque, *model.fz]
    assert all(math.isfinite(v) for v in state)
    assert all(abs(t) <= P.peak_torque_nm + 1e-9 for t in model.torque)


def test_bad_commands_are_rejected_and_saturated() -> None:
    sim = Simulation(load_scenario("step-steer", amplitude_deg=0.0))
    sim.step_comm([float("nan"), 0.0, 0.0, 0.0])
    assert sim.invalid_cmd_count == 1 and not sim.cmd_valid
    sim.step_comm([1.0, 2.0])  # wrong length
    assert sim.invalid_cmd_count == 2
    sim.step_comm([1e6, -1e6, 0.0, 0.0])
    assert sim.cmd_valid
    assert sim.tcmd[0] == pytest.approx(P.peak_torque_nm)
    assert sim.tcmd[1] == pytest.approx(-P.peak_torque_nm)
    assert sim.saturation_count == 2
    # above the base speed the power limit applies
    fast = Simulation(load_scenario("step-steer", amplitude_deg=0.0, speed_kmh=180.0))
    fast.step_comm([1e6] * 4)
    omega = fast.vehicle.omega[0]
    assert fast.tcmd[0] <= P.peak_power_w / (omega - 1.0)
    for sim_ in (sim, fast):
        sim_.step_comm(None)
        assert np.all(np.isfinite(list(sim_.truth_row().values())))
