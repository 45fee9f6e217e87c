"""The numpy reference (controller/core): float32 with the UD EKF against float64, the UD
EKF against the standard one, bounded OSQP iterations and the defined fallback, and a
reference controller that deep-copies and pickles mid-run and continues bit for bit."""

from __future__ import annotations

import copy
import pickle
from pathlib import Path

import numpy as np
import pytest

from controller.core.interfaces import PredictionContext, QpStatus
from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.learning.ud_ekf import UdEkf, udu_factor
from controller.core.mpc.qp import LinearizedMpc, QpConfig
from controller.registry import make_controller
from tests.recorded import config_file, recorded_inputs, replay, state_of


def test_float32_ud_stays_within_bounds_of_float64(tmp_path: Path) -> None:
    """float32 with the UD EKF vs the float64 reference on the same inputs. (Measured on
    these inputs: ΔM within 0.08 N·m of up to 1.7 kN·m; the standard EKF in float32
    instead drifted to 2.8 kN·m ΔM differences — why float32 needs UD.)"""
    rec = recorded_inputs("nmpc-rhonn", tmp_path)
    ref = replay("nmpc-rhonn", config_file(tmp_path), rec, backend="numpy")
    f32 = replay("nmpc-rhonn", config_file(tmp_path, 'precision = "float32"', 'form = "ud"'),
                 rec, backend="numpy")
    assert np.abs(ref[:, 4]).max() > 100.0          # the MPC really acted
    assert np.all(np.isfinite(f32))
    assert np.abs(f32[:, 4] - ref[:, 4]).max() < 5.0                     # N·m
    assert np.abs(f32[:, 5] - ref[:, 5]).max() < 1e-3                     # rad/s
    assert np.abs(f32[:, 7:] - ref[:, 7:]).max() < 1e-4                   # m/s, rad/s


def _ekf_data(steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Well-conditioned regressors h ∈ (−1, 1)^15 and errors e (3,) of a noisy linear map."""
    rng = np.random.default_rng(seed)
    H = np.tanh(rng.normal(size=(steps, 15)))
    w_true = rng.normal(size=(3, 15)) * 0.1
    E = H @ w_true.T + rng.normal(size=(steps, 3)) * 0.01
    return H, E


def test_ud_ekf_matches_the_standard_ekf_on_well_conditioned_data() -> None:
    cfg = EkfConfig(p0=1.0, q=1e-4, r=(1e-2, 1e-2, 1e-2), eig_check_every=0)
    std = BatchedEkf(3, 15, cfg)
    ud = UdEkf(3, 15, cfg)
    H, E = _ekf_data(300, 3)
    for h, e in zip(H, E, strict=True):
        err = e - std.W @ h                            # same innovation for both filters
        assert std.update(h, err) and ud.update(h, err)
    assert np.allclose(ud.W, std.W, rtol=1e-8, atol=1e-10)
    assert np.allclose(ud.P, std.P, rtol=1e-7, atol=1e-12)
    assert ud.D.min() > 0.0 and np.allclose(np.tril(ud.U, -1), 0.0)


def test_ud_factor_roundtrip_and_float32_positive_definite() -> None:
    rng = np.random.default_rng(2)
    M = rng.normal(size=(15, 15))
    P = M @ M.T + 1e-3 * np.eye(15)
    U, D = udu_factor(P)
    assert np.allclose(U @ np.diag(D) @ U.T, P, rtol=1e-10, atol=1e-10)
    # float32 with the paper-like tuning (P spans 1e-9..1e1): D stays > 0, no repair.
    cfg = EkfConfig(p0=10.0, q=1e-5, r=(1e-4, 1e-4, 1e-5), eig_check_every=0)
    ud = UdEkf(3, 15, cfg, dtype=np.float32)
    H, E = _ekf_data(2000, 8)
    H[:, 8:] *= 1e-3                                   # poorly excited directions
    for h, e in zip(H.astype(np.float32), E.astype(np.float32), strict=True):
        ud.update(h, e)
    assert ud.D.min() > 0.0
    assert np.linalg.eigvalsh(ud.P).min() > 0.0


class _LinModel:
    """x⁺ = A x + B ΔM (nx = 3) with exact Jacobians (protocol path of the QP)."""

    nx = 3

    def __init__(self) -> None:
        self.A = np.diag([0.99, 0.9, 0.9])
        self.B = np.array([0.0, 1e-5, 3.3e-5])

    def predict(self, x, delta_m, ctx, out):
        out[:] = self.A @ x + self.B * delta_m

    def linearize(self, x, delta_m, ctx, a_out, b_out):
        a_out[:] = self.A
        b_out[:] = self.B


def test_bounded_iterations_hit_is_counted_and_the_fallback_is_defined() -> None:
    cfg = QpConfig.from_dict({"osqp": {
        "max_iter": 1, "check_termination": 1, "warm_starting": False}})
    mpc = LinearizedMpc(_LinModel(), cfg, ts=0.05)
    x0 = np.array([18.0, 0.5, 0.3])
    dm, status, iters, fb = mpc.solve(x0, PredictionContext(), -0.5, 0.05, -500.0, 500.0, 0.0)
    assert status == QpStatus.MAX_ITER and iters == 1 and not fb
    assert -500.0 <= dm <= 500.0 and mpc.max_iter_hits == 1 and mpc.worst_iterations == 1
    # Non-finite state → no QP, the defined fallback (decayed previous ΔM), counted.
    dm, status, _, fb = mpc.solve(np.array([np.nan, 0.0, 0.0]), PredictionContext(), 0.1,
                                  0.0, -1800.0, 1800.0, 600.0)
    assert fb and status == QpStatus.FALLBACK and dm == pytest.approx(300.0)
    assert mpc.fallbacks == 1


def test_removed_mpc_keys_are_config_errors() -> None:
    from controller.core.config_schema import ConfigError

    for key, value in (("kernels", "numpy"), ("qp_backend", "osqp")):
        with pytest.raises(ConfigError, match=key):
            QpConfig.from_dict({key: value})


def _outs(c, seq) -> np.ndarray:
    rows = []
    for inp in seq:
        o = c.step(inp)
        rows.append([*o.torques, o.delta_m, o.yaw_rate_ref, o.vy_ref, *o.model_prediction])
    return np.array(rows, dtype=float)


@pytest.mark.parametrize("name", ["nmpc-rhonn", "nmpc-mf", "lmpc"])
def test_a_reference_controller_copies_and_pickles_mid_run(name: str, tmp_path: Path) -> None:
    """copy.deepcopy and pickle of a numpy-reference controller taken mid-run: the original
    is undisturbed (bit for bit equal to an uncopied twin), the two copies agree bit for
    bit, and they continue like the original at the QP solver's tolerance (a copy sets up
    its own OSQP and warm-starts it, as a checkpoint restore does)."""
    rec = recorded_inputs(name, tmp_path, steps=250)
    path = config_file(tmp_path)
    c, twin = (make_controller(name, path, backend="numpy") for _ in range(2))
    _outs(c, rec[:100])
    _outs(twin, rec[:100])
    copies = [copy.deepcopy(c), pickle.loads(pickle.dumps(c))]
    ref = _outs(c, rec[100:])
    assert np.array_equal(ref, _outs(twin, rec[100:]), equal_nan=True)
    got = [_outs(d, rec[100:]) for d in copies]
    assert np.array_equal(got[0], got[1], equal_nan=True)
    assert np.abs(ref[:, 4]).max() > 100.0                      # the MPC acted after the copy
    assert np.abs(got[0][:, :5] - ref[:, :5]).max() < 5.0        # N·m
    assert np.abs(got[0][:, 5:] - ref[:, 5:]).max() < 1e-2       # rad/s, m/s
    assert state_of(copies[0]).keys() == state_of(c).keys()
