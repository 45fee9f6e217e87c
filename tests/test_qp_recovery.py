"""The MPC's QP recovers from unusable data in one step, in the numpy reference and in the
C core alike: absurd envelope data are refused before OSQP sees them, and a failed solve
clears OSQP's iterate so that no NaN is warm-started into later solves. Tests of OSQP's own
failure paths run with ``unconstrained_first = false`` (every QP handed to OSQP)."""

from __future__ import annotations

import copy
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs, QpStatus
from controller.core.mpc.qp import QP_MAGNITUDE_LIMIT
from controller.native.backend import core_module
from controller.registry import make_controller
from tests.recorded import awkward_inputs, config_file, recorded_inputs

BACKENDS = ["numpy", pytest.param("native", marks=pytest.mark.skipif(
    core_module(False) is None, reason="the C core is not built"))]


@pytest.fixture(scope="module")
def recorded() -> list[ControllerInputs]:
    return recorded_inputs("nmpc-rhonn")


@pytest.fixture(scope="module")
def osqp_every_step(tmp_path_factory: pytest.TempPathFactory) -> str:
    """default.toml with every QP handed to OSQP (no unconstrained minimiser first)."""
    return config_file(tmp_path_factory.mktemp("osqp"), mpc="unconstrained_first = false")


def _fallbacks(c: object, seq: list[ControllerInputs]) -> np.ndarray:
    with warnings.catch_warnings():   # overflow warnings of the absurd input's arithmetic
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.array([bool(c.step(inp).fallback) for inp in seq])  # type: ignore[attr-defined]


@pytest.mark.parametrize("backend", BACKENDS)
def test_envelope_qp_recovers_on_the_step_after_an_absurd_speed(
        backend: str, recorded: list[ControllerInputs]) -> None:
    """Vx = 1e200 (finite) makes the envelope rows' values ≈ 1e198 and some l > u: that one
    step falls back, every later step solves again (the default configuration has the
    envelope on)."""
    seq = awkward_inputs(recorded, absurd=False)
    k_absurd = next(k for k, i in enumerate(seq) if abs(float(i.vx)) > 1e30)
    c = make_controller("nmpc-rhonn", None, backend=backend)
    assert c.qp.m == 6 * c.qp.N + 2                       # the envelope shape is in use
    fb = _fallbacks(c, seq)
    assert fb[k_absurd]
    assert not fb[k_absurd + 1:].any(), np.nonzero(fb[k_absurd + 1:])[0] + k_absurd + 1
    assert c.qp.fallbacks == int(fb.sum())


@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_nan_warm_start_costs_one_fallback_step(
        backend: str, name: str, recorded: list[ControllerInputs], osqp_every_step: str) -> None:
    """A restored state whose OSQP dual iterate is NaN: the first solve fails (fallback,
    ΔM decays inside the box), OSQP's iterate is cleared, and the following 49 steps solve;
    with the envelope rows (nmpc-rhonn) and without them (lmpc). With the unconstrained
    minimiser first (the default) a step that needs no OSQP warm-starts OSQP afresh: at most
    the first step falls back."""
    for path, first_fails in ((osqp_every_step, True), (None, None)):
        c = make_controller(name, path, backend=backend)
        _fallbacks(c, recorded[:150])
        state = c.get_state()
        state["qp.y"] = np.full(np.shape(state["qp.y"]), math.nan)
        c.set_state(state)
        fb = _fallbacks(c, recorded[150:200])
        if first_fails:
            assert fb[0]
        assert not fb[1:].any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_absurd_qp_data_are_refused_before_osqp(backend: str) -> None:
    """lmpc with a finite but absurd steering angle (1e200 rad): its bicycle references and
    so the QP gradient q are beyond 1e12; the step is a fallback (the data never reach OSQP)
    and the next step solves again."""
    seq = recorded_inputs("lmpc")[:160]
    seq[150] = copy.copy(seq[150])
    seq[150].swa_rad = 1e200
    c = make_controller("lmpc", None, backend=backend)
    fb = _fallbacks(c, seq[:150])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = c.step(seq[150])
    assert out.fallback and out.qp_iterations == 0   # OSQP never ran on these data
    assert not fb.any() and not _fallbacks(c, seq[151:]).any()
    assert c.qp.fallbacks == 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_absurd_hessian_alone_is_refused_before_osqp(
        backend: str, recorded: list[ControllerInputs]) -> None:
    """P = 2GᵀWG + reg grows with the sensitivities G squared, q = −2GᵀW(yd − ȳ) + … only
    linearly, times the free response's tracking error. A restored state whose RHONN weights
    are zero but for one absurd weight (1e8 m/s) on S(ωr) in the Vy increment makes
    ∂Vy/∂ωr ≈ 1.7e8 m/rad and so G's β rows ≈ 5e5 (P ≈ 5e14), while the free response never
    moves ωr: the yaw rate is exactly 0, the warm start ū and the applied ΔM are 0, so
    ωr̄ = 0 along the horizon, Vy stays as measured and q stays ≈ 5e5. The step is a fallback
    on P alone (OSQP never ran, counted); with the learned weights back the next steps solve
    again, in the reference and the core alike."""
    c = make_controller("nmpc-rhonn", None, backend=backend)
    assert not _fallbacks(c, recorded[:150]).any()
    learned = c.get_state()
    absurd = dict(learned)
    w = np.zeros_like(learned["rhonn.W"])
    w[1, 2] = 1e8                     # Vy row, φ₃ = S(ωr): ∂Vy_{k+1}/∂ωr_k = 1e8/0.6 m/rad
    absurd.update({"rhonn.W": w, "rhonn.has_record": 0.0,   # no EKF update on this step
                   "qp.sol": np.zeros_like(learned["qp.sol"]), "qp.zprev": 0.0,
                   "ctrl.dm_prev": 0.0})
    c.set_state(absurd)
    inp = copy.copy(recorded[150])
    inp.yaw_rate = 0.0                # the free response leaves ωr (and Vy) where they are
    out = c.step(inp)
    assert out.fallback and out.qp_iterations == 0   # OSQP never ran on these data
    assert c.qp.fallbacks == 1
    px, q = np.asarray(c.qp.Px, dtype=float), np.asarray(c.qp.q, dtype=float)
    assert np.isfinite(px).all() and np.abs(px).max() > 100.0 * QP_MAGNITUDE_LIMIT
    assert np.isfinite(q).all() and np.abs(q).max() < 1e-3 * QP_MAGNITUDE_LIMIT  # q alone: usable
    restored = c.get_state()          # the fallback's state, with the learned weights back
    restored["rhonn.W"] = learned["rhonn.W"]
    c.set_state(restored)
    assert not _fallbacks(c, recorded[151:170]).any()
    assert c.qp.fallbacks == 1 and c.qp.last_status == QpStatus.SOLVED


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("wheel", range(4))
def test_a_non_finite_wheel_speed_is_an_invalid_input(backend: str, wheel: int) -> None:
    """One NaN wheel speed (any wheel) makes the step an invalid-input step, as any other
    non-finite input does: ΔM held, no QP, counted; the next step runs the QP again."""
    seq = recorded_inputs("nmpc-rhonn")[:160]
    seq[150] = copy.copy(seq[150])
    speeds = np.array(seq[150].wheel_speeds, dtype=float)
    speeds[wheel] = math.nan
    seq[150].wheel_speeds = speeds
    c = make_controller("nmpc-rhonn", None, backend=backend)
    for inp in seq[:150]:
        c.step(inp)
    before = c.invalid_steps
    out = c.step(seq[150])
    assert c.invalid_steps == before + 1
    assert int(out.qp_status) == int(QpStatus.NOT_RUN)
    assert int(c.step(seq[151]).qp_status) != int(QpStatus.NOT_RUN)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_absurd_lateral_acceleration_is_refused_by_the_envelope_rows(backend: str) -> None:
    """nmpc-rhonn with a finite but absurd measured ay (1e200 m/s²) at one step: the
    envelope's look-ahead term lead_s·ay/Vx makes the rear-slip rows' offsets unusable while
    the yaw-rate rows' stay usable; the step is a fallback (the data never reach OSQP), the
    next step solves again, in the reference and the core alike."""
    seq = recorded_inputs("nmpc-rhonn")[:170]
    seq[150] = copy.copy(seq[150])
    seq[150].ay = 1e200
    c = make_controller("nmpc-rhonn", None, backend=backend)
    fb = _fallbacks(c, seq)
    assert fb[150] and not fb[:150].any() and not fb[151:].any(), np.nonzero(fb)[0]
    assert c.qp.fallbacks == 1


@pytest.mark.parametrize("sign", [1.0, -1.0], ids=["positive", "negative"])
def test_a_fallback_clips_the_decayed_dm_to_the_box(sign: float,
                                                    recorded: list[ControllerInputs]) -> None:
    """A restored state with an applied ΔM far outside the box (±1e5 N·m) and a NaN dual
    iterate: the step falls back and its ΔM, fallback_decay·ΔM_prev, is clipped to the box's
    edge (the output is the ΔM the allocation realises from it); the core as the reference:
    status and fallback equal, ΔM to 1e-6 of itself (the box is the motors' capacity times
    the model confidence after 150 learned steps, which the back-to-back tests bound at
    3e-7 of the scale with the packaged QP)."""
    outs = []
    for backend in ("numpy", "native"):
        if backend == "native" and core_module(False) is None:
            pytest.skip("the C core is not built")
        c = make_controller("nmpc-rhonn", None, backend=backend)
        _fallbacks(c, recorded[:150])
        state = c.get_state()
        state["qp.y"] = np.full(np.shape(state["qp.y"]), math.nan)
        state["ctrl.dm_prev"] = sign * 1e5
        c.set_state(state)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            o = c.step(recorded[150])
        outs.append((float(o.delta_m), int(o.qp_status), bool(o.fallback), float(c.dm_held)))
    (dm_ref, st_ref, fb_ref, held_ref), (dm_nat, st_nat, fb_nat, held_nat) = outs
    assert fb_ref and fb_nat and st_ref == st_nat
    assert 0.0 < sign * dm_ref < 1e4            # clipped: far below decay·1e5
    assert abs(dm_nat - dm_ref) <= 1e-6 * abs(dm_ref)
    # the MPC's own command (before the allocation, which would clip it too) is the box's
    # edge: at most the motors' capacity at zero pedal torque, 4 × 450 N·m
    assert 0.0 < sign * held_ref <= 1800.0 + 1e-9
    assert abs(held_nat - held_ref) <= 1e-6 * abs(held_ref)


def test_rate_rows_apart_from_the_box_are_refused_by_osqp(tmp_path: Path) -> None:
    """lmpc with rate-limit rows and no envelope (the previous ΔM is not clipped into the
    box there): a restored applied ΔM of 1e5 N·m puts the rate rows' interval [ΔM_prev ± rate
    step] apart from the box, the QP is infeasible, OSQP says so (a status the core maps to
    a failure) and the step falls back, ΔM clipped to the box; then the QP solves again. The
    core as the reference: statuses, fallbacks and ΔM (to 1e-6 of the scale) over 20 steps."""
    if core_module(False) is None:
        pytest.skip("the C core is not built")
    path = config_file(tmp_path, "rate_limit_nm_per_s = 20000.0")
    seq = recorded_inputs("lmpc")[:170]
    outs = []
    for backend in ("numpy", "native"):
        c = make_controller("lmpc", path, backend=backend)
        _fallbacks(c, seq[:150])
        state = c.get_state()
        state["ctrl.dm_prev"] = 1e5
        c.set_state(state)
        rows = []
        for inp in seq[150:]:
            o = c.step(inp)
            rows.append((float(o.delta_m), int(o.qp_status), bool(o.fallback)))
        outs.append(np.array(rows))
    ref, nat = outs
    assert ref[0, 2] and not ref[1:, 2].any() and 0.0 < ref[0, 0] < 1e4
    np.testing.assert_array_equal(nat[:, 1:], ref[:, 1:])
    assert np.max(np.abs(nat[:, 0] - ref[:, 0])) <= 1e-6 * np.max(np.abs(ref[:, 0]))

