"""Sensor model: quantisation to the CAN resolution, seeded noise, bias, estimator lag."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plant_sim.params import SensorParams, load_vehicle_params
from plant_sim.scenario import load_scenario
from plant_sim.sensors import SensorModel, quantise
from plant_sim.simulation import PEDAL_TORQUE_NM, Simulation


def _on_grid(value: float, res: float) -> bool:
    return abs(value / res - round(value / res)) < 1e-6


def _sample(model: SensorModel, **over: float) -> object:
    kw: dict = dict(swa_rad=0.1, accel_pedal=0.2, brake_pedal=0.0, stab_enable=True,
                    yaw_rate=0.2, ax=0.5, ay=3.0, roll=0.0, pitch=0.0, gravity=9.81,
                    omegas=[50.0, 50.1, 50.2, 50.3], vx=18.0, vy=0.3)
    kw.update(over)
    return model.sample(**kw)


def test_quantisation_to_can_resolution() -> None:
    p = load_vehicle_params().sensors
    model = SensorModel(p, 0.01, seed=1)
    from can_db.codec import Codec

    # the grids are the DBC's resolutions: the plant quantises once, to what the frame carries
    scale = {s.name: s.scale for m in Codec().messages.values() for s in m.signals}
    assert (scale["AX"], scale["WS_FL"]) == (0.005, 0.1)
    for _ in range(50):
        f = _sample(model)
        assert _on_grid(f.yaw_rate_degps, scale["YAW_RATE"])
        assert _on_grid(f.ax_mps2, scale["AX"]) and _on_grid(f.ay_mps2, scale["AY"])
        assert all(_on_grid(w, scale["WS_FL"]) for w in f.wheel_speeds_radps)
        assert _on_grid(f.swa_deg, scale["SWA"])
        assert _on_grid(f.vx_est_mps, scale["VX_EST"]) and _on_grid(f.vy_est_mps,
                                                                     scale["VY_EST"])
    assert quantise(1.234, 0.05) == pytest.approx(1.25)


def test_noise_and_bias_statistics() -> None:
    p = SensorParams(yaw_rate_noise_degps=0.2, yaw_rate_bias_degps=0.3,
                     accel_includes_gravity_tilt=False)
    model = SensorModel(p, 0.01, seed=7)
    r = np.array([_sample(model, yaw_rate=0.0).yaw_rate_degps for _ in range(4000)])
    # 4 standard errors of 4000 samples (was ~6 for the mean and ~7 for the σ): the mean's
    # SE is 0.2/√4000 = 0.0032 deg/s, the σ estimate's relative SE 1/√(2·4000) = 1.1 %.
    assert r.mean() == pytest.approx(0.3, abs=4 * 0.2 / math.sqrt(4000))
    assert r.std() == pytest.approx(0.2, rel=4 / math.sqrt(2 * 4000))


def test_gravity_tilt_and_estimator_lag() -> None:
    p = SensorParams(accel_noise_mps2=0.0, ay_bias_mps2=0.0, vx_noise_mps=0.0,
                     vy_noise_mps=0.0, vx_lag_s=0.1)
    model = SensorModel(p, 0.01, seed=0)
    f = _sample(model, ay=0.0, roll=0.05)
    assert f.ay_mps2 == pytest.approx(9.81 * math.sin(0.05), abs=0.002)
    # The estimator starts converged on the first sample (18 m/s), then follows truth through
    # a first-order lag, tau = 0.1 s, exact discretisation at 10 ms: x += a (v - x).
    _sample(model, vx=10.0)
    f = _sample(model, vx=20.0)
    a = 1.0 - math.exp(-0.01 / 0.1)
    x = 18.0 + a * (10.0 - 18.0)
    x += a * (20.0 - x)                              # 17.50 m/s
    assert f.vx_est_mps == pytest.approx(x, abs=0.0025)   # half the 0.005 m/s CAN quantum


def test_sensor_frames_seeded_and_pedal_contract() -> None:
    a = Simulation(load_scenario("slippery-curve"), seed=11)
    b = Simulation(load_scenario("slippery-curve"), seed=11)
    for _ in range(50):
        a.step_comm(None)
        b.step_comm(None)
        assert a.sensors() == b.sensors()
    f = a.sensors()
    assert 0.0 <= f.accel_pedal <= 1.0 and f.brake_pedal == 0.0
    # no command -> Tt/4 on each wheel, Tt = (accel - brake) * 4 * 450
    tt = (a.driver.accel_pedal - a.driver.brake_pedal) * PEDAL_TORQUE_NM
    a.step_comm(None)
    assert a.tcmd == pytest.approx([tt / 4.0] * 4)
    assert tt > 0.0
    assert PEDAL_TORQUE_NM == 1800.0
