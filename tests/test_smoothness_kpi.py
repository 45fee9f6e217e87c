"""Smoothness KPIs (harness/analysis/smoothness.py) against references computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.analysis.smoothness import (
    CHATTER_DEADBAND_NM,
    SMOOTHNESS_KEYS,
    chatter_count,
    delta_m_of,
    frame_rates,
    on_cycle_grid,
    smoothness,
)
from harness.run.controller_config import mpc_period_s

DT = 0.01  # s, the communication cycle


def _torques_for(delta_m: np.ndarray) -> np.ndarray:
    """Wheel torques (n, 4) N·m whose ΔM is ``delta_m``: right wheels +ΔM/4, left −ΔM/4."""
    q = np.asarray(delta_m, dtype=float) / 4.0
    return np.stack([-q, q, -q, q], axis=1)


def test_held_square_wave_by_hand() -> None:
    """ΔM = +400 / −400 N·m, each held 5 cycles (one 50 ms MPC period), 20 halves = 100
    cycles = 1 s: 19 flips of 800 N·m → TV 15 200 N·m in 1 s; every 5-cycle change is a flip,
    800 N·m; 19 increments of alternating sign → 18 reversals in 1 s. Per wheel a flip is a
    200 N·m step in 10 ms = 20 kN·m/s; 19 of the 99 steps of each wheel move, so more than 1 %
    of the 396 wheel steps are 20 kN·m/s: p99 = max."""
    dm = np.repeat(np.tile([400.0, -400.0], 10), 5)
    k = smoothness(dm, _torques_for(dm), cycle_s=DT, period_s=0.05)
    assert set(k) == set(SMOOTHNESS_KEYS)
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(15200.0)
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(800.0)
    assert k["dM_chatter_per_s"] == pytest.approx(18.0)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(20000.0)
    assert k["wheel_torque_rate_p99_Nm_per_s"] == pytest.approx(20000.0)


def test_slow_square_wave_and_a_period_spanning_whole_waves() -> None:
    """ΔM between 100 and 500 N·m, 10 cycles each, 10 halves = 100 cycles = 1 s: 9 flips of
    400 N·m → TV 3600 N·m/s, 8 reversals/s; over 5 cycles the largest change is one flip,
    400 N·m; over 20 cycles (one whole wave) ΔM repeats: 0."""
    dm = np.repeat(np.tile([100.0, 500.0], 5), 10)
    k = smoothness(dm, _torques_for(dm), cycle_s=DT, period_s=0.05)
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(3600.0)
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(400.0)
    assert k["dM_chatter_per_s"] == pytest.approx(8.0)
    whole = smoothness(dm, _torques_for(dm), cycle_s=DT, period_s=0.2)
    assert whole["dM_max_change_per_period_Nm"] == 0.0


def test_ramp_has_its_slope_as_rate_and_no_chatter() -> None:
    """Every wheel ramping at s = 5 kN·m/s for 101 cycles: rate max = p99 = s, no reversal.
    ΔM ramping at 2.5 kN·m/s: TV = 2500 · 1.00 s over a duration of 101 cycles = 1.01 s,
    and 2500 · 0.05 = 125 N·m per MPC period."""
    n, s = 101, 5000.0
    t = np.arange(n) * DT
    tq = np.stack([s * t, -s * t, s * t, -s * t], axis=1)
    k = smoothness(2500.0 * t, tq, cycle_s=DT)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(s, rel=1e-12)
    assert k["wheel_torque_rate_p99_Nm_per_s"] == pytest.approx(s, rel=1e-12)
    assert k["dM_chatter_per_s"] == 0.0
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(2500.0 * 1.00 / 1.01)
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(125.0)


def test_p99_ignores_a_single_spike() -> None:
    """Four wheels at 10 N·m per cycle (1 kN·m/s) for 100 steps, FL with one extra 100 N·m
    step (11 kN·m/s): max 11 kN·m/s; 399 of the 400 steps are 1 kN·m/s, so p99 = 1 kN·m/s."""
    tq = np.tile(10.0 * np.arange(101)[:, None], (1, 4))
    tq[50:, 0] += 100.0
    k = smoothness(delta_m_of(tq), tq, cycle_s=DT)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(11000.0)
    assert k["wheel_torque_rate_p99_Nm_per_s"] == pytest.approx(1000.0)


def test_deadband() -> None:
    """Increments of at most 5 N·m (resolution noise) are not moves; larger ones are."""
    assert CHATTER_DEADBAND_NM == 5.0
    assert chatter_count(np.array([0.0, 5.0, 0.0, 5.0, 0.0])) == 0
    assert chatter_count(np.array([200.0, 201.5, 200.0, 201.5])) == 0
    assert chatter_count(np.array([0.0, 5.5, 0.0, 5.5])) == 2
    # a small toggle between two moves the same way is no reversal
    assert chatter_count(np.array([0.0, 50.0, 48.0, 100.0])) == 0


def test_nans_are_ignored() -> None:
    """ΔM 0, 100, NaN, 0, 100 over 5 cycles (0.05 s): the finite samples 0, 100, 0, 100 give
    TV 300 N·m → 6000 N·m/s and 2 reversals → 40/s; over 2 cycles the only finite pair is
    (100, 0): 100 N·m. A NaN torque removes only the two steps of its wheel next to it."""
    dm = np.array([0.0, 100.0, math.nan, 0.0, 100.0])
    tq = np.tile(np.array([0.0, 1.0, 2.0, 3.0, 4.0])[:, None], (1, 4))
    tq[2, 0] = math.nan
    tq[3, 0] = 50.0  # the step 1 → 50 spans the gap: no rate
    k = smoothness(dm, tq, cycle_s=DT, period_s=0.02)
    assert k["dM_tv_per_s_Nm_per_s"] == pytest.approx(6000.0)
    assert k["dM_chatter_per_s"] == pytest.approx(40.0)
    assert k["dM_max_change_per_period_Nm"] == pytest.approx(100.0)
    assert k["wheel_torque_rate_max_Nm_per_s"] == pytest.approx(4600.0)  # 50 → 4 on FL
    lead = smoothness(np.array([math.nan, 0.0, 100.0, math.nan]), tq, cycle_s=DT)
    assert lead["dM_tv_per_s_Nm_per_s"] == pytest.approx(100.0 / 0.02)  # 2 cycles


@pytest.mark.parametrize("n", [0, 1])
def test_too_short_gives_none(n: int) -> None:
    k = smoothness(np.zeros(n), np.zeros((n, 4)))
    assert set(k) == set(SMOOTHNESS_KEYS) and all(v is None for v in k.values())


def test_all_nan_and_bad_cycle_give_none() -> None:
    nan = np.full(10, math.nan)
    assert all(v is None for v in smoothness(nan, np.full((10, 4), math.nan)).values())
    assert all(v is None for v in smoothness(np.ones(10), np.ones((10, 4)), 0.0).values())


def test_frames_on_the_cycle_grid() -> None:
    """A cycle with two frames keeps the last; a cycle without one is NaN; cycle −1 (before
    the first SYNC) is dropped; rates only between frames of consecutive cycles."""
    grid = on_cycle_grid(np.array([3, 4, 4, 6, -1]), np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    np.testing.assert_array_equal(grid, [1.0, 3.0, math.nan, 4.0])
    two = on_cycle_grid(np.array([1, 2]), np.array([[1.0, 2.0], [3.0, 4.0]]))
    np.testing.assert_array_equal(two, [[1.0, 2.0], [3.0, 4.0]])
    assert on_cycle_grid(np.array([]), np.zeros((0, 4))).shape == (0, 4)
    rates = frame_rates(np.array([0, 1, 2, 4, 5]), np.array([0.0, 10.0, 30.0, 30.0, 0.0]), DT)
    np.testing.assert_allclose(rates, [math.nan, 1000.0, 2000.0, math.nan, 3000.0])


def test_mpc_period_of_the_run_configuration() -> None:
    """The lag of dM_max_change_per_period_Nm comes from the controller TOML's ts_s."""
    assert mpc_period_s(None, {}) == pytest.approx(0.05)
    assert mpc_period_s("100hz", {}) == pytest.approx(0.01)
    assert mpc_period_s(None, {"controller.ts_s": 0.02}) == pytest.approx(0.02)
    assert mpc_period_s("no-such-config", {}) is None
