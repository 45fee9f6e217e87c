"""Course geometry of a run's scenario, for KPIs, plots and the rerun recording."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plant_sim.scenario import Scenario, load_scenario


@dataclass(frozen=True)
class CourseGeometry:
    """Boundaries (polylines, m), cones (m), the reference path (m), the arc length where
    the course proper ends (m), the scenario duration (s) and the gated lane sections
    (plant_sim.course.Lane: x0, x1, y_right, y_left in m; empty without a course)."""

    boundaries: list[np.ndarray]
    cones: np.ndarray
    ref_path: np.ndarray
    course_end_arc_m: float
    duration_s: float
    lanes: list[Any] = field(default_factory=list)


def scenario_for(name: str, mu: float | None, speed_kmh: float | None,
                 params: dict[str, object] | None = None) -> Scenario:
    """Load the scenario exactly as the plant process does (same overrides)."""
    parsed: dict[str, object] = {}
    for key, value in (params or {}).items():
        try:
            parsed[key] = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            parsed[key] = value
    return load_scenario(name, mu=mu, speed_kmh=speed_kmh, **parsed)


def course_geometry(scenario: Scenario, duration_s: float | None = None) -> CourseGeometry:
    """Geometry of ``scenario``; ``duration_s`` overrides the scenario's duration."""
    return CourseGeometry(boundaries=list(scenario.boundaries), cones=scenario.cones,
                          ref_path=scenario.reference_path_xy,
                          course_end_arc_m=float(scenario.course_end_s),
                          duration_s=float(duration_s if duration_s is not None
                                           else scenario.duration_s),
                          lanes=list(scenario.lanes))
