"""Linear 2-DoF bicycle (LMPC model) and the Jacobians of every prediction model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from controller.core.interfaces import ControllerInputs, PredictionContext
from controller.core.model.baselines import MODEL_KINDS, make_model
from controller.core.params import load_vehicle_params

P = load_vehicle_params()


def closed_form_steady_state(vx: float, delta: float) -> tuple[float, float]:
    """Textbook steady state of the linear bicycle, from its force/moment balance:
    m·vx·r = Fyf + Fyr, lf·Fyf = lr·Fyr, Fy = |C|·(steer − slip). Independent of the code."""
    m = P.mass_kg
    cf, cr = -P.cf_axle_n_per_rad, -P.cr_axle_n_per_rad
    # unknowns (beta, r): the two balance equations are linear in them
    a = np.array([[cf + cr, (cf * P.lf_m - cr * P.lr_m) / vx + m * vx],
                  [P.lf_m * cf - P.lr_m * cr, (cf * P.lf_m**2 + cr * P.lr_m**2) / vx]])
    rhs = np.array([cf * delta, P.lf_m * cf * delta])
    beta, r = np.linalg.solve(a, rhs)
    return float(r), float(beta)


def run_to_steady(kind: str, vx: float, delta: float, seconds: float = 20.0,
                  ts: float = 0.05) -> np.ndarray:
    model = make_model(kind, P)
    ctx = PredictionContext(delta_w=delta, total_torque=0.0, ts=ts)
    x = np.array([vx, 0.0, 0.0])
    out = np.zeros(3)
    for _ in range(round(seconds / ts)):
        model.predict(x, 0.0, ctx, out)
        x[:] = out
    return x


@pytest.mark.parametrize("vx", [5.0, 12.0, 18.0, 25.0, 35.0])
@pytest.mark.parametrize("delta", [0.004, -0.02])
def test_bicycle_steady_state_matches_closed_form(vx: float, delta: float) -> None:
    x = run_to_steady("bicycle", vx, delta)
    r_ss, beta_ss = closed_form_steady_state(vx, delta)
    assert x[0] == pytest.approx(vx, abs=1e-12)  # Tt = 0: speed held
    assert x[2] == pytest.approx(r_ss, rel=1e-6)
    assert x[1] / vx == pytest.approx(beta_ss, rel=1e-6, abs=1e-9)


def test_bicycle_signs() -> None:
    """+δ turns left (r > 0); +ΔM (right wheels push) turns left; Tt accelerates."""
    model = make_model("bicycle", P)
    out = np.zeros(3)
    model.predict(np.array([20.0, 0.0, 0.0]), 0.0, PredictionContext(0.02, 0.0, 0.05), out)
    assert out[2] > 0.0
    model.predict(np.array([20.0, 0.0, 0.0]), 1000.0, PredictionContext(0.0, 0.0, 0.05), out)
    assert out[2] > 0.0
    model.predict(np.array([20.0, 0.0, 0.0]), 0.0, PredictionContext(0.0, 1000.0, 0.05), out)
    assert out[0] == pytest.approx(20.0 + 0.05 * 1000.0 / (P.mass_kg * P.wheel_radius_m))


def test_bicycle_matches_exact_discretisation() -> None:
    """One step against the exact zero-order-hold discretisation (matrix exponential)."""
    model = make_model("bicycle", P)
    m, iz, lf, lr = P.mass_kg, P.yaw_inertia_kgm2, P.lf_m, P.lr_m
    cf, cr = P.cf_axle_n_per_rad, P.cr_axle_n_per_rad
    kdm = P.track_m / (2.0 * P.wheel_radius_m * iz)
    rng = np.random.default_rng(3)
    err = []
    for ts in (0.05, 0.01):
        for _ in range(100):
            vx, vy, r = rng.uniform(8, 35), rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 0.5)
            d, dm = rng.uniform(-0.08, 0.08), rng.uniform(-2500, 2500)
            a = np.array([[(cf + cr) / (m * vx), (cf * lf - cr * lr) / (m * vx) - vx],
                          [(lf * cf - lr * cr) / (iz * vx),
                           (lf * lf * cf + lr * lr * cr) / (iz * vx)]])
            big = np.zeros((3, 3))
            big[:2, :2] = a
            big[:2, 2] = [-cf / m * d, -lf * cf / iz * d + kdm * dm]
            exact = (expm(big * ts) @ np.array([vy, r, 1.0]))[:2]
            out = np.zeros(3)
            model.predict(np.array([vx, vy, r]), dm, PredictionContext(d, 0.0, ts), out)
            err.append(np.abs(out[1:] - exact))
    e = np.array(err)
    # stated accuracy: per 50 ms step, vy ≤ 0.2 km/h and r ≤ 1 deg/s worst case
    assert e[:, 0].max() * 3.6 < 0.2
    assert e[:, 1].max() * 180 / math.pi < 1.0


def _fd_jacobian(model, x: np.ndarray, dm: float, ctx: PredictionContext
                 ) -> tuple[np.ndarray, np.ndarray]:
    a = np.zeros((3, 3))
    op, om = np.zeros(3), np.zeros(3)
    for j, eps in enumerate((1e-5, 1e-6, 1e-6)):
        xp, xm = x.copy(), x.copy()
        xp[j] += eps
        xm[j] -= eps
        model.predict(xp, dm, ctx, op)
        model.predict(xm, dm, ctx, om)
        a[:, j] = (op - om) / (2 * eps)
    model.predict(x, dm + 1.0, ctx, op)
    model.predict(x, dm - 1.0, ctx, om)
    return a, (op - om) / 2.0


STATES = [
    (20.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    (18.0, 0.6, 0.3, 0.05, 800.0, 200.0),
    (25.0, -1.2, -0.4, -0.03, -1500.0, -300.0),
    (16.0, 1.5, 0.45, 0.09, 2000.0, 0.0),  # near the limit for the MF tyre
    (9.0, 0.2, 0.6, 0.12, 0.0, 500.0),  # two sub-steps at 50 ms
]


@pytest.mark.parametrize("kind", MODEL_KINDS)
@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("ts", [0.05, 0.01])
def test_jacobians_match_central_differences(kind: str, state: tuple, ts: float) -> None:
    model = make_model(kind, P)
    vx, vy, r, d, dm, tt = state
    x = np.array([vx, vy, r])
    ctx = PredictionContext(delta_w=d, total_torque=tt, ts=ts)
    a, b = np.zeros((3, 3)), np.zeros(3)
    model.linearize(x, dm, ctx, a, b)
    a_fd, b_fd = _fd_jacobian(model, x, dm, ctx)
    np.testing.assert_allclose(a, a_fd, rtol=1e-5, atol=2e-7)
    np.testing.assert_allclose(b, b_fd, rtol=1e-5, atol=1e-11)
    # one-pass variant gives the same numbers
    out, out2, a2, b2 = np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3)
    model.predict(x, dm, ctx, out)
    model.predict_linearize(x, dm, ctx, out2, a2, b2)
    np.testing.assert_allclose(out2, out, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(a2, a)
    np.testing.assert_array_equal(b2, b)


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_yaw_moment_input_gain(kind: str) -> None:
    """∂r+/∂ΔM ≈ ts·wB/(2·R·Iz) for a short step (the paper's known ΔM term)."""
    model = make_model(kind, P)
    a, b = np.zeros((3, 3)), np.zeros(3)
    ts = 0.01
    model.linearize(np.array([20.0, 0.0, 0.0]), 0.0, PredictionContext(0.0, 0.0, ts), a, b)
    assert b[2] == pytest.approx(ts * P.yaw_moment_per_delta_m / P.yaw_inertia_kgm2, rel=0.03)


def test_initial_state_copies_bus_estimates() -> None:
    model = make_model("7dof-mf", P)
    out = np.zeros(model.nx)
    model.initial_state(ControllerInputs(vx=17.0, vy=0.3, yaw_rate=-0.2), out)
    np.testing.assert_array_equal(out, [17.0, 0.3, -0.2])


def test_unknown_kind_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown prediction model"):
        make_model("rhonn", P)
