"""Every fault reaction of the controller node executed across real OS processes, in lockstep
and with the controller free-running on its own schedule (``--mode realtime
--controller-mode freerun``), plus the counters docs/safety/fault-reactions.md promises for
overload: the local hub's total drop count and SecOC's ``evicted_unverified``.

The reactions (controller/runtime/node.py, docs/user-guide.md "Controller degraded modes"; index in
docs/safety/fault-reactions.md):

* an exception in the core (injected: ``--fault core-exception[:D]@T``,
  controller/runtime/core_fault.py) → FAULT, latched until the controller process restarts:
  the driver's torque Tt = (ACCEL_PEDAL − BRAKE_PEDAL)/100 · 4 · 450 N·m split evenly over the
  four wheels, ΔM = 0, counted once in ``core_exceptions``;
* driver frame lost → DRIVER_LOST_RAMPDOWN: every wheel torque ramps to 0 at 1500 N·m/s,
  i.e. 15 N·m per 10 ms answer; measured here to the torque LSB (0.5 N·m on the wire: a
  difference of two quantised torques is exact to ±0.5 N·m, ±50 N·m/s over one 10 ms cycle).

The driving is the paper DLC with the driver holding a speed ramp (3 km/h per s) on the
accelerator, so the driver's torque is far from 0 (≈ 200 N·m a wheel) and a wrong share of it
(4× the driver's torque, or 0) cannot pass for the right one.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from can_db.codec import Codec
from can_db.faults import parse_fault
from can_db.secoc import PENDING
from can_db.transport.hub import LocalHub
from can_db.transport.localbus import LocalBus
from controller.core.interfaces import QpStatus
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.core_fault import FaultyCore
from controller.runtime.node import ControllerNode, Fault, Mode
from harness.analysis.run_data import RunData, load_run
from harness.report.run_report import run_and_report
from harness.run.hil_bench import route_frame_faults
from harness.run.runner import RunResult
from harness.run.spec import RunSpec
from tests.helpers_proc import live_children, spawn
from tests.test_controller_node import FakePlant, answer, torques

WHEELS = ("FL", "FR", "RL", "RR")
PEAK_TORQUE_NM = 450.0  # per wheel, N·m (DBC comment of WHEEL_TORQUE_CMD)
TORQUE_LSB_NM = 0.5  # WHEEL_TORQUE_CMD TQ_* resolution, N·m
CYCLE_S = 0.01  # communication cycle, s
RAMPDOWN_NM_PER_S = 1500.0  # docs: driver frame lost → every wheel torque ramps to 0 at this
DRIVER_ON_THE_PEDAL = {"speed": "hold", "speed_ramp_kmhps": 3.0}


def run(tmp_path: Path, *faults: str, duration: float, realtime: bool = False,
        params: dict[str, float] | None = None) -> tuple[RunResult, RunData]:
    """A dlc-paper run with the LMPC controller (the reactions are the node's, the same for
    every controller); ``realtime``: the plant paces on the wall clock and the controller
    free-runs on its own 10 ms schedule; ``params``: more scenario parameters."""
    result = run_and_report(RunSpec(
        scenario="dlc-paper", controller="lmpc", out_dir=tmp_path, duration_s=duration,
        mode="realtime" if realtime else "lockstep",
        controller_mode="freerun" if realtime else "lockstep",
        params={**DRIVER_ON_THE_PEDAL, **(params or {})}, faults=list(faults),
        make_plots=False, make_rrd=False))
    assert result.reason == "finished", result.metrics
    assert not live_children()
    return result, load_run(tmp_path)


def summary(tmp_path: Path, who: str) -> dict:
    """``controller_summary.json`` or ``plant_summary.json`` of the run."""
    return json.loads((tmp_path / f"{who}_summary.json").read_text())


def answers(data: RunData) -> dict[str, np.ndarray]:
    """The controller's answers in the order they were sent while the plant ran (up to the
    last SYNC on the bus: a free-running controller goes on ticking after the plant has
    finished, and then loses its driver frame): cycle echoed, MODE, FAULT_BITS, the four
    wheel torques (N·m) and the sim time of the SYNC echoed (s), one row per answer. A
    torque frame and a status frame go out together in every answer, so the i-th of each
    belong together."""
    tq, st = data.bus["WHEEL_TORQUE_CMD"], data.bus["CTRL_STATUS"]
    assert len(tq["cycle"]) == len(st["cycle"]) > 0
    assert np.array_equal(tq["cycle"], st["cycle"])
    keep = np.asarray(tq["t_log"]) <= np.asarray(data.bus["SYNC"]["t_log"])[-1]
    return {"cycle": np.asarray(tq["cycle"], dtype=int)[keep],
            "mode": np.asarray(st["MODE"], dtype=int)[keep],
            "bits": np.asarray(st["FAULT_BITS"], dtype=int)[keep],
            "qp": np.asarray(st["QP_STATUS"], dtype=int)[keep],
            "torques": np.column_stack([tq[f"TQ_{w}"] for w in WHEELS]).astype(float)[keep],
            "sim_time_s": np.asarray(tq["sim_time_s"], dtype=float)[keep]}


def driver_torque_per_wheel(data: RunData) -> dict[int, float]:
    """Cycle → the driver's torque split evenly, N·m a wheel, from the DRIVER_INPUTS frame
    of that cycle as it went over the bus: (ACCEL − BRAKE)/100 · 4 · 450 / 4."""
    drv = data.bus["DRIVER_INPUTS"]
    per_wheel = (np.asarray(drv["ACCEL_PEDAL"]) - np.asarray(drv["BRAKE_PEDAL"])) / 100.0 \
        * PEAK_TORQUE_NM
    return {int(c): float(t) for c, t in zip(drv["cycle"], per_wheel, strict=True)}


def assert_safe_fault_torques(ans: dict[str, np.ndarray], rows: np.ndarray,
                              driver: dict[int, float], lag_cycles: int = 0) -> None:
    """In every answer of ``rows`` the four torques are the driver's torque split evenly:
    equal to each other and to Tt/4 of the cycle answered (± the torque LSB). With
    ``lag_cycles`` (free-running) the driver frame may be up to that many cycles newer than
    the SYNC echoed."""
    assert rows.size > 0
    for i in rows:
        tq = ans["torques"][i]
        c = int(ans["cycle"][i])
        wanted = [driver[k] for k in range(c, c + lag_cycles + 1) if k in driver]
        assert wanted, f"no driver frame for cycle {c}"
        err = min(np.max(np.abs(tq - w)) for w in wanted)
        assert err <= TORQUE_LSB_NM, (c, tq.tolist(), wanted)


# ------------------------------------------------------------------- exception in the core
def test_core_exception_spec_and_its_way_to_the_controller(tmp_path: Path) -> None:
    """``core-exception[:D][@T]``: without D to the end of the run; the harness hands it to
    the controller process (``--fault``), never to the plant or its own process faults."""
    spec = parse_fault("core-exception@2s")
    assert (spec.at_s, spec.amount, spec.is_core_fault, spec.is_frame_fault) \
        == (2.0, float("inf"), True, False)
    assert parse_fault("core-exception:100ms@2s").amount == pytest.approx(0.1)
    plant_faults, ctrl_faults = route_frame_faults([spec, parse_fault("loss:1%")], Codec(),
                                                   lockstep=True)
    assert ctrl_faults == ["core-exception@2s", "loss:1%"]
    assert plant_faults == ["loss:1%"]


def test_node_latches_fault_and_ramps_down_without_the_driver_frame_in_between() -> None:
    """In-process, frame by frame: the core raises for 50 ms from 1 s; FAULT (driver torque
    0.3 · 4 · 450 / 4 = 135 N·m a wheel) stays after the window; without the driver frame the
    torques ramp down (15 N·m a cycle) and FAULT returns with the frame."""
    plant = FakePlant()
    core = FaultyCore(make_controller("lmpc"), [parse_fault("core-exception:50ms@1s")])
    node = ControllerNode(core, load_vehicle_params(), codec=Codec())  # type: ignore[arg-type]
    core.bind(lambda: node.record.sim_time_s)
    for _ in range(100):
        answer(node, plant.burst())
    assert node.mode is Mode.ACTIVE
    for _ in range(50):  # 1.00 .. 1.49 s
        frames = answer(node, plant.burst())
        assert frames["CTRL_STATUS"].values["MODE"] == Mode.FAULT
        np.testing.assert_allclose(torques(frames), 135.0, atol=TORQUE_LSB_NM)
    lost = [torques(answer(node, plant.burst(drop=("DRIVER_INPUTS",))))[0] for _ in range(6)]
    assert node.mode is Mode.DRIVER_LOST_RAMPDOWN
    assert lost[:3] == [135.0] * 3  # driver frame still valid (30 ms timeout) → FAULT
    assert lost[3:] == [120.0, 105.0, 90.0]
    frames = answer(node, plant.burst())
    assert frames["CTRL_STATUS"].values["MODE"] == Mode.FAULT
    np.testing.assert_allclose(torques(frames), 135.0, atol=TORQUE_LSB_NM)
    assert node.controller_exceptions == 1 and core.raised == 1


def test_core_exception_in_lockstep_latches_fault_with_the_driver_torque_split_evenly(
        tmp_path: Path) -> None:
    # the core raises for 100 ms from 2 s; FAULT stays latched after that window has closed
    result, data = run(tmp_path, "core-exception:100ms@2s", duration=3.0)
    ans = answers(data)
    cycles, modes = ans["cycle"], ans["mode"]
    assert np.array_equal(cycles, np.arange(cycles.size))  # lockstep: every cycle answered
    fault = modes == Mode.FAULT
    assert not fault[cycles < 200].any()
    assert np.all(modes[(cycles >= 5) & (cycles < 200)] == Mode.ACTIVE)
    # detected in the very cycle the core raised (SIM_TIME 2.00 s = cycle 200), and latched:
    # every answer to the end of the run (0.9 s after the injected window) says FAULT
    assert fault[cycles >= 200].all() and cycles[-1] >= 290
    # status: no optimiser result (QP failed, solver-fallback bit)
    assert np.all(ans["qp"][fault] == QpStatus.FAILED)
    assert np.all(ans["bits"][fault] & (1 << Fault.SOLVER_FALLBACK))
    # the safe torques: the driver's, split evenly (not 4× it, not 0, no yaw moment)
    driver = driver_torque_per_wheel(data)
    assert_safe_fault_torques(ans, np.flatnonzero(fault), driver)
    assert driver[200] > 100.0  # the driver is on the pedal when the core raises
    refs = data.bus["CTRL_REFS"]
    assert np.all(np.abs(np.asarray(refs["DELTA_M"])[np.asarray(refs["cycle"]) >= 200])
                  <= TORQUE_LSB_NM)
    # the plant applied every one of them (authenticated, valid)
    t_cycle, valid = data.truth_col("cycle"), data.truth_col("cmd_valid")
    assert np.all(valid[t_cycle >= 200] == 1) and result.metrics["fallback_events"] == 0
    for w, k in zip(WHEELS, range(4), strict=True):
        applied = data.truth_col(f"tcmd_{w.lower()}")
        sent = dict(zip(cycles.tolist(), ans["torques"][:, k].tolist(), strict=True))
        for c in range(200, 290):  # the answer to SYNC c acts from c to c + 1
            assert applied[np.flatnonzero(t_cycle == c + 1)[0]] == pytest.approx(sent[c],
                                                                                 abs=1e-6)
    # counted: one exception (the core is not stepped again while latched), one injected
    ctrl = summary(tmp_path, "controller")
    assert ctrl["core_exceptions"] == 1 and ctrl["injected"]["core-exception"] == 1


def test_core_exception_in_the_free_running_controller_latches_fault_too(
        tmp_path: Path) -> None:
    # real time: the plant paces on the wall clock, the controller answers on its own 10 ms
    # schedule (on_frame/tick) and the core raises from 1.5 s of simulated time on
    _, data = run(tmp_path, "core-exception@1.5s", duration=2.5, realtime=True)
    ans = answers(data)
    cycles, modes = ans["cycle"], ans["mode"]
    fault = modes == Mode.FAULT
    assert fault.any()
    first = int(np.argmax(fault))
    # never before the SYNC of 1.5 s was answered; within 10 cycles of it (wall-clock slack
    # of a loaded machine: the node answers the latest SYNC it has, once per tick)
    assert 150 <= cycles[first] <= 160, cycles[first]
    # latched to the end: FAULT in every later answer but those in which the driver frame
    # had timed out (a late plant burst on a loaded machine): those ramp down, as documented
    later = ans["mode"][first:]
    lost = later == Mode.DRIVER_LOST_RAMPDOWN
    assert np.all((later == Mode.FAULT) | lost)
    assert np.all(ans["bits"][first:][lost] & (1 << Fault.DRIVER_INVALID))
    assert np.count_nonzero(fault) >= 50  # ≥ 0.5 s of answers in FAULT
    # the driver frame a tick used may already be one of the burst after the SYNC it echoes
    assert_safe_fault_torques(ans, np.flatnonzero(fault), driver_torque_per_wheel(data),
                              lag_cycles=1)
    ctrl = summary(tmp_path, "controller")
    assert ctrl["core_exceptions"] == 1 and ctrl["injected"]["core-exception"] == 1


# ------------------------------------------------------------------ driver frame ramp-down
def _rampdown_steps(ans: dict[str, np.ndarray], fault_cycle: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The first unbroken run of answers in DRIVER_LOST_RAMPDOWN echoing ``fault_cycle`` or a
    later one, plus the answer before it (the torque the ramp starts from): their indices and
    |torque| per wheel, N·m."""
    ramp = (ans["mode"] == Mode.DRIVER_LOST_RAMPDOWN) & (ans["cycle"] >= fault_cycle)
    assert ramp.any()
    start = int(np.argmax(ramp))
    end = ramp.size if ramp[start:].all() else start + int(np.argmin(ramp[start:]))
    seg = np.arange(start - 1, end)
    assert np.all(ans["bits"][seg[1:]] & (1 << Fault.DRIVER_INVALID))
    return seg, np.abs(ans["torques"][seg])


def assert_ramp_rate(mag: np.ndarray, per_answer_nm: float,
                     exempt: np.ndarray | None = None) -> int:
    """Each wheel's |torque| falls by ``per_answer_nm`` per answer (± the torque LSB) down to
    the last step, which goes straight to 0 from ≤ ``per_answer_nm``; 0 from then on.
    ``exempt[j]``: the step from answer j to j + 1 is not measured (the caller checks it
    otherwise). Returns the number of full steps measured."""
    full = 0
    for k in range(4):
        m = mag[:, k]
        zero = np.flatnonzero(m == 0.0)
        assert zero.size > 0, f"wheel {WHEELS[k]} never reached 0: {m.tolist()}"
        end = int(zero[0])
        assert np.all(m[end:] == 0.0)
        steps = -np.diff(m[: end + 1])
        measured = np.ones(steps.size - 1, bool) if exempt is None else ~exempt[: steps.size - 1]
        assert np.all(np.abs(steps[:-1][measured] - per_answer_nm) <= TORQUE_LSB_NM), \
            (WHEELS[k], steps.tolist())
        assert 0.0 < steps[-1] <= per_answer_nm + TORQUE_LSB_NM
        full += int(measured.sum())
    return full


def test_lost_driver_frame_ramps_every_wheel_down_at_1500_nm_per_s(tmp_path: Path) -> None:
    _, data = run(tmp_path, "burst:1s,DRIVER_INPUTS@2s", duration=3.0)
    ans = answers(data)
    seg, mag = _rampdown_steps(ans, 200)
    # detected at the rx timeout: 3 cycles without the frame (docs: ≤ 3 cycles)
    assert 200 <= ans["cycle"][seg[1]] <= 203
    assert mag[0].min() > 90.0  # a ramp long enough to measure (≥ 6 steps on every wheel)
    # the rate in N·m/s on simulated time: the sim time of each answer from its SYNC
    t = ans["sim_time_s"][seg]
    np.testing.assert_allclose(np.diff(t), CYCLE_S, atol=1e-9)  # consecutive cycles
    full = assert_ramp_rate(mag, RAMPDOWN_NM_PER_S * CYCLE_S)
    assert full >= 24
    for k in range(4):  # a least-squares slope over the whole ramp: 1500 N·m/s ± 1 LSB
        m = mag[:, k]
        nz = np.flatnonzero(m > 0.0)
        slope = -np.polyfit(t[nz], m[nz], 1)[0]
        span = t[nz[-1]] - t[nz[0]]
        assert abs(slope - RAMPDOWN_NM_PER_S) <= TORQUE_LSB_NM / span, (WHEELS[k], slope)
    # the plant applied the ramp (truth trace: the answer to SYNC c acts from c to c + 1)
    t_cycle = data.truth_col("cycle")
    for k, w in enumerate(WHEELS):
        applied = data.truth_col(f"tcmd_{w.lower()}")
        for i in seg[1:]:
            row = np.flatnonzero(t_cycle == ans["cycle"][i] + 1)[0]
            assert applied[row] == pytest.approx(ans["torques"][i, k], abs=1e-6)


def test_lost_driver_frame_ramps_down_15_nm_per_answer_in_the_free_running_controller(
        tmp_path: Path) -> None:
    # the ramp is per answer: 15 N·m every tick of the node's own 10 ms schedule
    _, data = run(tmp_path, "burst:1s,DRIVER_INPUTS@1s", duration=2.5, realtime=True)
    ans = answers(data)
    seg, mag = _rampdown_steps(ans, 100)
    assert mag[0].min() > 90.0
    # On the wall clock a loaded machine can delay a sensor frame past its timeout. An
    # answer without valid sensors has ΔM = 0 from the output guard (total torque kept), which
    # moves each wheel by ±ΔM/4 on top of the ramp: that step is checked as ΔM = 0 instead.
    no_sensors = (ans["bits"][seg] & (1 << Fault.SENSORS_INVALID)) != 0
    dm = ans["torques"][seg] @ np.array([-1.0, 1.0, -1.0, 1.0])  # ΔM = FR + RR − FL − RL, N·m
    assert np.all(np.abs(dm[no_sensors]) <= 2 * TORQUE_LSB_NM)
    assert assert_ramp_rate(mag, RAMPDOWN_NM_PER_S * CYCLE_S, exempt=no_sensors[1:]) >= 24


# ------------------------------------------------------------------ function disabled
def test_stability_function_disabled_is_standby_without_yaw_moment(tmp_path: Path) -> None:
    # STAB_ENABLE = 0 until 1 s (the scenario's stab_enable_after_s), then 1
    _, data = run(tmp_path, duration=1.5, params={"stab_enable_after_s": 1.0})
    ans = answers(data)
    cycles, modes = ans["cycle"], ans["mode"]
    assert np.all(modes[(cycles >= 5) & (cycles < 100)] == Mode.STANDBY)
    assert np.all(modes[cycles >= 100] == Mode.ACTIVE)
    dm = ans["torques"] @ np.array([-1.0, 1.0, -1.0, 1.0])  # ΔM = FR + RR − FL − RL, N·m
    assert np.all(np.abs(dm[cycles < 100]) <= 2 * TORQUE_LSB_NM)
    assert np.abs(dm[cycles >= 100]).max() > 50.0  # the function acts once enabled


# ------------------------------------------------------------- free-running: own schedule
def test_free_running_controller_answers_on_its_own_schedule_without_sync(
        tmp_path: Path) -> None:
    # 300 ms without SYNC frames: a SYNC-driven controller would send nothing; the
    # free-running one keeps answering every tick, echoing the last SYNC it had, and says so
    _, data = run(tmp_path, "burst:300ms,SYNC@1s", duration=2.0, realtime=True)
    ans = answers(data)
    cycles = ans["cycle"]
    values, counts = np.unique(cycles[cycles >= 0], return_counts=True)  # -1: before SYNC 0
    held = int(values[np.argmax(counts)])
    assert 95 <= held <= 100  # the last SYNC before the gap
    repeats = np.flatnonzero(cycles == held)
    assert repeats.size >= 10  # ≥ 10 answers of its own (30 at 10 ms) during 300 ms
    assert np.any(ans["bits"][repeats] & (1 << Fault.SYNC_LOST))
    assert cycles[-1] > held + 30  # and it answers the SYNCs again after the gap


# ------------------------------------------------------------------- overload counters
@pytest.fixture
def private_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fresh runtime dir for the local bus (children inherit it through the environment)."""
    path = tmp_path / "rt"
    monkeypatch.setenv("RHONN_CAN_DIR", str(path))
    yield path


SLEEPER = """
import sys, time
from can_db.transport.localbus import LocalBus
bus = LocalBus("unit", node_name="sleeper", autostart=False)
print("ready", flush=True)
sys.stdin.read()  # never reads the bus; leaves when the test closes stdin
bus.shutdown()
"""


def test_hub_total_drop_count_is_every_frame_a_full_node_queue_lost(
        private_dir: Path, tmp_path: Path) -> None:
    """A node in another process that never reads, behind a 4 KiB queue: the hub (its own
    process) drops what does not fit and counts it, per node and in its total."""
    stats = tmp_path / "hub.json"
    n = 3000
    with LocalHub("unit", stats_path=stats, queue_kib=4):
        sleeper = spawn("-c", SLEEPER, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        try:
            assert sleeper.stdout is not None and sleeper.stdout.readline().startswith("ready")
            sender = LocalBus("unit", node_name="sender", autostart=False)
            reader = LocalBus("unit", node_name="reader", autostart=False)
            try:
                received = 0
                for k in range(n):
                    sender.send(can.Message(arbitration_id=0x300, data=k.to_bytes(4, "little"),
                                            is_extended_id=False))
                    while received <= k:  # the reader keeps up
                        msg = reader.recv(5.0)
                        assert msg is not None, f"reader lost frame {received}"
                        received += 1
            finally:
                sender.shutdown()
                reader.shutdown()
        finally:
            assert sleeper.stdin is not None
            sleeper.stdin.close()
            assert sleeper.wait(timeout=30) == 0
    hub = json.loads(stats.read_text())
    nodes = {node["name"]: node for node in hub["nodes"]}
    lost = n - nodes["sleeper"]["frames_out"]
    assert nodes["sleeper"]["dropped"] == lost > n // 2  # 4 KiB hold far fewer than 3000
    assert nodes["reader"]["dropped"] == 0 and nodes["reader"]["frames_out"] == n
    assert hub["frames"] == n
    assert hub["dropped"] == sum(node["dropped"] for node in hub["nodes"]) == lost


def test_secoc_counts_status_frames_evicted_without_their_authenticator(
        tmp_path: Path) -> None:
    """500 ms of CTRL_STATUS frames without their authenticators: the plant's SecOC
    receiver keeps the newest PENDING of them unverified and evicts the rest, counted in
    ``evicted_unverified``; the torque frames still verify, so control goes on."""
    result, _ = run(tmp_path, "burst:500ms,CTRL_STATUS_AUTH@2s", duration=3.0)
    dropped = summary(tmp_path, "controller")["injected"]["burst"]
    assert dropped == 50  # one authenticator per 10 ms cycle from 2.00 to 2.49 s
    secoc = summary(tmp_path, "plant")["secoc"]
    # every status frame of the gap is rejected unauthenticated; all but the newest
    # PENDING - 1 are evicted from the full pending queue (the first status frame after the
    # gap pushes out one more, and its authenticator then clears the rest)
    assert secoc["rejected"]["unauthenticated"] == dropped
    assert secoc["evicted_unverified"] == dropped - (PENDING - 1)
    assert result.metrics["fallback_events"] == 0
