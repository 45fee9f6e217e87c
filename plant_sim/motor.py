"""In-wheel motor: torque-speed-power envelope and first-order torque lag.

Torques in N·m (+ drives the wheel forward), wheel speed in rad/s, power in W, time in s.
"""

from __future__ import annotations

import math


class MotorModel:
    """Envelope |T| <= min(T_peak, P_peak / |omega|), braking torque faded near standstill.

    The lag is integrated exactly for a piecewise-constant command over one step:
    ``T += (T_cmd - T) * (1 - exp(-dt / tau))``.
    """

    def __init__(
        self,
        peak_torque_nm: float,
        peak_power_w: float,
        time_constant_s: float,
        regen_fade_speed_radps: float,
        step_s: float,
    ) -> None:
        if peak_torque_nm <= 0 or peak_power_w <= 0 or time_constant_s < 0:
            raise ValueError("motor limits must be positive and the time constant >= 0")
        self.peak_torque_nm = peak_torque_nm
        self.peak_power_w = peak_power_w
        self.time_constant_s = time_constant_s
        self.regen_fade_speed_radps = max(regen_fade_speed_radps, 1e-6)
        self.base_speed_radps = peak_power_w / peak_torque_nm
        self.lag_gain = 1.0 if time_constant_s == 0 else 1.0 - math.exp(-step_s / time_constant_s)

    def limits(self, omega_radps: float) -> tuple[float, float]:
        """(T_min, T_max) in N·m available at wheel speed omega (rad/s).

        Power limit above the base speed; negative (braking) torque fades linearly to zero
        below ``regen_fade_speed_radps`` so that braking stops the car rather than reversing it.
        """
        w = abs(omega_radps)
        t_max = self.peak_torque_nm if w <= self.base_speed_radps else self.peak_power_w / w
        fade = omega_radps / self.regen_fade_speed_radps
        if fade < 0.0:
            fade = 0.0
        elif fade > 1.0:
            fade = 1.0
        return -t_max * fade, t_max

    def saturate(self, torque_nm: float, omega_radps: float) -> tuple[float, bool]:
        """Clamp a command to the envelope; returns (torque N·m, saturated?)."""
        t_min, t_max = self.limits(omega_radps)
        if torque_nm > t_max:
            return t_max, True
        if torque_nm < t_min:
            return t_min, True
        return torque_nm, False
