"""Deterministic replay: feed a recorded bus log to a fresh controller node offline.

Only the plant's frames are replayed (in recorded order); the torque frames the node produces
are compared byte for byte with the ones recorded in the log.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import can

from can_db.codec import Codec
from controller.core.params import load_vehicle_params
from controller.core.registry import make_controller
from controller.runtime.node import ControllerNode

PLANT_FRAMES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")


@dataclass
class ReplayResult:
    """Comparison of replayed and recorded torque frames."""

    recorded: int
    replayed: int
    identical: int
    first_mismatch: int | None

    @property
    def bit_identical(self) -> bool:
        """Every recorded torque frame was reproduced exactly, and no extra one."""
        return self.recorded == self.replayed == self.identical and self.recorded > 0


def replay_log(log_path: str | Path, controller_name: str,
               config: str | None = None) -> ReplayResult:
    """Replay ``log_path`` (.blf/.asc) through ``controller_name`` in lockstep mode."""
    codec = Codec()
    plant_ids = {codec.messages[n].frame_id for n in PLANT_FRAMES}
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    node = ControllerNode(make_controller(controller_name, config), load_vehicle_params(),
                          codec=codec)
    recorded: list[bytes] = []
    replayed: list[bytes] = []
    for msg in can.LogReader(str(log_path)):
        if msg.arbitration_id == torque_id:
            recorded.append(bytes(msg.data))
        elif msg.arbitration_id in plant_ids:
            frames = node.on_frame_lockstep(msg)
            if frames:
                replayed.extend(bytes(f.data) for f in frames if f.arbitration_id == torque_id)
    identical = sum(a == b for a, b in zip(recorded, replayed, strict=False))
    mismatch = next((i for i, (a, b) in enumerate(zip(recorded, replayed, strict=False))
                     if a != b), None)
    return ReplayResult(len(recorded), len(replayed), identical, mismatch)
