"""The sideslip guard (controller/core/references/sideslip_guard.py) against the planar-motion
identity it is built on: β̇ = ay/Vx − ωr (β = Vy/Vx, Vx constant)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.references.sideslip_guard import SideslipGuard


class _Fixed:
    """Inner generator returning a fixed reference (ωrd rad/s, Vyd m/s, βd rad)."""

    def __init__(self, r: float) -> None:
        self.r = r
        self.not_converged = 7
        self.resets = 0

    def compute(self, vx, vy, yaw_rate, delta_w, total_torque, ay_meas):
        return self.r, 0.1, 0.1 / vx

    def reset(self) -> None:
        self.resets += 1


def test_inactive_below_the_threshold_and_delegates_counters() -> None:
    g = SideslipGuard(_Fixed(0.4), beta_rad=math.radians(2.0), gain_per_s=5.0, v_min=3.0)
    vx = 20.0
    vy = math.tan(math.radians(1.9)) * vx
    assert g.compute(vx, vy, 0.3, 0.05, 0.0, 3.0)[0] == 0.4
    assert g.active_calls == 0
    assert g.not_converged == 7          # counters of the wrapped generator pass through
    g.reset()
    assert g.inner.resets == 1


def test_limited_yaw_reference_makes_the_excess_sideslip_decay() -> None:
    # Oversteer in a left turn: β = −4° (threshold 2°), ay = +3 m/s², Vx = 20 m/s, the inner
    # reference asks for 0.4 rad/s. Tracking the guarded ωrd, the identity gives
    # β̇ = ay/Vx − ωrd = k·(|β| − β_g) > 0: the sideslip shrinks at the demanded rate.
    k, vx, ay = 5.0, 20.0, 3.0
    beta_g, beta = math.radians(2.0), math.radians(-4.0)
    g = SideslipGuard(_Fixed(0.4), beta_rad=beta_g, gain_per_s=k, v_min=3.0)
    r_d, vy_d, b_d = g.compute(vx, beta * vx, 0.45, 0.05, 0.0, ay)
    beta_dot = ay / vx - r_d
    assert math.isclose(beta_dot, k * (abs(beta) - beta_g), rel_tol=1e-12)
    assert r_d < 0.4 and g.active_calls == 1
    assert (vy_d, b_d) == (0.1, 0.1 / vx)     # only the yaw reference is limited
    # mirror image (right turn, β = +4°, inner −0.4 rad/s): the same decay from the other side
    g = SideslipGuard(_Fixed(-0.4), beta_rad=beta_g, gain_per_s=k, v_min=3.0)
    r_m, _, _ = g.compute(vx, -beta * vx, -0.45, -0.05, 0.0, -ay)
    assert math.isclose(-ay / vx - r_m, -k * (abs(beta) - beta_g), rel_tol=1e-12)


def test_a_reference_that_already_shrinks_beta_is_kept() -> None:
    # β = −4°, ay/Vx = 0.15 rad/s, demanded k·excess = 5 × 2° ≈ 0.175 rad/s → bound
    # ωrd ≤ −0.025 rad/s. An inner reference of −0.1 rad/s already satisfies it: kept.
    g = SideslipGuard(_Fixed(-0.1), beta_rad=math.radians(2.0), gain_per_s=5.0, v_min=3.0)
    r_d, _, _ = g.compute(20.0, math.radians(-4.0) * 20.0, 0.1, 0.05, 0.0, 3.0)
    assert r_d == -0.1 and g.active_calls == 0


def test_non_finite_or_slow_inputs_pass_the_inner_reference_through() -> None:
    g = SideslipGuard(_Fixed(0.4), beta_rad=0.01, gain_per_s=5.0, v_min=3.0)
    assert g.compute(2.0, -1.0, 0.0, 0.0, 0.0, 3.0)[0] == 0.4
    assert g.compute(20.0, math.nan, 0.0, 0.0, 0.0, 3.0)[0] == 0.4
    assert g.compute(20.0, -2.0, 0.0, 0.0, 0.0, math.nan)[0] == 0.4


def test_look_ahead_engages_before_the_threshold_on_beta_plus_t_beta_dot() -> None:
    # β = 1.5° is below the 2° threshold, but it grows at β̇ = ay/Vx − ωr = 3/20 − 0.10
    # = 0.05 rad/s; with T = 0.4 s the guard judges β_T = 0.0261799 + 0.4 × 0.05 = 0.0461799
    # rad (2.646°), 0.0112734 rad above the threshold: ωrd ≥ 0.15 + 5 × 0.0112734 = 0.2063668.
    vx, ay, wr, k, t = 20.0, 3.0, 0.10, 5.0, 0.4
    beta_g = 2.0 * math.pi / 180.0            # 0.0349066 rad
    beta = 1.5 * math.pi / 180.0              # 0.0261799 rad
    beta_t = beta + t * 0.05
    expected = 0.15 + k * (beta_t - beta_g)
    assert math.isclose(expected, 0.2063668, rel_tol=1e-6)      # the figures above
    g = SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0, lead_s=t)
    r_d, vy_d, b_d = g.compute(vx, beta * vx, wr, 0.05, 0.0, ay)
    assert math.isclose(r_d, expected, rel_tol=1e-12)
    assert g.active_calls == 1 and (vy_d, b_d) == (0.1, 0.1 / vx)
    # tracking it, the predicted sideslip decays at k times its excess (the identity)
    assert math.isclose(ay / vx - r_d, -k * (beta_t - beta_g), rel_tol=1e-9)
    # mirror image (β = −1.5° growing at −0.05 rad/s, ay = −3): the bound from the other side
    g = SideslipGuard(_Fixed(-0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0, lead_s=t)
    assert math.isclose(g.compute(vx, -beta * vx, -wr, -0.05, 0.0, -ay)[0], -expected,
                        rel_tol=1e-12)
    assert g.active_calls == 1
    # T = 0 (the default): the same inputs are below the threshold, the guard does not act
    for g in (SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0),
              SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0,
                            lead_s=0.0)):
        assert g.compute(vx, beta * vx, wr, 0.05, 0.0, ay)[0] == 0.1
        assert g.active_calls == 0
    # a non-finite measured yaw rate: no look-ahead, β alone (below the threshold)
    g = SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0, lead_s=t)
    assert g.compute(vx, beta * vx, math.nan, 0.05, 0.0, ay)[0] == 0.1
    assert g.active_calls == 0


def test_look_ahead_lets_go_while_beta_is_already_shrinking() -> None:
    # β = 2.5°, 0.5° above the threshold, shrinking at β̇ = 3/20 − 0.20 = −0.05 rad/s:
    # β_T = 0.0436332 − 0.4 × 0.05 = 0.0236332 rad (1.354°) < 2°, so the guard with T = 0.4 s
    # keeps the inner reference, while on β alone (T = 0) it raises ωrd to
    # 0.15 + 5 × 0.0087266 = 0.1936332.
    vx, ay, wr, k = 20.0, 3.0, 0.20, 5.0
    beta_g, beta = 2.0 * math.pi / 180.0, 2.5 * math.pi / 180.0
    lead = SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0, lead_s=0.4)
    assert lead.compute(vx, beta * vx, wr, 0.05, 0.0, ay)[0] == 0.1
    assert lead.active_calls == 0
    plain = SideslipGuard(_Fixed(0.1), beta_rad=beta_g, gain_per_s=k, v_min=3.0)
    r_d = plain.compute(vx, beta * vx, wr, 0.05, 0.0, ay)[0]
    assert math.isclose(r_d, 0.15 + k * (0.5 * math.pi / 180.0), rel_tol=1e-12)
    assert math.isclose(r_d, 0.1936332, rel_tol=1e-6) and plain.active_calls == 1


def test_config_wraps_every_kind_and_the_guard_acts_in_closed_loop(tmp_path) -> None:
    # [references] guard_gain_per_s > 0 wraps the configured generator; in a sine with dwell
    # at μ 1 (top amplitude) the guarded controller changes its yaw reference on some MPC
    # steps, and the unguarded default never does (no wrapper at all).
    from controller.core.grip import GripConfig, GripEstimator
    from controller.core.model.rhonn import RhonnConfig, RhonnModel
    from controller.core.mpc.envelope import HandlingConfig
    from controller.core.params import load_vehicle_params
    from controller.core.references.algorithm1 import RhonnRefConfig
    from controller.core.references.factory import REFERENCE_KINDS, make_rhonn_references
    from harness.paper.benchmark import controller_config_text
    from harness.run.inprocess_loop import run_in_process

    p = load_vehicle_params()
    model = RhonnModel(p, RhonnConfig(), 0.05)
    grip = GripEstimator(p, GripConfig(), 0.05)
    for kind in REFERENCE_KINDS:
        ref = make_rhonn_references(model, p, RhonnRefConfig(kind=kind, guard_gain_per_s=5.0),
                                    grip, HandlingConfig())
        assert isinstance(ref, SideslipGuard)
    assert not isinstance(make_rhonn_references(model, p, RhonnRefConfig()), SideslipGuard)

    runs = {}
    # (the guard is off by default: "off" sets its gain to 0 explicitly all the same)
    for name, refs in (("off", {"guard_gain_per_s": 0.0}), ("on", {"guard_gain_per_s": 5.0})):
        cfg = tmp_path / f"{name}.toml"
        cfg.write_text(controller_config_text(1, refs))
        runs[name] = run_in_process("sine-with-dwell", "nmpc-rhonn", mu=1.0, seed=1,
                                    config=str(cfg), amplitude_deg=270.0, direction="left")
    differ = runs["on"].yaw_rate_ref[:400] != runs["off"].yaw_rate_ref[:400]
    assert differ.any()
    # up to the first guarded step both runs are the same closed loop
    first = int(np.argmax(differ))
    assert first > 100
    assert np.array_equal(runs["on"].delta_m[:first], runs["off"].delta_m[:first])


def test_grip_scaled_threshold_follows_the_ay_envelope_between_its_bounds() -> None:
    """θ = clip(k · envelope(|ay|)/g, θ0, θmax): on 0.2 g it stays θ0, on 0.35 g it is
    k·0.35 (rad), on 0.9 g it is capped; the blend thresholds scale by the same θ/θ0."""
    from controller.core.references.algorithm1 import RhonnRefConfig
    from controller.core.references.intent import grip_scale

    th0, k, th_max = math.radians(3.0), math.radians(14.0), math.radians(5.0)
    cfg = RhonnRefConfig(guard_beta_rad=th0, grip_beta_per_g=k, grip_beta_max=th_max)
    assert grip_scale(cfg, 0.2 * 9.81) == 1.0
    assert grip_scale(cfg, 0.35 * 9.81) * th0 == pytest.approx(k * 0.35)
    assert grip_scale(cfg, 0.9 * 9.81) * th0 == pytest.approx(th_max)
    assert grip_scale(RhonnRefConfig(guard_beta_rad=th0), 9.0) == 1.0    # off

    # The guard, oversteer in a left turn (β = −4°, ωrd 0.5 rad/s): with ay 3.43 m/s²
    # (0.35 g: θ = 4.9°) β is inside, with 0.2 g (θ = 3°) the guard lowers ωrd.
    vx = 20.0
    vy = -math.tan(math.radians(4.0)) * vx
    for ay, acts in ((0.35 * 9.81, False), (0.2 * 9.81, True)):
        g = SideslipGuard(_Fixed(0.5), beta_rad=th0, gain_per_s=5.0, v_min=3.0,
                          beta_per_g=k, beta_max=th_max, ay_decay=math.exp(-0.05 / 3.0))
        g.compute(vx, vy, 0.5, 0.05, 0.0, ay)
        assert (g.active_calls == 1) is acts
