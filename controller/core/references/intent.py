"""Driver-intent references from the learned RHONN map.

Algorithm 1 (algorithm1.py) returns the *fixed point* of the learned map at the driver's
steering. At the grip limit that fixed point is saturated (the map has learned that the
tyres give no more), and with live EKF weights it sits just behind the measured state, so
the NMPC mostly damps the yaw the driver asks for (measured: ωrd ≈ 0.97 × ωr).

This generator asks the learned map a different question: *what does the driver's steering
ask of this car?* It takes the map's linear response to the steering, i.e. one Newton step
of the fixed-point equations from straight running (Vy = 0, ωr = 0) at the current Vx:

    C(δ) = bilinear coefficients of W φ at (Vx, δ)  (W φ = C0 + C1 ξ2 + C2 ξ3 + C3 ξ2 ξ3,
           ξ2 = S(Vy), ξ3 = S(ωr); increment form: the increments vanish at a fixed point)
    [C1_vy C2_vy; C1_r C2_r] · [ξ2; ξ3] = −(C0(δ) − C0(0))
    Vyd = S⁻¹(ξ2),  ωrd = S⁻¹(ξ3)

C0(δ) − C0(0) removes the learned offset at zero steering (sensor biases), so straight
steering asks for no yaw. The yaw gain ωrd/δ is the learned one — on a car with softer
tyres or more mass than Table 1 it follows the car, where the linear baseline reference
keeps the nominal bicycle gain. The weights are read from a slow copy (slow_weights.py,
τ = slow_tau_s) so one transient does not redefine the car's steady-state gain.

Guards (deterministic, no search):
* the 2×2 matrix must describe a stable equilibrium of the increment map (negative trace,
  positive determinant); otherwise — a cold or badly excited map — the kinematic
  neutral-steer values ωrd = Vx δw / L, Vyd = lr ωrd are used (counted in ``fallbacks``);
* ωrd is kept between 0 and r_kin_factor × the neutral-steer yaw rate (± r_band), as in
  Algorithm 1 — the steady state turns the way the wheels point;
* |Vyd| ≤ tan(beta_max) Vx;
* optional lead on the steering rate (intent_lead_s, s): ωrd += T·(gain)·dδw/dt, the yaw
  rate the path asks for ahead of the steady state (0 = off).
Below v_min the references are kinematic, as in Algorithm 1. βd = Vyd / Vx.
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.model.rhonn import RhonnModel
from controller.core.params import VehicleParams
from controller.core.references.algorithm1 import RhonnRefConfig, RhonnReferences
from controller.core.references.linear import LinearReferences
from controller.core.references.slow_weights import SlowWeights

_XI_CLIP = 0.995   # |ξ/μ| bound before atanh (S⁻¹), -
G_MPS2 = 9.81      # the g of the grip-scaled thresholds, m/s²


class IntentReferences:
    """ReferenceGenerator: the learned map's linear response to the driver's steering."""

    def __init__(self, model: RhonnModel, params: VehicleParams,
                 cfg: RhonnRefConfig | None = None) -> None:
        self.model = model
        self.params = params
        self.cfg = cfg or RhonnRefConfig()
        self.weights = SlowWeights(model, self.cfg.slow_tau_s, self.cfg.ts,
                                   key="ref.intent.w_slow")
        self.fallbacks = 0
        self.gain_last = 0.0      # learned yaw gain ωrd/δw of the last call, 1/s
        self._dw_prev = math.nan
        self._decay = math.exp(-self.cfg.ts / self.cfg.ay_decay_s)
        self.ay_envelope = 0.0

    def reset(self) -> None:
        """Forget the slow weights, the counters and the previous steering angle."""
        self.weights.reset()
        self.ay_envelope = 0.0
        self.fallbacks = 0
        self.gain_last = 0.0
        self._dw_prev = math.nan

    def _inverse_s(self, j: int, xi: float) -> float:
        """S_j⁻¹(ξ) = atanh(ξ/μ_j)/β_j (state units), ξ/μ clipped to ±_XI_CLIP."""
        m = self.model
        u = min(max(xi / m._mu[j], -_XI_CLIP), _XI_CLIP)
        return math.atanh(u) / m._beta[j]

    def steady_response(self, vx: float, delta_w: float) -> tuple[float, float] | None:
        """(Vyd m/s, ωrd rad/s): the map's linear steady response to δw rad at Vx m/s, or
        None when the learned 2×2 increment matrix is not a stable equilibrium."""
        w = self.weights
        c = np.array(w.coefficients(vx, delta_w))      # copy: the next call overwrites
        c_zero = w.coefficients(vx, 0.0)
        rhs_v = -(c[1, 0] - c_zero[1, 0])
        rhs_r = -(c[2, 0] - c_zero[2, 0])
        a11, a12, a21, a22 = c[1, 1], c[1, 2], c[2, 1], c[2, 2]
        if not self.model.increment:
            a11 -= 1.0
            a22 -= 1.0
        det = a11 * a22 - a12 * a21
        if not (math.isfinite(det) and det > 1e-9 and a11 + a22 < 0.0):
            return None
        xi_v = (a22 * rhs_v - a12 * rhs_r) / det
        xi_r = (a11 * rhs_r - a21 * rhs_v) / det
        if not (math.isfinite(xi_v) and math.isfinite(xi_r)):
            return None
        return self._inverse_s(1, xi_v), self._inverse_s(2, xi_r)

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad) for Vx m/s and road-wheel angle δw rad (the measured
        Vy m/s, ωr rad/s, Tt N·m and ay m/s² are not used: no search around the state)."""
        c, p = self.cfg, self.params
        self.weights.update()
        if math.isfinite(ay_meas):
            self.ay_envelope = max(abs(ay_meas), self.ay_envelope * self._decay)
        if not (math.isfinite(vx) and math.isfinite(delta_w)):
            return 0.0, 0.0, 0.0
        dw_rate = 0.0 if math.isnan(self._dw_prev) else (delta_w - self._dw_prev) / c.ts
        self._dw_prev = delta_w
        r_neutral = max(vx, 0.0) * delta_w / p.wheelbase_m
        if vx < c.v_min:
            vy_d = p.lr_m * r_neutral
            return r_neutral, vy_d, vy_d / c.v_min
        got = self.steady_response(vx, delta_w)
        if got is None:
            self.fallbacks += 1
            vy_d, r_d = p.lr_m * r_neutral, r_neutral
        else:
            vy_d, r_d = got
        self.gain_last = r_d / delta_w if abs(delta_w) > 1e-4 else self.gain_last
        if c.intent_lead_s > 0.0:
            r_d += c.intent_lead_s * self.gain_last * dw_rate
        r_kin = c.r_kin_factor * r_neutral
        r_d = min(max(r_d, min(r_kin, 0.0) - c.r_band), max(r_kin, 0.0) + c.r_band)
        if c.intent_ay_margin > 0.0:
            a_max = min(max(c.intent_ay_margin * self.ay_envelope, c.ay_floor), c.ay_ceiling)
            r_d = min(max(r_d, -a_max / vx), a_max / vx)
        v_lim = math.tan(c.beta_max) * vx
        vy_d = min(max(vy_d, -v_lim), v_lim)
        return r_d, vy_d, vy_d / vx

    def get_state(self) -> dict[str, np.ndarray | float]:
        """The slow weight copy, the |ay| envelope m/s² and the last δw rad."""
        d = self.weights.get_state()
        d["ref.intent.ay_envelope"] = float(self.ay_envelope)
        d["ref.intent.dw_prev"] = float(self._dw_prev)
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        self.weights.set_state(d)
        self.ay_envelope = float(d.get("ref.intent.ay_envelope", 0.0))
        self._dw_prev = float(d.get("ref.intent.dw_prev", math.nan))


class BicycleDemand:
    """The driver's yaw demand from the nominal bicycle (references/linear.py: the paper's
    baseline reference from Table 1), with an optional steering lead (intent_lead_s, s) and
    limited by the grip seen so far: |ωrd| ≤ a_max/Vx, a_max = clip(intent_ay_margin ×
    envelope(|ay|), ay_floor, ay_ceiling) m/s² (the envelope of Algorithm 1)."""

    def __init__(self, params: VehicleParams, cfg: RhonnRefConfig) -> None:
        self.cfg = cfg
        self.linear = LinearReferences(params)
        self._decay = math.exp(-cfg.ts / cfg.ay_decay_s)
        self.ay_envelope = 0.0
        self._dw_prev = math.nan

    def reset(self) -> None:
        """Forget the envelope and the previous steering angle."""
        self.ay_envelope = 0.0
        self._dw_prev = math.nan

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad); arguments as ReferenceGenerator.compute."""
        c = self.cfg
        if math.isfinite(ay_meas):
            self.ay_envelope = max(abs(ay_meas), self.ay_envelope * self._decay)
        r_d, vy_d, b_d = self.linear.compute(vx, vy, yaw_rate, delta_w, total_torque, ay_meas)
        if not math.isfinite(delta_w):
            return r_d, vy_d, b_d
        rate = 0.0 if math.isnan(self._dw_prev) else (delta_w - self._dw_prev) / c.ts
        self._dw_prev = delta_w
        if c.intent_lead_s > 0.0 and abs(delta_w) > 1e-5:
            r_d += c.intent_lead_s * (r_d / delta_w) * rate
        if c.intent_ay_margin > 0.0 and vx > c.v_min:
            a_max = min(max(c.intent_ay_margin * self.ay_envelope, c.ay_floor), c.ay_ceiling)
            r_d = min(max(r_d, -a_max / vx), a_max / vx)
        return r_d, vy_d, b_d

    def get_state(self) -> dict[str, np.ndarray | float]:
        """The |ay| envelope m/s² and the last δw rad."""
        return {"ref.demand.ay_envelope": float(self.ay_envelope),
                "ref.demand.dw_prev": float(self._dw_prev)}

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        self.ay_envelope = float(d.get("ref.demand.ay_envelope", 0.0))
        self._dw_prev = float(d.get("ref.demand.dw_prev", math.nan))


def grip_scale(cfg: RhonnRefConfig, ay_envelope: float) -> float:
    """Factor (≥ 1) on the sideslip thresholds from the grip the car has shown: θ/θ0 with
    θ = clip(grip_beta_per_g · envelope/g, θ0, grip_beta_max), θ0 = guard_beta_rad (rad);
    1 when grip_beta_per_g = 0. ay_envelope m/s²."""
    if cfg.grip_beta_per_g <= 0.0 or cfg.guard_beta_rad <= 0.0:
        return 1.0
    theta = min(max(cfg.grip_beta_per_g * ay_envelope / G_MPS2, cfg.guard_beta_rad),
                max(cfg.grip_beta_max, cfg.guard_beta_rad))
    return theta / cfg.guard_beta_rad


class BlendedReferences:
    """A yaw *demand* while the car is stable, Algorithm 1 (the learned fixed point: what
    the car settles at) as the sideslip grows.

    demand: "learned" — IntentReferences (the learned map's linear response, kind "blend");
    "bicycle" — BicycleDemand (nominal bicycle limited by the grip, kind "demand").
    Both generators run every call. With β = Vy/Vx measured (rad) and w = clip((|β| − β_lo)
    / (β_hi − β_lo), 0, 1), (β_lo, β_hi) = (blend_beta_lo, blend_beta_hi):
        ωrd = (1 − w)·ωrd_demand + w·ωrd_algorithm1,   Vyd likewise.
    ``weight_last`` is the last w."""

    def __init__(self, model: RhonnModel, params: VehicleParams,
                 cfg: RhonnRefConfig | None = None, demand: str = "learned") -> None:
        self.cfg = cfg or RhonnRefConfig()
        self.demand: IntentReferences | BicycleDemand = (
            IntentReferences(model, params, self.cfg) if demand == "learned"
            else BicycleDemand(params, self.cfg))
        self.fixed_point = RhonnReferences(model, params, self.cfg)
        self.weight_last = 0.0
        self.model = model

    @property
    def not_converged(self) -> int:
        """Algorithm 1 searches that hit their iteration bound (the fixed-point part runs
        every call, so its bounded-iteration count is this generator's)."""
        return self.fixed_point.not_converged

    def reset(self) -> None:
        """Reset both parts."""
        self.demand.reset()
        self.fixed_point.reset()
        self.weight_last = 0.0

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad); arguments as ReferenceGenerator.compute."""
        c = self.cfg
        ri, vi, _ = self.demand.compute(vx, vy, yaw_rate, delta_w, total_torque, ay_meas)
        ra, va, _ = self.fixed_point.compute(vx, vy, yaw_rate, delta_w, total_torque, ay_meas)
        beta = abs(vy) / max(vx, c.v_min) if math.isfinite(vy) and math.isfinite(vx) else 0.0
        k = grip_scale(c, self.demand.ay_envelope)
        lo, hi = k * c.blend_beta_lo, k * c.blend_beta_hi
        span = max(hi - lo, 1e-6)
        w = min(max((beta - lo) / span, 0.0), 1.0)
        self.weight_last = w
        r_d = (1.0 - w) * ri + w * ra
        vy_d = (1.0 - w) * vi + w * va
        return r_d, vy_d, vy_d / max(vx, c.v_min)

    def get_state(self) -> dict[str, np.ndarray | float]:
        """State of both parts (envelopes, slow weight copies, last steering angle)."""
        d = self.fixed_point.get_state()
        d.update(self.demand.get_state())
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        self.fixed_point.set_state(d)
        self.demand.set_state(d)
