"""Available road friction μ̂ from bus signals only (no road μ from the plant).

Grip is observable only while a tyre is near saturation: in the linear range any μ above
the grip in use fits the measurements. The estimator therefore combines

* the grip in use, a = √(ax² + ay²)/g (-): a lower bound of μ at every instant;
* a saturation index σ ∈ [0, 1] from the axle slip angles: on a linear tyre the slip an
  axle needs for the measured lateral acceleration is α_lin = −k·ay (k = m·l_other /
  (L·|C_axle|), rad per m/s², from the nominal axle cornering stiffness: the steady moment
  balance gives each axle its share of m·ay). The measured slip angles are

      α_r = (Vy − lr·ωr)/Vx,          α_f = (Vy + lf·ωr)/Vx − δw   (rad)

  and the excess e = max(|α_r − α_r,lin|, |α_f − α_f,lin|) is the slip the tyres need beyond
  the linear law, i.e. how far along their saturation they are (a brush tyre needs 1.5× the
  linear slip at 75 % and 3× at 100 % of its grip). σ = clip((e − e_lo)/(e_hi − e_lo), 0, 1).

* the grip shown: e = a peak hold of a that decays with τ_hold (a road that has given a
  lateral acceleration recently will give it again).

The estimate follows one target that moves continuously between the two situations,

    target = (1 − σ) · clip(k_shown · e, μ_floor, μ_max) + σ · a
    dμ̂/dt = (target − μ̂) / τ,       μ̂ ≥ a,

so with linear tyres the car is credited with k_shown times the grip it has shown (at least
μ_floor: a road that has shown nothing yet is assumed to give μ_floor), and a saturated car
pulls μ̂ to the grip it achieves now within ~τ (the road has just shown its limit, e.g. after
a friction drop). k_shown, μ_floor, μ_max and τ_hold are the |ay| envelope values measured
for the references (1.15, 4 / 9.81, 9.5 / 9.81, 3 s; references/algorithm1.py). Every map is
continuous in every input; the state is two numbers. Below v_min (m/s), for non-finite
inputs and for an implausible grip in use (above 3 g) the estimate is held.
This is the grip the stable-handling envelope and the grip-limited yaw demand use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from controller.core.config_schema import (
    ConfigError,
    build_section,
    require_band,
    require_positive,
)
from controller.core.params import VehicleParams

G_MPS2 = 9.81
MU_LOWEST = 0.05
"""The estimate never goes below this, - (below glare ice): the demand and the envelope
divide by it."""
GRIP_IMPLAUSIBLE = 3.0
"""A grip in use a above this (-, i.e. 3 g) is no road tyre's but a sensor or bus fault:
the estimate is held, as for a non-finite input (an absurd finite a would otherwise latch
the grip shown for good)."""


@dataclass(slots=True)
class GripConfig:
    """[grip] table. mu_max: highest estimate, -. mu_floor: the estimate of a road that has
    shown no grip yet, -. shown_factor: k_shown, -. hold_tau_s: decay of the grip shown, s.
    tau_s: time constant of the estimate, s. slip_excess_lo_rad / slip_excess_hi_rad: slip
    beyond the linear law, rad, where the saturation index starts / reaches 1. v_min_mps: no
    update below this speed, m/s."""

    mu_max: float = 0.97
    mu_floor: float = 0.41
    shown_factor: float = 1.15
    hold_tau_s: float = 3.0
    tau_s: float = 0.1
    slip_excess_lo_rad: float = 0.0087
    slip_excess_hi_rad: float = 0.026
    v_min_mps: float = 5.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GripConfig:
        """Build from the [grip] table; unknown keys and wrong types raise ConfigError."""
        cfg = build_section(cls, d, "grip")
        if not 0.0 < cfg.mu_floor <= cfg.mu_max:
            raise ConfigError("grip", "mu_floor", "needs 0 < mu_floor <= mu_max")
        require_positive(cfg, "grip", ("shown_factor", "hold_tau_s", "tau_s", "v_min_mps"))
        require_band(cfg, "grip", "slip_excess_lo_rad", "slip_excess_hi_rad")
        return cfg


class GripEstimator:
    """μ̂ (-) updated once per MPC period ts (s); see the module docstring."""

    def __init__(self, params: VehicleParams, cfg: GripConfig, ts: float) -> None:
        self.cfg = cfg
        self.ts = float(ts)
        L = params.wheelbase_m
        self.lf, self.lr = params.lf_m, params.lr_m
        # linear slip per lateral acceleration of each axle, rad/(m/s²)
        self.k_front = params.mass_kg * params.lr_m / (L * abs(params.cf_axle_n_per_rad))
        self.k_rear = params.mass_kg * params.lf_m / (L * abs(params.cr_axle_n_per_rad))
        self.hold = math.exp(-self.ts / cfg.hold_tau_s)   # peak-hold decay per update, -
        self.gain = min(self.ts / cfg.tau_s, 1.0)         # estimate update gain, -
        self.mu = cfg.mu_floor        # the estimate, -
        self.shown = 0.0              # grip shown e, -
        self.saturation = 0.0         # last saturation index σ, -
        self.grip_used = 0.0          # last a = |(ax, ay)|/g, -

    def reset(self) -> None:
        """Back to a road that has shown nothing."""
        self.mu = self.cfg.mu_floor
        self.shown = 0.0
        self.saturation = 0.0
        self.grip_used = 0.0

    def slip_excess(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                    ay: float) -> float:
        """Slip beyond the linear law, rad (max over the two axles); vx m/s, vy m/s, yaw
        rate rad/s, road-wheel angle rad, ay m/s²."""
        a_r = (vy - self.lr * yaw_rate) / vx
        a_f = (vy + self.lf * yaw_rate) / vx - delta_w
        return max(abs(a_r + self.k_rear * ay), abs(a_f + self.k_front * ay))

    def update(self, vx: float, vy: float, yaw_rate: float, delta_w: float, ax: float,
               ay: float) -> float:
        """One period: the new μ̂ (-). Held when an input is not finite, vx < v_min, the grip
        in use is implausible (GRIP_IMPLAUSIBLE) or the slip excess overflows."""
        c = self.cfg
        if not (math.isfinite(vx + vy + yaw_rate + delta_w + ax + ay) and vx >= c.v_min_mps):
            return self.mu
        a = math.sqrt(ax * ax + ay * ay) / G_MPS2
        e = self.slip_excess(vx, vy, yaw_rate, delta_w, ay)
        if not (a <= GRIP_IMPLAUSIBLE and math.isfinite(e)):   # overflow to inf, NaN
            return self.mu
        s = min(max((e - c.slip_excess_lo_rad) / (c.slip_excess_hi_rad - c.slip_excess_lo_rad),
                    0.0), 1.0)
        self.shown = max(a, self.shown * self.hold)
        credit = min(max(c.shown_factor * self.shown, c.mu_floor), c.mu_max)
        target = (1.0 - s) * credit + s * a
        mu = self.mu + self.gain * (target - self.mu)
        self.mu = min(max(mu, a, MU_LOWEST), c.mu_max)
        self.saturation = s
        self.grip_used = a
        return self.mu

    def get_state(self) -> dict[str, float]:
        """μ̂ and the grip shown (-) for a checkpoint."""
        return {"grip.mu": float(self.mu), "grip.shown": float(self.shown)}

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore get_state()."""
        self.mu = float(d.get("grip.mu", self.cfg.mu_floor))
        self.shown = float(d.get("grip.shown", 0.0))
