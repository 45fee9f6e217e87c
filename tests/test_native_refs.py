"""C reference generators (controller/native/src/refs*.c, slow_weights.c, sideslip_guard.c)
back to back with the numpy reference (references/factory.make_rhonn_references), through a
cffi module whose declarations are generated from the modules' headers
(controller/native/module_ffi.py: no layout, size or constant is written here; the
configuration is filled by controller/native/config.py, as in production).

Data: a synthetic nonlinear single-track run (tanh tyres, 400 steps of 50 ms): low speed
below v_min, straight running, a steering sine, a long low-μ corner in which |β| crosses
1°–3° (blend range) and grows to ≈ 10° (guard and Algorithm 1 rounds), a braking phase back
below v_min, seeded sensor noise and a few non-finite inputs. The RHONN weights are learned
on that run by the model's own observe/record (EKF), one W per step; both implementations
read the same W at every step, so the slow weight copies and the envelopes are exercised.

Bounds, per output y ∈ (ωrd rad/s, Vyd m/s, βd rad) with floors s = (0.1, 1.0, 0.05):
  float64: |Δy| ≤ 256 · 2^-53 · (|y| + s) ≈ 2.8e-14 (|y| + s). Not bit-exact because numpy
    evaluates the (Vy, ωr) coefficient collapse with np.matmul (BLAS summation order) and
    tanh with its own SIMD routine, the C code with a sequential sum and libm (≈ 1 ulp
    each); cancellation in the coefficients (literal form: |W| up to ≈ 34 for O(1) outputs)
    and the 2×2 Newton / linear solves amplify that (the chain argument of float32 below,
    with u = 2^-53). Measured ≤ 27 u (|y| + s) = 3.0e-15 (|y| + s).
  float32 (C float build vs the float32 numpy model, whose reference maths is float64 on
    float32 weights): |Δy| ≤ 256 · 2^-24 · (|y| + s) ≈ 1.5e-5 (|y| + s). Each reference is
    the end of a chain of ≈ 30 float roundings (collapse 4 terms, residual 4 terms, up to
    3 Newton steps, blend and guard), each ≤ u = 2^-24 relative to operands of the size of
    (|y| + s), amplified up to ≈ 8× by the 2×2 solves (|det| small next to the entries);
    30 · 8 ≈ 256. Measured ≤ 64 u (|y| + s) (literal form), ≤ 13 u for the increment form.
Envelopes, blend weight, learned gain: the same bounds (floor 1); Algorithm 1's cost_last
(a small residual, cancellation): floor 0.1 m/s.
Discrete decisions (grid argmin, Newton acceptance, convergence, fallbacks, guard activity,
rounds) must agree exactly step by step in both precisions on these data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import PredictionContext
from controller.core.model.rhonn import RhonnConfig, RhonnModel
from controller.core.params import load_vehicle_params
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import make_rhonn_references
from controller.core.references.linear import LinearReferences
from controller.native import config as native_config
from controller.native.build_tools import NoCompilerError
from controller.native.controller import ArrayView, NativeReferences
from controller.native.module_ffi import build_module

TS = 0.05
N_STEPS = 400
P = load_vehicle_params()
SOURCES = ("rhonn.c", "slow_weights.c", "refs_alg1.c", "refs_intent.c", "sideslip_guard.c",
           "refs.c")
SCALE = np.array([0.1, 1.0, 0.05])          # output floors: rad/s, m/s, rad
GAMMA = {False: 256 * 2.0 ** -53, True: 256 * 2.0 ** -24}
COST_SCALE = 0.1                            # floor of the cost comparison, m/s
# the [references] defaults of default.toml that differ from RhonnRefConfig's
DEFAULTS = dict(intent_ay_margin=1.15, blend_beta_lo=0.01745, blend_beta_hi=0.05236,
                guard_gain_per_s=2.5, guard_beta_rad=0.05236, guard_lead_s=0.4)
GUARD_LEAD_S = 0.4                          # [references] guard_lead_s of the default
NAN_ROWS = {120: 5, 140: 1, 160: 2, 300: 0, 310: 3}   # step -> input column set to NaN
NAN_W_STEP = 330                                      # a step with a non-finite weight


# ---------------------------------------------------------------------- data
def simulate(seed: int = 3) -> np.ndarray:
    """(N, 6) rows [vx m/s, vy m/s, r rad/s, δw rad, Tt N·m, ay m/s²] of a nonlinear
    single-track car (tanh tyres, 10 sub-steps per period) with seeded sensor noise."""
    rng = np.random.default_rng(seed)
    m, iz, lf, lr = P.mass_kg, P.yaw_inertia_kgm2, P.lf_m, P.lr_m
    cf, cr = abs(P.cf_axle_n_per_rad), abs(P.cr_axle_n_per_rad)
    fzf, fzr = m * 9.81 * lr / (lf + lr), m * 9.81 * lf / (lf + lr)
    vx, vy, r = 1.5, 0.0, 0.0
    rows = []
    for k in range(N_STEPS):
        t = k * TS
        ax = 4.0 if t < 5.0 else (-9.0 if t > 17.8 else 0.0)
        if t < 6.0:
            dw = 0.01 * math.sin(1.3 * t)
        elif t < 10.0:
            dw = 0.02 * math.sin(math.pi * (t - 6.0))
        elif t < 12.0:
            dw = 0.0
        elif t < 15.5:
            dw = 0.028
        elif t < 16.0:
            dw = 0.0
        else:
            dw = -0.03 * math.sin(3.0 * (t - 16.0))
        mu = 0.45 if 11.0 < t < 16.5 else 0.9
        ay = 0.0
        h = TS / 10
        for _ in range(10):
            fyf = mu * fzf * math.tanh(cf * (dw - (vy + lf * r) / max(vx, 1.0)) / (mu * fzf))
            fyr = mu * fzr * math.tanh(-cr * (vy - lr * r) / max(vx, 1.0) / (mu * fzr))
            ay = (fyf * math.cos(dw) + fyr) / m
            dr = (lf * fyf * math.cos(dw) - lr * fyr) / iz
            vy += h * (ay - vx * r)
            r += h * dr
            vx = max(vx + h * ax, 0.5)
        rows.append((vx + rng.normal(0, 0.02), vy + rng.normal(0, 0.01),
                     r + rng.normal(0, 0.002), dw, m * P.wheel_radius_m * ax,
                     ay + rng.normal(0, 0.05)))
    return np.array(rows)


def learn(seq: np.ndarray, form: str) -> np.ndarray:
    """(N, 3, 15): the EKF-learned W after each step (series-parallel, ΔM = 0)."""
    model = RhonnModel(P, RhonnConfig(form=form), TS, dtype=np.float64)
    ctx = PredictionContext(ts=TS)
    out = np.zeros(3)
    ws = []
    for vx, vy, r, dw, tt, _ay in seq:
        x = np.array([vx, vy, r])
        model.observe(x, learn=True)
        ctx.delta_w, ctx.total_torque = float(dw), float(tt)
        model.record(x, 0.0, ctx, out)
        ws.append(model.W.copy())
    w = np.array(ws)
    w[NAN_W_STEP, 1, 4] = np.nan
    return w


@pytest.fixture(scope="module")
def data() -> dict[str, Any]:
    seq = simulate()
    ws = {"increment": learn(seq, "increment"), "literal": learn(seq, "literal"),
          "cold": np.zeros((N_STEPS, 3, 15))}   # cold start W0 = 0, learning off
    for k, col in NAN_ROWS.items():
        seq[k, col] = np.nan
    return {"seq": seq, "W": ws}


@dataclass
class Lib:
    """One build of some core modules: its cffi module (``ffi``; functions and constants
    in ``clib``) and its precision (real_t float when ``f32``)."""

    module: Any
    f32: bool

    @property
    def ffi(self) -> Any:
        return self.module.ffi

    @property
    def clib(self) -> Any:
        return self.module.lib

    def reals(self, a: np.ndarray) -> Any:
        """``real_t *`` on the memory of ``a`` (C-contiguous, of the build's real_t)."""
        if a.dtype != np_dtype(self.f32) or not a.flags.c_contiguous:
            raise ValueError(f"need a C-contiguous {np.dtype(np_dtype(self.f32))} array")
        return self.ffi.cast("real_t *", self.ffi.from_buffer(a))


def build_lib(sources: tuple[str, ...], out_dir: Path, f32: bool, name: str) -> Lib:
    """``sources`` (names in controller/native/src) in one precision, as a Lib."""
    try:
        module = build_module(sources, out_dir, defines=("RH_FLOAT32",) if f32 else (),
                              name=name)
    except NoCompilerError as e:
        pytest.skip(str(e))
    lib = Lib(module, f32)
    assert lib.ffi.sizeof("real_t") == np.dtype(np_dtype(f32)).itemsize
    return lib


def np_dtype(float32: bool = False) -> type[np.floating[Any]]:
    """numpy's real_t of the build."""
    return np.float32 if float32 else np.float64


def init_structs(lib: Lib, cfg: RhonnRefConfig, params: Any) -> tuple[Any, Any]:
    """The two structs rh_refs_init reads (rh_refs_config_t, rh_vehicle_t), filled as
    production fills them (controller/native/config.py)."""
    c = lib.ffi.new("rh_refs_config_t *")
    native_config.refs_config(lib.module, c[0], cfg)
    v = lib.ffi.new("rh_vehicle_t *")
    native_config.fill(lib.module, v[0], params)
    return c, v


def model_view(lib: Lib, model: Any, w: np.ndarray) -> Any:
    """rh_rhonn_view_t (rhonn.h) of a RhonnModel (its mu, beta, form) reading the weights
    ``w``, a C-contiguous (3, 15) array of the build's real_t that the caller keeps alive
    (e.g. the model's own W when its dtype matches)."""
    if w.size != lib.clib.RH_NW:
        raise ValueError(f"W must have {lib.clib.RH_NW} entries")
    v = lib.ffi.new("rh_rhonn_view_t *")
    v.W = lib.reals(w)
    for i in range(lib.clib.RH_NXI):
        v.mu[i], v.beta[i] = float(model._mu[i]), float(model._beta[i])
    v.increment = 1 if model.increment else 0
    return v


def refs_state(lib: Lib, st: Any) -> NativeReferences:
    """The rh_refs_t ``st`` through production's state access (controller/native/controller.py
    NativeReferences: get_state / set_state with the Python generators' keys)."""
    return NativeReferences(ArrayView(lib.module), st)


@pytest.fixture(scope="module")
def libs(tmp_path_factory: pytest.TempPathFactory) -> dict[bool, Lib]:
    out_dir: Path = tmp_path_factory.mktemp("native_refs")
    res = {}
    for f32 in (False, True):
        lib = build_lib(SOURCES, out_dir, f32, "refs32" if f32 else "refs64")
        assert lib.clib.rh_refs_sizeof_state() == lib.ffi.sizeof("rh_refs_t")
        assert lib.clib.rh_refs_sizeof_config() == lib.ffi.sizeof("rh_refs_config_t")
        res[f32] = lib
    return res


# ---------------------------------------------------------------------- pair runner
class Pair:
    """The numpy generator and the C one on the same model weights and inputs."""

    def __init__(self, lib: Lib, cfg: RhonnRefConfig, weights: str,
                 c_cfg: RhonnRefConfig | None = None) -> None:
        """weights: key of data["W"] ("increment", "literal": learned; "cold": W = 0)."""
        self.lib = lib
        dt = np_dtype(lib.f32)
        form = "literal" if weights == "literal" else "increment"
        self.model = RhonnModel(P, RhonnConfig(form=form), TS, dtype=dt)
        self.py = make_rhonn_references(self.model, P, cfg)
        self.st = lib.ffi.new("rh_refs_t *")
        c, v = init_structs(lib, c_cfg or cfg, P)
        assert lib.clib.rh_refs_init(self.st, c, v) == 0
        self.w = np.zeros((3, 15), dt)
        self.view = model_view(lib, self.model, self.w)
        self.out = lib.ffi.new("real_t[3]")
        inner = getattr(self.py, "inner", self.py)
        self.alg1 = getattr(inner, "fixed_point", inner if hasattr(inner, "rounds_last") else None)
        self.intent = getattr(inner, "demand", inner)
        self.intent = self.intent if hasattr(self.intent, "fallbacks") else None

    def set_w(self, w: np.ndarray) -> None:
        self.model.W[:] = w
        self.w[:] = w

    def step(self, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One call of both on the row rounded to the working precision."""
        args = [float(np_dtype(self.lib.f32)(x)) for x in row]
        a = np.array(self.py.compute(*args), dtype=float)
        self.lib.clib.rh_refs_compute(self.st, self.view, *args, self.out)
        return a, np.array(list(self.out), dtype=float)

    def counters(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(py, c) integer diagnostics that must agree exactly."""
        st, py, c = self.st, [], []
        if self.alg1 is not None:
            py += [self.alg1.not_converged, self.alg1.rounds_last]
            c += [st.alg1.not_converged, st.alg1.rounds_last]
        if self.intent is not None:
            py.append(self.intent.fallbacks)
            c.append(st.intent.fallbacks)
        if hasattr(self.py, "active_calls"):
            py.append(self.py.active_calls)
            c.append(st.guard.active_calls)
        return tuple(py), tuple(c)

    def reals(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(py, c, scale) real-valued state compared within the bound."""
        st, py, c, sc = self.st, [], [], []
        if self.alg1 is not None:
            py += [self.alg1.ay_envelope, self.alg1.cost_last]
            c += [st.alg1.ay_envelope, st.alg1.cost_last]
            sc += [1.0, COST_SCALE]
        if self.intent is not None:
            py += [self.intent.ay_envelope, self.intent.gain_last]
            c += [st.intent.ay_envelope, st.intent.gain_last]
            sc += [1.0, 1.0]
        if hasattr(self.py, "weight_last"):
            py.append(self.py.weight_last)
            c.append(st.weight_last)
            sc.append(1.0)
        return np.array(py, float), np.array(c, float), np.array(sc)


def within(a: np.ndarray, b: np.ndarray, scale: np.ndarray, gamma: float) -> np.ndarray:
    """Elementwise |a − b| ≤ γ (|a| + scale); non-finite values must be identical (NaN where
    both are NaN)."""
    both_nan = np.isnan(a) & np.isnan(b)
    with np.errstate(invalid="ignore"):
        ok = (a == b) | (np.isfinite(a) & np.isfinite(b)
                         & (np.abs(a - b) <= gamma * (np.abs(a) + scale)))
    return both_nan | ok


def run_sequence(pair: Pair, data: dict[str, Any], weights: str, steps: range,
                 gamma: float) -> float:
    """Step both over ``steps``; assert outputs, counters and state; the max normalised
    output error |Δy| / (|y| + s) (finite rows)."""
    seq, ws = data["seq"], data["W"][weights]
    worst = 0.0
    for k in steps:
        pair.set_w(ws[k])
        a, b = pair.step(seq[k])
        assert within(a, b, SCALE, gamma).all(), f"step {k}: numpy {a} vs C {b}"
        pc, cc = pair.counters()
        assert pc == cc, f"step {k}: counters numpy {pc} vs C {cc}"
        pr, cr, sc = pair.reals()
        assert within(pr, cr, sc, gamma).all(), f"step {k}: state numpy {pr} vs C {cr}"
        fin = np.isfinite(a) & np.isfinite(b)
        if fin.any():
            worst = max(worst, float((np.abs(a - b) / (np.abs(a) + SCALE))[fin].max()))
    return worst


CASES: dict[str, tuple[str, RhonnRefConfig]] = {
    "algorithm1": ("increment", RhonnRefConfig(kind="algorithm1")),
    "algorithm1-slow-n7": ("increment", RhonnRefConfig(kind="algorithm1", slow_tau_s=0.5,
                                                       grid_n=7, max_rounds=4,
                                                       newton_iters=2)),
    "algorithm1-literal-guard": ("literal", RhonnRefConfig(kind="algorithm1",
                                                           guard_gain_per_s=5.0)),
    "intent-slow-lead-cap": ("increment", RhonnRefConfig(kind="intent", slow_tau_s=0.3,
                                                         intent_lead_s=0.1,
                                                         intent_ay_margin=1.15)),
    "intent-literal": ("literal", RhonnRefConfig(kind="intent")),
    "blend-guard": ("increment", RhonnRefConfig(kind="blend", **DEFAULTS)),
    "demand-default": ("increment", RhonnRefConfig(kind="demand", **DEFAULTS)),
    "demand-default-cold": ("cold", RhonnRefConfig(kind="demand", **DEFAULTS)),
    "intent-cold": ("cold", RhonnRefConfig(kind="intent")),
    "demand-lead-slow": ("increment", RhonnRefConfig(kind="demand", intent_lead_s=0.15,
                                                     intent_ay_margin=1.15,
                                                     slow_tau_s=0.4)),
    "guard-only-algorithm1": ("increment", RhonnRefConfig(kind="algorithm1", **{
        k: v for k, v in DEFAULTS.items() if k.startswith("guard")})),
    # the guard on β alone (no look-ahead; the default acts on β + T·(ay/Vx − ωr))
    "demand-guard-on-beta": ("increment", RhonnRefConfig(kind="demand", **{
        **DEFAULTS, "guard_lead_s": 0.0, "guard_gain_per_s": 5.0})),
    # the demand references without their friction limit (intent_ay_margin = 0)
    "demand-no-friction-limit": ("increment", RhonnRefConfig(kind="demand", **{
        **DEFAULTS, "intent_ay_margin": 0.0})),
    # a zero-width blend band (β_hi = β_lo): the weight's span floored at 1e-6 rad, a switch
    "blend-zero-band": ("increment", RhonnRefConfig(kind="blend", **{
        **DEFAULTS, "blend_beta_hi": DEFAULTS["blend_beta_lo"]})),
    "algorithm1-literal-guard-lead": ("literal", RhonnRefConfig(
        kind="algorithm1", guard_gain_per_s=5.0, guard_lead_s=GUARD_LEAD_S)),
}


def test_default_case_is_default_toml() -> None:
    """"demand-default" is the shipped [references] table with the earlier default's kind and
    guard: the shipped kind is "grip", whose refs-module part is Algorithm 1 without a guard
    (grip_demand.c blends it in; the controller-level tests cover that), so the cases here
    run the same numbers the shipped design feeds its Algorithm 1."""
    import tomllib
    from dataclasses import replace
    from importlib import resources

    text = resources.files("controller").joinpath("config/default.toml").read_text()
    shipped = RhonnRefConfig.from_dict(tomllib.loads(text)["references"])
    assert shipped.kind == "grip" and shipped.guard_gain_per_s == 0.0
    assert replace(shipped, kind="demand", guard_gain_per_s=2.5) == CASES["demand-default"][1]


def test_sequence_covers_the_branches(data: dict[str, Any]) -> None:
    """The data reach every regime the bounds are claimed for."""
    seq = data["seq"]
    ok = np.isfinite(seq).all(axis=1)
    vx, vy = seq[ok, 0], seq[ok, 1]
    beta = np.abs(vy) / np.maximum(vx, 3.0)
    assert (vx < 3.0).sum() >= 5                                    # below v_min
    assert ((beta > 0.01745) & (beta < 0.05236)).sum() >= 30         # blend range
    assert (beta > 0.05236).sum() >= 30                               # guard, Algorithm 1
    assert ((beta < 0.005) & (vx > 10.0)).sum() >= 30                # straight running


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
@pytest.mark.parametrize("case", list(CASES))
def test_matches_numpy(case: str, f32: bool, libs: dict[bool, Lib],
                       data: dict[str, Any]) -> None:
    weights, cfg = CASES[case]
    pair = Pair(libs[f32], cfg, weights)
    worst = run_sequence(pair, data, weights, range(N_STEPS), GAMMA[f32])
    assert worst <= GAMMA[f32]
    # the branches were taken (counters of the run)
    st = pair.st
    if pair.alg1 is not None:
        assert st.alg1.not_converged < N_STEPS - 20
        assert st.alg1.not_converged > 0 or weights == "cold"
    if "guard" in case or case == "demand-default":
        assert st.guard.active_calls >= 10
    if case in ("intent-literal", "intent-cold"):
        assert st.intent.fallbacks > 0
    # the state dict as the Python get_state (production's NativeReferences on this build)
    for key, val in refs_state(pair.lib, st).get_state().items():
        ref = pair.py.get_state()[key]
        np.testing.assert_allclose(val, ref, rtol=GAMMA[f32] * 16, atol=GAMMA[f32] * 16)


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
def test_reset_and_state_restore(f32: bool, libs: dict[bool, Lib],
                                 data: dict[str, Any]) -> None:
    """reset() mid-run, and a C state moved into a fresh struct, continue as numpy does."""
    weights, cfg = CASES["demand-lead-slow"]
    cfg = replace(cfg, kind="blend")
    pair = Pair(libs[f32], cfg, weights)
    g = GAMMA[f32]
    run_sequence(pair, data, weights, range(0, 150), g)
    pair.py.reset()
    libs[f32].clib.rh_refs_reset(pair.st)
    libs[f32].clib.rh_refs_set_slow_weights(pair.st, libs[f32].reals(pair.w))
    run_sequence(pair, data, weights, range(150, 250), g)
    fresh = Pair(libs[f32], cfg, weights)
    refs_state(fresh.lib, fresh.st).set_state(refs_state(pair.lib, pair.st).get_state())
    fresh.py.set_state(pair.py.get_state())
    for name in ("not_converged", "rounds_last"):   # counters are not in get_state
        setattr(fresh.st.alg1, name, getattr(pair.st.alg1, name))
        setattr(fresh.alg1, name, getattr(pair.alg1, name))
    fresh.st.intent.fallbacks = pair.st.intent.fallbacks
    fresh.intent.fallbacks = pair.intent.fallbacks
    fresh.st.intent.gain_last = pair.st.intent.gain_last
    fresh.intent.gain_last = pair.intent.gain_last
    fresh.st.alg1.cost_last = pair.st.alg1.cost_last
    fresh.alg1.cost_last = pair.alg1.cost_last
    run_sequence(fresh, data, weights, range(250, N_STEPS), g)


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
def test_guard_lead_changes_the_references_on_these_data(f32: bool, libs: dict[bool, Lib],
                                                          data: dict[str, Any]) -> None:
    """The look-ahead cases are not the T = 0 cases in disguise: on these data the lead
    changes ωrd on some steps and the number of guarded calls (in numpy and C alike), and a
    C generator without the lead (guard_lead_s = 0) fails the comparison with numpy's T."""
    weights, cfg = CASES["demand-default"]
    assert cfg.guard_lead_s == GUARD_LEAD_S
    base = replace(cfg, guard_lead_s=0.0)
    with_lead, without = Pair(libs[f32], cfg, weights), Pair(libs[f32], base, weights)
    seq, ws = data["seq"], data["W"][weights]
    differ = 0
    for k in range(N_STEPS):
        with_lead.set_w(ws[k])
        without.set_w(ws[k])
        a, b = with_lead.step(seq[k])[1], without.step(seq[k])[1]
        differ += int(np.isfinite(a[0]) and np.isfinite(b[0]) and a[0] != b[0])
    assert differ >= 10
    assert with_lead.st.guard.active_calls != without.st.guard.active_calls
    assert with_lead.py.active_calls == with_lead.st.guard.active_calls
    ported_without_lead = Pair(libs[f32], cfg, weights, c_cfg=base)
    with pytest.raises(AssertionError):
        run_sequence(ported_without_lead, data, weights, range(N_STEPS), GAMMA[f32])


def test_detects_a_port_error(libs: dict[bool, Lib], data: dict[str, Any]) -> None:
    """The comparison fails for a C generator configured 1e-6 off the numpy one."""
    weights, cfg = CASES["demand-default"]
    pair = Pair(libs[False], cfg, weights, c_cfg=replace(cfg, eta=cfg.eta * (1.0 + 1e-6)))
    with pytest.raises(AssertionError):
        run_sequence(pair, data, weights, range(N_STEPS), GAMMA[False])


@pytest.mark.parametrize("change,code", [
    (dict(grid_n=17), -2), (dict(grid_n=8), -2), (dict(grid_n=1), -2),
    (dict(max_rounds=17), -3), (dict(max_rounds=-1), -3), (dict(newton_iters=17), -4),
    (dict(ts=0.0), -5), (dict(ay_decay_s=0.0), -5), (dict(kind="linear"), -1),
    (dict(newton_iters=-1), -4), (dict(kind="algorithm1", ts=0.0), -5),
    (dict(kind="algorithm1", ay_decay_s=0.0), -5),
    (dict(grid_n=15, max_rounds=16, newton_iters=16), 0),
])
def test_init_rejects_out_of_range(change: dict[str, Any], code: int,
                                   libs: dict[bool, Lib]) -> None:
    lib = libs[False]
    st = lib.ffi.new("rh_refs_t *")
    c, v = init_structs(lib, replace(RhonnRefConfig(kind="demand"), **change), P)
    assert lib.clib.rh_refs_init(st, c, v) == code
    assert st.status == code
    if code != 0:   # an unusable generator outputs zeros, and a reset leaves it so
        w = np.zeros((3, 15))
        view = model_view(lib, RhonnModel(P, RhonnConfig(), TS), w)
        for reset in (False, True):
            if reset:
                lib.clib.rh_refs_reset(st)
                assert st.status == code
            out = lib.ffi.new("real_t[3]", [1.0, 1.0, 1.0])
            lib.clib.rh_refs_compute(st, view, 20.0, 0.5, 0.1, 0.02, 0.0, 2.0, out)
            assert list(out) == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
def test_grid_tie_goes_to_the_first_node(f32: bool, libs: dict[bool, Lib]) -> None:
    """Exact ties of the grid selection go to the first node in row-major order (np.argmin):
    a flat map (W = 0) and a centre midway between two ωr nodes (dyadic box ±2^-6 rad/s)."""
    band = 2.0 ** -6
    cfg = RhonnRefConfig(kind="algorithm1", r_band=band)
    pair = Pair(libs[f32], cfg, "cold")
    pair.set_w(np.zeros((3, 15)))
    yaw = 0.375 * band      # nodes at k·band/4: equally far from 0.25 and 0.5 band
    a, b = pair.step(np.array([10.0, 0.0, yaw, 0.0, 0.0, 0.0]))
    assert a[0] == 0.25 * band
    np.testing.assert_array_equal(a, b)


# Search configurations that reach the decisions the default tuning leaves alone (MC/DC of
# refs_alg1.c), each run over the whole sequence against numpy (outputs, counters, state).
SEARCH_EDGES: dict[str, RhonnRefConfig] = {
    # the loop bounds at their compile-time maxima (grid 15 × 15, 16 rounds, 16 Newton
    # steps); a fixed radius and a tiny ε_t, so rounds run out (for-else: not converged)
    "maxima": RhonnRefConfig(kind="algorithm1", grid_n=15, max_rounds=16, newton_iters=16,
                             eps_t=1e-12, drs_vy=0.0, drs_r=0.0),
    # a Vy radius covering ±v_lim from the first round and a small, slowly growing ωr one:
    # the box reaches one end of the ωr band rounds before the other (the "whole feasible
    # box" test with its ωr conditions false one at a time)
    "r-box-edges": RhonnRefConfig(kind="algorithm1", max_rounds=16, eps_t=1e-12,
                                  rs0_vy=100.0, rs0_r=0.004, drs_r=0.004),
    # η = ∞: every cost with an ωr residual is +∞, the selection all +∞ (np.argmin's first
    # node); the NaN weight step keeps a NaN selection in the same run
    "infinite-eta": RhonnRefConfig(kind="algorithm1", eta=math.inf),
    # the same on the literal model (the all-+∞ selection's cost without the increment form)
    "infinite-eta-literal": RhonnRefConfig(kind="algorithm1", eta=math.inf),
}


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
@pytest.mark.parametrize("case", list(SEARCH_EDGES))
def test_search_edges_match_numpy(case: str, f32: bool, libs: dict[bool, Lib],
                                  data: dict[str, Any]) -> None:
    """The configurations of SEARCH_EDGES step for step as numpy; each reaches its edge on
    these data (rounds run out; the box covers one ωr end first; an all-+∞ selection).
    "maxima" and "r-box-edges" in float64 only: their ε_t = 1e-12 is below what a float32
    cost resolves, so convergence there is the precision's decision, not the port's."""
    if f32 and not case.startswith("infinite-eta"):
        pytest.skip("ε_t below the float32 resolution of the cost")
    cfg = SEARCH_EDGES[case]
    weights = "literal" if case.endswith("-literal") else "increment"
    pair = Pair(libs[f32], cfg, weights)
    seq, ws = data["seq"], data["W"][weights]
    rounds, costs, edges = [], [], set()
    for k in range(N_STEPS):
        pair.set_w(ws[k])
        a, b = pair.step(seq[k])
        assert within(a, b, SCALE, GAMMA[f32]).all(), f"step {k}: numpy {a} vs C {b}"
        pc, cc = pair.counters()
        assert pc == cc, f"step {k}: counters numpy {pc} vs C {cc}"
        pr, cr, sc = pair.reals()
        assert within(pr, cr, sc, GAMMA[f32]).all(), f"step {k}: numpy {pr} vs C {cr}"
        rounds.append(pair.alg1.rounds_last)
        costs.append(pair.alg1.cost_last)
        if case == "r-box-edges":
            edges |= _r_box_edges(pair, seq[k], cfg)
    if case == "maxima":
        assert rounds.count(16) > 10
    elif case == "r-box-edges":
        assert edges == {"lo", "hi"}, edges
    else:
        assert sum(c == math.inf for c in costs) > 10 and not all(c == math.inf for c in costs)


def _r_box_edges(pair: Pair, row: np.ndarray, cfg: RhonnRefConfig) -> set[str]:
    """Which end of the ωr band ("lo": r_lo, "hi": r_hi) the search box of some round
    reached first while the other was still inside (numpy's own geometry of this step)."""
    vx, _vy, yaw, dw = (float(x) for x in row[:4])
    if not (math.isfinite(vx) and math.isfinite(dw) and vx >= cfg.v_min):
        return set()
    alg = pair.alg1
    r_lim = alg.a_max() / vx
    r_kin = cfg.r_kin_factor * vx * dw / P.wheelbase_m
    r_lo = max(min(r_kin, 0.0) - cfg.r_band, -r_lim)
    r_hi = min(max(r_kin, 0.0) + cfg.r_band, r_lim)
    cr = min(max(yaw if math.isfinite(yaw) else 0.0, r_lo), r_hi)
    out = set()
    for k in range(alg.rounds_last):
        rr = cfg.rs0_r + k * cfg.drs_r
        lo_in, hi_in = cr - rr <= r_lo, cr + rr >= r_hi
        if lo_in != hi_in:
            out.add("lo" if lo_in else "hi")
    return out


@pytest.mark.parametrize("iters", [15, 16])
def test_newton_runs_its_full_iteration_budget_like_numpy(iters: int,
                                                          libs: dict[bool, Lib]) -> None:
    """``it < RH_REFS_NEWTON_MAX && it < newton_iters`` (refs_alg1.c newton) with the budget
    at its maximum, 16: a map whose fixed point (0, 0) is a double root (residuals
    S(Vy) − S(ωr) and S(Vy)·S(ωr): W[1,1] = 1, W[1,2] = −1, W[2,7] = 1, increment form), so
    Newton converges linearly, each step halving the distance and quartering the cost, and
    ε_t = 0 never stops it early: every one of the 16 steps is accepted. C equals numpy, and
    the 16th step quarters the cost of the 15th."""
    w = np.zeros((3, 15))
    w[1, 1], w[1, 2], w[2, 7] = 1.0, -1.0, 1.0
    costs = []
    for n in (iters - 1, iters):
        cfg = RhonnRefConfig(kind="algorithm1", eps_t=0.0, max_rounds=1, newton_iters=n)
        pair = Pair(libs[False], cfg, "increment")
        pair.set_w(w)
        a, b = pair.step(np.array([10.0, 0.13, 0.013, 0.02, 0.0, 2.0]))
        assert within(a, b, SCALE, GAMMA[False]).all(), (n, a, b)
        pr, cr, sc = pair.reals()
        assert within(pr, cr, sc, GAMMA[False]).all(), (n, pr, cr)
        costs.append(float(pair.st.alg1.cost_last))
    assert 0.2 < costs[1] / costs[0] < 0.3, costs


def _steady_w(case: str) -> np.ndarray:
    """Weights of the intent references' steady-state solve, increment form: a11 = W[1,1],
    a12 = W[1,2], a21 = W[2,1], a22 = W[2,2]; rhs from the δw terms W[1,3], W[2,3]."""
    w = np.zeros((3, 15))
    if case == "stable":        # det 1, trace −2: the solve
        w[1, 1], w[2, 2], w[1, 3], w[2, 3] = -1.0, -1.0, 0.5, 0.25
    elif case == "unstable":    # det 1 > 1e-9 but trace +2 ≥ 0: refused
        w[1, 1], w[2, 2], w[1, 3], w[2, 3] = 1.0, 1.0, 0.5, 0.25
    elif case == "xi-v-overflow":   # det 1e10, trace < 0, a22·rhs_v overflows: ξv = ±∞
        w[1, 1], w[2, 2], w[1, 3] = -1.0, -1e10, 1e300
    else:                       # "xi-r-overflow": a11·rhs_r overflows, ξv = 0
        w[1, 1], w[2, 2], w[2, 3] = -1e10, -1.0, 1e300
    return w


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")
@pytest.mark.parametrize("case", ["stable", "unstable", "xi-v-overflow", "xi-r-overflow"])
def test_intent_steady_state_refusals_match_numpy(case: str, libs: dict[bool, Lib]) -> None:
    """``finite(det) && det > 1e-9 && a11 + a22 < 0`` and ``finite(ξv) && finite(ξr)``
    (refs_intent.c steady response), one condition at a time: a stable map is solved, an
    unstable one (trace ≥ 0 with a positive determinant) and a solve that overflows in one
    component are refused; the references then fall back to the neutral-steer values,
    counted in ``fallbacks``, as in numpy. Float64 only: the overflow needs weights beyond
    float32's range."""
    pair = Pair(libs[False], RhonnRefConfig(kind="intent"), "increment")
    pair.set_w(_steady_w(case))
    a, b = pair.step(np.array([15.0, 0.2, 0.1, 0.03, 0.0, 2.0]))
    assert within(a, b, SCALE, GAMMA[False]).all(), (case, a, b)
    (py_fb,), (c_fb,) = pair.counters()
    assert py_fb == c_fb == (0 if case == "stable" else 1)


@pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])
def test_bicycle_demand_beyond_the_guard_speed_matches_numpy(f32: bool, libs: dict[bool, Lib],
                                                             data: dict[str, Any]) -> None:
    """The demand design's bicycle references above the packaged car's guard speed
    (1 + K·vx² < 0.5 for this oversteering car: the denominator floored at DEN_MIN) and
    below it, step for step as numpy (outputs and counters), on learned weights."""
    k_grad = LinearReferences(P).understeer_gradient
    assert k_grad < 0.0
    pair = Pair(libs[f32], RhonnRefConfig(kind="demand"), "increment")
    pair.set_w(data["W"]["increment"][N_STEPS - 1])
    for vx in (20.0, 45.0, 50.0, 60.0, 75.0):
        for dw in (0.01, -0.02):
            a, b = pair.step(np.array([vx, 0.2, vx * dw / P.wheelbase_m, dw, 0.0, 2.0]))
            assert within(a, b, SCALE, GAMMA[f32]).all(), (vx, dw, a, b)
            pc, cc = pair.counters()
            assert pc == cc, (vx, dw, pc, cc)
    assert 1.0 + k_grad * 60.0 ** 2 < 0.5

