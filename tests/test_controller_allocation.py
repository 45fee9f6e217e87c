"""Torque allocation (eq. 16) and the pedal map."""

from __future__ import annotations

import math
import tracemalloc
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from controller.core.allocation import AllocationConfig, TorqueAllocator
from controller.core.params import load_vehicle_params
from controller.core.pedal_map import total_torque_from_pedals

VEHICLE = load_vehicle_params()
# The static allocation law (eq. 16, limits, split) is tested without the motor torque-rate
# limit; the rate limit has its own tests below.
P = replace(VEHICLE, torque_rate_nm_per_s=0.0)
finite = st.floats(-1e4, 1e4, allow_nan=False)
anyf = st.floats(allow_nan=True, allow_infinity=True)


def limit(w: float) -> float:
    """Independent per-motor limit: min(T_peak, P_peak/|ω|); non-finite ω → T_peak."""
    if not math.isfinite(w) or w == 0.0:
        return P.peak_torque_nm
    return min(P.peak_torque_nm, P.peak_power_w / abs(w))


def test_pedal_map_contract() -> None:
    assert total_torque_from_pedals(1.0, 0.0, 450.0) == 1800.0
    assert total_torque_from_pedals(0.0, 1.0, 450.0) == -1800.0
    assert total_torque_from_pedals(0.3, 0.1, 450.0) == pytest.approx(0.2 * 1800.0)
    assert total_torque_from_pedals(2.0, -1.0, 450.0) == 1800.0       # clipped
    assert total_torque_from_pedals(math.nan, math.inf, 450.0) == 0.0  # NaN → released


@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-8, 8), st.floats(-8, 8),
       st.floats(0.0, 150.0))
def test_eq16_holds_exactly_when_feasible(ft: float, fd: float, ax: float, ay: float,
                                          w: float) -> None:
    al = TorqueAllocator(P)
    lim = limit(w)
    c = 2 * lim                                   # side capacity
    # Sample a feasible (Tt, ΔM): |Tt ± ΔM| ≤ 2c.
    tt = ft * 2 * c
    dm = fd * (2 * c - abs(tt))
    ws = np.full(4, w)
    t = al.allocate(tt, dm, ax, ay, ws)
    assert t.sum() == pytest.approx(tt, abs=1e-9 * 1800)
    assert (t[1] + t[3] - t[0] - t[2]) == pytest.approx(dm, abs=1e-9 * 1800)
    assert np.all(np.abs(t) <= lim + 1e-9)


@given(finite, finite, anyf, anyf, st.lists(anyf, min_size=4, max_size=4))
def test_limits_respected_and_delta_m_has_priority(tt: float, dm: float, ax: float,
                                                   ay: float, ws: list[float]) -> None:
    al = TorqueAllocator(P)
    t = al.allocate(tt, dm, ax, ay, np.array(ws))
    lims = np.array([limit(w) for w in ws])
    assert np.all(np.isfinite(t))
    assert np.all(np.abs(t) <= lims + 1e-9)
    cl, cr = lims[0] + lims[2], lims[1] + lims[3]
    # ΔM is kept as far as any Tt can realise it; Tt yields.
    dm_feasible = min(max(dm, -(cl + cr)), cl + cr)
    assert al.dm_applied == pytest.approx(dm_feasible, abs=1e-6)
    assert al.dm_applied == pytest.approx(t[1] + t[3] - t[0] - t[2], abs=1e-6)
    assert al.tt_applied == pytest.approx(t.sum(), abs=1e-6)


def test_power_limit_bites_above_base_speed() -> None:
    al = TorqueAllocator(P)
    w = 200.0                                     # rad/s: P/ω = 225 N·m < 450
    t = al.allocate(4000.0, 0.0, 0.0, 0.0, np.full(4, w))
    np.testing.assert_allclose(np.abs(t), 225.0)
    assert al.delta_m_capacity(np.full(4, w)) == pytest.approx(4 * 225.0)
    assert al.delta_m_capacity(np.full(4, 10.0)) == pytest.approx(4 * 450.0)


def test_front_rear_split_follows_normal_load() -> None:
    al = TorqueAllocator(P)
    ws = np.full(4, 50.0)
    t0 = al.allocate(800.0, 0.0, 0.0, 0.0, ws).copy()
    L = P.wheelbase_m
    # Static: front share lr/L.
    assert t0[0] / (t0[0] + t0[2]) == pytest.approx(P.lr_m / L)
    t_acc = al.allocate(800.0, 0.0, 3.0, 0.0, ws).copy()
    assert t_acc[2] > t0[2] and t_acc[0] < t0[0]            # load to the rear
    t_brk = al.allocate(-800.0, 0.0, -5.0, 0.0, ws).copy()
    assert abs(t_brk[0]) > abs(t_brk[2])                      # braking: front takes more
    eq = TorqueAllocator(P, AllocationConfig(split="equal"))
    np.testing.assert_allclose(eq.allocate(800.0, 0.0, 3.0, 0.0, ws), 200.0)


def test_saturated_front_wheel_moves_torque_to_the_rear_same_side() -> None:
    al = TorqueAllocator(P)
    ws = np.array([50.0, 50.0, 50.0, 50.0])
    t = al.allocate(0.0, 1800.0, -9.0, 0.0, ws)      # hard braking shifts load forward
    assert t[1] + t[3] == pytest.approx(900.0)
    assert t[0] + t[2] == pytest.approx(-900.0)
    assert np.all(np.abs(t) <= 450.0 + 1e-9)


def test_no_memory_growth_over_1e5_allocations() -> None:
    al = TorqueAllocator(P)
    ws = np.full(4, 50.0)
    rng = np.random.default_rng(0)
    vals = rng.normal(0, 1000, size=(100_000, 2))
    for k in range(1000):
        al.allocate(vals[k, 0], vals[k, 1], 1.0, 2.0, ws)
    tracemalloc.start()
    base = tracemalloc.take_snapshot()
    for k in range(100_000):
        al.allocate(vals[k, 0], vals[k, 1], 1.0, 2.0, ws)
    grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(base, "filename")
                if s.size_diff > 0)
    tracemalloc.stop()
    assert grown < 10_000     # bytes; tracemalloc's own bookkeeping is a few kB


# ------------------------------------------------------------------ motor torque rate
def test_rate_limit_slews_every_wheel_by_rate_times_cycle() -> None:
    """From rest, a full drive request ramps each wheel by rate·cycle per call (10 kN·m/s ×
    10 ms = 100 N·m) until the static allocation is reached; Tt and ΔM are those realised."""
    a = TorqueAllocator(VEHICLE)
    static = TorqueAllocator(P)
    step = VEHICLE.torque_rate_nm_per_s * AllocationConfig().cycle_s
    assert step == pytest.approx(100.0)
    ws = np.full(4, 10.0)
    target = static.allocate(1200.0, 400.0, 0.0, 0.0, ws).copy()
    prev = np.zeros(4)
    for _k in range(1, 8):
        out = a.allocate(1200.0, 400.0, 0.0, 0.0, ws).copy()
        expected = np.clip(target, prev - step, prev + step)
        np.testing.assert_allclose(out, expected, atol=1e-12)
        assert a.tt_applied == pytest.approx(out.sum())
        assert a.dm_applied == pytest.approx(out[1] + out[3] - out[0] - out[2])
        prev = out
    np.testing.assert_allclose(prev, target, atol=1e-12)
    assert a.rate_limited_calls == math.ceil(np.max(np.abs(target)) / step) - 1


@given(st.lists(st.tuples(finite, finite, st.floats(0.0, 150.0)), min_size=2, max_size=30))
def test_rate_limit_never_exceeded_and_motor_limit_has_priority(
        seq: list[tuple[float, float, float]]) -> None:
    a = TorqueAllocator(VEHICLE)
    step = VEHICLE.torque_rate_nm_per_s * AllocationConfig().cycle_s
    prev = np.zeros(4)
    for tt, dm, w in seq:
        out = a.allocate(tt, dm, 0.0, 0.0, np.full(4, w)).copy()
        lim = limit(w)
        assert np.all(np.abs(out) <= lim + 1e-9)
        # a wheel moves by more than one step only when its limit cut it
        moved = np.abs(out - prev)
        assert np.all((moved <= step + 1e-9) | (np.abs(out) >= lim - 1e-9))
        prev = out


def test_reset_starts_the_motors_from_zero() -> None:
    a = TorqueAllocator(VEHICLE)
    ws = np.full(4, 10.0)
    for _ in range(10):
        a.allocate(1800.0, 0.0, 0.0, 0.0, ws)
    a.reset()
    out = a.allocate(1800.0, 0.0, 0.0, 0.0, ws)
    assert np.all(out <= 100.0 + 1e-12) and a.rate_limited_calls == 1
