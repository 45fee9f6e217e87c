"""Deterministic replay: feed a recorded bus log to a fresh controller node offline.

Only the plant's frames are replayed (in recorded order); the torque frames the node produces
are compared byte for byte with the ones recorded in the log.

A log of a SecOC run (it holds SYNC_AUTH frames) is replayed with SecOC: the node verifies the
recorded SYNC authenticators as it did live, the recorded torque frames count only when their
authenticator verifies (a rogue node's frames in the log are left out), and the replayed
torque authenticators (MACs) must match the recorded ones as well.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import can

from can_db.codec import Codec
from can_db.secoc import ControllerSecOc, SecOcObserver
from can_db.secoc_keys import SecOcKeys
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
    secured: bool = False  # SecOC log: authenticators compared too

    @property
    def bit_identical(self) -> bool:
        """Every recorded torque frame was reproduced exactly, and no extra one."""
        return self.recorded == self.replayed == self.identical and self.recorded > 0


def log_is_secured(log_path: str | Path) -> bool:
    """True when the log holds SYNC authenticators (a SecOC run)."""
    auth_id = Codec().messages["SYNC_AUTH"].frame_id
    return any(msg.arbitration_id == auth_id for msg in can.LogReader(str(log_path)))


def replay_log(log_path: str | Path, controller_name: str,
               config: str | None = None, keys: SecOcKeys | None = None) -> ReplayResult:
    """Replay ``log_path`` (.blf/.asc) through ``controller_name`` in lockstep mode; with
    ``keys`` (needed for a SecOC log) the node runs SecOC and MACs are compared too."""
    codec = Codec()
    names = PLANT_FRAMES + (("SYNC_AUTH",) if keys is not None else ())
    plant_ids = {codec.messages[n].frame_id for n in names}
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    torque_auth_id = codec.messages["WHEEL_TORQUE_AUTH"].frame_id
    secoc = ControllerSecOc(codec, keys) if keys is not None else None
    observer = SecOcObserver(codec, keys) if keys is not None else None
    node = ControllerNode(make_controller(controller_name, config), load_vehicle_params(),
                          codec=codec, secoc=secoc)
    recorded: list[bytes] = []
    replayed: list[bytes] = []
    last_auth: bytes = b""
    for msg in can.LogReader(str(log_path)):
        if observer is not None:
            _, released = observer.observe(msg)
            if msg.arbitration_id == torque_auth_id:
                last_auth = bytes(msg.data)
            if released is not None and released.arbitration_id == torque_id:
                recorded.append(bytes(released.data) + last_auth)
        elif msg.arbitration_id == torque_id:
            recorded.append(bytes(msg.data))
        if msg.arbitration_id in plant_ids:
            frames = node.on_frame_lockstep(msg)
            if frames:
                replayed.extend(_torque_records(frames, torque_id, torque_auth_id,
                                                secured=keys is not None))
    identical = sum(a == b for a, b in zip(recorded, replayed, strict=False))
    mismatch = next((i for i, (a, b) in enumerate(zip(recorded, replayed, strict=False))
                     if a != b), None)
    return ReplayResult(len(recorded), len(replayed), identical, mismatch, keys is not None)


def _torque_records(frames: list[can.Message], torque_id: int, auth_id: int, *,
                    secured: bool) -> list[bytes]:
    """Torque payloads (followed by their authenticator's payload when ``secured``)."""
    out: list[bytes] = []
    for i, frame in enumerate(frames):
        if frame.arbitration_id != torque_id:
            continue
        data = bytes(frame.data)
        if secured:
            nxt = frames[i + 1] if i + 1 < len(frames) else None
            data += bytes(nxt.data) if nxt is not None and nxt.arbitration_id == auth_id \
                else b""
        out.append(data)
    return out
