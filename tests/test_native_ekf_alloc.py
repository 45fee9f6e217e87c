"""Back-to-back tests of the C EKF (standard and UD form), allocation, pedal map and passive
step (controller/native/src/{ekf,ud_ekf,allocation,pedal_map,passive}.c) against the numpy
references (controller/core/learning/ekf.py, ud_ekf.py, allocation.py, pedal_map.py,
passive.py), in both builds (real_t double, and float with RH_FLOAT32), through a cffi module
whose declarations are generated from the modules' headers (controller/native/module_ffi.py:
no layout, size or constant is written here; configuration structs are filled by field name
as controller/native/config.py fills production's).

Error measures (norm-wise relative, so a cancellation in one entry does not dominate):
  err(W) = max|W_c − W_ref| / max|W_ref|,  err(P) = max|P_c − P_ref| / max|P_ref|.

EKF bounds, derived: one step is a few length-15 dot products, a division and a rank-one
update; each computed entry carries ≤ ~L·ε relative rounding (L = 15) of the operand norms,
and the numpy reference sums in a different order (BLAS / pairwise), so one step from the
same state differs by ≤ c·L·ε with c ~ 10 for margin: PER_STEP = 150·ε (float64: 3.3e-14).
Over N steps the filter contracts (the Riccati map is a contraction in P, W is driven by
the same errors), so differences add at most linearly: END = N·PER_STEP; for N = 600,
float64 END = 2.0e-11. The eigenvalue floor (Jacobi here, LAPACK's eigh in numpy)
reconstructs P from eigenpairs: ≤ ~L·ε·‖P‖·(a few) per repair, so the one-step bound of
the repair scenario is 10·PER_STEP. float32 (ε32 = 1.2e-7): PER_STEP = 1.8e-5,
END = 1.1e-2; plus the stronger check that the C float32 UD filter's error against the
float64 filter is no worse than twice the numpy float32 filter's (both are float32 filters
of the same algorithm). The float32 standard form is tested as far as the reference runs
it (its numpy path works in float32), on sequences where the eigenvalue-floor decision is
robust (p_floor ≫ ε32·‖P‖); the project requires the UD form for float32.
Allocation: a handful of flops per output: float64 within 4ε·T_peak of the reference
(T_peak = per-motor peak torque); float32 within 64 ε32·T_peak of the float64 reference
(inputs rounded to float32). With the motor torque-rate limit (sequences of calls): that bound
plus ε·T_peak per consecutive held call of the wheel (test_allocation_rate_limit_sequence_...;
measured float64 0, float32 8.6e-5 N·m); the held-call counter equal (float32: but for holds
by no more than rounding, ≤ 0.5 % of the calls).
Counters, accept/reject decisions and event counts must match exactly.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from controller.core.allocation import AllocationConfig, TorqueAllocator
from controller.core.interfaces import ControllerInputs, QpStatus
from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.learning.ud_ekf import UdEkf, udu_factor
from controller.core.model.rhonn import phi_batch
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.passive import PassiveController
from controller.core.pedal_map import total_torque_from_pedals
from controller.core.registry import load_controller_config
from controller.native import config as native_config
from controller.native.backend import core_module
from controller.native.build_tools import NoCompilerError
from controller.native.controller import pack_ud_factor, unpack_ud_factor
from controller.native.module_ffi import build_module

SOURCES = ("ekf.c", "ud_ekf.c", "allocation.c", "pedal_map.c", "passive.c")
EPS = {np.float64: float(np.finfo(np.float64).eps), np.float32: float(np.finfo(np.float32).eps)}
N_STEPS = 600
PER_STEP = {np.float64: 150 * EPS[np.float64], np.float32: 150 * EPS[np.float32]}
END = {dt: N_STEPS * PER_STEP[dt] for dt in PER_STEP}

# Measured maxima, printed at the end of the test run with -s (for the report).
MEASURED: dict[str, float] = {}


def _note(key: str, value: float) -> None:
    MEASURED[key] = max(MEASURED.get(key, 0.0), float(value))


@pytest.fixture(scope="session", autouse=True)
def _print_measured():
    yield
    if MEASURED:
        print("\nmeasured max errors:")
        for k in sorted(MEASURED):
            print(f"  {k}: {MEASURED[k]:.3e}")


class Core:
    """One build of the five modules: the functions and constants of its cffi module by
    name, and helpers for its structs and arrays."""

    def __init__(self, module) -> None:
        self.module, self.ffi = module, module.ffi

    def __getattr__(self, name: str):
        return getattr(self.module.lib, name)

    def new(self, ctype: str, src=None, **values):
        """A new zeroed ``ctype *``; its fields filled by name from ``src`` / ``values``
        (controller/native/config.py's fill) when given."""
        p = self.ffi.new(f"{ctype} *")
        if src is not None or values:
            native_config.fill(self.module, p[0], src, **values)
        return p

    def ptr(self, a: np.ndarray):
        """A C array (double* or float*, by a's dtype) on a's memory."""
        assert a.flags.c_contiguous
        return self.ffi.from_buffer({8: "double[]", 4: "float[]"}[a.dtype.itemsize], a)

    def view(self, arr, dt) -> np.ndarray:
        """A numpy view of a C array (e.g. a struct's array field)."""
        return np.frombuffer(self.ffi.buffer(arr), dt)


def _check_sizes(c: Core) -> None:
    """The binding's struct sizes are the library's own (rh_ekf_sizes, ...)."""
    out = c.ffi.new("int[3]")
    for fn, types in (("rh_ekf_sizes", ("rh_ekf_t", "rh_ekf_config_t", "rh_ekf_counters_t")),
                      ("rh_alloc_sizes", ("rh_alloc_t", "rh_alloc_config_t", "rh_vehicle_t"))):
        getattr(c, fn)(out)
        assert list(out) == [c.ffi.sizeof(t) for t in types], fn
    assert c.rh_ud_ekf_size() == c.ffi.sizeof("rh_ud_ekf_t")
    assert c.rh_passive_out_size() == c.ffi.sizeof("rh_passive_out_t")


def _build(dt, tmp_path_factory):
    """(Core, dtype) of the five modules in precision dt."""
    defines = () if dt is np.float64 else ("RH_FLOAT32",)
    try:
        module = build_module(SOURCES, tmp_path_factory.getbasetemp() / "native_ekf_alloc",
                              defines=defines, name=f"ekfalloc_{np.dtype(dt).name}")
    except NoCompilerError as exc:  # pragma: no cover - machines without cc
        pytest.skip(str(exc))
    core = Core(module)
    assert core.ffi.sizeof("real_t") == np.dtype(dt).itemsize
    _check_sizes(core)
    return core, dt


@pytest.fixture(scope="module", params=[np.float64, np.float32], ids=["f64", "f32"])
def lib(request, tmp_path_factory):
    """(Core, dtype) of the five modules in each precision."""
    return _build(request.param, tmp_path_factory)


@pytest.fixture(scope="module")
def lib32(tmp_path_factory):
    """The float32 build."""
    return _build(np.float32, tmp_path_factory)


@pytest.fixture(scope="module")
def lib64(tmp_path_factory):
    """The float64 build."""
    return _build(np.float64, tmp_path_factory)


# ----------------------------------------------------------------------------- EKF
class CFilter:
    """The C filter with the BatchedEkf / UdEkf interface (W, P, counters, update)."""

    def __init__(self, cdll: Core, dt, cfg: EkfConfig, w0: np.ndarray, ud: bool) -> None:
        self.lib, self.dt, self.ud = cdll, dt, ud
        self.s = cdll.new("rh_ud_ekf_t" if ud else "rh_ekf_t")
        self.pre = "rh_ud_ekf_" if ud else "rh_ekf_"
        self._cfg = cdll.new("rh_ekf_config_t", cfg)
        w0_c = cdll.ffi.NULL if w0 is None else cdll.ptr(   # NULL: zeros
            np.ascontiguousarray(np.asarray(w0, dtype=dt).ravel()))
        getattr(cdll, self.pre + "init")(self.s, self._cfg, w0_c)
        self._h = np.zeros(15, dt)
        self._e = np.zeros(3, dt)
        self._x = np.zeros(3, dt)
        self._c = np.zeros(3, dt)

    def fn(self, name: str):
        return getattr(self.lib, self.pre + name)

    @property
    def W(self) -> np.ndarray:
        return self.lib.view(self.s.W, self.dt).reshape(3, 15).copy()

    @property
    def P(self) -> np.ndarray:
        if self.ud:
            out = np.zeros(self.lib.RH_EKF_NP)
            self.fn("covariance")(self.s, self.lib.ptr(out))
            return out.reshape(3, 15, 15)
        return self.lib.view(self.s.P, self.dt).reshape(3, 15, 15).astype(np.float64)

    def counters(self) -> dict[str, int]:
        """rh_ekf_counters_t by field name (EkfCounters.as_dict()'s keys)."""
        cnt = self.s.counters
        return {n: int(getattr(cnt, n)) for n, _ in self.lib.ffi.typeof(cnt).fields}

    def update(self, h: np.ndarray, e: np.ndarray) -> bool:
        self._h[:] = h
        self._e[:] = e
        return bool(self.fn("update")(self.s, self.lib.ptr(self._h), self.lib.ptr(self._e)))

    def update_error(self, h, x, chi, e_out: np.ndarray) -> bool:
        self._h[:] = h
        self._x[:] = x
        self._c[:] = chi
        ptr = self.lib.ptr
        ok = self.fn("update_error")(self.s, ptr(self._h), ptr(self._x), ptr(self._c),
                                     ptr(self._e))
        e_out[:] = self._e
        return bool(ok)

    def load(self, ref) -> None:
        """Copy the reference state (W and P, or U and D) into the C struct."""
        ffi = self.lib.ffi
        for name in ("W", "U", "D") if self.ud else ("W", "P"):
            a = getattr(ref, name)
            if name == "U":  # the core stores the strictly upper parts, packed
                a = pack_ud_factor(a)
            a = np.ascontiguousarray(a, self.dt)
            dst = getattr(self.s, name)
            assert a.nbytes == ffi.sizeof(dst), name
            ffi.memmove(dst, a, a.nbytes)
        if not self.ud:
            self.s.since_eig = ref._since_eig


def _relerr(a: np.ndarray, ref: np.ndarray) -> float:
    a = np.asarray(a, np.float64)
    ref = np.asarray(ref, np.float64)
    return float(np.max(np.abs(a - ref)) / max(np.max(np.abs(ref)), 1e-300))


# Scenario configs: "guards" exercises NaN rejection, weight clips and trace resets;
# "eig" makes P lose eigenvalues below p_floor (tiny q, large p_floor) to trigger repairs
# (standard form) and the floor of D (UD form).
CFG_GUARDS = EkfConfig(p0=0.3, q=2e-3, r=(1e-2, 1e-2, 1e-3), zeta=(1.0, 0.8, 1.0),
                       p_floor=1e-9, trace_max=6.0, w_max=50.0, eig_check_every=100)
CFG_EIG = EkfConfig(p0=1.0, q=1e-7, r=(1e-3, 1e-3, 1e-4), zeta=(1.0, 1.0, 1.0),
                    p_floor=1e-3, trace_max=1e3, w_max=1e3, eig_check_every=50)


def make_sequence(seed: int, n: int = N_STEPS, zero_run: tuple[int, int] = (300, 480)):
    """Regressors (n, 15) of realistic ξ (|ξ| < 1: tanh of a smooth random state), a
    true weight matrix (3, 15), noise (n, 3) and per-step event tags:
    'nan_h', 'inf_e', 'nan_x' (rejected), 'huge' (error × 1e6: weight clip), zero φ over
    zero_run (vehicle at rest: no excitation, trace(P) grows by 15 q per step)."""
    rng = np.random.default_rng(seed)
    s = np.zeros(4)
    xi = np.empty((n, 4))
    for k in range(n):
        s = 0.95 * s + rng.normal(0.0, 0.35, 4)
        xi[k] = 0.9 * np.tanh(s)
    H = phi_batch(xi)
    H[zero_run[0]:zero_run[1]] = 0.0
    w_true = rng.normal(0.0, 0.5, (3, 15))
    noise = rng.normal(0.0, 1.0, (n, 3)) * np.array([0.05, 0.02, 0.01])
    events = {37: "nan_h", 38: "inf_e", 39: "nan_x", 120: "huge", 121: "inf_h", 250: "huge"}
    return H, w_true, noise, events


def _step_inputs(k, H, w_true, noise, events, w_ref):
    """(h, x, chi) of step k: χ = W_ref φ (the model's prediction), x = W_true φ + noise."""
    h = H[k].copy()
    chi = w_ref.astype(np.float64) @ h
    x = w_true @ h + noise[k]
    ev = events.get(k)
    if ev == "nan_h":
        h[3] = np.nan
    elif ev == "inf_h":
        h[0] = np.inf
    elif ev == "inf_e":
        x[1] = np.inf
    elif ev == "nan_x":
        x[2] = np.nan
    elif ev == "huge":
        x = x + 1e6
    return h, x, chi


def _ref_filter(cfg, w0, dt, ud):
    return (UdEkf if ud else BatchedEkf)(3, 15, cfg, w0=w0, dtype=dt)


def _run_pair(cdll, dt, cfg, seed, ud, sync: bool):
    """Run reference (numpy path) and C over one sequence via update_error (the model's
    call). sync: copy the reference state into C before every step (one-step error).
    Returns (max W error, max P error, end W error, end P error, reference counters)."""
    H, w_true, noise, events = make_sequence(seed)
    w0 = np.random.default_rng(seed + 1).normal(0.0, 0.1, (3, 15))
    ref = _ref_filter(cfg, w0, dt, ud)
    c = CFilter(cdll, dt, cfg, w0, ud)
    assert _relerr(c.W, ref.W) == 0.0 and _relerr(c.P, ref.P) == 0.0
    e_ref = np.zeros(3, dt)
    e_c = np.zeros(3, dt)
    ew = ep = 0.0
    for k in range(N_STEPS):
        h, x, chi = _step_inputs(k, H, w_true, noise, events, ref.W)
        h, x, chi = (np.asarray(v, dt) for v in (h, x, chi))
        if sync:
            c.load(ref)
        ok_ref = ref.update_error(h, x, chi, e_ref)
        ok_c = c.update_error(h, x, chi, e_c)
        assert ok_c == ok_ref, f"step {k}: accepted C {ok_c} ref {ok_ref}"
        np.testing.assert_array_equal(e_c, e_ref)
        if not sync:
            assert c.counters() == ref.counters.as_dict(), f"step {k}"
        ew = max(ew, _relerr(c.W, ref.W))
        ep = max(ep, _relerr(c.P, ref.P))
    return ew, ep, _relerr(c.W, ref.W), _relerr(c.P, ref.P), ref.counters.as_dict()


def _forms(dt):
    """(standard, UD) in both precisions: the float32 standard form is not a project
    configuration (UD is required for float32) but the reference runs it, so it is held
    to the same bounds."""
    return (False, True)


@pytest.mark.parametrize("scenario", ["guards", "eig"])
def test_ekf_sequence_matches_reference(lib, scenario):
    cdll, dt = lib
    cfg = CFG_GUARDS if scenario == "guards" else CFG_EIG
    for ud in _forms(dt):
        name = f"{'ud' if ud else 'std'}_{np.dtype(dt).name}_{scenario}"
        ew, ep, ew_end, ep_end, cnt = _run_pair(cdll, dt, cfg, 11, ud, sync=False)
        _note(f"{name} W drift", ew)
        _note(f"{name} P drift", ep)
        # the events of the sequence really happened
        assert cnt["rejected"] == 4 and cnt["updates"] == N_STEPS - 4
        if scenario == "guards":
            assert cnt["weight_clips"] >= 2 and cnt["trace_resets"] >= 1
        elif ud:  # no eigenvalue floor in the UD form (its D floor acts instead)
            assert cnt["eig_repairs"] == 0
        else:
            assert cnt["eig_repairs"] >= 3
        assert ew <= END[dt] and ep <= END[dt], (name, ew, ep)
        assert ew_end <= END[dt] and ep_end <= END[dt]


@pytest.mark.parametrize("scenario", ["guards", "eig"])
def test_ekf_one_step_bound(lib, scenario):
    """From the reference state, one C step stays within PER_STEP of the reference step."""
    cdll, dt = lib
    cfg = CFG_GUARDS if scenario == "guards" else CFG_EIG
    for ud in _forms(dt):
        name = f"{'ud' if ud else 'std'}_{np.dtype(dt).name}_{scenario}"
        ew, ep, *_ = _run_pair(cdll, dt, cfg, 12, ud, sync=True)
        _note(f"{name} W one-step", ew)
        _note(f"{name} P one-step", ep)
        bound = PER_STEP[dt]
        if scenario == "eig":
            bound = 10 * bound  # eigen-decomposition (Jacobi vs LAPACK) on repair steps
        assert ew <= bound and ep <= bound, (name, ew, ep, bound)


def test_float32_ud_accuracy_vs_float64(lib32):
    """The C float32 UD filter tracks the float64 filter as well as numpy's float32 does."""
    cdll, _ = lib32
    H, w_true, noise, events = make_sequence(13)
    w0 = np.random.default_rng(14).normal(0.0, 0.1, (3, 15))
    ref64 = _ref_filter(CFG_GUARDS, w0, np.float64, True)
    ref32 = _ref_filter(CFG_GUARDS, w0, np.float32, True)
    c32 = CFilter(cdll, np.float32, CFG_GUARDS, w0, True)
    e = np.zeros(3)
    e32 = np.zeros(3, np.float32)
    worst_c = worst_np = 0.0
    for k in range(N_STEPS):
        h, x, chi = _step_inputs(k, H, w_true, noise, events, ref64.W)
        ref64.update_error(h, x, chi, e)
        h32, x32, chi32 = (np.asarray(v, np.float32) for v in (h, x, chi))
        ref32.update_error(h32, x32, chi32, e32)
        c32.update_error(h32, x32, chi32, e32)
        worst_c = max(worst_c, _relerr(c32.W, ref64.W))
        worst_np = max(worst_np, _relerr(ref32.W, ref64.W))
    _note("ud_float32 W vs float64 (C)", worst_c)
    _note("ud_float32 W vs float64 (numpy f32)", worst_np)
    assert worst_c <= 2.0 * worst_np + 100 * EPS[np.float32], (worst_c, worst_np)


def test_ekf_eig_check_without_repair_changes_nothing(lib):
    """eig_check_every > 0 with every eigenvalue above the floor: bit-identical to
    eig_check_every = 0 (the Jacobi decomposition must not perturb P)."""
    cdll, dt = lib
    H, w_true, noise, _ = make_sequence(21)
    cfg_on = EkfConfig(p0=1.0, q=1e-4, r=(1e-2, 1e-2, 1e-3), p_floor=1e-9,
                       eig_check_every=7)
    cfg_off = EkfConfig(p0=1.0, q=1e-4, r=(1e-2, 1e-2, 1e-3), p_floor=1e-9,
                        eig_check_every=0)
    a = CFilter(cdll, dt, cfg_on, None, False)
    b = CFilter(cdll, dt, cfg_off, None, False)
    for k in range(300):
        h = H[k]
        e = w_true @ h + noise[k] - a.W @ h
        assert a.update(h, e) and b.update(h, e)
    assert a.counters()["eig_repairs"] == 0
    assert np.array_equal(a.W, b.W) and np.array_equal(a.P, b.P)
    # enforce_spd on a healthy P repairs nothing and keeps it bit-for-bit
    before = a.P
    assert cdll.rh_ekf_enforce_spd(a.s) == 0
    assert np.array_equal(a.P, before)


def test_ekf_enforce_spd_matches_eigh(lib64):
    """Direct repair of indefinite / non-finite P against BatchedEkf.enforce_spd (the
    standard form, float64)."""
    cdll, dt = lib64
    rng = np.random.default_rng(5)
    cfg = EkfConfig(p_floor=1e-3)
    ref = BatchedEkf(3, 15, cfg)
    c = CFilter(cdll, dt, cfg, None, False)
    for trial in range(20):
        for i in range(3):
            Q, _ = np.linalg.qr(rng.normal(size=(15, 15)))
            lam = np.exp(rng.uniform(-12, 2, 15)) * rng.choice([1, 1, 1, -1], 15)
            if trial % 5 == 0:
                lam[:4] = lam[0]  # a repeated eigenvalue (degenerate eigenvectors)
            ref.P[i] = (Q * lam) @ Q.T
            ref.P[i] = 0.5 * (ref.P[i] + ref.P[i].T)
        c.load(ref)
        if trial == 3:
            # A non-finite entry: numpy's eigh raises LinAlgError (the reference has no
            # defined result); C treats it as a non-finite eigenvalue: P_i = p0 I.
            cdll.view(c.s.P, dt).reshape(3, 15, 15)[1, 2, 5] = np.nan
            cdll.view(c.s.P, dt).reshape(3, 15, 15)[1, 5, 2] = np.nan
            assert cdll.rh_ekf_enforce_spd(c.s) >= 1
            np.testing.assert_array_equal(c.P[1], cfg.p0 * np.eye(15))
            assert np.all(np.isfinite(c.P))
            continue
        n_ref = ref.enforce_spd()
        n_c = cdll.rh_ekf_enforce_spd(c.s)
        assert n_c == n_ref
        err = _relerr(c.P, ref.P)
        _note("std_float64 enforce_spd P", err)
        assert err <= 100 * EPS[np.float64], err
        np.testing.assert_array_equal(c.P, np.swapaxes(c.P, 1, 2))  # exactly symmetric
        assert np.linalg.eigvalsh(c.P).min() >= cfg.p_floor * (1 - 1e-9)


@pytest.mark.parametrize("rel", [-1e-3, -1e-9, 1e-12, 1e-9, 1e-3, 10.0])
def test_ekf_eigenvalue_floor_decides_like_eigh_at_the_boundary(lib64, rel: float) -> None:
    """The core skips the Jacobi path when a Cholesky factorisation of P − (floor + margin) I
    succeeds; at the floor itself (smallest eigenvalue (1 + rel) × p_floor) it must still
    repair exactly what eigh repairs, and leave P bit for bit alone otherwise."""
    cdll, dt = lib64
    rng = np.random.default_rng(7)
    cfg = EkfConfig(p_floor=1e-3)
    ref = BatchedEkf(3, 15, cfg)
    c = CFilter(cdll, dt, cfg, None, False)
    for i in range(3):
        Q, _ = np.linalg.qr(rng.normal(size=(15, 15)))
        lam = np.exp(rng.uniform(-3, 2, 15))
        lam[0] = cfg.p_floor * (1.0 + rel)
        ref.P[i] = (Q * lam) @ Q.T
        ref.P[i] = 0.5 * (ref.P[i] + ref.P[i].T)
    c.load(ref)
    before = c.P.copy()
    n_ref = ref.enforce_spd()
    n_c = cdll.rh_ekf_enforce_spd(c.s)
    assert n_c == n_ref
    if n_ref == 0:
        np.testing.assert_array_equal(c.P, before)
    else:
        assert _relerr(c.P, ref.P) <= 100 * EPS[np.float64]


def test_ekf_freeze_reset_and_update_paths(lib):
    cdll, dt = lib
    for ud in _forms(dt):
        w0 = np.arange(45, dtype=float).reshape(3, 15) / 45.0
        c = CFilter(cdll, dt, EkfConfig(), w0, ud)
        ref = _ref_filter(EkfConfig(), w0, dt, ud)
        np.testing.assert_array_equal(c.W, np.asarray(w0, dt))
        c.fn("freeze")(c.s)
        assert not ref.update(np.zeros(15, dt), np.zeros(3, dt), learn=False)
        h = np.full(15, 0.3, dt)
        e = np.array([0.1, -0.2, 0.05], dt)
        assert c.update(h, e) and ref.update(h, e)
        assert c.counters() == ref.counters.as_dict()
        assert _relerr(c.W, ref.W) <= PER_STEP[dt]
        # a non-positive innovation variance is rejected (R < 0 and h = 0)
        bad = CFilter(cdll, dt, EkfConfig(r=(-1.0, 1.0, 1.0)), None, ud)
        assert not bad.update(np.zeros(15, dt), np.zeros(3, dt))
        assert bad.counters()["rejected"] == 1 and bad.counters()["updates"] == 0
        c.fn("reset")(c.s)
        ref.reset()
        assert c.counters() == ref.counters.as_dict() == {k: 0 for k in ref.counters.as_dict()}
        np.testing.assert_array_equal(c.W, ref.W)
        np.testing.assert_allclose(c.P, ref.P, rtol=0, atol=0)


def test_ud_covariance_roundtrip(lib):
    """rh_ud_ekf_covariance == UdEkf.P and rh_ud_ekf_set_covariance == udu_factor."""
    cdll, dt = lib
    H, _, noise, _ = make_sequence(31)
    ref = UdEkf(3, 15, EkfConfig(), dtype=dt)
    for k in range(100):
        ref.update(np.asarray(H[k], dt), np.asarray(noise[k], dt))
    c = CFilter(cdll, dt, EkfConfig(), None, True)
    c.load(ref)
    err = _relerr(c.P, ref.P)
    _note(f"ud_{np.dtype(dt).name} covariance", err)
    assert err <= 100 * EPS[np.float64]
    P = ref.P
    assert cdll.rh_ud_ekf_set_covariance(c.s, cdll.ptr(np.ascontiguousarray(P))) == 0
    for i in range(3):
        U, D = udu_factor(P[i])
        Uc = unpack_ud_factor(cdll.view(c.s.U, dt).reshape(3, -1)[i], 15)
        Dc = cdll.view(c.s.D, dt).reshape(3, 15)[i]
        tol = 1e-9 if dt is np.float64 else 4 * EPS[np.float32]
        np.testing.assert_allclose(Dc, D, rtol=tol)
        np.testing.assert_allclose(Uc, U, rtol=tol, atol=tol)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")
def test_an_overflowing_innovation_variance_is_rejected_like_the_reference(lib):
    """``!(finite(ssum) && smin > 0)`` (standard) and ``!(finite(s) && s > 0)`` (UD) with the
    finiteness condition alone: a covariance so large (1e300, float32 1e30) that the first
    neuron's innovation variance h'P h + R overflows to +inf while the others stay finite
    and positive; the update is rejected, as by the reference, W and the counters equal."""
    cdll, dt = lib
    big = 1e300 if dt is np.float64 else 1e30
    h = np.full(15, 1e5, dt)
    e = np.array([0.1, -0.2, 0.05], dt)
    for ud in _forms(dt):
        ref = _ref_filter(EkfConfig(), None, dt, ud)
        if ud:
            ref.D[0, :] = big
        else:
            ref.P[0] = big * np.eye(15)
        c = CFilter(cdll, dt, EkfConfig(), None, ud)
        c.load(ref)
        w_before = c.W
        assert not ref.update(h, e) and not c.update(h, e)
        assert c.counters() == ref.counters.as_dict() and c.counters()["rejected"] == 1
        np.testing.assert_array_equal(c.W, w_before)
        np.testing.assert_array_equal(c.W, ref.W)


def test_ekf_floor_at_minus_infinity_repairs_nothing(lib):
    """``!(d > 0) || !finite(d)`` (the Cholesky screen of rh_ekf_enforce_spd) with its
    second condition alone: p_floor = −∞ shifts the diagonal to +∞, a positive but not
    finite pivot, so the screen sends P_i to the eigenvalue path, where nothing is below
    −∞: P is left bit for bit alone (indefinite P_i included), as by the reference."""
    cdll, dt = lib
    rng = np.random.default_rng(11)
    cfg = EkfConfig(p_floor=-math.inf)
    ref = BatchedEkf(3, 15, cfg, dtype=dt)
    for i in range(3):
        Q, _ = np.linalg.qr(rng.normal(size=(15, 15)))
        lam = np.exp(rng.uniform(-3, 2, 15)) * (1.0 if i == 0 else rng.choice([1, -1], 15))
        ref.P[i] = 0.5 * ((Q * lam) @ Q.T + ((Q * lam) @ Q.T).T)
    c = CFilter(cdll, dt, cfg, None, False)
    c.load(ref)
    before = c.P.copy()
    assert cdll.rh_ekf_enforce_spd(c.s) == ref.enforce_spd() == 0
    np.testing.assert_array_equal(c.P, before)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")
def test_ekf_eigenvalue_overflow_resets_like_the_reference(lib64):
    """``finite && finite(lam_a)`` (rh_ekf_enforce_spd), both conditions: a finite P_i with
    an eigenvalue beyond the largest double (block [[1e308, 1e308], [1e308, 1.5e308]],
    eigenvalue ≈ 2.3e308) and an indefinite diagonal entry (so the Cholesky screen fails):
    the Jacobi rotation overflows to +∞ in the second eigenvalue, the later ones are not
    looked at, and P_i is reset to p0 I, as the reference (eigh's eigenvalues not finite)."""
    cdll, dt = lib64
    cfg = EkfConfig(p_floor=1e-3)
    ref = BatchedEkf(3, 15, cfg)
    p = np.eye(15)
    p[0, 0], p[1, 1], p[0, 1], p[1, 0], p[5, 5] = 1e308, 1.5e308, 1e308, 1e308, -1.0
    ref.P[1] = p
    c = CFilter(cdll, dt, cfg, None, False)
    c.load(ref)
    assert cdll.rh_ekf_enforce_spd(c.s) == ref.enforce_spd() == 1
    np.testing.assert_array_equal(c.P, ref.P)
    np.testing.assert_array_equal(c.P[1], cfg.p0 * np.eye(15))


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_ud_set_covariance_counts_bad_pivots_like_udu_factor(lib):
    """``!(finite(D_j) && D_j > 0)`` (rh_ud_ekf_set_covariance), one condition at a time: a
    covariance with a negative diagonal entry (a finite, non-positive pivot) and one with a
    NaN entry (non-finite pivots from there on); the count of bad pivots and the factors
    are udu_factor's (NaN where it has NaN), the third neuron's identity is fine."""
    cdll, dt = lib
    P = np.stack([np.eye(15)] * 3)
    P[0, 7, 7] = -1.0
    P[1, 3, 3] = np.nan
    c = CFilter(cdll, dt, EkfConfig(), None, True)
    bad = cdll.rh_ud_ekf_set_covariance(c.s, cdll.ptr(np.ascontiguousarray(P)))
    want = 0
    for i in range(3):
        U, D = udu_factor(P[i])
        want += int(np.sum(~(np.isfinite(D) & (D > 0.0))))
        np.testing.assert_array_equal(cdll.view(c.s.D, dt).reshape(3, 15)[i],
                                      np.asarray(D, dt))
        np.testing.assert_array_equal(
            unpack_ud_factor(cdll.view(c.s.U, dt).reshape(3, -1)[i], 15),
            np.asarray(U, dt))
    assert bad == want and want >= 2


needs_core = pytest.mark.skipif(core_module(False) is None,
                                reason="the C core is not built (no C compiler at install)")


def _rhonn_cfg(ekf: EkfConfig):
    """The packaged configuration with [rhonn.ekf] replaced."""
    cfg = load_controller_config()
    return replace(cfg, rhonn=replace(cfg.rhonn, ekf=ekf))


@needs_core
def test_ekf_config_layout():
    """rh_ekf_config_t as production fills it (controller/native/config.py, by field name):
    every EkfConfig value in its field; ValueError unless r and zeta have RH_EKF_N entries."""
    cfg = EkfConfig(p0=2.0, q=3e-5, r=(1.0, 2.0, 3.0), zeta=(0.1, 0.2, 0.3), p_floor=1e-8,
                    trace_max=55.0, w_max=7.0, eig_check_every=9)
    c = native_config.ctrl_config("nmpc-rhonn", _rhonn_cfg(cfg)).rhonn.ekf
    assert (c.p0, c.q, list(c.r), list(c.zeta), c.p_floor, c.trace_max, c.w_max,
            c.eig_check_every) == (2.0, 3e-5, [1.0, 2.0, 3.0], [0.1, 0.2, 0.3], 1e-8, 55.0,
                                   7.0, 9)
    with pytest.raises(ValueError):
        native_config.ctrl_config("nmpc-rhonn", _rhonn_cfg(EkfConfig(r=(1.0, 2.0))))


# ------------------------------------------------------------------------ allocation
@pytest.fixture(scope="module")
def params() -> VehicleParams:
    return load_vehicle_params()


class CAlloc:
    def __init__(self, cdll: Core, dt, params: VehicleParams, cfg: AllocationConfig) -> None:
        self.lib, self.dt, self.ffi = cdll, dt, cdll.ffi
        self.s = cdll.new("rh_alloc_t")
        self._veh = cdll.new("rh_vehicle_t", params)
        self._cfg = cdll.new("rh_alloc_config_t", cfg, split=native_config.constant(
            cdll.module, "RH_ALLOC_SPLIT_", cfg.split))
        cdll.rh_alloc_init(self.s, self._veh, self._cfg)
        self._ws = np.zeros(4, dt)
        self.out = np.zeros(4, dt)

    def allocate(self, tt, dm, ax, ay, ws, limits_current=False) -> np.ndarray:
        self._ws[:] = ws
        self.lib.rh_alloc_allocate(self.s, tt, dm, ax, ay, self.lib.ptr(self._ws),
                                   int(limits_current), self.lib.ptr(self.out))
        return self.out

    def dm_capacity(self, ws) -> float:
        self._ws[:] = ws
        return float(self.lib.rh_alloc_dm_capacity(self.s, self.lib.ptr(self._ws)))


def _alloc_cases(n: int, seed: int, dt) -> list[tuple]:
    """(Tt, ΔM, ax, ay, ws) with infeasible demands, power-limited and non-finite speeds."""
    rng = np.random.default_rng(seed)
    cases = []
    for k in range(n):
        ws = rng.uniform(-20.0, 250.0, 4)           # 100 rad/s: base speed (power limit)
        if k % 7 == 0:
            ws[rng.integers(4)] = [np.nan, np.inf, -np.inf, 0.0][k % 4]
        if k % 11 == 0:
            ws[:] = rng.uniform(150.0, 400.0, 4)     # all power limited
        tt = rng.uniform(-4000.0, 4000.0) * (1.0 if k % 3 else 0.2)
        dm = rng.uniform(-4000.0, 4000.0) * (0.1 if k % 2 else 1.0)
        if k % 13 == 0:
            tt = [np.nan, np.inf, 1e12][k % 3]
        if k % 17 == 0:
            dm = [np.nan, -np.inf, -1e12][k % 3]
        ax, ay = rng.uniform(-15.0, 15.0, 2)
        if k % 19 == 0:
            ax = np.nan
        if k % 23 == 0:
            ay = np.inf
        # inputs representable in the working precision (the C API takes real_t)
        tt, dm, ax, ay = (float(dt(v)) for v in (tt, dm, ax, ay))
        cases.append((tt, dm, ax, ay, np.asarray(np.asarray(ws, dt), np.float64)))
    return cases


@pytest.mark.parametrize("split", ["normal_load", "equal"])
def test_allocation_matches_reference(lib, params, split):
    cdll, dt = lib
    cfg = AllocationConfig(split=split)
    ref = TorqueAllocator(params, cfg, dtype=np.float64)
    c = CAlloc(cdll, dt, params, cfg)
    tp = params.peak_torque_nm
    tol = 4 * EPS[dt] * tp * (1.0 if dt is np.float64 else 16.0)
    worst = 0.0
    n_infeasible = n_power = 0
    for tt, dm, ax, ay, ws in _alloc_cases(1500, 7 if split == "equal" else 8, dt):
        t_ref = ref.allocate(tt, dm, ax, ay, ws).copy()
        t_c = c.allocate(tt, dm, ax, ay, ws).copy()
        lim = ref.limits.copy()
        np.testing.assert_allclose(cdll.view(c.s.limits, dt), lim, rtol=4 * EPS[dt])
        worst = max(worst, float(np.max(np.abs(t_c - t_ref))))
        assert abs(c.s.tt_applied - ref.tt_applied) <= 2 * tol
        assert abs(c.s.dm_applied - ref.dm_applied) <= 2 * tol
        # eq. 16 identities and the limits, in the C result itself
        assert np.all(np.abs(t_c) <= cdll.view(c.s.limits, dt) * (1 + 4 * EPS[dt]))
        s = t_c.astype(np.float64)
        assert abs(s.sum() - c.s.tt_applied) <= 4 * tol
        assert abs((s[1] + s[3] - s[0] - s[2]) - c.s.dm_applied) <= 4 * tol
        feasible = (math.isfinite(tt) and math.isfinite(dm) and abs(ref.dm_applied - dm) == 0
                    and abs(ref.tt_applied - tt) <= 1e-9 * max(1.0, abs(tt)))
        if feasible:
            assert abs(c.s.tt_applied - tt) <= 2 * tol + 1e-9 * abs(tt)
            assert abs(c.s.dm_applied - dm) <= 2 * tol
        else:
            n_infeasible += 1
        n_power += bool(np.any(lim < tp))
    _note(f"alloc_{np.dtype(dt).name}_{split} |dT| N m", worst)
    assert worst <= tol, (worst, tol)
    assert n_infeasible >= 100 and n_power >= 300


def test_allocation_limits_current_and_capacity(lib, params):
    """dm_capacity computes the limits that allocate(limits_current=1) then uses."""
    cdll, dt = lib
    ref = TorqueAllocator(params, AllocationConfig(), dtype=np.float64)
    c = CAlloc(cdll, dt, params, AllocationConfig())
    rng = np.random.default_rng(3)
    for _ in range(200):
        ws = np.asarray(np.asarray(rng.uniform(0.0, 300.0, 4), dt), np.float64)
        other = rng.uniform(0.0, 300.0, 4)
        cap_ref = ref.delta_m_capacity(ws)
        cap_c = c.dm_capacity(ws)
        assert abs(cap_c - cap_ref) <= 8 * EPS[dt] * params.peak_torque_nm
        tt, dm = (float(dt(v)) for v in rng.uniform(-3000, 3000, 2))
        # limits_current: the ws passed now must be ignored (other speeds)
        t_ref = ref.allocate(tt, dm, 1.0, -2.0, other, limits_current=True)
        t_c = c.allocate(tt, dm, 1.0, -2.0, other, limits_current=True)
        assert np.max(np.abs(t_c - t_ref)) <= 16 * EPS[dt] * params.peak_torque_nm
    # a wrong limits_current mirror would fail here: limits from ws, not other
    c.dm_capacity(np.full(4, 300.0))
    out = c.allocate(4 * 450.0, 0.0, 0.0, 0.0, np.zeros(4), limits_current=True)
    assert np.sum(out) <= 4 * 150.0 * (1 + 1e-6)


def test_allocation_into_its_own_out_array_equals_a_separate_output(lib, params):
    """The header allows torques == a->out (in place): the same torques, bit for bit, as
    with a separate output array, and within the reference's tolerance of TorqueAllocator,
    over cases with infeasible demands and power limits."""
    cdll, dt = lib
    ref = TorqueAllocator(params, AllocationConfig(), dtype=np.float64)
    sep = CAlloc(cdll, dt, params, AllocationConfig())
    inp = CAlloc(cdll, dt, params, AllocationConfig())
    own = inp.s.out
    tol = 4 * EPS[dt] * params.peak_torque_nm * (1.0 if dt is np.float64 else 16.0)
    for tt, dm, ax, ay, ws in _alloc_cases(200, 11, dt):
        t_sep = sep.allocate(tt, dm, ax, ay, ws).copy()
        inp._ws[:] = ws
        cdll.rh_alloc_allocate(inp.s, tt, dm, ax, ay, cdll.ptr(inp._ws),
                               0, own)
        t_own = cdll.view(inp.s.out, dt).copy()
        np.testing.assert_array_equal(t_own, t_sep)
        assert (inp.s.tt_applied, inp.s.dm_applied) == (sep.s.tt_applied, sep.s.dm_applied)
        assert np.max(np.abs(t_own - ref.allocate(tt, dm, ax, ay, ws))) <= tol


def test_front_share_matches_reference(lib, params):
    cdll, dt = lib
    ref = TorqueAllocator(params, AllocationConfig())
    c = CAlloc(cdll, dt, params, AllocationConfig())
    sl, sr = cdll.ffi.new("real_t *"), cdll.ffi.new("real_t *")
    for ax, ay in [(0, 0), (3, -4), (-14, 20), (np.nan, 2), (1, np.inf), (12, 12)]:
        cdll.rh_alloc_front_share(c.s, ax, ay, sl,
                                  sr)
        r = ref.front_share(ax, ay)
        np.testing.assert_allclose([sl[0], sr[0]], r, rtol=8 * EPS[dt])


@needs_core
def test_alloc_config_layout(lib64):
    """rh_alloc_config_t's split as production fills it (controller/native/config.py): the
    RH_ALLOC_SPLIT_* constant of the header (the module build's and the core's alike);
    ValueError for a split the core does not have."""
    cdll, _ = lib64

    def split(name: str) -> int:
        cfg = load_controller_config()
        cfg = replace(cfg, allocation=AllocationConfig(split=name))
        return native_config.ctrl_config("passive", cfg).alloc.split

    assert split("equal") == cdll.RH_ALLOC_SPLIT_EQUAL != cdll.RH_ALLOC_SPLIT_NORMAL_LOAD
    assert split("normal_load") == cdll.RH_ALLOC_SPLIT_NORMAL_LOAD
    with pytest.raises(ValueError):
        split("rear")


# ------------------------------------------------------------ pedal map and passive
def test_pedal_map(lib, params):
    cdll, dt = lib
    tp = params.peak_torque_nm
    vals = [0.0, 0.3, 1.0, -0.5, 1.7, np.nan, np.inf, -np.inf, 0.999]
    for a in vals:
        for b in vals:
            ref = total_torque_from_pedals(a, b, tp)
            got = cdll.rh_pedal_total_torque(a, b, tp)
            assert abs(got - ref) <= 4 * EPS[dt] * 4 * tp, (a, b, got, ref)


def test_passive_step_matches_reference(lib, params):
    params = replace(params, torque_rate_nm_per_s=0.0)   # the passive car: no slew
    cdll, dt = lib
    al = CAlloc(cdll, dt, params, AllocationConfig())
    out = cdll.new("rh_passive_out_t")
    cdll.rh_passive_reset(out)
    assert out.qp_status == int(QpStatus.NOT_RUN) == cdll.RH_QP_NOT_RUN
    ref = PassiveController(params, TorqueAllocator(params, AllocationConfig()), 0.01)
    rng = np.random.default_rng(17)
    ws = np.zeros(4, dt)
    for k in range(300):
        inp = ControllerInputs()
        inp.accel_pedal, inp.brake_pedal = (float(dt(v)) for v in rng.uniform(-0.2, 1.2, 2))
        if k % 9 == 0:
            inp.accel_pedal = np.nan
        inp.ax, inp.ay = (float(dt(v)) for v in rng.uniform(-12, 12, 2))
        if k % 10 == 0:
            inp.ay = np.nan
        ws[:] = rng.uniform(0.0, 300.0, 4)
        inp.wheel_speeds = ws.astype(np.float64)
        o = ref.step(inp)
        cdll.rh_passive_step(al.s, inp.accel_pedal, inp.brake_pedal, inp.ax,
                             inp.ay, cdll.ptr(ws), out)
        tol = 16 * EPS[dt] * params.peak_torque_nm
        np.testing.assert_allclose(cdll.view(out.torques, dt), o.torques, rtol=0,
                                   atol=tol)
        assert abs(out.total_torque - o.total_torque) <= tol
        assert abs(out.delta_m - o.delta_m) <= tol
        assert abs(out.delta_m) <= tol  # ΔM = 0 is always feasible
        assert (out.qp_status, out.qp_iterations, out.fallback) == (
            o.qp_status, o.qp_iterations, int(o.fallback))


# ------------------------------------------------------------ motor torque-rate limit
def _rate_sequence(n: int, seed: int, dt) -> list[tuple]:
    """(Tt, ΔM, ax, ay, ws, limits_current, reset) per call, N·m, m/s², rad/s: smooth
    driving that the slew follows, demand jumps between extremes (the wheels held for several
    calls), wheel speeds rising into the power limit under load (limits falling below the
    previous torque: cut at once), chaotic demands (held nearly every call), non-finite
    inputs, allocations on limits computed by dm_capacity, and two resets. Inputs rounded to
    the working precision."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        phase = (k * 5) // n
        if phase == 0:                                   # smooth driving
            tt = 1500.0 * math.sin(0.02 * k) + rng.normal(0, 20.0)
            dm = 1200.0 * math.sin(0.05 * k)
            ws = rng.uniform(10.0, 80.0, 4)
        elif phase == 1:                                 # jumps between extremes
            tt = 3500.0 if (k // 15) % 2 else -3500.0
            dm = -2500.0 if (k // 25) % 2 else 2500.0
            ws = rng.uniform(20.0, 90.0, 4)
        elif phase == 2:                                 # speeds into the power limit
            w = 60.0 + 240.0 * ((k % 40) / 40.0)
            tt, dm = 3600.0, 600.0 * math.sin(0.3 * k)
            ws = w + rng.uniform(-5.0, 5.0, 4)
        else:                                            # chaotic demands
            tt, dm = rng.uniform(-4000.0, 4000.0, 2)
            ws = rng.uniform(-20.0, 300.0, 4)
        ax, ay = rng.uniform(-12.0, 12.0, 2)
        if k % 29 == 0:
            tt = [np.nan, np.inf, 1e12][k % 3]
        if k % 31 == 0:
            dm = [np.nan, -np.inf, -1e12][k % 3]
        if k % 37 == 0:
            ws[rng.integers(4)] = [np.nan, np.inf, 0.0][k % 3]
        if k % 41 == 0:
            ay = np.nan
        tt, dm, ax, ay = (float(dt(v)) for v in (tt, dm, ax, ay))
        ws = np.asarray(np.asarray(ws, dt), np.float64)
        out.append((tt, dm, ax, ay, ws, k % 3 == 1, k in (n // 3, (4 * n) // 5)))
    return out


@pytest.mark.parametrize("cycle_s", [0.01, 0.002], ids=["step100", "step20"])
def test_allocation_rate_limit_sequence_matches_reference(lib, params, cycle_s):
    """Sequences of calls with the motor torque-rate limit (VehicleParams.torque_rate_nm_per_s
    × AllocationConfig.cycle_s per call; 100 and 20 N·m): torques, realised (Tt, ΔM), the
    previous torques and the held-call counter against TorqueAllocator, with resets.

    Bound per wheel and call: TOL + L·ε·T_peak, TOL the allocation bound of
    test_allocation_matches_reference and L the number of consecutive calls up to this one in
    which the reference held that wheel (its output differs from the allocation without the
    limit). A held wheel outputs prev ± step (or ±limit): one more rounding of a number
    ≤ T_peak (≤ ε·T_peak/2) on top of the previous output's error, so the error can grow by
    that along a run of held calls and starts again from TOL when the wheel reaches its
    target. float64: the same IEEE operations in the same order as the reference (measured
    0); float32 against the float64 reference on float32-rounded inputs. Every held/not-held
    decision, and so the counter of held calls, must be equal, except in float32 on calls
    where the reference held a wheel by no more than the rounding bound (≤ 0.5 % of the
    calls; measured 2 of 2000 with 100 N·m steps, 0 with 20; C − numpy: float64 0, float32
    8.6e-5 N·m = 0.025 of the bound)."""
    cdll, dt = lib
    cfg = AllocationConfig(cycle_s=cycle_s)
    ref = TorqueAllocator(params, cfg, dtype=np.float64)
    free = TorqueAllocator(replace(params, torque_rate_nm_per_s=0.0), cfg, dtype=np.float64)
    c = CAlloc(cdll, dt, params, cfg)
    tp = params.peak_torque_nm
    step = params.torque_rate_nm_per_s * cycle_s
    assert ref.rate_step == pytest.approx(step) and c.s.rate_step == pytest.approx(step)
    tol = 4 * EPS[dt] * tp * (1.0 if dt is np.float64 else 16.0)
    run = np.zeros(4)
    worst = worst_ratio = 0.0
    held_calls = cut_calls = flips = 0
    for tt, dm, ax, ay, ws, lim_cur, reset in _rate_sequence(2000, 5, dt):
        if reset:
            ref.reset()
            cdll.rh_alloc_reset(c.s)
            run[:] = 0.0
            assert c.s.rate_limited_calls == 0 and not np.any(cdll.view(c.s.prev, dt))
        prev_ref = ref.prev.copy()
        n_ref, n_c = ref.rate_limited_calls, c.s.rate_limited_calls
        if lim_cur:   # the controller's step: limits from dm_capacity, then allocate on them
            free.delta_m_capacity(ws)
            assert abs(c.dm_capacity(ws) - ref.delta_m_capacity(ws)) <= 8 * EPS[dt] * tp
        target = free.allocate(tt, dm, ax, ay, ws, limits_current=lim_cur).copy()
        t_ref = ref.allocate(tt, dm, ax, ay, ws, limits_current=lim_cur).copy()
        t_c = c.allocate(tt, dm, ax, ay, ws, limits_current=lim_cur).copy()
        held = t_ref != target
        run = np.where(held, run + 1.0, 0.0)
        bound = tol + run * EPS[dt] * tp
        err = np.abs(t_c - t_ref)
        assert np.all(err <= bound), (err, bound, t_c, t_ref)
        worst = max(worst, float(err.max()))
        worst_ratio = max(worst_ratio, float((err / bound).max()))
        ref_held, c_held = ref.rate_limited_calls - n_ref, c.s.rate_limited_calls - n_c
        if ref_held != c_held:
            # only where the reference held a wheel by no more than rounding (a wheel
            # saturated at a motor limit that fell, computed as t_side − t_other, lands an ulp
            # outside its own window): never in float64
            assert dt is np.float32 and not np.any(np.abs(t_ref - target) > bound), (
                t_ref, target, t_c)
            flips += 1
        assert np.all(np.abs(cdll.view(c.s.prev, dt) - ref.prev) <= bound)
        assert abs(c.s.tt_applied - ref.tt_applied) <= 4 * bound.max()
        assert abs(c.s.dm_applied - ref.dm_applied) <= 4 * bound.max()
        # the slew itself, in the C result: within one step of the previous torques unless
        # the motor limit cut the wheel
        lim = cdll.view(c.s.limits, dt).astype(float)
        moved = np.abs(t_c - prev_ref)
        assert np.all((moved <= step + 2 * bound) | (np.abs(t_c) >= lim * (1 - 4 * EPS[dt])))
        held_calls += bool(held.any())
        cut_calls += bool(np.any((moved > step + 2 * bound) & held))
    _note(f"alloc_rate_{np.dtype(dt).name}_{cycle_s} |dT| N m", worst)
    _note(f"alloc_rate_{np.dtype(dt).name}_{cycle_s} err/bound", worst_ratio)
    _note(f"alloc_rate_{np.dtype(dt).name}_{cycle_s} ulp-level hold decisions apart", flips)
    assert flips <= 0.005 * 2000
    assert ref.rate_limited_calls >= 200 and held_calls >= 500
    assert cut_calls >= 5      # the motor limit fell below the previous torque


def test_allocation_rate_limit_comparison_detects_a_port_error(lib64, params):
    """A C allocator whose rate step is 1e-9 relative off fails the rate-limit comparison."""
    cdll, dt = lib64
    cfg = AllocationConfig()
    ref = TorqueAllocator(params, cfg)
    c = CAlloc(cdll, dt, params, cfg)
    c.s.rate_step = c.s.rate_step * (1.0 + 1e-9)
    tol = 4 * EPS[dt] * params.peak_torque_nm
    worst = 0.0
    for tt, dm, ax, ay, ws, _lim_cur, _reset in _rate_sequence(400, 5, dt):
        t_ref = ref.allocate(tt, dm, ax, ay, ws).copy()
        worst = max(worst, float(np.max(np.abs(c.allocate(tt, dm, ax, ay, ws) - t_ref))))
    assert worst > 100 * tol
