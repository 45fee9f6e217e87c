"""The controller's bus node: lockstep answers, degraded modes, malformed input."""

from __future__ import annotations

import itertools
import math

import can
import numpy as np

from can_db.codec import Codec, Transmitter
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode, Fault, Mode
from tests.helpers_node import answer, torques

CODEC = Codec()
PARAMS = load_vehicle_params()


class FakePlant:
    """Encodes plant bursts; individual frames can be dropped or corrupted."""

    def __init__(self) -> None:
        self.tx = Transmitter(CODEC)
        self.cycle = 0
        self.rng = np.random.default_rng(3)  # sensor noise, as on a real car

    def burst(self, *, accel: float = 0.3, swa_deg: float = 0.0,
              drop: tuple[str, ...] = (), stuck_yaw: float | None = None
              ) -> list[can.Message]:
        vx = 18.0
        n = self.rng.normal
        frames = {
            "DRIVER_INPUTS": {"SWA": swa_deg, "ACCEL_PEDAL": 100 * accel, "BRAKE_PEDAL": 0,
                              "STAB_ENABLE": 1},
            "MOTION_SENSORS": {"YAW_RATE": n(0, 0.1) if stuck_yaw is None else stuck_yaw,
                               "AX": n(0, 0.03), "AY": n(0, 0.03)},
            "WHEEL_SPEEDS": {f"WS_{w}": vx / 0.358 for w in ("FL", "FR", "RL", "RR")},
            "VEHICLE_EST": {"VX_EST": vx + n(0, 0.05), "VY_EST": n(0, 0.02)},
            "SYNC": {"CYCLE": self.cycle, "SIM_TIME": self.cycle * 0.01},
        }
        self.cycle += 1
        return [self.tx.message(n, v) for n, v in frames.items() if n not in drop]



def test_every_sync_is_answered_with_its_cycle_echoed() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("passive"), PARAMS)
    for k in range(300):
        frames = answer(node, plant.burst())
        assert frames["WHEEL_TORQUE_CMD"].values["ECHO_CYCLE"] == k % 256
        assert frames["CTRL_STATUS"].values["ECHO_CYCLE"] == k % 256
    assert node.mode is Mode.ACTIVE
    # passive: ΔM = 0 and the driver's torque Tt = accel * 4 * 450 N·m, split by axle load
    t = torques(frames)
    assert abs(t.sum() - 0.3 * 4 * 450.0) <= 1.0
    assert t[0] == t[1] and t[2] == t[3]


def test_invalid_sensors_give_zero_yaw_moment_and_pass_the_driver_through() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("nmpc-rhonn"), PARAMS)
    for _ in range(20):
        answer(node, plant.burst(swa_deg=60.0))
    for _ in range(10):  # motion sensors lost: invalid after 3 cycles (30 ms)
        frames = answer(node, plant.burst(swa_deg=60.0, drop=("MOTION_SENSORS",)))
    status = frames["CTRL_STATUS"].values
    assert status["MODE"] == Mode.DEGRADED_SENSORS
    assert int(status["FAULT_BITS"]) & (1 << Fault.SENSORS_INVALID)
    t = torques(frames)
    assert abs(t[1] + t[3] - t[0] - t[2]) <= 1.0  # ΔM = 0 (within quantisation)
    assert abs(t.sum() - 0.3 * 4 * 450.0) <= 2.0  # Tt passed through


def test_lost_driver_frame_ramps_torques_to_zero() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("passive"), PARAMS,
                                              rampdown_nm_per_s=1500.0)
    for _ in range(10):
        answer(node, plant.burst(accel=0.8))
    totals, modes = [], []
    for _ in range(40):
        frames = answer(node, plant.burst(accel=0.8, drop=("DRIVER_INPUTS",)))
        totals.append(np.abs(torques(frames)).max())
        modes.append(frames["CTRL_STATUS"].values["MODE"])
    # timeout 30 ms: the 4th cycle without the frame is the first in ramp-down
    assert modes.index(Mode.DRIVER_LOST_RAMPDOWN) <= 3
    totals = totals[modes.index(Mode.DRIVER_LOST_RAMPDOWN):]
    # 360 N·m per wheel ramps at 15 N·m per cycle: monotone, reaches zero within 25 cycles
    assert all(b <= a for a, b in itertools.pairwise(totals))
    assert totals[2] > 0.0 and totals[-1] == 0.0


def test_malformed_frames_never_stop_the_node() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("nmpc-rhonn"), PARAMS)
    rng = np.random.default_rng(7)
    for _ in range(100):
        junk = [can.Message(arbitration_id=int(rng.integers(0, 0x800)),
                            data=bytes(rng.integers(0, 256, int(rng.integers(0, 9)))),
                            is_extended_id=False) for _ in range(3)]
        frames = answer(node, junk + plant.burst())
        assert np.all(np.isfinite(torques(frames)))
        assert np.all(np.abs(torques(frames)) <= PARAMS.peak_torque_nm)
    assert sum(node.monitor.counts.values()) > 0
    assert node.mode in (Mode.ACTIVE, Mode.DEGRADED_SENSORS)


def test_a_corrupted_sync_is_not_answered() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("passive"), PARAMS)
    burst = plant.burst()
    bad = bytearray(burst[-1].data)
    bad[5] ^= 0x01
    burst[-1] = can.Message(arbitration_id=burst[-1].arbitration_id, data=bytes(bad),
                            is_extended_id=False)
    assert all(node.on_frame_lockstep(f) is None for f in burst)
    assert node.monitor.counts["bad_crc"] == 1
    assert math.isfinite(answer(node, plant.burst())["CTRL_REFS"].values["DELTA_M"])


def test_a_frozen_yaw_rate_is_detected_within_ten_frames() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("nmpc-rhonn"), PARAMS)
    for _ in range(30):
        assert answer(node, plant.burst())["CTRL_STATUS"].values["MODE"] == Mode.ACTIVE
    modes = [answer(node, plant.burst(stuck_yaw=2.5))["CTRL_STATUS"].values["MODE"]
             for _ in range(12)]
    # valid CRC and counters: only the plausibility check sees it, after 10 equal values
    assert modes[:9] == [Mode.ACTIVE] * 9 and modes[9:] == [Mode.DEGRADED_SENSORS] * 3
    assert node.frozen.detections == 1
    for _ in range(2):  # the signal moves again: the sensor is trusted again
        frames = answer(node, plant.burst())
    assert frames["CTRL_STATUS"].values["MODE"] == Mode.ACTIVE


def test_a_restarted_plant_is_detected_and_control_resumes() -> None:
    plant, node = FakePlant(), ControllerNode(make_controller("nmpc-rhonn"), PARAMS)
    plant.cycle = 500
    for _ in range(20):
        answer(node, plant.burst())
    restarted = FakePlant()  # simulated time starts again at 0, counters at 0
    statuses = [answer(node, restarted.burst())["CTRL_STATUS"].values for _ in range(5)]
    assert node.plant_restarts == 1
    assert statuses[-1]["MODE"] == Mode.ACTIVE and statuses[-1]["ECHO_CYCLE"] == 4
