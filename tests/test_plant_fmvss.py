"""harness/analysis/fmvss126.py on synthetic traces with known answers, and the steering robot."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.analysis.fmvss126 import (
    G,
    amplitude_schedule_deg,
    evaluate_sine_with_dwell,
    find_a_deg,
)
from plant_sim.driver import sine_with_dwell_deg

F = 0.7  # Hz


def _synthetic(amplitude: float, decay_tau: float, sign: float = 1.0) -> dict[str, np.ndarray]:
    """SWA from the robot profile starting at t = 1 s; yaw rate = SWA * k after COS decaying
    with time constant decay_tau; straight-line x and a known lateral offset y."""
    t = np.arange(0.0, 6.0, 0.001)
    swa = np.array([sign * sine_with_dwell_deg(ti - 1.0, amplitude) for ti in t])
    t_cos = 1.0 + 1.0 / F + 0.5
    r = np.where(t < t_cos, 0.002 * swa, 0.0)
    peak = np.min(sign * r[(t > 1.0 + 0.5 / F) & (t < t_cos)]) * sign
    r = np.where(t >= t_cos, peak * np.exp(-(t - t_cos) / decay_tau), r)
    x = 22.0 * t
    y = sign * 0.5 * np.clip(t - 1.0, 0.0, None) ** 2  # lateral displacement 0.5 t^2
    return {"t": t, "swa": swa, "r": r, "x": x, "y": y, "yaw": np.zeros_like(t)}


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_bos_cos_and_ratios(sign: float) -> None:
    amp = 120.0
    tr = _synthetic(amp, decay_tau=0.5, sign=sign)
    res = evaluate_sine_with_dwell(tr["t"], tr["swa"], tr["r"], tr["x"], tr["y"], tr["yaw"],
                                   amplitude_deg=amp, a_deg=20.0)
    t_bos = 1.0 + math.asin(5.0 / amp) / (2 * math.pi * F)
    assert res.t_bos_s == pytest.approx(t_bos, abs=2e-3)
    assert res.t_cos_s == pytest.approx(1.0 + 1.0 / F + 0.5, abs=2e-3)
    assert res.yrr_1s == pytest.approx(math.exp(-1.0 / 0.5), rel=1e-2)
    assert res.yrr_175s == pytest.approx(math.exp(-1.75 / 0.5), rel=1e-2)
    assert res.pass_yrr_1s and res.pass_yrr_175s
    # y = 0.5 (t - 1)^2 relative to the line held at BOS (heading 0)
    expected_lat = 0.5 * ((t_bos + 1.07 - 1.0) ** 2 - (t_bos - 1.0) ** 2)
    assert res.lateral_displacement_m == pytest.approx(expected_lat, abs=1e-3)
    assert res.lateral_required  # 120 >= 5 * 20
    assert res.passed == (expected_lat >= 1.83)


def test_slow_decay_fails_yaw_ratio() -> None:
    tr = _synthetic(120.0, decay_tau=5.0)
    res = evaluate_sine_with_dwell(tr["t"], tr["swa"], tr["r"], tr["x"], tr["y"], tr["yaw"])
    assert not res.pass_yrr_1s and not res.passed


def test_amplitude_schedule() -> None:
    sched = amplitude_schedule_deg(20.0)
    assert sched == pytest.approx([30, 40, 50, 60, 70, 80, 90, 100, 110, 120, 130])
    capped = amplitude_schedule_deg(50.0)
    assert capped[0] == 75.0 and capped[-1] == 270.0 and max(capped) == 270.0
    assert len(capped) == len(set(capped))
    std = amplitude_schedule_deg(30.0, standard_rule=True)
    assert std[-1] == 270.0  # greater of 6.5A = 195 and 270
    assert amplitude_schedule_deg(50.0, standard_rule=True)[-1] == 300.0


def test_find_a_from_linear_data() -> None:
    ay = np.linspace(0.0, 0.6 * G, 500)
    swa = 60.0 * ay / G + 2.0  # deg; 0.3 g -> 20 deg
    assert find_a_deg(swa, ay) == pytest.approx(20.0, rel=1e-9)
    with pytest.raises(ValueError):
        find_a_deg(swa[:100], ay[:100])  # never reaches 0.375 g


def test_robot_profile_shape() -> None:
    assert sine_with_dwell_deg(0.0, 100.0) == 0.0
    assert sine_with_dwell_deg(0.25 / F, 100.0) == pytest.approx(100.0)
    assert sine_with_dwell_deg(0.75 / F + 0.25, 100.0) == -100.0  # dwell
    assert sine_with_dwell_deg(1.0 / F + 0.5 + 0.01, 100.0) == 0.0
