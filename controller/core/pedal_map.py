"""Pedal map: driver pedals → total wheel-torque demand Tt (shared contract with the plant).

    Tt = (accel − brake) · 4 · T_peak        N·m, pedals in 0..1 (clipped; NaN → 0)

Linear on purpose: the plant applies the same map, so Tt is known exactly on both sides.
"""

from __future__ import annotations

import math


def _pedal(v: float) -> float:
    """Clip a pedal position to 0..1; non-finite reads as released (0)."""
    if not math.isfinite(v):
        return 0.0
    return 0.0 if v < 0.0 else (1.0 if v > 1.0 else v)


def total_torque_from_pedals(accel_pedal: float, brake_pedal: float,
                             peak_torque_nm: float) -> float:
    """Tt, N·m, for pedal positions 0..1 and the per-motor peak torque, N·m."""
    return (_pedal(float(accel_pedal)) - _pedal(float(brake_pedal))) * 4.0 * peak_torque_nm
