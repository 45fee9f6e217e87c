"""The learned ΔM effectiveness θ in the C core (controller/native/src/yaw_gain.c, the model's
use of it in rhonn_model.c) against the numpy reference (controller/core/learning/
input_gain.py, controller/core/model/rhonn.py), the oracle.

Bounds:

* the joint filter alone, on tests/test_rhonn_dm_gain.py's synthetic closed-loop data
  (4000 updates, ΔM a state feedback) and on guard-heavy tunings (trace resets, eigenvalue
  floors, weight clips): float64 standard form |ΔW| ≤ 1e-11 and P ≤ 1e-9 of its scale
  (measured 2.6e-12 and 2.4e-11: numpy's matmul sums P h in another order than the C loop);
  UD form in float64 and float32 ≤ 4 ulp of the working precision (measured 0: the
  reference's scalar loops are the C's operation order); guard counters equal.
* the whole nmpc-rhonn step with [rhonn] dm_gain_p0 = 0.1 on recorded closed-loop inputs
  (invalid and non-finite inputs spliced in, allocate_only between steps), per output signal
  relative to its scale, and θ after every step:
  - float64, packaged jerk-weight QP: 20 × the reference's own spread under one-ulp input
    and QP-data moves (test_native_core's conditioning bound; measured C − numpy 7.3e-9 of
    the scale, θ 1.1e-8, against spreads of 6.9e-8 and 1.0e-7);
  - float64, move-weight QP: 1e-8 of the scale, θ 1e-8 (measured 9.5e-10, 3.8e-10);
  - float32 (UD): BOUND_F32 or 3 × the float32 reference's own spread under one-float32-ulp
    moves, whichever is larger, θ 1e-3 or 3 × its spread (measured C − numpy 2.8e-4 and
    4.7e-4 of the scale, θ 1e-4, against spreads of 8.7e-4 / 1.3e-3 and 5.3e-4 / 2.8e-4:
    the one-step error the filters learn from, e = x − χ, is a difference of near-equal
    numbers, and the reference keeps the ΔM gains and u in float64);
  - learned state (W, P, the joint filter's W and P, u) within test_native_core's state
    bounds, both filters' counters equal.
"""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs
from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.learning.input_gain import YawGainFilter
from controller.core.model.rhonn import N_PHI
from controller.core.registry import load_controller_config
from controller.native.backend import core_module
from controller.native.config import ctrl_config, fill
from controller.native.controller import NativeController
from controller.registry import make_controller
from controller.runtime.checkpoint import (
    config_hash,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from tests.recorded import awkward_inputs, recorded_inputs, set_toml_keys
from tests.test_native_core import (
    BOUND_DEFAULT,
    BOUND_F32,
    F32_SPREAD_FACTOR,
    SPREAD_FACTOR,
    SPREAD_SEEDS,
    TIGHT_HANDLING,
    _f32_safe,
    _path,
    assert_close,
    perturbed,
    qp_data_perturbed,
    run,
    scale_errors,
)
from tests.test_rhonn_dm_gain import EKF, closed_loop_data

needs_core = pytest.mark.skipif(core_module(False) is None or core_module(True) is None,
                                reason="the C core is not built (no C compiler at install)")
pytestmark = needs_core

DM_GAIN = "dm_gain_p0 = 0.1"
# |θ_C − θ_numpy| at every step, -. float32: the learned state's bound of test_native_core
# (1e-3 of its scale; θ ≈ 1); the one-step error e = x − χ the filters learn from is a
# difference of near-equal numbers, so χ's float32 rounding (the reference keeps the ΔM
# gains and u in float64, the core in float) is a relative 1e-5..1e-4 of e.
THETA_BOUND = {"float64": 1e-8, "float32": 1e-3}
# float32: OSQP iteration counts may differ on this share of the steps (a termination check
# on the other side of eps; test_native_core's sideslip-guard tests allow the same)
F32_ITERATION_SLACK = 0.03


# ------------------------------------------------------------------ the filter alone
class CFilter:
    """rh_yaw_gain_t through the generated binding, with numpy views of W, P / U, D."""

    def __init__(self, f32: bool, ekf: EkfConfig, w_r0: np.ndarray, p0: float = 0.1,
                 lo: float = 0.4, hi: float = 2.5) -> None:
        self.m = core_module(f32)
        ffi, lib = self.m.ffi, self.m.lib
        self.dt = np.float32 if f32 else np.float64
        self.ud = ekf.form == "ud"
        self.g = ffi.new("rh_yaw_gain_t *")
        ec = ffi.new("rh_ekf_config_t *")
        fill(self.m, ec[0], ekf)
        gc = ffi.new("rh_yaw_gain_config_t *",
                     {"dm_gain_p0": p0, "dm_gain_min": lo, "dm_gain_max": hi})
        self.rc = lib.rh_yaw_gain_init(self.g, gc, ec, int(self.ud),
                                       ffi.new("real_t[15]", [float(w) for w in w_r0]))
        assert lib.rh_yaw_gain_size() == ffi.sizeof("rh_yaw_gain_t")
        self.W = np.frombuffer(ffi.buffer(self.g.W), self.dt)
        self._M = np.frombuffer(ffi.buffer(self.g.PU), self.dt).reshape(16, 16)
        self._D = np.frombuffer(ffi.buffer(self.g.D), self.dt)
        self._phi = np.zeros(N_PHI, self.dt)

    @property
    def P(self) -> np.ndarray:
        """The covariance (16, 16), float64 (U D Uᵀ in the UD form)."""
        M = self._M.astype(float)
        return (M * self._D.astype(float)) @ M.T if self.ud else M

    def update(self, phi: np.ndarray, u: float, e: float) -> bool:
        ffi = self.m.ffi
        self._phi[:] = phi
        return bool(self.m.lib.rh_yaw_gain_update(
            self.g, ffi.cast("real_t *", ffi.from_buffer(self._phi)), u, e))

    def counters(self) -> dict[str, int]:
        return {n: int(getattr(self.g.counters, n))
                for n, _ in self.m.ffi.typeof(self.g.counters).fields}


# guard-heavy tunings on top of tests/test_rhonn_dm_gain.py's EKF (its data stays the same)
GUARDS = {
    "plain": EKF,
    # P grows by 16 q per step past trace_max: reset to p0 I, θ's variance to p0 as well
    "trace-reset": replace(EKF, p0=1.0, q=0.05, trace_max=20.0),
    # a floor above the converged eigenvalues: the standard form's periodic repair acts
    "eig-floor": replace(EKF, p_floor=1e-4, eig_check_every=50),
    # a weight bound below the true weights: clipped at every update, θ then at its floor
    "weight-clip": replace(EKF, w_max=0.03),
    # the same floor without the periodic check: never repaired
    "no-eig-check": replace(EKF, p_floor=1e-4, eig_check_every=0),
}
FILTER_CASES = [("float64", "standard"), ("float64", "ud"), ("float32", "ud")]


def _run_filters(precision: str, form: str, ekf: EkfConfig, theta_true: float, n: int,
                 w_r0: np.ndarray) -> tuple[YawGainFilter, CFilter, float, float]:
    """Both filters on the same data (errors from the reference's own estimate); the worst
    |ΔW| and the worst |ΔP| relative to the reference's max |P| over all updates."""
    dt = np.float32 if precision == "float32" else np.float64
    ekf = replace(ekf, form=form)
    phi, u, y = closed_loop_data(theta_true, n, seed=3)
    ref = YawGainFilter(N_PHI, ekf, w_r0, 0.1, 0.4, 2.5, dtype=dt)
    c = CFilter(precision == "float32", ekf, w_r0)
    assert c.rc == 0
    np.testing.assert_array_equal(c.W, ref.filter.W[0])
    np.testing.assert_array_equal(c.P, ref.get_state()["P"][0].astype(float))
    w_err = p_err = 0.0
    for k in range(n):
        e = float(y[k] - (float(ref.w_row.astype(float) @ phi[k]) + ref.theta * u[k]))
        accepted = ref.update(phi[k].astype(dt), float(u[k]), e)
        assert c.update(phi[k], float(u[k]), e) == accepted
        w_err = max(w_err, float(np.max(np.abs(c.W.astype(float) - ref.filter.W[0]))))
        p_ref = np.asarray(ref.get_state()["P"][0], float)
        p_err = max(p_err, float(np.max(np.abs(c.P - p_ref)) / np.max(np.abs(p_ref))))
    return ref, c, w_err, p_err


def _filter_bounds(precision: str, form: str) -> tuple[float, float]:
    if form == "standard":
        return 1e-11, 1e-9
    eps = float(np.finfo(np.float32 if precision == "float32" else np.float64).eps)
    return 4 * eps, 4 * eps


@pytest.mark.parametrize(("precision", "form"), FILTER_CASES)
@pytest.mark.parametrize("theta_true", [0.64, 1.3, 5.0])
def test_the_c_filter_equals_the_reference_on_closed_loop_data(precision: str, form: str,
                                                               theta_true: float) -> None:
    """θ where ΔM is a state feedback (0.64, 1.3: found; 5.0: held at dm_gain_max)."""
    w_r0 = np.random.default_rng(5).normal(0.0, 0.01, N_PHI)
    ref, c, w_err, p_err = _run_filters(precision, form, EKF, theta_true, 4000, w_r0)
    print(f"{precision} {form} θ {theta_true}: |ΔW| {w_err:.3g}, |ΔP| {p_err:.3g} of scale")
    w_bound, p_bound = _filter_bounds(precision, form)
    assert w_err <= w_bound and p_err <= p_bound, (w_err, p_err)
    assert c.counters() == ref.filter.counters.as_dict()
    expected = min(theta_true, 2.5)
    assert abs(float(c.W[N_PHI]) - expected) < 0.05


@pytest.mark.parametrize(("precision", "form"), FILTER_CASES)
@pytest.mark.parametrize("guard", ["trace-reset", "eig-floor", "weight-clip", "no-eig-check"])
def test_the_c_filter_s_guards_act_as_the_reference_s(precision: str, form: str,
                                                      guard: str) -> None:
    ekf = GUARDS[guard]
    ref, c, w_err, p_err = _run_filters(precision, form, ekf, 1.3, 2000, np.zeros(N_PHI))
    print(f"{precision} {form} {guard}: |ΔW| {w_err:.3g}, |ΔP| {p_err:.3g} of scale")
    w_bound, p_bound = _filter_bounds(precision, form)
    assert w_err <= w_bound and p_err <= p_bound, (w_err, p_err)
    counts = c.counters()
    assert counts == ref.filter.counters.as_dict()
    acted = {"trace-reset": "trace_resets", "eig-floor": "eig_repairs",
             "weight-clip": "weight_clips", "no-eig-check": "eig_repairs"}[guard]
    # the UD form has no eigenvalue floor; without the periodic check neither form repairs
    if guard == "no-eig-check" or (guard == "eig-floor" and form == "ud"):
        assert counts[acted] == 0
    else:
        assert counts[acted] > 0
    assert 0.4 <= float(c.W[N_PHI]) <= 2.5


@pytest.mark.parametrize("f32", [False, True], ids=["float64", "float32"])
@pytest.mark.parametrize("form", ["standard", "ud"])
def test_a_rejected_update_changes_nothing_and_reset_is_the_cold_start(f32: bool,
                                                                       form: str) -> None:
    c = CFilter(f32, replace(EKF, form=form), np.full(N_PHI, 0.01))
    phi, u, y = closed_loop_data(1.3, 50, seed=2)
    for k in range(50):
        c.update(phi[k], float(u[k]), float(y[k]))
    w, p = c.W.copy(), c.P.copy()
    bad_phi = phi[0].copy()
    bad_phi[3] = np.inf
    for args in ((phi[0], float("nan"), 0.01), (phi[0], 0.0, float("inf")), (bad_phi, 0.0, 0.0)):
        assert not c.update(*args)
        assert np.array_equal(c.W, w) and np.array_equal(c.P, p)
    assert c.counters()["rejected"] == 3
    c.m.lib.rh_yaw_gain_reset(c.g)
    assert float(c.W[N_PHI]) == 1.0 and np.all(c.W[:N_PHI] == c.dt(0.01))
    P = c.P
    assert P[N_PHI, N_PHI] == pytest.approx(0.1) and not np.any(P[N_PHI, :N_PHI])
    assert np.all(np.diag(P)[:N_PHI] == c.dt(EKF.p0))
    assert c.counters()["rejected"] == 0


@pytest.mark.parametrize("f32", [False, True], ids=["float64", "float32"])
@pytest.mark.parametrize("form", ["standard", "ud"])
@pytest.mark.parametrize("case", ["overflow", "non-positive"])
def test_an_unusable_innovation_variance_is_rejected_as_by_the_reference(
        f32: bool, form: str, case: str) -> None:
    """A finite regressor whose h' P h overflows (φ at 1e200, or 1e30 in float), and a
    non-positive variance (R = −1 with h = 0): rejected, nothing changed, as the reference."""
    dt = np.float32 if f32 else np.float64
    ekf = replace(EKF, form=form)
    phi, u, e = np.zeros(N_PHI), 0.0, 0.01
    if case == "overflow":
        phi[:] = 1e30 if f32 else 1e200
    else:
        ekf = replace(ekf, r=(1e-4, 1e-4, -1.0))
    ref = YawGainFilter(N_PHI, ekf, np.zeros(N_PHI), 0.1, 0.4, 2.5, dtype=dt)
    c = CFilter(f32, ekf, np.zeros(N_PHI))
    w, p = c.W.copy(), c.P.copy()
    with np.errstate(over="ignore"):   # the reference's h' P h overflows, as intended
        assert not ref.update(phi.astype(dt), u, e)
    assert not c.update(phi, u, e)
    assert np.array_equal(c.W, w) and np.array_equal(c.P, p)
    assert c.counters() == ref.filter.counters.as_dict() and c.counters()["rejected"] == 1


def _spd_with_small_eigenvalues(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    lam = np.geomspace(1e-7, 1.0, n)
    P = (q * lam) @ q.T
    return 0.5 * (P + P.T)


@pytest.mark.parametrize("n", [15, 16])
def test_the_eigenvalue_floor_of_either_size_equals_the_reference(n: int) -> None:
    """rh_ekf_floor_spd (ekf.c, the state EKF's 15 and the joint filter's 16) against
    BatchedEkf.enforce_spd (numpy's eigh): equal to 1e-12 of the scale; a covariance above
    the floor is left bit for bit; a non-finite one becomes p0 I; a size outside 1..16 is
    refused (0, untouched). rh_ekf_jacobi_eig (15 × 15): the eigen-decomposition."""
    m = core_module(False)
    ffi, lib = m.ffi, m.lib
    floor, p0 = 1e-4, 2.0
    P = _spd_with_small_eigenvalues(n, seed=n)
    ref = BatchedEkf(1, n, EkfConfig(p0=p0, r=(1e-2,), zeta=(1.0,), p_floor=floor))
    ref.P[0] = P
    assert ref.enforce_spd() == 1
    buf = P.copy()
    ptr = ffi.cast("real_t *", ffi.from_buffer(buf))
    assert lib.rh_ekf_floor_spd(ptr, n, floor, p0) == 1
    np.testing.assert_allclose(buf, ref.P[0], rtol=0, atol=1e-12)
    assert np.min(np.linalg.eigvalsh(buf)) >= floor * (1 - 1e-9)
    above = buf.copy()
    assert lib.rh_ekf_floor_spd(ptr, n, floor * 0.5, p0) == 0
    assert np.array_equal(buf, above)
    for bad_n in (0, 17):
        assert lib.rh_ekf_floor_spd(ptr, bad_n, floor, p0) == 0
        assert np.array_equal(buf, above)
    buf[1, 2] = buf[2, 1] = np.nan
    assert lib.rh_ekf_floor_spd(ptr, n, floor, p0) == 1
    assert np.array_equal(buf, p0 * np.eye(n))
    if n == 15:
        A = _spd_with_small_eigenvalues(15, seed=3)
        V, lam = np.zeros((15, 15)), np.zeros(15)
        sweeps = lib.rh_ekf_jacobi_eig(ffi.cast("real_t *", ffi.from_buffer(A)),
                                       ffi.cast("real_t *", ffi.from_buffer(V)),
                                       ffi.cast("real_t *", ffi.from_buffer(lam)))
        assert 1 <= sweeps <= lib.RH_EKF_JACOBI_SWEEPS
        np.testing.assert_allclose(np.sort(lam), np.linalg.eigvalsh(A), rtol=0, atol=1e-14)
        np.testing.assert_allclose(A @ V, V * lam, rtol=0, atol=1e-14)


@pytest.mark.parametrize(("p0", "lo", "hi"), [(-0.1, 0.4, 2.5), (float("nan"), 0.4, 2.5),
                                              (float("inf"), 0.4, 2.5),
                                              (0.0, 0.4, 2.5), (0.1, 0.0, 2.5),
                                              (0.1, 1.2, 2.5), (0.1, 0.4, 0.9)])
def test_the_filter_refuses_a_bad_configuration(p0: float, lo: float, hi: float) -> None:
    """rh_yaw_gain_init (p0 = 0 is the model's "off", never an active filter), and through
    rh_ctrl_init: code -1 (the Python side refuses these before; the core must not run on
    them if handed them). p0 = 0 through rh_ctrl_init is the feature off."""
    assert CFilter(False, EKF, np.zeros(N_PHI), p0, lo, hi).rc == -1
    for f32 in (False, True):
        module = core_module(f32)
        toml = load_controller_config()
        cfg = ctrl_config("nmpc-rhonn", toml, module)
        cfg.rhonn_dm_gain.dm_gain_p0, cfg.rhonn_dm_gain.dm_gain_min = p0, lo
        cfg.rhonn_dm_gain.dm_gain_max = hi
        if p0 == 0.0:
            assert NativeController("nmpc-rhonn", toml, module, cfg).model.dm_gain_on is False
        else:
            with pytest.raises(ValueError, match=r"code -1"):
                NativeController("nmpc-rhonn", toml, module, cfg)


# ------------------------------------------------------------------ the whole step
def _dm_path(tmp: Path, precision: str, handling: str = "", keys: str = DM_GAIN) -> str:
    base = Path(_path(tmp, precision, handling=handling))
    p = base.with_name(f"{base.stem}-dm{abs(hash(keys))}.toml")
    p.write_text(set_toml_keys(base.read_text(), "[rhonn]", keys))
    return str(p)


def _run_theta(c: Any, seq: list[ControllerInputs]) -> tuple[tuple[np.ndarray, np.ndarray],
                                                              np.ndarray]:
    """run(c, seq, hold=1) and θ after every MPC step."""
    reals, ints, theta = [], [], []
    for inp in seq:
        r, i = run(c, [inp], hold=1)
        reals.append(r)
        ints.append(i)
        theta.append(c.model.theta)
    return (np.concatenate(reals), np.concatenate(ints)), np.array(theta)


def _conditioning(path: str, seq: list[ControllerInputs],
                  ref: tuple[tuple[np.ndarray, np.ndarray], np.ndarray],
                  precision: str) -> tuple[np.ndarray, float]:
    """test_native_core.conditioning_bound with θ: the reference's largest spread over
    SPREAD_SEEDS one-ulp input and QP-data perturbations, per output signal and for θ,
    × SPREAD_FACTOR (float64, ulp 2⁻⁵², floors 1e-12 and THETA_BOUND) or × F32_SPREAD_FACTOR
    (float32, ulp 2⁻²³, floors BOUND_F32 and THETA_BOUND), as the core's tests bound
    sequences whose own rounding spread is large."""
    f32 = precision == "float32"
    ulp, factor = (2.0**-23, F32_SPREAD_FACTOR) if f32 else (2.0**-52, SPREAD_FACTOR)
    (ra, _), th = ref
    spread, th_spread = np.zeros(ra.shape[1]), 0.0
    for seed in range(SPREAD_SEEDS):
        for c, s in ((make_controller("nmpc-rhonn", path, backend="numpy"),
                      perturbed(seq, seed, ulp)),
                     (qp_data_perturbed(make_controller("nmpc-rhonn", path, backend="numpy"),
                                        seed, ulp), seq)):
            (rp, _), tp = _run_theta(c, s)
            spread = np.maximum(spread, scale_errors(ra, rp))
            th_spread = max(th_spread, float(np.max(np.abs(tp - th))))
    print(f"{precision} reference's own spread: outputs ≤ {np.max(spread):.3g} of scale, "
          f"θ {th_spread:.3g}")
    return (np.maximum(factor * spread, BOUND_F32 if f32 else 1e-12),
            max(factor * th_spread, THETA_BOUND[precision]))


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> list[ControllerInputs]:
    return awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path_factory.mktemp("rec")),
                          absurd=False)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_step_with_the_learned_gain_equals_the_reference(
        precision: str, sequence: list[ControllerInputs], tmp_path: Path) -> None:
    seq = _f32_safe(sequence) if precision == "float32" else sequence
    path = _dm_path(tmp_path, precision)
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    assert type(nat).__name__ == "NativeController" and nat.model.dm_gain_on
    ra, th_a = _run_theta(ref, seq)
    rb, th_b = _run_theta(nat, seq)
    # θ moved: the comparison is of a learning filter, not of a constant 1
    assert np.max(np.abs(th_a - 1.0)) > 0.05
    # the jerk-weight QP carries OSQP's termination spread into the learning, θ too
    bound, th_bound = _conditioning(path, seq, (ra, th_a), precision)
    np.testing.assert_allclose(th_b, th_a, rtol=0, atol=th_bound)
    worst = assert_close(ra, rb, bound, 0.0 if precision == "float64" else F32_ITERATION_SLACK)
    print(f"{precision}: θ C − numpy {np.max(np.abs(th_b - th_a)):.3g} (bound {th_bound:.3g}),"
          f" outputs {worst:.3g} of scale (bound {np.min(bound):.3g}..{np.max(bound):.3g})")
    # the learned gain changes what the controller does (against the feature off)
    off = run(make_controller("nmpc-rhonn", _path(tmp_path, precision), backend="native"),
              seq, hold=1)
    assert np.nanmax(np.abs(off[0] - rb[0])) > 1.0


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_learned_gain_state_equals_the_reference(
        precision: str, sequence: list[ControllerInputs], tmp_path: Path) -> None:
    """On the move-weight QP (no solver spread): outputs to BOUND_DEFAULT (float64), θ, the
    joint filter's W and P, the weights, and both filters' counters."""
    seq = _f32_safe(sequence) if precision == "float32" else sequence
    path = _dm_path(tmp_path, precision, handling=TIGHT_HANDLING)
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    ra, th_a = _run_theta(ref, seq)
    rb, th_b = _run_theta(nat, seq)
    if precision == "float64":
        bound, th_bound = BOUND_DEFAULT, THETA_BOUND[precision]
    else:
        bound, th_bound = _conditioning(path, seq, (ra, th_a), precision)
    np.testing.assert_allclose(th_b, th_a, rtol=0, atol=th_bound)
    worst = assert_close(ra, rb, bound, 0.0 if precision == "float64" else F32_ITERATION_SLACK)
    print(f"{precision} move-weight QP: θ C − numpy {np.max(np.abs(th_b - th_a)):.3g}, "
          f"outputs {worst:.3g} of scale")
    sa, sb = ref.get_state(), nat.get_state()
    assert sa.keys() == sb.keys() and "rhonn.dm_gain.W" in sb
    tol = 1e-9 if precision == "float64" else 1e-3
    for k in ("rhonn.W", "rhonn.P", "rhonn.dm_gain.W", "rhonn.dm_gain.P", "rhonn.rec_u"):
        a, b = np.asarray(sa[k], float), np.asarray(sb[k], float)
        np.testing.assert_allclose(b, a, rtol=0, atol=tol * max(float(np.max(np.abs(a))), 1e-9),
                                   err_msg=k)
    # the joint filter owns the yaw row
    np.testing.assert_array_equal(np.asarray(sb["rhonn.W"])[2],
                                  np.asarray(sb["rhonn.dm_gain.W"])[0, :N_PHI])
    assert nat.model.counters.as_dict() == ref.model.ekf.counters.as_dict()
    g = nat.model
    assert {n: int(getattr(g._m.dm_gain.counters, n)) for n in ref.model.dm_gain.filter
            .counters.as_dict()} == ref.model.dm_gain.filter.counters.as_dict()


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_restore_and_reset_with_the_learned_gain_follow_the_reference(
        precision: str, sequence: list[ControllerInputs], tmp_path: Path) -> None:
    """A native controller restored mid-run from the reference's get_state (θ, the joint
    filter's W and P, the pending u) continues like the reference restored from it; reset()
    returns both to θ = 1 and the cold start."""
    seq = _f32_safe(sequence)
    path = _dm_path(tmp_path, precision, handling=TIGHT_HANDLING)
    src = make_controller("nmpc-rhonn", path, backend="numpy")
    run(src, seq[:170])
    snap = src.get_state()
    assert abs(src.model.theta - 1.0) > 0.01
    outs, thetas = [], []
    for backend in ("numpy", "native"):
        c = make_controller("nmpc-rhonn", path, backend=backend)
        run(c, seq[:40])
        c.set_state(snap)
        thetas.append(c.model.theta)
        a = run(c, seq[170:])
        c.reset()
        assert c.model.theta == 1.0
        b = run(c, seq[:120])
        outs.append((a, b))
    assert thetas[1] == pytest.approx(thetas[0], abs=THETA_BOUND[precision])
    bound = BOUND_F32 if precision == "float32" else BOUND_DEFAULT
    slack = F32_ITERATION_SLACK if precision == "float32" else 0.0
    assert_close(outs[0][0], outs[1][0], bound, slack)
    assert_close(outs[0][1], outs[1][1], bound, slack)


def test_a_restored_non_finite_u_is_refused_by_the_joint_filter_as_by_the_reference(
        sequence: list[ControllerInputs], tmp_path: Path) -> None:
    """A checkpoint whose pending u is NaN: the state EKF learns from the next step, the joint
    filter rejects it (counted), θ stays, and the yaw row keeps the state EKF's update, in the
    core as in the reference."""
    path = _dm_path(tmp_path, "float64", handling=TIGHT_HANDLING)
    src = make_controller("nmpc-rhonn", path, backend="numpy")
    run(src, sequence[:100])
    snap = src.get_state()
    snap["rhonn.rec_u"] = float("nan")
    after = []
    for backend in ("numpy", "native"):
        c = make_controller("nmpc-rhonn", path, backend=backend)
        c.set_state(snap)
        theta, w = c.model.theta, np.array(c.model.W, float)
        c.step(sequence[100])
        assert c.model.theta == theta
        assert not np.array_equal(np.array(c.model.W, float)[2], w[2])   # the EKF's update
        counters = (c.model.dm_gain.filter.counters.as_dict() if backend == "numpy" else
                    {n: int(getattr(c.model._m.dm_gain.counters, n)) for n in
                     ("updates", "rejected")})
        after.append((np.array(c.model.W, float), counters["rejected"], counters["updates"]))
    np.testing.assert_allclose(after[1][0], after[0][0], rtol=0, atol=1e-12)
    assert after[1][1:] == after[0][1:] == (1, 0)


def test_native_checkpoint_round_trip_and_copies_with_the_learned_gain(
        sequence: list[ControllerInputs], tmp_path: Path) -> None:
    """The checkpoint file holds the joint filter's state bit for bit and a fresh native
    controller restores it (θ and the ΔM gains with it); a deepcopy runs on bit for bit."""
    path = _dm_path(tmp_path, "float64")
    a = make_controller("nmpc-rhonn", path, backend="native")
    run(a, sequence[:120])
    ckpt = tmp_path / "c.npz"
    cfg_hash = config_hash("nmpc-rhonn", path)
    save_checkpoint(ckpt, a, cfg_hash=cfg_hash, steps=120)
    _, data = read_checkpoint(ckpt)
    state = a.get_state()
    for k in ("rhonn.dm_gain.W", "rhonn.dm_gain.P", "rhonn.rec_u"):
        assert np.array_equal(np.asarray(data[k]), np.asarray(state[k])), k
    b = make_controller("nmpc-rhonn", path, backend="native")
    assert load_checkpoint(ckpt, b, cfg_hash=cfg_hash).restored
    assert b.model.theta == a.model.theta != 1.0
    # the ΔM gains follow θ at once (the QP's b_prev from them at the next step)
    assert (b.model._m.kd_now, b.model._m.kd_prev) == (a.model._m.kd_now, a.model._m.kd_prev)
    for k in ("rhonn.dm_gain.W", "rhonn.dm_gain.P", "rhonn.rec_u", "rhonn.W"):
        assert np.array_equal(np.asarray(b.get_state()[k]), np.asarray(state[k])), k
    d = copy.deepcopy(a)
    r1, r2 = run(a, sequence[120:200]), run(d, sequence[120:200])
    assert np.array_equal(r1[0], r2[0], equal_nan=True) and a.model.theta == d.model.theta


# ------------------------------------------------------------------ across processes
def test_the_controller_process_learns_the_gain_in_the_c_core_and_checkpoints_it(
        tmp_path: Path) -> None:
    """A closed-loop run (plant and controller processes over the bus) with dm_gain_p0 = 0.1:
    the controller process runs the C core, its checkpoint holds a θ that moved, and the
    numpy reference and a native controller in this process both restore it."""
    ckpt = tmp_path / "learned.npz"
    result = run_and_report(RunSpec(
        scenario="step-steer", controller="nmpc-rhonn", out_dir=tmp_path / "run",
        duration_s=4.0, controller_overrides=(("rhonn.dm_gain_p0", 0.1),),
        controller_extra_args=("--checkpoint", str(ckpt)), make_plots=False, make_rrd=False))
    assert result.reason == "finished" and result.controller_code == 0
    summary = json.loads((tmp_path / "run" / "controller_summary.json").read_text())
    assert summary["backend"] == "native"
    header, data = read_checkpoint(ckpt)
    theta = float(np.asarray(data["rhonn.dm_gain.W"])[0, N_PHI])
    assert 0.4 <= theta <= 2.5 and theta != 1.0
    print(f"θ learned in the controller process: {theta:.4f}")
    cfg_path = tmp_path / "dm.toml"
    cfg_path.write_text(set_toml_keys(Path(_path(tmp_path, "float64")).read_text(), "[rhonn]",
                                      DM_GAIN))
    for backend in ("numpy", "native"):
        c = make_controller("nmpc-rhonn", str(cfg_path), backend=backend)
        res = load_checkpoint(ckpt, c, cfg_hash=header["config_hash"])
        assert res.restored, res.reason
        assert c.model.theta == pytest.approx(theta, abs=1e-12)
