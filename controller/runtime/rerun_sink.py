"""Optional live rerun recording from the controller process (``--rerun FILE``).

Writes to a file sink only (no network, no viewer). Logged after the cycle's frames are sent,
so it never delays the answer.
"""

from __future__ import annotations

from typing import Any

from controller.runtime.node import ControllerNode


class RerunSink:
    """Per-cycle controller signals on the ``cycle`` and ``sim_time`` timelines."""

    def __init__(self, path: str, controller_name: str) -> None:
        # rerun-sdk is optional (the harness extra): a deployed controller without it starts
        # as fast as before and refuses --rerun at its argument check
        import rerun as rr

        self._rr: Any = rr
        self.rec = rr.RecordingStream(application_id="rhonn-tv",
                                      recording_id=f"controller-{controller_name}")
        self.rec.save(path)

    def log(self, node: ControllerNode) -> None:
        rr, rec, out = self._rr, node.record, node.record.outputs
        self.rec.set_time("cycle", sequence=max(rec.cycle, 0))
        self.rec.set_time("sim_time", duration=rec.sim_time_s)
        self.rec.log("controller/delta_m", rr.Scalars(float(out.delta_m)))
        self.rec.log("controller/yaw_rate/ref", rr.Scalars(float(out.yaw_rate_ref)))
        self.rec.log("controller/yaw_rate/actual", rr.Scalars(float(node.inputs.yaw_rate)))
        self.rec.log("controller/beta/ref", rr.Scalars(float(out.beta_ref)))
        self.rec.log("controller/torques", rr.Scalars([float(t) for t in node.torques]))
        self.rec.log("controller/mode", rr.Scalars(float(rec.mode)))
        self.rec.log("controller/step_us", rr.Scalars(rec.step_ns / 1000.0))

    def close(self) -> None:
        self.rec.flush()
