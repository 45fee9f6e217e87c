"""The stable-handling envelope the QP keeps the car in (after Beal & Gerdes, "Model
predictive control for vehicle stabilization at the limits of handling", IEEE TCST 21(4),
2013), and the grip-limited yaw demand that goes with it.

Envelope, from the grip estimate μ̂ (-, controller/core/grip.py) and the speed Vx (m/s):

* yaw rate: |ωr| ≤ r_max = k_r · μ̂ · g / Vx (rad/s): the yaw rate of a steady turn at the
  friction limit (Beal & Gerdes eq. 18, k_r = 1);
* rear-axle slip: |α_r| ≤ α_max = k_α · atan(3 μ̂ Fz_r / |C_r|) (rad), α_r = β − lr·ωr/Vx
  the rear slip angle (small angles), with β read ``lead_s`` ahead: β + T·(ay/Vx − ωr)
  (β̇ = ay/Vx − ωr, the planar-motion identity; measured ay). atan(3μFz/C) is the slip at
  which a brush (Fiala) tyre saturates (Beal & Gerdes eq. 19); k_α < 1 leaves the margin a
  Magic Formula tyre needs, whose force peaks before the brush tyre's.

Both are soft constraints on the predicted stages with one non-negative slack each,
dimensionless (the excess as a fraction of the bound), priced by an exact (linear) penalty
and a small quadratic term: the optimiser trades tracking against the envelope
continuously and the QP stays feasible (controller/core/mpc/qp.py builds the rows).

What differs from Beal & Gerdes: their envelope is in (β, ωr) with β bounded through the
rear slip at the current yaw rate; here the rear slip is the constrained quantity itself,
with a look-ahead on β because a 3 × 50 ms horizon cannot move β (ΔM moves ωr within one
period, β only through ωr). Their μ is known; here it is the estimate.

Grip-limited demand (the nmpc-rhonn reference ``kind = "grip"``, references/grip_demand.py,
configured here): the driver's yaw demand of the nominal bicycle (references/linear.py),
smoothly limited to the envelope's yaw rate,

    ωrd = r_lin / (1 + |r_lin / r_lim|^n)^(1/n),   r_lim = k_d · μ̂ · g / Vx,

continuous in every input (no switch on β, ay or μ̂); βd is the bicycle's β_ss scaled by the
same factor. n = ``demand_sharpness`` (4: 1.5 % below r_lin at half the limit). With a
learned model, a share w = fixed_point_share · σ of Algorithm 1's steady state of the learned
map (references/algorithm1.py: what this car settles at) is blended in, with
w = fixed_point_share · clip((|β| − β_lo)/(β_hi − β_lo), 0, 1) on the measured sideslip: the
learned car takes over continuously as the car slides.
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
from controller.core.grip import G_MPS2
from controller.core.params import VehicleParams


@dataclass(slots=True)
class HandlingConfig:
    """[handling] table.

    envelope: envelope rows in the nmpc-rhonn QP. move_weight: λ_Δ, the ΔM increment
    penalty per (kN·m)² of the nmpc-rhonn QP (added to [mpc] delta_rate_weight).
    jerk_weight: λ₂, the ΔM second-difference penalty per (kN·m)² of the nmpc-rhonn QP
    (added to [mpc] delta_accel_weight).
    baselines_envelope: the same rows and move and jerk weights in the baselines' QP.
    baselines_grip_demand: the baselines' linear yaw reference limited by the
    grip estimate as the nmpc-rhonn demand is (a production ESC bounds its reference by the
    grip it sees). yaw_margin: k_r, -. rear_slip_factor: k_α, -. lead_s: look-ahead on β, s.
    slack_linear: exact penalty per unit slack (fraction of a bound). slack_quad: quadratic
    penalty per unit slack². demand_margin: k_d, -. demand_sharpness: n, -.
    fixed_point_share: largest share of Algorithm 1's learned steady state in the nmpc-rhonn
    demand, -; fixed_point_beta_lo / _hi: measured |β|, rad, where that share starts to grow
    / is reached. v_min_mps: no envelope rows below
    this speed, m/s.
    """

    envelope: bool = True
    move_weight: float = 0.0
    jerk_weight: float = 0.0
    baselines_envelope: bool = False
    baselines_grip_demand: bool = False
    yaw_margin: float = 1.0
    rear_slip_factor: float = 0.5
    lead_s: float = 0.3
    slack_linear: float = 100.0
    slack_quad: float = 100.0
    demand_margin: float = 1.0
    demand_sharpness: float = 4.0
    fixed_point_share: float = 0.0
    fixed_point_beta_lo: float = 0.0175
    fixed_point_beta_hi: float = 0.0524
    v_min_mps: float = 5.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HandlingConfig:
        """Build from the [handling] table; unknown keys and wrong types raise ConfigError."""
        cfg = build_section(cls, d, "handling")
        require_positive(cfg, "handling",
                         ("yaw_margin", "rear_slip_factor", "demand_margin", "demand_sharpness"))
        if not 0.0 <= cfg.fixed_point_share <= 1.0:
            raise ConfigError("handling", "fixed_point_share", "must be in [0, 1]")
        require_band(cfg, "handling", "fixed_point_beta_lo", "fixed_point_beta_hi")
        for key in ("lead_s", "slack_linear", "slack_quad", "move_weight", "jerk_weight"):
            if not getattr(cfg, key) >= 0.0:
                raise ConfigError("handling", key, "must be >= 0")
        return cfg


class HandlingEnvelope:
    """Envelope bounds from the grip estimate (see the module docstring)."""

    def __init__(self, params: VehicleParams, cfg: HandlingConfig) -> None:
        self.cfg = cfg
        self.lr = params.lr_m
        L = params.wheelbase_m
        # rear axle static load over its cornering stiffness, rad per unit μ (×3: Fiala)
        self._slip_per_mu = 3.0 * params.mass_kg * G_MPS2 * params.lf_m / (
            L * abs(params.cr_axle_n_per_rad))

    def yaw_rate_max(self, mu: float, vx: float) -> float:
        """r_max, rad/s, at μ̂ (-) and Vx (m/s, floored at v_min_mps)."""
        return self.cfg.yaw_margin * mu * G_MPS2 / max(vx, self.cfg.v_min_mps)

    def rear_slip_max(self, mu: float) -> float:
        """α_max, rad, at μ̂ (-)."""
        return self.cfg.rear_slip_factor * math.atan(self._slip_per_mu * mu)
