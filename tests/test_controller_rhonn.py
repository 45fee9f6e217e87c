"""RHONN structure, Jacobians and EKF identification (paper eq. 5–12, 17, appendix)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs, PredictionContext
from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.model.rhonn import (
    N_PHI,
    PHI_SUBSETS,
    RhonnConfig,
    RhonnEstimator,
    RhonnModel,
    phi_batch,
)
from controller.core.params import load_vehicle_params

P = load_vehicle_params()


def _model(form: str = "increment", seed: int = 0) -> RhonnModel:
    m = RhonnModel(P, RhonnConfig(form=form), ts=0.05)
    m.W[:] = np.random.default_rng(seed).normal(0.0, 0.3, size=(3, N_PHI))
    return m


def test_phi_is_the_15_products_of_distinct_subsets_in_paper_order() -> None:
    subsets = [s for k in (1, 2, 3, 4) for s in itertools.combinations(range(4), k)]
    assert list(PHI_SUBSETS) == subsets          # 4 singles, 6 pairs, 4 triples, 1 quad
    m = _model()
    x, dw = np.array([17.0, -0.8, 0.31]), 0.07
    xi = [np.tanh(x[0] / 30), np.tanh(x[1] / 3), np.tanh(x[2] / 0.6), np.tanh(dw / 0.15)]
    expected = [float(np.prod([xi[j] for j in s])) for s in subsets]
    np.testing.assert_allclose(m.phi(x, dw), expected, rtol=1e-14)


@pytest.mark.parametrize("form", ["increment", "literal"])
def test_analytic_jacobians_match_finite_differences(form: str) -> None:
    m = _model(form)
    ctx = PredictionContext(delta_w=0.05, total_torque=300.0, ts=0.05)
    x, dm = np.array([15.0, 0.4, -0.2]), 250.0
    a, b = np.zeros((3, 3)), np.zeros(3)
    m.linearize(x, dm, ctx, a, b)
    f0, f1 = np.zeros(3), np.zeros(3)
    h = 1e-6
    for j in range(3):
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        m.predict(xp, dm, ctx, f0)
        m.predict(xm, dm, ctx, f1)
        np.testing.assert_allclose(a[:, j], (f0 - f1) / (2 * h), rtol=1e-6, atol=1e-8)
    m.predict(x, dm + 1.0, ctx, f0)
    m.predict(x, dm - 1.0, ctx, f1)
    np.testing.assert_allclose(b, (f0 - f1) / 2.0, rtol=1e-8, atol=1e-12)
    # Known ΔM part (eq. 17 × Ts): Ts·wB/(2 Iz r) per N·m.
    assert b[2] == pytest.approx(0.05 * P.track_m / (2 * P.yaw_inertia_kgm2 * P.wheel_radius_m))


def test_bilinear_collapse_reproduces_w_phi() -> None:
    m = _model(seed=5)
    vx, dw = 21.0, 0.03
    c = m.bilinear_coefficients(vx, dw).copy()
    for vy, r in [(0.0, 0.0), (0.7, -0.2), (-1.5, 0.4)]:
        a, b = m.xi(1, vy), m.xi(2, r)
        direct = m.W @ m.phi(np.array([vx, vy, r]), dw)
        np.testing.assert_allclose(c[:, 0] + c[:, 1] * a + c[:, 2] * b + c[:, 3] * a * b,
                                   direct, rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------- identification
W_TRUE = np.zeros((3, N_PHI))
W_TRUE[0, [0, 7]] = [-0.02, 0.05]                 # drag-like, Vy·ωr coupling
W_TRUE[1, [1, 2, 3, 5, 8]] = [-0.25, 0.1, 0.3, -0.4, 0.05]
W_TRUE[2, [1, 2, 3, 6, 9, 12]] = [0.04, -0.2, 0.2, 0.15, -0.03, 0.05]
ID_STEPS = 3000


def _synthetic_run(model: RhonnModel, steps: int, noise: float, seed: int) -> np.ndarray:
    """Identify the synthetic increment-form system χ⁺ = x + known + W_TRUE φ(x, u).

    Returns the per-step (truth, one-step prediction) pairs, shape (steps, 2, 3)."""
    rng = np.random.default_rng(seed)
    truth = RhonnModel(P, RhonnConfig(form="increment"), ts=0.05)
    truth.W[:] = W_TRUE
    x = np.array([15.0, 0.0, 0.0])
    ctx = PredictionContext(ts=0.05)
    pred, nxt = np.full(3, np.nan), np.zeros(3)
    log = np.zeros((steps, 2, 3))
    for k in range(steps):
        meas = x + rng.normal(0.0, noise, 3) * np.array([1.0, 1.0, 0.1])
        model.observe(meas, True)
        log[k, 0], log[k, 1] = x, pred
        # Persistent excitation: steering and drive torque, Vx kept within 5–35 m/s.
        ctx.delta_w = 0.1 * np.sin(0.031 * k) + 0.05 * rng.normal()
        ctx.total_torque = 1500.0 * np.sin(0.011 * k) + 1500.0 * (20.0 - x[0]) / 15.0
        dm = 800.0 * rng.normal()
        model.record(meas, dm, ctx, pred)
        truth.predict(x, dm, ctx, nxt)
        x = nxt.copy()
    return log


def test_ekf_identifies_known_weights_and_one_step_rmse_below_1pct() -> None:
    cfg = RhonnConfig(form="increment", ekf=EkfConfig(p0=10.0, q=0.0, r=(1e-4, 1e-4, 1e-5)))
    m = RhonnModel(P, cfg, ts=0.05)
    log = _synthetic_run(m, ID_STEPS, noise=0.0, seed=1)
    # Weights converge to the true ones.
    np.testing.assert_allclose(m.W, W_TRUE, atol=2e-3)
    # One-step RMSE over the last 500 steps < 1 % of each signal's RMS.
    tail = log[-500:]
    rmse = np.sqrt(np.mean((tail[:, 1] - tail[:, 0]) ** 2, axis=0))
    rms = np.sqrt(np.mean(tail[:, 0] ** 2, axis=0))
    assert np.all(rmse < 0.01 * rms), (rmse, rms)
    # Already at 1000 steps (50 s at 20 Hz) the error is below 1 %.
    mid = log[1000:1500]
    rmse_mid = np.sqrt(np.mean((mid[:, 1] - mid[:, 0]) ** 2, axis=0))
    assert np.all(rmse_mid < 0.01 * np.sqrt(np.mean(mid[:, 0] ** 2, axis=0)))


def test_ekf_with_measurement_noise_predicts_at_the_noise_floor() -> None:
    """With noisy measurements (σ = 0.01 m/s, 0.001 rad/s) the one-step error vs the truth
    stays within 1.5 σ: the series-parallel predictor starts from the noisy x, so σ is the
    floor; weights are biased by noise on the regressors (errors in variables)."""
    m = RhonnModel(P, RhonnConfig(form="increment", ekf=EkfConfig(
        p0=10.0, q=0.0, r=(1e-4, 1e-4, 1e-6))), ts=0.05)
    log = _synthetic_run(m, ID_STEPS, noise=0.01, seed=2)
    tail = log[-500:]
    rmse = np.sqrt(np.mean((tail[:, 1] - tail[:, 0]) ** 2, axis=0))
    assert np.all(rmse < 1.5 * np.array([0.01, 0.01, 0.001])), rmse


def test_p_stays_symmetric_positive_definite_over_1e5_noisy_steps() -> None:
    rng = np.random.default_rng(7)
    ekf = BatchedEkf(3, N_PHI, EkfConfig(p0=10.0, q=1e-5, r=(1e-4, 1e-4, 1e-5),
                                         eig_check_every=0))
    # Regressors like the vehicle's: ξ in (−1, 1), strongly correlated products.
    n = 100_000
    scale = (np.arange(n) % 7)[:, None]
    xi = np.tanh(np.array([0.6, 0.1, 0.1, 0.1]) + 0.3 * rng.normal(size=(n, 4)) * scale)
    H = phi_batch(xi)
    E = rng.normal(0.0, 0.01, size=(n, 3))
    for k in range(n):
        ekf.update(H[k], E[k])
    for i in range(3):
        assert np.array_equal(ekf.P[i], ekf.P[i].T)              # exactly symmetric
        assert np.linalg.eigvalsh(ekf.P[i]).min() > 0.0
        assert np.trace(ekf.P[i]) <= ekf.cfg.trace_max
    assert ekf.counters.updates == 100_000
    assert np.all(np.isfinite(ekf.W))


def test_guards_count_rejections_resets_clips_and_freezes() -> None:
    ekf = BatchedEkf(3, N_PHI, EkfConfig(p0=1.0, q=1.0, trace_max=40.0, w_max=0.5))
    h = np.full(N_PHI, 0.01)
    w_before = ekf.W.copy()
    assert not ekf.update(h, np.array([np.nan, 0.0, 0.0]))
    assert not ekf.update(np.full(N_PHI, np.inf), np.zeros(3))
    assert not ekf.update(h, np.zeros(3), learn=False)
    assert ekf.counters.rejected == 2 and ekf.counters.frozen == 1
    assert np.array_equal(ekf.W, w_before)
    for _ in range(10):   # q = 1 per step: the trace passes 40 quickly → counted resets
        ekf.update(h, np.full(3, 100.0))
    assert ekf.counters.trace_resets > 0
    assert ekf.counters.weight_clips > 0 and np.abs(ekf.W).max() <= 0.5


def test_learning_frozen_while_sensors_invalid() -> None:
    est = RhonnEstimator(P)
    inp = ControllerInputs(vx=18.0, vy=0.1, yaw_rate=0.05, swa_rad=0.2)
    tq = np.array([10.0, 20.0, 10.0, 20.0])
    for _ in range(5):
        est.step(inp, tq, 0.05)
    w = est.model.W.copy()
    inp.sensors_valid = False
    inp.vy = 3.0
    for _ in range(5):
        out = est.step(inp, tq, 0.05)
        assert np.all(np.isnan(out))
    assert np.array_equal(est.model.W, w)
    assert est.model.ekf.counters.frozen >= 5


def test_estimator_from_cold_start_tracks_a_moving_state() -> None:
    """Fidelity-study contract: cold start, one-step estimate at the new time."""
    est = RhonnEstimator(P)
    inp = ControllerInputs()
    errs = []
    prev = None
    for k in range(400):
        inp.vx = 18.0 - 0.01 * k
        inp.vy = 0.3 * np.sin(0.2 * k)
        inp.yaw_rate = 0.1 * np.sin(0.2 * k + 0.3)
        inp.swa_rad = 1.5 * np.sin(0.2 * k + 0.6)
        if prev is not None:
            errs.append(prev - np.array([inp.vx, inp.vy, inp.yaw_rate]))
        prev = est.step(inp, np.zeros(4), 0.05).copy()
    late = np.abs(np.array(errs[-100:]))
    assert late.max(axis=0)[1] < 0.05 and late.max(axis=0)[2] < 0.02


def test_innovation_adaptive_process_noise_opens_p_only_after_a_surprise() -> None:
    """q_nis: a neuron whose normalised innovation e²/s exceeds q_nis gets Q multiplied by
    e²/(s·q_nis) (capped at q_boost_max) for that step; the others get q. Checked on P's
    diagonal against the plain filter: the rank-1 part is the same, only Q differs."""
    h = np.linspace(0.1, 1.0, N_PHI)
    base = EkfConfig(p0=1.0, q=1e-4, r=(1.0, 1.0, 1.0))
    adaptive = EkfConfig(p0=1.0, q=1e-4, r=(1.0, 1.0, 1.0), q_nis=4.0, q_boost_max=50.0)
    s = 1.0 + float(h @ h)                     # innovation variance of every neuron, P = I
    e = np.array([0.0, np.sqrt(8.0 * s), np.sqrt(1e6 * s)])   # e²/s = 0, 8, 1e6
    plain, adapt = BatchedEkf(3, N_PHI, base), BatchedEkf(3, N_PHI, adaptive)
    plain.update(h, e)
    adapt.update(h, e)
    extra = np.diagonal(adapt.P, axis1=1, axis2=2) - np.diagonal(plain.P, axis1=1, axis2=2)
    np.testing.assert_allclose(extra[0], 0.0, atol=1e-15)            # no surprise: q
    np.testing.assert_allclose(extra[1], 1e-4 * (8.0 / 4.0 - 1.0), rtol=1e-9)
    np.testing.assert_allclose(extra[2], 1e-4 * (50.0 - 1.0), rtol=1e-9)   # capped
    np.testing.assert_array_equal(adapt.W, plain.W)                 # the gain is unchanged
