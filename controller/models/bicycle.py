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
Fyf = −Cf·δ > 0 (to the left). The slip-angle denominator is max(|vx|, V_LOW_MPS).

Discretisation: explicit Euler sub-steps of at most h_max = 5 ms (10 per 50 ms step, 2 per
10 ms). The lateral eigenvalues are ≈ −2|C|/(m·vx) and ≈ −(Cf·lf² + Cr·lr²)/(Iz·vx), at most
≈ −105 s⁻¹ with vx clamped at 1 m/s, so h·λ ≤ 0.53: stable and non-oscillatory everywhere.
The Euler map has exactly the continuous steady state (g = 0 is its fixed point) and its
one-step error against the exact (matrix-exponential) discretisation is < 1 % at 20 m/s.
Jacobians are analytic (see _substep.py).
"""

from __future__ import annotations

from controller.interfaces import PredictionContext
from controller.models._substep import V_LOW_MPS, SubstepModel
from controller.params import VehicleParams


class BicycleModel(SubstepModel):
    """Linear 2-DoF bicycle; implements PredictionModel (nx = 3)."""

    nx = 3

    def __init__(self, params: VehicleParams, h_max: float = 0.005) -> None:
        """params: vehicle parameters (Table 1). h_max: sub-step bound, s."""
        self.p = params
        self.h_max = float(h_max)
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
        den = vx if vx > V_LOW_MPS else (-vx if vx < -V_LOW_MPS else V_LOW_MPS)
        fyf = self._cf * ((vy + self._lf * r) / den - self._delta)
        fyr = self._cr * ((vy - self._lr * r) / den)
        return (self._ax,
                (fyf + fyr) / self._m - vx * r,
                (self._lf * fyf - self._lr * fyr) / self._iz + self._dm_term)

    def _rhs_jac(self, vx: float, vy: float, r: float) -> tuple[float, ...]:
        m, iz, lf, lr, cf, cr = self._m, self._iz, self._lf, self._lr, self._cf, self._cr
        if vx > V_LOW_MPS:
            den, dden = vx, 1.0
        elif vx < -V_LOW_MPS:
            den, dden = -vx, -1.0
        else:
            den, dden = V_LOW_MPS, 0.0
        inv = 1.0 / den
        af = (vy + lf * r) * inv - self._delta
        ar = (vy - lr * r) * inv
        fyf = cf * af
        fyr = cr * ar
        # ∂Fy/∂vx through the 1/den of the slip angle
        dfyf_vx = -cf * (vy + lf * r) * inv * inv * dden
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
