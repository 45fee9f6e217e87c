"""The near-limit pieces of the numpy reference: the grip estimate, the stable-handling
envelope's bounds, the grip-limited demand (continuity) and the QP with envelope rows and
the ΔM move penalty, each against an independent closed form or a direct solve."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.core.config_schema import ConfigError
from controller.core.grip import G_MPS2, GripConfig, GripEstimator
from controller.core.interfaces import PredictionContext, QpStatus
from controller.core.model.bicycle import BicycleModel
from controller.core.mpc.envelope import HandlingConfig, HandlingEnvelope
from controller.core.mpc.qp import LinearizedMpc, QpConfig, envelope_a_dense, envelope_pattern
from controller.core.params import load_vehicle_params
from controller.core.references.grip_demand import GripDemandReferences
from controller.core.references.linear import LinearReferences

P = load_vehicle_params()
TS = 0.05


# ------------------------------------------------------------------ grip estimate
def _linear_state(ay: float, vx: float) -> tuple[float, float, float]:
    """(vy m/s, yaw rate rad/s, δw rad) of a steady turn on linear tyres at ay m/s², Vx m/s:
    both axle slips exactly the linear law (independent of the estimator's code)."""
    L, m = P.wheelbase_m, P.mass_kg
    r = ay / vx
    a_r = -m * P.lf_m / (L * abs(P.cr_axle_n_per_rad)) * ay
    a_f = -m * P.lr_m / (L * abs(P.cf_axle_n_per_rad)) * ay
    vy = vx * a_r + P.lr_m * r
    delta = (vy + P.lf_m * r) / vx - a_f
    return vy, r, delta


def test_linear_tyres_credit_the_grip_shown_times_the_factor() -> None:
    """No saturation (slip exactly linear): μ̂ → clip(k_shown · a, μ_floor, μ_max) with
    a = |ay|/g; at 0.5 g that is 0.575, reached within 2 s of τ = 0.1 s."""
    cfg = GripConfig()
    g = GripEstimator(P, cfg, TS)
    vy, r, d = _linear_state(0.5 * G_MPS2, 20.0)
    for _ in range(40):
        g.update(20.0, vy, r, d, 0.0, 0.5 * G_MPS2)
    assert g.saturation == 0.0
    assert g.mu == pytest.approx(cfg.shown_factor * 0.5, rel=1e-6)
    # a road that has shown little: the floor
    g.reset()
    vy, r, d = _linear_state(0.1 * G_MPS2, 20.0)
    for _ in range(40):
        g.update(20.0, vy, r, d, 0.0, 0.1 * G_MPS2)
    assert g.mu == pytest.approx(cfg.mu_floor, rel=1e-6)


def test_saturated_rear_axle_pulls_the_estimate_to_the_grip_in_use_within_half_a_second() -> None:
    """After a friction drop the rear axle needs 2° more slip than the linear law at the
    0.36 g it still makes: σ = 1 and μ̂ follows a = 0.36 within 0.5 s (τ = 0.1 s: e^−5)."""
    cfg = GripConfig()
    g = GripEstimator(P, cfg, TS)
    vy, r, d = _linear_state(0.6 * G_MPS2, 20.0)
    for _ in range(40):
        g.update(20.0, vy, r, d, 0.0, 0.6 * G_MPS2)
    before = g.mu
    ay = 0.36 * G_MPS2
    vy, r, d = _linear_state(ay, 20.0)
    vy -= 20.0 * math.radians(2.0)            # the rear slides out 2° beyond the linear law
    t = 0.0
    while g.mu > 0.37 and t < 2.0:
        g.update(20.0, vy, r, d, 0.0, ay)
        t += TS
    assert g.saturation == 1.0 and before > 0.6
    assert t <= 0.5
    assert g.mu >= 0.36 - 1e-12               # never below the grip in use


@given(st.floats(0.0, 12.0), st.floats(-0.1, 0.1), st.floats(5.0, 40.0))
def test_estimate_bounded_and_not_below_the_grip_in_use(ay: float, dslip: float,
                                                        vx: float) -> None:
    cfg = GripConfig()
    g = GripEstimator(P, cfg, TS)
    vy, r, d = _linear_state(ay, vx)
    for _ in range(5):
        mu = g.update(vx, vy + vx * dslip, r, d, 0.0, ay)
        assert min(ay / G_MPS2, cfg.mu_max) - 1e-12 <= mu <= cfg.mu_max


def test_non_finite_or_slow_input_holds_the_estimate() -> None:
    g = GripEstimator(P, GripConfig(), TS)
    mu = g.mu
    for bad in (math.nan, math.inf):
        assert g.update(20.0, bad, 0.1, 0.01, 0.0, 3.0) == mu
    assert g.update(2.0, 0.0, 0.1, 0.01, 0.0, 8.0) == mu


@pytest.mark.parametrize("saturated", [False, True])
def test_absurd_finite_acceleration_holds_the_estimate_and_later_steps_update(
        saturated: bool) -> None:
    """ax = 1e200 (finite; ax² overflows) or a grip in use above 3 g is a sensor fault: the
    estimate, the grip shown and the diagnostics are held, and the next plausible inputs
    move the estimate again (with linear or with saturated tyres)."""
    vy, r, d = _linear_state(3.0, 20.0)
    vy += 20.0 * (0.05 if saturated else 0.0)
    g = GripEstimator(P, GripConfig(), TS)
    for _ in range(5):
        g.update(20.0, vy, r, d, 0.0, 3.0)
    held = (g.mu, g.shown, g.saturation, g.grip_used)
    for ax in (1e200, 3.01 * G_MPS2):
        assert g.update(20.0, vy, r, d, ax, 3.0) == held[0]
        assert (g.mu, g.shown, g.saturation, g.grip_used) == held
    mu = [g.update(20.0, vy, r, d, 0.0, 3.0 + 0.5 * k) for k in range(1, 6)]
    assert all(math.isfinite(m) for m in mu) and len(set(mu)) == 5


def test_grip_config_refuses_a_zero_minimum_speed() -> None:
    with pytest.raises(ConfigError, match="v_min_mps"):
        GripConfig.from_dict({"v_min_mps": 0.0})


# ------------------------------------------------------------------ envelope bounds
def test_envelope_bounds_closed_form() -> None:
    """r_max = k_r μ g / Vx; α_max = k_α atan(3 μ Fz_r / |C_r|), Fz_r = m g lf / L."""
    h = HandlingConfig(yaw_margin=1.2, rear_slip_factor=0.7)
    env = HandlingEnvelope(P, h)
    fzr = P.mass_kg * 9.81 * P.lf_m / P.wheelbase_m
    assert env.yaw_rate_max(0.5, 20.0) == pytest.approx(1.2 * 0.5 * 9.81 / 20.0)
    assert env.rear_slip_max(0.35) == pytest.approx(
        0.7 * math.atan(3 * 0.35 * fzr / abs(P.cr_axle_n_per_rad)))
    assert env.yaw_rate_max(0.5, 1.0) == env.yaw_rate_max(0.5, h.v_min_mps)   # floored Vx


# ------------------------------------------------------------------ grip-limited demand
def test_demand_is_the_bicycle_below_the_limit_and_saturates_smoothly() -> None:
    g = GripEstimator(P, GripConfig(), TS)
    g.mu = 0.5
    h = HandlingConfig(fixed_point_share=0.0)
    refs = GripDemandReferences(P, g, h)
    lin = LinearReferences(P)
    vx = 20.0
    r_lim = h.demand_margin * 0.5 * 9.81 / vx
    small = 0.002
    r, _, b = refs.compute(vx, 0.0, 0.0, small, 0.0, 0.0)
    r_lin, _, b_lin = lin.compute(vx, 0.0, 0.0, small, 0.0, 0.0)
    n = h.demand_sharpness
    f = 1.0 / (1.0 + abs(r_lin / r_lim) ** n) ** (1.0 / n)
    assert r == pytest.approx(f * r_lin) and b == pytest.approx(f * b_lin)
    assert f > 0.999
    big, _, _ = refs.compute(vx, 0.0, 0.0, 0.2, 0.0, 0.0)
    assert r_lim * 0.99 < big < r_lim


@settings(max_examples=200)
@given(st.floats(5.0, 40.0), st.floats(-0.3, 0.3), st.floats(-3.0, 3.0), st.floats(0.1, 1.0))
def test_demand_is_continuous_in_every_input(vx: float, delta: float, vy: float,
                                             mu: float) -> None:
    """No value of β, δ, Vx or μ̂ at which the reference jumps: a 1e-7 change of any input
    moves ωrd and βd by at most a bounded multiple of it (Lipschitz on this box). The learned
    part is off (its grid search is not part of this check)."""
    g = GripEstimator(P, GripConfig(), TS)
    refs = GripDemandReferences(P, g, HandlingConfig(fixed_point_share=0.0))
    g.mu = mu
    base = refs.compute(vx, vy, 0.0, delta, 0.0, 0.0)
    eps = 1e-7
    for dv, dd, dy, dm in ((eps, 0, 0, 0), (0, eps, 0, 0), (0, 0, eps, 0), (0, 0, 0, eps)):
        g.mu = mu + dm
        moved = refs.compute(vx + dv, vy + dy, 0.0, delta + dd, 0.0, 0.0)
        assert abs(moved[0] - base[0]) <= 50.0 * eps
        assert abs(moved[2] - base[2]) <= 50.0 * eps


# ------------------------------------------------------------------ QP
def _mpc(env: HandlingEnvelope | None, move: float = 0.0, rate: float = 0.0, jerk: float = 0.0
         ) -> tuple[LinearizedMpc, BicycleModel, PredictionContext]:
    model = BicycleModel(P)
    cfg = QpConfig(delta_rate_weight=move, rate_limit_nm_per_s=rate, delta_accel_weight=jerk,
                   osqp={**QpConfig().osqp, "eps_abs": 1e-9, "eps_rel": 1e-9,
                         "max_iter": 4000})
    return LinearizedMpc(model, cfg, TS, env), model, PredictionContext(ts=TS)


def test_move_penalty_hessian_and_gradient_closed_form() -> None:
    """P = 2(GᵀWG + λI + λ_Δ DᵀD) and q₀ gets −2 λ_Δ z_prev: the solution equals the
    unconstrained minimiser of that quadratic (direct solve) when the box is wide."""
    qp, _, ctx = _mpc(None, move=3.0)
    x0 = np.array([20.0, 0.2, 0.15])
    dm, _, _, _ = qp.solve(x0, ctx, 0.3, 0.0, -1e6, 1e6, 500.0)
    N = qp.N
    D = np.eye(N) - np.eye(N, k=-1)
    W = np.diag(qp.wdiag)
    G = qp.G.astype(float)
    H = 2 * (G.T @ W @ G + qp.cfg.input_reg * np.eye(N) + 3.0 * D.T @ D)
    zbar = qp._zbar
    g = -2 * G.T @ W @ (qp.yd - qp.ybar + G @ zbar)
    g[0] -= 2 * 3.0 * 0.5            # z_prev = 500 N·m / 1000
    z = np.linalg.solve(H, -g)
    assert dm == pytest.approx(z[0] * qp.cfg.u_scale, rel=1e-5, abs=1e-3)


def test_jerk_penalty_hessian_and_gradient_closed_form() -> None:
    """P gets 2 λ₂ D2ᵀD2 (D2 the second difference) and q gets 2 λ₂ D2ᵀc with c = (z_{−2} −
    2z_{−1}, z_{−1}, 0 …), z_{−1} the ΔM applied now and z_{−2} the one applied at the solve
    before: the second solve's answer equals the direct minimiser of that quadratic."""
    qp, _, ctx = _mpc(None, move=0.5, jerk=2.0)
    x0 = np.array([20.0, 0.2, 0.15])
    qp.solve(x0, ctx, 0.3, 0.0, -1e6, 1e6, -300.0)
    dm, _, _, _ = qp.solve(x0, ctx, 0.3, 0.0, -1e6, 1e6, 500.0)
    N = qp.N
    D = np.eye(N) - np.eye(N, k=-1)
    D2 = np.eye(N) - 2.0 * np.eye(N, k=-1) + np.eye(N, k=-2)
    c = np.zeros(N)
    c[0], c[1] = -0.3 - 2.0 * 0.5, 0.5  # z_{−2} − 2 z_{−1}, z_{−1} (kN·m)
    W = np.diag(qp.wdiag)
    G = qp.G.astype(float)
    H = 2 * (G.T @ W @ G + qp.cfg.input_reg * np.eye(N) + 0.5 * D.T @ D + 2.0 * D2.T @ D2)
    g = -2 * G.T @ W @ (qp.yd - qp.ybar + G @ qp._zbar) + 2 * 2.0 * D2.T @ c
    g[0] -= 2 * 0.5 * 0.5            # the move weight's −2 λ_Δ z_{−1}
    z = np.linalg.solve(H, -g)
    assert dm == pytest.approx(z[0] * qp.cfg.u_scale, rel=1e-5, abs=1e-3)
    qp.reset()  # a reset forgets both applied ΔM
    assert qp._dm_prev_z == qp._dm_prev2_z == 0.0


def test_jerk_penalty_leaves_a_ramp_free() -> None:
    """The second difference of a ramp is zero: with the last two applied ΔM on a ramp (200,
    400 N·m) and nothing to track, a heavy jerk weight continues the ramp (≈ 600 N·m) where
    without it ΔM returns to about zero."""
    x0 = np.array([20.0, 0.0, 0.0])
    plans = {}
    for jerk in (0.0, 50.0):
        qp, _, ctx = _mpc(None, jerk=jerk)
        qp.solve(x0, ctx, 0.0, 0.0, -1e6, 1e6, 200.0)
        dm, _, _, _ = qp.solve(x0, ctx, 0.0, 0.0, -1e6, 1e6, 400.0)
        plans[jerk] = dm
    # no yaw demand: without the jerk weight ΔM goes to ~0; with a heavy one it keeps the ramp
    assert abs(plans[0.0]) < 50.0
    assert plans[50.0] == pytest.approx(600.0, rel=0.1)


def test_envelope_rows_hold_the_yaw_rate_bound_with_zero_slack_when_feasible() -> None:
    """A yaw reference far above r_max: without the envelope the QP asks for ΔM that drives
    the predicted ωr past r_max; with it every predicted stage stays within r_max (the
    slack is zero: the box allows it) — checked on the linearised outputs."""
    h = HandlingConfig(yaw_margin=1.0, slack_linear=1e4, slack_quad=1e2)
    env = HandlingEnvelope(P, h)
    x0 = np.array([20.0, 0.0, 0.2])
    r_max = 0.18
    free, _, ctx = _mpc(None)
    free.solve(x0, ctx, 1.0, 0.0, -1800.0, 1800.0, 0.0)
    assert np.max(free.ybar[0::2] + free.G[0::2] @ (free.sol / 1000.0 - free._zbar)) > r_max
    qp, _, ctx = _mpc(env)
    qp.solve(x0, ctx, 1.0, 0.0, -1800.0, 1800.0, 0.0, (r_max, 1.0, 0.0))
    z = qp.sol / 1000.0
    yaw = qp.ybar[0::2] + qp.G[0::2] @ (z - qp._zbar)
    assert np.max(yaw) <= r_max * (1 + 1e-4)
    assert qp.slack[0] == pytest.approx(0.0, abs=1e-5)


def test_envelope_slack_absorbs_an_unreachable_bound() -> None:
    """A bound the box cannot reach (|ωr| ≤ 0.01 rad/s from 0.3 rad/s in 150 ms with
    ±100 N·m): the QP stays solvable; the slack equals the excess the best ΔM leaves."""
    env = HandlingEnvelope(P, HandlingConfig(slack_linear=1e4, slack_quad=1.0))
    qp, _, ctx = _mpc(env)
    x0 = np.array([20.0, 0.0, 0.3])
    dm, status, _, fb = qp.solve(x0, ctx, 0.0, 0.0, -100.0, 100.0, 0.0, (0.01, 1.0, 0.0))
    assert status == QpStatus.SOLVED and not fb and dm == pytest.approx(-100.0, abs=1e-3)
    yaw = qp.ybar[0::2] + qp.G[0::2] @ (qp.sol / 1000.0 - qp._zbar)
    assert qp.slack[0] == pytest.approx(np.max(np.abs(yaw)) / 0.01 - 1.0, rel=1e-3)


@pytest.mark.parametrize("held_nm", [0.0, 150.0])
def test_a_collapsed_box_is_solved_without_osqp_as_osqp_solves_it(held_nm: float) -> None:
    """A box that holds every stage at one ΔM (the model not yet confident: 0 N·m; here also
    150 N·m) leaves only the slacks free: the QP's solution is ΔM = that value and each slack
    the excess of its rows there. Solved without OSQP (no iteration, counted) and equal to
    OSQP's answer on the same data; the yaw slack equals max |ωr_i| / r_max − 1 on the
    linearised outputs."""
    env = HandlingEnvelope(P, HandlingConfig(slack_linear=100.0, slack_quad=100.0))
    x0 = np.array([20.0, 0.05, 0.3])
    answers = []
    for first in (True, False):
        qp, _, ctx = _mpc(env, rate=40_000.0)
        qp.cfg.unconstrained_first = first
        dm, status, iters, fb = qp.solve(x0, ctx, 0.0, 0.0, held_nm, held_nm, held_nm,
                                         (0.1, 0.02, 3.0))
        assert status == QpStatus.SOLVED and not fb and dm == held_nm
        assert (iters == 0) == first and qp.unconstrained_solves == int(first)
        yaw = qp.ybar[0::2] + qp.G[0::2] @ (qp.sol / 1000.0 - qp._zbar)
        answers.append((qp.slack.copy(), np.max(np.abs(yaw)) / 0.1 - 1.0))
    (exact, excess), (osqp_slack, _) = answers
    assert exact[0] == pytest.approx(excess, rel=1e-9) and exact[0] > 0.5
    np.testing.assert_allclose(exact, osqp_slack, atol=1e-6)


def test_a_collapsed_box_that_breaks_a_rate_row_is_left_to_osqp() -> None:
    """Plain shape (no envelope): the rate row of the first stage is anchored to the applied
    ΔM, so a box collapsed far from it is infeasible: no closed form, OSQP decides (and the
    controller falls back), as without the shortcut."""
    qp, _, ctx = _mpc(None, rate=1000.0)
    x0 = np.array([20.0, 0.0, 0.1])
    _, status, _, fb = qp.solve(x0, ctx, 0.0, 0.0, 500.0, 500.0, 0.0)
    assert qp.unconstrained_solves == 0
    assert status == QpStatus.FALLBACK and fb


def test_envelope_pattern_matches_the_dense_rows() -> None:
    """The CSC pattern OSQP is set up with has exactly the structural non-zeros of A."""
    for n in (1, 3, 6):
        _, A = envelope_pattern(n)
        dense = envelope_a_dense(n, np.ones((4 * n, n)))
        assert np.array_equal(A.toarray() != 0, dense != 0)
        assert A.shape == (6 * n + 2, n + 2)


def test_generated_solver_pattern_is_the_reference_pattern() -> None:
    """osqp_gen builds the envelope shape's OSQP problem without the controller package; its
    patterns equal the reference's."""
    from controller.native import osqp_gen
    for n in (1, 3, 10):
        p_ref, a_ref = envelope_pattern(n)
        p_gen, a_gen = osqp_gen.envelope_pattern(n)
        assert (p_ref != p_gen).nnz == 0 and (a_ref != a_gen).nnz == 0
