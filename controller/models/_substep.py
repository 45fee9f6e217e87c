"""Shared machinery of the 3-state prediction models: guarded explicit sub-stepping with
forward-mode (analytic) sensitivities.

A model supplies the continuous right-hand side ẋ = g(x, ΔM) for x = [vx m/s, vy m/s, r rad/s]
(`_rhs`) and the same with its Jacobian (`_rhs_jac`). One controller step of ts seconds is
n = ceil(ts / h_max) explicit-Euler sub-steps of h = ts/n. The Jacobians of the discrete map
are propagated through the sub-steps exactly (chain rule), so `linearize` is the exact
derivative of `predict`, not an approximation of it.

Guard: if x[0:3], ΔM, ctx.delta_w, ctx.total_torque or ctx.ts is non-finite (or ts <= 0),
or the result overflows, every output is filled with NaN; nothing is raised. The caller
treats NaN as a failed step.
"""

from __future__ import annotations

import math

import numpy as np

from controller.interfaces import ControllerInputs, PredictionContext

MAX_SUBSTEPS = 200
"""Upper bound on sub-steps per call (bounded run time); above it h grows beyond h_max."""

V_LOW_MPS = 1.0
"""Slip denominators use max(|v_x,wheel|, V_LOW_MPS), m/s: below ~1 m/s slip is undefined and
the lateral dynamics become stiff (eigenvalues ∝ 1/vx); this keeps them bounded."""


class SubstepModel:
    """Base class: implements PredictionModel on top of `_prepare`, `_rhs`, `_rhs_jac`."""

    nx: int = 3
    h_max: float = 0.005  # s, sub-step bound; subclasses/factories override

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
        if ts <= 0.0:
            return 0
        n = math.ceil(ts / self.h_max - 1e-9)
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
        vx, vy, r = float(x[0]), float(x[1]), float(x[2])
        rhs = self._rhs
        for _ in range(n):
            g0, g1, g2 = rhs(vx, vy, r)
            vx += h * g0
            vy += h * g1
            r += h * g2
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
        """predict + linearize in one pass (same results, about half the cost of both)."""
        self._propagate(x, delta_m, ctx, out, a_out, b_out)

    def _propagate(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                   out: np.ndarray | None, a_out: np.ndarray, b_out: np.ndarray) -> None:
        n = self._substeps(x, delta_m, ctx)
        if n == 0:
            self._fail(out, a_out, b_out)
            return
        h = float(ctx.ts) / n
        vx, vy, r = float(x[0]), float(x[1]), float(x[2])
        # sensitivities S = ∂z/∂x0 (row-major) and sb = ∂z/∂ΔM
        s00, s01, s02, s10, s11, s12, s20, s21, s22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
        sb0 = sb1 = sb2 = 0.0
        rhs_jac = self._rhs_jac
        for _ in range(n):
            (g0, g1, g2, j00, j01, j02, j10, j11, j12, j20, j21, j22,
             c0, c1, c2) = rhs_jac(vx, vy, r)
            # S <- S + h·J·S ; sb <- sb + h·(J·sb + c)
            t00 = j00 * s00 + j01 * s10 + j02 * s20
            t01 = j00 * s01 + j01 * s11 + j02 * s21
            t02 = j00 * s02 + j01 * s12 + j02 * s22
            t10 = j10 * s00 + j11 * s10 + j12 * s20
            t11 = j10 * s01 + j11 * s11 + j12 * s21
            t12 = j10 * s02 + j11 * s12 + j12 * s22
            t20 = j20 * s00 + j21 * s10 + j22 * s20
            t21 = j20 * s01 + j21 * s11 + j22 * s21
            t22 = j20 * s02 + j21 * s12 + j22 * s22
            u0 = j00 * sb0 + j01 * sb1 + j02 * sb2 + c0
            u1 = j10 * sb0 + j11 * sb1 + j12 * sb2 + c1
            u2 = j20 * sb0 + j21 * sb1 + j22 * sb2 + c2
            s00 += h * t00
            s01 += h * t01
            s02 += h * t02
            s10 += h * t10
            s11 += h * t11
            s12 += h * t12
            s20 += h * t20
            s21 += h * t21
            s22 += h * t22
            sb0 += h * u0
            sb1 += h * u1
            sb2 += h * u2
            vx += h * g0
            vy += h * g1
            r += h * g2
        total = (vx + vy + r + s00 + s01 + s02 + s10 + s11 + s12 + s20 + s21 + s22
                 + sb0 + sb1 + sb2)
        if not math.isfinite(total):
            self._fail(out, a_out, b_out)
            return
        if out is not None:
            out[0] = vx
            out[1] = vy
            out[2] = r
        a_out[0, 0] = s00
        a_out[0, 1] = s01
        a_out[0, 2] = s02
        a_out[1, 0] = s10
        a_out[1, 1] = s11
        a_out[1, 2] = s12
        a_out[2, 0] = s20
        a_out[2, 1] = s21
        a_out[2, 2] = s22
        b_out[0] = sb0
        b_out[1] = sb1
        b_out[2] = sb2

    @staticmethod
    def _fail(out: np.ndarray | None, a_out: np.ndarray, b_out: np.ndarray) -> None:
        if out is not None:
            out.fill(np.nan)
        a_out.fill(np.nan)
        b_out.fill(np.nan)
