"""Vehicle and motor parameters as the controller knows them (loaded from TOML)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from controller.core.config_schema import ConfigError, require_nonnegative, require_positive


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """Rigid-body, wheel and motor parameters (SI units).

    mass_kg: kg. yaw_inertia_kgm2: kg·m². lf_m, lr_m: CG to axle, m. track_m: wB, m.
    wheel_inertia_kgm2: kg·m². wheel_radius_m: m. cf/cr_axle_n_per_rad: axle cornering
    stiffness, N/rad, paper sign (negative). cg_height_m: m. steering_ratio: steering-wheel
    angle per road-wheel angle, -. peak_torque_nm: per motor, N·m. peak_power_w: per motor, W.
    torque_rate_nm_per_s: per motor, the largest |dT/dt| the motor follows, N·m/s (0 = no
    limit; the allocation slews every wheel torque within it).
    """

    mass_kg: float
    yaw_inertia_kgm2: float
    lf_m: float
    lr_m: float
    track_m: float
    wheel_inertia_kgm2: float
    wheel_radius_m: float
    cf_axle_n_per_rad: float
    cr_axle_n_per_rad: float
    cg_height_m: float
    steering_ratio: float
    peak_torque_nm: float
    peak_power_w: float
    torque_rate_nm_per_s: float = 0.0

    @property
    def wheelbase_m(self) -> float:
        """lf + lr, m."""
        return self.lf_m + self.lr_m

    @property
    def yaw_moment_per_delta_m(self) -> float:
        """Body yaw moment per unit ΔM, wB / (2 r), (N·m)/(N·m) = 1/m · m."""
        return self.track_m / (2.0 * self.wheel_radius_m)


def load_vehicle_params(path: str | Path | None = None) -> VehicleParams:
    """Read [vehicle] and [motors] from a TOML file (default: the packaged vehicle.toml)."""
    if path is None:
        text = resources.files("controller").joinpath("config/vehicle.toml").read_text()
    else:
        text = Path(path).read_text()
    data = tomllib.loads(text)
    params = VehicleParams(**data["vehicle"], **data["motors"])
    check_vehicle_params(params)
    return params


_POSITIVE = ("mass_kg", "yaw_inertia_kgm2", "lf_m", "lr_m", "track_m", "wheel_inertia_kgm2",
             "wheel_radius_m", "steering_ratio", "peak_torque_nm", "peak_power_w")


def check_vehicle_params(p: VehicleParams) -> None:
    """ConfigError naming the first parameter out of its physical range: masses, inertias,
    lengths, ratio and motor ratings finite and > 0, the axle cornering stiffnesses finite
    and < 0 (the paper's sign), the CG height and the torque rate finite and >= 0."""
    require_positive(p, "vehicle", _POSITIVE)
    require_nonnegative(p, "vehicle", ("cg_height_m", "torque_rate_nm_per_s"))
    for key in ("cf_axle_n_per_rad", "cr_axle_n_per_rad"):
        if not -math.inf < getattr(p, key) < 0.0:
            raise ConfigError("vehicle", key, "must be a finite number < 0 (paper sign)")
