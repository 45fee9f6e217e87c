"""Scenarios as data: a TOML manoeuvre file -> :class:`Scenario`.

A scenario is a packaged name (``plant_sim/scenarios/NAME.toml``) or a user's file: any
reference containing '/' or ending in ``.toml`` is a path. Both are held to one typed schema
(:mod:`plant_sim.scenario_schema`, docs/scenarios.md): top-level keys ``description``,
``duration_s``, ``speed_kmh`` (initial speed), ``stab_enable_after_s`` (default 0) and tables
``[course]`` (geometry, see :mod:`plant_sim.course`), ``[road]`` (friction field, see
:mod:`plant_sim.road`) and ``[driver]`` (see :class:`plant_sim.driver.DriverSpec`).

``load_scenario(ref, mu=..., speed_kmh=..., **params)``: ``mu`` overrides the base road
friction (patches keep their ratio to it), ``speed_kmh`` the initial speed (and a speed-holding
driver's target when it holds the initial speed); any other keyword overrides the key of that
name wherever it appears (top level, course, road or driver), e.g. ``amplitude_deg=200,
direction="right"`` for ``sine-with-dwell``, or ``steps=[(8.0, 0.5)]`` (a road friction
step to 0.5 at 8 s, :mod:`plant_sim.road`) for any scenario; a key the file leaves out goes
where the schema has it. Unknown keywords are an error.

Every problem is a :class:`ScenarioError` whose message is one line naming the source (the
file as given, or ``scenario NAME``), the key and the problem.
"""

from __future__ import annotations

import copy
import difflib
import functools
import json
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from plant_sim.course import Course, Lane, course_from_spec
from plant_sim.driver import DriverSpec
from plant_sim.path import ReferencePath
from plant_sim.road import FrictionField, friction_from_spec
from plant_sim.scenario_schema import Key, SpecError, check_spec, check_value, key_homes


class ScenarioError(ValueError):
    """A scenario that cannot be loaded; the message is one line."""


class ScenarioKeyError(ScenarioError, KeyError):
    """An unknown scenario name or parameter (also a KeyError, as a lookup that failed)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


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


def is_scenario_file(ref: str) -> bool:
    """True when ``ref`` names a file (contains '/' or ends in .toml), not a packaged name."""
    return "/" in ref or ref.endswith(".toml")


def scenario_label(ref: str) -> str:
    """A short name for ``ref``: the file stem of a file, else the packaged name."""
    return Path(ref).stem if is_scenario_file(ref) else ref


def scenario_source(ref: str) -> str:
    """How errors name ``ref``: the path as given, or ``scenario NAME``."""
    return ref if is_scenario_file(ref) else f"scenario {ref}"


def check_scenario_ref(ref: str) -> None:
    """Raise ScenarioKeyError unless ``ref`` is a packaged name or looks like a file path
    (the file itself is read by :func:`read_spec`)."""
    names = list_scenarios()
    if not is_scenario_file(ref) and ref not in names:
        close = difflib.get_close_matches(ref, names, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise ScenarioKeyError(f"unknown scenario {ref!r}; {hint}choose from "
                               f"{', '.join(names)}, or give a PATH.toml")


def read_spec(ref: str) -> dict[str, Any]:
    """The TOML of a packaged name or a file, as read (not yet checked)."""
    check_scenario_ref(ref)
    if not is_scenario_file(ref):
        text = resources.files("plant_sim").joinpath(f"scenarios/{ref}.toml").read_text()
        return tomllib.loads(text)
    path = Path(ref)
    if not path.exists():
        raise ScenarioError(f"{ref}: no such file")
    if not path.is_file():
        raise ScenarioError(f"{ref}: not a file")
    try:
        text = path.read_text(encoding="utf-8")
    except PermissionError:
        raise ScenarioError(f"{ref}: not readable") from None
    except UnicodeDecodeError:
        raise ScenarioError(f"{ref}: not UTF-8 text") from None
    except OSError as exc:
        raise ScenarioError(f"{ref}: cannot be read ({exc.strerror or exc})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{ref}: not valid TOML: {exc}") from None


def _param_value(key: Key, value: Any) -> Any:
    """A parameter given as text (a command line, a campaign file) is a number where the
    schema wants one, and JSON where it wants a list or a table (``steps=[[8, 0.3]]``)."""
    if not isinstance(value, str):
        return value
    try:
        if key.kind == "number":
            return float(value)
        if key.kind in ("steps", "tables", "table"):
            return json.loads(value)
    except ValueError:
        pass  # the schema check names the key and the value
    return value


def scenario_spec(ref: str, speed_kmh: float | None = None,
                  **params: Any) -> dict[str, Any]:
    """The checked spec of ``ref`` with the parameter overrides applied (every number a
    float); raises ScenarioError (ScenarioKeyError for an unknown name or parameter)."""
    src = scenario_source(ref)
    raw = read_spec(ref)
    try:
        check_spec(raw)
    except SpecError as exc:
        raise ScenarioError(f"{src}: {exc}") from None
    spec = copy.deepcopy(raw)
    homes = key_homes(spec)
    for name, value in params.items():
        if name not in homes:
            close = difflib.get_close_matches(name, list(homes), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ScenarioKeyError(f"{src}: no parameter {name!r}{hint}")
        for table, key in homes[name]:
            try:
                checked = check_value(key, _param_value(key, value), f"parameter {name}")
            except SpecError as exc:
                raise ScenarioError(f"{src}: {exc}") from None
            (spec.setdefault(table, {}) if table else spec)[name] = checked
    if speed_kmh is not None:
        spec["speed_kmh"] = float(speed_kmh)
    try:
        return check_spec(spec)
    except SpecError as exc:
        raise ScenarioError(f"{src}: {exc}") from None


def load_scenario(
    ref: str, *, mu: float | None = None, speed_kmh: float | None = None,
    vehicle_width_m: float | None = None, **params: Any,
) -> Scenario:
    """Load a packaged scenario or a scenario file with overrides (see the module docstring).

    vehicle_width_m: b for the ISO 3888 cone layout, m (default: the packaged vehicle.toml).
    """
    if vehicle_width_m is None:
        vehicle_width_m = _packaged_vehicle_width()
    spec = scenario_spec(ref, speed_kmh, **params)
    try:
        friction = friction_from_spec(spec["road"])
        if mu is not None:
            friction = friction.scaled(float(mu))
        course: Course = course_from_spec(spec["course"], vehicle_width_m)
        driver = DriverSpec.from_dict(spec["driver"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ScenarioError(f"{scenario_source(ref)}: {exc}") from None
    return Scenario(
        name=scenario_label(ref),
        description=str(spec.get("description", "")),
        path=course.path,
        friction=friction,
        driver=driver,
        initial_speed_mps=spec["speed_kmh"] / 3.6,
        start_xy=course.start_xy,
        start_yaw_rad=0.0,
        duration_s=spec["duration_s"],
        stab_enable_after_s=float(spec.get("stab_enable_after_s", 0.0)),
        boundaries=course.boundaries,
        cones=course.cones,
        lanes=course.lanes,
        course_end_s=course.course_end_s,
        spec=spec,
    )
