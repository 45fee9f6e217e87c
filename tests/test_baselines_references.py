"""Linear steady-state references (LMPC / NMPC-MF targets)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from controller.core.params import load_vehicle_params
from controller.core.references.linear import DEN_MIN, LinearReferences

P = load_vehicle_params()
REFS = LinearReferences(P)


def bicycle_steady_state(vx: float, delta: float) -> tuple[float, float]:
    """Independent reference: solve the bicycle's steady-state force/moment balance."""
    m = P.mass_kg
    cf, cr = -P.cf_axle_n_per_rad, -P.cr_axle_n_per_rad
    lf, lr = P.lf_m, P.lr_m
    a = np.array([[cf + cr, (cf * lf - cr * lr) / vx + m * vx],
                  [lf * cf - lr * cr, (cf * lf**2 + cr * lr**2) / vx]])
    beta, r = np.linalg.solve(a, np.array([cf * delta, lf * cf * delta]))
    return float(r), float(beta)


def test_understeer_gradient_and_critical_speed() -> None:
    """Table 1: very slightly oversteering; v_crit ≈ 66 m/s (238 km/h)."""
    L = P.wheelbase_m
    k = P.mass_kg / L**2 * (P.lr_m / 108350.0 - P.lf_m / 105898.0)
    assert REFS.understeer_gradient == pytest.approx(k, rel=1e-12)
    assert REFS.understeer_gradient < 0.0
    assert REFS.critical_speed_mps == pytest.approx(66.05, abs=0.05)
    assert REFS.guard_speed_mps == pytest.approx(REFS.critical_speed_mps * math.sqrt(0.5))
    assert REFS.guard_speed_mps > 85.0 / 3.6 * 1.5  # far above every scenario speed


@pytest.mark.parametrize("vx", [0.5, 5.0, 18.06, 23.6, 40.0, -10.0])
@pytest.mark.parametrize("delta", [0.01, -0.05])
def test_matches_closed_form_below_guard(vx: float, delta: float) -> None:
    r_ref, vy_ref, beta_ref = REFS.compute(vx, 0.3, -0.1, delta, 500.0, 2.0)
    r_ss, beta_ss = bicycle_steady_state(vx, delta)
    assert r_ref == pytest.approx(r_ss, rel=1e-9)
    assert beta_ref == pytest.approx(beta_ss, rel=1e-9)
    assert vy_ref == pytest.approx(beta_ss * vx, rel=1e-9)


def test_textbook_formula() -> None:
    vx, d = 20.0, 0.03
    K, L = REFS.understeer_gradient, P.wheelbase_m
    r_ref, _, beta_ref = REFS.compute(vx, 0.0, 0.0, d, 0.0, 0.0)
    assert r_ref == pytest.approx(vx * d / (L * (1 + K * vx**2)))
    beta = d * (P.lr_m - P.mass_kg * P.lf_m * vx**2 / (L * 105898.0)) / (L * (1 + K * vx**2))
    assert beta_ref == pytest.approx(beta)


def test_finite_and_guarded_at_and_beyond_critical_speed() -> None:
    vc = REFS.critical_speed_mps
    d = 0.01
    speeds = np.sort(np.concatenate([np.linspace(0.9 * REFS.guard_speed_mps, 1.5 * vc, 400),
                                     [vc, vc * (1 - 1e-12), vc * (1 + 1e-12), 500.0, 1e3]]))
    prev = 0.0
    for vx in speeds:
        r, vy, beta = REFS.compute(float(vx), 0.0, 0.0, d, 0.0, 0.0)
        assert math.isfinite(r) and math.isfinite(vy) and math.isfinite(beta)
        assert r > 0.0  # never flips sign past v_crit
        gain = r / d
        assert gain <= float(vx) / (P.wheelbase_m * DEN_MIN) + 1e-9
        assert r >= prev - 1e-12  # monotone in speed through the guard
        prev = r


def test_zero_speed_limit() -> None:
    r, vy, beta = REFS.compute(0.0, 0.0, 0.0, 0.1, 0.0, 0.0)
    assert r == 0.0 and vy == 0.0
    assert beta == pytest.approx(0.1 * P.lr_m / P.wheelbase_m)
    r2, _, beta2 = REFS.compute(1e-9, 0.0, 0.0, 0.1, 0.0, 0.0)
    assert abs(r2) < 1e-9 and beta2 == pytest.approx(beta)


def test_invalid_inputs_give_neutral_reference() -> None:
    for vx, d in ((math.nan, 0.1), (20.0, math.inf), (-math.inf, 0.0), (20.0, math.nan),
                  (2e3, 0.1), (20.0, 1.6)):
        assert REFS.compute(vx, 0.0, 0.0, d, 0.0, 0.0) == (0.0, 0.0, 0.0)


@given(vx=st.floats(allow_nan=True, allow_infinity=True),
       d=st.floats(allow_nan=True, allow_infinity=True),
       other=st.floats(allow_nan=True, allow_infinity=True))
def test_never_raises_and_finite(vx: float, d: float, other: float) -> None:
    out = REFS.compute(vx, other, other, d, other, other)
    assert all(math.isfinite(v) for v in out)
