"""Cone strikes from the body footprint (harness/analysis/footprint.py)."""

from __future__ import annotations

import numpy as np

from harness.analysis.footprint import Footprint, packaged_footprint, struck_cones

FP = Footprint(front_m=2.0, rear_m=2.0, width_m=1.9)


def test_a_cone_beside_the_track_within_half_a_body_width_is_struck() -> None:
    x = np.linspace(0.0, 50.0, 501)  # straight along +X at y = 0
    y, yaw = np.zeros_like(x), np.zeros_like(x)
    cones = np.array([[20.0, 0.90], [20.0, -0.90], [30.0, 1.00], [30.0, -1.00]])
    assert struck_cones(x, y, yaw, cones, FP).tolist() == [True, True, False, False]


def test_yaw_turns_the_footprint() -> None:
    """Across the track (yaw 90°) the body's length, not its width, reaches sideways."""
    y = np.linspace(-10.0, 10.0, 201)
    x, yaw = np.zeros_like(y), np.full_like(y, np.pi / 2)
    cones = np.array([[0.9, 0.0], [1.5, 0.0]])
    assert struck_cones(x, y, yaw, cones, FP).tolist() == [True, False]


def test_packaged_footprint_uses_the_vehicle_width_and_axles() -> None:
    fp = packaged_footprint()
    assert fp.width_m == 1.90
    assert 4.0 < fp.front_m + fp.rear_m < 5.0
