"""The vehicle's body footprint over a run and the cones it strikes.

The footprint is a rectangle in the vehicle frame: width b (the body width that sizes the
ISO 3888 cone layout, ``vehicle_width_m`` in plant_sim/params/vehicle.toml) and length from
the CG forward ``lf + front overhang`` and back ``lr + rear overhang``. Table 1 of the paper
gives lf, lr and the track but no body length, so the overhangs below are an assumption
(bumper-to-axle distances of a mid-size car) and named as such on the plots. The same
footprint sizes the plots' cone strikes and the benchmark's ISO 3888 *course* verdict
(harness/analysis/verdicts.py), so a plotted strike is a counted one. A cone counts as
struck when its base point lies inside the footprint at any sample of the truth trace
(100 Hz, ≤ 0.2 m of travel per sample at 65 km/h).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources

import numpy as np

FRONT_OVERHANG_M = 0.95  # assumption: body overhang ahead of the front axle, m
REAR_OVERHANG_M = 1.05  # assumption: body overhang behind the rear axle, m


@dataclass(frozen=True)
class Footprint:
    """Body rectangle relative to the CG: ``front_m`` ahead, ``rear_m`` behind, ``width_m``
    across (all m)."""

    front_m: float
    rear_m: float
    width_m: float

    @classmethod
    def for_vehicle(cls, lf_m: float, lr_m: float, width_m: float) -> Footprint:
        """Footprint from the CG–axle distances and the body width, m (overhangs added)."""
        return cls(lf_m + FRONT_OVERHANG_M, lr_m + REAR_OVERHANG_M, width_m)

    def corners_over_time(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """(T, 4, 2) world positions of the four corners, m, for CG tracks x, y m, yaw rad."""
        hw = self.width_m / 2
        local = np.array([[self.front_m, hw], [self.front_m, -hw],
                          [-self.rear_m, -hw], [-self.rear_m, hw]])
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        cx = x[:, None] + c * local[None, :, 0] - s * local[None, :, 1]
        cy = y[:, None] + s * local[None, :, 0] + c * local[None, :, 1]
        return np.stack([cx, cy], axis=-1)

    def corners(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(5, 2) closed outline in world coordinates, m, for CG (x, y) m and yaw rad."""
        local = np.array([[self.front_m, self.width_m / 2], [self.front_m, -self.width_m / 2],
                          [-self.rear_m, -self.width_m / 2], [-self.rear_m, self.width_m / 2],
                          [self.front_m, self.width_m / 2]])
        c, s = np.cos(yaw), np.sin(yaw)
        return np.column_stack([x + c * local[:, 0] - s * local[:, 1],
                                y + s * local[:, 0] + c * local[:, 1]])


def packaged_footprint() -> Footprint:
    """The footprint of the packaged vehicle (plant_sim/params/vehicle.toml)."""
    text = resources.files("plant_sim").joinpath("params/vehicle.toml").read_text()
    raw = tomllib.loads(text)
    flat: dict[str, float] = {}
    for table in raw.values():
        if isinstance(table, dict):
            flat.update({k: v for k, v in table.items() if isinstance(v, int | float)})
    return Footprint.for_vehicle(float(flat["lf_m"]), float(flat["lr_m"]),
                                 float(flat["vehicle_width_m"]))


def struck_cones(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, cones: np.ndarray,
                 fp: Footprint) -> np.ndarray:
    """Boolean mask over ``cones`` (M, 2) m: True where the footprint covered the cone at
    some sample of the CG track (x, y m; yaw rad)."""
    pts = np.asarray(cones, dtype=float).reshape(-1, 2)
    x, y, yaw = (np.asarray(a, dtype=float) for a in (x, y, yaw))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
    x, y, yaw = x[ok], y[ok], yaw[ok]
    if pts.size == 0 or x.size == 0:
        return np.zeros(len(pts), dtype=bool)
    dx = pts[:, 0:1] - x[None, :]
    dy = pts[:, 1:2] - y[None, :]
    c, s = np.cos(yaw)[None, :], np.sin(yaw)[None, :]
    lon = c * dx + s * dy  # along the body, m
    lat = -s * dx + c * dy  # across the body, m
    inside = (lon <= fp.front_m) & (lon >= -fp.rear_m) & (np.abs(lat) <= fp.width_m / 2)
    return inside.any(axis=1)
