"""Scenarios as data: ``plant_sim/scenarios/NAME.toml`` -> :class:`Scenario`.

A scenario TOML has top-level keys ``description``, ``duration_s``, ``speed_kmh`` (initial
speed), ``stab_enable_after_s`` (default 0) and tables ``[course]`` (geometry, see
:mod:`plant_sim.course`), ``[road]`` (friction field, see :mod:`plant_sim.road`) and
``[driver]`` (see :class:`plant_sim.driver.DriverSpec`).

``load_scenario(name, mu=..., speed_kmh=..., **params)``: ``mu`` overrides the base road
friction (patches keep their ratio to it), ``speed_kmh`` the initial speed (and a speed-holding
driver's target when it holds the initial speed); any other keyword overrides the key of that
name wherever it appears (top level, course, road or driver), e.g. ``amplitude_deg=200,
direction="right"`` for ``sine-with-dwell``, or ``steps=[(8.0, 0.5)]`` (a road friction
step to 0.5 at 8 s, :mod:`plant_sim.road`) for any scenario. Unknown keywords are an error.
"""

from __future__ import annotations

import copy
import functools
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from plant_sim.course import Course, Lane, course_from_spec
from plant_sim.driver import DriverSpec
from plant_sim.path import ReferencePath
from plant_sim.road import FrictionField, friction_from_spec

_TOP_KEYS = ("description", "duration_s", "speed_kmh", "stab_enable_after_s")
_ROAD_KEYS = ("patches", "split", "steps")   # [road] keys a scenario may leave out


@functools.cache
def _packaged_vehicle_width() -> float:
    """b (m) from the packaged vehicle.toml."""
    text = resources.files("plant_sim").joinpath("params/vehicle.toml").read_text()
    return float(tomllib.loads(text)["body"]["vehicle_width_m"])


@dataclass(slots=True)
class Scenario:
    """A ready-to-run scenario. Units: m, s, m/s; mu dimensionless.

    path: reference path (driver target and lateral-deviation reference). boundaries: course
    boundary polylines, each an (N, 2) array of (x, y) in m; cones: (N, 2) array, m; lanes:
    gated lane sections (DLC courses). course_end_s: arc length (m) where the course proper
    ends (KPIs look "through the course and 2 s after it").
    """

    name: str
    description: str
    path: ReferencePath
    friction: FrictionField
    driver: DriverSpec
    initial_speed_mps: float
    start_xy: tuple[float, float]
    start_yaw_rad: float
    duration_s: float
    stab_enable_after_s: float
    boundaries: list[np.ndarray] = field(default_factory=list)
    cones: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    lanes: list[Lane] = field(default_factory=list)
    course_end_s: float = 0.0
    spec: dict[str, Any] = field(default_factory=dict)

    @property
    def mu(self) -> float:
        """Base road friction, -."""
        return self.friction.mu

    @property
    def speed_kmh(self) -> float:
        """Initial speed, km/h."""
        return self.initial_speed_mps * 3.6

    @property
    def reference_path_xy(self) -> np.ndarray:
        """Reference path as an (N, 2) array, m."""
        return np.column_stack([self.path.x, self.path.y])


def list_scenarios() -> list[str]:
    """Names of the packaged scenarios (sorted)."""
    folder = resources.files("plant_sim").joinpath("scenarios")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _read_spec(name: str) -> dict[str, Any]:
    if name not in list_scenarios():
        raise KeyError(f"unknown scenario {name!r}; available: {', '.join(list_scenarios())}")
    text = resources.files("plant_sim").joinpath(f"scenarios/{name}.toml").read_text()
    return tomllib.loads(text)


def load_scenario(
    name: str, *, mu: float | None = None, speed_kmh: float | None = None,
    vehicle_width_m: float | None = None, **params: Any,
) -> Scenario:
    """Load a packaged scenario with overrides (see the module docstring).

    vehicle_width_m: b for the ISO 3888 cone layout, m (default: the packaged vehicle.toml).
    """
    if vehicle_width_m is None:
        vehicle_width_m = _packaged_vehicle_width()
    spec = copy.deepcopy(_read_spec(name))
    for tbl in ("course", "road", "driver"):
        spec.setdefault(tbl, {})
    for key, value in params.items():
        hit = False
        if key in spec and key not in ("course", "road", "driver"):
            spec[key] = value
            hit = True
        for tbl in ("course", "road", "driver"):
            if key in spec[tbl]:
                spec[tbl][key] = value
                hit = True
        if not hit:
            # allow driver/course parameters that the file leaves at their default
            if key in DriverSpec.__dataclass_fields__:
                spec["driver"][key] = value
            elif key in _ROAD_KEYS:
                spec["road"][key] = value
            else:
                raise KeyError(f"scenario {name!r} has no parameter {key!r}")
    if speed_kmh is not None:
        spec["speed_kmh"] = float(speed_kmh)
    unknown = set(spec) - set(_TOP_KEYS) - {"course", "road", "driver"}
    if unknown:
        raise KeyError(f"scenario {name!r}: unknown keys {sorted(unknown)}")
    friction = friction_from_spec(spec["road"])
    if mu is not None:
        friction = friction.scaled(float(mu))
    course: Course = course_from_spec(spec["course"], vehicle_width_m)
    driver = DriverSpec.from_dict(spec["driver"])
    v0 = float(spec.get("speed_kmh", 0.0)) / 3.6
    if v0 < 0:
        raise ValueError("initial speed must be >= 0")
    return Scenario(
        name=name,
        description=str(spec.get("description", "")),
        path=course.path,
        friction=friction,
        driver=driver,
        initial_speed_mps=v0,
        start_xy=course.start_xy,
        start_yaw_rad=0.0,
        duration_s=float(spec.get("duration_s", 10.0)),
        stab_enable_after_s=float(spec.get("stab_enable_after_s", 0.0)),
        boundaries=course.boundaries,
        cones=course.cones,
        lanes=course.lanes,
        course_end_s=course.course_end_s,
        spec=spec,
    )
