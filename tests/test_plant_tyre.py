"""Magic Formula tyre: published coefficients, scaling to Table 1, signs, friction scaling."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant_sim.params import load_vehicle_params
from plant_sim.tyre import load_tyre_config, make_vehicle_tyres

TABLE1_CF = -108350.0  # N/rad, front axle (paper sign)
TABLE1_CR = -105898.0  # N/rad, rear axle


def test_published_table_a31_values() -> None:
    """Spot-check the transcription of Pacejka (2006) Table A3.1 (205/60R15)."""
    pub = load_tyre_config()["published"]
    expected = {"FNOMIN": 4000.0, "PCX1": 1.685, "PDX1": 1.210, "PKX1": 21.51, "PCY1": 1.193,
                "PDY1": -0.990, "PDY2": 0.145, "PEY1": -1.003, "PKY1": -14.95, "PKY2": 2.130,
                "RBX1": 12.35, "RBX2": -10.77, "RCX1": 1.092, "RBY1": 6.461, "RBY2": 4.196,
                "RCY1": 1.081, "QSY1": 0.01}
    for key, value in expected.items():
        assert pub[key] == value, key


def test_axle_cornering_stiffness_matches_table1() -> None:
    p = load_vehicle_params()
    front, rear = make_vehicle_tyres()
    fzf, fzr = p.static_wheel_loads_n
    cf = 2.0 * front.cornering_stiffness(fzf)
    cr = 2.0 * rear.cornering_stiffness(fzr)
    assert cf == pytest.approx(TABLE1_CF, rel=1e-3)
    assert cr == pytest.approx(TABLE1_CR, rel=1e-3)
    # the analytic slope agrees with the force function (finite difference)
    h = 1e-5
    slope = (front.forces(0.0, h, fzf)[1] - front.forces(0.0, -h, fzf)[1]) / (2 * h)
    assert 2.0 * slope == pytest.approx(TABLE1_CF, rel=2e-3)


def test_sign_convention_and_zero_slip() -> None:
    front, _ = make_vehicle_tyres()
    assert front.forces(0.0, 0.0, 5000.0) == (0.0, 0.0)
    fx, fy = front.forces(0.0, 0.05, 5000.0)
    assert fy < 0.0  # + alpha (contact point sliding left) -> force to the right
    fx, fy = front.forces(0.05, 0.0, 5000.0)
    assert fx > 0.0 and fy == 0.0
    fx, _ = front.forces(-0.05, 0.0, 5000.0)
    assert fx < 0.0
    # left/right mirror: Fy(-alpha) = -Fy(alpha), Fx unchanged (symmetrised set)
    a = front.forces(0.08, 0.1, 5000.0)
    b = front.forces(0.08, -0.1, 5000.0)
    assert b[0] == pytest.approx(a[0], rel=1e-12)
    assert b[1] == pytest.approx(-a[1], rel=1e-12)


def test_combined_slip_reduces_forces() -> None:
    front, _ = make_vehicle_tyres()
    fz = 5000.0
    fy_pure = front.forces(0.0, 0.1, fz)[1]
    fx_pure = front.forces(0.1, 0.0, fz)[0]
    fx_c, fy_c = front.forces(0.1, 0.1, fz)
    assert abs(fy_c) < abs(fy_pure)
    assert abs(fx_c) < abs(fx_pure)


def test_friction_scaling_sets_peak() -> None:
    front, _ = make_vehicle_tyres()
    fz = front.fz0
    alphas = [i * 0.005 for i in range(1, 120)]
    kappas = [i * 0.005 for i in range(1, 120)]
    for mu in (1.0, 0.35):
        peak_y = max(abs(front.forces(0.0, a, fz, mu, mu)[1]) for a in alphas)
        peak_x = max(front.forces(k, 0.0, fz, mu, mu)[0] for k in kappas)
        assert peak_y / fz == pytest.approx(0.990 * mu, rel=0.01)  # |PDY1| * LMUY
        assert peak_x / fz == pytest.approx(1.210 * mu, rel=0.01)  # PDX1 * LMUX


@settings(max_examples=300, deadline=None)
@given(
    kappa=st.floats(allow_nan=True, allow_infinity=True, width=64),
    alpha=st.floats(-10.0, 10.0),
    fz=st.floats(-1e5, 1e5),
    mu=st.floats(0.0, 2.0),
)
def test_forces_always_finite(kappa: float, alpha: float, fz: float, mu: float) -> None:
    front, rear = make_vehicle_tyres()
    for tyre in (front, rear):
        fx, fy = tyre.forces(kappa, alpha, fz, mu, mu)
        assert math.isfinite(fx) and math.isfinite(fy)
        # bounded by the friction circle with margin (peak mu_x 1.21 at most x 3 load cap)
        assert abs(fx) <= 2.0 * max(mu, 1e-3) * 3.0 * tyre.fz0 + 1e-6
