"""Sensors the controller sees: noise, bias and quantisation to the CAN resolution, seeded.

Sampled once per communication cycle (the RNG draws are therefore independent of how often
``Simulation.sensors()`` is read). Units are in the field names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plant_sim.params import SensorParams


@dataclass(frozen=True, slots=True)
class SensorFrame:
    """One cycle of measured signals (what goes on the bus).

    swa_deg: steering-wheel angle, deg (+ left). accel_pedal, brake_pedal: 0..1.
    stab_enable: the stability function may act. yaw_rate_degps: deg/s (+ left).
    ax_mps2, ay_mps2: body-mounted accelerometer, m/s^2. wheel_speeds_radps: FL, FR, RL, RR
    in rad/s. vx_est_mps, vy_est_mps: upstream estimator output at the CG, m/s.
    """

    swa_deg: float
    accel_pedal: float
    brake_pedal: float
    stab_enable: bool
    yaw_rate_degps: float
    ax_mps2: float
    ay_mps2: float
    wheel_speeds_radps: tuple[float, float, float, float]
    vx_est_mps: float
    vy_est_mps: float


def quantise(value: float, resolution: float) -> float:
    """Round to the nearest multiple of ``resolution`` (no-op if resolution <= 0)."""
    if resolution <= 0.0:
        return value
    return round(value / resolution) * resolution


def _lag_gain(dt: float, tau: float) -> float:
    """Exact first-order-lag update gain for step dt (s) and time constant tau (s)."""
    return 1.0 if tau <= 0.0 else 1.0 - math.exp(-dt / tau)


class SensorModel:
    """Noise/bias/quantisation of the motion sensors and the estimator's first-order lag."""

    def __init__(self, params: SensorParams, comm_period_s: float, seed: int) -> None:
        self.p = params
        self.rng = np.random.default_rng(seed)
        self.a_vx = _lag_gain(comm_period_s, params.vx_lag_s)
        self.a_vy = _lag_gain(comm_period_s, params.vy_lag_s)
        self.vx_f: float | None = None
        self.vy_f = 0.0

    def sample(
        self, *, swa_rad: float, accel_pedal: float, brake_pedal: float, stab_enable: bool,
        yaw_rate: float, ax: float, ay: float, roll: float, pitch: float, gravity: float,
        omegas: list[float], vx: float, vy: float,
    ) -> SensorFrame:
        """Measure the truth (SI: rad, rad/s, m/s^2, m/s) and return the quantised frame."""
        p = self.p
        n = self.rng.standard_normal(10).tolist()
        if p.accel_includes_gravity_tilt:
            # specific force seen by a body-mounted sensor: + roll (right side down) tilts the
            # y axis up-left, so gravity adds g*sin(roll) to ay; + pitch (nose down) adds to ax
            ax_s = ax * math.cos(pitch) - gravity * math.sin(pitch)
            ay_s = ay * math.cos(roll) + gravity * math.sin(roll)
        else:
            ax_s, ay_s = ax, ay
        vx_m = vx + p.vx_bias_mps + p.vx_noise_mps * n[8]
        vy_m = vy + p.vy_bias_mps + p.vy_noise_mps * n[9]
        if self.vx_f is None:
            self.vx_f, self.vy_f = vx_m, vy_m  # estimator converged at start
        else:
            self.vx_f += self.a_vx * (vx_m - self.vx_f)
            self.vy_f += self.a_vy * (vy_m - self.vy_f)
        wn, wr = p.wheel_speed_noise_radps, p.wheel_speed_res_radps
        wheels = (
            quantise(omegas[0] + wn * n[4], wr), quantise(omegas[1] + wn * n[5], wr),
            quantise(omegas[2] + wn * n[6], wr), quantise(omegas[3] + wn * n[7], wr),
        )
        return SensorFrame(
            swa_deg=quantise(math.degrees(swa_rad) + p.swa_noise_deg * n[0], p.swa_res_deg),
            accel_pedal=min(1.0, max(0.0, accel_pedal)),
            brake_pedal=min(1.0, max(0.0, brake_pedal)),
            stab_enable=bool(stab_enable),
            yaw_rate_degps=quantise(math.degrees(yaw_rate) + p.yaw_rate_bias_degps
                                    + p.yaw_rate_noise_degps * n[1], p.yaw_rate_res_degps),
            ax_mps2=quantise(ax_s + p.ax_bias_mps2 + p.accel_noise_mps2 * n[2], p.accel_res_mps2),
            ay_mps2=quantise(ay_s + p.ay_bias_mps2 + p.accel_noise_mps2 * n[3], p.accel_res_mps2),
            wheel_speeds_radps=wheels,
            vx_est_mps=quantise(self.vx_f, p.vx_est_res_mps),
            vy_est_mps=quantise(self.vy_f, p.vy_est_res_mps),
        )
