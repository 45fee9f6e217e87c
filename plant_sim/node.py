"""The plant's side of the bus, without sockets or clocks: the frames of a cycle out of the
simulation (SecOC and injected faults included), torque commands into it, and the one
command-loss policy of lockstep and real time (:meth:`PlantNode.advance`). The process
(plant_sim/process.py) and the in-process loop (harness/run/inprocess_loop.py) both drive it."""

from __future__ import annotations

import logging

import can

from can_db.codec import Codec, Decoded, Transmitter
from can_db.faults import FaultInjector
from can_db.monitor import RxMonitor
from can_db.secoc import PlantSecOc
from plant_sim.simulation import Simulation

TORQUE_FRAME = "WHEEL_TORQUE_CMD"
WHEELS = ("FL", "FR", "RL", "RR")
#: largest share of a run's cycles on the driver fallback for a loop that held (2 %): past
#: it the plant warns (once), a one-shot plant ends with exit code 4, and the harness calls
#: the run ``degraded`` (harness/analysis/loop_health.py). A clean lockstep run has none; a
#: lost controller or a SecOC key mismatch has every cycle.
FALLBACK_SHARE_MAX = 0.02
#: cycles before the share is judged during a run (0.5 s of 10 ms cycles): the first
#: cycles of a start alone do not warn
FALLBACK_WARN_AFTER_CYCLES = 50
#: why a plant drives on its fallback, for the warning and the one-shot plant's last line
FALLBACK_HINT = ("no torque command accepted: no controller answers on this bus, or it uses "
                 "other SecOC keys (its log then says 'first rejected SYNC frame (bad_mac)'), "
                 "or SecOC is on in one process only")

log = logging.getLogger("rhonn-plant")


def fallback_text(fallback_cycles: int, cycles: int) -> str:
    """``the plant fell back in 100% of its cycles (300 of 300; limit 2%)``."""
    share = fallback_cycles / cycles if cycles else 0.0
    return (f"the plant fell back in {share:.0%} of its cycles ({fallback_cycles} of "
            f"{cycles}; limit {FALLBACK_SHARE_MAX:.0%})")


def fallback_passed(fallback_cycles: int, cycles: int) -> bool:
    """True when the fallback share of ``cycles`` is over :data:`FALLBACK_SHARE_MAX`."""
    return cycles > 0 and fallback_cycles > FALLBACK_SHARE_MAX * cycles


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
        self.fallback_warned = False  # the share passed FALLBACK_SHARE_MAX once (logged)
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
            self._warn_fallback()
            return
        if command is None:
            self.held_cycles += 1
        else:
            self.commanded_cycles += 1
        v = self._in_force.values
        self.sim.step_comm([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])

    def _warn_fallback(self) -> None:
        """Log once when the fallback share passes its limit (after the first cycles)."""
        cycles = self.fallback_cycles + self.held_cycles + self.commanded_cycles
        if self.fallback_warned or cycles < FALLBACK_WARN_AFTER_CYCLES \
                or not fallback_passed(self.fallback_cycles, cycles):
            return
        self.fallback_warned = True
        log.warning("%s so far: %s", fallback_text(self.fallback_cycles, cycles), FALLBACK_HINT)
