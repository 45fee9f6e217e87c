"""Output safety envelope: configuration errors, the packaged and file configurations, and
the conflict paths that only non-default parameters (or float rounding) reach."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.core.config_schema import ConfigError
from controller.core.params import load_vehicle_params
from controller.runtime.envelope import (
    EnvelopeConfig,
    EnvelopeCounters,
    SafetyEnvelope,
    _clip,
    load_envelope_config,
)

PARAMS = load_vehicle_params()
TP, PP, DT = PARAMS.peak_torque_nm, PARAMS.peak_power_w, 0.01


def run(env: SafetyEnvelope, cmd, ws=(0.0,) * 4, zero_dm: bool = False, prev=(0.0,) * 4
        ) -> tuple[np.ndarray, bool]:
    """One envelope step; returns the output and the 'limited' flag."""
    out = np.zeros(4)
    acted = env.apply(np.array(cmd, dtype=float), np.array(ws, dtype=float), zero_dm,
                      np.array(prev, dtype=float), out)
    return out, acted


def dm(t) -> float:
    """ΔM = T2 + T4 − T1 − T3, N·m."""
    return float((t[1] - t[0]) + (t[3] - t[2]))


# -------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("key", ["torque_quantum_nm", "clip_tol_nm"])
@pytest.mark.parametrize("value", [-0.5, math.inf, math.nan])
def test_quantum_and_clip_tolerance_must_be_finite_and_not_negative(key: str, value: float
                                                                     ) -> None:
    with pytest.raises(ConfigError, match=key):
        EnvelopeConfig.from_dict({key: value})


@pytest.mark.parametrize("key", ["torque_rate_nm_per_s", "delta_m_rate_nm_per_s"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.inf])
def test_rates_must_be_finite_and_positive(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=key):
        EnvelopeConfig.from_dict({key: value})


def test_zero_quantum_and_zero_tolerance_are_accepted() -> None:
    cfg = EnvelopeConfig.from_dict({"torque_quantum_nm": 0.0, "clip_tol_nm": 0.0})
    assert cfg.torque_quantum_nm == 0.0 and cfg.clip_tol_nm == 0.0


def test_packaged_configuration_holds_the_documented_defaults() -> None:
    cfg = load_envelope_config()
    assert cfg == EnvelopeConfig(60000.0, 180000.0, 0.5, 1e-6)


def test_configuration_from_a_file(tmp_path: Path) -> None:
    path = tmp_path / "env.toml"
    path.write_text("[envelope]\ntorque_rate_nm_per_s = 1000.0\ntorque_quantum_nm = 0.0\n")
    cfg = load_envelope_config(path)
    assert cfg.torque_rate_nm_per_s == 1000.0 and cfg.torque_quantum_nm == 0.0
    assert cfg.delta_m_rate_nm_per_s == 180000.0   # untouched keys keep their default
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    assert load_envelope_config(empty) == EnvelopeConfig()
    bad = tmp_path / "bad.toml"
    bad.write_text("[envelope]\nclip_tol_nm = -1.0\n")
    with pytest.raises(ConfigError):
        load_envelope_config(str(bad))


@pytest.mark.parametrize(("tp", "pp", "dt"), [(0.0, PP, DT), (TP, 0.0, DT), (TP, PP, 0.0),
                                              (-1.0, PP, DT), (TP, PP, math.nan)])
def test_the_envelope_refuses_non_positive_peaks_and_period(tp: float, pp: float, dt: float
                                                             ) -> None:
    with pytest.raises(ValueError, match="peak torque, peak power and dt"):
        SafetyEnvelope(EnvelopeConfig(), tp, pp, dt)


def test_per_cycle_bounds_and_the_conflict_free_condition() -> None:
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=45000.0,
                                        delta_m_rate_nm_per_s=180000.0), TP, PP, DT)
    assert env.d_wheel == pytest.approx(TP) and env.d_dm == pytest.approx(4.0 * TP)
    assert env.conflict_free                        # both bounds exactly at their minimum
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=44000.0), TP, PP, DT)
    assert not env.conflict_free                    # the wheel rate below T_peak per cycle
    env = SafetyEnvelope(EnvelopeConfig(delta_m_rate_nm_per_s=179000.0), TP, PP, DT)
    assert not env.conflict_free                    # the ΔM rate below 4·T_peak per cycle


def test_clip_helper() -> None:
    assert _clip(5.0, 0.0, 1.0) == 1.0 and _clip(-5.0, 0.0, 1.0) == 0.0
    assert _clip(0.5, 0.0, 1.0) == 0.5 and _clip(1.0, 0.0, 1.0) == 1.0


def test_wheel_limit_without_quantum_is_the_exact_power_limit() -> None:
    env = SafetyEnvelope(EnvelopeConfig(torque_quantum_nm=0.0), TP, PP, DT)
    assert env.wheel_limit(123.0) == PP / 123.0
    assert env.wheel_limit(-123.0) == PP / 123.0
    assert env.wheel_limit(PP / TP) == TP                    # the corner speed: T_peak
    assert env.wheel_limit(math.nan) == TP and env.wheel_limit(-math.inf) == TP


# ---------------------------------------------------------------------- conflict paths
def test_rate_window_beyond_the_power_limit_gives_way_to_the_motor_limit() -> None:
    """100 N·m per cycle from ±450 N·m cannot reach the 300 N·m power limit at 150 rad/s:
    the motor limit wins (a counted conflict), on either sign."""
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=10000.0), TP, PP, DT)
    prev = (450.0, 450.0, -450.0, -450.0)
    out, acted = run(env, prev, ws=(150.0,) * 4, prev=prev)
    assert out.tolist() == [300.0, 300.0, -300.0, -300.0]
    assert env.counters.conflicts == 4 and env.counters.power_limit == 4
    assert acted and env.counters.limited_steps == 1


def test_wheel_windows_win_over_the_delta_m_rate() -> None:
    """Each wheel is pinned to its power limit (a conflict each) and the ΔM those pins
    allow lies outside the ΔM rate window: the wheel windows win, one more conflict."""
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=10000.0,
                                        delta_m_rate_nm_per_s=10000.0), TP, PP, DT)
    prev = (-450.0, 450.0, -450.0, 450.0)   # ΔM 1800; reachable: 1200 only
    out, acted = run(env, prev, ws=(150.0,) * 4, prev=prev)
    assert out.tolist() == [-300.0, 300.0, -300.0, 300.0]
    assert dm(out) == 1200.0
    assert env.counters.conflicts == 5 and acted


def test_zero_yaw_moment_beyond_the_delta_m_rate_is_a_counted_conflict() -> None:
    env = SafetyEnvelope(EnvelopeConfig(delta_m_rate_nm_per_s=50000.0), TP, PP, DT)
    prev = (-300.0, 300.0, 0.0, 0.0)         # ΔM 600 > 500 N·m per cycle
    out, _ = run(env, prev, zero_dm=True, prev=prev)
    assert out.tolist() == [0.0, 0.0, 0.0, 0.0]
    assert env.counters.conflicts == 1 and env.counters.dm_zeroed == 1
    assert env.last_zeroed
    # inside the ΔM rate: no conflict
    env = SafetyEnvelope(EnvelopeConfig(delta_m_rate_nm_per_s=50000.0), TP, PP, DT)
    prev = (-250.0, 250.0, 0.0, 0.0)         # ΔM 500: exactly the bound
    out, _ = run(env, prev, zero_dm=True, prev=prev)
    assert dm(out) == 0.0 and env.counters.conflicts == 0


def test_pair_window_without_overlap_takes_the_symmetric_point_inside_the_motor_limit() -> None:
    """Zero ΔM with rate windows of the two front wheels apart: the midpoint of the gap,
    clipped to the smaller motor limit, for both wheels (a counted conflict)."""
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=10000.0,
                                        delta_m_rate_nm_per_s=10000.0), TP, PP, DT)
    prev = (-450.0, 450.0, 100.0, 100.0)    # FL window [-450,-350], FR [350, 450]
    out, _ = run(env, prev, ws=(0.0, 150.0, 0.0, 0.0), zero_dm=True, prev=prev)
    # FR: L = 300 < p - d = 350, pinned to 300 (conflict); gap [-350, 300] → -25
    assert out[0] == out[1] == -25.0
    assert out[2] == out[3]
    # FR pinned to its limit, the front pair's gap, and ΔM 900 beyond the 100 N·m rate
    assert env.counters.conflicts == 3


def test_side_split_at_a_rounded_corner_stays_inside_the_envelope() -> None:
    """Float rounding at a corner of the wheel windows can make the side-sum window empty
    by an ulp; the envelope then takes its midpoint and every limit still holds."""
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    cmd = [-575.9832939505687, 458.2945065089252, -407.63080725422526, -51.16615123553129]
    ws = [0.0, 92.14794857878894, 0.0, -358.34841234352973]
    prev = [-306.0883162092864, -330.8679903970997, 380.99101756715856, 289.69144890429664]
    out, acted = run(env, cmd, ws=ws, prev=prev)
    assert acted and np.all(np.isfinite(out))
    for i in range(4):
        assert abs(out[i]) <= env.wheel_limit(ws[i]) + 1e-9
        assert abs(out[i] - prev[i]) <= env.d_wheel + 1e-9
    assert abs(dm(out) - dm(prev)) <= env.d_dm + 1e-9
    assert out.tolist() == [-450.0, 269.1320096029003, -219.00898243284144, 125.5]


def test_counters_start_at_zero_and_count_steps() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    assert env.counters == EnvelopeCounters()
    run(env, [0.0] * 4)
    run(env, [0.0] * 4)
    assert env.counters.steps == 2 and env.counters.limited_steps == 0


def test_class_defaults_are_the_packaged_configuration() -> None:
    """A node built without a file gets the same limits as one built from envelope.toml."""
    assert EnvelopeConfig() == load_envelope_config()
    assert EnvelopeConfig.from_dict({}) == EnvelopeConfig()


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_yaw_moment_change_exactly_at_the_delta_m_rate_passes_unchanged(sign: float) -> None:
    """ΔM from 0 to ±1800 N·m in one cycle is exactly the bound: no limit acts."""
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    cmd = [-sign * 450.0, sign * 450.0, -sign * 450.0, sign * 450.0]
    out, acted = run(env, cmd)
    assert dm(out) == sign * env.d_dm and out.tolist() == cmd
    assert not acted and env.counters.dm_rate_limit == 0 and env.counters.limited_steps == 0


# ----------------------------------------------------------------- boundaries and counts
def test_rate_limit_is_counted_for_a_command_inside_the_motor_limit_too() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    out, acted = run(env, [300.0, 0.0, 0.0, 0.0], prev=(-450.0, 0.0, 0.0, 0.0))
    assert out[0] == 150.0 and acted                      # -450 + 600 N·m per cycle
    assert env.counters.rate_limit == 1 and env.counters.torque_limit == 0


def test_rate_limit_is_counted_for_a_command_at_the_motor_limit() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    out, acted = run(env, [-TP, 0.0, 0.0, 0.0], prev=(300.0, 0.0, 0.0, 0.0))
    assert out[0] == -300.0 and acted
    assert env.counters.rate_limit == 1 and env.counters.torque_limit == 0


@pytest.mark.parametrize(("prev", "cmd"), [(-450.0, 150.0), (450.0, -150.0)])
def test_a_command_exactly_at_the_rate_window_edge_passes_unchanged(prev: float, cmd: float
                                                                    ) -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    out, acted = run(env, [cmd, cmd, cmd, cmd], prev=(prev,) * 4)
    assert out.tolist() == [cmd] * 4 and not acted
    assert env.counters.rate_limit == 0 and env.counters.limited_steps == 0


def test_a_command_exactly_at_the_power_limit_passes_unchanged() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    out, acted = run(env, [300.0, -300.0, 300.0, -300.0], ws=(150.0,) * 4,
                     prev=(300.0, -300.0, 300.0, -300.0))
    assert out.tolist() == [300.0, -300.0, 300.0, -300.0] and not acted
    assert env.counters.power_limit == 0


def test_zero_clip_tolerance_counts_no_total_torque_loss_on_the_fast_path() -> None:
    env = SafetyEnvelope(EnvelopeConfig(clip_tol_nm=0.0), TP, PP, DT)
    out, acted = run(env, [10.0, 20.0, 30.0, 40.0], prev=(10.0, 20.0, 30.0, 40.0))
    assert out.tolist() == [10.0, 20.0, 30.0, 40.0]
    assert not acted and env.counters.tt_reduced == 0


def test_counters_have_a_fixed_set_of_fields() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    with pytest.raises(AttributeError):
        env.counters.typo = 1  # type: ignore[attr-defined]


def test_zero_yaw_moment_with_equal_axles_is_not_an_equalisation() -> None:
    """Front and rear differ, left equals right on each axle: ΔM is already 0."""
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    cmd = [200.0, 200.0, 100.0, 100.0]
    out, acted = run(env, cmd, zero_dm=True, prev=cmd)
    assert out.tolist() == cmd and not acted
    assert env.counters.dm_zeroed == 0 and not env.last_zeroed


# ------------------------------------------------------------- the lever, by an oracle
def _windows(env: SafetyEnvelope, ws, prev) -> tuple[list[float], list[float]]:
    lo, hi = [], []
    for w, p in zip(ws, prev, strict=True):
        L = env.wheel_limit(w)
        lo.append(max(-L, p - env.d_wheel))
        hi.append(min(L, p + env.d_wheel))
    return lo, hi


_T = st.floats(-450.0, 450.0)
_W = st.one_of(st.just(0.0), st.floats(-300.0, 300.0))


@settings(max_examples=400, deadline=None, derandomize=True)
@given(cmd=st.lists(_T, min_size=4, max_size=4), prev=st.lists(_T, min_size=4, max_size=4),
       ws=st.lists(_W, min_size=4, max_size=4),
       rate=st.sampled_from([20000.0, 40000.0, 60000.0]),
       dm_rate=st.sampled_from([30000.0, 90000.0, 180000.0]))
def test_the_lever_keeps_the_nearest_yaw_moment_then_the_nearest_total(
        cmd, prev, ws, rate, dm_rate) -> None:
    """Independent of the implementation: with the wheel windows [max(-L, p-d), min(L, p+d)]
    the output's ΔM is the commanded one clipped to the ΔM rate window and then to the range
    the windows allow; its Tt is the commanded one clipped to what that ΔM allows."""
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=rate,
                                        delta_m_rate_nm_per_s=dm_rate), TP, PP, DT)
    prev = [min(max(p, -env.wheel_limit(w)), env.wheel_limit(w)) for p, w in zip(prev, ws,
                                                                                 strict=True)]
    out, _ = run(env, cmd, ws=ws, prev=prev)
    if env.counters.conflicts:
        return   # the windows themselves conflict: covered by the conflict tests
    lo, hi = _windows(env, ws, prev)
    cm = [min(max(c, -TP), TP) for c in cmd]
    dm_c, dm_p = dm(cm), dm(prev)
    dm_lo, dm_hi = dm_p - env.d_dm, dm_p + env.d_dm
    dm_min = (lo[1] + lo[3]) - (hi[0] + hi[2])
    dm_max = (hi[1] + hi[3]) - (lo[0] + lo[2])
    want_dm = min(max(min(max(dm_c, dm_lo), dm_hi), dm_min), dm_max)
    assert dm(out) == pytest.approx(want_dm, abs=1e-6)
    s_lo = max(lo[0] + lo[2], lo[1] + lo[3] - want_dm)
    s_hi = min(hi[0] + hi[2], hi[1] + hi[3] - want_dm)
    want_tt = min(max(sum(cm), 2.0 * s_lo + want_dm), 2.0 * s_hi + want_dm)
    assert float(out.sum()) == pytest.approx(want_tt, abs=1e-6)
    for i in range(4):
        assert lo[i] - 1e-9 <= out[i] <= hi[i] + 1e-9


def test_wheel_windows_win_over_the_delta_m_rate_on_the_negative_side() -> None:
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=10000.0,
                                        delta_m_rate_nm_per_s=10000.0), TP, PP, DT)
    prev = (450.0, -450.0, 450.0, -450.0)   # ΔM -1800; reachable: -1200 only
    out, acted = run(env, prev, ws=(150.0,) * 4, prev=prev)
    assert out.tolist() == [300.0, -300.0, 300.0, -300.0]
    assert env.counters.conflicts == 5 and acted


def test_a_non_finite_previous_output_reads_as_zero() -> None:
    env = SafetyEnvelope(EnvelopeConfig(torque_rate_nm_per_s=10000.0), TP, PP, DT)
    out, _ = run(env, [450.0, -450.0, 0.0, 0.0], prev=(np.nan, np.inf, 0.0, 0.0))
    assert out.tolist() == [100.0, -100.0, 100.0, -100.0]   # 0 ± 100 N·m per cycle
    assert env.counters.bad_prev == 2


def test_a_previous_output_exactly_at_the_peak_is_not_garbage() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    out, acted = run(env, [TP, -TP, TP, -TP], prev=(TP, -TP, TP, -TP))
    assert out.tolist() == [TP, -TP, TP, -TP] and not acted
    assert env.counters.bad_prev == 0


def test_small_positive_peaks_and_rates_are_valid() -> None:
    env = SafetyEnvelope(EnvelopeConfig(), 0.5, 0.5, 0.5)
    assert env.t_peak == 0.5 and env.p_peak == 0.5 and env.dt == 0.5
    cfg = EnvelopeConfig.from_dict({"torque_rate_nm_per_s": 0.5,
                                    "delta_m_rate_nm_per_s": 0.25})
    assert cfg.torque_rate_nm_per_s == 0.5 and cfg.delta_m_rate_nm_per_s == 0.25


def test_initial_state_and_fixed_fields() -> None:
    env = SafetyEnvelope(load_envelope_config(), TP, PP, DT)
    assert env.last_zeroed is False and env.limits.tolist() == [TP] * 4
    with pytest.raises(AttributeError):
        env.cfg.typo = 1  # type: ignore[attr-defined]
