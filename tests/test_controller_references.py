"""Steady-state references: Algorithm 1 on maps with known fixed points (eq. 18–20)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.model.rhonn import N_PHI, RhonnConfig, RhonnModel
from controller.core.params import load_vehicle_params
from controller.core.references.algorithm1 import RhonnRefConfig, RhonnReferences

P = load_vehicle_params()
VX, DW = 20.0, 0.03


def _model_with_fixed_point(vy_star: float, r_star: float) -> RhonnModel:
    """Increment-form weights whose lateral map at (VX, DW) has the fixed point (vy*, r*):
    g = A (ξ − ξ*) with a stable A; the constant −A ξ* is carried by φ_1 = S(Vx)
    (constant at fixed Vx), the linear parts by φ_2 = S(Vy) and φ_3 = S(ωr)."""
    m = RhonnModel(P, RhonnConfig(form="increment"))
    a_star, b_star = m.xi(1, vy_star), m.xi(2, r_star)
    s1 = m.xi(0, VX)
    A = np.array([[-0.3, 0.1], [0.05, -0.25]])
    W = np.zeros((3, N_PHI))
    W[1, 1], W[1, 2] = A[0]
    W[2, 1], W[2, 2] = A[1]
    W[1, 0] = -(A[0] @ [a_star, b_star]) / s1
    W[2, 0] = -(A[1] @ [a_star, b_star]) / s1
    m.W[:] = W
    return m


def _residual_cost(m: RhonnModel, vy: float, r: float, eta: float) -> float:
    phi = m.phi(np.array([VX, vy, r]), DW)
    g = m.W @ phi
    return abs(g[1]) + eta * abs(g[2])


@pytest.mark.parametrize(("vy_star", "r_star"), [(0.4, 0.12), (-0.9, 0.2), (0.05, 0.02)])
def test_search_returns_the_known_fixed_point_within_threshold(vy_star: float,
                                                              r_star: float) -> None:
    m = _model_with_fixed_point(vy_star, r_star)
    cfg = RhonnRefConfig(r_kin_factor=50.0, ay_floor=9.0)   # limits wide open here
    ref = RhonnReferences(m, P, cfg)
    r_d, vy_d, b_d = ref.compute(VX, 0.0, 0.0, DW, 0.0, 0.0)
    assert _residual_cost(m, vy_d, r_d, cfg.eta) <= cfg.eps_t
    assert vy_d == pytest.approx(vy_star, abs=2e-3)
    assert r_d == pytest.approx(r_star, abs=5e-4)
    assert b_d == pytest.approx(vy_d / VX)
    assert ref.not_converged == 0


def test_fixed_point_outside_limits_gives_a_bounded_reference_and_is_counted() -> None:
    # Fixed point at ωr = 0.6 rad/s > a_max / Vx = 4 / 20 = 0.2 rad/s.
    m = _model_with_fixed_point(0.2, 0.6)
    cfg = RhonnRefConfig(r_kin_factor=50.0, ay_floor=4.0, ay_ceiling=4.0)
    ref = RhonnReferences(m, P, cfg)
    r_d, vy_d, _ = ref.compute(VX, 0.0, 0.0, DW, 0.0, 0.0)
    assert abs(r_d) <= 4.0 / VX + 1e-12
    assert abs(vy_d) <= math.tan(cfg.beta_max) * VX + 1e-12
    assert r_d == pytest.approx(4.0 / VX, abs=0.02)     # pushed against the limit
    assert ref.not_converged == 1
    assert ref.rounds_last <= cfg.max_rounds


def test_yaw_reference_turns_the_way_the_wheels_point() -> None:
    # A (spurious) fixed point with the wrong sign is outside the kinematic band.
    m = _model_with_fixed_point(0.0, -0.15)
    cfg = RhonnRefConfig()
    ref = RhonnReferences(m, P, cfg)
    r_d, _, _ = ref.compute(VX, 0.0, 0.0, DW, 0.0, 0.0)      # DW > 0: left turn
    assert r_d >= -cfg.r_band - 1e-12
    r_kin = cfg.r_kin_factor * VX * DW / P.wheelbase_m
    assert r_d <= r_kin + cfg.r_band + 1e-12


def test_search_is_local_it_returns_from_the_first_neighbourhood() -> None:
    """A fixed point inside the initial radius around the measured state is found in the
    first round (Algorithm 1 searches outward from the previous state)."""
    m = RhonnModel(P, RhonnConfig())
    a0 = m.xi(1, 0.3)
    W = np.zeros((3, N_PHI))
    W[2, 2] = -0.3                        # g_r = −0.3 S(ωr)        → ωr* = 0
    W[1, 1] = -0.2                        # g_vy = −0.2 (S(Vy) − S(0.3)) → Vy* = 0.3 m/s
    W[1, 0] = 0.2 * a0 / m.xi(0, VX)
    m.W[:] = W
    ref = RhonnReferences(m, P, RhonnRefConfig(r_kin_factor=50.0, ay_floor=9.0))
    r_d, vy_d, _ = ref.compute(VX, 0.25, 0.01, DW, 0.0, 0.0)
    assert vy_d == pytest.approx(0.3, abs=2e-3) and abs(r_d) < 1e-3
    assert ref.rounds_last == 1


def test_low_speed_and_non_finite_inputs_are_guarded() -> None:
    m = _model_with_fixed_point(0.4, 0.12)
    ref = RhonnReferences(m, P, RhonnRefConfig())
    r_d, vy_d, b_d = ref.compute(1.0, 0.0, 0.0, 0.1, 0.0, 0.0)
    assert r_d == pytest.approx(1.0 * 0.1 / P.wheelbase_m)     # kinematic below v_min
    assert vy_d == pytest.approx(P.lr_m * r_d)
    assert abs(b_d) < 1.0 and math.isfinite(b_d)
    for bad in (math.nan, math.inf, -math.inf):
        out = ref.compute(bad, 0.1, 0.1, 0.02, 0.0, bad)
        assert all(math.isfinite(v) for v in out)
        out = ref.compute(20.0, bad, bad, 0.02, 0.0, 0.0)
        assert all(math.isfinite(v) for v in out)


def test_ay_envelope_raises_the_yaw_limit_and_decays() -> None:
    m = _model_with_fixed_point(0.0, 0.0)
    cfg = RhonnRefConfig(ay_floor=4.0, ay_ceiling=9.0, ay_margin=1.2, ay_decay_s=1.0)
    ref = RhonnReferences(m, P, cfg)
    assert ref.a_max() == 4.0
    ref.compute(VX, 0.0, 0.0, DW, 0.0, 6.0)
    assert ref.a_max() == pytest.approx(7.2)
    for _ in range(200):                       # 10 s of straight driving
        ref.compute(VX, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert ref.a_max() == 4.0
