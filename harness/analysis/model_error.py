"""One-step model error of a controller fed a recorded bus log offline (replay-style).

The plant's frames of a ``.blf``/``.asc`` log go through a fresh ``ControllerNode`` in
lockstep exactly as in ``harness.run.replay`` (so the torque frames can be compared byte for
byte with the recorded ones); optionally the controller first restores a checkpoint. At
each MPC update the node's measured state x_k = [vx m/s, vy m/s, r rad/s] is compared with
the prediction ``ControllerOutputs.model_prediction`` made one MPC step earlier.

This is how the checkpoint test measures "warm vs cold": the same recorded inputs through a
restored and a cold controller, so the comparison is not confounded by different
trajectories; the restored replay reproduces the live run's torque frames bit for bit, which
proves it is the controller that ran.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from can_db.codec import Codec
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.checkpoint import RestoreResult, config_hash, load_checkpoint
from controller.runtime.node import ControllerNode

PLANT_FRAMES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")


@dataclass
class ModelErrorResult:
    """Per-MPC-step one-step errors and the torque frames produced."""

    sim_time_s: np.ndarray                    # (n,) s, time of the measurement
    errors: np.ndarray                        # (n, 3) x_meas − prediction [m/s, m/s, rad/s]
    torque_frames: list[bytes] = field(default_factory=list)
    restore: RestoreResult | None = None

    def rms(self, until_s: float | None = None) -> np.ndarray:
        """RMS error per state (3,) over measurements with sim time < until_s (all: None)."""
        sel = self.errors if until_s is None else self.errors[self.sim_time_s < until_s]
        if len(sel) == 0:
            return np.full(3, np.nan)
        return np.sqrt(np.mean(sel * sel, axis=0))


def one_step_errors(frames: Iterable[can.Message] | str | Path, controller_name: str,
                    checkpoint: str | Path | None = None, config: str | None = None
                    ) -> ModelErrorResult:
    """Replay ``frames`` (or a log file) through ``controller_name``; see the module doc."""
    if isinstance(frames, str | Path):
        frames = can.LogReader(str(frames))
    codec = Codec()
    plant_ids = {codec.messages[n].frame_id for n in PLANT_FRAMES}
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    controller = make_controller(controller_name, config)
    restore = None
    if checkpoint is not None:
        restore = load_checkpoint(checkpoint, controller,
                                  cfg_hash=config_hash(controller_name, config))
    node = ControllerNode(controller, load_vehicle_params(), codec=codec)
    times: list[float] = []
    errs: list[np.ndarray] = []
    out_frames: list[bytes] = []
    pending = np.full(3, np.nan)
    for msg in frames:
        if msg.arbitration_id not in plant_ids:
            continue
        answer = node.on_frame_lockstep(msg)
        if not answer:
            continue
        out_frames.extend(bytes(f.data) for f in answer if f.arbitration_id == torque_id)
        rec = node.record
        if not rec.mpc_update:
            continue
        inp = node.inputs
        x = np.array([inp.vx, inp.vy, inp.yaw_rate])
        if inp.sensors_valid and np.all(np.isfinite(pending)):
            times.append(rec.sim_time_s)
            errs.append(x - pending)
        pending = np.array(rec.outputs.model_prediction, dtype=float)
    return ModelErrorResult(np.array(times), np.array(errs).reshape(-1, 3), out_frames,
                            restore)
