"""Shared machinery of the 3-state prediction models: guarded Heun sub-stepping with
forward-mode (analytic) sensitivities.

A model supplies the continuous right-hand side ẋ = g(x, ΔM) for x = [vx m/s, vy m/s, r rad/s]
(`_rhs`) and the same with its Jacobian (`_rhs_jac`). One controller step of ts seconds is
n Heun (explicit trapezoid, 2nd order) sub-steps of h = ts/n,
n = max(ceil(ts/h_max), ceil(ts·λ/H_LAMBDA_MAX)), where λ = stiff_rate / max(|vx|, V_LOW_MPS)
bounds the lateral eigenvalues (they scale with 1/vx). At ts = 50 ms one sub-step is used
above ≈ 13 m/s, more below (n changes in integer jumps with vx, so f is piecewise smooth in
vx). Measured for the 7dof-mf model over 150 ms from random states at 10–30 m/s (yaw-rate
error RMS vs 0.5 ms sub-steps; cost of predict_linearize): Euler 1 step 0.72 deg/s 11 µs,
Euler 2 steps 0.34 deg/s 20 µs, Heun 1 step 0.09 deg/s 18 µs, Heun 2 steps 0.03 deg/s 35 µs.
Heun with one step per 50 ms is the choice: its error is well below the error of the model
reduction itself (quasi-steady slip vs the full 7-DoF: 0.29 deg/s RMS). H_LAMBDA_MAX = 0.5
rather than 1.0 costs extra sub-steps only below 13 m/s and there cuts the bicycle's one-step
error 3–4× (0.39 vs 1.66 deg/s RMS at 3–8 m/s).

The Jacobians of the discrete map are propagated through the sub-steps exactly (chain rule),
so `linearize` is the exact derivative of `predict`, not an approximation of it.

Guard: if x[0:3], ΔM, ctx.delta_w, ctx.total_torque or ctx.ts is non-finite, or ts is not
in (0, 1] s, or the result overflows, every output is filled with NaN; nothing is raised. The caller
treats NaN as a failed step.
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.interfaces import ControllerInputs, PredictionContext

MAX_TS_S = 1.0
"""Longest step a prediction model accepts, s (longer ts counts as invalid input)."""

MAX_SUBSTEPS = 200
"""Upper bound on sub-steps per call (bounded run time); above it h grows beyond h_max."""

V_LOW_MPS = 1.0
"""Slip denominators use max(|v_x,wheel|, V_LOW_MPS), m/s: below ~1 m/s slip is undefined and
the lateral dynamics become stiff (eigenvalues ∝ 1/vx); this keeps them bounded."""


H_LAMBDA_MAX = 0.5
"""Largest h·λ per Heun sub-step (stability needs < 2; 0.5 keeps the low-speed error small)."""


def stiffness_rate(c_front_n_per_rad: float, c_rear_n_per_rad: float, mass_kg: float,
                   yaw_inertia_kgm2: float, lf_m: float, lr_m: float) -> float:
    """Upper bound of |λ|·vx of the linear lateral dynamics, m/s², from axle stiffnesses."""
    cf, cr = abs(c_front_n_per_rad), abs(c_rear_n_per_rad)
    # 1.25: margin for the coupling terms (Table 1 car: bound 104.5, true max 107.7 at 1 m/s)
    return 1.25 * max((cf + cr) / mass_kg, (cf * lf_m * lf_m + cr * lr_m * lr_m) / yaw_inertia_kgm2)


class SubstepModel:
    """Base class: implements PredictionModel on top of `_prepare`, `_rhs`, `_rhs_jac`."""

    nx: int = 3
    h_max: float = 0.05  # s, sub-step bound; subclasses/factories override
    stiff_rate: float = 0.0  # m/s², see stiffness_rate(); subclasses set it

    # --- to be provided by subclasses --------------------------------------------------
    def _prepare(self, ctx: PredictionContext, delta_m: float) -> None:
        """Cache per-call constants (steering, torques) as attributes."""
        raise NotImplementedError

    def _rhs(self, vx: float, vy: float, r: float) -> tuple[float, float, float]:
        """Continuous derivative (v̇x m/s², v̇y m/s², ṙ rad/s²)."""
        raise NotImplementedError

    def _rhs_jac(self, vx: float, vy: float, r: float) -> tuple[float, ...]:
        """(g0, g1, g2, ∂g/∂x row-major 9 entries, ∂g/∂ΔM 3 entries)."""
        raise NotImplementedError

    # --- PredictionModel -----------------------------------------------------------------
    def initial_state(self, inputs: ControllerInputs, out: np.ndarray) -> None:
        """out[0:3] = measured/estimated [vx m/s, vy m/s, r rad/s] from the bus inputs."""
        out[0] = inputs.vx
        out[1] = inputs.vy
        out[2] = inputs.yaw_rate

    def _substeps(self, x: np.ndarray, delta_m: float, ctx: PredictionContext) -> int:
        """Validate inputs, prepare the call; return the number of sub-steps (0 = invalid)."""
        ts = float(ctx.ts)
        dm = float(delta_m)
        vals = (float(x[0]), float(x[1]), float(x[2]), dm, float(ctx.delta_w),
                float(ctx.total_torque), ts)
        for v in vals:
            if not math.isfinite(v):
                return 0
        if not 0.0 < ts <= MAX_TS_S:
            return 0
        vabs = abs(vals[0])
        lam = self.stiff_rate / (vabs if vabs > V_LOW_MPS else V_LOW_MPS)
        n = max(math.ceil(ts / self.h_max - 1e-9), math.ceil(ts * lam / H_LAMBDA_MAX - 1e-9))
        n = min(max(n, 1), MAX_SUBSTEPS)
        self._prepare(ctx, dm)
        return n

    def predict(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                out: np.ndarray) -> None:
        """out (3,) = state after ctx.ts seconds with ΔM (N·m) held."""
        n = self._substeps(x, delta_m, ctx)
        if n == 0:
            out.fill(np.nan)
            return
        h = float(ctx.ts) / n
        hh = 0.5 * h
        vx, vy, r = float(x[0]), float(x[1]), float(x[2])
        rhs = self._rhs
        for _ in range(n):
            a0, a1, a2 = rhs(vx, vy, r)
            b0, b1, b2 = rhs(vx + h * a0, vy + h * a1, r + h * a2)
            vx += hh * (a0 + b0)
            vy += hh * (a1 + b1)
            r += hh * (a2 + b2)
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(r)):
            out.fill(np.nan)
            return
        out[0] = vx
        out[1] = vy
        out[2] = r

    def linearize(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                  a_out: np.ndarray, b_out: np.ndarray) -> None:
        """a_out (3,3) = ∂f/∂x, b_out (3,) = ∂f/∂ΔM (per N·m) of the discrete map f."""
        self._propagate(x, delta_m, ctx, None, a_out, b_out)

    def predict_linearize(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                          out: np.ndarray, a_out: np.ndarray, b_out: np.ndarray) -> None:
        """predict + linearize in one pass (same results, cheaper than both calls)."""
        self._propagate(x, delta_m, ctx, out, a_out, b_out)

    def _propagate(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                   out: np.ndarray | None, a_out: np.ndarray, b_out: np.ndarray) -> None:
        """Heun sub-steps of z and of its sensitivities S = ∂z/∂x0, sb = ∂z/∂ΔM:
        z1 = z + h·g(z), S1 = S + h·J·S, sb1 = sb + h·(J·sb + c);
        z+ = z + h/2·(g(z) + g(z1)), S+ = S + h/2·(J·S + J1·S1), likewise sb+."""
        n = self._substeps(x, delta_m, ctx)
        if n == 0:
            self._fail(out, a_out, b_out)
            return
        h = float(ctx.ts) / n
        hh = 0.5 * h
        z0, z1, z2 = float(x[0]), float(x[1]), float(x[2])
        S = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        sb = (0.0, 0.0, 0.0)
        rhs_jac = self._rhs_jac
        for _ in range(n):
            a = rhs_jac(z0, z1, z2)
            JS = _jm(a, S)
            ua = _jv(a, sb)
            u0, u1, u2 = ua[0] + a[12], ua[1] + a[13], ua[2] + a[14]
            S1 = _axpy(h, JS, S)
            b = rhs_jac(z0 + h * a[0], z1 + h * a[1], z2 + h * a[2])
            JS1 = _jm(b, S1)
            vb = _jv(b, (sb[0] + h * u0, sb[1] + h * u1, sb[2] + h * u2))
            S = _axpy(hh, _add(JS, JS1), S)
            sb = (sb[0] + hh * (u0 + vb[0] + b[12]), sb[1] + hh * (u1 + vb[1] + b[13]),
                  sb[2] + hh * (u2 + vb[2] + b[14]))
            z0 += hh * (a[0] + b[0])
            z1 += hh * (a[1] + b[1])
            z2 += hh * (a[2] + b[2])
        if not math.isfinite(z0 + z1 + z2 + sum(S) + sb[0] + sb[1] + sb[2]):
            self._fail(out, a_out, b_out)
            return
        if out is not None:
            out[0] = z0
            out[1] = z1
            out[2] = z2
        (a_out[0, 0], a_out[0, 1], a_out[0, 2], a_out[1, 0], a_out[1, 1], a_out[1, 2],
         a_out[2, 0], a_out[2, 1], a_out[2, 2]) = S
        b_out[0], b_out[1], b_out[2] = sb

    @staticmethod
    def _fail(out: np.ndarray | None, a_out: np.ndarray, b_out: np.ndarray) -> None:
        if out is not None:
            out.fill(np.nan)
        a_out.fill(np.nan)
        b_out.fill(np.nan)


def _jm(g: tuple[float, ...], S: tuple[float, ...]) -> tuple[float, ...]:
    """J·S for J = g[3:12] and S, both 3×3 row-major."""
    j00, j01, j02, j10, j11, j12, j20, j21, j22 = g[3:12]
    s00, s01, s02, s10, s11, s12, s20, s21, s22 = S
    return (j00 * s00 + j01 * s10 + j02 * s20, j00 * s01 + j01 * s11 + j02 * s21,
            j00 * s02 + j01 * s12 + j02 * s22,
            j10 * s00 + j11 * s10 + j12 * s20, j10 * s01 + j11 * s11 + j12 * s21,
            j10 * s02 + j11 * s12 + j12 * s22,
            j20 * s00 + j21 * s10 + j22 * s20, j20 * s01 + j21 * s11 + j22 * s21,
            j20 * s02 + j21 * s12 + j22 * s22)


def _axpy(h: float, a: tuple[float, ...], y: tuple[float, ...]) -> tuple[float, ...]:
    """y + h·a for 9-tuples."""
    return (y[0] + h * a[0], y[1] + h * a[1], y[2] + h * a[2], y[3] + h * a[3],
            y[4] + h * a[4], y[5] + h * a[5], y[6] + h * a[6], y[7] + h * a[7],
            y[8] + h * a[8])


def _add(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
    """a + b for 9-tuples."""
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5],
            a[6] + b[6], a[7] + b[7], a[8] + b[8])


def _jv(g: tuple[float, ...], v: tuple[float, float, float]) -> tuple[float, float, float]:
    """J·v for J = g[3:12] (3×3 row-major)."""
    return (g[3] * v[0] + g[4] * v[1] + g[5] * v[2],
            g[6] * v[0] + g[7] * v[1] + g[8] * v[2],
            g[9] * v[0] + g[10] * v[1] + g[11] * v[2])
