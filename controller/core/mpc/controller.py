"""Generic MPC controller: PredictionModel + ReferenceGenerator + QP + allocation.

One ``step()`` per MPC period Ts (s):
  1. sanitise inputs (non-finite → invalid; nothing raises);
  2. Tt from the pedals (pedal_map), δw = swa / steering_ratio (road-wheel angle, rad);
  3. adaptive models learn from the prediction they made last step (frozen when invalid);
  4. the grip estimate μ̂ (controller/core/grip.py, when configured) and the references
     (ωrd rad/s, Vyd m/s, βd rad) from the ReferenceGenerator;
  5. QP (nmpc.LinearizedMpc) for ΔM, N·m — only when active: sensors valid, stab_enable,
     and Vx ≥ v_min; otherwise ΔM = 0 and the status is NOT_RUN. An adaptive model with
     ``confidence()`` (the RHONN) scales the ΔM box by it (0 while still learning);
     ctx.delta_m_prev carries the ΔM applied over the last period (actuator dead time);
     with a HandlingEnvelope the QP also keeps ωr and the rear slip inside the bounds
     that μ̂ gives (controller/core/mpc/envelope.py);
  6. allocation of (Tt, ΔM) to the four motors (allocation.TorqueAllocator);
  7. one-step model prediction with the applied inputs (for the fidelity evaluation).

``allocate_only()`` between MPC updates re-allocates the held ΔM with the fresh pedal Tt
(status fields keep describing the held ΔM; qp_iterations = 0).
While inputs are invalid the reference outputs hold their last valid values.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controller.core.allocation import TorqueAllocator
from controller.core.grip import GripEstimator
from controller.core.interfaces import (
    ControllerInputs,
    ControllerOutputs,
    PredictionContext,
    PredictionModel,
    QpStatus,
    ReferenceGenerator,
)
from controller.core.mpc.envelope import HandlingEnvelope
from controller.core.mpc.qp import LinearizedMpc, QpConfig
from controller.core.params import VehicleParams
from controller.core.pedal_map import total_torque_from_pedals


def inputs_finite(inputs: ControllerInputs) -> bool:
    """True when every numeric input is finite (one reduction, no exceptions)."""
    s = (inputs.swa_rad + inputs.accel_pedal + inputs.brake_pedal + inputs.yaw_rate
         + inputs.ax + inputs.ay + inputs.vx + inputs.vy)
    ws = inputs.wheel_speeds
    if type(ws) is np.ndarray and ws.ndim == 1 and ws.dtype == np.float64:
        return math.isfinite(s + sum(ws.tolist()))   # the usual case, ≈ 1.5 µs less than np.sum
    try:
        s += float(np.sum(ws))
    except (TypeError, ValueError):
        return False
    return math.isfinite(s)


class MpcController:
    """Controller protocol implementation shared by nmpc-rhonn, nmpc-mf and lmpc."""

    def __init__(self, name: str, params: VehicleParams, model: PredictionModel,
                 references: ReferenceGenerator, qp_cfg: QpConfig, allocator: TorqueAllocator,
                 ts: float, v_min: float = 3.0, grip: GripEstimator | None = None,
                 envelope: HandlingEnvelope | None = None) -> None:
        self.name = name
        self.grip = grip
        self.envelope = envelope
        self.params = params
        self.model = model
        self.references = references
        self.allocator = allocator
        self.ts = float(ts)
        self.v_min = float(v_min)
        self.qp = LinearizedMpc(model, qp_cfg, ts, envelope)
        self.dtype = self.qp.dtype   # working precision (float64 | float32)
        self.backend = "numpy"
        self.adaptive = all(hasattr(model, a) for a in ("observe", "record", "forget_record"))
        self._confidence = getattr(model, "confidence", None)
        self.confidence = 1.0   # last model confidence (scales the ΔM box), -
        self.out = ControllerOutputs()
        self._ctx = PredictionContext(ts=self.ts)
        self._x = np.zeros(int(model.nx))
        self._pred = np.zeros(int(model.nx))
        self._ws = np.zeros(4)
        self.dm_held = 0.0      # N·m, last MPC command (before allocation)
        self.dm_prev = 0.0      # N·m, last applied ΔM (rate-limit reference)
        self.steps = 0
        self.invalid_steps = 0

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        """Cold start: model weights/filters, references, warm starts, outputs."""
        for part in (self.model, self.references, self.grip):
            r = getattr(part, "reset", None)
            if r is not None:
                r()
        self.qp.reset()
        self.allocator.reset()
        o = self.out
        o.torques[:] = 0.0
        o.total_torque = o.delta_m = 0.0
        o.yaw_rate_ref = o.vy_ref = o.beta_ref = 0.0
        o.qp_status = int(QpStatus.NOT_RUN)
        o.qp_iterations = 0
        o.fallback = False
        o.model_prediction[:] = np.nan
        self.dm_held = self.dm_prev = 0.0
        self.steps = self.invalid_steps = 0

    def _wheel_speeds(self, inputs: ControllerInputs, finite: bool) -> np.ndarray:
        """Copy of the wheel speeds rad/s (zeros if the array is unusable)."""
        ws = self._ws
        if finite:
            ws[:] = inputs.wheel_speeds
        else:
            try:
                ws[:] = inputs.wheel_speeds
            except (TypeError, ValueError):
                ws[:] = 0.0
        return ws

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        """One MPC period; see the module docstring. Never raises on bad numbers."""
        self.steps += 1
        o, p, ctx = self.out, self.params, self._ctx
        finite = inputs_finite(inputs)
        valid = bool(inputs.sensors_valid) and finite
        if not valid:
            self.invalid_steps += 1
        ws = self._wheel_speeds(inputs, finite)
        tt = total_torque_from_pedals(inputs.accel_pedal, inputs.brake_pedal, p.peak_torque_nm)
        swa = float(inputs.swa_rad)
        dw = swa / p.steering_ratio if math.isfinite(swa) else 0.0
        ctx.delta_w = dw
        ctx.total_torque = tt
        ctx.wheel_speeds = ws
        ctx.delta_m_prev = self.dm_prev   # ΔM applied over the last period, N·m
        x = self._x
        if valid:
            self.model.initial_state(inputs, x)
            if not math.isfinite(sum(x.tolist())):
                valid = False
        if self.adaptive:
            self.model.observe(x, valid)  # frozen (and counted) when invalid
        vx = float(inputs.vx)
        if valid and self.grip is not None:
            self.grip.update(vx, float(inputs.vy), float(inputs.yaw_rate), dw,
                             float(inputs.ax), float(inputs.ay))
        if valid:
            r_d, vy_d, b_d = self.references.compute(
                vx, float(inputs.vy), float(inputs.yaw_rate), dw, tt, float(inputs.ay))
            if math.isfinite(r_d + vy_d + b_d):
                o.yaw_rate_ref, o.vy_ref, o.beta_ref = r_d, vy_d, b_d
        active = valid and bool(inputs.stab_enable) and vx >= self.v_min
        if active:
            cap = self.allocator.delta_m_capacity(ws)
            cmax = self.qp.cfg.delta_m_max_nm
            if cmax > 0.0:
                cap = min(cap, cmax)
            if self._confidence is not None:
                # Adaptive model: the box shrinks with the model confidence (0 while the
                # RHONN is still learning from a cold start; see rhonn.RhonnModel).
                self.confidence = self._confidence()
                cap *= self.confidence
            env = None
            if self.envelope is not None and self.grip is not None \
                    and vx >= self.envelope.cfg.v_min_mps:
                mu = self.grip.mu
                env = (self.envelope.yaw_rate_max(mu, vx), self.envelope.rear_slip_max(mu),
                       float(inputs.ay))
            dm, status, iters, fb = self.qp.solve(
                x, ctx, o.yaw_rate_ref, o.beta_ref, -cap, cap, self.dm_prev, env)
        else:
            dm, status, iters, fb = 0.0, QpStatus.NOT_RUN, 0, False
            self.qp.sol[:] = 0.0
        self.dm_held = dm
        self._allocate(inputs, tt, dm, ws, limits_current=active)
        o.qp_status = int(status)
        o.qp_iterations = int(iters)
        o.fallback = bool(fb)
        # One-step prediction with what is actually applied.
        ctx.total_torque = self.allocator.tt_applied
        if valid:
            if self.adaptive:
                self.model.record(x, o.delta_m, ctx, o.model_prediction)
            else:
                self.model.predict(x, o.delta_m, ctx, self._pred)
                o.model_prediction[:] = self._pred[:3]
        else:
            if self.adaptive:
                self.model.forget_record()
            o.model_prediction[:] = np.nan
        return o

    def _allocate(self, inputs: ControllerInputs, tt: float, dm: float,
                  ws: np.ndarray, limits_current: bool = False) -> None:
        o, al = self.out, self.allocator
        o.torques[:] = al.allocate(tt, dm, float(inputs.ax), float(inputs.ay), ws,
                                   limits_current)
        o.total_torque = tt
        o.delta_m = al.dm_applied
        self.dm_prev = al.dm_applied

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        """Re-allocate the held ΔM with the fresh pedal torque (no learning, no QP)."""
        p = self.params
        finite = inputs_finite(inputs)
        ws = self._wheel_speeds(inputs, finite)
        tt = total_torque_from_pedals(inputs.accel_pedal, inputs.brake_pedal, p.peak_torque_nm)
        ok = finite and bool(inputs.sensors_valid) and bool(inputs.stab_enable)
        ok = ok and float(inputs.vx) >= self.v_min
        self._allocate(inputs, tt, self.dm_held if ok else 0.0, ws)
        self.out.qp_iterations = 0
        return self.out

    # ------------------------------------------------------------------ checkpoint
    def get_state(self) -> dict[str, np.ndarray | float]:
        """Learned/warm state of every part (flat dict of arrays and floats)."""
        d: dict[str, Any] = {}
        for part in (self.model, self.references, self.grip):
            g = getattr(part, "get_state", None)
            if g is not None:
                d.update(g())
        d.update(self.qp.get_state())
        d["alloc.prev"] = self.allocator.prev.copy()
        d["ctrl.dm_held"] = float(self.dm_held)
        d["ctrl.dm_prev"] = float(self.dm_prev)
        d["ctrl.refs"] = np.array([self.out.yaw_rate_ref, self.out.vy_ref, self.out.beta_ref])
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        for part in (self.model, self.references, self.grip):
            s = getattr(part, "set_state", None)
            if s is not None:
                s(d)
        self.qp.set_state(d)
        self.allocator.prev[:] = np.asarray(d.get("alloc.prev", np.zeros(4)), dtype=float)
        self.dm_held = float(d["ctrl.dm_held"])
        self.dm_prev = float(d["ctrl.dm_prev"])
        refs = np.asarray(d["ctrl.refs"], dtype=float)
        self.out.yaw_rate_ref, self.out.vy_ref, self.out.beta_ref = (float(v) for v in refs)
