"""Test-course geometry: reference path, lane sections, boundaries and cones (all in m).

Courses start with the vehicle heading +x; the course proper begins at x = 0.

ISO 3888-1 (double lane change), b = vehicle width: sections 15 / 30 / 25 / 25 / 15 m, lane
widths 1.1b+0.25 / - / 1.2b+0.25 / - / 1.3b+0.25, lateral offset 3.5 m. Interpretation used
here (documented choice): the 3.5 m offset is between the RIGHT-hand boundaries of lanes 1 and
3 (lane centres 3.5 + 0.05 b apart), and lane 5 shares its right-hand boundary with lane 1.

ISO 3888-2 (obstacle avoidance): sections 12 / 13.5 / 11 / 12.5 / 12 m, widths
1.1b+0.25 / - / b+1 / - / max(1.3b+0.25, 3) m; lane 3's right boundary is 1 m left of lane 1's
left boundary (edge to edge); lane 5 shares its right-hand boundary with lane 1.

The reference path joins the lane centres with quintic (zero curvature at the ends)
transitions spanning the free sections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plant_sim.path import ReferencePath, curvature_path, plateau_path


@dataclass(frozen=True, slots=True)
class Lane:
    """A gated lane section: x0 <= x <= x1 with y_right <= y <= y_left (m)."""

    x0: float
    x1: float
    y_right: float
    y_left: float


@dataclass(slots=True)
class Course:
    """Geometry of a scenario. boundaries: polylines (N, 2) in m for plots; cones (N, 2) m;
    lanes: gated sections (DLC only); course_end_s: arc length where the course proper ends."""

    path: ReferencePath
    boundaries: list[np.ndarray] = field(default_factory=list)
    cones: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    lanes: list[Lane] = field(default_factory=list)
    course_end_s: float = 0.0
    start_xy: tuple[float, float] = (0.0, 0.0)


def _lane_course(
    lengths: list[float], widths: list[float], y_rights: list[float], lead_in: float,
    run_out: float,
) -> Course:
    """Generic 5-section lane-change course (sections 1, 3, 5 gated)."""
    xs = np.concatenate([[0.0], np.cumsum(lengths)])
    lanes = []
    for k, sec in enumerate((0, 2, 4)):
        lanes.append(Lane(float(xs[sec]), float(xs[sec + 1]), y_rights[k],
                          y_rights[k] + widths[k]))
    centres = [0.5 * (ln.y_left + ln.y_right) for ln in lanes]
    knots = [-lead_in, xs[1], xs[2], xs[3], xs[4], xs[5] + run_out]
    path = plateau_path(knots, centres, x_end=float(xs[5] + run_out), x_start=-lead_in)
    boundaries: list[np.ndarray] = []
    cones: list[tuple[float, float]] = []
    for ln in lanes:
        for yb in (ln.y_right, ln.y_left):
            boundaries.append(np.array([[ln.x0, yb], [ln.x1, yb]]))
            xm = 0.5 * (ln.x0 + ln.x1)
            cones.extend([(ln.x0, yb), (xm, yb), (ln.x1, yb)])
    s_end, _ = path.project(float(xs[5]), centres[-1])
    path.reset()
    return Course(path, boundaries, np.array(cones), lanes, s_end, (-lead_in, centres[0]))


def iso3888_1(vehicle_width_m: float, lead_in_m: float = 20.0, run_out_m: float = 60.0) -> Course:
    """ISO 3888-1 double lane change for a vehicle of width b (m)."""
    b = vehicle_width_m
    wa, wb, wc = 1.1 * b + 0.25, 1.2 * b + 0.25, 1.3 * b + 0.25
    yr1 = -0.5 * wa
    return _lane_course([15.0, 30.0, 25.0, 25.0, 15.0], [wa, wb, wc],
                        [yr1, yr1 + 3.5, yr1], lead_in_m, run_out_m)


def iso3888_2(vehicle_width_m: float, lead_in_m: float = 20.0, run_out_m: float = 60.0) -> Course:
    """ISO 3888-2 obstacle avoidance (severe lane change) for a vehicle of width b (m)."""
    b = vehicle_width_m
    wa, wb, wc = 1.1 * b + 0.25, b + 1.0, max(1.3 * b + 0.25, 3.0)
    yr1 = -0.5 * wa
    return _lane_course([12.0, 13.5, 11.0, 12.5, 12.0], [wa, wb, wc],
                        [yr1, 0.5 * wa + 1.0, yr1], lead_in_m, run_out_m)


def straight(length_m: float, lead_in_m: float = 0.0, half_width_m: float = 1.75) -> Course:
    """Straight road along +x from x = -lead_in (m); boundaries at +-half_width (m)."""
    path = curvature_path([(length_m + lead_in_m, 0.0, 0.0)], x0=-lead_in_m)
    return Course(path, [path.offset_polyline(half_width_m), path.offset_polyline(-half_width_m)],
                  course_end_s=path.length_m, start_xy=(-lead_in_m, 0.0))


def curve(
    radius_m: float, arc_deg: float, straight_in_m: float, clothoid_m: float,
    straight_out_m: float, direction: str = "left", half_width_m: float = 1.75,
) -> Course:
    """Straight, clothoid entry, constant-radius arc, clothoid exit, straight (m, deg)."""
    sign = _sign(direction)
    k = sign / radius_m
    # the arc angle includes the two clothoids' turning (each turns L/(2R))
    arc_len = max(0.0, math.radians(arc_deg) * radius_m - clothoid_m)
    pieces = [(straight_in_m, 0.0, 0.0), (clothoid_m, 0.0, k), (arc_len, k, k),
              (clothoid_m, k, 0.0), (straight_out_m, 0.0, 0.0)]
    path = curvature_path(pieces)
    return Course(path, [path.offset_polyline(half_width_m), path.offset_polyline(-half_width_m)],
                  course_end_s=path.length_m - straight_out_m)


def circle(
    radius_m: float, laps: float, lead_in_m: float = 30.0, direction: str = "left",
    half_width_m: float = 1.75,
) -> Course:
    """Straight lead-in (m), short clothoid, then ``laps`` laps of a circle of radius R (m)."""
    k = _sign(direction) / radius_m
    clothoid = min(10.0, 0.25 * radius_m)
    pieces = [(lead_in_m, 0.0, 0.0), (clothoid, 0.0, k),
              (2.0 * math.pi * radius_m * laps, k, k)]
    path = curvature_path(pieces, x0=-lead_in_m)
    return Course(path, [path.offset_polyline(half_width_m), path.offset_polyline(-half_width_m)],
                  course_end_s=path.length_m, start_xy=(-lead_in_m, 0.0))


def _sign(direction: str) -> float:
    if direction not in ("left", "right"):
        raise ValueError(f"direction must be 'left' or 'right', got {direction!r}")
    return 1.0 if direction == "left" else -1.0


def course_from_spec(spec: dict[str, Any], vehicle_width_m: float) -> Course:
    """Build a course from a scenario's ``[course]`` table (key ``type`` selects the builder)."""
    kw = {k: v for k, v in spec.items() if k != "type"}
    kind = spec.get("type")
    if kind == "iso3888_1":
        return iso3888_1(vehicle_width_m, **kw)
    if kind == "iso3888_2":
        return iso3888_2(vehicle_width_m, **kw)
    if kind == "straight":
        return straight(**kw)
    if kind == "curve":
        return curve(**kw)
    if kind == "circle":
        return circle(**kw)
    raise ValueError(f"unknown course type {kind!r}")
