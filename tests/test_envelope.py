"""Output safety envelope: each limit against hand-computed values, and fuzzed inputs
(any floats, any flags, step sequences) always inside the envelope."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller.core.config_schema import ConfigError
from controller.core.interfaces import ControllerOutputs, QpStatus
from controller.core.params import load_vehicle_params
from controller.runtime.envelope import EnvelopeConfig, SafetyEnvelope, load_envelope_config
from controller.runtime.node import ControllerNode, Fault
from tests.test_controller_node import CODEC, FakePlant, answer, torques

PARAMS = load_vehicle_params()
TP, PP, DT = PARAMS.peak_torque_nm, PARAMS.peak_power_w, 0.01
D_WHEEL, D_DM = 600.0, 1800.0   # N·m per 10 ms cycle with the packaged parameters
TOL = 1e-9


def make(cfg: EnvelopeConfig | None = None) -> SafetyEnvelope:
    return SafetyEnvelope(cfg or load_envelope_config(), TP, PP, DT)


def run(env: SafetyEnvelope, cmd, ws=(0.0,) * 4, zero_dm=False, prev=(0.0,) * 4
        ) -> np.ndarray:
    out = np.zeros(4)
    env.apply(np.array(cmd, dtype=float), np.array(ws, dtype=float), zero_dm,
              np.array(prev, dtype=float), out)
    return out


def dm(t) -> float:
    """ΔM = T2 + T4 − T1 − T3, N·m, summed per axle (exactly 0 for equal axle pairs)."""
    return float((t[1] - t[0]) + (t[3] - t[2]))


# ----------------------------------------------------------------------- hand-computed
def test_packaged_parameters_make_the_limits_conflict_free() -> None:
    env = make()
    assert env.d_wheel == pytest.approx(D_WHEEL) and env.d_dm == pytest.approx(D_DM)
    assert env.conflict_free


def test_a_command_inside_every_limit_passes_bit_for_bit() -> None:
    env = make()
    cmd = [-123.456789, 200.1, 17.25, -0.001]
    prev = [-100.0, 180.0, 10.0, 0.0]
    out = run(env, cmd, ws=(50.0, 51.0, 50.5, 49.0), prev=prev)
    assert out.tolist() == cmd
    c = env.counters
    assert c.limited_steps == c.rate_limit == c.power_limit == c.dm_rate_limit == 0


def test_torque_limit() -> None:
    env = make()
    out = run(env, [600.0, 1e9, -451.0, -600.0], prev=(450.0, 450.0, -450.0, -450.0))
    assert out.tolist() == [450.0, 450.0, -450.0, -450.0]
    assert env.counters.torque_limit == 4 and env.counters.limited_steps == 1


def test_power_limit_at_the_measured_wheel_speed_floored_to_the_frame_resolution() -> None:
    env = make()
    # 45 kW / 150 rad/s = 300 N·m; 45 kW / 123 rad/s = 365.85 → 365.5 (0.5 N·m grid)
    assert env.wheel_limit(150.0) == 300.0 and env.wheel_limit(-150.0) == 300.0
    assert env.wheel_limit(123.0) == 365.5
    assert env.wheel_limit(100.0) == TP and env.wheel_limit(0.0) == TP
    assert env.wheel_limit(5e-324) == TP and env.wheel_limit(1e300) == 0.0
    out = run(env, [400.0] * 4, ws=(150.0, -150.0, 123.0, 0.0), prev=(300.0,) * 4)
    # ΔM was 0 and is kept: the right side loses what FR loses (the left side is fuller)
    assert out.tolist() == [300.0, 300.0, 365.5, 365.5]
    assert env.counters.power_limit == 3


def test_a_limited_wheel_hands_its_torque_to_the_other_wheel_of_its_side() -> None:
    env = make()
    cmd = [200.0, 200.0, 400.0, 400.0]
    out = run(env, cmd, ws=(0.0, 0.0, 150.0, 0.0), prev=cmd)
    assert out.tolist() == [300.0, 200.0, 300.0, 400.0]  # Tt 1200 and ΔM 0 kept
    assert env.counters.tt_reduced == 0


def test_an_invalid_wheel_speed_falls_back_to_the_peak_torque() -> None:
    env = make()
    out = run(env, [440.0] * 4, ws=(math.nan, math.inf, -math.inf, 0.0), prev=(440.0,) * 4)
    assert out.tolist() == [440.0] * 4
    assert env.counters.invalid_speed == 3 and env.counters.limited_steps == 0


def test_per_wheel_rate_limit() -> None:
    env = make()
    out = run(env, [450.0] * 4, prev=(-450.0,) * 4)
    assert out.tolist() == [150.0] * 4   # -450 + 600 N·m per cycle
    assert env.counters.rate_limit == 4


def test_delta_m_rate_limit_keeps_the_total_torque() -> None:
    env = make(EnvelopeConfig(delta_m_rate_nm_per_s=50000.0))  # 500 N·m per cycle
    out = run(env, [-100.0, 300.0, -100.0, 300.0])            # Tt 400, ΔM 800
    # ΔM → 500: sides (Tt ∓ ΔM)/2 = -50 / 450, split evenly from the commands
    assert out.tolist() == [-25.0, 225.0, -25.0, 225.0]
    assert dm(out) == 500.0 and out.sum() == 400.0
    assert env.counters.dm_rate_limit == 1 and env.counters.tt_reduced == 0


def test_full_yaw_moment_reversal_takes_two_cycles() -> None:
    env = make()
    prev = np.array([450.0, -450.0, 450.0, -450.0])  # ΔM = -1800
    cmd = [-450.0, 450.0, -450.0, 450.0]             # ΔM = +1800
    first = run(env, cmd, prev=prev)
    assert first.tolist() == [0.0] * 4              # both rate limits bind at ΔM = 0
    assert run(env, cmd, prev=first).tolist() == cmd


def test_zero_yaw_moment_equalises_each_axle_and_keeps_the_total() -> None:
    env = make()
    cmd = [100.0, 300.0, 50.0, 150.0]
    out = run(env, cmd, zero_dm=True, prev=cmd)
    assert out.tolist() == [200.0, 200.0, 100.0, 100.0]
    assert env.counters.dm_zeroed == 1 and env.counters.limited_steps == 0


def test_zero_yaw_moment_with_an_asymmetric_power_limit_moves_torque_across_axles() -> None:
    env = make()
    out = run(env, [200.0, 200.0, 100.0, 100.0], ws=(0.0, 300.0, 0.0, 0.0), zero_dm=True,
              prev=(150.0, 150.0, 100.0, 100.0))
    assert out.tolist() == [150.0, 150.0, 150.0, 150.0]  # FR ≤ 150 N·m; Tt 600 kept


def test_zero_yaw_moment_releases_a_full_yaw_moment_within_the_rate_limits() -> None:
    env = make()
    prev = [-450.0, 450.0, -450.0, 450.0]
    out = run(env, prev, zero_dm=True, prev=prev)
    assert out.tolist() == [0.0] * 4 and env.counters.conflicts == 0


def test_non_finite_commands_read_as_zero_and_are_counted() -> None:
    env = make()
    out = run(env, [math.nan, math.inf, -math.inf, 1e308], prev=(0.0, 0.0, 0.0, 440.0))
    assert out.tolist() == [0.0, 0.0, 0.0, 450.0]
    assert env.counters.nonfinite_cmd == 3 and env.counters.torque_limit == 1


def test_a_garbage_previous_output_is_sanitised() -> None:
    env = make()
    out = run(env, [450.0] * 4, prev=(math.nan, math.inf, -1e9, 0.0))
    # previous read as 0, +450, -450, 0: the rate window of RL is [-450, 150]; the left
    # side then holds 600 N·m and the right side follows, so no yaw moment appears (ΔM is
    # kept before Tt)
    assert out.tolist() == [450.0, 300.0, 150.0, 300.0]
    assert env.counters.bad_prev == 3 and env.counters.tt_reduced == 1


def test_when_the_parameters_conflict_zero_yaw_moment_and_motor_limits_win() -> None:
    env = make(EnvelopeConfig(torque_rate_nm_per_s=10000.0, delta_m_rate_nm_per_s=10000.0))
    assert not env.conflict_free
    prev = [-450.0, 450.0, -450.0, 450.0]
    out = run(env, prev, zero_dm=True, prev=prev)
    assert out[0] == out[1] and out[2] == out[3] and env.counters.conflicts > 0


def test_config_validation() -> None:
    with pytest.raises(ConfigError):
        EnvelopeConfig.from_dict({"torque_rate": 1.0})
    with pytest.raises(ValueError):
        EnvelopeConfig.from_dict({"torque_rate_nm_per_s": -1.0})
    with pytest.raises(ValueError):
        EnvelopeConfig.from_dict({"delta_m_rate_nm_per_s": math.nan})


# ------------------------------------------------------------------------- fuzzed
ANY = st.floats(allow_nan=True, allow_infinity=True, width=64)
WHEELS = st.lists(ANY, min_size=4, max_size=4)
# Mostly-plausible values too, so the interesting (partly binding) cases are well covered.
TORQUE = st.one_of(ANY, st.floats(-700.0, 700.0))
SPEED = st.one_of(ANY, st.floats(-400.0, 400.0))
STEP = st.tuples(st.lists(TORQUE, min_size=4, max_size=4),
                 st.lists(SPEED, min_size=4, max_size=4), st.booleans())


def _limit(w: float) -> float:
    """Independent oracle of the motor limit (without the 0.5 N·m floor), N·m."""
    if not math.isfinite(w) or w == 0.0:
        return TP
    return min(TP, PP / abs(w))


def _sanitised(prev: list[float]) -> list[float]:
    return [0.0 if not math.isfinite(p) else min(max(p, -TP), TP) for p in prev]


def check_envelope(out: np.ndarray, ws: list[float], zero_dm: bool, prev: list[float]
                   ) -> None:
    """Every limit holds for one step (prev: the previous output as given)."""
    p = _sanitised(prev)
    assert np.all(np.isfinite(out))
    for i in range(4):
        assert abs(out[i]) <= _limit(ws[i]) + TOL, (i, out, ws)
        assert abs(out[i] - p[i]) <= D_WHEEL + 1e-6, (i, out, p)
    assert abs(dm(out) - dm(p)) <= D_DM + 1e-6
    if zero_dm:
        assert out[0] == out[1] and out[2] == out[3] and dm(out) == 0.0


@settings(max_examples=1500, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(cmd=st.lists(TORQUE, min_size=4, max_size=4), ws=st.lists(SPEED, min_size=4,
                                                                  max_size=4),
       prev=WHEELS, zero_dm=st.booleans())
def test_fuzzed_single_steps_always_hold_the_envelope(cmd, ws, prev, zero_dm) -> None:
    env = make()
    out = np.zeros(4)
    env.apply(np.array(cmd), np.array(ws), zero_dm, np.array(prev), out)
    check_envelope(out, ws, zero_dm, prev)
    assert env.counters.conflicts == 0


@settings(max_examples=300, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(steps=st.lists(STEP, min_size=1, max_size=40), start=WHEELS)
def test_fuzzed_sequences_respect_the_rate_limits_step_to_step(steps, start) -> None:
    env = make()
    prev = np.array(start)
    out = np.zeros(4)
    for cmd, ws, zero_dm in steps:
        env.apply(np.array(cmd), np.array(ws), zero_dm, prev, out)
        check_envelope(out, ws, zero_dm, prev.tolist())
        prev = out.copy()
    assert env.counters.conflicts == 0


@settings(max_examples=300, deadline=None, derandomize=True)
@given(cmd=st.lists(st.floats(-300.0, 300.0), min_size=4, max_size=4),
       delta=st.lists(st.floats(-299.0, 299.0), min_size=4, max_size=4))
def test_fuzzed_commands_inside_the_envelope_are_untouched(cmd, delta) -> None:
    env = make()
    prev = [c - d for c, d in zip(cmd, delta, strict=True)]
    prev = [min(max(p, -TP), TP) for p in prev]
    out = run(env, cmd, ws=(100.0,) * 4, prev=prev)
    if abs(dm(cmd) - dm(prev)) <= D_DM:
        assert out.tolist() == cmd


# --------------------------------------------------------------------- in the node
class GarbageController:
    """Answers with whatever torques it is told to (NaN, huge, bang-bang)."""

    name, ts = "garbage", 0.01

    def __init__(self, seq: list[list[float]]) -> None:
        self.seq, self.k, self.out = seq, 0, ControllerOutputs()

    def _next(self, _inputs) -> ControllerOutputs:
        self.out.torques[:] = self.seq[self.k % len(self.seq)]
        self.out.qp_status = int(QpStatus.NOT_RUN)
        self.k += 1
        return self.out

    step = allocate_only = _next

    def reset(self) -> None:
        self.k = 0


def test_node_applies_the_envelope_to_every_answer_and_flags_clipping() -> None:
    seq = [[1e9, -1e9, math.nan, 450.0], [-450.0, 450.0, -450.0, 450.0],
           [450.0, -450.0, 450.0, -450.0], [math.inf, 0.0, 0.0, -math.inf]]
    node = ControllerNode(GarbageController(seq), PARAMS)
    plant = FakePlant()
    prev = np.zeros(4)
    flagged = 0
    for _ in range(40):
        frames = answer(node, plant.burst())
        t = torques(frames)
        assert np.all(np.abs(t) <= TP)
        # on the wire: the envelope's rate limit plus at most one 0.5 N·m LSB of rounding
        assert np.all(np.abs(t - prev) <= D_WHEEL + 0.5)
        assert abs(dm(t) - dm(prev)) <= D_DM + 2.0
        flagged += bool(int(frames["CTRL_STATUS"].values["FAULT_BITS"])
                        & (1 << Fault.TORQUE_CLIPPED))
        prev = t
    assert flagged >= 30 and node.envelope.counters.limited_steps == flagged


def test_node_zeroes_the_yaw_moment_when_stability_is_disabled() -> None:
    node = ControllerNode(GarbageController([[-100.0, 300.0, -50.0, 250.0]]), PARAMS)
    plant = FakePlant()
    orig = plant.burst

    def burst_disabled(**kw):
        frames = orig(**kw)
        return [CODEC.message("DRIVER_INPUTS", {"SWA": 0.0, "ACCEL_PEDAL": 30.0,
                                                "BRAKE_PEDAL": 0.0, "STAB_ENABLE": 0},
                              plant.cycle - 1) if f.arbitration_id == 0x100 else f
                for f in frames]

    for _ in range(10):
        frames = answer(node, burst_disabled())
    t = torques(frames)
    assert t[0] == t[1] == 100.0 and t[2] == t[3] == 100.0
    assert frames["CTRL_REFS"].values["DELTA_M"] == 0.0
