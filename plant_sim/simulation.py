"""Plant simulation: scenario + driver + vehicle + sensors, advanced one communication cycle
at a time (no bus I/O; ``plant_sim/process.py`` wraps this for the CAN bus).

Torque contract (shared with the controller): the driver's total torque demand is
``Tt = (accel_pedal - brake_pedal) * 4 * 450 N·m``; without a valid command the plant applies
Tt/4 to each wheel ("the car without the stability function"). Commands are saturated at the
motor envelope (torque, power, braking fade) using the wheel speeds at the start of the cycle.

A run is ``finished`` when the duration is reached, the car reached the end of the reference
path, came to rest (speed < stop_speed_mps after min_time_s) or left the test area
(|lateral deviation| > max_lateral_dev_m, path-following runs only). ``spun`` latches when
|beta| > beta_limit_deg or |yaw rate| > yaw_rate_limit_degps above min_speed_mps; the
simulation carries on regardless.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import numpy as np

from plant_sim.body import VehicleModel
from plant_sim.driver import Driver
from plant_sim.overrides import seeded_sensor_params
from plant_sim.params import VehicleParams, load_vehicle_params
from plant_sim.scenario import Scenario
from plant_sim.sensors import SensorFrame, SensorModel

WHEELS = ("fl", "fr", "rl", "rr")

# Truth trace, one row per communication cycle. Units: t_s s; x_m, y_m m (global); yaw_rad,
# beta_rad, roll_rad (+ right side down), pitch_rad (+ nose down), swa_rad, delta_f_rad rad;
# vx/vy m/s (body axes at the CG); yaw_rate rad/s; ax/ay m/s^2 (CG, body axes, no gravity);
# omega rad/s; tcmd (applied command after saturation) / tact (motor output) N·m; fz, fx, fy N
# (fx, fy in wheel axes); mu -; alpha rad and kappa - (relaxed slips); lateral_dev_m + = left of
# the path; delta_m_nm = T2 + T4 - T1 - T3 of the applied command; total_torque_nm = the
# driver's Tt; spun, cmd_valid 0/1; saturations = saturated wheel commands this cycle.
TRACE_COLUMNS: list[str] = [
    "t_s", "cycle", "x_m", "y_m", "yaw_rad", "vx_mps", "vy_mps", "yaw_rate_radps", "beta_rad",
    "ax_mps2", "ay_mps2", "roll_rad", "pitch_rad", "swa_rad", "delta_f_rad", "accel_pedal",
    "brake_pedal", "stab_enable",
    *[f"omega_{w}" for w in WHEELS],
    *[f"tcmd_{w}" for w in WHEELS],
    *[f"tact_{w}" for w in WHEELS],
    *[f"fz_{w}" for w in WHEELS],
    *[f"mu_{w}" for w in WHEELS],
    *[f"fx_{w}" for w in WHEELS],
    *[f"fy_{w}" for w in WHEELS],
    *[f"alpha_{w}" for w in WHEELS],
    *[f"kappa_{w}" for w in WHEELS],
    "lateral_dev_m", "path_s_m", "speed_mps", "delta_m_nm", "total_torque_nm",
    "spun", "cmd_valid", "saturations",
]

PEDAL_TORQUE_NM = 4.0 * 450.0  # N·m of total torque per unit pedal (CAN/controller contract)


class Simulation:
    """One scenario run. See the module docstring for the contract; units in the names."""

    def __init__(self, scenario: Scenario, params: VehicleParams | None = None,
                 seed: int = 0) -> None:
        self.scenario = scenario
        self.params = params if params is not None else load_vehicle_params()
        p = self.params
        self.comm_period_s = p.comm_period_s
        self.steps_per_cycle = round(p.comm_period_s / p.step_s)
        if abs(self.steps_per_cycle * p.step_s - p.comm_period_s) > 1e-9:
            raise ValueError("comm_period_s must be an integer multiple of step_s")
        self.trace_columns = list(TRACE_COLUMNS)
        self.vehicle = VehicleModel(p)
        sx, sy = scenario.start_xy
        self.vehicle.reset(x=sx, y=sy, psi=scenario.start_yaw_rad, vx=scenario.initial_speed_mps)
        # own copy of the path: its projection warm-start index is per run, so several
        # simulations of one Scenario object may coexist
        self.path = copy.copy(scenario.path)
        self.path.reset()
        self.driver = Driver(scenario.driver, self.path, p.wheelbase_m, p.steering_ratio,
                             scenario.initial_speed_mps, p)
        # seed 0: the biases of vehicle.toml; other seeds draw them (plant_sim/overrides.py)
        self.sensor_model = SensorModel(seeded_sensor_params(p.sensors, seed),
                                        p.comm_period_s, seed)
        self._road_mu = math.nan   # base friction of the field in force, -
        self._set_friction(0.0)
        self.cycle = 0
        self.time_s = 0.0
        self.spun = False
        self.finished = False
        self.finish_reason = ""
        self.cmd_valid = False
        self.saturation_count = 0  # total saturated torque commands (per wheel per cycle)
        self.invalid_cmd_count = 0  # cycles with a command containing NaN/inf or wrong length
        self.tcmd = [0.0, 0.0, 0.0, 0.0]
        self._sat_this_cycle = 0
        self.path_s, self.lateral_dev = self.path.project(self.vehicle.x, self.vehicle.y)
        self._plan()
        self._frame = self._sample_sensors()

    # ------------------------------------------------------------------ helpers
    @property
    def stab_enable(self) -> bool:
        """The stability function may act (scenario's stab_enable_after_s reached)."""
        return self.time_s >= self.scenario.stab_enable_after_s - 1e-9

    @property
    def total_torque_nm(self) -> float:
        """Driver's total torque demand Tt from the pedals, N·m."""
        return (self.driver.accel_pedal - self.driver.brake_pedal) * PEDAL_TORQUE_NM

    def _set_friction(self, t_s: float) -> None:
        """Use the road's field in force at t_s s (a time step of the road changes it)."""
        road = self.scenario.friction
        mu = road.base_mu_at_time(t_s)
        if mu == self._road_mu:
            return
        self._road_mu = mu
        field = road.at_time(t_s)
        self._mu_const = field.uniform
        self._mu_lookup = field.mu_at
        # the wheels' μ is also set here, not only in the next step, so the truth row written
        # before the first step carries the road's friction
        for i, (wx, wy) in enumerate(self.vehicle.wheel_positions()):
            self.vehicle.mu[i] = (self._mu_const if self._mu_const is not None
                                  else self._mu_lookup(wx, wy))

    def _plan(self) -> None:
        v = self.vehicle
        self.driver.plan(self.time_s, v.x, v.y, v.psi, v.vx, self.path_s, self.comm_period_s)

    def _sample_sensors(self) -> SensorFrame:
        v = self.vehicle
        return self.sensor_model.sample(
            swa_rad=self.driver.swa, accel_pedal=self.driver.accel_pedal,
            brake_pedal=self.driver.brake_pedal, stab_enable=self.stab_enable, yaw_rate=v.r,
            ax=v.ax, ay=v.ay, roll=v.phi, pitch=v.theta, gravity=self.params.gravity_mps2,
            omegas=v.omega, vx=v.vx, vy=v.vy,
        )

    def _commands(self, torque_cmd: Sequence[float] | None) -> list[float]:
        """Validated and saturated per-wheel torque (N·m); counts saturations."""
        valid = torque_cmd is not None
        if valid:
            try:
                raw = [float(t) for t in torque_cmd]  # type: ignore[union-attr]
            except (TypeError, ValueError):
                raw = []
            valid = len(raw) == 4 and all(math.isfinite(t) for t in raw)
            if not valid:
                self.invalid_cmd_count += 1
        if not valid:
            raw = [0.25 * self.total_torque_nm] * 4
        self.cmd_valid = valid
        motor = self.vehicle.motor
        out = []
        sat = 0
        for t, w in zip(raw, self.vehicle.omega, strict=True):
            tc, s = motor.saturate(t, w)
            out.append(tc)
            sat += s
        self._sat_this_cycle = sat
        self.saturation_count += sat
        return out

    # ------------------------------------------------------------------ API
    def step_comm(self, torque_cmd: Sequence[float] | None) -> None:
        """Advance one communication cycle with the wheel torque command (FL, FR, RL, RR, N·m)
        or None (no valid command: the driver's Tt split evenly). No-op once ``finished``."""
        if self.finished:
            return
        self.tcmd = self._commands(torque_cmd)
        if self.scenario.friction.steps:
            self._set_friction(self.time_s)
        n = self.steps_per_cycle
        dt = self.params.step_s
        swas = self.driver.swa_steps(self.time_s, n, dt)
        inv_ratio = 1.0 / self.params.steering_ratio
        self.vehicle.advance([s * inv_ratio for s in swas], self.tcmd, self._mu_const,
                             self._mu_lookup)
        self.cycle += 1
        self.time_s = self.cycle * self.comm_period_s
        v = self.vehicle
        self.path_s, self.lateral_dev = self.path.project(v.x, v.y)
        self._check_spin_and_finish()
        self._plan()
        self._frame = self._sample_sensors()

    def _check_spin_and_finish(self) -> None:
        v = self.vehicle
        p = self.params
        speed = math.hypot(v.vx, v.vy)
        if speed > p.min_speed_mps and (
            abs(v.beta) > math.radians(p.beta_limit_deg)
            or abs(v.r) > math.radians(p.yaw_rate_limit_degps)
        ):
            self.spun = True
        if not all(math.isfinite(q) for q in (v.x, v.y, v.vx, v.vy, v.r)):
            # cannot happen by design; fail safe rather than propagate NaN downstream
            self.finished, self.finish_reason = True, "non-finite state"
        elif self.time_s >= self.scenario.duration_s - 1e-9:
            self.finished, self.finish_reason = True, "duration"
        elif self.path_s >= self.path.length_m:
            self.finished, self.finish_reason = True, "end of path"
        elif self.time_s >= p.min_time_s and speed < p.stop_speed_mps:
            self.finished, self.finish_reason = True, "stopped"
        elif self.scenario.driver.steer == "path" and abs(self.lateral_dev) > p.max_lateral_dev_m:
            self.finished, self.finish_reason = True, "left the test area"

    def sensors(self) -> SensorFrame:
        """Measured signals at the current cycle (noisy, biased, quantised, seeded)."""
        return self._frame

    def truth_row(self) -> dict[str, float]:
        """True state for the trace, keys = ``trace_columns``."""
        return dict(zip(self.trace_columns, self.truth_values(), strict=True))

    def truth_values(self) -> tuple[float, ...]:
        """True state for the trace as a tuple in ``trace_columns`` order (no dict: this is
        the plant process's per-cycle trace line)."""
        v = self.vehicle
        t = self.tcmd
        drv = self.driver
        return (
            self.time_s, float(self.cycle), v.x, v.y, v.psi, v.vx, v.vy, v.r, v.beta, v.ax,
            v.ay, v.phi, v.theta, drv.swa, v.delta, drv.accel_pedal, drv.brake_pedal,
            float(self.stab_enable),
            *v.omega[:4], *t[:4], *v.torque[:4], *v.fz[:4], *v.mu[:4], *v.fx[:4],
            *v.fy[:4], *v.alpha_t[:4], *v.kappa_t[:4],
            self.lateral_dev, self.path_s, math.hypot(v.vx, v.vy),
            t[1] + t[3] - t[0] - t[2], self.total_torque_nm, float(self.spun),
            float(self.cmd_valid), float(self._sat_this_cycle),
        )


def run_passive(
    scenario: Scenario, seed: int = 0, params: VehicleParams | None = None,
    max_time_s: float | None = None,
) -> dict[str, np.ndarray]:
    """Run a scenario open loop (no controller: torque = driver's Tt split evenly).

    Returns the truth trace as columns -> arrays (one row per communication cycle, including
    the initial state at t = 0).
    """
    sim = Simulation(scenario, params=params, seed=seed)
    rows = [sim.truth_row()]
    while not sim.finished and (max_time_s is None or sim.time_s < max_time_s - 1e-9):
        sim.step_comm(None)
        rows.append(sim.truth_row())
    return {c: np.array([r[c] for r in rows]) for c in sim.trace_columns}
