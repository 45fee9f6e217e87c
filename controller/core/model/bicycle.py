"""Linear 2-DoF bicycle ("single-track") model: the LMPC's prediction model (paper IV-B).

States x = [vx m/s, vy m/s, r rad/s]; input ΔM N·m; ctx.delta_w (rad), ctx.total_torque Tt
(N·m) held over the step.

    v̇x = Tt / (m·R)                                (no drag, no lateral coupling)
    v̇y = (Fyf + Fyr) / m − vx·r
    ṙ  = (lf·Fyf − lr·Fyr) / Iz + wB/(2·R·Iz) · ΔM
    Fyf = Cf · αf,  αf = (vy + lf·r)/vx − δ          (axle forces, N; slip angles, rad)
    Fyr = Cr · αr,  αr = (vy − lr·r)/vx

Sign convention: Cf, Cr are the paper's NEGATIVE axle cornering stiffnesses (Table 1), and
α is the ISO slip angle (velocity direction minus wheel heading), so Fy = C·α pushes the
axle back toward its heading: e.g. a left steer δ > 0 at vy = r = 0 gives αf = −δ and
Fyf = −Cf·δ > 0 (to the left). Low-speed guard: the slip-angle denominator is
max(|vx|, V_LOW_MPS), and below V_LOW_MPS the steering term fades as δ·|vx|/V_LOW_MPS, so a
car at standstill gets no side force from steering alone.

Discretisation: Heun sub-steps (see _substep.py): one per step above ≈ 13 m/s at
ts = 50 ms, more at low speed where the lateral eigenvalues (≈ −105 s⁻¹·(1 m/s)/vx) are fast.
Measured against the exact (matrix-exponential) discretisation over random states
(3–35 m/s, |r| ≤ 0.6 rad/s, |ΔM| ≤ 3000 N·m, ts = 50 and 10 ms): one-step error RMS
0.09 deg/s in r and 0.04 km/h in vy (max 0.56 deg/s, 0.13 km/h). The continuous steady
state is a fixed point of the discrete map (g = 0 ⇒ z+ = z), so steady states are exact.
Jacobians are analytic (see _substep.py).
"""

from __future__ import annotations

from controller.core.interfaces import PredictionContext
from controller.core.model._substep import (
    V_LOW_MPS,
    SubstepModel,
    stiffness_rate,
)
from controller.core.params import VehicleParams


class BicycleModel(SubstepModel):
    """Linear 2-DoF bicycle; implements PredictionModel (nx = 3)."""

    nx = 3

    def __init__(self, params: VehicleParams, h_max: float = 0.05) -> None:
        """params: vehicle parameters (Table 1). h_max: sub-step bound, s."""
        self.p = params
        self.h_max = float(h_max)
        self.stiff_rate = stiffness_rate(params.cf_axle_n_per_rad, params.cr_axle_n_per_rad,
                                         params.mass_kg, params.yaw_inertia_kgm2,
                                         params.lf_m, params.lr_m)
        self._m = params.mass_kg
        self._iz = params.yaw_inertia_kgm2
        self._lf = params.lf_m
        self._lr = params.lr_m
        self._cf = params.cf_axle_n_per_rad  # N/rad, negative (paper sign)
        self._cr = params.cr_axle_n_per_rad
        self._kdm = params.track_m / (2.0 * params.wheel_radius_m * params.yaw_inertia_kgm2)
        self._delta = 0.0
        self._ax = 0.0
        self._dm_term = 0.0

    def _prepare(self, ctx: PredictionContext, delta_m: float) -> None:
        self._delta = float(ctx.delta_w)
        self._ax = float(ctx.total_torque) / (self._m * self.p.wheel_radius_m)
        self._dm_term = self._kdm * delta_m

    def _rhs(self, vx: float, vy: float, r: float) -> tuple[float, float, float]:
        if vx > V_LOW_MPS or vx < -V_LOW_MPS:
            den, steer = abs(vx), self._delta
        else:
            den, steer = V_LOW_MPS, self._delta * abs(vx) / V_LOW_MPS
        fyf = self._cf * ((vy + self._lf * r) / den - steer)
        fyr = self._cr * ((vy - self._lr * r) / den)
        return (self._ax,
                (fyf + fyr) / self._m - vx * r,
                (self._lf * fyf - self._lr * fyr) / self._iz + self._dm_term)

    def _rhs_jac(self, vx: float, vy: float, r: float) -> tuple[float, ...]:
        m, iz, lf, lr, cf, cr = self._m, self._iz, self._lf, self._lr, self._cf, self._cr
        d = self._delta
        if vx > V_LOW_MPS:
            den, dden, steer, dsteer = vx, 1.0, d, 0.0
        elif vx < -V_LOW_MPS:
            den, dden, steer, dsteer = -vx, -1.0, d, 0.0
        else:
            sgn = 1.0 if vx >= 0.0 else -1.0
            den, dden, steer, dsteer = V_LOW_MPS, 0.0, d * sgn * vx / V_LOW_MPS, d * sgn / V_LOW_MPS
        inv = 1.0 / den
        af = (vy + lf * r) * inv - steer
        ar = (vy - lr * r) * inv
        fyf = cf * af
        fyr = cr * ar
        # ∂Fy/∂vx through the 1/den of the slip angle (and the low-speed steering fade)
        dfyf_vx = -cf * ((vy + lf * r) * inv * inv * dden + dsteer)
        dfyr_vx = -cr * (vy - lr * r) * inv * inv * dden
        return (
            self._ax,
            (fyf + fyr) / m - vx * r,
            (lf * fyf - lr * fyr) / iz + self._dm_term,
            0.0, 0.0, 0.0,
            (dfyf_vx + dfyr_vx) / m - r, (cf + cr) * inv / m, (cf * lf - cr * lr) * inv / m - vx,
            (lf * dfyf_vx - lr * dfyr_vx) / iz, (lf * cf - lr * cr) * inv / iz,
            (lf * lf * cf + lr * lr * cr) * inv / iz,
            0.0, 0.0, self._kdm,
        )
