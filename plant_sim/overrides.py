"""Plant parameter overrides (``--vehicle KEY=VALUE``) and per-seed sensor biases.

Overrides (robustness studies). KEY is either a numeric field of
:class:`plant_sim.params.VehicleParams` set to an absolute value (``mass_kg=2380``,
``yaw_inertia_kgm2=4390``, ``cg_height_m=0.65`` ...) or one of the relative keys:

* ``mass_scale`` — factor on the total mass, -;
* ``yaw_inertia_scale`` — factor on Iz, -;
* ``cg_shift_m`` — CG moved forward by this many metres (lf − d, lr + d; wheelbase kept), m;
* ``cornering_stiffness_scale`` — factor on the tyres' cornering stiffness (MF λ_Kyα,
  both axles), -;
* ``tyre_peak_scale`` — factor on the tyres' peak friction coefficients (PDX1, PDY1:
  the tyre's own grip, independent of the road μ), -.

Every absolute value must be > 0 (``roll_stiffness_front_share`` also < 1; ``step_s`` must
divide the 10 ms communication cycle, which is fixed by the bus schedule and no override).
Unknown keys, non-numbers, non-finite values and factors <= 0 raise ``ValueError`` (one
line naming the key).

Per-seed sensor biases: seed 0 keeps the biases of vehicle.toml (the reference runs stay
bit-identical); every other seed draws each constant bias uniformly within
±BIAS_SPREAD × max(|nominal|, floor) from its own generator (independent of the noise
stream), so a seed changes the noise, the biases and — through the controller config —
the RHONN's initial weights.
"""

from __future__ import annotations

import copy
import difflib
import math
from dataclasses import fields, replace
from typing import Any

import numpy as np

from plant_sim.params import SensorParams, VehicleParams

RELATIVE_KEYS = ("mass_scale", "yaw_inertia_scale", "cg_shift_m",
                 "cornering_stiffness_scale", "tyre_peak_scale")
BIAS_SPREAD = 2.0
# (field, floor of the spread's base value in the field's unit)
_BIASES = (("yaw_rate_bias_degps", 0.05), ("ax_bias_mps2", 0.02), ("ay_bias_mps2", 0.02),
           ("vx_bias_mps", 0.02), ("vy_bias_mps", 0.02))


# fixed by the bus schedule (10 ms cycle, docs/can-matrix.md): the controller, the harness and
# the CAN timing all run on it, so the plant may not change it on its own
_FIXED = ("comm_period_s",)
# absolute keys with an upper bound besides > 0 (a share)
_AT_MOST_ONE = ("roll_stiffness_front_share",)


def vehicle_keys() -> list[str]:
    """Every accepted override key."""
    numeric = [f.name for f in fields(VehicleParams)
               if f.name not in ("sensors", "tyre_config", *_FIXED)]
    return sorted(numeric) + list(RELATIVE_KEYS)


def _factor(key: str, value: float) -> float:
    if not value > 0.0:
        raise ValueError(f"{key} must be a factor > 0, got {value:g}")
    return value


def _unknown(key: str) -> ValueError:
    if key in _FIXED:
        return ValueError(f"{key} is fixed by the bus schedule, not an override")
    close = difflib.get_close_matches(key, vehicle_keys(), n=1, cutoff=0.6)
    if close:
        return ValueError(f"unknown vehicle override {key!r}; did you mean {close[0]!r}?")
    return ValueError(f"unknown vehicle override {key!r}; accepted: "
                      f"{', '.join(RELATIVE_KEYS)} or a number of plant_sim/params/vehicle.toml "
                      "(e.g. mass_kg, cg_height_m)")


def apply_vehicle_overrides(params: VehicleParams, overrides: dict[str, Any]) -> VehicleParams:
    """A copy of ``params`` with ``overrides`` applied (see the module docstring); a bad
    key or value raises ValueError naming the key (one line)."""
    if not overrides:
        return params
    numeric = set(vehicle_keys()) - set(RELATIVE_KEYS)
    changes: dict[str, Any] = {}
    tyre = copy.deepcopy(params.tyre_config)
    for key, raw in overrides.items():
        try:
            value = float(raw)
        except (TypeError, ValueError):
            raise ValueError(f"{key}={raw!r} is not a number") from None
        if not math.isfinite(value):
            raise ValueError(f"{key} must be a finite number, got {raw!r}")
        if key in numeric:
            # every absolute plant parameter is a positive physical quantity
            if not value > 0.0 or (key in _AT_MOST_ONE and not value < 1.0):
                bounds = "> 0 and < 1" if key in _AT_MOST_ONE else "> 0"
                raise ValueError(f"{key} must be {bounds}, got {value:g}")
            changes[key] = value
        elif key == "mass_scale":
            changes["mass_kg"] = params.mass_kg * _factor(key, value)
        elif key == "yaw_inertia_scale":
            changes["yaw_inertia_kgm2"] = params.yaw_inertia_kgm2 * _factor(key, value)
        elif key == "cg_shift_m":
            if not abs(value) < min(params.lf_m, params.lr_m):
                raise ValueError(f"cg_shift_m = {value:g} m moves the CG off the wheelbase "
                                 f"(|shift| < {min(params.lf_m, params.lr_m):g} m)")
            changes["lf_m"] = params.lf_m - value
            changes["lr_m"] = params.lr_m + value
        elif key == "cornering_stiffness_scale":
            f = _factor(key, value)
            tyre["scaling"]["LKY_FRONT"] = tyre["scaling"]["LKY_FRONT"] * f
            tyre["scaling"]["LKY_REAR"] = tyre["scaling"]["LKY_REAR"] * f
        elif key == "tyre_peak_scale":
            f = _factor(key, value)
            tyre["published"]["PDX1"] = tyre["published"]["PDX1"] * f
            tyre["published"]["PDY1"] = tyre["published"]["PDY1"] * f
        else:
            raise _unknown(key)
    mass = changes.get("mass_kg", params.mass_kg)
    unsprung = 4.0 * changes.get("unsprung_mass_per_corner_kg",
                                 params.unsprung_mass_per_corner_kg)
    if not mass > unsprung:
        raise ValueError(f"mass_kg = {mass:g} kg leaves no sprung mass (four corners carry "
                         f"{unsprung:g} kg)")
    step = changes.get("step_s", params.step_s)
    n = params.comm_period_s / step
    if abs(n - round(n)) > 1e-9 or round(n) < 1:
        raise ValueError(f"step_s = {step:g} s must divide the {params.comm_period_s:g} s "
                         "communication cycle")
    return replace(params, tyre_config=tyre, **changes)


def seeded_sensor_params(sensors: SensorParams, seed: int) -> SensorParams:
    """Sensor parameters with the constant biases drawn for ``seed`` (seed 0: unchanged)."""
    if seed == 0:
        return sensors
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xB1A5])
    changes = {}
    for name, floor in _BIASES:
        base = max(abs(float(getattr(sensors, name))), floor)
        changes[name] = float(rng.uniform(-BIAS_SPREAD * base, BIAS_SPREAD * base))
    return replace(sensors, **changes)


def parse_key_values(items: list[str], flag: str = "--vehicle") -> dict[str, float]:
    """``["mass_scale=1.15", ...]`` → ``{"mass_scale": 1.15}``; a bad item raises ValueError."""
    out: dict[str, float] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{flag} needs KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"{flag} {key}: {value!r} is not a number") from None
    return out
