"""7-DoF vehicle model reduced for NMPC prediction (NMPC-MF / 7dof-li), nx = 3.

The full 7-DoF model (body vx, vy, r + four wheel-spin DoF, see estimator.py) is reduced
here with QUASI-STEADY LONGITUDINAL SLIP: the wheel-spin time constant
τ ≈ Iw·vx / (R²·Kx) is 1–5 ms at 5–20 m/s, far below Ts = 50 ms, so within a step each wheel
sits at the slip where its tyre force balances the applied torque, Fx_i = T_i / R. With the
nominal friction μ_nominal = 1 the motors (450 N·m → 1257 N) cannot exceed a tyre's grip,
so this holds exactly for the model; it neglects the wheel's rotational inertia in v̇x
(4·Iw/R² = 75 kg, 3.6 % of m) and the 1–5 ms slip transient. Accuracy against the full
7-DoF model and cost are measured in tests/test_baselines_seven_dof.py and the report.

Per-wheel torques from the horizon inputs (held Tt, decision ΔM), equal split per side:
T_FL = T_RL = (Tt − ΔM)/4, T_FR = T_RR = (Tt + ΔM)/4 (satisfies paper eq. 16 exactly).

Lateral tyre force per wheel (pure slip, ISO α = atan2(v_y,w, max(|v_x,w|, 1 m/s))):
* "7dof-mf": Fy = −MF(α, Fz) from mf_tyre_fit.toml with μ = μ_nominal (see tyre.py);
* "7dof-li": Fy = C_i·α, C_i = half the axle's Table 1 stiffness (negative), load-independent.
Normal loads: chassis.py, with the quasi-static accelerations ax ≈ Tt/(m·R) and ay ≈ vx·r
(steady-state value; keeps the map a function of x alone).

Body (front wheels steered by δ, forces rotated into body axes):
    v̇x = ΣFX/m + vy·r,   v̇y = ΣFY/m − vx·r,   ṙ = Σ(x_i·FY_i − y_i·FX_i)/Iz
"""

from __future__ import annotations

import math

from controller.interfaces import PredictionContext
from controller.models._substep import V_LOW_MPS, SubstepModel
from controller.models.chassis import G_MPS2, clamp_load, make_corners
from controller.models.tyre import MfTyreSet, mf_eval, mf_force
from controller.params import VehicleParams


class SevenDofPrediction(SubstepModel):
    """Quasi-steady-slip 7-DoF prediction model; implements PredictionModel (nx = 3)."""

    nx = 3

    def __init__(self, params: VehicleParams, tyres: MfTyreSet | None,
                 h_max: float = 0.025) -> None:
        """params: vehicle. tyres: MF set for "7dof-mf", None for linear tyres ("7dof-li").
        h_max: sub-step bound, s (default 25 ms: 2 sub-steps per 50 ms step; see report)."""
        self.p = params
        self.tyres = tyres
        self.h_max = float(h_max)
        self._mf = tyres is not None
        self._m = params.mass_kg
        self._iz = params.yaw_inertia_kgm2
        self._R = params.wheel_radius_m
        self._fz_max = params.mass_kg * G_MPS2
        self._mu = tyres.mu_nominal if tyres is not None else 1.0
        corners = make_corners(params)
        # per wheel: (x, y, front, fz_static, kx_ax, ky_ay, c_lin, lateral MF curve, side)
        self._wheels = tuple(
            (c.x_m, c.y_m, c.front, c.fz_static_n, c.kx_ax, c.ky_ay, c.c_lin,
             None if tyres is None else (tyres.front if c.front else tyres.rear).lateral,
             1.0 if c.y_m < 0.0 else -1.0)  # side: +1 right (T = (Tt+ΔM)/4), −1 left
            for c in corners)
        self._cd = 1.0
        self._sd = 0.0
        self._ax = 0.0
        self._fx_mean = 0.0
        self._fx_dm = 0.0

    def _prepare(self, ctx: PredictionContext, delta_m: float) -> None:
        d = float(ctx.delta_w)
        self._cd = math.cos(d)
        self._sd = math.sin(d)
        tt = float(ctx.total_torque)
        self._ax = tt / (self._m * self._R)
        self._fx_mean = tt / (4.0 * self._R)  # N per wheel from Tt
        self._fx_dm = delta_m / (4.0 * self._R)  # N per wheel from ΔM (sign by side)

    def _rhs(self, vx: float, vy: float, r: float) -> tuple[float, float, float]:
        cd, sd, mu, mf = self._cd, self._sd, self._mu, self._mf
        ay = vx * r
        sx = sy = mz = 0.0
        for xw, yw, front, fzs, kax, kay, clin, curve, side in self._wheels:
            u = vx - yw * r
            v = vy + xw * r
            fx = self._fx_mean + side * self._fx_dm
            if front:
                uw = u * cd + v * sd
                vw = v * cd - u * sd
            else:
                uw, vw = u, v
            den = uw if uw > V_LOW_MPS else (-uw if uw < -V_LOW_MPS else V_LOW_MPS)
            alpha = math.atan2(vw, den)
            if mf:
                fz = fzs + kax * self._ax + kay * ay
                fz = min(max(fz, 50.0), self._fz_max)
                fy = -mf_force(curve, alpha, fz, mu)
            else:
                fy = -clin * alpha
            if front:
                fX = fx * cd - fy * sd
                fY = fx * sd + fy * cd
            else:
                fX, fY = fx, fy
            sx += fX
            sy += fY
            mz += xw * fY - yw * fX
        return sx / self._m + vy * r, sy / self._m - vx * r, mz / self._iz

    def _rhs_jac(self, vx: float, vy: float, r: float) -> tuple[float, ...]:
        cd, sd, mu, mf = self._cd, self._sd, self._mu, self._mf
        ay = vx * r
        sx = sy = mz = 0.0
        # accumulated partials of ΣFX, ΣFY, Mz w.r.t. (vx, vy, r) and ΔM
        X0 = X1 = X2 = Y0 = Y1 = Y2 = M0 = M1 = M2 = 0.0
        Xb = Yb = Mb = 0.0
        fdm = 1.0 / (4.0 * self._R)
        for xw, yw, front, fzs, kax, kay, clin, curve, side in self._wheels:
            u = vx - yw * r
            v = vy + xw * r
            fx = self._fx_mean + side * self._fx_dm
            dfx = side * fdm  # ∂Fx/∂ΔM
            # ∂u/∂x = (1, 0, −y), ∂v/∂x = (0, 1, x) -> wheel-frame components
            if front:
                uw = u * cd + v * sd
                vw = v * cd - u * sd
                uw0, uw1, uw2 = cd, sd, -yw * cd + xw * sd
                vw0, vw1, vw2 = -sd, cd, xw * cd + yw * sd
            else:
                uw, vw = u, v
                uw0, uw1, uw2 = 1.0, 0.0, -yw
                vw0, vw1, vw2 = 0.0, 1.0, xw
            if uw > V_LOW_MPS:
                den, dden = uw, 1.0
            elif uw < -V_LOW_MPS:
                den, dden = -uw, -1.0
            else:
                den, dden = V_LOW_MPS, 0.0
            alpha = math.atan2(vw, den)
            q = 1.0 / (den * den + vw * vw)
            a_v = den * q  # ∂α/∂vw
            a_u = -vw * q * dden  # ∂α/∂uw
            al0 = a_v * vw0 + a_u * uw0
            al1 = a_v * vw1 + a_u * uw1
            al2 = a_v * vw2 + a_u * uw2
            if mf:
                fz, ok = clamp_load(fzs + kax * self._ax + kay * ay, self._fz_max)
                F, Fs, Ff = mf_eval(curve, alpha, fz, mu)
                fy = -F
                kz = -Ff * kay * ok  # ∂Fy/∂ay through the load
                fy0 = -Fs * al0 + kz * r
                fy1 = -Fs * al1
                fy2 = -Fs * al2 + kz * vx
            else:
                fy = -clin * alpha
                fy0, fy1, fy2 = -clin * al0, -clin * al1, -clin * al2
            if front:
                fX = fx * cd - fy * sd
                fY = fx * sd + fy * cd
                X0 -= sd * fy0
                X1 -= sd * fy1
                X2 -= sd * fy2
                Y0 += cd * fy0
                Y1 += cd * fy1
                Y2 += cd * fy2
                M0 += xw * cd * fy0 + yw * sd * fy0
                M1 += xw * cd * fy1 + yw * sd * fy1
                M2 += xw * cd * fy2 + yw * sd * fy2
                Xb += cd * dfx
                Yb += sd * dfx
                Mb += xw * sd * dfx - yw * cd * dfx
            else:
                fX, fY = fx, fy
                Y0 += fy0
                Y1 += fy1
                Y2 += fy2
                M0 += xw * fy0
                M1 += xw * fy1
                M2 += xw * fy2
                Xb += dfx
                Mb -= yw * dfx
            sx += fX
            sy += fY
            mz += xw * fY - yw * fX
        im = 1.0 / self._m
        iz = 1.0 / self._iz
        return (
            sx * im + vy * r, sy * im - vx * r, mz * iz,
            X0 * im, X1 * im + r, X2 * im + vy,
            Y0 * im - r, Y1 * im, Y2 * im - vx,
            M0 * iz, M1 * iz, M2 * iz,
            Xb * im, Yb * im, Mb * iz,
        )
