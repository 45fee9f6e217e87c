"""Driver models: preview path follower + speed holder, and open-loop steering robots.

Units: steering-wheel angle (SWA) in rad internally (deg in the spec), + = left; speed m/s
(km/h in the spec); time s; pedals 0..1.

Lateral ("steer" modes):

* ``path``: single-point preview (pure-pursuit geometry) on the scenario's reference path:
  preview distance max(preview_min_m, preview_time_s * vx); the road-wheel angle that puts the
  car on the circle through the preview point, times the steering ratio, is the SWA target.
  A human-like neuromuscular first-order lag and a SWA rate limit act on it.
* ``sine_dwell``: FMVSS 126 / UN R140 robot: 0.7 Hz sine, 500 ms dwell at the second peak.
* ``ramp``: slowly increasing steer (FMVSS 126 "SIS": 13.5 deg/s) from ``start_s``.
* ``step``: step steer (ISO 7401 style) at ``step_rate_degps`` to ``amplitude_deg``.
* ``none``: straight ahead.

Longitudinal ("speed" modes): ``hold`` (PI + feed-forward on the speed error; target may ramp),
``coast`` (pedals released), ``brake`` (brake pedal ramped to ``brake_pedal`` at
``brake_start_s``; steering still follows the path).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from plant_sim.path import ReferencePath

STEER_MODES = ("path", "sine_dwell", "ramp", "step", "none")
SPEED_MODES = ("hold", "coast", "brake")


@dataclass(frozen=True, slots=True)
class DriverSpec:
    """Driver configuration (the scenario's ``[driver]`` table); units in the names."""

    steer: str = "path"
    speed: str = "hold"
    # path follower
    preview_time_s: float = 0.8
    preview_min_m: float = 6.0
    steer_gain: float = 1.0
    neuromuscular_lag_s: float = 0.10
    swa_rate_limit_degps: float = 600.0
    max_swa_deg: float = 540.0
    # speed holder
    target_speed_kmh: float | None = None  # None: hold the initial speed
    speed_ramp_kmhps: float = 0.0
    speed_kp: float = 0.6  # pedal per m/s of error
    speed_ki: float = 0.15  # pedal per m of integrated error
    # open-loop robots
    amplitude_deg: float = 180.0
    direction: str = "left"
    start_s: float = 1.0
    frequency_hz: float = 0.7
    dwell_s: float = 0.5
    steer_rate_degps: float = 13.5
    step_rate_degps: float = 500.0
    # braking
    brake_pedal: float = 1.0
    brake_start_s: float = 1.0
    pedal_rate_per_s: float = 4.0

    def __post_init__(self) -> None:
        if self.steer not in STEER_MODES:
            raise ValueError(f"driver.steer must be one of {STEER_MODES}, got {self.steer!r}")
        if self.speed not in SPEED_MODES:
            raise ValueError(f"driver.speed must be one of {SPEED_MODES}, got {self.speed!r}")
        if self.direction not in ("left", "right"):
            raise ValueError(f"driver.direction must be 'left' or 'right', got {self.direction!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DriverSpec:
        """Build from a TOML table; unknown keys are an error (typos must not pass silently)."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise KeyError(f"unknown driver parameters: {sorted(unknown)}")
        return cls(**data)


def sine_with_dwell_deg(t_rel: float, amplitude_deg: float, frequency_hz: float = 0.7,
                        dwell_s: float = 0.5) -> float:
    """FMVSS 126 sine-with-dwell SWA (deg) at time t_rel (s) after steering starts; + first."""
    if t_rel <= 0.0:
        return 0.0
    w = 2.0 * math.pi * frequency_hz
    t_peak2 = 0.75 / frequency_hz  # second (negative) peak
    if t_rel < t_peak2:
        return amplitude_deg * math.sin(w * t_rel)
    if t_rel < t_peak2 + dwell_s:
        return -amplitude_deg
    if t_rel < 1.0 / frequency_hz + dwell_s:
        return amplitude_deg * math.sin(w * (t_rel - dwell_s))
    return 0.0


class Driver:
    """Stateful driver: ``plan()`` once per communication cycle, ``swa_steps()`` per cycle
    gives the SWA at every integration step (lag and rate limit integrated at that rate)."""

    def __init__(self, spec: DriverSpec, path: ReferencePath, wheelbase_m: float,
                 steering_ratio: float, initial_speed_mps: float, params: Any) -> None:
        self.spec = spec
        self.path = path
        self.wheelbase_m = wheelbase_m
        self.ratio = steering_ratio
        self.v0 = initial_speed_mps
        self.v_target0 = (initial_speed_mps if spec.target_speed_kmh is None
                          else spec.target_speed_kmh / 3.6)
        self.sign = 1.0 if spec.direction == "left" else -1.0
        self.params = params  # VehicleParams, for the speed holder's feed-forward
        self.swa = 0.0  # rad, actual steering-wheel angle
        self.swa_target = 0.0  # rad
        self.accel_pedal = 0.0
        self.brake_pedal = 0.0
        self._integ = 0.0

    # ------------------------------------------------------------------ longitudinal
    def target_speed(self, t: float) -> float:
        """Speed target at time t, m/s."""
        return self.v_target0 + self.spec.speed_ramp_kmhps / 3.6 * t

    def _pedals(self, t: float, vx: float, dt: float) -> None:
        sp = self.spec
        if sp.speed == "coast":
            self.accel_pedal = self.brake_pedal = 0.0
            return
        if sp.speed == "brake":
            self.accel_pedal = 0.0
            want = sp.brake_pedal if t >= sp.brake_start_s else 0.0
            step = sp.pedal_rate_per_s * dt
            self.brake_pedal += max(-step, min(step, want - self.brake_pedal))
            return
        p = self.params
        v_t = self.target_speed(t)
        err = v_t - vx
        # feed-forward: drag + rolling resistance + ramp acceleration, as a pedal fraction
        full_force = 4.0 * p.peak_torque_nm / p.wheel_radius_m
        f_ff = (0.5 * p.air_density_kgpm3 * p.drag_area_m2 * v_t * v_t
                + p.rolling_resistance_coeff * p.mass_kg * p.gravity_mps2
                + p.mass_kg * sp.speed_ramp_kmhps / 3.6)
        u_free = sp.speed_kp * err + sp.speed_ki * self._integ + f_ff / full_force
        if -1.0 < u_free < 1.0 or (u_free >= 1.0 and err < 0) or (u_free <= -1.0 and err > 0):
            self._integ += err * dt  # conditional integration (anti-windup)
        u = max(-1.0, min(1.0, sp.speed_kp * err + sp.speed_ki * self._integ + f_ff / full_force))
        step = sp.pedal_rate_per_s * dt
        want_acc, want_brk = max(u, 0.0), max(-u, 0.0)
        self.accel_pedal += max(-step, min(step, want_acc - self.accel_pedal))
        self.brake_pedal += max(-step, min(step, want_brk - self.brake_pedal))

    # ------------------------------------------------------------------ lateral
    def _path_target(self, x: float, y: float, psi: float, vx: float, s_now: float) -> float:
        sp = self.spec
        look = max(sp.preview_min_m, sp.preview_time_s * abs(vx))
        tx, ty, _ = self.path.point_at(s_now + look)
        dx, dy = tx - x, ty - y
        c, s = math.cos(psi), math.sin(psi)
        xb = c * dx + s * dy
        yb = -s * dx + c * dy
        d2 = xb * xb + yb * yb
        if d2 < 1e-6:
            return self.swa_target
        curvature = 2.0 * yb / d2  # circle through the CG tangent to the heading
        delta = math.atan(self.wheelbase_m * curvature) * sp.steer_gain
        lim = math.radians(sp.max_swa_deg)
        return max(-lim, min(lim, delta * self.ratio))

    def plan(self, t: float, x: float, y: float, psi: float, vx: float, s_now: float,
             dt_comm: float) -> None:
        """Update pedals and the SWA target from the state at the start of a cycle.

        t: s; x, y: CG position m; psi: yaw rad; vx: m/s; s_now: arc length on the path, m.
        """
        self._pedals(t, vx, dt_comm)
        if self.spec.steer == "path":
            self.swa_target = self._path_target(x, y, psi, vx, s_now)

    def robot_swa_deg(self, t: float) -> float:
        """Open-loop SWA (deg) of the robot modes at time t (s)."""
        sp = self.spec
        tr = t - sp.start_s
        if sp.steer == "sine_dwell":
            return self.sign * sine_with_dwell_deg(tr, sp.amplitude_deg, sp.frequency_hz,
                                                   sp.dwell_s)
        if sp.steer == "ramp":
            return self.sign * min(sp.max_swa_deg, max(0.0, tr) * sp.steer_rate_degps)
        if sp.steer == "step":
            return self.sign * min(sp.amplitude_deg, max(0.0, tr) * sp.step_rate_degps)
        return 0.0

    def swa_steps(self, t0: float, n: int, dt: float) -> list[float]:
        """SWA (rad) at the n integration steps t0 + k*dt, k = 1..n; updates the state."""
        sp = self.spec
        out: list[float] = []
        if sp.steer == "path":
            tau = sp.neuromuscular_lag_s
            rate = math.radians(sp.swa_rate_limit_degps) * dt
            a = 1.0 - math.exp(-dt / tau) if tau > 0 else 1.0
            swa, target = self.swa, self.swa_target
            for _ in range(n):
                d = (target - swa) * a
                swa += rate if d > rate else (-rate if d < -rate else d)
                out.append(swa)
            self.swa = swa
            return out
        if sp.steer == "none":
            self.swa = 0.0
            return [0.0] * n
        for k in range(1, n + 1):
            out.append(math.radians(self.robot_swa_deg(t0 + k * dt)))
        self.swa = out[-1]
        return out
