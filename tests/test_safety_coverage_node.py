"""The controller node's safety decisions, each against an independent reference: the fault
bits of one answer, the mode and its change count, the zero yaw moment outside ACTIVE, the
core's fault reaction (latched, the driver's torque split evenly), the ramp-down of a lost
driver, the output envelope's clip bit and the rx-overload bit, and the MPC's cadence.

The core is a scripted stand-in (a unit test of the node, not of a controller): it returns
the torques it is given and counts its calls, so every torque on the bus is known in advance.
"""

from __future__ import annotations

import math

import can
import numpy as np
import pytest

from can_db.codec import Codec, Decoded, Transmitter
from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.params import load_vehicle_params
from controller.runtime.node import ControllerNode, Fault, Mode
from tests.helpers_node import answer, torques

CODEC = Codec()
PARAMS = load_vehicle_params()
COMM_S = 0.01  # communication cycle, s


class ScriptedCore:
    """A controller that answers the torques it holds (N·m, FL FR RL RR), counts its calls
    and raises on the step numbers it is told to."""

    name = "scripted"
    ts = 0.05

    def __init__(self, torques: tuple[float, float, float, float] = (90.0, 110.0, 90.0, 110.0),
                 *, raise_at_step: int | None = None, fallback: bool = False) -> None:
        self.torques = np.array(torques, dtype=float)
        self.raise_at_step = raise_at_step
        self.fallback = fallback
        self.steps = 0
        self.allocations = 0
        self.seen: list[ControllerInputs] = []

    def reset(self) -> None:
        """Nothing learned."""

    def _out(self, inputs: ControllerInputs) -> ControllerOutputs:
        self.seen.append(ControllerInputs(**{k: getattr(inputs, k)
                                             for k in ControllerInputs.__slots__}))
        t = self.torques
        return ControllerOutputs(torques=t.copy(), total_torque=float(t.sum()),
                                 delta_m=float(t[1] + t[3] - t[0] - t[2]),
                                 yaw_rate_ref=0.1, beta_ref=0.01,
                                 qp_status=int(QpStatus.SOLVED), qp_iterations=7,
                                 fallback=self.fallback)

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        self.steps += 1
        if self.raise_at_step is not None and self.steps >= self.raise_at_step:
            raise RuntimeError("core bug")
        return self._out(inputs)

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        self.allocations += 1
        return self._out(inputs)


class Plant:
    """Plant bursts whose sensor values move every cycle (no frozen signal) at 18 m/s."""

    def __init__(self) -> None:
        self.tx = Transmitter(CODEC)
        self.cycle = 0

    def burst(self, *, accel: float = 0.3, brake: float = 0.0, stab: int = 1,
              drop: tuple[str, ...] = ()) -> list[can.Message]:
        k = self.cycle
        frames = {
            "DRIVER_INPUTS": {"SWA": 10.0, "ACCEL_PEDAL": 100 * accel,
                              "BRAKE_PEDAL": 100 * brake, "STAB_ENABLE": stab},
            "MOTION_SENSORS": {"YAW_RATE": 1.0 + 0.1 * (k % 7), "AX": 0.01 * (k % 5),
                               "AY": 0.5 + 0.01 * (k % 3)},
            "WHEEL_SPEEDS": {f"WS_{w}": 50.0 for w in ("FL", "FR", "RL", "RR")},
            "VEHICLE_EST": {"VX_EST": 18.0 + 0.01 * (k % 5), "VY_EST": 0.01 * (k % 3)},
            "SYNC": {"CYCLE": k, "SIM_TIME": k * COMM_S},
        }
        self.cycle += 1
        return [self.tx.message(n, v) for n, v in frames.items() if n not in drop]



def status(frames: dict[str, Decoded]) -> tuple[Mode, int]:
    v = frames["CTRL_STATUS"].values
    return Mode(int(v["MODE"])), int(v["FAULT_BITS"])


def bits(*faults: Fault) -> int:
    return sum(1 << int(f) for f in faults)


def make_node(core: ScriptedCore, **kw: object) -> ControllerNode:
    return ControllerNode(core, PARAMS, comm_period_s=COMM_S, **kw)  # type: ignore[arg-type]


def test_the_fault_bits_name_exactly_what_failed() -> None:
    plant, node = Plant(), make_node(ScriptedCore())
    for _ in range(5):
        frames = answer(node, plant.burst())
        assert status(frames) == (Mode.ACTIVE, 0)
    for _ in range(5):  # the rx timeout is 3 cycles: stale from the 4th burst without it
        frames = answer(node, plant.burst(drop=("MOTION_SENSORS",)))
    assert status(frames) == (Mode.DEGRADED_SENSORS, bits(Fault.SENSORS_INVALID))
    for _ in range(5):
        frames = answer(node, plant.burst())
    assert status(frames) == (Mode.ACTIVE, 0)
    for _ in range(5):
        frames = answer(node, plant.burst(drop=("DRIVER_INPUTS",)))
    assert status(frames) == (Mode.DRIVER_LOST_RAMPDOWN, bits(Fault.DRIVER_INVALID))
    for _ in range(5):
        frames = answer(node, plant.burst(drop=("DRIVER_INPUTS", "WHEEL_SPEEDS")))
    assert status(frames) == (Mode.DRIVER_LOST_RAMPDOWN,
                              bits(Fault.DRIVER_INVALID, Fault.SENSORS_INVALID))


def test_a_lost_sync_is_its_own_fault_bit_in_free_running_mode() -> None:
    plant, node = Plant(), make_node(ScriptedCore())
    for k in range(5):
        t = k * COMM_S
        for f in plant.burst():
            node.on_frame(f, t)
        frames = {d.name: d for d in (CODEC.decode_message(m) for m in node.tick(t))}
        assert status(frames) == (Mode.ACTIVE, 0)  # type: ignore[arg-type]
    for k in range(5, 10):  # everything but the SYNC: stale 3 cycles after the last one
        t = k * COMM_S
        for f in plant.burst(drop=("SYNC",)):
            node.on_frame(f, t)
        frames = {d.name: d for d in (CODEC.decode_message(m) for m in node.tick(t))}
    assert status(frames) == (Mode.ACTIVE, bits(Fault.SYNC_LOST))  # type: ignore[arg-type]
    assert node.record.cycle == 4  # the last SYNC's cycle and time are still echoed
    assert node.record.sim_time_s == pytest.approx(4 * COMM_S)


def test_before_any_sync_the_record_names_no_cycle() -> None:
    """-1 is the timing log's "no SYNC answered yet" (process.py logs record.cycle)."""
    node = make_node(ScriptedCore())
    frames = {d.name: d for d in (CODEC.decode_message(m) for m in node.tick(0.0))}
    assert node.record.cycle == -1 and node.record.sim_time_s == 0.0
    assert frames["WHEEL_TORQUE_CMD"].values["ECHO_CYCLE"] == 0  # type: ignore[union-attr]
    # no driver frame ever: INIT, not a ramp-down; every input stream is missing
    assert status(frames) == (Mode.INIT, bits(Fault.SENSORS_INVALID,  # type: ignore[arg-type]
                                              Fault.DRIVER_INVALID, Fault.SYNC_LOST))


def test_mode_changes_count_the_transitions_seen_on_the_bus() -> None:
    plant, node = Plant(), make_node(ScriptedCore())
    plan = [()] * 4 + [("VEHICLE_EST",)] * 5 + [()] * 4 + [("DRIVER_INPUTS",)] * 5 + [()] * 3
    modes = [status(answer(node, plant.burst(drop=d)))[0] for d in plan]
    previous, changes = [Mode.INIT, *modes[:-1]], 0
    for before, now in zip(previous, modes, strict=True):
        changes += now is not before
    assert changes == 5  # INIT→ACTIVE→DEGRADED→ACTIVE→RAMPDOWN→ACTIVE
    assert node.mode_changes == changes and node.mode is modes[-1] is Mode.ACTIVE


@pytest.mark.parametrize(("stab", "drop", "mode"), [
    (0, (), Mode.STANDBY),
    (1, ("WHEEL_SPEEDS",), Mode.DEGRADED_SENSORS),
])
def test_outside_active_the_yaw_moment_is_zero_and_the_total_kept(
        stab: int, drop: tuple[str, ...], mode: Mode) -> None:
    """The core keeps asking for ΔM = 40 N·m; only ACTIVE lets it through."""
    plant, node = Plant(), make_node(ScriptedCore((90.0, 110.0, 90.0, 110.0)))
    for _ in range(3):
        t = torques(answer(node, plant.burst()))
    assert t[1] + t[3] - t[0] - t[2] == 40.0
    for _ in range(5):
        frames = answer(node, plant.burst(stab=stab, drop=drop))
    t = torques(frames)
    assert status(frames)[0] is mode
    assert t[1] + t[3] - t[0] - t[2] == 0.0 and t.sum() == 400.0
    assert frames["CTRL_REFS"].values["DELTA_M"] == 0.0


def test_a_clipped_command_sets_only_the_clip_bit() -> None:
    plant, node = Plant(), make_node(ScriptedCore((100.0, 100.0, 100.0, 100.0)))
    for _ in range(3):
        assert status(answer(node, plant.burst())) == (Mode.ACTIVE, 0)
    node.controller.torques[:] = (100.0, 600.0, 100.0, 100.0)  # type: ignore[attr-defined]
    frames = answer(node, plant.burst())
    assert status(frames) == (Mode.ACTIVE, bits(Fault.TORQUE_CLIPPED))
    assert torques(frames)[1] == PARAMS.peak_torque_nm


def test_a_solver_fallback_sets_only_its_bit() -> None:
    plant, node = Plant(), make_node(ScriptedCore(fallback=True))
    for _ in range(3):
        frames = answer(node, plant.burst())
    assert status(frames) == (Mode.ACTIVE, bits(Fault.SOLVER_FALLBACK))


def test_a_core_that_raises_latches_fault_with_the_drivers_torque_split_evenly() -> None:
    """FAULT answers Tt = (ACCEL − BRAKE)/100 · 4 · 450 N·m (the DBC's WHEEL_TORQUE_CMD
    comment), a quarter per wheel, ΔM = 0, QP failed; the core is never stepped again."""
    core = ScriptedCore((90.0, 110.0, 90.0, 110.0), raise_at_step=2)
    plant, node = Plant(), make_node(core)
    accel, brake = 0.51, 0.2
    tt = (100 * accel - 100 * brake) / 100 * 4 * 450.0
    quarter = round(tt / 4 * 2) / 2  # 139.5 N·m on the 0.5 N·m torque grid
    for _ in range(5):  # step 1 at the first cycle, step 2 (raises) at the 6th
        assert status(answer(node, plant.burst(accel=accel, brake=brake)))[0] is Mode.ACTIVE
    calls = (core.steps, core.allocations)
    for k in range(10):  # the first: the step that raised; then latched, no step tried
        frames = answer(node, plant.burst(accel=accel, brake=brake))
        assert status(frames) == (Mode.FAULT, bits(Fault.SOLVER_FALLBACK))
        assert torques(frames).tolist() == [quarter] * 4
        out = node.record.outputs  # the record the rerun sink logs
        assert out.delta_m == 0.0 and out.qp_iterations == 0 and out.fallback
        assert k == 0 or not node.record.mpc_update
        v = frames["CTRL_STATUS"].values
        assert v["QP_STATUS"] == QpStatus.FAILED and v["QP_ITER"] == 0
        refs = frames["CTRL_REFS"].values
        assert refs["DELTA_M"] == 0.0 and refs["YAW_RATE_REF"] == 0.0 and refs["BETA_REF"] == 0.0
    assert (core.steps, core.allocations) == (calls[0] + 1, calls[1])  # the one that raised
    assert node.controller_exceptions == 1 and node.core_fault_latched
    # a lost driver frame still ramps down; FAULT returns with the driver frame
    for _ in range(5):
        frames = answer(node, plant.burst(accel=accel, brake=brake, drop=("DRIVER_INPUTS",)))
    assert status(frames)[0] is Mode.DRIVER_LOST_RAMPDOWN
    for _ in range(2):
        frames = answer(node, plant.burst(accel=accel, brake=brake))
    assert status(frames)[0] is Mode.FAULT and torques(frames).tolist() == [quarter] * 4
    assert core.steps == calls[0] + 1 and node.controller_exceptions == 1


def test_a_lost_driver_ramps_every_wheel_to_zero_at_the_set_rate() -> None:
    rate = 1000.0  # N·m/s: 10 N·m per 10 ms cycle
    start = (100.0, -37.5, 20.0, 0.0)
    plant, node = Plant(), make_node(ScriptedCore(start), rampdown_nm_per_s=rate)
    for _ in range(3):
        assert torques(answer(node, plant.burst())).tolist() == list(start)
    seen = []
    for _ in range(16):
        frames = answer(node, plant.burst(drop=("DRIVER_INPUTS",)))
        seen.append((status(frames)[0], torques(frames)))
    ramp = [t for mode, t in seen if mode is Mode.DRIVER_LOST_RAMPDOWN]
    assert len(ramp) == 13  # the timeout is 3 cycles: the 4th without the frame ramps
    assert [t.tolist() for mode, t in seen[:3]] == [list(start)] * 3
    step = rate * COMM_S
    for mode, _ in seen[3:]:
        assert mode is Mode.DRIVER_LOST_RAMPDOWN
    v = frames["CTRL_STATUS"].values  # no step of the core during the ramp-down
    assert v["QP_STATUS"] == QpStatus.NOT_RUN and v["QP_ITER"] == 0
    out = node.record.outputs  # the record the rerun sink logs (the frame saturates at 0)
    assert out.delta_m == 0.0 and out.qp_iterations == 0 and out.qp_status == QpStatus.NOT_RUN
    assert not node.record.mpc_update
    for k, t in enumerate(ramp, start=1):
        expected = [math.copysign(max(0.0, abs(s) - k * step), s) if s else 0.0 for s in start]
        assert t.tolist() == expected, k


def test_the_ramp_down_zeroes_non_finite_and_small_torques() -> None:
    node = make_node(ScriptedCore(), rampdown_nm_per_s=1500.0)  # 15 N·m per cycle
    node.torques[:] = (math.nan, -math.inf, 15.0, -15.5)
    node._ramp_down()
    assert node.torques.tolist() == [0.0, 0.0, 0.0, -0.5]


def test_an_overflowing_burst_sets_the_overload_bit_once() -> None:
    plant, node = Plant(), make_node(ScriptedCore())
    for _ in range(3):
        assert status(answer(node, plant.burst())) == (Mode.ACTIVE, 0)
    burst = plant.burst()
    extra = [plant.tx.message("DRIVER_INPUTS", {"SWA": 10.0, "ACCEL_PEDAL": 30.0,
                                                "BRAKE_PEDAL": 0.0, "STAB_ENABLE": 1})
             for _ in range(3)]  # 4 driver frames in one burst: the buffer keeps 3
    frames = answer(node, extra + burst)
    assert node.rx_drop_counts() == {"burst_full": 1}
    assert status(frames) == (Mode.ACTIVE, bits(Fault.RX_OVERLOAD))
    assert node.record.fault_bits == bits(Fault.RX_OVERLOAD)  # the bit, not a saturated byte
    for _ in range(2):
        assert not status(answer(node, plant.burst()))[1] & bits(Fault.RX_OVERLOAD)
    assert node.rx_overload_cycles == 1


def test_the_full_step_runs_on_the_first_valid_cycle_then_every_controller_period() -> None:
    core = ScriptedCore()
    plant, node = Plant(), make_node(core)
    assert node.mpc_every == round(core.ts / COMM_S) == 5
    updates = []
    for _ in range(12):
        answer(node, plant.burst())
        updates.append(node.record.mpc_update)
    assert updates == [k % 5 == 0 for k in range(12)]
    assert (core.steps, core.allocations) == (3, 9)
    # the core sees the sensors as valid and the driver's inputs in SI units
    last = core.seen[-1]
    assert last.sensors_valid and last.stab_enable
    assert last.accel_pedal == pytest.approx(0.3) and last.swa_rad == pytest.approx(
        math.radians(10.0))


def test_the_status_frame_reports_the_time_the_step_took() -> None:
    """COMPUTE_TIME is the clock's advance across the core's step, µs (the clock only
    measures; a clock that advances 250 µs per reading gives 250 µs)."""
    ticks = iter(range(0, 10**9, 250_000))
    plant, node = Plant(), make_node(ScriptedCore(), clock_ns=lambda: next(ticks))
    for _ in range(3):
        frames = answer(node, plant.burst())
        assert node.record.step_ns == 250_000
        assert frames["CTRL_STATUS"].values["COMPUTE_TIME"] == 250.0
