"""7-DoF vehicle model reduced for NMPC prediction (NMPC-MF / 7dof-li), nx = 3.

The full 7-DoF model (body vx, vy, r + four wheel-spin DoF, see estimator.py) is reduced
here with QUASI-STEADY LONGITUDINAL SLIP: the wheel-spin time constant
τ ≈ Iw·vx / (R²·Kx) ≈ 0.18 ms per m/s of speed (1–4 ms at 5–20 m/s) is far below
Ts = 50 ms, so within a step each wheel sits at the slip where its tyre force balances the
applied torque, Fx_i = T_i / R. With the nominal friction μ_nominal = 1 a motor
(450 N·m → 1257 N) exceeds its tyre's grip only on an almost lifted wheel (Fz < 1.04 kN),
so this is the model's exact quasi-steady state; it neglects the wheels' rotational inertia
in v̇x (4·Iw/R² = 75 kg, 3.6 % of m) and the slip transient.

Measured against the full 7-DoF model (estimator.py, 1 ms) over the 150 ms horizon from
random states up to the limit: yaw-rate error 0.29 deg/s RMS (max 1.5), vy max 0.38 km/h
(tests/test_baselines_seven_dof.py::test_reduced_prediction_vs_full_7dof). The full model
as the prediction model (nx = 7, 1 ms sub-steps) costs ≈ 440 µs for predict alone
(measured), several ms with 7×7 Jacobians, for no accuracy the NMPC can use. Here: one Heun
step per 50 ms (see _substep.py), predict_linearize ≈ 20 µs per stage (bicycle ≈ 6 µs).

Per-wheel torques from the horizon inputs (held Tt, decision ΔM), equal split per side:
T_FL = T_RL = (Tt − ΔM)/4, T_FR = T_RR = (Tt + ΔM)/4 (satisfies paper eq. 16 exactly).

Lateral tyre force per wheel (pure slip, ISO α = atan2(v_y,w, max(|v_x,w|, 1 m/s))):
* "7dof-mf": Fy = −MF(α, Fz) from mf_tyre_fit.toml with μ = μ_nominal, or the road μ the
  controller is told ([controller] mu_estimate > 0; see tyre.with_mu_estimate);
* "7dof-li": Fy = C_i·α, C_i = half the axle's Table 1 stiffness (negative), load-independent.
Driving resistances (both): rolling resistance f·m·g (ramped in below 0.5 m/s) and aero drag
k·vx·|vx| on v̇x, with f and k taken from the plant like the tyre (mf_tyre_fit.toml
[resistance]; the paper's 7-DoF parameters came from CarSim). Without them the open-loop vx
drifts ≈ 6 km/h in 11 s of coasting against the plant.
Normal loads: chassis.py, with the quasi-static accelerations ax ≈ Tt/(m·R) and ay ≈ vx·r
(steady-state value; keeps the map a function of x alone).

Body (front wheels steered by δ, forces rotated into body axes):
    v̇x = ΣFX/m + vy·r − f·g·ramp(vx) − k·vx·|vx|/m,
    v̇y = ΣFY/m − vx·r,   ṙ = Σ(x_i·FY_i − y_i·FX_i)/Iz
"""

from __future__ import annotations

import math

from controller.core.interfaces import PredictionContext
from controller.core.model._substep import V_LOW_MPS, SubstepModel, stiffness_rate
from controller.core.model.chassis import G_MPS2, clamp_load, make_corners
from controller.core.model.tyre import FZ_MIN_N, MfTyreSet, mf_eval, mf_force
from controller.core.params import VehicleParams


class SevenDofPrediction(SubstepModel):
    """Quasi-steady-slip 7-DoF prediction model; implements PredictionModel (nx = 3)."""

    nx = 3

    def __init__(self, params: VehicleParams, tyres: MfTyreSet, linear: bool = False,
                 h_max: float = 0.05) -> None:
        """params: vehicle. tyres: MF set and driving resistances. linear: Table 1 linear
        tyres ("7dof-li") instead of the MF ("7dof-mf"). h_max: sub-step bound, s
        (default: one Heun step per 50 ms above ≈ 13 m/s)."""
        self.p = params
        self.tyres = tyres
        self.linear = bool(linear)
        res = tyres.resistance
        self._rr = res.rolling_coeff * G_MPS2  # m/s² at full ramp
        self._rr_ramp = res.ramp_speed_mps
        self._kd = res.drag_n_per_mps2 / params.mass_kg  # 1/m
        self.h_max = float(h_max)
        self.stiff_rate = stiffness_rate(params.cf_axle_n_per_rad, params.cr_axle_n_per_rad,
                                         params.mass_kg, params.yaw_inertia_kgm2,
                                         params.lf_m, params.lr_m)
        self._mf = not self.linear
        self._m = params.mass_kg
        self._iz = params.yaw_inertia_kgm2
        self._R = params.wheel_radius_m
        self._fz_max = params.mass_kg * G_MPS2
        self._mu = tyres.mu_nominal
        corners = make_corners(params)
        # per wheel: (x, y, front, fz_static, kx_ax, ky_ay, c_lin, lateral MF curve, side,
        # load cap); side +1 right (T = (Tt+ΔM)/4), −1 left
        wheels = []
        for c in corners:
            curve = (tyres.front if c.front else tyres.rear).lateral
            cap = min(self._fz_max, curve.fz_cap())
            wheels.append((c.x_m, c.y_m, c.front, c.fz_static_n, c.kx_ax, c.ky_ay, c.c_lin,
                           curve, 1.0 if c.y_m < 0.0 else -1.0, cap))
        self._wheels = tuple(wheels)
        self._base = (0.0, 0.0, 0.0)  # (ΣFX, ΣFY, Mz) of the quasi-steady Fx, per call
        self._dm = (0.0, 0.0, 0.0)  # their ∂/∂ΔM, per call
        self._call: list[tuple] = [(), (), (), ()]  # per-wheel constants of this call
        self._prepare(PredictionContext(), 0.0)

    def _prepare(self, ctx: PredictionContext, delta_m: float) -> None:
        """Everything that is constant over the call: the rotation by δ, the quasi-steady
        longitudinal forces and their ΔM derivative, and per wheel the (linear) maps from
        x to the wheel-frame velocities and from Fy to (ΣFX, ΣFY, Mz)."""
        d = float(ctx.delta_w)
        cd, sd = math.cos(d), math.sin(d)
        tt = float(ctx.total_torque)
        ax = tt / (self._m * self._R)
        fx_mean = tt / (4.0 * self._R)  # N per wheel from Tt
        fx_dm = delta_m / (4.0 * self._R)  # N per wheel from ΔM (sign by side)
        fdm = 1.0 / (4.0 * self._R)
        bx = by = bm = dx = dy = dmz = 0.0
        for i, (xw, yw, front, fzs, kax, kay, clin, curve, side, fzcap) in enumerate(
                self._wheels):
            fx = fx_mean + side * fx_dm
            if front:
                # u_w = cd·u + sd·v, v_w = cd·v − sd·u with u = vx − y·r, v = vy + x·r
                w = (cd, sd, -yw * cd + xw * sd, -sd, cd, xw * cd + yw * sd,
                     -sd, cd, xw * cd + yw * sd)
                fX, fY = fx * cd, fx * sd
                gX, gY = cd * side * fdm, sd * side * fdm
            else:
                w = (1.0, 0.0, -yw, 0.0, 1.0, xw, 0.0, 1.0, xw)
                fX, fY = fx, 0.0
                gX, gY = side * fdm, 0.0
            bx += fX
            by += fY
            bm += xw * fY - yw * fX
            dx += gX
            dy += gY
            dmz += xw * gY - yw * gX
            self._call[i] = (*w, fzs + kax * ax, kay, curve, clin, fzcap)
        self._base = (bx, by, bm)
        self._dm = (dx, dy, dmz)

    def _rhs(self, vx: float, vy: float, r: float) -> tuple[float, float, float]:
        mu, mf = self._mu, self._mf
        ay = vx * r
        sx, sy, mz = self._base
        for (uw0, uw1, uw2, vw0, vw1, vw2, cx, cy, cm, fzb, kay, curve, clin,
             fzcap) in self._call:
            uw = uw0 * vx + uw1 * vy + uw2 * r
            vw = vw0 * vx + vw1 * vy + vw2 * r
            den = uw if uw > V_LOW_MPS else (-uw if uw < -V_LOW_MPS else V_LOW_MPS)
            alpha = math.atan2(vw, den)
            if mf:
                fz = min(max(fzb + kay * ay, FZ_MIN_N), fzcap)
                fy = -mf_force(curve, alpha, fz, mu)
            else:
                fy = -clin * alpha
            sx += cx * fy
            sy += cy * fy
            mz += cm * fy
        res, _ = self._resistance(vx)
        return sx / self._m + vy * r + res, sy / self._m - vx * r, mz / self._iz

    def _resistance(self, vx: float) -> tuple[float, float]:
        """(v̇x from rolling resistance + drag, m/s²; its ∂/∂vx, 1/s)."""
        avx = vx if vx >= 0.0 else -vx
        s = vx / self._rr_ramp
        if s > 1.0:
            s, ds = 1.0, 0.0
        elif s < -1.0:
            s, ds = -1.0, 0.0
        else:
            ds = 1.0 / self._rr_ramp
        return -(self._rr * s + self._kd * vx * avx), -(self._rr * ds + 2.0 * self._kd * avx)

    def _rhs_jac(self, vx: float, vy: float, r: float) -> tuple[float, ...]:
        mu, mf = self._mu, self._mf
        ay = vx * r
        sx, sy, mz = self._base
        # accumulated partials of ΣFX, ΣFY, Mz w.r.t. (vx, vy, r)
        X0 = X1 = X2 = Y0 = Y1 = Y2 = M0 = M1 = M2 = 0.0
        for (uw0, uw1, uw2, vw0, vw1, vw2, cx, cy, cm, fzb, kay, curve, clin,
             fzcap) in self._call:
            uw = uw0 * vx + uw1 * vy + uw2 * r
            vw = vw0 * vx + vw1 * vy + vw2 * r
            if uw > V_LOW_MPS:
                den, dden = uw, 1.0
            elif uw < -V_LOW_MPS:
                den, dden = -uw, -1.0
            else:
                den, dden = V_LOW_MPS, 0.0
            alpha = math.atan2(vw, den)
            q = 1.0 / (den * den + vw * vw)
            a_v = den * q  # ∂α/∂v_w
            a_u = -vw * q * dden  # ∂α/∂u_w
            if mf:
                fz, ok = clamp_load(fzb + kay * ay, fzcap)
                F, Fs, Ff = mf_eval(curve, alpha, fz, mu)
                fy = -F
                kz = -Ff * kay * ok  # ∂Fy/∂ay through the load (ay = vx·r)
                fy0 = -Fs * (a_v * vw0 + a_u * uw0) + kz * r
                fy1 = -Fs * (a_v * vw1 + a_u * uw1)
                fy2 = -Fs * (a_v * vw2 + a_u * uw2) + kz * vx
            else:
                fy = -clin * alpha
                fy0 = -clin * (a_v * vw0 + a_u * uw0)
                fy1 = -clin * (a_v * vw1 + a_u * uw1)
                fy2 = -clin * (a_v * vw2 + a_u * uw2)
            sx += cx * fy
            sy += cy * fy
            mz += cm * fy
            X0 += cx * fy0
            X1 += cx * fy1
            X2 += cx * fy2
            Y0 += cy * fy0
            Y1 += cy * fy1
            Y2 += cy * fy2
            M0 += cm * fy0
            M1 += cm * fy1
            M2 += cm * fy2
        im = 1.0 / self._m
        iz = 1.0 / self._iz
        dx, dy, dmz = self._dm
        res, dres = self._resistance(vx)
        return (
            sx * im + vy * r + res, sy * im - vx * r, mz * iz,
            X0 * im + dres, X1 * im + r, X2 * im + vy,
            Y0 * im - r, Y1 * im, Y2 * im - vx,
            M0 * iz, M1 * iz, M2 * iz,
            dx * im, dy * im, dmz * iz,
        )
