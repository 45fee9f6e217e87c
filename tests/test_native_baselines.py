"""Back-to-back tests of the C physics baselines (controller/native/src: bicycle.c,
seven_dof.c, mf_tyre.c, substep.c, linear_refs.c) against the numpy/Python reference
classes (BicycleModel, SevenDofPrediction mf/linear, LinearReferences, tyre.mf_eval), both
precisions, through a cffi module whose declarations are generated from the modules' headers
(controller/native/module_ffi.py: no layout is written here; the configuration structs are
filled by controller/native/config.py, as in production).

Bounds (componentwise, c = C result, ref = Python result, u = unit roundoff):

* float64 build: |c − ref| ≤ 1e-12·(|ref| + s). The C code performs the reference's
  operations in the reference's order with the same libm (glibc, as CPython's math) and
  -ffp-contract=off, so agreement is expected to the last bit or within a few ulps
  (measured: see the report); 1e-12 leaves room for a libm or compiler difference of a few
  ulps amplified through the ≤ 13 sub-steps while any modelling error (a wrong term, sign,
  clamp or branch) is many orders of magnitude larger.
* float32 build vs the float64 reference evaluated at the float32-rounded inputs (the Python
  reference has no dtype: it computes in Python floats): |c − ref| ≤ K·u32·(|ref| + s),
  u32 = 2⁻²⁴. Derivation: each output is a chain of at most a few hundred roundings per
  sub-step (forward error γ_n ≈ n·u on terms of magnitude ≤ s), the parameters (m, Iz, Cf,
  MF coefficients) enter rounded once (relative u each, condition ≈ 1), and the Heun map is
  contractive for h·λ ≤ 0.5, so rounding does not grow across sub-steps beyond their count
  (≤ 13 here). The tyre's slip angle atan2(v_w, u_w) is well conditioned (relative error ≈ u
  in both arguments → ≈ u absolute in α), as are exp/sin/cos/atan. The Jacobian entries are
  the worst: S+ = S + h/2·(J·S + J1·S1) sums ~10 products per entry per sub-step with
  |h·J| up to ≈ 2 (h·vx), i.e. ≈ 20–40 roundings on operands of the column scale. K = 64.
  Measured worst case over 20 seeds × 300 rows: 11 u (A of 7dof-mf), ≤ 7 u for B, ≤ 1.3 u
  for xn.
* s is the column scale: the largest |ref| of that output component over the sample set
  (a normwise floor for entries that are small by cancellation, e.g. ∂vx+/∂vy or vy after a
  near-zero step). It keeps the test honest: an error of K·u·s on the largest entry is still
  3–4 orders of magnitude below any physically meaningful difference.

The linear references are a closed formula; their float32 bound is derived per output
(see test_linear_refs).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.core.interfaces import PredictionContext
from controller.core.model.bicycle import BicycleModel
from controller.core.model.seven_dof import SevenDofPrediction
from controller.core.model.tyre import load_mf_tyres, mf_eval, mf_force
from controller.core.params import load_vehicle_params
from controller.core.references.linear import LinearReferences
from controller.native import config as native_config
from controller.native.build_tools import SRC_DIR, NoCompilerError
from controller.native.module_ffi import build_module

P = load_vehicle_params()
TYRES = load_mf_tyres()
SOURCES = ("substep.c", "mf_tyre.c", "bicycle.c", "seven_dof.c", "linear_refs.c")
U32 = 2.0 ** -24
TOL = {"f64": 1e-12, "f32": 64 * U32}
N_SAMPLES = 300


@dataclass
class Native:
    """One compiled build: the cffi module, its precision and the numpy dtype of real_t."""

    module: Any
    prec: str
    dtype: Any

    @property
    def lib(self) -> Any:
        return self.module.lib

    @property
    def ffi(self) -> Any:
        return self.module.ffi

    def arr(self, n: int) -> np.ndarray:
        return np.zeros(n, dtype=self.dtype)

    def ptr(self, a: np.ndarray) -> Any:
        assert a.dtype == self.dtype and a.flags.c_contiguous
        return self.ffi.from_buffer("real_t[]", a)

    def ctx(self, delta: float, tt: float, ts: float) -> Any:
        """An rh_ctx_t (rh_params.h) with δw rad, Tt N·m, ts s (values rounded to real_t)."""
        c = self.ffi.new("rh_ctx_t *")
        c.delta_w, c.total_torque, c.ts = delta, tt, ts
        return c

    def new(self, ctype: str, src: Any = None, **values: Any) -> Any:
        """A new ``ctype *``, its fields filled from ``src``'s attributes of the same names
        (controller/native/config.py's fill) when given."""
        p = self.ffi.new(f"{ctype} *")
        if src is not None:
            native_config.fill(self.module, p[0], src, **values)
        return p

    def vehicle(self, params: Any = P) -> Any:
        return self.new("rh_vehicle_t", params)

    def curve(self, curve: Any) -> Any:
        """rh_mf_curve_t (working precision) of an MfCurve."""
        return self.new("rh_mf_curve_t", curve)


def build(prec: str, tmp: Path, sources: tuple[str | Path, ...] = SOURCES,
          name: str = "rh_baselines") -> Native:
    defines = ("RH_FLOAT32",) if prec == "f32" else ()
    headers = [Path(s).with_suffix(".h").name for s in SOURCES]
    try:
        module = build_module(sources, tmp, defines=defines, headers=headers, name=name)
    except NoCompilerError as exc:
        pytest.skip(str(exc))
    return Native(module, prec, np.float32 if prec == "f32" else np.float64)


@pytest.fixture(scope="module", params=["f64", "f32"])
def nat(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Native:
    return build(request.param, tmp_path_factory.getbasetemp() / "native_baselines")


# --- samples -----------------------------------------------------------------------------------
def samples(seed: int, n: int = N_SAMPLES) -> np.ndarray:
    """(n, 7) rows [vx m/s, vy m/s, r rad/s, ΔM N·m, δw rad, Tt N·m, ts s] over the operating
    range: uniform vx 3–40, vy ±3, r ±1, δ ±0.15, Tt ±2000, ΔM ±1800 (first half); a
    near-limit block with body slip |vy/vx| ≤ 0.2 and |vx·r| ≤ 12 m/s² at the same speeds
    (tyres at and past their MF peak with realistic loads); a few low-speed rows (vx −2…3,
    where the V_LOW guard and up to ~13 sub-steps act). ts ∈ {0.05, 0.02, 0.01} s."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, 7))
    out[:, 0] = rng.uniform(3.0, 40.0, n)
    out[:, 1] = rng.uniform(-3.0, 3.0, n)
    out[:, 2] = rng.uniform(-1.0, 1.0, n)
    out[:, 3] = rng.uniform(-1800.0, 1800.0, n)
    out[:, 4] = rng.uniform(-0.15, 0.15, n)
    out[:, 5] = rng.uniform(-2000.0, 2000.0, n)
    out[:, 6] = rng.choice([0.05, 0.05, 0.02, 0.01], n)
    lim = slice(n // 2, n - n // 10)
    k = out[lim].shape[0]
    out[lim, 1] = out[lim, 0] * rng.uniform(-0.2, 0.2, k)
    out[lim, 2] = rng.uniform(-12.0, 12.0, k) / out[lim, 0]
    low = slice(n - n // 10, n)
    out[low, 0] = rng.uniform(-2.0, 3.0, out[low].shape[0])
    return out


def rounded(rows: np.ndarray, prec: str) -> np.ndarray:
    """The inputs as the C build sees them: float32-rounded for f32 (except ts, which the
    reference gets exact: see substep.c's ts tolerance), unchanged for f64."""
    if prec == "f64":
        return rows
    r = rows.astype(np.float32).astype(np.float64)
    r[:, 6] = rows[:, 6]
    return r


def front_slip_beyond_peak(rows: np.ndarray) -> float:
    """Fraction of rows whose front-axle slip angle (rad, small-angle estimate) is past the
    MF lateral peak at the static load (coverage check of the near-limit block)."""
    fz = P.mass_kg * 9.81 * P.lr_m / (2.0 * P.wheelbase_m)
    grid = np.linspace(0.0, 0.6, 6001)
    a_peak = grid[int(np.argmax([mf_force(TYRES.front.lateral, float(a), fz, 1.0)
                                 for a in grid]))]
    alpha = (rows[:, 1] + P.lf_m * rows[:, 2]) / np.abs(rows[:, 0]) - rows[:, 4]
    return float(np.mean(np.abs(alpha) > a_peak))


# --- comparison --------------------------------------------------------------------------------
def scaled_error(c: np.ndarray, ref: np.ndarray) -> float:
    """max over entries of |c − ref| / (|ref| + s), s = the column scale (max |ref| of that
    component over the sample set). c, ref: (n, k)."""
    s = np.max(np.abs(ref), axis=0, keepdims=True)
    return float(np.max(np.abs(c.astype(np.float64) - ref) / (np.abs(ref) + s + 1e-300)))


def run_model(nat: Native, rows: np.ndarray, model: Any, c_model: Any, fn: str
              ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Run reference and C predict / predict_linearize on all rows; {name: (c, ref)}."""
    lib = nat.lib
    c_pred = getattr(lib, f"rh_{fn}_predict")
    c_pl = getattr(lib, f"rh_{fn}_predict_linearize")
    n = rows.shape[0]
    res = {k: (np.zeros((n, m)), np.zeros((n, m)))
           for k, m in (("xn_predict", 3), ("xn", 3), ("A", 9), ("B", 3))}
    x, xn, xp, A, B = nat.arr(3), nat.arr(3), nat.arr(3), nat.arr(9), nat.arr(3)
    rx, rxn, rxp, rA, rB = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3)
    for i, (vx, vy, r, dm, d, tt, ts) in enumerate(rows):
        x[:] = (vx, vy, r)
        rx[:] = (vx, vy, r)
        ctx = nat.ctx(d, tt, ts)
        c_pred(c_model, nat.ptr(x), dm, ctx, nat.ptr(xp))
        c_pl(c_model, nat.ptr(x), dm, ctx, nat.ptr(xn), nat.ptr(A), nat.ptr(B))
        pctx = PredictionContext(delta_w=float(d), total_torque=float(tt), ts=float(ts))
        model.predict(rx, float(dm), pctx, rxp)
        model.predict_linearize(rx, float(dm), pctx, rxn, rA, rB)
        for k, c, ref in (("xn_predict", xp, rxp), ("xn", xn, rxn), ("A", A, rA.ravel()),
                          ("B", B, rB)):
            res[k][0][i] = c
            res[k][1][i] = ref
    return res


def seven_dof_config(nat: Native, linear: bool) -> Any:
    """rh_seven_dof_config_t of SevenDofPrediction(P, TYRES, linear), as production fills it."""
    cfg = nat.new("rh_seven_dof_config_t")
    native_config.seven_dof_config(nat.module, cfg[0], TYRES, linear=linear)
    return cfg


def init_bicycle(nat: Native) -> Any:
    m = nat.new("rh_bicycle_t")
    nat.lib.rh_bicycle_init(m, nat.vehicle(), native_config.BICYCLE_H_MAX_S)
    return m


def init_seven(nat: Native, linear: bool) -> Any:
    m = nat.new("rh_seven_dof_t")
    nat.lib.rh_seven_dof_init(m, nat.vehicle(), seven_dof_config(nat, linear))
    return m


MODELS: dict[str, tuple[Callable[[], Any], Callable[[Native], Any], str]] = {
    "bicycle": (lambda: BicycleModel(P), init_bicycle, "bicycle"),
    "7dof-mf": (lambda: SevenDofPrediction(P, TYRES, linear=False),
                lambda n: init_seven(n, False), "seven_dof"),
    "7dof-li": (lambda: SevenDofPrediction(P, TYRES, linear=True),
                lambda n: init_seven(n, True), "seven_dof"),
}


# --- tests -------------------------------------------------------------------------------------
def test_layout_sizes(nat: Native) -> None:
    """The binding's structs have the compiled structs' sizes, and real_t is the build's."""
    lib, ffi = nat.lib, nat.ffi
    assert ffi.sizeof("real_t") == np.dtype(nat.dtype).itemsize
    assert ffi.sizeof("rh_bicycle_t") == lib.rh_bicycle_sizeof()
    assert ffi.sizeof("rh_seven_dof_t") == lib.rh_seven_dof_sizeof()
    assert ffi.sizeof("rh_linear_refs_t") == lib.rh_linear_refs_sizeof()
    x = nat.arr(3)
    lib.rh_substep_initial_state(12.5, -0.25, 0.5, nat.ptr(x))  # initial_state: x = [vx, vy, r]
    assert x.tolist() == [12.5, -0.25, 0.5]


def test_sample_coverage() -> None:
    """The sample set reaches past the MF peak (near-limit) and the low-speed guard."""
    rows = samples(1)
    assert front_slip_beyond_peak(rows) > 0.15
    assert np.sum(np.abs(rows[:, 0]) <= 1.0) >= 5


def test_init_constants(nat: Native) -> None:
    """Config-derived constants equal the reference's (rounded to real_t)."""
    ref7 = SevenDofPrediction(P, TYRES)
    m7 = init_seven(nat, False)
    assert m7.stiff_rate == ref7.stiff_rate and m7.h_max_s == ref7.h_max
    rnd = (lambda v: float(np.float32(v))) if nat.prec == "f32" else float
    assert [m7.m, m7.iz, m7.radius, m7.mu, m7.rr, m7.rr_ramp, m7.kd] == [
        rnd(v) for v in (ref7._m, ref7._iz, ref7._R, ref7._mu, ref7._rr, ref7._rr_ramp,
                         ref7._kd)]
    for i in range(4):
        w = m7.w[i]
        got = [w.x, w.y, w.front, w.fz_static, w.kx_ax, w.ky_ay, w.c_lin, w.side, w.fz_cap,
               *(getattr(w.lateral, f) for f in ("fz0_n", "c", "d1", "d2", "k1", "k2", "k3",
                                                  "e1", "e2"))]
        xw, yw, front, fzs, kax, kay, clin, cv, side, cap = ref7._wheels[i]
        assert got == [rnd(v) for v in (
            xw, yw, 1.0 if front else 0.0, fzs, kax, kay, clin, side, cap, cv.fz0_n, cv.c,
            cv.d1, cv.d2, cv.k1, cv.k2, cv.k3, cv.e1, cv.e2)], i
    rb = BicycleModel(P)
    mb = init_bicycle(nat)
    assert mb.stiff_rate == rb.stiff_rate
    assert [mb.m, mb.iz, mb.lf, mb.lr, mb.cf, mb.cr, mb.kdm, mb.radius] == [
        rnd(v) for v in (rb._m, rb._iz, rb._lf, rb._lr, rb._cf, rb._cr, rb._kdm,
                         P.wheel_radius_m)]


@pytest.mark.parametrize("kind", list(MODELS))
def test_model_back_to_back(nat: Native, kind: str) -> None:
    """xn of predict and of predict_linearize, A and B vs the reference over N_SAMPLES rows."""
    make_ref, make_c, fn = MODELS[kind]
    rows = rounded(samples(7 + len(kind)), nat.prec)
    res = run_model(nat, rows, make_ref(), make_c(nat), fn)
    for name, (c, ref) in res.items():
        assert np.all(np.isfinite(ref)), name
        err = scaled_error(c, ref)
        print(f"{kind} {nat.prec} {name}: max scaled error {err:.3g} "
              f"({err / (U32 if nat.prec == 'f32' else 2.0 ** -53):.3g} u)")
        assert err <= TOL[nat.prec], (kind, name, err)


@pytest.mark.parametrize("kind", list(MODELS))
def test_invalid_inputs_give_nan(nat: Native, kind: str) -> None:
    """Non-finite state/input or ts outside (0, 1] s: every output NaN, like the reference."""
    make_ref, make_c, fn = MODELS[kind]
    cm, ref = make_c(nat), make_ref()
    c_pred = getattr(nat.lib, f"rh_{fn}_predict")
    c_pl = getattr(nat.lib, f"rh_{fn}_predict_linearize")
    good = (20.0, 0.5, 0.2, 100.0, 0.05, 300.0, 0.05)
    cases = [(0, math.nan), (1, math.inf), (2, -math.inf), (3, math.nan), (4, math.nan),
             (5, math.inf), (6, math.nan), (6, 0.0), (6, -0.05), (6, 1.5)]
    for idx, bad in cases:
        v = list(good)
        v[idx] = bad
        x, xn, xp, A, B = nat.arr(3), nat.arr(3), nat.arr(3), nat.arr(9), nat.arr(3)
        x[:] = v[:3]
        ctx = nat.ctx(v[4], v[5], v[6])
        c_pred(cm, nat.ptr(x), v[3], ctx, nat.ptr(xp))
        c_pl(cm, nat.ptr(x), v[3], ctx, nat.ptr(xn), nat.ptr(A), nat.ptr(B))
        rxp, rxn, rA, rB = np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3)
        pctx = PredictionContext(delta_w=v[4], total_torque=v[5], ts=v[6])
        ref.predict(np.array(v[:3]), v[3], pctx, rxp)
        ref.predict_linearize(np.array(v[:3]), v[3], pctx, rxn, rA, rB)
        assert np.all(np.isnan(rxp)) and np.all(np.isnan(rA)), (idx, bad)  # reference
        for a in (xp, xn, A, B):
            assert np.all(np.isnan(a)), (kind, idx, bad)
    # and the good case is finite (the NaN above is not a broken model)
    x, xn, A, B = nat.arr(3), nat.arr(3), nat.arr(9), nat.arr(3)
    x[:] = good[:3]
    c_pl(cm, nat.ptr(x), good[3], nat.ctx(*good[4:]), nat.ptr(xn), nat.ptr(A), nat.ptr(B))
    assert np.all(np.isfinite(np.concatenate([xn, A, B])))


def test_mf_eval(nat: Native) -> None:
    """rh_mf_eval vs tyre.mf_eval on a grid of slips (±0.6 rad, past the peak) and loads
    (FZ_MIN … cap), front and rear lateral curves, μ 1 and 0.35."""
    mu_s = (1.0, 0.35)
    s_grid = np.linspace(-0.6, 0.6, 41)
    fz_grid = np.linspace(50.0, 2.0 * TYRES.front.lateral.fz0_n, 15)
    out = nat.arr(3)
    for curve in (TYRES.front.lateral, TYRES.rear.lateral):
        cc = nat.curve(curve)
        c_rows, r_rows = [], []
        for mu in mu_s:
            for fz in fz_grid:
                for s in s_grid:
                    sr, fzr, mur = (float(nat.dtype(v)) for v in (s, fz, mu))
                    nat.lib.rh_mf_eval(cc, sr, fzr, mur, nat.ptr(out))
                    c_rows.append(out.astype(np.float64))
                    r_rows.append(mf_eval(curve, sr, fzr, mur))
        err = scaled_error(np.array(c_rows), np.array(r_rows))
        print(f"mf_eval {nat.prec}: max scaled error {err:.3g}")
        assert err <= TOL[nat.prec]


def test_linear_refs(nat: Native) -> None:
    """rh_linear_refs_compute vs LinearReferences.compute: vx −50…80 m/s (beyond the guard
    speed 46.7 m/s, so the DEN_MIN floor acts), δ ±0.15 rad, and invalid inputs → (0, 0, 0).

    float64: |c − ref| ≤ 1e-12·|ref| (same operations, same order). float32 (inputs rounded,
    reference in float64 on them), u = 2⁻²⁴: den = max(1 + K·v², 0.5) has relative error
    ≤ 4u (K rounded, v², product, sum; |K·v²| ≤ 0.5 where unfloored, den ≥ 0.5); r_ss =
    vx·δ/(L·den) adds 4 roundings and L's: ≤ 10u relative. β = δ·(lr − βk·v²)/(L·den): the
    numerator cancels near vx ≈ 11.45 m/s, so its error is ≤ 4u·|δ|·(lr + βk·v²) absolute,
    giving |Δβ| ≤ 10u·|δ|·(lr + βk·v²)/(L·den); vy_ref = β·vx: |Δvy| ≤ |vx|·|Δβ| + u·|vy|.
    The test uses 2× these bounds."""
    ref = LinearReferences(P)
    st = nat.new("rh_linear_refs_t")
    nat.lib.rh_linear_refs_init(st, nat.vehicle())
    nat.lib.rh_linear_refs_reset(st)
    assert st.critical_speed_mps == ref.critical_speed_mps
    assert st.guard_speed_mps == ref.guard_speed_mps
    rng = np.random.default_rng(3)
    n = 400
    vx = np.concatenate([rng.uniform(-50.0, 80.0, n), [0.0, 11.45, ref.guard_speed_mps]])
    d = np.concatenate([rng.uniform(-0.15, 0.15, n), [0.1, 0.1, -0.1]])
    if nat.prec == "f32":
        vx = vx.astype(np.float32).astype(np.float64)
        d = d.astype(np.float32).astype(np.float64)
    out = nat.arr(3)
    c_rows, r_rows = [], []
    for v, dw in zip(vx, d, strict=True):
        nat.lib.rh_linear_refs_compute(st, v, 1.0, 0.3, dw, 500.0, 2.0, nat.ptr(out))
        c_rows.append(out.astype(np.float64))
        r_rows.append(ref.compute(float(v), 1.0, 0.3, float(dw), 500.0, 2.0))
    c, r = np.array(c_rows), np.array(r_rows)
    assert np.any(1.0 + ref.understeer_gradient * vx ** 2 < 0.5)  # the floor is exercised
    if nat.prec == "f64":
        bound = 1e-12 * np.abs(r)
    else:
        L = P.wheelbase_m
        den = np.maximum(1.0 + ref.understeer_gradient * vx * vx, 0.5)
        mag_b = 10 * U32 * np.abs(d) * (P.lr_m + ref._beta_k * vx * vx) / (L * den)
        bound = 2.0 * np.stack([10 * U32 * np.abs(r[:, 0]), np.abs(vx) * mag_b
                                + U32 * np.abs(r[:, 1]), mag_b], axis=1)
    err = np.abs(c - r)
    print(f"linear refs {nat.prec}: max |err|/bound {np.max(err / (bound + 1e-300)):.3g}, "
          f"max rel {np.max(err / (np.abs(r) + 1e-300)):.3g}")
    assert np.all(err <= bound)
    # invalid input → neutral reference, as the Python
    for v, dw in ((math.nan, 0.1), (10.0, math.nan), (1001.0, 0.1), (10.0, 1.6),
                  (math.inf, 0.0), (-1001.0, 0.1)):
        out[:] = 7.0
        nat.lib.rh_linear_refs_compute(st, v, 0.0, 0.0, dw, 0.0, 0.0, nat.ptr(out))
        assert ref.compute(v, 0.0, 0.0, dw, 0.0, 0.0) == (0.0, 0.0, 0.0)
        assert np.all(out == 0.0), (v, dw)


def _mf_curve(nat: Native, curve: Any) -> Any:
    return nat.curve(curve)


@pytest.mark.parametrize("case", ["grip", "no-grip", "no-stiffness", "both"])
def test_mf_no_grip_or_no_stiffness_gives_zero_force_as_the_reference(nat: Native,
                                                                       case: str) -> None:
    """``D <= 1e-9 || K <= 0`` (rh_mf_force, rh_mf_eval), one condition at a time: μ = 0
    makes D = 0 with K > 0; a fit whose stiffness polynomial k1 + k2·dfz is negative at the
    load makes K < 0 with D > 0; either gives a zero force and zero derivatives, like
    tyre.mf_force/mf_eval; with both positive the force is the reference's (not zero)."""
    base = TYRES.front.lateral
    mu = 0.0 if case in ("no-grip", "both") else 0.9
    curve = base if case in ("grip", "no-grip") else replace(base, k1=-abs(base.k1))
    fz, s = float(nat.dtype(0.8 * base.fz0_n)), float(nat.dtype(0.05))
    assert (curve.k1 + curve.k2 * (fz - curve.fz0_n) / curve.fz0_n > 0.0) == (
        case in ("grip", "no-grip"))
    cc = _mf_curve(nat, curve)
    out = nat.arr(3)
    nat.lib.rh_mf_eval(cc, s, fz, mu, nat.ptr(out))
    force = float(nat.lib.rh_mf_force(cc, s, fz, mu))
    ref, ref_force = mf_eval(curve, s, fz, mu), mf_force(curve, s, fz, mu)
    if case == "grip":
        assert abs(ref_force) > 100.0
        assert scaled_error(np.array([[force, *out]]), np.array([[ref_force, *ref]])) \
            <= TOL[nat.prec]
    else:
        assert ref == (0.0, 0.0, 0.0) and ref_force == 0.0
        assert force == 0.0 and list(out) == [0.0, 0.0, 0.0]


def test_init_constants_of_a_light_car(nat: Native) -> None:
    """A 900 kg car (the packaged one with its mass cut): its weight m·g is below the
    lateral curves' load cap, so the wheels' load cap is m·g, and the axle term (cf + cr)/m
    of the substep stiffness bound exceeds the yaw term; both as the reference's."""
    light = replace(P, mass_kg=900.0)
    ref7 = SevenDofPrediction(light, TYRES)
    m7 = nat.new("rh_seven_dof_t")
    nat.lib.rh_seven_dof_init(m7, nat.vehicle(light), seven_dof_config(nat, linear=False))
    cf, cr = abs(light.cf_axle_n_per_rad), abs(light.cr_axle_n_per_rad)
    axle = (cf + cr) / light.mass_kg
    assert axle > (cf * light.lf_m ** 2 + cr * light.lr_m ** 2) / light.yaw_inertia_kgm2
    assert m7.stiff_rate == ref7.stiff_rate == 1.25 * axle
    rnd = (lambda v: float(np.float32(v))) if nat.prec == "f32" else float
    weight = light.mass_kg * 9.80665
    for i in range(4):
        cap = ref7._wheels[i][-1]
        assert cap < TYRES.front.lateral.fz_cap() and math.isclose(cap, weight, rel_tol=1e-3)
        assert m7.w[i].fz_cap == rnd(cap), i
    mb = nat.new("rh_bicycle_t")
    nat.lib.rh_bicycle_init(mb, nat.vehicle(light), native_config.BICYCLE_H_MAX_S)
    assert mb.stiff_rate == BicycleModel(light).stiff_rate == 1.25 * axle


def test_mf_curvature_above_one_is_clamped_as_the_reference(nat: Native) -> None:
    """A fit whose curvature E = e1 + e2·dfz exceeds 1 at the load (the curve would fold
    back): rh_mf_eval clamps E to 1 and its load derivative to 0, rh_mf_force takes
    min(E, 1), as tyre.mf_eval/mf_force; on slips before and past the peak, both loads."""
    base = TYRES.front.lateral
    curve = replace(base, e1=1.4)
    out = nat.arr(3)
    cc = _mf_curve(nat, curve)
    c_rows, r_rows = [], []
    for fz in (0.6 * base.fz0_n, 1.3 * base.fz0_n):
        fzr = float(nat.dtype(fz))
        assert curve.e1 + curve.e2 * (fzr - curve.fz0_n) / curve.fz0_n > 1.0
        for s in (-0.4, -0.05, 0.02, 0.1, 0.5):
            sr = float(nat.dtype(s))
            nat.lib.rh_mf_eval(cc, sr, fzr, 0.9, nat.ptr(out))
            force = float(nat.lib.rh_mf_force(cc, sr, fzr, 0.9))
            c_rows.append([force, *out.astype(np.float64)])
            r_rows.append([mf_force(curve, sr, fzr, 0.9), *mf_eval(curve, sr, fzr, 0.9)])
    assert scaled_error(np.array(c_rows), np.array(r_rows)) <= TOL[nat.prec]


def test_linear_refs_of_an_understeering_car_have_no_critical_speed(nat: Native) -> None:
    """A rear axle stiff enough for K = m/L²·(lr/cf − lf/cr) > 0 (understeer; the packaged
    car oversteers): critical and guard speeds are +∞ as in LinearReferences, and the
    references (no DEN_MIN floor reached) equal the reference's."""
    params = replace(P, cr_axle_n_per_rad=2.0 * P.cf_axle_n_per_rad * P.lf_m / P.lr_m)
    ref = LinearReferences(params)
    assert ref.understeer_gradient > 0.0
    st = nat.new("rh_linear_refs_t")
    nat.lib.rh_linear_refs_init(st, nat.vehicle(params))
    nat.lib.rh_linear_refs_reset(st)
    assert st.critical_speed_mps == ref.critical_speed_mps == math.inf
    assert st.guard_speed_mps == ref.guard_speed_mps == math.inf
    out = nat.arr(3)
    for v, dw in ((5.0, 0.1), (30.0, -0.05), (70.0, 0.02)):
        nat.lib.rh_linear_refs_compute(st, v, 1.0, 0.3, dw, 500.0, 2.0, nat.ptr(out))
        r = np.array(ref.compute(v, 1.0, 0.3, dw, 500.0, 2.0))
        tol = 1e-12 if nat.prec == "f64" else 32 * U32
        assert np.all(np.abs(out.astype(np.float64) - r) <= tol * np.abs(r)), (v, dw)


def _constant_rhs(nat: Native, g: tuple[float, ...]) -> Any:
    """A sub-step right-hand side with the constant derivative g (3 values: the
    rh_substep_rhs_fn; 15: the rh_substep_rhs_jac_fn, whose Jacobian and input sensitivity
    are zero)."""
    def rhs(_call: Any, _vx: float, _vy: float, _r: float, out: Any) -> None:
        for k in range(len(g)):
            out[k] = g[k]
    fn = "rh_substep_rhs_fn" if len(g) == 3 else "rh_substep_rhs_jac_fn"
    return nat.ffi.callback(fn, rhs)


@pytest.mark.parametrize("beyond", [0, 56])
def test_substeps_are_capped_at_the_compile_time_maximum(nat: Native, beyond: int) -> None:
    """``i < n && i < RH_SUBSTEP_MAX`` (rh_substep_predict, rh_substep_propagate):
    rh_substep_count never asks for more than RH_SUBSTEP_MAX, and a caller that does (n =
    RH_SUBSTEP_MAX + beyond) gets RH_SUBSTEP_MAX sub-steps of length ts/n. Closed form: with
    a constant derivative g each Heun sub-step adds h·g, exactly for these dyadic values, so
    x_n = x0 + min(n, MAX)·h·g with h = ts/n = 1/256 s; the sensitivities stay the identity
    and zero."""
    n = nat.lib.RH_SUBSTEP_MAX + beyond
    g, x0 = (0.5, -0.25, 0.125), (8.0, 1.0, -0.5)
    ts = n / 256.0
    want = np.array(x0) + min(n, nat.lib.RH_SUBSTEP_MAX) / 256.0 * np.array(g)
    x, xn, A, B = nat.arr(3), nat.arr(3), nat.arr(9), nat.arr(3)
    x[:] = x0
    nat.lib.rh_substep_predict(_constant_rhs(nat, g), nat.ffi.NULL, n, ts, nat.ptr(x), nat.ptr(xn))
    np.testing.assert_array_equal(xn, want)
    xn[:] = 0.0
    nat.lib.rh_substep_propagate(_constant_rhs(nat, (*g, *[0.0] * 12)), nat.ffi.NULL, n, ts,
                                 nat.ptr(x), nat.ptr(xn), nat.ptr(A), nat.ptr(B))
    np.testing.assert_array_equal(xn, want)
    np.testing.assert_array_equal(A, np.eye(3).ravel())
    np.testing.assert_array_equal(B, np.zeros(3))


@pytest.mark.parametrize("bad", [None, 0, 1, 2], ids=["none", "vx", "vy", "r"])
def test_substep_prediction_is_nan_when_any_state_is_not_finite(nat: Native,
                                                                bad: int | None) -> None:
    """``!(finite(vx) && finite(vy) && finite(r))`` (rh_substep_predict), one condition at a
    time: a derivative infinite in one component makes only that component non-finite; the
    prediction is then NaN in all three (the reference _substep's finiteness test); with
    none, the closed-form x0 + n·h·g."""
    g = [0.5, -0.25, 0.125]
    if bad is not None:
        g[bad] = math.inf
    x0 = (8.0, 1.0, -0.5)
    x, xn = nat.arr(3), nat.arr(3)
    x[:] = x0
    nat.lib.rh_substep_predict(_constant_rhs(nat, tuple(g)), nat.ffi.NULL, 4, 4 / 256.0, nat.ptr(x),
                               nat.ptr(xn))
    if bad is None:
        np.testing.assert_array_equal(xn, np.array(x0) + 4 / 256.0 * np.array(g))
    else:
        assert np.all(np.isnan(xn)), (bad, xn)


@pytest.mark.parametrize("kind", list(MODELS))
def test_substep_count_at_its_bounds_matches_the_reference(nat: Native, kind: str) -> None:
    """The sub-step count at its ends, as the reference: ts = 1 s (the longest accepted) at
    |vx| below V_LOW, where ceil(ts·λ/H_LAMBDA_MAX) ≈ 260 exceeds the 200-step cap (capped),
    and ts = 1e-12 s, where both ceilings are 0 (floored at one step). predict and
    predict_linearize vs the reference; the long step in float64 only (200 sub-steps of
    float32 rounding exceed the per-call tolerance)."""
    make_ref, make_c, fn = MODELS[kind]
    m = make_c(nat)
    assert 1.0 * m.stiff_rate / 1.0 / 0.5 > nat.lib.RH_SUBSTEP_MAX + 50
    rows = [[0.5, 0.05, 0.02, 50.0, 0.02, 100.0, 1e-12],
            [-0.3, 0.0, -0.01, -80.0, 0.0, 0.0, 1e-12],
            [12.0, 0.3, 0.1, 300.0, 0.03, 500.0, 1e-12]]
    if nat.prec == "f64":
        rows += [[0.5, 0.05, 0.02, 50.0, 0.02, 100.0, 1.0],
                 [-0.3, 0.0, -0.01, -80.0, 0.0, 0.0, 1.0]]
    res = run_model(nat, rounded(np.array(rows), nat.prec), make_ref(), m, fn)
    for name, (c, ref) in res.items():
        assert np.all(np.isfinite(ref)), name
        assert scaled_error(c, ref) <= TOL[nat.prec], (kind, name)


@pytest.mark.parametrize("kind", list(MODELS))
def test_linearize_without_the_next_state(nat: Native, kind: str) -> None:
    """substep.h allows xn = NULL (A and B only): the same A and B, bit for bit, as the call
    with xn, and NaN in both when the inputs are invalid (ts = 0; the reference's NaN: see
    test_invalid_inputs_give_nan)."""
    _make_ref, make_c, fn = MODELS[kind]
    m = make_c(nat)
    c_pl = getattr(nat.lib, f"rh_{fn}_predict_linearize")
    x = nat.arr(3)
    x[:] = (20.0, 0.5, 0.2)
    for ts, ok in ((0.05, True), (0.0, False)):
        xn, A, B, A0, B0 = nat.arr(3), nat.arr(9), nat.arr(3), nat.arr(9), nat.arr(3)
        c_pl(m, nat.ptr(x), 100.0, nat.ctx(0.05, 300.0, ts), nat.ptr(xn),
             nat.ptr(A), nat.ptr(B))
        c_pl(m, nat.ptr(x), 100.0, nat.ctx(0.05, 300.0, ts), nat.ffi.NULL,
             nat.ptr(A0), nat.ptr(B0))
        assert np.all(np.isfinite(np.concatenate([A, B]))) == ok
        np.testing.assert_array_equal(A0, A)
        np.testing.assert_array_equal(B0, B)


def test_planted_error_is_caught(tmp_path: Path) -> None:
    """The float64 back-to-back comparison detects a small planted error: the drag term of
    the 7-DoF Jacobian (2·kd·|vx| → 1.9·kd·|vx|, a change of ≈ 1e-4 in A[0][0]) and, in a
    second build, the yaw-moment arm of the rear-wheel Fx (a 1 % error)."""
    src = (SRC_DIR / "seven_dof.c").read_text()
    for old, new in (("RH_R(2.0) * m->kd * avx", "RH_R(1.9) * m->kd * avx"),
                     ("bm += xw * fY - yw * fX;", "bm += xw * fY - RH_R(1.01) * yw * fX;")):
        assert old in src
        mutated = tmp_path / f"seven_dof_mut{len(new)}.c"
        mutated.write_text(src.replace(old, new))
        srcs = (*(s for s in SOURCES if s != "seven_dof.c"), mutated)
        nat = build("f64", tmp_path, srcs, name="rh_baselines_mut")
        rows = samples(11, 40)
        res = run_model(nat, rows, SevenDofPrediction(P, TYRES), init_seven(nat, False),
                        "seven_dof")
        worst = max(scaled_error(c, r) for c, r in res.values())
        print(f"planted {new!r}: max scaled error {worst:.3g}")
        assert worst > 1e3 * TOL["f64"], (old, worst)
