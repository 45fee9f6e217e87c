"""Back-to-back tests of the C core (controller/native) against the numpy reference
(controller/core), the oracle, on recorded closed-loop inputs.

Bounds (per signal, relative to that signal's largest magnitude over the sequence):

* float64: the sequence's own conditioning. The reference is run again on inputs perturbed
  by one ulp (vx, vy, yaw rate × (1 ± 2⁻⁵²), four seeds of signs); the largest spread that
  gives, per signal, is what rounding alone does to this sequence on any CPU or BLAS. The core
  must stay within 20× that spread (floor 1e-12); the tests pass with OpenBLAS forced to its
  Katmai, Nehalem, Haswell and SkylakeX kernels (OPENBLAS_CORETYPE). Measured: C − numpy
  = 0.3–0.5× the spread (nmpc-rhonn 1.0e-11 vs 2.1e-11, nmpc-mf 1.2e-15 vs 4.5e-15, lmpc
  1.3e-15 vs 3.5e-15; nmpc-rhonn with N = 5, a sequence with up to 125 OSQP iterations per
  step, 2.5e-7 vs 5.4e-7). On the default configuration the error must also be ≤ 1e-9.
* float32 (UD EKF), every MPC: 2e-4 of the signal's scale (measured ≤ 4e-5): float32 rounding
  (6e-8) amplified by the learning and by OSQP's termination at eps 1e-5.
QP status and fallback flags must match exactly, and so must OSQP's iteration counts in
float64 on the non-chaotic sequences; in float32 and after the absurd input they may differ
on ≤ 1 % of the steps (a termination check landing on the other side of eps).

The tight bounds hold on sequences that are not chaotic. A finite but absurd Vy of 1e200
drives the EKF's weights to their bound, after which the learning is sensitive to the last
bit: that sequence has its own test (the safety reaction equal, then finite commands).
Inputs that do not fit a float are non-finite to a float32 core, so the float32
comparisons leave them out.
"""

from __future__ import annotations

import copy
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs, QpStatus
from controller.core.registry import load_controller_config
from controller.native.backend import core_module
from controller.native.config import ctrl_config
from controller.native.controller import NativeController
from controller.registry import make_controller
from tests.recorded import awkward_inputs, config_file, recorded_inputs, set_toml_keys

needs_core = pytest.mark.skipif(core_module(False) is None or core_module(True) is None,
                                reason="the C core is not built (no C compiler at install)")
pytestmark = needs_core

SIGNALS = ("T1", "T2", "T3", "T4", "Tt", "dM", "r_ref", "vy_ref", "b_ref", "pred_vx",
           "pred_vy", "pred_r")
BOUND_DEFAULT = 1e-8   # float64 (measured ≤ 7.6e-9 on the move-weight QP and 8.0e-9 as the
                       # packaged design's ceiling, on sequences recorded with it: the envelope
                       # rows' data come from products summed in another order by numpy's
                       # matmul than by the C loops, and OSQP iterates over 6N + 2 rows)
SOLVER_BOUND = 1e-3    # after an OSQP termination check lands apart (see the tests using it)
DIVERGED_BOUND = 1e-2  # ... in an ill-conditioned stretch, fed back through the learning
BOUND_F32 = 5e-4          # measured ≤ 3.3e-4 of T2's scale with the grip estimate, which the
                          # float32 core computes from float32 inputs and the reference from
                          # the float64 ones
F32_SPREAD_FACTOR = 3.0   # float32 sequences whose own rounding spread exceeds BOUND_F32
SPREAD_FACTOR = 20.0
SPREAD_SEEDS = 4


# The packaged ΔM cost is the jerk weight ([handling] jerk_weight): ramps are free, so the QP is
# less well conditioned and OSQP's iterates carry one-ulp differences of its data further
# (measured: C − numpy up to 3.0e-7 of the scale over a whole sequence; the reference itself,
# its QP data moved by one ulp, 8.1e-8–3.0e-6, the conditioning bound's yardstick). The move
# weight's QP instead keeps C and numpy within BOUND_DEFAULT: tests that compare learned state
# or a restore to the last bits run on it.
TIGHT_HANDLING = "move_weight = 1.0\njerk_weight = 0.0"


def _path(tmp: Path, precision: str, mpc: str = "", refs: str = "",
          handling: str = "") -> str:
    ekf = 'form = "ud"' if precision == "float32" else ""
    p = Path(config_file(tmp, f'precision = "{precision}"\n{mpc}', ekf))
    if refs:
        p.write_text(set_toml_keys(p.read_text(), "[references]", refs))
    if handling:   # its own file: config_file names by [mpc] and [rhonn.ekf] only
        q = p.with_name(f"{p.stem}-h{abs(hash(handling))}.toml")
        q.write_text(set_toml_keys(p.read_text(), "[handling]", handling))
        return str(q)
    return str(p)


def _row(o: Any) -> tuple[list[float], list[int]]:
    real = [*o.torques.tolist(), o.total_torque, o.delta_m, o.yaw_rate_ref, o.vy_ref,
            o.beta_ref, *o.model_prediction.tolist()]
    return real, [int(o.qp_status), int(o.qp_iterations), int(bool(o.fallback))]


def run(c: Any, seq: list[ControllerInputs], hold: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Real outputs (rows, 12) and integer outputs (rows, 3) of every step (and of ``hold``
    allocate_only calls after each)."""
    reals, ints = [], []
    for inp in seq:
        r, i = _row(c.step(inp))
        reals.append(r)
        ints.append(i)
        for _ in range(hold):
            r, i = _row(c.allocate_only(inp))
            reals.append(r)
            ints.append(i)
    return np.array(reals, float), np.array(ints)


def scale_errors(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per signal: max |x − y| / max |x| over the rows where x is a number."""
    out = np.zeros(x.shape[1])
    for j in range(x.shape[1]):
        ok = ~np.isnan(x[:, j])
        if ok.any():
            scale = max(float(np.max(np.abs(x[ok, j]))), 1e-12)
            out[j] = float(np.max(np.abs(x[ok, j] - y[ok, j]))) / scale
    return out


def perturbed(seq: list[ControllerInputs], seed: int = 0,
              ulp: float = 2.0**-52) -> list[ControllerInputs]:
    """seq with vx, vy and the yaw rate moved by one ulp (seeded signs; ``ulp`` relative,
    float64's by default)."""
    rng = np.random.default_rng(seed)
    out = []
    for inp in seq:
        q = copy.copy(inp)
        q.wheel_speeds = np.array(inp.wheel_speeds, dtype=float)
        for k in ("vx", "vy", "yaw_rate"):
            setattr(q, k, float(getattr(q, k)) * (1.0 + float(rng.choice([-1, 1])) * ulp))
        out.append(q)
    return out


def qp_data_perturbed(controller: Any, seed: int, ulp: float = 2.0**-52) -> Any:
    """``controller`` (the numpy reference) with every OSQP data update (P, q, l, u) moved by
    one ulp (seeded signs): the rounding by which the C core's QP data differ from numpy's
    (sums in another order), which one-ulp input moves do not reach."""
    rng = np.random.default_rng(seed)
    solver = controller.qp.solver
    update = solver.update

    def moved(**data: Any) -> Any:
        for k in ("q", "Px", "l", "u"):
            if data.get(k) is not None:
                a = np.array(data[k], dtype=float)
                data[k] = a * (1.0 + rng.choice([-1.0, 1.0], a.shape) * ulp)
        return update(**data)

    solver.update = moved
    return controller


def conditioning_bound(name: str, path: str, seq: list[ControllerInputs], hold: int,
                       ref_out: tuple[np.ndarray, np.ndarray], ulp: float = 2.0**-52,
                       factor: float = SPREAD_FACTOR, floor: float = 1e-12) -> np.ndarray:
    """Per-signal bound: ``factor`` × the reference's largest spread over SPREAD_SEEDS
    one-ulp input perturbations and SPREAD_SEEDS one-ulp QP-data perturbations (float64:
    SPREAD_FACTOR, ulp 2⁻⁵², floor 1e-12)."""
    spread = np.zeros(ref_out[0].shape[1])
    for seed in range(SPREAD_SEEDS):
        pert = run(make_controller(name, path, backend="numpy"), perturbed(seq, seed, ulp),
                   hold=hold)
        spread = np.maximum(spread, scale_errors(ref_out[0], pert[0]))
        ref = make_controller(name, path, backend="numpy")
        if getattr(ref, "qp", None) is not None:
            pert = run(qp_data_perturbed(ref, seed, ulp), seq, hold=hold)
            spread = np.maximum(spread, scale_errors(ref_out[0], pert[0]))
    return np.maximum(factor * spread, floor)


def assert_close(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
                 bound: float | np.ndarray, iteration_slack: float = 0.0,
                 status_slack: float = 0.0) -> float:
    """Per-signal scale-relative agreement (NaN where both are NaN); fallback equal; QP status
    equal except solved ↔ solved-inaccurate (both accepted) on at most ``status_slack`` of
    the steps; OSQP iteration counts equal except on at most ``iteration_slack`` of the steps
    (a termination check landing on the other side of eps); returns the worst error."""
    (ra, ia), (rb, ib) = a, b
    assert np.array_equal(np.isnan(ra), np.isnan(rb)), "NaN pattern differs"
    np.testing.assert_array_equal(ia[:, 2], ib[:, 2], err_msg="fallback differs")
    accepted = (int(QpStatus.SOLVED), int(QpStatus.SOLVED_INACCURATE))
    swapped = np.isin(ia[:, 0], accepted) & np.isin(ib[:, 0], accepted)
    other = (ia[:, 0] != ib[:, 0]) & ~swapped
    assert not other.any(), f"QP status differs at steps {np.flatnonzero(other)[:10]}"
    n_swapped = int(np.sum(ia[:, 0] != ib[:, 0]))
    assert n_swapped <= status_slack * len(ia), f"QP status differs on {n_swapped} steps"
    differ = int(np.sum(ia[:, 1] != ib[:, 1]))
    assert differ <= iteration_slack * len(ia), f"iterations differ on {differ} steps"
    errs = scale_errors(ra, rb)
    bounds = np.broadcast_to(np.asarray(bound, dtype=float), errs.shape)
    for name, err, bd in zip(SIGNALS, errs, bounds, strict=True):
        assert err <= bd, f"{name}: scale-relative error {err:.3g} > {bd:.3g}"
    return float(errs.max())


def _f32_safe(seq: list[ControllerInputs]) -> list[ControllerInputs]:
    """The sequence without inputs a float cannot hold (non-finite to a float32 core)."""
    return [i for i in seq if all(abs(float(getattr(i, k))) < 1e30 for k in ("vx", "vy"))]


def test_binding_types_are_the_compiled_ones() -> None:
    """The generated binding's structs have the sizes the compiled core reports."""
    for f32 in (False, True):
        m = core_module(f32)
        sizes = m.ffi.new("int64_t[2]")
        m.lib.rh_ctrl_sizes(sizes)
        assert sizes[0] == m.ffi.sizeof("rh_ctrl_t")
        assert sizes[1] == m.ffi.sizeof("rh_ctrl_config_t")
        assert m.ffi.sizeof("real_t") == (4 if f32 else 8)


@pytest.mark.parametrize("name", ["nmpc-rhonn", "nmpc-mf", "lmpc"])
@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_step_equals_the_numpy_reference(name: str, precision: str,
                                                tmp_path: Path) -> None:
    """Whole steps on recorded inputs with invalid/non-finite inputs spliced in, with
    allocate_only between MPC steps."""
    seq = awkward_inputs(recorded_inputs(name, tmp_path), absurd=False)
    if precision == "float32":
        seq = _f32_safe(seq)
    path = _path(tmp_path, precision)
    ref = make_controller(name, path, backend="numpy")
    nat = make_controller(name, path, backend="native")
    assert type(nat).__name__ == "NativeController"
    ra = run(ref, seq, hold=1)
    if precision == "float32":
        assert_close(ra, run(nat, seq, hold=1), BOUND_F32, iteration_slack=0.01)
    else:
        rb = run(nat, seq, hold=1)
        assert_close(ra, rb, conditioning_bound(name, path, seq, 1, ra))
        # and to the last bits on the well-conditioned move-weight QP (TIGHT_HANDLING)
        tight = _path(tmp_path, precision, handling=TIGHT_HANDLING)
        assert_close(run(make_controller(name, tight, backend="numpy"), seq, hold=1),
                     run(make_controller(name, tight, backend="native"), seq, hold=1),
                     BOUND_DEFAULT)
    assert nat.steps == ref.steps and nat.invalid_steps == ref.invalid_steps
    assert nat.qp.max_iter_hits == ref.qp.max_iter_hits
    assert nat.qp.fallbacks == ref.qp.fallbacks
    assert nat.qp.worst_iterations == ref.qp.worst_iterations


def test_native_after_an_absurd_input_keeps_the_reference_s_safety_reactions(
        tmp_path: Path) -> None:
    """Vy = 1e200 (finite): the QP data are unusable (fallback), the EKF clips its weights,
    and the QP solves again from the next step on. What is tested is the safety reaction:
    up to the first solve after the absurd input, statuses, fallbacks and NaN patterns equal
    and the outputs within SOLVER_BOUND; after it, the learning runs on clipped weights and
    is chaotic in the reference itself (one ulp of one earlier input moves its outputs by
    1.7 of their scale and 64 QP statuses), so there both fall back on the same steps (none),
    command finite torques and ΔM, have the same NaN pattern, and have counted the same
    weight clips up to that first solve (both clip again later)."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=True)
    path = _path(tmp_path, "float64")
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    k = next(j for j, i in enumerate(seq) if abs(float(i.vy)) > 1e30)
    cut = 2 * (k + 2)                    # rows: a step and its allocate_only each
    head = [run(c, seq[:k + 2], hold=1) for c in (ref, nat)]
    clips = (ref.model.ekf.counters.weight_clips, nat.model.counters.weight_clips)
    assert clips[0] == clips[1] >= 1
    tail = [run(c, seq[k + 2:], hold=1) for c in (ref, nat)]
    (ra, ia), (rb, ib) = ((np.vstack([h[0], t[0]]), np.vstack([h[1], t[1]]))
                          for h, t in zip(head, tail, strict=True))
    assert ia[2 * k, 2] == 1             # the absurd step falls back
    assert_close((ra[:cut], ia[:cut]), (rb[:cut], ib[:cut]), SOLVER_BOUND,
                 iteration_slack=0.01)
    np.testing.assert_array_equal(ia[:, 2], ib[:, 2])
    assert not ia[cut:, 2].any()
    assert np.array_equal(np.isnan(ra), np.isnan(rb)), "NaN pattern differs"
    commands = [SIGNALS.index(n) for n in ("T1", "T2", "T3", "T4", "dM")]
    for r in (ra, rb):
        assert np.isfinite(r[cut:, commands]).all()
    assert nat.qp.fallbacks == ref.qp.fallbacks >= 1
    assert ref.model.ekf.counters.weight_clips > clips[0]
    assert nat.model.counters.weight_clips > clips[1]


@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc"])
def test_native_after_a_checkpoint_with_a_nan_applied_dm_equals_the_reference(
        name: str, tmp_path: Path) -> None:
    """set_state with ``ctrl.dm_prev`` = NaN (a checkpoint can carry one): the next step's
    QP takes 0 for the previous ΔM (rate rows, delay state, fallback decay), as the
    reference does; outputs, statuses and fallbacks as the reference's over 20 steps."""
    seq = recorded_inputs(name, tmp_path)[:170]
    path = _path(tmp_path, "float64", handling=TIGHT_HANDLING)
    ref = make_controller(name, path, backend="numpy")
    nat = make_controller(name, path, backend="native")
    assert_close(run(ref, seq[:150]), run(nat, seq[:150]), BOUND_DEFAULT)
    for c in (ref, nat):
        d = c.get_state()
        d["ctrl.dm_prev"] = math.nan
        c.set_state(d)
    assert_close(run(ref, seq[150:]), run(nat, seq[150:]), BOUND_DEFAULT)


@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc"])
def test_native_warm_start_with_neither_iterate_changes_nothing(name: str,
                                                               tmp_path: Path) -> None:
    """The binding's warm_start(x or None, y or None) with both None (with and without the
    envelope rows' slacks) leaves OSQP's iterates as they were: the run continues bit for bit
    as an untouched twin's."""
    seq = recorded_inputs(name, tmp_path)[:170]
    path = _path(tmp_path, "float64")
    a = make_controller(name, path, backend="native")
    b = make_controller(name, path, backend="native")
    run(a, seq[:150])
    run(b, seq[:150])
    b.warm_start(None, None)
    ra, rb = run(a, seq[150:]), run(b, seq[150:])
    assert np.array_equal(ra[0], rb[0], equal_nan=True) and np.array_equal(ra[1], rb[1])


def test_native_at_the_envelope_speed_floor_equals_the_reference(tmp_path: Path) -> None:
    """Vx exactly at the envelope rows' speed floor ([handling] v_min_mps, 5 m/s): the rows
    are on (vx ≥ floor) and their look-ahead divides by the floor itself; outputs as the
    reference's to BOUND_DEFAULT on the move-weight QP, the QP run on those steps."""
    path = _path(tmp_path, "float64", handling=TIGHT_HANDLING)
    floor = load_controller_config(path).handling.v_min_mps
    assert floor == 5.0
    seq = recorded_inputs("nmpc-rhonn", tmp_path)[:170]
    for k in range(150, 156):
        seq[k] = copy.copy(seq[k])
        seq[k].vx = floor
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    ra, rb = run(ref, seq), run(nat, seq)
    assert_close(ra, rb, BOUND_DEFAULT)
    assert np.all(ra[1][150:156, 0] != int(QpStatus.NOT_RUN))


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")
def test_native_refuses_an_overflowing_learning_error_as_the_reference(
        tmp_path: Path) -> None:
    """Vx = 1.7e308 then −1.7e308 (each finite, each step valid): the second step's one-step
    error x − χ overflows to −∞, so the EKF refuses that update (counted in ``rejected``) and
    the model confidence filter is not fed, as in the reference. Counters equal, statuses
    and fallbacks equal over the whole run, outputs within SOLVER_BOUND up to the refused
    step (after it the learning runs on clipped weights, see the absurd-input test)."""
    seq = recorded_inputs("nmpc-rhonn", tmp_path)[:170]
    for k, vx in ((150, 1.7e308), (151, -1.7e308)):
        seq[k] = copy.copy(seq[k])
        seq[k].vx = vx
    path = _path(tmp_path, "float64", handling=TIGHT_HANDLING)
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    (ra, ia), (rb, ib) = run(ref, seq[:151]), run(nat, seq[:151])
    before = ref.model.ekf.counters.rejected
    assert_close(run(ref, seq[151:152]), run(nat, seq[151:152]), SOLVER_BOUND)
    assert ref.model.ekf.counters.rejected == before + 1
    assert_close((ra, ia), (rb, ib), SOLVER_BOUND)
    (ra, ia), (rb, ib) = run(ref, seq[152:]), run(nat, seq[152:])
    np.testing.assert_array_equal(ia[:, 2], ib[:, 2])
    assert np.array_equal(np.isnan(ra), np.isnan(rb)), "NaN pattern differs"
    assert nat.model.counters.as_dict() == ref.model.ekf.counters.as_dict()


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_rhonn_state_and_counters_equal_the_reference(precision: str,
                                                             tmp_path: Path) -> None:
    """Learned weights, covariances, gate, references' state and the EKF counters, on the
    move-weight QP (TIGHT_HANDLING: the closed loop carries no solver rounding spread)."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False)
    if precision == "float32":
        seq = _f32_safe(seq)
    path = _path(tmp_path, precision, handling=TIGHT_HANDLING)
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    run(ref, seq)
    run(nat, seq)
    sa, sb = ref.get_state(), nat.get_state()
    assert sa.keys() == sb.keys()
    tol = 1e-9 if precision == "float64" else 1e-3
    for k in sa:
        a, b = np.asarray(sa[k], float), np.asarray(sb[k], float)
        scale = max(float(np.nanmax(np.abs(a))) if np.isfinite(a).any() else 1.0, 1e-9)
        if k == "qp.slack":   # fractions of a bound, zero to OSQP's tolerance when inactive
            scale = 1e-5 / tol
        np.testing.assert_allclose(b, a, rtol=0, atol=tol * scale, err_msg=k)
    assert nat.model.counters.as_dict() == ref.model.ekf.counters.as_dict()
    inner = getattr(ref.references, "inner", ref.references)   # under a sideslip guard or not
    assert nat.references.not_converged == inner.not_converged


MPC_VARIANTS = {
    "rate-limit": ("rate_limit_nm_per_s = 20000.0", ""),
    # the paper's QP without rate rows (lmpc: no envelope either): box rows only, set again
    # only when the box moves
    "no-rate-rows": ("rate_limit_nm_per_s = 0.0", ""),
    # the same with every QP handed to OSQP: the box, set once, stays in OSQP between solves
    "no-rate-rows-osqp": ("rate_limit_nm_per_s = 0.0\nunconstrained_first = false", ""),
    # every QP to OSQP (no unconstrained minimiser first), stopped at max_iter
    "max-iter": ("delta_m_max_nm = 900.0\nunconstrained_first = false", "max_iter = 6"),
    # one Ruiz pass per data update instead of the template's four (a run-time setting)
    "one-ruiz-pass": ("delta_m_max_nm = 900.0\nunconstrained_first = false", "scaling = 1"),
    "horizon-5": ("horizon = 5\nq_yaw = 100.0\nr_beta = 1000.0", ""),
    "sqp-2": ("sqp_iterations = 2", ""),
    # one stage (the jerk term's second row absent), and a ΔM cap above the motors' capacity
    # (the capacity binds)
    "horizon-1": ("horizon = 1", ""),
    "cap-above-capacity": ("delta_m_max_nm = 1.0e6", ""),
}


@pytest.mark.parametrize("variant", sorted(MPC_VARIANTS))
@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc"])
def test_native_step_in_other_configurations(name: str, variant: str, tmp_path: Path) -> None:
    """Rate-limit rows, a ΔM cap with OSQP stopped at max_iter (hits counted alike), a longer
    horizon (another generated solver) and two SQP rounds."""
    mpc, osqp = MPC_VARIANTS[variant]
    seq = awkward_inputs(recorded_inputs(name, tmp_path), absurd=False)
    path = Path(_path(tmp_path, "float64", mpc))
    if osqp:
        path.write_text(set_toml_keys(path.read_text(), "[mpc.osqp]", osqp))
    ref = make_controller(name, str(path), backend="numpy")
    nat = make_controller(name, str(path), backend="native")
    ra = run(ref, seq, hold=1)
    assert_close(ra, run(nat, seq, hold=1), conditioning_bound(name, str(path), seq, 1, ra))
    assert nat.qp.max_iter_hits == ref.qp.max_iter_hits
    if variant == "max-iter":
        assert nat.qp.max_iter_hits > 10


def test_a_singular_hessian_is_left_to_osqp(tmp_path: Path) -> None:
    """ΔM acting only from the next period (dm_dead_time_s = Ts) and no input, move or jerk
    weight: the last stage's ΔM moves no predicted output, P's ΔM block is singular, the
    Cholesky factor of the unconstrained minimiser stops, and OSQP solves every QP whose box
    leaves ΔM free — in the reference and the core alike, within the sequence's conditioning.
    The start-up steps, whose box is collapsed to 0 N·m (the model not yet confident), have
    their closed form whatever P is: ΔM 0 on exactly those."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False)
    path = Path(_path(tmp_path, "float64", "input_reg = 0.0",
                      handling="jerk_weight = 0.0\nmove_weight = 0.0"))
    path.write_text(set_toml_keys(path.read_text(), "[rhonn]", "dm_dead_time_s = 0.05"))
    ref = make_controller("nmpc-rhonn", str(path), backend="numpy")
    nat = make_controller("nmpc-rhonn", str(path), backend="native")
    ra = run(ref, seq, hold=1)
    assert_close(ra, run(nat, seq, hold=1), conditioning_bound("nmpc-rhonn", str(path), seq, 1, ra))
    steps = ra[1][0::2]                                   # the steps (an allocate_only after each)
    closed = (steps[:, 1] == 0) & (steps[:, 0] == int(QpStatus.SOLVED))
    assert ref.qp.unconstrained_solves == nat.qp.unconstrained_solves == int(closed.sum()) > 0
    assert np.all(ra[0][0::2][closed, SIGNALS.index("dM")] == 0.0)
    assert ref.qp.worst_iterations > 0 and nat.qp.fallbacks == ref.qp.fallbacks


@pytest.mark.parametrize("lead", [0.0, 0.4], ids=["lead-0", "lead-0.4"])
@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_with_the_sideslip_guard_acting(precision: str, lead: float,
                                               tmp_path: Path) -> None:
    """The guard from |β| 0.5°, on β alone and with the look-ahead ([references]
    guard_lead_s = 0.4 s: on β + T·(ay/Vx − ωr)): equal to the reference, and it acted as
    often in both (113 / 167 of 307 steps in float32).

    float64: within the sequence's conditioning, as every float64 case. float32: the guard
    acting from 0.5° makes this sequence much more sensitive than the default one — the
    float32 reference itself moves the torques by 2.1–3.8e-4 (lead 0) and 1.6–2.2e-4 (lead
    0.4) of their scale when vx, vy, ωr are moved by one float32 ulp (2⁻²³, four seeds), more
    than BOUND_F32. So the bound is BOUND_F32 or F32_SPREAD_FACTOR × that spread, whichever is
    larger (measured C − numpy: 2.6e-4 and 1.6e-4, ≈ 0.7× the spread)."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False)
    if precision == "float32":
        seq = _f32_safe(seq)
    path = _path(tmp_path, precision,
                 refs=f'kind = "demand"\nguard_gain_per_s = 2.5\n'
                      f"guard_beta_rad = 0.00873\nguard_lead_s = {lead!r}")
    # the guard's own design: the paper's QP (no envelope rows, no move weight)
    Path(path).write_text(set_toml_keys(Path(path).read_text(), "[handling]",
                                        "envelope = false"))
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    assert type(nat).__name__ == "NativeController"
    assert ref.references.lead_s == lead
    ra, rb = run(ref, seq), run(nat, seq)
    if precision == "float32":
        bound = conditioning_bound("nmpc-rhonn", path, seq, 0, ra, ulp=2.0**-23,
                                   factor=F32_SPREAD_FACTOR, floor=BOUND_F32)
        # OSQP's iteration counts once the guard holds ΔM at its bounds (steps 239–296) are
        # as sensitive as the outputs: 15 of 307 differ by 5–25 iterations with lead 0.4
        # (outputs within 0.14 of the bound), 4 of 307 with every QP handed to OSQP
        assert_close(ra, rb, bound, iteration_slack=0.06)
    else:
        assert_close(ra, rb, conditioning_bound("nmpc-rhonn", path, seq, 0, ra))
    assert nat.references.active_calls == ref.references.active_calls > 10
    assert nat.qp.unconstrained_solves == ref.qp.unconstrained_solves > 0


@pytest.mark.parametrize("kind", ["linear", "algorithm1", "intent", "blend"])
def test_native_with_every_reference_design(kind: str, tmp_path: Path) -> None:
    """Every [references] kind (the ablation designs too) runs on the core and equals the
    reference within the sequence's conditioning. With Algorithm 1 alone the QP saturates ΔM
    and needs 50–60 OSQP iterations around step 200, where a termination check can land on
    the other side of eps: one of four one-ulp perturbations of the reference does that too
    (spread 1.0e-3 of T1's scale, the C core 1.0e-3). Where the core's iteration counts
    differ (≤ 3 % of the steps), the bound is at least DIVERGED_BOUND, so the test does not
    hinge on a perturbation hitting the flip on another machine."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False)
    path = _path(tmp_path, "float64", refs=f'kind = "{kind}"')
    ref = make_controller("nmpc-rhonn", path, backend="numpy")
    nat = make_controller("nmpc-rhonn", path, backend="native")
    assert type(nat).__name__ == "NativeController"
    ra, rb = run(ref, seq), run(nat, seq)
    bound = conditioning_bound("nmpc-rhonn", path, seq, 0, ra)
    if np.any(ra[1][:, 1] != rb[1][:, 1]):
        bound = np.maximum(bound, DIVERGED_BOUND)
    assert_close(ra, rb, bound, iteration_slack=0.03)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_native_reset_and_set_state_mid_run(precision: str, tmp_path: Path) -> None:
    """A native controller restored mid-run from the reference's get_state continues like
    the reference restored from it; reset() returns both to the cold start (on the
    move-weight QP, TIGHT_HANDLING; the jerk weight's restored z₋₂ is in the pickle test)."""
    seq = _f32_safe(awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False))
    path = _path(tmp_path, precision, handling=TIGHT_HANDLING)
    src = make_controller("nmpc-rhonn", path, backend="numpy")
    run(src, seq[:170])
    snap = src.get_state()
    outs = []
    for backend in ("numpy", "native"):
        c = make_controller("nmpc-rhonn", path, backend=backend)
        run(c, seq[:40])
        c.set_state(snap)
        a = run(c, seq[170:])
        c.reset()
        b = run(c, seq[:120])
        outs.append((a, b))
    bound = BOUND_F32 if precision == "float32" else BOUND_DEFAULT
    slack = 0.01 if precision == "float32" else 0.0
    assert_close(outs[0][0], outs[1][0], bound, slack)
    assert_close(outs[0][1], outs[1][1], bound, slack)


@pytest.mark.parametrize("name", ["nmpc-rhonn", "passive"])
def test_native_with_unusable_wheel_speeds_equals_the_reference(name: str,
                                                                 tmp_path: Path) -> None:
    """Wheel speeds that are not numbers (None) make an MPC step invalid
    (ΔM held at zero, allocation on zero speeds) and the passive controller allocate on zero
    speeds, with allocate_only between steps (for passive, the same as a step); a non-finite
    ax or ay is replaced by 0 in the passive allocation. An MPC step whose inputs sum to a
    finite number (ay = −1e308 against vx = vy = 1e308) while vx + vy + r overflows is invalid
    too. Outputs and counters as the
    reference's, to BOUND_DEFAULT on the move-weight QP."""
    seq = recorded_inputs(name if name != "passive" else "lmpc", tmp_path)[:200]
    for k, kw in ((150, {"wheel_speeds": None}), (151, {"wheel_speeds": None}),
                  (160, {"wheel_speeds": None, "ax": math.nan}), (170, {"ay": math.inf})):
        seq[k] = copy.copy(seq[k])
        for key, v in kw.items():
            setattr(seq[k], key, v)
    if name != "passive":   # inputs whose sum is finite while vx + vy + r overflows: invalid
        seq[180] = copy.copy(seq[180])
        seq[180].vx, seq[180].vy, seq[180].ay = 1e308, 1e308, -1e308
    path = _path(tmp_path, "float64", handling=TIGHT_HANDLING)
    ref = make_controller(name, path, backend="numpy")
    nat = make_controller(name, path, backend="native")
    ra, rb = run(ref, seq, hold=1), run(nat, seq, hold=1)
    assert_close(ra, rb, BOUND_DEFAULT)
    if name == "passive":
        assert np.any(ra[0][2 * 150:2 * 152, :4] != 0.0)   # zero speeds still allocate
    else:
        assert nat.invalid_steps == ref.invalid_steps >= 3
        assert np.all(ra[1][2 * 150:2 * 152, 0] == int(QpStatus.NOT_RUN))


@pytest.mark.parametrize("name", ["nmpc-rhonn", "nmpc-mf", "lmpc", "passive"])
def test_native_replay_is_bit_identical_and_deepcopy_runs_on_bit_for_bit(
        name: str, tmp_path: Path) -> None:
    """Two fresh controllers give the same bits; a deepcopy taken mid-run continues with
    exactly the bits of the original (OSQP's workspace pointers relocated)."""
    seq = awkward_inputs(recorded_inputs(name if name != "passive" else "lmpc", tmp_path))
    path = _path(tmp_path, "float64")
    a = make_controller(name, path, backend="native")
    b = make_controller(name, path, backend="native")
    ra, rb = run(a, seq), run(b, seq)
    assert np.array_equal(ra[0], rb[0], equal_nan=True) and np.array_equal(ra[1], rb[1])
    c = make_controller(name, path, backend="native")
    run(c, seq[:150])
    d = copy.deepcopy(c)
    r1, r2 = run(c, seq[150:]), run(d, seq[150:])
    assert np.array_equal(r1[0], r2[0], equal_nan=True) and np.array_equal(r1[1], r2[1])
    assert np.array_equal(r1[0], ra[0][150:], equal_nan=True)


def test_native_pickle_restores_the_checkpoint_state(tmp_path: Path) -> None:
    """pickle carries the configuration and get_state(): learned state equal, and the next
    steps agree with the original within the solver tolerance (OSQP's ρ restarts)."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path), absurd=False)
    c = make_controller("nmpc-rhonn", _path(tmp_path, "float64"), backend="native")
    run(c, seq[:120])
    d = pickle.loads(pickle.dumps(c))
    for k, v in c.get_state().items():
        np.testing.assert_array_equal(np.asarray(d.get_state()[k]), np.asarray(v), err_msg=k)
    r1, r2 = run(c, seq[120:160]), run(d, seq[120:160])
    # N·m / rad/s scale; measured 0.20 N·m at one step: the copy's OSQP restarts its adaptive
    # ρ, and the envelope shape's 6N + 2 rows converge to eps from the other ρ a little apart
    np.testing.assert_allclose(r2[0], r1[0], rtol=0, atol=0.3)


def test_unsupported_configurations_fall_back_to_the_reference_with_a_reason(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A horizon beyond the generated solvers: auto → the numpy reference (logged once with
    the reason); native → an error naming it."""
    path = _path(tmp_path, "float64", "horizon = 12\nq_yaw = 100.0\nr_beta = 1000.0")
    c = make_controller("lmpc", path)
    assert type(c).__name__ == "MpcController"
    assert any("horizon = 12" in r.getMessage() for r in caplog.records)
    with pytest.raises(RuntimeError, match="horizon = 12"):
        make_controller("lmpc", path, backend="native")
    path = _path(tmp_path, "float64")   # OSQP without Ruiz passes: not the generated solver
    Path(path).write_text(set_toml_keys(Path(path).read_text(), "[mpc.osqp]", "scaling = 0"))
    assert type(make_controller("lmpc", path)).__name__ == "MpcController"
    with pytest.raises(RuntimeError, match="scaling = 0"):
        make_controller("lmpc", path, backend="native")


def test_generated_solver_template_uses_the_configured_osqp_settings() -> None:
    """The install generates OSQP with QpConfig's default settings (one source of truth)."""
    from controller.core.mpc.qp import QpConfig
    from controller.native.osqp_gen import TEMPLATE_SETTINGS

    assert QpConfig().osqp == TEMPLATE_SETTINGS


def test_ctrl_config_carries_the_toml(tmp_path: Path) -> None:
    """The packed config holds what the TOML says (a changed key reaches the struct)."""
    from controller.core.registry import load_controller_config

    cfg = load_controller_config(_path(tmp_path, "float64", "q_yaw = 42.0"))
    c = ctrl_config("nmpc-rhonn", cfg)
    assert c.qp.q_yaw[0] == 42.0 and c.qp.horizon == cfg.mpc.horizon
    assert c.rhonn.ekf_form == 0 and c.vehicle.mass_kg == cfg.params.mass_kg


@pytest.mark.parametrize(("field", "value"), [
    ("ts_s", 0.0), ("kind", 99), ("kind", -1),
    ("qp.horizon", 0), ("qp.horizon", 99), ("qp.sqp_iterations", 0),
    ("qp.sqp_iterations", 11), ("qp.u_scale", 0.0), ("qp.u_scale", float("nan")),
    ("qp.scaling", 0)])
def test_the_core_refuses_a_configuration_outside_its_range(field: str, value: float) -> None:
    """The C core's own init checks (rh_ctrl_init, rh_qp_init), one condition at a time: the
    Python side refuses these before, but the core must not run on them if handed them."""
    for float32 in (False, True):
        module = core_module(float32)
        toml = load_controller_config()
        good = ctrl_config("lmpc", toml, module)
        NativeController("lmpc", toml, module, good)  # the unchanged configuration runs
        target = good.qp if field.startswith("qp.") else good
        setattr(target, field.removeprefix("qp."), value)
        with pytest.raises(ValueError, match=r"invalid controller configuration \(code -1\)"):
            NativeController("lmpc", toml, module, good)


@pytest.mark.parametrize(("kind", "field", "value"), [
    (1, "kind", 99), (1, "ay_decay_s", 0.0), (2, "ay_decay_s", 0.0)],
    ids=["unknown-kind", "intent-decay-0", "blend-decay-0"])
def test_the_core_refuses_a_reference_configuration_it_cannot_run(kind: int, field: str,
                                                                  value: float) -> None:
    """rh_refs_init's checks through rh_ctrl_init (nmpc-rhonn with the state-based
    references, intent = 1 or blend = 2; linear would bypass them): an unknown reference
    design, or a non-positive ay decay time (the intent part's check, first in the blend), is
    refused with code -1 (the Python side never hands them over); the unchanged
    configuration runs."""
    for float32 in (False, True):
        module = core_module(float32)
        toml = load_controller_config()
        cfg = ctrl_config("nmpc-rhonn", toml, module)
        cfg.refs.kind = kind
        NativeController("nmpc-rhonn", toml, module, cfg)
        setattr(cfg.refs, field, value)
        with pytest.raises(ValueError, match=r"invalid controller configuration \(code -1\)"):
            NativeController("nmpc-rhonn", toml, module, cfg)


def test_the_core_refuses_an_unknown_ekf_form() -> None:
    """rh_rhonn_model_init's form check (ts is rh_ctrl_init's): an EKF form that is neither
    the standard (0) nor the UD one (1) is refused, both valid ones run."""
    for float32 in (False, True):
        module = core_module(float32)
        for form, ok in ((0, True), (1, True), (7, False)):
            toml = load_controller_config()
            cfg = ctrl_config("nmpc-rhonn", toml, module)
            cfg.rhonn.ekf_form = form
            if ok:
                NativeController("nmpc-rhonn", toml, module, cfg)
            else:
                with pytest.raises(ValueError, match=r"code -1"):
                    NativeController("nmpc-rhonn", toml, module, cfg)


def test_the_core_clamps_a_negative_dead_time_to_zero(tmp_path: Path) -> None:
    """rh_rhonn_model_init clamps T_d to [0, Ts] like the reference's min(max(T_d, 0), Ts);
    the Python side refuses T_d < 0 before, so the core's lower clamp is checked in closed
    form: handed T_d = −0.1 s it runs bit for bit as with T_d = 0."""
    seq = recorded_inputs("nmpc-rhonn", tmp_path)[:120]
    for float32 in (False, True):
        module = core_module(float32)
        rows = []
        for td in (0.0, -0.1):
            toml = load_controller_config()
            cfg = ctrl_config("nmpc-rhonn", toml, module)
            cfg.rhonn.dm_dead_time_s = td
            core = NativeController("nmpc-rhonn", toml, module, cfg)
            rows.append(run(core, seq))
        assert np.array_equal(rows[0][0], rows[1][0], equal_nan=True)
        assert np.array_equal(rows[0][1], rows[1][1])
        assert np.any(rows[0][0][:, SIGNALS.index("dM")] != 0.0)


# [rhonn] keys (with the move-weight QP) at the edges of the model's gate and form: the
# warm-up's step count rounds half to even like Python's round() (2.7 → 3, 2.5 → 2,
# 5.5 → 6 steps at ts = 0.05 s; the quotients are exact in binary), a gate switched off
# (gate_err_hi = 0: confidence 1) and the literal form (eq. 17, its own rollout Jacobian).
GATE_EDGES = {"warmup-2.7": ("gate_warmup_s = 0.135", 3),
              "warmup-2.5": ("gate_warmup_s = 0.125", 2),
              "warmup-5.5": ("gate_warmup_s = 0.275", 6),
              "gate-off": ("gate_err_hi = 0.0", 10),
              "literal": ('form = "literal"', 10),
              # no warm-up (zero steps), no error filter (τ = 0: the last error alone), a
              # dead time beyond Ts (clamped to Ts), and a band so tight the raw confidence
              # goes below 0 (clamped)
              "warmup-0": ("gate_warmup_s = 0.0", 0),
              "tau-0": ("gate_tau_s = 0.0", 10),
              "dead-time-past-ts": ("dm_dead_time_s = 0.08", 10),
              "tight-band": ("gate_err_lo = 0.0\ngate_err_hi = 0.001", 10)}


@pytest.mark.parametrize("case", list(GATE_EDGES))
def test_native_model_gate_and_form_edges_equal_the_reference(case: str,
                                                              tmp_path: Path) -> None:
    """The model confidence (which scales the ΔM box) equals the reference's at every step,
    the outputs within BOUND_DEFAULT of their scale (status and fallback exact), over the
    first 150 recorded steps; the reference's warm-up count is the closed form."""
    keys, gate_n = GATE_EDGES[case]
    base = Path(_path(tmp_path, "float64", handling=TIGHT_HANDLING))
    path = base.with_name(f"{base.stem}-{case}.toml")
    path.write_text(set_toml_keys(base.read_text(), "[rhonn]", keys))
    seq = recorded_inputs("nmpc-rhonn", tmp_path)[:150]
    ref = make_controller("nmpc-rhonn", str(path), backend="numpy")
    nat = make_controller("nmpc-rhonn", str(path), backend="native")
    assert ref.model._gate_n == gate_n
    rows_ref, rows_nat, conf = [], [], []
    for inp in seq:
        rows_ref.append(_row(ref.step(inp)))
        rows_nat.append(_row(nat.step(inp)))
        conf.append((ref.confidence, nat.confidence))
    c = np.array(conf)
    np.testing.assert_allclose(c[:, 1], c[:, 0], rtol=0, atol=1e-9)
    if case == "gate-off":
        assert np.all(c == 1.0)
    elif case == "tight-band":   # the filtered error stays above 1 mrad/s: box shut
        assert np.all(c == 0.0)
    elif case == "tau-0":        # the unfiltered error: from shut straight to open
        assert np.any(c[:, 0] == 0.0) and np.any(c[:, 0] == 1.0)
    elif case != "dead-time-past-ts":
        assert np.any(c[:, 0] == 0.0) and np.any((c[:, 0] > 0.0) & (c[:, 0] < 1.0))
    pack = [(np.array([r for r, _ in rows], float), np.array([i for _, i in rows]))
            for rows in (rows_ref, rows_nat)]
    if case == "dead-time-past-ts":   # ΔM acts only one step late: less well conditioned
        assert_close(pack[0], pack[1],
                     conditioning_bound("nmpc-rhonn", str(path), seq, 0, pack[0]))
    else:
        assert_close(pack[0], pack[1], BOUND_DEFAULT)
