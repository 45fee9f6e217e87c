"""The plant's side of the bus, without sockets or clocks: the frames of a cycle out of the
simulation (SecOC and injected faults included), torque commands into it, and the one
command-loss policy of lockstep and real time (:meth:`PlantNode.advance`). The process
(plant_sim/process.py) and the in-process loop (harness/run/inprocess_loop.py) both drive it."""

from __future__ import annotations

import can

from can_db.codec import Codec, Decoded, Transmitter
from can_db.faults import FaultInjector
from can_db.monitor import RxMonitor
from can_db.secoc import PlantSecOc
from plant_sim.simulation import Simulation

TORQUE_FRAME = "WHEEL_TORQUE_CMD"
WHEELS = ("FL", "FR", "RL", "RR")


class PlantNode:
    """Frames out of the simulation, torque commands into it (no sockets, no clocks)."""

    def __init__(self, sim: Simulation, codec: Codec | None = None,
                 injector: FaultInjector | None = None,
                 secoc: PlantSecOc | None = None,
                 command_hold_s: float | None = None) -> None:
        """``command_hold_s``: how long the last accepted torque command stays in force
        without a fresh one, s (None: the rx monitor's default, 3 × the DBC cycle time)."""
        self.sim = sim
        self.secoc = secoc  # SecOC hook: None = frames are not authenticated
        self.codec = codec or Codec()
        self.injector = injector
        self.tx = Transmitter(self.codec)
        self.monitor = RxMonitor(
            self.codec, (TORQUE_FRAME, "CTRL_STATUS", "CTRL_REFS"),
            timeouts_s=None if command_hold_s is None else {TORQUE_FRAME: command_hold_s})
        self.torque_id = self.codec.messages[TORQUE_FRAME].frame_id
        self.fallback_cycles = 0  # cycles on the driver fallback (no command in force)
        self.commanded_cycles = 0  # cycles on a fresh command
        self.held_cycles = 0  # cycles on the last command, held (no fresh one this cycle)
        self._in_force: Decoded | None = None  # the last accepted torque command

    def burst(self) -> list[can.Message]:
        """The frames of the current cycle, SYNC last (after fault injection, if any)."""
        frames = self._clean_burst()
        if self.secoc is not None:  # SecOC hook: authenticators after SYNC and the data frames
            if self.injector is not None:  # faults of the plant's own sensors and E2E first:
                frames = self.injector.apply(frames, self.sim.time_s, stage="sender")  # signed
                return self.injector.apply(self.secoc.protect(frames, self.sim.cycle),
                                           self.sim.time_s, stage="bus")
            frames = self.secoc.protect(frames, self.sim.cycle)
        if self.injector is None:
            return frames
        return self.injector.apply(frames, self.sim.time_s)

    def _clean_burst(self) -> list[can.Message]:
        s = self.sim.sensors()
        ws = s.wheel_speeds_radps
        return [
            self.tx.message("DRIVER_INPUTS", {
                "SWA": s.swa_deg, "ACCEL_PEDAL": 100.0 * s.accel_pedal,
                "BRAKE_PEDAL": 100.0 * s.brake_pedal, "STAB_ENABLE": float(s.stab_enable)}),
            self.tx.message("MOTION_SENSORS", {"YAW_RATE": s.yaw_rate_degps, "AX": s.ax_mps2,
                                               "AY": s.ay_mps2}),
            self.tx.message("WHEEL_SPEEDS", {f"WS_{w}": ws[i] for i, w in enumerate(WHEELS)}),
            self.tx.message("VEHICLE_EST", {"VX_EST": s.vx_est_mps, "VY_EST": s.vy_est_mps}),
            self.tx.message("SYNC", {"CYCLE": self.sim.cycle, "SIM_TIME": self.sim.time_s}),
        ]

    def receive(self, msg: can.Message, now_s: float) -> Decoded | None:
        """Validate a frame; return it when it is an accepted torque command or status."""
        if self.secoc is not None:  # SecOC hook: verified before the E2E monitor sees it
            verified = self.secoc.feed(msg, self.sim.cycle)
            if verified is None:
                return None
            msg = verified
        result = self.monitor.process(msg, now_s)
        if isinstance(result, Decoded) and result.name in (TORQUE_FRAME, "CTRL_STATUS"):
            return result
        return None

    def rx_drop_counts(self) -> dict[str, int]:
        """Frames dropped by the plant's bounded rx queues, by reason: the SecOC receiver's
        pending frames (``secoc_pending_full``); the plant buffers nothing else."""
        if self.secoc is None:
            return {}
        return {"secoc_pending_full": int(getattr(self.secoc.receiver, "evicted", 0))}

    def advance(self, command: Decoded | None, now_s: float | None = None) -> None:
        """Integrate one cycle with the command in force: ``command`` (this cycle's accepted
        torque frame, None when there is none), else the last accepted one while the rx
        monitor holds the torque stream valid at ``now_s`` (the command hold time, in the
        clock ``receive`` was given; None: the simulated time); else the driver fallback.
        The same rule in lockstep and in real time."""
        if command is not None:
            self._in_force = command
        now = self.sim.time_s if now_s is None else now_s
        if self._in_force is None or not self.monitor.valid(TORQUE_FRAME, now):
            self.fallback_cycles += 1
            self.sim.step_comm(None)
            return
        if command is None:
            self.held_cycles += 1
        else:
            self.commanded_cycles += 1
        v = self._in_force.values
        self.sim.step_comm([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])
