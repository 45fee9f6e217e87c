"""The lockstep bus log is the same for the same run whether the controller's answer reaches
the bus as one atomic burst (the local bus's ``send_many``) or frame by frame (SocketCAN,
python-can's virtual bus), where the plant's next burst can overtake the answer's last
frames: SecOC authenticators carry no ECHO_CYCLE and must still land in their frame's cycle.
"""

from __future__ import annotations

from pathlib import Path

import can

from can_db.codec import Codec
from can_db.secoc import ControllerSecOc, PlantSecOc
from can_db.secoc_keys import load_keys
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode
from harness.run.bus_logger import SimTimeStamper
from plant_sim.node import PlantNode
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation
from tests.recorded import record_over_virtual_bus

CYCLES = 40
#: the controller's frames the plant needs before it goes on (torque and its authenticator)
PLANT_WAITS_FOR = ("WHEEL_TORQUE_CMD", "WHEEL_TORQUE_AUTH")


def secoc_cycles(cycles: int) -> list[tuple[list[can.Message], list[can.Message]]]:
    """(plant burst, controller answer) of each cycle of an in-process lockstep loop with
    SecOC on both sides (test keys)."""
    codec, keys = Codec(), load_keys("ci-test-key")
    plant = PlantNode(Simulation(load_scenario("dlc-paper")), codec,
                      secoc=PlantSecOc(codec, keys, trip=3))
    node = ControllerNode(make_controller("lmpc"), load_vehicle_params(), codec=codec,
                          secoc=ControllerSecOc(codec, keys))
    out = []
    for _ in range(cycles):
        burst = plant.burst()
        answer: list[can.Message] = []
        for msg in burst:
            answer += node.on_frame_lockstep(msg) or []
        out.append((burst, answer))
        plant.advance(None)
    return out


def atomic_order(cycles: list[tuple[list[can.Message], list[can.Message]]]) -> list[can.Message]:
    """Bus order on the local bus: each answer whole, before the next burst."""
    return [m for burst, answer in cycles for m in (*burst, *answer)]


def frame_by_frame_order(cycles: list[tuple[list[can.Message], list[can.Message]]],
                         codec: Codec) -> list[can.Message]:
    """Bus order on SocketCAN at its worst: once the plant has what it waits for, its next
    burst (SYNC and SYNC_AUTH included) goes out before the rest of the answer."""
    waits = {codec.messages[n].frame_id for n in PLANT_WAITS_FOR}
    frames: list[can.Message] = []
    late: list[can.Message] = []
    for burst, answer in cycles:
        frames += burst + late
        cut = max(i for i, m in enumerate(answer) if m.arbitration_id in waits) + 1
        frames += answer[:cut]
        late = answer[cut:]
    return frames + late


def stamped(frames: list[can.Message]) -> list[tuple[float, int, bytes]]:
    stamper = SimTimeStamper(Codec(), epoch_s=0.0)
    out: list[can.Message] = []
    for f in frames:
        out += stamper.feed(can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                        is_extended_id=f.is_extended_id))
    out += stamper.flush()
    return [(round(m.timestamp, 9), m.arbitration_id, bytes(m.data)) for m in out]


def test_authenticators_keep_their_cycle_when_the_answer_is_sent_frame_by_frame() -> None:
    codec = Codec()
    cycles = secoc_cycles(CYCLES)
    atomic, split = atomic_order(cycles), frame_by_frame_order(cycles, codec)
    status_auth = codec.messages["CTRL_STATUS_AUTH"].frame_id
    assert sum(m.arbitration_id == status_auth for m in atomic) == CYCLES
    assert [m.arbitration_id for m in split] != [m.arbitration_id for m in atomic]  # overtaken
    assert sorted(id(m) for m in split) == sorted(id(m) for m in atomic)  # same frames
    assert stamped(split) == stamped(atomic)


def _record(path: Path, frames: list[can.Message], channel: str) -> None:
    """``frames`` sent one by one on a python-can virtual bus (as on SocketCAN), recorded
    by the harness's recorder into ``path``."""
    assert record_over_virtual_bus(path, frames, channel).frames == len(frames)


def test_recorded_log_is_the_same_cycle_by_cycle_for_both_bus_orders(tmp_path: Path) -> None:
    codec = Codec()
    cycles = secoc_cycles(CYCLES)
    _record(tmp_path / "atomic.blf", atomic_order(cycles), "order-atomic")
    _record(tmp_path / "split.blf", frame_by_frame_order(cycles, codec), "order-split")

    def read(path: Path) -> list[tuple[float, int, bytes]]:
        with can.BLFReader(path) as log:
            msgs = list(log)
        t0 = msgs[0].timestamp
        return [(round(m.timestamp - t0, 6), m.arbitration_id, bytes(m.data)) for m in msgs]

    atomic, split = read(tmp_path / "atomic.blf"), read(tmp_path / "split.blf")
    assert len(atomic) == sum(len(b) + len(a) for b, a in cycles)
    assert split == atomic
