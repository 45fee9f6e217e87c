"""Plant parameters: loading ``params/vehicle.toml`` (and the tyre TOML) into typed objects.

Every field is SI; the unit is in the field name (``_m``, ``_kg``, ``_s``, ``_nm`` ...).
The TOML file carries the one-line reason/source of each value.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any

from plant_sim.tyre import MagicFormulaTyre, build_coefficients, load_tyre_config


@dataclass(frozen=True, slots=True)
class SensorParams:
    """Sensor noise (1 sigma per comm cycle), constant bias and quantisation (CAN resolution)."""

    yaw_rate_noise_degps: float = 0.10
    yaw_rate_bias_degps: float = 0.05
    accel_noise_mps2: float = 0.03
    ax_bias_mps2: float = 0.02
    ay_bias_mps2: float = -0.02
    accel_includes_gravity_tilt: bool = True
    wheel_speed_noise_radps: float = 0.02
    swa_noise_deg: float = 0.0
    yaw_rate_res_degps: float = 0.005
    accel_res_mps2: float = 0.005
    wheel_speed_res_radps: float = 0.1
    swa_res_deg: float = 0.05
    vx_est_res_mps: float = 0.005
    vy_est_res_mps: float = 0.002
    # upstream estimator model (truth + bias + noise, first-order lag), m/s and s
    vx_noise_mps: float = 0.05
    vx_bias_mps: float = 0.0
    vx_lag_s: float = 0.02
    vy_noise_mps: float = 0.02
    vy_bias_mps: float = 0.0
    vy_lag_s: float = 0.05


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """All plant parameters (SI; see ``params/vehicle.toml`` for the reason of each value)."""

    # body
    mass_kg: float
    yaw_inertia_kgm2: float
    lf_m: float
    lr_m: float
    track_m: float
    cg_height_m: float
    vehicle_width_m: float
    unsprung_mass_per_corner_kg: float
    gravity_mps2: float
    # suspension
    roll_axis_height_m: float
    pitch_axis_height_m: float
    roll_inertia_kgm2: float
    pitch_inertia_kgm2: float
    roll_stiffness_nm_per_rad: float
    roll_damping_nms_per_rad: float
    roll_stiffness_front_share: float
    pitch_stiffness_nm_per_rad: float
    pitch_damping_nms_per_rad: float
    # wheel
    wheel_inertia_kgm2: float
    wheel_radius_m: float
    rolling_resistance_coeff: float
    rr_smoothing_speed_mps: float
    # steering
    steering_ratio: float
    max_road_wheel_angle_deg: float
    # aero
    air_density_kgpm3: float
    drag_area_m2: float
    # motors
    peak_torque_nm: float
    peak_power_w: float
    time_constant_s: float
    regen_fade_speed_radps: float
    # integration
    step_s: float
    comm_period_s: float
    # spin / finish
    beta_limit_deg: float
    yaw_rate_limit_degps: float
    min_speed_mps: float
    stop_speed_mps: float
    min_time_s: float
    max_lateral_dev_m: float
    sensors: SensorParams = field(default_factory=SensorParams)
    tyre_config: dict[str, Any] = field(default_factory=dict)

    @property
    def wheelbase_m(self) -> float:
        """L = lf + lr, m."""
        return self.lf_m + self.lr_m

    @property
    def sprung_mass_kg(self) -> float:
        """Total minus four unsprung corners, kg."""
        return self.mass_kg - 4.0 * self.unsprung_mass_per_corner_kg

    @property
    def static_wheel_loads_n(self) -> tuple[float, float]:
        """(front, rear) static load per wheel, N."""
        w = self.mass_kg * self.gravity_mps2
        return w * self.lr_m / (2.0 * self.wheelbase_m), w * self.lf_m / (2.0 * self.wheelbase_m)

    def tyres(self) -> tuple[MagicFormulaTyre, MagicFormulaTyre]:
        """(front, rear) Magic Formula tyres built from ``tyre_config``."""
        return (
            MagicFormulaTyre(build_coefficients(self.tyre_config, "front")),
            MagicFormulaTyre(build_coefficients(self.tyre_config, "rear")),
        )

    def with_changes(self, **changes: Any) -> VehicleParams:
        """A copy with some fields replaced (for tests and parameter studies)."""
        return replace(self, **changes)


_SECTIONS = ("body", "suspension", "wheel", "steering", "aero", "motors", "integration", "spin",
             "finish")


def load_vehicle_params(
    path: str | Path | None = None, tyre_path: str | Path | None = None
) -> VehicleParams:
    """Load the vehicle TOML (default: packaged ``params/vehicle.toml``) and the tyre TOML."""
    if path is None:
        text = resources.files("plant_sim").joinpath("params/vehicle.toml").read_text()
    else:
        text = Path(path).read_text()
    data = tomllib.loads(text)
    flat: dict[str, Any] = {}
    for section in _SECTIONS:
        flat.update(data.get(section, {}))
    sensor_kw = dict(data.get("sensors", {}))
    sensor_kw.update(data.get("estimator", {}))
    known = {f.name for f in fields(SensorParams)}
    unknown = set(sensor_kw) - known
    if unknown:
        raise KeyError(f"unknown sensor parameters: {sorted(unknown)}")
    expected = {f.name for f in fields(VehicleParams)} - {"sensors", "tyre_config"}
    missing = expected - set(flat)
    extra = set(flat) - expected
    if missing or extra:
        raise KeyError(f"vehicle params: missing {sorted(missing)}, unknown {sorted(extra)}")
    return VehicleParams(
        **flat, sensors=SensorParams(**sensor_kw), tyre_config=load_tyre_config(tyre_path)
    )
