"""Bus logs in simulated time (lockstep), the three log formats, and replay that infers the
controller and splits a log at a controller restart.

The closed loop here is in-process (PlantNode + ControllerNode exchanging frames in a list,
no sockets): these are unit tests of the logger and the replay; the end-to-end runs over a
real bus are in test_closed_loop.py."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from can_db.codec import Codec
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode
from harness.run.bus_logger import PERIOD_S, SimTimeStamper, open_writer
from harness.run.replay import replay_log
from plant_sim.node import PlantNode
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation
from tests.recorded import record_over_virtual_bus

TORQUE = "WHEEL_TORQUE_CMD"


def lockstep_frames(cycles: int, controller: str, restart_at: int | None = None,
                    gap: int = 3, late_status: bool = False) -> list[can.Message]:
    """Frames of an in-process lockstep loop in bus order. ``restart_at``: the controller
    process is replaced by a fresh one there, after ``gap`` unanswered cycles.
    ``late_status``: the controller's status/refs arrive after the next plant burst."""
    codec = Codec()
    plant = PlantNode(Simulation(load_scenario("dlc-paper")), codec)
    params = load_vehicle_params()

    def fresh() -> ControllerNode:
        return ControllerNode(make_controller(controller), params, codec=codec)

    node, frames, held = fresh(), [], []
    torque_id = codec.messages[TORQUE].frame_id
    for k in range(cycles):
        burst = plant.burst()
        frames += burst
        frames += held
        held = []
        silent = restart_at is not None and restart_at <= k < restart_at + gap
        if restart_at is not None and k == restart_at + gap:
            node = fresh()
        answer = None
        if not silent:
            for msg in burst:
                out = node.on_frame_lockstep(msg)
                if out:
                    answer = out
        command = None
        if answer:
            for f in answer:
                if late_status and f.arbitration_id != torque_id:
                    held.append(f)
                else:
                    frames.append(f)
            command = plant.receive(next(f for f in answer if f.arbitration_id == torque_id),
                                    plant.sim.time_s)
        plant.advance(command)
    return frames + held


def test_sim_time_stamps_keep_every_message_on_its_10ms_cycle() -> None:
    frames = lockstep_frames(60, "lmpc", late_status=True)
    stamper = SimTimeStamper(Codec(), epoch_s=1000.0)
    out: list[can.Message] = []
    for f in frames:
        out += stamper.feed(f)
    out += stamper.flush()
    assert len(out) == len(frames)
    t = np.array([m.timestamp for m in out])
    assert np.all(np.diff(t) >= 0)  # the file is in time order
    for arb in {m.arbitration_id for m in out}:
        d = np.diff(t[[m.arbitration_id == arb for m in out]])
        assert np.allclose(d, PERIOD_S, atol=1e-9), hex(arb)  # late answers included
    assert t[0] == pytest.approx(1000.0)


def test_a_plant_restart_does_not_step_the_log_time_back() -> None:
    stamper = SimTimeStamper(Codec(), epoch_s=0.0)
    first, second = lockstep_frames(20, "passive"), lockstep_frames(20, "passive")
    out = []
    for f in first + second:
        out += stamper.feed(f)
    out += stamper.flush()
    t = np.array([m.timestamp for m in out])
    assert np.all(np.diff(t) >= 0)
    assert t[-1] == pytest.approx(0.39, abs=0.005)  # 40 cycles of 10 ms, one time line


@pytest.mark.parametrize("suffix", ["blf", "asc", "mf4"])
def test_recorder_writes_each_format_readable_with_its_time_base(tmp_path: Path,
                                                                  suffix: str) -> None:
    frames = lockstep_frames(30, "passive")
    path = tmp_path / f"bus.{suffix}"
    rec = record_over_virtual_bus(path, frames, "ux16-rec-" + suffix)
    read = list(can.LogReader(str(path)))
    assert len(read) == len(frames)
    assert [bytes(m.data) for m in read] == [bytes(f.data) for f in frames]
    t = np.array([m.timestamp for m in read])
    sync = [m.arbitration_id == 0x10F for m in read]
    assert np.allclose(np.diff(t[sync]), PERIOD_S, atol=2e-6)
    assert "simulated time" in rec.time_base
    if suffix == "asc":
        assert rec.time_base in path.read_text()
    if suffix == "mf4":
        from asammdf import MDF

        with MDF(path) as mdf:
            assert "simulated time" in mdf.header.comment


def test_open_writer_rejects_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="use one of"):
        open_writer(tmp_path / "bus.txt")


def _write_blf(frames: list[can.Message], path: Path) -> Path:
    stamper = SimTimeStamper(Codec(), epoch_s=0.0)
    with open_writer(path) as writer:
        for f in frames:
            for m in stamper.feed(f):
                writer.on_message_received(m)
        for m in stamper.flush():
            writer.on_message_received(m)
    return path


def test_replay_infers_the_controller_from_ctrl_status(tmp_path: Path) -> None:
    log = _write_blf(lockstep_frames(80, "lmpc"), tmp_path / "bus.blf")
    result = replay_log(log)
    assert result.controller == "lmpc"
    assert result.bit_identical and len(result.segments) == 1
    assert not replay_log(log, "passive").bit_identical  # a named one is used as given


def test_replay_splits_at_a_controller_restart(tmp_path: Path) -> None:
    log = _write_blf(lockstep_frames(120, "nmpc-rhonn", restart_at=50), tmp_path / "bus.blf")
    result = replay_log(log)
    assert [s.controller for s in result.segments] == ["nmpc-rhonn", "nmpc-rhonn"]
    assert result.bit_identical, result
    assert result.recorded == 120 - 3
