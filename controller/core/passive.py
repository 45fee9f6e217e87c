"""Passive baseline: ΔM = 0, the driver's torque split by the allocator (paper IV-B)."""

from __future__ import annotations

import math

import numpy as np

from controller.core.allocation import TorqueAllocator
from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.params import VehicleParams
from controller.core.pedal_map import total_torque_from_pedals


class PassiveController:
    """No stabilisation: T1..T4 from Tt (pedals) only; references and prediction unset."""

    def __init__(self, params: VehicleParams, allocator: TorqueAllocator, ts: float,
                 name: str = "passive") -> None:
        self.name = name
        self.params = params
        self.allocator = allocator
        self.ts = float(ts)
        self.out = ControllerOutputs()
        self._ws = np.zeros(4)

    def reset(self) -> None:
        """Nothing learned; clears the outputs and the motors' previous torques."""
        self.allocator.reset()
        o = self.out
        o.torques[:] = 0.0
        o.total_torque = o.delta_m = 0.0
        o.qp_status = int(QpStatus.NOT_RUN)
        o.qp_iterations = 0
        o.fallback = False

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        """Tt = pedal map; ΔM = 0; allocation within the motor limits."""
        o, ws = self.out, self._ws
        try:
            ws[:] = inputs.wheel_speeds
        except (TypeError, ValueError):
            ws[:] = 0.0
        tt = total_torque_from_pedals(inputs.accel_pedal, inputs.brake_pedal,
                                      self.params.peak_torque_nm)
        ax, ay = float(inputs.ax), float(inputs.ay)
        o.torques[:] = self.allocator.allocate(tt, 0.0, ax if math.isfinite(ax) else 0.0,
                                               ay if math.isfinite(ay) else 0.0, ws)
        o.total_torque = tt
        o.delta_m = self.allocator.dm_applied
        o.qp_status = int(QpStatus.NOT_RUN)
        o.qp_iterations = 0
        o.fallback = False
        return o

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        """Same as step (nothing is held)."""
        return self.step(inputs)

    def get_state(self) -> dict[str, np.ndarray | float]:
        """No learned state; the motors' previous torques (N·m, the rate limit's memory)."""
        return {"alloc.prev": self.allocator.prev.copy()}

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state() (a checkpoint without the torques starts them at zero)."""
        self.allocator.prev[:] = np.asarray(d.get("alloc.prev", np.zeros(4)), dtype=float)
