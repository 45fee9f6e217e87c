"""Open-loop 7-DoF state estimators for the model-fidelity study (paper Tables 2–3).

"7dof-mf" and "7dof-li" integrate the full 7-DoF model — body vx, vy, r and the four wheel
spins ω_i — from the driver/actuator inputs only: road-wheel angle δ = swa / steering_ratio
and the four applied wheel torques. They never look at the measured motion (open loop),
which is how the paper compares them with the RHONN.

Cold start (documented difference to the RHONN): as in the paper, the 7-DoF models start at
the true initial state (paper: 65 km/h), whereas the RHONN starts from 0 and learns. Set it
with `initialise(vx, vy, r)`; it is kept across `reset()`. Without it, the first `step()`
after a reset takes [inputs.vx, inputs.vy, inputs.yaw_rate] (the bus's estimated-velocity
and yaw-rate frames) as the initial state, once. Wheels start free-rolling (ω_i = u_i / R).

Model (see chassis.py and seven_dof.py for geometry and conventions):
* tyres: pure-slip; "mf": Fx = MFx(κ, Fz), Fy = −MFy(α, Fz) at μ = μ_nominal (the road μ
  the controller is told when [controller] mu_estimate > 0, see tyre.with_mu_estimate);
  "li": Fy = C_i·α (Table 1 halves, negative), Fx = Kx_i·κ with Kx_i the fitted MF
  longitudinal stiffness at the static load (Table 1 has none);
  κ = (ω·R − u_w)/max(|u_w|, 1 m/s), α = atan2(v_w, max(|u_w|, 1 m/s));
* normal loads: static + quasi-static transfer from the model's own ax, ay of the previous
  sub-step (one sub-step lag breaks the algebraic loop);
* wheels: Iw·ω̇ = T − R·Fx, linearly implicit Euler with the slip at the updated body speed
  (stable for the 0.3–5 ms slip time constant at any speed, no artificial wheel inertia);
  body: explicit Euler. Sub-step ≤ 1 ms.
* driving resistances as in seven_dof.py (rolling f·m·g, aero k·vx·|vx|, from the plant's
  parameters via mf_tyre_fit.toml); no roll/pitch dynamics, no tyre relaxation, pure slip.

Guards: non-finite steering or torque values hold the last valid value; torques are clamped
to ±2·peak motor torque; dt that is non-finite or ≤ 0 does not integrate; dt is capped at
1 s per call. A non-finite initial state becomes rest, a finite one is clamped to
±MAX_SPEED_MPS / ±MAX_YAW_RATE_RADPS. If the state ever becomes non-finite the estimate is NaN
until reset().
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.interfaces import ControllerInputs
from controller.core.model._substep import V_LOW_MPS
from controller.core.model.chassis import G_MPS2, make_corners
from controller.core.model.tyre import FZ_MIN_N, MfTyreSet, mf_eval, mf_force
from controller.core.params import VehicleParams

MAX_DT_S = 1.0
"""Longest interval integrated per step() call, s."""
MAX_SPEED_MPS = 100.0
"""Initial vx, vy are clamped to ±this, m/s (a non-physical start cannot overflow)."""
MAX_YAW_RATE_RADPS = 10.0
"""Initial r is clamped to ±this, rad/s."""


class SevenDofEstimator:
    """Open-loop 7-DoF estimator; implements StateEstimator."""

    def __init__(self, params: VehicleParams, tyres: MfTyreSet, linear: bool,
                 h_max: float = 0.001) -> None:
        """params: vehicle. tyres: MF set (for "li" only its longitudinal stiffness is used).
        linear: True for 7dof-li. h_max: internal sub-step bound, s."""
        self.p = params
        self.linear = bool(linear)
        self.h_max = float(h_max)
        self._m = params.mass_kg
        self._iz = params.yaw_inertia_kgm2
        self._R = params.wheel_radius_m
        self._iw = params.wheel_inertia_kgm2
        self._fz_max = params.mass_kg * G_MPS2
        self._mu = tyres.mu_nominal
        res = tyres.resistance
        self._rr = res.rolling_coeff * G_MPS2 * params.mass_kg  # N at full ramp
        self._rr_ramp = res.ramp_speed_mps
        self._kd = res.drag_n_per_mps2  # N/(m/s)²
        self._t_max = 2.0 * params.peak_torque_nm
        wheels = []
        for c in make_corners(params):
            axle = tyres.front if c.front else tyres.rear
            kx_lin = axle.longitudinal.stiffness(c.fz_static_n)
            cap = min(self._fz_max, axle.lateral.fz_cap(), axle.longitudinal.fz_cap())
            wheels.append((c.x_m, c.y_m, c.front, c.fz_static_n, c.kx_ax, c.ky_ay, c.c_lin,
                           kx_lin, axle.lateral, axle.longitudinal, cap))
        self._wheels = tuple(wheels)
        self._est = np.zeros(3)
        self._init: tuple[float, float, float] | None = None
        self._omega = [0.0, 0.0, 0.0, 0.0]
        self._torque = [0.0, 0.0, 0.0, 0.0]
        # per-wheel scratch of one sub-step: ω̇, ∂ω̇/∂ω, ∂ω̇/∂u_w, u_w
        self._wg = [0.0, 0.0, 0.0, 0.0]
        self._wdg = [0.0, 0.0, 0.0, 0.0]
        self._wgu = [0.0, 0.0, 0.0, 0.0]
        self._wuw = [0.0, 0.0, 0.0, 0.0]
        self.reset()

    # --- StateEstimator ------------------------------------------------------------------
    def initialise(self, vx: float, vy: float = 0.0, r: float = 0.0) -> None:
        """Set the cold-start state [vx m/s, vy m/s, r rad/s] (kept across reset) and reset."""
        self._init = (float(vx), float(vy), float(r))
        self.reset()

    def reset(self) -> None:
        """Back to the cold-start state (initialise(), or the first step's measured state)."""
        self._delta = 0.0
        for i in range(4):
            self._torque[i] = 0.0
        self._started = False
        if self._init is not None:
            self._set_state(*self._init)

    def step(self, inputs: ControllerInputs, torques: np.ndarray, dt: float) -> np.ndarray:
        """Advance by dt s with the applied wheel torques FL..RR (N·m); return the estimate
        [vx m/s, vy m/s, r rad/s] (an internal array that the next call overwrites)."""
        if not self._started:
            self._set_state(float(inputs.vx), float(inputs.vy), float(inputs.yaw_rate))
        d = float(inputs.swa_rad) / self.p.steering_ratio
        if math.isfinite(d):
            self._delta = d
        tm = self._t_max
        for i in range(4):
            t = float(torques[i])
            if math.isfinite(t):
                self._torque[i] = min(max(t, -tm), tm)
        dt = float(dt)
        if math.isfinite(dt) and dt > 0.0:
            dt = min(dt, MAX_DT_S)
            n = max(1, math.ceil(dt / self.h_max - 1e-9))
            h = dt / n
            cd, sd = math.cos(self._delta), math.sin(self._delta)
            for _ in range(n):
                self._substep(h, cd, sd)
        if math.isfinite(self._vx + self._vy + self._r):
            self._est[0] = self._vx
            self._est[1] = self._vy
            self._est[2] = self._r
        else:
            self._est.fill(np.nan)
        return self._est

    # --- internals -----------------------------------------------------------------------
    def _set_state(self, vx: float, vy: float, r: float) -> None:
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(r)):
            vx = vy = r = 0.0
        vx = min(max(vx, -MAX_SPEED_MPS), MAX_SPEED_MPS)
        vy = min(max(vy, -MAX_SPEED_MPS), MAX_SPEED_MPS)
        r = min(max(r, -MAX_YAW_RATE_RADPS), MAX_YAW_RATE_RADPS)
        self._vx, self._vy, self._r = vx, vy, r
        for i, w in enumerate(self._wheels):
            self._omega[i] = (vx - w[1] * r) / self._R  # free rolling
        self._ax = 0.0
        self._ay = vx * r
        self._started = True
        self._est[0], self._est[1], self._est[2] = vx, vy, r

    def _substep(self, h: float, cd: float, sd: float) -> None:
        """One sub-step: tyre forces at the start state, explicit Euler for the body, then
        the wheels linearly implicit with their slip taken at the UPDATED body speed
        (first-order correction ∂g/∂u_w·Δu_w). Using the start speed instead would make the
        implicit step act like a (1 − h·∂g/∂ω)-times heavier wheel (≈ 30 % at 1 ms, 18 m/s)."""
        vx, vy, r = self._vx, self._vy, self._r
        ax, ay = self._ax, self._ay
        mu, R, iw, lin = self._mu, self._R, self._iw, self.linear
        sx = sy = mz = 0.0
        omega, torque = self._omega, self._torque
        wg, wdg, wgu, wuw = self._wg, self._wdg, self._wgu, self._wuw
        for i, (xw, yw, front, fzs, kax, kay, clin, kxl, clat, clong, fzcap) in enumerate(
                self._wheels):
            u = vx - yw * r
            v = vy + xw * r
            if front:
                uw = u * cd + v * sd
                vw = v * cd - u * sd
            else:
                uw, vw = u, v
            if uw > V_LOW_MPS:
                den, dden = uw, 1.0
            elif uw < -V_LOW_MPS:
                den, dden = -uw, -1.0
            else:
                den, dden = V_LOW_MPS, 0.0
            alpha = math.atan2(vw, den)
            kappa = (omega[i] * R - uw) / den
            if lin:
                fx, dfx = kxl * kappa, kxl
                fy = -clin * alpha
            else:
                fz = min(max(fzs + kax * ax + kay * ay, FZ_MIN_N), fzcap)
                fx, dfx, _ = mf_eval(clong, kappa, fz, mu)
                fy = -mf_force(clat, alpha, fz, mu)
            # wheel: g = ω̇ = (T − R·Fx)/Iw, ∂g/∂ω and ∂g/∂u_w through κ
            wg[i] = (torque[i] - R * fx) / iw
            # past the MF peak ∂Fx/∂κ < 0: explicit step there (no division blow-up)
            wdg[i] = min(-R * R * dfx / (den * iw), 0.0)
            wgu[i] = R * dfx * (1.0 + kappa * dden) / (den * iw)
            wuw[i] = uw
            if front:
                fX = fx * cd - fy * sd
                fY = fx * sd + fy * cd
            else:
                fX, fY = fx, fy
            sx += fX
            sy += fY
            mz += xw * fY - yw * fX
        s = vx / self._rr_ramp
        s = 1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)
        sx -= self._rr * s + self._kd * vx * (vx if vx >= 0.0 else -vx)
        self._ax = sx / self._m
        self._ay = sy / self._m
        vx1 = vx + h * (self._ax + vy * r)
        vy1 = vy + h * (self._ay - vx * r)
        r1 = r + h * mz / self._iz
        self._vx, self._vy, self._r = vx1, vy1, r1
        for i, w in enumerate(self._wheels):
            xw, yw, front = w[0], w[1], w[2]
            u = vx1 - yw * r1
            uw = u * cd + (vy1 + xw * r1) * sd if front else u
            g = wg[i] + wgu[i] * (uw - wuw[i])
            omega[i] += h * g / (1.0 - h * wdg[i])
