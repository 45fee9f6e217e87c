"""Smoothness KPIs (harness/analysis/smoothness.py) against hand-computed references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.analysis.smoothness import SMOOTHNESS_KEYS, chatter_count, smoothness


def _torques_for(delta_m: np.ndarray) -> np.ndarray:
    """Wheel torques (n, 4) whose ΔM is ``delta_m``: right wheels +ΔM/4, left −ΔM/4."""
    q = np.asarray(delta_m, dtype=float) / 4.0
    return np.stack([-q, q, -q, q], axis=1)


def test_held_square_wave_by_hand() -> None:
    """ΔM = ±400 N·m held 5 cycles each (a 50 ms MPC period), 20 periods over 1 s at 10 ms:
    19 flips of 800 N·m → TV 15 200 N·m in 1 s; the largest change over one period 800;
    every flip is one 200 N·m step per wheel in 10 ms = 20 kN·m/s; 18 sign reversals."""
    dm = np.repeat(np.tile([400.0, -400.0], 10), 5)
    k = smoothness(_torques_for(dm), cycle_s=0.01, period_s=0.05)
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(19 * 800.0 / 1.0)
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(800.0)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(200.0 / 0.01)
    assert k["dM_chatter_per_s"] == pytest.approx(18.0)
    # 19 of the 99 per-wheel steps move: the p99 of 396 wheel-steps is the full rate
    assert k["wheel_torque_rate_p99_Nm_per_s"] == pytest.approx(20000.0)


def test_ramp_has_its_slope_as_rate_and_no_chatter() -> None:
    """Every wheel ramping at 5 kN·m/s: rate max = p99 = 5000 N·m/s exactly, no reversal."""
    n = 101
    t = np.arange(n) * 0.01
    tq = np.stack([5000.0 * t, 5000.0 * t, -2500.0 * t, 0.0 * t], axis=1)
    k = smoothness(tq, cycle_s=0.01)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(5000.0)
    assert k["dM_chatter_per_s"] == 0.0
    dm = tq[:, 1] + tq[:, 3] - tq[:, 0] - tq[:, 2]        # 2500·t
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx((dm[-1] - dm[0]) / (n * 0.01))
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(2500.0 * 0.05)


def test_deadband_and_nan_rows() -> None:
    assert chatter_count(np.array([0.0, 3.0, 0.0, 3.0, 0.0])) == 0      # within 5 N·m
    assert chatter_count(np.array([0.0, 30.0, 0.0, 30.0])) == 2
    dm = np.array([0.0, 100.0, math.nan, 0.0, 100.0])
    k = smoothness(_torques_for(dm), cycle_s=0.01)
    # the NaN row is dropped: ΔM 0, 100, 0, 100 over 4 cycles
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(300.0 / 0.04)


def test_too_short_gives_none() -> None:
    for tq in (np.zeros((0, 4)), np.zeros((1, 4))):
        k = smoothness(tq)
        assert set(k) == set(SMOOTHNESS_KEYS) and all(v is None for v in k.values())
