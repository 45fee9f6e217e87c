"""Guards of the nmpc-rhonn references: yaw-reference level and roughness in a
steady corner and in the DLC, the reference designs by config, seeded initial weights."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from controller.core.grip import GripConfig, GripEstimator
from controller.core.model.rhonn import RhonnConfig, RhonnModel
from controller.core.mpc.envelope import HandlingConfig
from controller.core.params import load_vehicle_params
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import REFERENCE_KINDS, make_rhonn_references
from controller.core.references.intent import IntentReferences
from harness.paper.benchmark import controller_config_text
from harness.run.inprocess_loop import run_in_process

P = load_vehicle_params()


def _ref_stats(res, t_from: float = 0.0) -> tuple[float, float]:
    """(mean ref·sgn / mean actual·sgn where |ωr| > 5°/s, RMS 2nd difference of the
    reference at the 50 ms MPC period, rad/s)."""
    yr = res.truth["yaw_rate_radps"][1:]
    t = res.truth["t_s"][1:]
    ref = res.yaw_rate_ref
    n = min(yr.size, ref.size)
    yr, ref, t = yr[:n], ref[:n], t[:n]
    m = (np.abs(yr) > math.radians(5.0)) & (t >= t_from)
    sgn = np.sign(yr[m])
    level = float(np.mean(ref[m] * sgn) / np.mean(yr[m] * sgn))
    r50 = ref[t >= t_from][::5]
    rough = float(np.sqrt(np.mean(np.diff(r50, 2) ** 2)))
    return level, rough


@pytest.fixture(scope="module")
def dlc_runs():
    return {c: run_in_process("dlc-paper", c, speed_kmh=70.0) for c in ("nmpc-rhonn", "nmpc-mf")}


def test_dlc_yaw_reference_level_and_roughness(dlc_runs) -> None:
    # Algorithm 1 references (paper QP): 0.93 × the measured yaw rate where |ωr| > 5°/s and
    # ~11× rougher than the linear reference. The default (grip-limited demand) measured
    # 0.942 and 4.6× (dlc-paper, 70 km/h, seed 0): on μ 0.35 it asks for a little less yaw
    # than the car turns with, by design; the bounds are the regression to beat.
    lvl_r, rough_r = _ref_stats(dlc_runs["nmpc-rhonn"])
    lvl_l, rough_l = _ref_stats(dlc_runs["nmpc-mf"])
    assert 0.92 <= lvl_r <= 1.05
    assert 0.97 <= lvl_l <= 1.03
    assert rough_r <= 5.0 * rough_l


def test_steady_corner_yaw_reference_matches_the_car(tmp_path) -> None:
    # Step steer 40° at 80 km/h, μ 1 (~0.4 g): in the steady part (t ≥ 3 s) the reference
    # must sit on the car's yaw rate (within 5 %). Roughness (RMS 2nd difference at 50 ms),
    # measured: the paper's Algorithm 1 (no sideslip guard) 0.016 rad/s, the default 0.019.
    # This car corners at 0.4 g with |β| ≈ 3.3°, where the default has blended fully into
    # Algorithm 1's learned steady state ([handling] fixed_point_beta_hi = 3°): its reference
    # is Algorithm 1's there, and must stay within 1.25 × its roughness and below 1.5°/s.
    res = run_in_process("step-steer", "nmpc-rhonn")
    lvl, rough = _ref_stats(res, t_from=3.0)
    assert abs(lvl - 1.0) <= 0.05
    cfg = tmp_path / "a1.toml"
    cfg.write_text(controller_config_text(0, {"kind": "algorithm1", "guard_gain_per_s": 0.0}))
    lvl_a1, rough_a1 = _ref_stats(run_in_process("step-steer", "nmpc-rhonn", config=str(cfg)),
                                  t_from=3.0)
    assert abs(lvl_a1 - 1.0) <= 0.05
    assert rough <= math.radians(1.5)
    assert rough <= 1.25 * rough_a1


def test_intent_reference_asks_for_the_drivers_yaw_on_the_dlc(tmp_path) -> None:
    cfg = tmp_path / "intent.toml"
    # the paper's QP (no envelope, no move weight), as the kind was measured
    cfg.write_text(controller_config_text(0, {"kind": "intent", "handling.envelope": False}))
    lvl, _ = _ref_stats(run_in_process("dlc-paper", "nmpc-rhonn", speed_kmh=70.0,
                                       config=str(cfg)))
    assert lvl >= 0.98     # Algorithm 1: 0.957–0.969 here


def test_reference_kinds_build_and_unknown_kind_fails() -> None:
    model = RhonnModel(P, RhonnConfig(), 0.05)
    grip = GripEstimator(P, GripConfig(), 0.05)
    for kind in REFERENCE_KINDS:
        ref = make_rhonn_references(model, P, RhonnRefConfig(kind=kind), grip, HandlingConfig())
        r, vy, b = ref.compute(20.0, 0.0, 0.0, 0.02, 0.0, 0.0)
        assert all(math.isfinite(v) for v in (r, vy, b))
        assert r >= -0.02    # turns the way the wheels point (within r_band, rad/s)
    with pytest.raises(ValueError, match=r"references\.kind"):
        make_rhonn_references(model, P, RhonnRefConfig(kind="nope"))


def test_intent_uses_the_learned_gain_when_the_map_is_stable() -> None:
    model = RhonnModel(P, RhonnConfig(), 0.05)
    ref = IntentReferences(model, P, RhonnRefConfig(kind="intent"))
    assert ref.steady_response(20.0, 0.02) is None            # W = 0: no equilibrium
    # A hand-made stable map: Δωr = −k (ξ3 − g ξ4 ξ1-free), Δvy = −k ξ2 → ωr* from δ.
    w = np.zeros((3, 15))
    w[1, 1] = -0.2        # ξ2 (Vy) on the Vy increment
    w[2, 2] = -0.2        # ξ3 (ωr) on the ωr increment
    w[2, 3] = 0.2 * 2.0   # ξ4 (δ) on the ωr increment: steady ξ3 = 2 ξ4
    model.W[:] = w
    vy, r = ref.steady_response(20.0, 0.01)
    xi4 = math.tanh(0.01 / 0.15)
    assert r == pytest.approx(math.atanh(2.0 * xi4) * 0.6, rel=1e-9)
    assert vy == pytest.approx(0.0, abs=1e-12)


def test_seeded_initial_weights_and_config_text() -> None:
    w0 = RhonnModel(P, RhonnConfig(), 0.05).W.copy()
    a = RhonnModel(P, RhonnConfig(init_seed=3), 0.05).W.copy()
    b = RhonnModel(P, RhonnConfig(init_seed=3), 0.05).W.copy()
    assert not w0.any() and a.any()
    np.testing.assert_array_equal(a, b)
    raw = tomllib.loads(controller_config_text(4, {"kind": "intent", "slow_tau_s": 1.0}))
    assert raw["rhonn"]["init_seed"] == 4
    assert raw["references"]["kind"] == "intent"
    assert raw["references"]["slow_tau_s"] == 1.0
    assert raw["references"]["eta"] == 5.0          # the rest of the packaged file is kept
    raw = tomllib.loads(controller_config_text(4, {"kind": "demand", "mpc.horizon": 10}))
    assert raw["mpc"]["horizon"] == 10 and raw["references"]["kind"] == "demand"
    assert raw["mpc"]["q_yaw"] == 100.0             # the other [mpc] keys stay
