"""The controller's bus node logic, free of sockets and clocks (the process wraps it).

Lockstep (sync-driven): frames of a plant burst are buffered until the SYNC frame arrives and
are then validated at the SYNC's simulated time, so the same bus input gives bit-identical
torque frames (this is what ``rhonn-harness replay`` checks). Free-running: frames are
validated on arrival at the caller's monotonic time and ``tick`` answers on the node's own
schedule with the latest SYNC cycle echoed.

Every communication cycle (10 ms) the node answers with WHEEL_TORQUE_CMD, CTRL_STATUS and
CTRL_REFS. The full controller step (learning, references, QP) runs every ``ts`` of the
controller (50 ms by default); in between, the held ΔM is re-allocated with the fresh pedal
torque. Degraded modes:

* stability function disabled by the driver (STAB_ENABLE = 0) → STANDBY: ΔM = 0;
* any sensor frame (MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST) invalid or timed out →
  DEGRADED_SENSORS: ΔM = 0, the driver's torque passed through, learning frozen;
* driver frame invalid or timed out → DRIVER_LOST_RAMPDOWN: every wheel torque ramps to
  zero at ``rampdown_nm_per_s``;
* the controller raised → FAULT: the driver's torque split evenly, counted. FAULT is
  latched: the core is not stepped again until the controller process restarts (its state
  may be half-updated by the step that raised); a lost driver frame still ramps down
  (the driver's torque is unknown then) and FAULT returns with the driver frame.

Bounded rx queues (docs/safety/queues.md): the lockstep burst buffer keeps at most
:func:`burst_bound` frames per monitored ID and drops the oldest (counted in ``rx_drops``);
malformed frames and frames of IDs the node does not monitor are counted on arrival and never
buffered. A cycle in which any bounded rx queue dropped a frame sets FAULT_BITS bit 7
(RX_OVERLOAD).

SecOC (optional ``secoc``, can_db/secoc.py): SYNC counts only once its authenticator has
verified (an unauthenticated SYNC is not answered); the driver and sensor frames count only
once their own authenticators verify, which the SecOC receiver checks when the SYNC of their
burst has verified (a forged or replayed frame is dropped and counted, never seen by the rx
monitor); the torque and status frames are followed by their authenticators.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import can
import numpy as np

from can_db.codec import Codec, Decoded, MessageSpec, Rejected, Transmitter
from can_db.monitor import RxMonitor
from can_db.secoc import PLANT_SECURED, SECURED, ControllerSecOc
from controller.core.interfaces import Controller, ControllerInputs, ControllerOutputs, QpStatus
from controller.core.params import VehicleParams
from controller.runtime.envelope import EnvelopeConfig, SafetyEnvelope, load_envelope_config
from controller.runtime.plausibility import CHECKED as FROZEN_CHECKED
from controller.runtime.plausibility import FrozenSignalMonitor

log = logging.getLogger(__name__)

SENSOR_FRAMES = ("MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")
DRIVER_FRAME = "DRIVER_INPUTS"
MONITORED = (DRIVER_FRAME, *SENSOR_FRAMES, "SYNC")
PLANT_RESTART_BACKSTEP_S = 0.5  # SYNC time jumping back by more than this: a new plant
# Cycles of frames the lockstep burst buffer keeps per monitored ID: the rx timeout (3 cycles,
# RxMonitor's timeout_factor). An older frame belongs to a cycle whose SYNC stream has timed
# out by then, and the newer frames of its ID overwrite its values anyway; 3 cycles let two
# lost SYNCs in a row pass without a counter gap.
BURST_CYCLES = 3
BURST_FULL = "burst_full"  # rx_drops reason: oldest frame of an ID pushed out of the burst
SECOC_PENDING_FULL = "secoc_pending_full"  # rx_drops reason: SecOC receiver evicted unverified
CONTROLLER_IDS = {"passive": 0, "nmpc-rhonn": 1, "nmpc-mf": 2, "lmpc": 3}


class Mode(IntEnum):
    """CTRL_STATUS.MODE values (see the DBC's value table)."""

    INIT = 0
    ACTIVE = 1
    STANDBY = 2
    DEGRADED_SENSORS = 3
    DRIVER_LOST_RAMPDOWN = 4
    FAULT = 5


class Fault(IntEnum):
    """CTRL_STATUS.FAULT_BITS bit positions."""

    SENSORS_INVALID = 0
    DRIVER_INVALID = 1
    SYNC_LOST = 2
    SOLVER_FALLBACK = 3
    NONFINITE_INPUT = 4
    LEARNING_RESET = 5
    TORQUE_CLIPPED = 6
    RX_OVERLOAD = 7  # a bounded rx queue dropped frames since the previous answer


def burst_bound(spec: MessageSpec, comm_period_s: float) -> int:
    """Frames of message ``spec`` the lockstep burst buffer keeps: its frames per
    communication cycle (``comm_period_s`` s over its DBC GenMsgCycleTime, at least 1) times
    BURST_CYCLES."""
    per_cycle = 1 if spec.cycle_time_s <= 0.0 \
        else max(1, math.ceil(comm_period_s / spec.cycle_time_s - 1e-9))
    return per_cycle * BURST_CYCLES


@dataclass(slots=True)
class CycleRecord:
    """What the node did in one answered cycle (for the timing log and status frame)."""

    cycle: int = -1
    sim_time_s: float = 0.0
    step_ns: int = 0
    mpc_update: bool = False
    mode: Mode = Mode.INIT
    fault_bits: int = 0
    outputs: ControllerOutputs = field(default_factory=ControllerOutputs)


class ControllerNode:
    """Turns received plant frames into torque/status frames around a pure Controller."""

    def __init__(self, controller: Controller, params: VehicleParams, *,
                 codec: Codec | None = None, comm_period_s: float = 0.01,
                 rampdown_nm_per_s: float = 1500.0,
                 clock_ns: Callable[[], int] | None = None,
                 envelope: EnvelopeConfig | None = None,
                 secoc: ControllerSecOc | None = None) -> None:
        self.controller = controller
        self.secoc = secoc  # SecOC hook: None = frames are not authenticated
        self.params = params
        self.codec = codec or Codec()
        self.monitor = RxMonitor(self.codec, MONITORED)
        # without SecOC: the authenticators a SecOC plant sends, by frame ID (module doc)
        self._plant_auth_ids = {} if secoc is not None else {
            self.codec.messages[SECURED[n]].frame_id: SECURED[n] for n in PLANT_SECURED}
        self.authenticators_ignored = 0
        self.tx = Transmitter(self.codec)
        self.comm_period_s = comm_period_s
        self.mpc_every = max(1, round(controller.ts / comm_period_s))
        self.rampdown_nm_per_s = rampdown_nm_per_s
        # The clock only measures compute time for the status frame; it never feeds the
        # algorithm, so outputs stay deterministic.
        self._clock_ns = clock_ns or (lambda: 0)
        self.controller_id = CONTROLLER_IDS.get(controller.name, 15)
        self.inputs = ControllerInputs()
        self.torques = np.zeros(4)
        self.record = CycleRecord()
        self.last_sync: Decoded | None = None
        # Lockstep burst buffer, one bounded deque of (frame, decoded) per monitored ID but
        # SYNC. Drop-oldest: the SYNC stamps every buffered frame with its own time, so the
        # newest frame of an ID is the one that belongs to it; keeping the first ones would
        # feed values cycles old as fresh. A dropped frame then shows as a counter_jump, as a
        # frame lost on the bus does (tolerated and counted).
        self._burst: dict[int, deque[tuple[can.Message, Decoded]]] = {
            spec.frame_id: deque(maxlen=burst_bound(spec, comm_period_s))
            for spec in (self.codec.messages[n] for n in MONITORED if n != "SYNC")}
        self.rx_drops: dict[str, int] = {BURST_FULL: 0}
        self.rx_overload_cycles = 0  # answers sent with FAULT_BITS bit 7 set
        self._drops_answered = 0  # rx drops already reported by an answer
        self._sync_id = self.codec.messages["SYNC"].frame_id
        self._last_stamp = 0.0  # sim time of the last SYNC, s (stamps early rejections)
        self._cycles_since_mpc = self.mpc_every  # run the MPC on the first valid cycle
        self.mode = Mode.INIT
        self.mode_changes = 0
        self.controller_exceptions = 0
        self.core_fault_latched = False  # the core raised: FAULT until a process restart
        self.plant_restarts = 0
        self.frozen = FrozenSignalMonitor()
        # Output safety envelope (controller/runtime/envelope.py) and its previous output, N·m.
        self.envelope = SafetyEnvelope(envelope or load_envelope_config(),
                                       params.peak_torque_nm, params.peak_power_w,
                                       comm_period_s)
        self._env_prev = np.zeros(4)

    # ----------------------------------------------------------------- lockstep
    def on_frame_lockstep(self, msg: can.Message) -> list[can.Message] | None:
        """Buffer a frame; on SYNC validate the burst at sim time and answer the cycle."""
        sync = None
        if self.secoc is not None:  # SecOC hook: SYNC released only by its authenticator
            verified = self.secoc.feed(msg)
            if verified is None:
                return None
            msg = verified
            sync = self.secoc.receiver.released_sync  # decoded already (for its freshness)
        elif msg.arbitration_id in self._plant_auth_ids:
            self._authenticator_ignored(msg.arbitration_id)
        if msg.arbitration_id != self._sync_id:
            slot = self._burst.get(msg.arbitration_id)
            if slot is None:  # unknown or unmonitored ID (a flood): counted now, not inside
                self.monitor.process(msg, self._last_stamp)  # the next SYNC's turnaround
                return None
            decoded = self.codec.decode_message(msg)
            if isinstance(decoded, Rejected):  # malformed: counted now, takes no slot (its
                self.monitor.process(msg, self._last_stamp, decoded)  # count needs no time)
                return None
            if len(slot) == slot.maxlen:
                self.rx_drops[BURST_FULL] += 1  # the append pushes the oldest out
            slot.append((msg, decoded))
            return None
        if sync is None:
            sync = self.codec.decode_message(msg)
        now = sync.values["SIM_TIME"] if isinstance(sync, Decoded) else None
        stamp = now if now is not None else (self.last_sync.values["SIM_TIME"]
                                             if self.last_sync else 0.0)
        if (self.last_sync is not None and now is not None
                and now < self.last_sync.values["SIM_TIME"] - PLANT_RESTART_BACKSTEP_S):
            self._plant_restarted()
        self._last_stamp = stamp
        for slot in self._burst.values():  # per ID in arrival order (streams independent)
            for frame, decoded in slot:
                self._accept(frame, stamp, decoded)
            slot.clear()
        if self.secoc is not None:  # SecOC: the burst's driver and sensor frames that verified
            for frame in self.secoc.released_data:
                self._accept(frame, stamp)
        result = self._accept(msg, stamp, sync)
        if not isinstance(result, Decoded):
            return None  # a corrupted SYNC is not answered: the plant's timeout handles it
        self.last_sync = result
        return self._answer(stamp)

    def _accept(self, msg: can.Message, now_s: float,
                decoded: Decoded | Rejected | None = None) -> object:
        """Rx validation, then the frozen-signal check on accepted sensor frames
        (``decoded``: the frame already decoded, if it was)."""
        result = self.monitor.process(msg, now_s, decoded)
        if isinstance(result, Decoded) and result.name in FROZEN_CHECKED:
            self.frozen.update(result.name, result.values, self.inputs.vx)
        return result

    def _authenticator_ignored(self, frame_id: int) -> None:
        """A plant's SecOC authenticator reached this node without SecOC: counted, the first
        one logged (the plant rejects every answer as unauthenticated, so it falls back)."""
        self.authenticators_ignored += 1
        if self.authenticators_ignored == 1:
            log.warning("SecOC is off here (--no-secoc) but the plant authenticates its frames "
                        "(%s on the bus): it will reject every answer of this controller as "
                        "unauthenticated and fall back to the driver's torques; run both with "
                        "SecOC (drop --no-secoc) or both without",
                        self._plant_auth_ids[frame_id])

    def _plant_restarted(self) -> None:
        """Simulated time went backwards: a new plant. Forget every stream's state (its
        frames must prove themselves again); the learned controller state is kept."""
        self.plant_restarts += 1
        # the model's pending one-step prediction belongs to the old plant's time line:
        # learning from it would be one large bogus error
        forget = getattr(getattr(self.controller, "model", None), "forget_record", None)
        if callable(forget):
            forget()
        counts = self.monitor.counts
        self.monitor = RxMonitor(self.codec, MONITORED)
        self.monitor.counts = counts
        self.frozen = FrozenSignalMonitor()

    # ------------------------------------------------------------ free-running
    def on_frame(self, msg: can.Message, now_s: float) -> None:
        """Validate a frame on arrival (free-running mode), ``now_s`` monotonic seconds."""
        if self.secoc is not None:  # SecOC hook
            verified = self.secoc.feed(msg)
            if verified is None:
                return
            msg = verified
            for frame in self.secoc.released_data:  # released with their burst's SYNC
                self._accept(frame, now_s)
        elif msg.arbitration_id in self._plant_auth_ids:
            self._authenticator_ignored(msg.arbitration_id)
        result = self._accept(msg, now_s)
        if isinstance(result, Decoded) and result.name == "SYNC":
            self.last_sync = result

    def tick(self, now_s: float) -> list[can.Message]:
        """Answer one cycle on the node's own schedule (free-running mode)."""
        return self._answer(now_s)

    # ------------------------------------------------------------------ shared
    def _answer(self, now_s: float) -> list[can.Message]:
        rec = self.record
        rec.cycle = int(self.last_sync.values["CYCLE"]) if self.last_sync else -1
        rec.sim_time_s = self.last_sync.values["SIM_TIME"] if self.last_sync else 0.0
        driver_ok = self.monitor.valid(DRIVER_FRAME, now_s)
        sensors_ok = self.monitor.all_valid(SENSOR_FRAMES, now_s) \
            and not self.frozen.any_faulty()
        sync_ok = self.monitor.valid("SYNC", now_s)
        self._fill_inputs(sensors_ok)
        fault_bits = (0 if sensors_ok else 1 << Fault.SENSORS_INVALID) \
            | (0 if driver_ok else 1 << Fault.DRIVER_INVALID) \
            | (0 if sync_ok else 1 << Fault.SYNC_LOST)

        start = self._clock_ns()
        rec.mpc_update = False
        if not driver_ok:
            mode = Mode.DRIVER_LOST_RAMPDOWN if self.mode is not Mode.INIT else Mode.INIT
            self._ramp_down()
            out = rec.outputs
            out.delta_m, out.qp_status, out.qp_iterations = 0.0, int(QpStatus.NOT_RUN), 0
        else:
            out, mode = self._run_controller(sensors_ok)
            rec.outputs = out
            np.copyto(self.torques, out.torques)
        rec.step_ns = self._clock_ns() - start

        clipped = self._apply_envelope(zero_dm=not (sensors_ok and self.inputs.stab_enable))
        if clipped:
            fault_bits |= 1 << Fault.TORQUE_CLIPPED
        if out.fallback:
            fault_bits |= 1 << Fault.SOLVER_FALLBACK
        if mode != self.mode:
            self.mode_changes += 1
        self.mode = rec.mode = mode
        if self._rx_overloaded():
            fault_bits |= 1 << Fault.RX_OVERLOAD
        rec.fault_bits = fault_bits
        return self._frames(rec)

    def rx_drop_counts(self) -> dict[str, int]:
        """Frames dropped by the node's bounded rx queues, by reason (docs/safety/queues.md):
        ``burst_full`` (lockstep burst buffer), ``secoc_pending_full`` (SecOC receiver)."""
        counts = dict(self.rx_drops)
        if self.secoc is not None:
            counts[SECOC_PENDING_FULL] = int(getattr(self.secoc.receiver, "evicted", 0))
        return counts

    def _rx_overloaded(self) -> bool:
        """True when a bounded rx queue dropped frames since the previous answer."""
        total = self.rx_drops[BURST_FULL]  # (no dict built: this runs every answer)
        if self.secoc is not None:
            total += int(getattr(self.secoc.receiver, "evicted", 0))
        if total == self._drops_answered:
            return False
        self._drops_answered = total
        self.rx_overload_cycles += 1
        return True

    def _run_controller(self, sensors_ok: bool) -> tuple[ControllerOutputs, Mode]:
        inputs = self.inputs
        if self.core_fault_latched:
            return self._fault_outputs(), Mode.FAULT
        if not sensors_ok:
            mode = Mode.DEGRADED_SENSORS
        elif not inputs.stab_enable:
            mode = Mode.STANDBY
        else:
            mode = Mode.ACTIVE
        try:
            self._cycles_since_mpc += 1
            if self._cycles_since_mpc >= self.mpc_every:
                self._cycles_since_mpc = 0
                self.record.mpc_update = True
                out = self.controller.step(inputs)
            else:
                out = self.controller.allocate_only(inputs)
        except Exception:  # a bug in the core must not stop the node: pass the driver through
            self.controller_exceptions += 1
            self.core_fault_latched = True
            return self._fault_outputs(), Mode.FAULT
        return out, mode

    def _fault_outputs(self) -> ControllerOutputs:
        """FAULT's safe output: the driver's total torque Tt (pedals × 4 × peak torque, N·m)
        split evenly over the four wheels, ΔM = 0, QP failed (the car without the stability
        function, as the plant's own fallback)."""
        inputs = self.inputs
        out = self.record.outputs
        total = (inputs.accel_pedal - inputs.brake_pedal) * 4.0 * self.params.peak_torque_nm
        out.torques[:] = total / 4.0
        out.total_torque, out.delta_m = total, 0.0
        out.qp_status, out.qp_iterations, out.fallback = int(QpStatus.FAILED), 0, True
        out.yaw_rate_ref = out.beta_ref = 0.0
        return out

    def _fill_inputs(self, sensors_ok: bool) -> None:
        inp = self.inputs
        drv = self.monitor.latest(DRIVER_FRAME)
        if drv is not None:
            v = drv.values
            inp.swa_rad = math.radians(v["SWA"])
            inp.accel_pedal = v["ACCEL_PEDAL"] / 100.0
            inp.brake_pedal = v["BRAKE_PEDAL"] / 100.0
            inp.stab_enable = bool(v["STAB_ENABLE"])
        mot = self.monitor.latest("MOTION_SENSORS")
        if mot is not None:
            inp.yaw_rate = math.radians(mot.values["YAW_RATE"])
            inp.ax, inp.ay = mot.values["AX"], mot.values["AY"]
        whl = self.monitor.latest("WHEEL_SPEEDS")
        if whl is not None:
            w = whl.values
            inp.wheel_speeds[0], inp.wheel_speeds[1] = w["WS_FL"], w["WS_FR"]
            inp.wheel_speeds[2], inp.wheel_speeds[3] = w["WS_RL"], w["WS_RR"]
        est = self.monitor.latest("VEHICLE_EST")
        if est is not None:
            inp.vx, inp.vy = est.values["VX_EST"], est.values["VY_EST"]
        inp.sensors_valid = sensors_ok

    def _ramp_down(self) -> None:
        step = self.rampdown_nm_per_s * self.comm_period_s
        for i in range(4):
            t = self.torques[i]
            self.torques[i] = 0.0 if abs(t) <= step or not math.isfinite(t) \
                else t - math.copysign(step, t)

    def _apply_envelope(self, zero_dm: bool) -> bool:
        """Final output guard, independent of the optimiser (runtime/envelope.py): finite,
        motor torque/power limits at the last received wheel speeds, per-wheel and ΔM rate
        limits, ΔM = 0 when ``zero_dm``. True when a limit clipped (FAULT_BITS bit 6)."""
        limited = self.envelope.apply(self.torques, self.inputs.wheel_speeds, zero_dm,
                                      self._env_prev, self.torques)
        np.copyto(self._env_prev, self.torques)
        return limited

    def _frames(self, rec: CycleRecord) -> list[can.Message]:
        echo = rec.cycle % 256 if rec.cycle >= 0 else 0
        t = self.torques
        out = rec.outputs
        compute_us = rec.step_ns / 1000.0
        frames = [
            self.tx.message("WHEEL_TORQUE_CMD", {"TQ_FL": t[0], "TQ_FR": t[1], "TQ_RL": t[2],
                                                 "TQ_RR": t[3], "ECHO_CYCLE": echo}),
            self.tx.message("CTRL_STATUS", {
                "MODE": int(rec.mode), "FAULT_BITS": rec.fault_bits,
                "QP_STATUS": int(out.qp_status), "QP_ITER": out.qp_iterations,
                "COMPUTE_TIME": compute_us, "ECHO_CYCLE": echo,
                "CONTROLLER_ID": self.controller_id}),
            self.tx.message("CTRL_REFS", {
                "DELTA_M": (t[1] + t[3] - t[0] - t[2]),
                "YAW_RATE_REF": math.degrees(out.yaw_rate_ref),
                "BETA_REF": math.degrees(out.beta_ref), "ECHO_CYCLE": echo}),
        ]
        if self.secoc is not None:  # SecOC hook: authenticators after torque and status
            frames = self.secoc.protect(frames, rec.cycle)
        return frames
