"""The learned ΔM effectiveness θ (controller/core/learning/input_gain.py, [rhonn] dm_gain_*).

The reference is least squares on synthetic data with a known θ: the joint filter must find
it where ΔM is a feedback of the state (the regressor of θ correlated with φ), where a
regression on ΔM alone is biased.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from controller.core.config_schema import ConfigError
from controller.core.interfaces import PredictionContext
from controller.core.learning.ekf import EkfConfig
from controller.core.learning.input_gain import YawGainFilter
from controller.core.model.rhonn import N_PHI, RhonnConfig, RhonnModel
from controller.core.params import load_vehicle_params

EKF = EkfConfig(p0=10.0, q=1e-5, r=(1e-4, 1e-4, 1e-5))


def closed_loop_data(theta: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray,
                                                               np.ndarray]:
    """φ (n, 15), u (n,) rad/s and the yaw increment y (n,) rad/s = w·φ + θ·u + noise, with
    u a feedback of the state (−0.5 × the state part) plus a small independent share."""
    rng = np.random.default_rng(seed)
    w_true = rng.normal(0.0, 0.02, N_PHI)
    phi = np.tanh(rng.normal(0.0, 0.6, (n, N_PHI)))
    state_part = phi @ w_true
    u = -0.5 * state_part + rng.normal(0.0, 0.002, n)
    y = state_part + theta * u + rng.normal(0.0, 0.001, n)
    return phi, u, y


@pytest.mark.parametrize("form", ["standard", "ud"])
@pytest.mark.parametrize("theta_true", [0.64, 1.0, 1.3])
def test_the_joint_filter_finds_the_effectiveness_where_delta_m_is_a_state_feedback(
        form: str, theta_true: float) -> None:
    phi, u, y = closed_loop_data(theta_true, 4000, seed=3)
    g = YawGainFilter(N_PHI, replace(EKF, form=form), np.zeros(N_PHI), 0.1, 0.4, 2.5)
    for k in range(phi.shape[0]):
        pred = float(g.w_row @ phi[k]) + g.theta * u[k]
        assert g.update(phi[k], float(u[k]), float(y[k] - pred))
    # the reference: least squares on [φ, u]
    coef = np.linalg.lstsq(np.column_stack([phi, u]), y, rcond=None)[0]
    assert abs(coef[-1] - theta_true) < 0.05
    assert abs(g.theta - theta_true) < 0.05
    # a regression on u alone is what the joint filter avoids: biased by the feedback
    alone = float(u @ y / (u @ u))
    assert abs(alone - theta_true) > 0.5


def test_theta_stays_in_its_bounds_and_reset_returns_to_the_nominal_gain() -> None:
    phi, u, y = closed_loop_data(5.0, 600, seed=1)
    g = YawGainFilter(N_PHI, EKF, np.zeros(N_PHI), 0.1, 0.4, 2.5)
    for k in range(phi.shape[0]):
        g.update(phi[k], float(u[k]), float(y[k] - g.w_row @ phi[k] - g.theta * u[k]))
        assert 0.4 <= g.theta <= 2.5
    assert g.theta == 2.5
    g.reset()
    assert g.theta == 1.0
    assert g.filter.P[0, N_PHI, N_PHI] == pytest.approx(0.1)
    assert not np.any(g.filter.P[0, N_PHI, :N_PHI])


def test_a_non_finite_input_leaves_the_estimate() -> None:
    g = YawGainFilter(N_PHI, EKF, np.zeros(N_PHI), 0.1, 0.4, 2.5)
    before = g.get_state()
    assert not g.update(np.zeros(N_PHI), float("nan"), 0.01)
    after = g.get_state()
    assert np.array_equal(before["W"], after["W"]) and np.array_equal(before["P"], after["P"])


def _model(dm_gain_p0: float) -> RhonnModel:
    return RhonnModel(load_vehicle_params(), RhonnConfig(dm_gain_p0=dm_gain_p0,
                                                         dm_dead_time_s=0.02), ts=0.05)


def test_the_model_predicts_with_the_learned_gain_and_the_mpc_reads_it() -> None:
    """A car whose ΔM turns it 0.7 × as hard as the nominal gain says: the model's θ goes
    towards 0.7 and its ΔM sensitivities (b, b_prev) follow."""
    m = _model(0.1)
    ref = _model(0.0)
    ctx = PredictionContext(delta_w=0.02, ts=0.05)
    rng = np.random.default_rng(7)
    x = np.array([20.0, 0.0, 0.0])
    out = np.zeros(3)
    dm_prev = 0.0
    for _ in range(1500):
        dm = float(rng.normal(0.0, 600.0))
        ctx.delta_m_prev = dm_prev
        m.record(x, dm, ctx, out)
        # the "car": nominal model's yaw increment at 0.7 × the ΔM part
        u = ref.kd_now * dm + ref.kd_prev * dm_prev
        x = np.array([20.0, 0.0, 0.98 * x[2] + 0.7 * u])
        m.observe(x, True)
        dm_prev = dm
    assert m.theta == pytest.approx(0.7, abs=0.05)
    a, b = np.zeros((3, 3)), np.zeros(3)
    m.linearize(x, 0.0, ctx, a, b)
    assert b[2] == pytest.approx(m.theta * ref.kd_now)
    assert m.b_prev[2] == pytest.approx(m.theta * ref.kd_prev)
    state = m.get_state()
    fresh = _model(0.1)
    fresh.set_state(state)
    assert fresh.theta == m.theta and fresh.b_prev[2] == m.b_prev[2]
    m.reset()
    assert m.theta == 1.0 and m.b_prev[2] == ref.b_prev[2]


def test_off_by_default_and_bad_values_are_refused() -> None:
    assert RhonnConfig().dm_gain_p0 == 0.0
    assert _model(0.0).dm_gain is None
    with pytest.raises(ConfigError, match="dm_gain_p0"):
        RhonnConfig.from_dict({"dm_gain_p0": -1.0})
    with pytest.raises(ConfigError, match="dm_gain_min"):
        RhonnConfig.from_dict({"dm_gain_p0": 0.1, "dm_gain_min": 1.2})
