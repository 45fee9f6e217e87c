"""Linear steady-state references of the baselines LMPC and NMPC-MF (paper Section IV-B).

The classic 2-DoF bicycle steady state at the current speed vx (m/s) and road-wheel angle
δ (rad), with positive axle stiffnesses |Cf|, |Cr| (N/rad) and L = lf + lr (m)::

    K     = m/L² · (lr/|Cf| − lf/|Cr|)                 understeer gradient, s²/m²
    r_ss  = vx·δ / (L·(1 + K·vx²))                      rad/s
    β_ss  = δ·(lr − m·lf·vx²/(L·|Cr|)) / (L·(1 + K·vx²)) rad
    vy_ref = β_ss·vx                                     m/s

As in the paper these references ignore the road friction: on a μ = 0.35 road they ask for
more yaw rate than the tyres can deliver. That is the baseline's known weakness (the paper
blames LMPC's and NMPC-MF's problems on it) and is deliberately NOT corrected here.

Critical-speed guard (numerical safety only): with Table 1's Cf, Cr the linear car is very
slightly oversteering, K = −2.29e−4 s²/m², so 1 + K·vx² → 0 at the critical speed
v_crit = 1/sqrt(−K) ≈ 66.1 m/s (238 km/h) and the gain would go to infinity and change sign
beyond it. The denominator is floored at DEN_MIN = 0.5, i.e. the gain is frozen in shape above
v_crit/√2 ≈ 46.7 m/s (168 km/h; above every scenario) and r_ss grows only linearly with vx
there. For an understeering parameter set (K ≥ 0) the guard never acts.

β_ss is computed directly (not as vy_ref / vx), so it stays finite as vx → 0 (→ lr·δ/L).
Invalid input — non-finite or non-physical vx (|vx| > 1000 m/s) or δ (|δ| > π/2) — returns
(0, 0, 0): a neutral reference (the controller forces ΔM = 0 on invalid inputs anyway).
"""

from __future__ import annotations

import math

from controller.core.params import VehicleParams

DEN_MIN = 0.5
"""Floor on 1 + K·vx² (dimensionless); see the module docstring."""
MAX_SPEED_MPS = 1000.0
"""|vx| above this (m/s) is treated as invalid input."""
MAX_STEER_RAD = 0.5 * math.pi
"""|δ| above this (rad) is treated as invalid input."""


class LinearReferences:
    """ReferenceGenerator from the linear 2-DoF bicycle's steady state (no μ)."""

    def __init__(self, params: VehicleParams) -> None:
        """params: vehicle parameters (Table 1; paper-sign negative Cf, Cr)."""
        self.p = params
        cf = abs(params.cf_axle_n_per_rad)
        cr = abs(params.cr_axle_n_per_rad)
        L = params.wheelbase_m
        self.wheelbase_m = L
        self.understeer_gradient = params.mass_kg / (L * L) * (params.lr_m / cf
                                                              - params.lf_m / cr)
        """K, s²/m² (< 0: oversteering)."""
        self.critical_speed_mps = (1.0 / math.sqrt(-self.understeer_gradient)
                                   if self.understeer_gradient < 0.0 else math.inf)
        """v_crit, m/s (inf for an understeering car)."""
        self.guard_speed_mps = (math.sqrt((1.0 - DEN_MIN) / -self.understeer_gradient)
                                if self.understeer_gradient < 0.0 else math.inf)
        """Speed above which the denominator floor DEN_MIN acts, m/s."""
        self._beta_k = params.mass_kg * params.lf_m / (L * cr)  # s²/m

    def steady_state(self, vx: float, delta_w: float) -> tuple[float, float]:
        """(r_ss rad/s, β_ss rad) at speed vx m/s and road-wheel angle delta_w rad."""
        v2 = vx * vx
        den = 1.0 + self.understeer_gradient * v2
        if den < DEN_MIN:
            den = DEN_MIN
        L = self.wheelbase_m
        r_ss = vx * delta_w / (L * den)
        beta_ss = delta_w * (self.p.lr_m - self._beta_k * v2) / (L * den)
        return r_ss, beta_ss

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(yaw_rate_ref rad/s, vy_ref m/s, beta_ref rad). Only vx (m/s) and delta_w (rad)
        are used; vy, yaw_rate, total_torque and ay_meas are ignored (linear references)."""
        vx = float(vx)
        delta_w = float(delta_w)
        if not (abs(vx) <= MAX_SPEED_MPS and abs(delta_w) <= MAX_STEER_RAD):  # also NaN
            return 0.0, 0.0, 0.0
        r_ss, beta_ss = self.steady_state(vx, delta_w)
        return r_ss, beta_ss * vx, beta_ss
