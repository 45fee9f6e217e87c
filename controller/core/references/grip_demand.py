"""The grip-limited yaw demand (``[references] kind = "grip"``): the bicycle demand smoothly
limited to the grip estimate, with Algorithm 1's learned steady state blended in by |β|
(the law and its parameters: controller/core/mpc/envelope.py, ``[handling]``)."""

from __future__ import annotations

import math
from typing import Any

from controller.core.grip import G_MPS2, GripEstimator
from controller.core.interfaces import ReferenceGenerator
from controller.core.mpc.envelope import HandlingConfig
from controller.core.params import VehicleParams
from controller.core.references.linear import LinearReferences


class GripDemandReferences:
    """ReferenceGenerator: the bicycle yaw demand smoothly limited by the grip estimate."""

    def __init__(self, params: VehicleParams, grip: GripEstimator, cfg: HandlingConfig,
                 v_min: float = 3.0, fixed_point: ReferenceGenerator | None = None) -> None:
        self.linear = LinearReferences(params)
        self.grip = grip
        self.cfg = cfg
        self.v_min = float(v_min)
        self.fixed_point = fixed_point if cfg.fixed_point_share > 0.0 else None
        self.factor_last = 1.0   # ωrd / r_lin of the last call, -
        self.weight_last = 0.0   # share of the learned steady state in the last call, -

    @property
    def not_converged(self) -> int:
        """Algorithm 1 searches that hit their iteration bound (0 without it)."""
        return int(getattr(self.fixed_point, "not_converged", 0))

    @property
    def rounds_last(self) -> int:
        """Algorithm 1's rounds in the last call (0 without its share)."""
        return int(getattr(self.fixed_point, "rounds_last", 0))

    def reset(self) -> None:
        """The learned steady-state search's memory (the grip estimate is reset by its
        owner)."""
        self.factor_last = 1.0
        self.weight_last = 0.0
        r = getattr(self.fixed_point, "reset", None)
        if r is not None:
            r()

    def get_state(self) -> dict[str, Any]:
        """Algorithm 1's state (its |ay| envelope and previous point), if used."""
        g = getattr(self.fixed_point, "get_state", None)
        return g() if g is not None else {}

    def set_state(self, d: dict[str, Any]) -> None:
        """Restore get_state()."""
        s = getattr(self.fixed_point, "set_state", None)
        if s is not None:
            s(d)

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad) at Vx m/s and road-wheel angle δw rad."""
        r_lin, _, b_lin = self.linear.compute(vx, vy, yaw_rate, delta_w, total_torque, ay_meas)
        c = self.cfg
        r_lim = c.demand_margin * self.grip.mu * G_MPS2 / max(vx, self.v_min)
        n = c.demand_sharpness
        f = 1.0 / (1.0 + abs(r_lin / r_lim) ** n) ** (1.0 / n)
        self.factor_last = f
        r_d, vy_d = f * r_lin, f * b_lin * vx
        if self.fixed_point is not None:
            ra, va, _ = self.fixed_point.compute(vx, vy, yaw_rate, delta_w, total_torque,
                                                 ay_meas)
            beta = abs(vy) / max(vx, self.v_min) if math.isfinite(vy + vx) else 0.0
            w = c.fixed_point_share * min(max(
                (beta - c.fixed_point_beta_lo) / (c.fixed_point_beta_hi - c.fixed_point_beta_lo),
                0.0), 1.0)
            self.weight_last = w
            r_d = (1.0 - w) * r_d + w * ra
            vy_d = (1.0 - w) * vy_d + w * va
        return r_d, vy_d, vy_d / max(vx, self.v_min)
