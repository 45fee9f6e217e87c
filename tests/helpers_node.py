"""Lockstep answers of a Python ``ControllerNode``, decoded (shared by the node tests)."""

from __future__ import annotations

import can
import numpy as np

from can_db.codec import Codec, Decoded
from controller.runtime.node import ControllerNode

CODEC = Codec()


def answer(node: ControllerNode, frames: list[can.Message]) -> dict[str, Decoded]:
    """Feed one lockstep burst; the node's answer, decoded, by frame name."""
    out = None
    for f in frames:
        out = node.on_frame_lockstep(f) or out
    assert out is not None
    decoded = [CODEC.decode_message(m) for m in out]
    assert all(isinstance(d, Decoded) for d in decoded)
    return {d.name: d for d in decoded}  # type: ignore[union-attr]


def torques(frames: dict[str, Decoded]) -> np.ndarray:
    """The four wheel torque commands FL, FR, RL, RR of an answer, N·m."""
    v = frames["WHEEL_TORQUE_CMD"].values
    return np.array([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])
