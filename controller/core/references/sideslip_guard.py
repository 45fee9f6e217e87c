"""Sideslip guard on any yaw-rate reference.

The QP weighs β, but with N = 3 stages of 50 ms ΔM cannot move β inside the horizon
(∂β₂/∂ΔM ≈ 0.1°/kN·m, measured): the β objective never limits a slide. What ΔM *can* move
within one period is the yaw rate, and the yaw rate sets how β evolves. With Vy, ay in
body axes (ay the accelerometer's lateral acceleration, m/s²):

    V̇y = ay − ωr·Vx   ⇒   β̇ ≈ ay/Vx − ωr          (β = Vy/Vx, Vx slowly varying)

an identity of planar motion that holds at any grip and needs no model. The guard turns
a sideslip limit into a yaw-rate limit: while |β| exceeds ``guard_beta_rad`` by e, the
yaw reference is held on the side where β shrinks at least at rate k·e:

    sgn(β)·ωrd ≥ sgn(β)·ay/Vx + k·e,     k = guard_gain_per_s (1/s)

Below the threshold, or on the side already satisfying the bound, the inner reference is
returned unchanged; so in normal driving the guard is inactive. It wraps any
ReferenceGenerator (design choice and thresholds measured in `rhonn-harness benchmark`).

Look-ahead (``lead_s`` = T, s; 0 = off): the guard acts on β_T = β + T·β̇ with the same
identity for β̇, i.e. on the sideslip T seconds ahead if it kept growing (the phase-plane
view of stability: a slide is judged by β and β̇ together). It engages before a
fast-growing slide reaches the threshold and lets go while β is already shrinking.

Grip-scaled threshold (``beta_per_g`` rad per g, ``beta_max`` rad; 0 = off; numpy reference
only): threshold = clip(beta_per_g · envelope(|ay|)/g, beta_rad, beta_max), the envelope a
peak hold of |ay| decaying by ``ay_decay`` per call (the grip the car has shown).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controller.core.interfaces import ReferenceGenerator

_G = 9.81   # the g of the grip-scaled threshold, m/s²


class SideslipGuard:
    """ReferenceGenerator wrapper: limits ωrd so that |β| above ``beta_rad`` decays."""

    def __init__(self, inner: ReferenceGenerator, beta_rad: float, gain_per_s: float,
                 v_min: float, lead_s: float = 0.0, beta_per_g: float = 0.0,
                 beta_max: float = 0.0, ay_decay: float = 0.0) -> None:
        self.inner = inner
        self.beta_rad = float(beta_rad)      # |β| threshold, rad
        self.gain_per_s = float(gain_per_s)  # decay rate demanded per rad of excess, 1/s
        self.v_min = float(v_min)            # no guard below this speed, m/s
        self.lead_s = float(lead_s)          # look-ahead on β̇, s
        self.beta_per_g = float(beta_per_g)  # grip-scaled threshold, rad per g (0 = off)
        self.beta_max = float(beta_max)      # its upper bound, rad
        self.ay_decay = float(ay_decay)      # |ay| envelope decay factor per call, -
        self.ay_envelope = 0.0               # |ay| envelope, m/s²
        self.active_calls = 0                # calls since the last reset in which the
                                             #   guard changed ωrd

    def __getattr__(self, name: str) -> Any:
        # Counters and diagnostics of the wrapped generator (not_converged, weight_last, …).
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def reset(self) -> None:
        """Reset the wrapped generator and the activity counter."""
        r = getattr(self.inner, "reset", None)
        if r is not None:
            r()
        self.active_calls = 0
        self.ay_envelope = 0.0

    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad): the inner references, ωrd limited as above."""
        r_d, vy_d, b_d = self.inner.compute(vx, vy, yaw_rate, delta_w, total_torque, ay_meas)
        if self.beta_per_g > 0.0 and math.isfinite(ay_meas):
            self.ay_envelope = max(abs(ay_meas), self.ay_envelope * self.ay_decay)
        if not (vx > self.v_min and math.isfinite(vy) and math.isfinite(ay_meas)):
            return r_d, vy_d, b_d
        beta = vy / vx
        if self.lead_s > 0.0 and math.isfinite(yaw_rate):
            beta += self.lead_s * (ay_meas / vx - yaw_rate)
        threshold = self.beta_rad
        if self.beta_per_g > 0.0:
            threshold = min(max(self.beta_per_g * self.ay_envelope / _G, threshold),
                            max(self.beta_max, threshold))
        excess = abs(beta) - threshold
        if excess <= 0.0:
            return r_d, vy_d, b_d
        s = 1.0 if beta > 0.0 else -1.0
        r_lim = ay_meas / vx + s * self.gain_per_s * excess
        if s * r_d < s * r_lim:
            r_d = r_lim
            self.active_calls += 1
        return r_d, vy_d, b_d

    def get_state(self) -> dict[str, np.ndarray | float]:
        """State of the wrapped generator (the guard itself is memoryless)."""
        g = getattr(self.inner, "get_state", None)
        return g() if g is not None else {}

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        s = getattr(self.inner, "set_state", None)
        if s is not None:
            s(d)
