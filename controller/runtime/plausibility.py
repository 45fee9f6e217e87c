"""Frozen-signal detection: a sensor value that stops changing while the car moves.

A stuck sensor still sends well-formed frames (valid CRC, running alive counter), so E2E
protection cannot see it. Every real inertial or estimator signal carries noise well above
its CAN resolution (plant defaults: yaw rate σ 0.1 deg/s vs 0.005 deg/s per bit; ax/ay 0.03 vs
0.005 m/s²; vx/vy estimates 0.05 / 0.02 vs 0.005 / 0.002 m/s), so the same raw value on
``frozen_frames`` consecutive frames at speed is a fault. Wheel speeds are not checked: their
noise is below their 0.1 rad/s resolution, so equal consecutive values are normal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

CHECKED = {
    "MOTION_SENSORS": ("YAW_RATE", "AX", "AY"),
    "VEHICLE_EST": ("VX_EST", "VY_EST"),
}


@dataclass
class FrozenSignalMonitor:
    """Counts identical consecutive values per signal; a message is faulty while any of its
    checked signals has been identical for ``frozen_frames`` frames (default 10 = 100 ms)."""

    frozen_frames: int = 10
    min_speed_mps: float = 1.0
    _last: dict[str, float] = field(default_factory=dict)
    _repeats: dict[str, int] = field(default_factory=dict)
    detections: int = 0
    _faulty: dict[str, bool] = field(default_factory=dict)

    def update(self, message: str, values: dict[str, float], speed_mps: float) -> None:
        """Feed one accepted frame of ``message`` (physical values); speed in m/s."""
        signals = CHECKED.get(message)
        if signals is None:
            return
        faulty = False
        for name in signals:
            value = values.get(name)
            if value is None:
                continue
            if self._last.get(name) == value and abs(speed_mps) >= self.min_speed_mps:
                self._repeats[name] = self._repeats.get(name, 0) + 1
            else:
                self._repeats[name] = 0
            self._last[name] = value
            faulty = faulty or self._repeats[name] >= self.frozen_frames - 1
        if faulty and not self._faulty.get(message, False):
            self.detections += 1
        self._faulty[message] = faulty

    def faulty(self, message: str) -> bool:
        """True while ``message`` carries a frozen signal."""
        return self._faulty.get(message, False)

    def any_faulty(self) -> bool:
        """True while any checked message carries a frozen signal."""
        return any(self._faulty.values())
