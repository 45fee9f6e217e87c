"""The compiled MPC step (mpc/compiled.py, kernels/step.py) against the generic step.

Whole steps of nmpc-rhonn, nmpc-mf and lmpc in both precisions on recorded closed-loop
inputs with the awkward cases spliced in (NaN and invalid inputs, low speed, the
stability function off, wheel speeds that are not a float64 array, a finite but absurd
speed that makes the QP data unusable → fallback, allocate_only between MPC steps):
the compiled path equals the generic step with the same kernels bit for bit — every
output, every counter, get_state — and the numpy reference within 1e-9 (float64).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import ControllerInputs
from controller.core.kernels import AVAILABLE
from controller.core.mpc.compiled import CompiledStep
from harness.bench.controller_step import set_toml_keys
from tests.test_kernels import config_file, recorded_inputs

needs_numba = pytest.mark.skipif(not AVAILABLE, reason="numba not importable")

VARIANTS = {   # (extra [mpc] lines, extra [rhonn.ekf] lines)
    "float64": ("", ""),
    "float32-ud": ('precision = "float32"', 'form = "ud"'),
    "float32-standard": ('precision = "float32"', ""),
    "float64-ud": ("", 'form = "ud"'),
}
CASES = [("nmpc-rhonn", v) for v in VARIANTS] + [
    (n, v) for n in ("nmpc-mf", "lmpc") for v in ("float64", "float32-ud")]


def _copy(inp: ControllerInputs) -> ControllerInputs:
    out = ControllerInputs(**{k: getattr(inp, k) for k in ControllerInputs.__slots__})
    out.wheel_speeds = np.array(inp.wheel_speeds, dtype=float)
    return out


def awkward_inputs(rec: list[ControllerInputs], absurd: bool = True) -> list[ControllerInputs]:
    """The recorded inputs with edge cases spliced in after the controller acted (absurd:
    also a finite Vy of 1e200, which makes the QP data unusable and drives the EKF's
    weights to their bound)."""
    seq = [_copy(i) for i in rec]
    k = 150

    def at(j: int, **kw: Any) -> None:
        inp = _copy(seq[j])
        for name, v in kw.items():
            setattr(inp, name, v)
        seq.insert(j, inp)

    at(k, vy=math.nan)                              # non-finite input
    at(k + 3, sensors_valid=False)                  # invalid frames
    at(k + 5, yaw_rate=math.inf, sensors_valid=False)
    at(k + 8, vx=2.0)                               # below v_min: no QP
    at(k + 11, stab_enable=False)                   # stability function off
    at(k + 14, vx=1e200)                            # finite, absurd
    if absurd:
        at(k + 15, vy=1e200)                        # → QP data unusable: fallback
    at(k + 17, accel_pedal=math.nan, brake_pedal=0.3)
    at(k + 20, swa_rad=math.nan)
    ws_list = _copy(seq[k + 23])
    ws_list.wheel_speeds = [float(v) for v in ws_list.wheel_speeds]  # generic path
    seq.insert(k + 23, ws_list)
    return seq


def state_of(c: Any) -> dict[str, Any]:
    """Outputs, counters and learned state of an MpcController, as plain values."""
    o, qp, al = c.out, c.qp, c.allocator
    d: dict[str, Any] = {
        "out": [*o.torques.tolist(), o.total_torque, o.delta_m, o.yaw_rate_ref, o.vy_ref,
                o.beta_ref, o.qp_status, o.qp_iterations, o.fallback,
                *o.model_prediction.tolist()],
        "ctrl": [c.steps, c.invalid_steps, float(c.dm_held), float(c.dm_prev),
                 float(c.confidence)],
        "qp": [qp.max_iter_hits, qp.fallbacks, qp.worst_iterations, qp.last_iterations,
               int(qp.last_status), float(qp._lo_last), float(qp._hi_last),
               *qp.sol.tolist(), *qp.l.tolist(), *qp.u.tolist()],
        "alloc": [float(al.tt_applied), float(al.dm_applied), *al.limits.tolist()],
    }
    m = c.model
    if hasattr(m, "ekf"):
        r = c.references
        inner = getattr(r, "inner", r)
        fp, dem = inner.fixed_point, inner.demand
        d["rhonn"] = [m.err_ms, m.learn_steps, m._gate_open, m._has_record,
                      *m.ekf.counters.as_dict().values(), getattr(m.ekf, "_since_eig", 0)]
        d["refs"] = [getattr(r, "active_calls", 0), inner.not_converged, inner.weight_last,
                     fp.rounds_last, fp.cost_last, fp.ay_envelope, dem.ay_envelope,
                     dem._dw_prev]
    for k, v in c.get_state().items():
        d["state." + k] = np.asarray(v, dtype=float).ravel().tolist()
    return d


def run(c: Any, seq: list[ControllerInputs], hold: int = 0) -> tuple[np.ndarray, list]:
    """Step c on seq (with ``hold`` allocate_only calls after each step); the outputs
    (steps, 17) and the state after every 25th step."""
    rows, states = [], []
    for k, inp in enumerate(seq):
        c.step(inp)
        rows.append(state_of(c)["out"])
        for _ in range(hold):
            o = c.allocate_only(inp)
            rows.append([*o.torques.tolist(), o.delta_m])
        if k % 25 == 0:
            states.append(state_of(c))
    return rows, states


def _assert_same(a: Any, b: Any) -> None:
    """Bit-identical (NaN equal to NaN), with the first difference in the message."""
    if a == b:
        return
    if a and isinstance(a[0], list):      # rows of different lengths
        assert len(a) == len(b)
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(np.asarray(x, dtype=float), np.asarray(y, dtype=float),
                                  equal_nan=True), (k, x, y)
        return
    fa = np.asarray(a, dtype=float)
    fb = np.asarray(b, dtype=float)
    assert fa.shape == fb.shape and np.array_equal(fa, fb, equal_nan=True), (a, b)


def _assert_states(sa: list[dict], sb: list[dict]) -> None:
    assert len(sa) == len(sb)
    for x, y in zip(sa, sb, strict=True):
        assert x.keys() == y.keys()
        for k in x:
            try:
                _assert_same(x[k], y[k])
            except AssertionError as e:
                raise AssertionError(f"{k}: {e}") from None


def make(name: str, path: str, compiled: bool, one_call: bool = True) -> Any:
    from controller.registry import make_controller

    c = make_controller(name, path)
    assert isinstance(c.compiled, CompiledStep)
    c.use_compiled(compiled)
    c.compiled.one_call = one_call
    return c


def with_backend(path: str, backend: str) -> str:
    """The config at ``path`` with ``[mpc] qp_backend`` set (skips "embedded" when OSQP's
    generated solver cannot be built here)."""
    p = Path(path)
    out = p.with_name(p.stem + f"-{backend}.toml")
    out.write_text(set_toml_keys(p.read_text(), "[mpc]", f'qp_backend = "{backend}"'))
    if backend == "embedded":
        from controller.core.mpc import osqp_embedded

        try:
            osqp_embedded.compiler()
        except osqp_embedded.EmbeddedBuildError as exc:
            pytest.skip(f"the generated OSQP solver is not available: {exc}")
    return str(out)


@needs_numba
@pytest.mark.parametrize("backend", ["osqp", "embedded"])
@pytest.mark.parametrize(("name", "variant"), CASES)
def test_compiled_step_equals_the_generic_step_bit_for_bit(name: str, variant: str,
                                                           backend: str,
                                                           tmp_path: Path) -> None:
    """backend "osqp": two compiled calls around the Python OSQP round; "embedded": one
    compiled call with OSQP's generated solver inside (the generic step calls the same
    solver through its Python calls)."""
    mpc, ekf = VARIANTS[variant]
    seq = awkward_inputs(recorded_inputs(name, tmp_path))
    path = with_backend(config_file(tmp_path, 'kernels = "numba"\n' + mpc, ekf), backend)
    ra, sa = run(make(name, path, False), seq, hold=2)
    cb = make(name, path, True)
    assert cb.qp.backend == backend
    rb, sb = run(cb, seq, hold=2)
    _assert_same(ra, rb)
    _assert_states(sa, sb)
    st = state_of(cb)
    assert st["ctrl"][1] >= 4                 # invalid steps were seen
    assert st["qp"][1] >= 1                   # the fallback acted
    assert max(abs(r[4]) for r in rb if len(r) > 5) > 100.0   # the MPC acted


@needs_numba
@pytest.mark.parametrize("name", ["nmpc-rhonn", "nmpc-mf", "lmpc"])
def test_compiled_step_equals_the_numpy_reference(name: str, tmp_path: Path) -> None:
    """float64: the compiled path vs the readable numpy path ≤ 1e-9 on every output
    (relative to max(1, |value|)) and equal counters. Without the absurd Vy: the weights
    it leaves at their bound make the loop chaotic, and rounding differences of the
    kernels (1e-16) then grow to 2e-7 (the step-by-step kernels show the same)."""
    seq = awkward_inputs(recorded_inputs(name, tmp_path), absurd=False)
    from controller.registry import make_controller

    make_numpy = make_controller(name, config_file(tmp_path, 'kernels = "numpy"'))
    assert make_numpy.compiled is None
    ref, sref = run(make_numpy, seq)
    fast, sfast = run(make(name, config_file(tmp_path, 'kernels = "numba"'), True), seq)
    a, b = np.array(ref, dtype=float), np.array(fast, dtype=float)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    err = np.abs(np.nan_to_num(a) - np.nan_to_num(b)) / np.maximum(1.0, np.abs(np.nan_to_num(a)))
    assert err.max() <= 1e-9, err.max(axis=0)
    for x, y in zip(sref, sfast, strict=True):
        assert x["ctrl"][:2] == y["ctrl"][:2]
        assert x["qp"][:4] == y["qp"][:4]       # max_iter hits, fallbacks, iterations
        if "rhonn" in x:
            assert x["rhonn"][1:] == y["rhonn"][1:]   # learn steps, gate, record, EKF
            assert x["refs"][:2] == y["refs"][:2]     # guard calls, not converged


@needs_numba
def test_compiled_step_with_the_sideslip_guard_acting(tmp_path: Path) -> None:
    """nmpc-rhonn with the guard from |β| 0.5°: compiled == generic, and the guard acted."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path))
    path = Path(config_file(tmp_path, 'kernels = "numba"'))
    text = set_toml_keys(path.read_text(), "[references]", "guard_beta_rad = 0.00873")
    path = tmp_path / "guard.toml"
    path.write_text(text)
    ca = make("nmpc-rhonn", str(path), False)
    cb = make("nmpc-rhonn", str(path), True)
    ra, sa = run(ca, seq)
    rb, sb = run(cb, seq)
    _assert_same(ra, rb)
    _assert_states(sa, sb)
    assert cb.references.active_calls == ca.references.active_calls > 10


@needs_numba
@pytest.mark.parametrize("variant", ["float64", "float32-ud"])
def test_compiled_replay_is_bit_identical_and_set_state_continues_equal(
        variant: str, tmp_path: Path) -> None:
    """Run to run the compiled path is bit-identical; a controller restored mid-run by
    set_state continues exactly as a generic controller restored from the same state."""
    mpc, ekf = VARIANTS[variant]
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path))
    path = config_file(tmp_path, 'kernels = "numba"\n' + mpc, ekf)
    r1, _ = run(make("nmpc-rhonn", path, True), seq)
    src = make("nmpc-rhonn", path, True)
    r2, _ = run(src, seq[:170])
    _assert_same(r1[:170], r2)
    snap = src.get_state()
    rest = []
    for compiled in (False, True):
        c = make("nmpc-rhonn", path, compiled)
        c.set_state(snap)
        rest.append(run(c, seq[170:]))
    _assert_same(rest[0][0], rest[1][0])
    _assert_states(rest[0][1], rest[1][1])


@needs_numba
def test_reset_then_compiled_steps_equal_the_generic_ones(tmp_path: Path) -> None:
    """reset() between two runs: the compiled path still equals the generic step."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path))[:120]
    path = config_file(tmp_path, 'kernels = "numba"')
    res = []
    for compiled in (False, True):
        c = make("nmpc-rhonn", path, compiled)
        run(c, seq)
        c.reset()
        res.append(run(c, seq))
    _assert_same(res[0][0], res[1][0])
    _assert_states(res[0][1], res[1][1])


MPC_VARIANTS = {   # [mpc] lines exercising the other branches of the compiled step
    "rate-limit": "rate_limit_nm_per_s = 20000.0",
    "cap": "delta_m_max_nm = 900.0",
    "horizon-5": "horizon = 5\nq_yaw = 100.0\nr_beta = 1000.0",
}


@needs_numba
@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("mpc", sorted(MPC_VARIANTS))
@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc"])
def test_compiled_step_equals_the_generic_step_in_other_configurations(
        name: str, mpc: str, precision: str, tmp_path: Path) -> None:
    """Rate limit (rows beyond the box), a ΔM cap below the motor capacity (in float32 the
    cap is then a Python float, not a float32 scalar), a longer horizon, and OSQP's
    max_iter hit: compiled == generic bit for bit."""
    seq = awkward_inputs(recorded_inputs(name, tmp_path))
    lines = f'kernels = "numba"\nprecision = "{precision}"\n{MPC_VARIANTS[mpc]}'
    path = Path(config_file(tmp_path, lines, 'form = "ud"' if precision == "float32" else ""))
    if mpc == "cap":   # and OSQP stopped early: the max_iter hits are counted alike
        path.write_text(set_toml_keys(path.read_text(), "[mpc.osqp]", "max_iter = 6"))
    ca = make(name, str(path), False)
    cb = make(name, str(path), True)
    ra, sa = run(ca, seq, hold=1)
    rb, sb = run(cb, seq, hold=1)
    _assert_same(ra, rb)
    _assert_states(sa, sb)
    if mpc == "cap":
        assert cb.qp.max_iter_hits == ca.qp.max_iter_hits > 0
        assert max(abs(r[4]) for r in rb if len(r) > 5) <= 900.0 + 1e-9


@needs_numba
@pytest.mark.parametrize(("name", "variant"), [("nmpc-rhonn", "float64"),
                                               ("nmpc-rhonn", "float32-ud"),
                                               ("nmpc-mf", "float64"), ("lmpc", "float32-ud")])
def test_one_compiled_call_equals_the_two_call_path(name: str, variant: str,
                                                    tmp_path: Path) -> None:
    """On the generated solver: one compiled call (solver inside) == pre, the solver's
    Python round, post — bit for bit, incl. set_state mid-run and reset."""
    mpc, ekf = VARIANTS[variant]
    seq = awkward_inputs(recorded_inputs(name, tmp_path))
    path = with_backend(config_file(tmp_path, 'kernels = "numba"\n' + mpc, ekf), "embedded")
    res = []
    for one in (False, True):
        c = make(name, path, True, one_call=one)
        r1 = run(c, seq[:170], hold=1)
        snap = c.get_state()
        c.reset()
        c.set_state(snap)
        r2 = run(c, seq[170:], hold=1)
        res.append((r1, r2))
    for k in range(2):
        _assert_same(res[0][k][0], res[1][k][0])
        _assert_states(res[0][k][1], res[1][k][1])


@needs_numba
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_spd_clear_never_skips_a_repair_enforce_spd_would_make(dtype: type) -> None:
    """kernels.step.spd_clear lets the compiled step skip BatchedEkf.enforce_spd (three
    eigh, ≈ 150 µs, every eig_check_every updates: half of nmpc-rhonn's slowest 1 % of
    steps, measured) only when that changes nothing. Seeded P with smallest eigenvalues from
    far above to below the floor, and non-finite ones."""
    from controller.core.kernels.step import spd_clear
    from controller.core.learning.ekf import BatchedEkf, EkfConfig

    rng = np.random.default_rng(5)
    cfg = EkfConfig()
    margin = 1e-5 if dtype == np.float32 else 1e-9
    cleared = 0
    for k in range(600):
        ekf = BatchedEkf(3, 15, cfg, dtype=dtype)
        for i in range(3):
            q, _ = np.linalg.qr(rng.normal(size=(15, 15)))
            lam = 10.0 ** rng.uniform(-6 if dtype == np.float64 else -2, 0, 15)
            if rng.uniform() < 0.2:                              # around the floor
                lam[0] = cfg.p_floor * 10.0 ** rng.uniform(-3, 3)
            ekf.P[i] = ((q * lam) @ q.T).astype(dtype)
            ekf.P[i] = 0.5 * (ekf.P[i] + ekf.P[i].T)
        if k % 50 == 0:
            ekf.P[k % 3, 2, 2] = np.nan
        before = ekf.P.copy()
        ok = spd_clear(ekf.P, cfg.p_floor, margin, np.zeros(225))
        assert np.array_equal(ekf.P, before, equal_nan=True)     # spd_clear only reads
        if ok:
            cleared += 1
            assert ekf.enforce_spd() == 0
            assert np.array_equal(ekf.P, before)
    assert 100 < cleared < 550, cleared    # both outcomes were exercised


@needs_numba
def test_compiled_step_equals_generic_when_the_eigenvalue_floor_repairs(
        tmp_path: Path) -> None:
    """A floor so high that enforce_spd repairs P: the compiled step sees it cannot skip
    the repair and runs it; compiled == generic bit for bit, repairs counted alike."""
    seq = awkward_inputs(recorded_inputs("nmpc-rhonn", tmp_path))[:200]
    path = config_file(tmp_path, 'kernels = "numba"', "p_floor = 1e-4\neig_check_every = 7")
    ca, cb = make("nmpc-rhonn", path, False), make("nmpc-rhonn", path, True)
    ra, sa = run(ca, seq)
    rb, sb = run(cb, seq)
    _assert_same(ra, rb)
    _assert_states(sa, sb)
    rep = cb.model.ekf.counters.eig_repairs
    assert rep == ca.model.ekf.counters.eig_repairs and rep > 0


@needs_numba
def test_the_address_table_follows_the_solver_and_refuses_buffers_it_would_misread(
        tmp_path: Path) -> None:
    """The one-call kernels read the buffers through raw addresses (kernels.step T_*):
    after reset() (a new generated solver) the table names the new solver and its x/y
    buffers, and a buffer of another dtype or layout is refused, never misread."""
    from controller.core.kernels import step as ks

    seq = recorded_inputs("nmpc-rhonn", tmp_path)[:5]
    path = with_backend(config_file(tmp_path, 'kernels = "numba"'), "embedded")
    c = make("nmpc-rhonn", path, True)
    cs = c.compiled
    run(c, seq)
    old = cs._addr
    c.reset()
    run(c, seq)
    emb = c.qp._emb
    assert cs._addr == int(emb.round_address()) != old
    assert cs._tab[ks.T_SOLVER] == cs._addr
    assert cs._tab[ks.T_XS] == emb.solution.x.ctypes.data
    assert cs._tab[ks.T_Y] == emb.solution.y_buf.ctypes.data
    assert any(a is emb.solution.x for a in cs._tab_keep)
    arrays = list(cs._pre_arrays)
    for k, bad in ((4, arrays[4].astype(np.float32)),          # qb in float32
                   (0, np.zeros(2 * arrays[0].size)[::2])):     # fb not contiguous
        wrong = list(arrays)
        wrong[k] = bad
        with pytest.raises(ValueError, match=f"buffer {k}"):
            cs._table(tuple(wrong), cs._xs, cs._ys, cs._addr)


@needs_numba
def test_a_controller_with_a_compiled_step_refuses_to_be_copied(tmp_path: Path) -> None:
    """Its address table points into its own buffers: a copy is refused with a clear
    error (copy.deepcopy, pickle), never made to share or outlive them."""
    import copy
    import pickle

    c = make("lmpc", config_file(tmp_path, 'kernels = "numba"'), True)
    for attempt in (lambda: copy.deepcopy(c), lambda: pickle.dumps(c),
                    lambda: copy.copy(c.compiled)):
        with pytest.raises(TypeError, match="cannot be copied"):
            attempt()
