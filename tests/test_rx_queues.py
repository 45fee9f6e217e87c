"""Bounded rx queues (docs/safety/queues.md): every queue a received frame can wait in has a
bound, a drop policy and a counter per drop reason.

Unit tests check each bound and counter exactly; the tests across processes flood a real
lockstep controller process and a real plant process over the local bus (hub process) and
check that memory stays flat, the next SYNC is answered within the plant's lockstep wait
(200 ms, its own deadline) and the drops are counted in the summaries.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import threading
import time
from pathlib import Path

import can
import pytest

from can_db.codec import Codec, Decoded, MessageSpec, Transmitter
from can_db.secoc import PENDING, ControllerSecOc
from can_db.secoc_keys import load_keys
from can_db.transport.bus import open_bus
from can_db.transport.hub import LocalHub
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import (
    BURST_CYCLES,
    BURST_FULL,
    MONITORED,
    ControllerNode,
    Fault,
    burst_bound,
)
from harness.run.flood import END_MARKER_ID, END_MARKERS
from plant_sim import process as plant_process
from tests.helpers_proc import interrupt_and_wait, live_children, spawn

CODEC = Codec()
LOCKSTEP_WAIT_S = 0.2  # the plant's lockstep wait for an answer (rhonn-plant --wait-ms 200)
RSS_GROWTH_MAX_KB = 16 * 1024
MOTION = CODEC.messages["MOTION_SENSORS"].frame_id
TORQUE = CODEC.messages["WHEEL_TORQUE_CMD"].frame_id
SYNC_ID = CODEC.messages["SYNC"].frame_id


def _node(secoc: ControllerSecOc | None = None) -> ControllerNode:
    return ControllerNode(make_controller("passive"), load_vehicle_params(), secoc=secoc)


def _burst(tx: Transmitter, cycle: int) -> list[can.Message]:
    """One plant burst of cycle ``cycle`` (car at 20 m/s, pedal 10 %), SYNC last."""
    return [
        tx.message("DRIVER_INPUTS", {"SWA": 0.0, "ACCEL_PEDAL": 10.0, "BRAKE_PEDAL": 0.0,
                                     "STAB_ENABLE": 1.0}),
        tx.message("MOTION_SENSORS", {"YAW_RATE": 0.01 * (cycle % 7), "AX": 0.0, "AY": 0.0}),
        tx.message("WHEEL_SPEEDS", {f"WS_{w}": 60.0 for w in ("FL", "FR", "RL", "RR")}),
        tx.message("VEHICLE_EST", {"VX_EST": 20.0, "VY_EST": 0.002 * (cycle % 5)}),
        tx.message("SYNC", {"CYCLE": float(cycle), "SIM_TIME": cycle * 0.01}),
    ]


def _status(frames: list[can.Message]) -> Decoded:
    status = next(CODEC.decode_message(f) for f in frames
                  if f.arbitration_id == CODEC.messages["CTRL_STATUS"].frame_id)
    assert isinstance(status, Decoded)
    return status


def _run_cycle(node: ControllerNode, tx: Transmitter, cycle: int,
               extra: list[can.Message] = ()) -> list[can.Message]:
    """Feed a burst with ``extra`` frames before its SYNC; the node's answer."""
    frames = _burst(tx, cycle)
    answer = None
    for msg in [*frames[:-1], *extra, frames[-1]]:
        answer = node.on_frame_lockstep(msg)
    assert answer is not None
    return answer


# ------------------------------------------------------------------------------ unit tests
def test_burst_bound_comes_from_the_dbc_cycle_times() -> None:
    for name in MONITORED:
        if name != "SYNC":
            assert burst_bound(CODEC.messages[name], 0.01) == BURST_CYCLES == 3
    fast = MessageSpec(name="X", frame_id=1, length=8, cycle_time_s=0.005, senders=(),
                       signals=())
    assert burst_bound(fast, 0.01) == 2 * BURST_CYCLES  # two frames a cycle
    none = MessageSpec(name="Y", frame_id=2, length=8, cycle_time_s=0.0, senders=(),
                       signals=())
    assert burst_bound(none, 0.01) == BURST_CYCLES


def test_valid_frames_between_syncs_keep_the_newest_three_and_count_every_drop() -> None:
    node, tx = _node(), Transmitter(CODEC)
    for k in range(5):
        status = _status(_run_cycle(node, tx, k))
        assert not int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
    flood = [tx.message("MOTION_SENSORS", {"YAW_RATE": 0.0, "AX": 0.0, "AY": 0.0})
             for _ in range(20)]
    frames = _burst(tx, 5)
    for msg in [*frames[:-1], *flood]:
        assert node.on_frame_lockstep(msg) is None
    assert [len(q) for q in node._burst.values()] == [1, 3, 1, 1]
    # 21 MOTION_SENSORS frames in the cycle (the burst's and 20 more), 3 kept
    assert node.rx_drops == {BURST_FULL: 18}
    jumps = node.monitor.counts["counter_jump"]
    status = _status(node.on_frame_lockstep(frames[-1]))
    assert int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
    # the newest three were validated: one gap in the alive counter (18 frames lost)
    assert node.monitor.counts["counter_jump"] == jumps + 1
    assert node.monitor.latest("MOTION_SENSORS").values["YAW_RATE"] == 0.0  # the newest
    assert node.rx_overload_cycles == 1
    status = _status(_run_cycle(node, tx, 6))  # no drop in this cycle: bit 7 clear again
    assert not int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
    assert node.rx_drop_counts() == {BURST_FULL: 18} and node.rx_overload_cycles == 1


def test_a_sync_less_flood_of_300k_valid_frames_holds_three_per_id() -> None:
    node, tx = _node(), Transmitter(CODEC)
    _run_cycle(node, tx, 0)
    names = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")
    proto = {n: tx.message(n, {s.name: 0.0 for s in CODEC.messages[n].signals})
             for n in names}
    for i in range(300_000):
        node.on_frame_lockstep(proto[names[i % 4]])
    assert [len(q) for q in node._burst.values()] == [3, 3, 3, 3]
    assert node.rx_drops[BURST_FULL] == 300_000 - 12
    start = time.perf_counter()
    answer = node.on_frame_lockstep(_burst(tx, 1)[-1])
    elapsed = time.perf_counter() - start
    assert answer is not None and elapsed < LOCKSTEP_WAIT_S  # 12 frames validated, not 300k


def test_malformed_and_unmonitored_frames_are_counted_on_arrival_and_never_buffered() -> None:
    node, tx = _node(), Transmitter(CODEC)
    _run_cycle(node, tx, 0)
    short = can.Message(arbitration_id=MOTION, data=b"\x01\x02\x03", is_extended_id=False)
    refs = tx.message("CTRL_REFS", {"DELTA_M": 0.0, "YAW_RATE_REF": 0.0, "BETA_REF": 0.0,
                                    "ECHO_CYCLE": 0.0})
    ignored = node.monitor.ignored
    for _ in range(1000):
        node.on_frame_lockstep(short)
        node.on_frame_lockstep(refs)
    assert node.monitor.counts["wrong_length"] == 1000  # counted before any SYNC
    assert node.monitor.ignored == ignored + 1000
    assert all(len(q) == 0 for q in node._burst.values())
    status = _status(_run_cycle(node, tx, 1))
    assert node.rx_drops == {BURST_FULL: 0}
    assert not int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
    assert int(status.values["MODE"]) == 1  # ACTIVE: the flood had no effect on control


def test_secoc_pending_evictions_are_rx_drops_and_set_rx_overload() -> None:
    secoc = ControllerSecOc(Codec(), load_keys("ci-test-key"))
    node = _node(secoc)
    sync = CODEC.messages["SYNC"]
    forged = Transmitter(CODEC).message("SYNC", {"CYCLE": 1.0, "SIM_TIME": 0.01})
    for _ in range(PENDING + 25):  # unauthenticated SYNC frames: 16 kept, 25 evicted
        node.on_frame_lockstep(forged)
    assert len(secoc.receiver.streams[sync.frame_id].pending) == PENDING
    assert node.rx_drop_counts() == {BURST_FULL: 0, "secoc_pending_full": 25}
    node.last_sync = None
    node._answer(0.0)
    assert node.record.fault_bits & (1 << Fault.RX_OVERLOAD)
    node._answer(0.01)
    assert not node.record.fault_bits & (1 << Fault.RX_OVERLOAD)


def test_recorder_time_order_heap_is_bounded_without_sync() -> None:
    from harness.run.bus_logger import MAX_HELD, SimTimeStamper

    stamper = SimTimeStamper(CODEC, epoch_s=0.0)
    tx = Transmitter(CODEC)
    written = sum(len(stamper.feed(m)) for m in _burst(tx, 0))  # one cycle: SYNC seen
    flood = can.Message(arbitration_id=0x3A0, data=bytes(8), is_extended_id=False)
    written += sum(len(stamper.feed(flood)) for _ in range(10_000))
    assert len(stamper._out) == MAX_HELD  # the heap holds the newest MAX_HELD
    assert stamper.released_early == 10_000 + 5 - MAX_HELD
    assert written == stamper.released_early  # every frame is written, none dropped
    assert written + len(stamper.flush()) == 10_005


class _EndlessBus:
    """A bus that always has one more (flood) frame; it fails the test after ``limit``
    reads, which only an rx loop without a bound reaches."""

    def __init__(self, limit: int) -> None:
        self.reads, self.limit = 0, limit
        self.frame = can.Message(arbitration_id=TORQUE, data=b"\x00\x00\x00",
                                 is_extended_id=False)

    def recv(self, timeout: float | None = None) -> can.Message:
        self.reads += 1
        assert self.reads < self.limit, "the lockstep wait never ended under the flood"
        return self.frame

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        pass


def test_plant_lockstep_wait_ends_under_an_endless_flood() -> None:
    sim = plant_process.check_scenario("constant-radius", None, None, {})
    node = plant_process.PlantNode(sim)
    bus = _EndlessBus(limit=200_000)
    stats = {"lockstep_timeouts": 0, "waits_cut_by_flood": 0}
    args = argparse.Namespace(wait_ms=1.0, lost_after=3, reconnect_s=0.0, duration=0.05)
    trace = plant_process.TraceWriter(None, [])
    reason = plant_process._run_lockstep(bus, node, trace, args, stats, lambda: False)
    assert reason == "finished" and sim.cycle == 5
    assert stats["waits_cut_by_flood"] == 5 and stats["lockstep_timeouts"] == 5
    assert node.fallback_cycles == 5
    assert node.monitor.counts["wrong_length"] == bus.reads


# ------------------------------------------------------------------- across processes
def _rss_kb(pid: int) -> int:
    """VmRSS of process ``pid``, kB (/proc/PID/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for {pid}")


def _start(err: Path, *args: str) -> subprocess.Popen[str]:
    """``python -m ...`` as a child with its stdout piped, stderr to ``err`` (stacks on a hang
    at shutdown: PYTHONFAULTHANDLER)."""
    with open(err, "w") as f:  # the child has its own copy of the descriptor
        return spawn(*args, stdout=subprocess.PIPE, stderr=f,
                     env={**os.environ, "PYTHONFAULTHANDLER": "1"})


def _wait_ready(proc, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("ready"):
            return
        if not line and proc.poll() is not None:
            raise AssertionError(f"{what} exited with {proc.returncode}")
    raise AssertionError(f"{what} not ready within {timeout_s} s")


def _hub_dropped(stats_path: Path, pid: int) -> int:
    stats = json.loads(stats_path.read_text())
    return sum(n["dropped"] for n in stats["nodes"] if n["name"].endswith(f":{pid}"))


class _Listener(threading.Thread):
    """A bus node reading every frame in a thread: counts SYNC frames seen after the flood's
    end marker (the plant has then read every flood frame: it sends a burst only after
    reading the answer to the previous one, which the hub forwarded after the marker)."""

    def __init__(self, spec: str) -> None:
        super().__init__(daemon=True)
        self.bus = open_bus(spec)
        self.syncs_after_marker: int | None = None
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.is_set():
            msg = self.bus.recv(timeout=0.1)
            if msg is None:
                continue
            if msg.arbitration_id == END_MARKER_ID and self.syncs_after_marker is None:
                self.syncs_after_marker = 0
            elif msg.arbitration_id == SYNC_ID and self.syncs_after_marker is not None:
                self.syncs_after_marker += 1

    def wait_syncs_after_marker(self, n: int, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while (self.syncs_after_marker or 0) < n:
            assert time.monotonic() < deadline, f"{self.syncs_after_marker} SYNCs after marker"
            time.sleep(0.02)

    def close(self) -> None:
        self._done.set()
        self.join(timeout=5.0)
        self.bus.shutdown()


def _resend_marker_until_seen(spec: str, listener: _Listener, timeout_s: float = 10.0) -> None:
    """The flood's own end markers (10 in 200 ms) can all be dropped for a listener that a
    loaded machine starved while its queue at the hub was full of flood frames; the flood
    process has ended, so a marker sent now still follows every flood frame."""
    if listener.syncs_after_marker is not None:
        return
    bus = open_bus(spec)
    try:
        marker = can.Message(arbitration_id=END_MARKER_ID, data=b"", is_extended_id=False)
        deadline = time.monotonic() + timeout_s
        while listener.syncs_after_marker is None and time.monotonic() < deadline:
            bus.send(marker)
            time.sleep(0.1)
    finally:
        bus.shutdown()


class _Driver:
    """The test process as the plant of a lockstep controller: sends bursts, times answers."""

    def __init__(self, spec: str) -> None:
        self.bus = open_bus(spec)
        self.tx = Transmitter(CODEC)
        self.cycle = 0
        self.marker_seen = False  # the flood's end marker: every flood frame was forwarded

    def _read(self, timeout: float) -> can.Message | None:
        msg = self.bus.recv(timeout=timeout)
        if msg is not None and msg.arbitration_id == END_MARKER_ID:
            self.marker_seen = True
        return msg

    def drain(self) -> None:
        """Read what is queued (the flood's frames), so our own queue at the hub stays short."""
        while self._read(0.0) is not None:
            pass

    def wait_marker(self, timeout_s: float = 30.0) -> None:
        """Until the flood's end marker: the hub has forwarded every flood frame by then, to
        the controller too, so the next SYNC reaches it after all of them."""
        deadline = time.monotonic() + timeout_s
        while not self.marker_seen:
            assert time.monotonic() < deadline, "no end marker from the flood"
            self._read(0.1)

    def cycle_latency(self, timeout_s: float = 5.0) -> tuple[float, Decoded]:
        """Send the next burst; seconds from its SYNC to the answer's status frame, and the
        status (frames of an earlier cycle are skipped)."""
        self.drain()  # the flood's frames read so far
        frames = _burst(self.tx, self.cycle)
        echo = self.cycle % 256
        self.cycle += 1
        self.bus.send_many(frames)
        sent = time.perf_counter()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self._read(0.5)
            if msg is None or msg.arbitration_id != CODEC.messages["CTRL_STATUS"].frame_id:
                continue
            status = CODEC.decode_message(msg)
            if isinstance(status, Decoded) and int(status.values["ECHO_CYCLE"]) == echo:
                return time.perf_counter() - sent, status
        raise AssertionError(f"no answer to cycle {self.cycle - 1} within {timeout_s} s")


def _children_now() -> set[int]:
    """PIDs of this test process's live descendants (an earlier test's detached hub may
    still be idling out: only the processes a test started are its to clean up)."""
    return {p.pid for p in live_children()}


def _new_children(before: set[int]) -> list[int]:
    """Live descendants that were not there when the test began."""
    return [p.pid for p in live_children() if p.pid not in before]


def _flood(spec: str, seconds: float, rate: float, kind: str, *messages: str) -> int:
    """Run the flood process to its end; frames it sent."""
    args = ["-m", "harness.run.flood", "--bus", spec, "--rate", str(rate), "--kind", kind,
            "--duration", str(seconds), "--end-marker"]
    for m in messages:
        args += ["--message", m]
    proc = spawn(*args, stdout=-1)
    out, _ = proc.communicate(timeout=seconds + 60)
    assert proc.returncode == 0, out
    return int(out.split("flood sent ")[1].split()[0])


def test_local_bus_node_holds_one_received_packet_at_most() -> None:
    """The node's own rx buffer is refilled only when empty: ≤ MAX_BATCH − 1 frames wait."""
    from can_db.transport.localbus import MAX_BATCH

    with LocalHub() as hub:
        a, b = open_bus(hub.spec), open_bus(hub.spec)
        try:
            frame = can.Message(arbitration_id=0x3A0, data=bytes(8), is_extended_id=False)
            a.send_many([frame] * 200)  # packets of 64, 64, 64 and 8 frames
            peak = 0
            for _ in range(200):
                assert b.recv(timeout=5.0) is not None
                peak = max(peak, len(b._rx))
            assert peak == MAX_BATCH - 1 and len(b._rx) == 0
        finally:
            a.shutdown()
            b.shutdown()


@pytest.mark.parametrize("syncs_during_flood", [True, False], ids=["between-syncs", "no-sync"])
def test_lockstep_controller_process_stays_flat_under_a_valid_id_flood(
        tmp_path: Path, syncs_during_flood: bool) -> None:
    before = _children_now()
    stats_path = tmp_path / "hub.json"
    summary = tmp_path / "controller_summary.json"
    with LocalHub(stats_path=stats_path) as hub:
        ctrl = _start(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                      hub.spec, "--controller", "passive", "--mode", "lockstep", "--summary",
                      str(summary), "--no-secoc")  # the test's bursts are unauthenticated
        try:
            _wait_ready(ctrl, "controller")
            driver = _Driver(hub.spec)
            for _ in range(50):
                driver.cycle_latency()
            rss0 = _rss_kb(ctrl.pid)
            seconds, rate = 3.0, 20_000.0
            flood = spawn("-m", "harness.run.flood", "--bus", hub.spec, "--rate", str(rate),
                          "--kind", "valid", "--message", "MOTION_SENSORS", "--duration",
                          str(seconds), "--end-marker", stdout=-1)
            syncs, overloaded = 0, 0
            while flood.poll() is None:
                if syncs_during_flood:
                    _, status = driver.cycle_latency()
                    syncs += 1
                    overloaded += bool(int(status.values["FAULT_BITS"])
                                       & (1 << Fault.RX_OVERLOAD))
                else:
                    driver.drain()
                time.sleep(0.05)
            out, _ = flood.communicate(timeout=30)
            sent = int(out.split("flood sent ")[1].split()[0])
            driver.wait_marker()
            latency, status = driver.cycle_latency()  # the next SYNC after the flood
            rss1 = _rss_kb(ctrl.pid)
            _, status2 = driver.cycle_latency()  # no drop since: bit 7 clear
            driver.bus.shutdown()
            assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
        finally:
            if ctrl.poll() is None:
                ctrl.kill()
    s = json.loads(summary.read_text())
    # the hub's drops for the controller can include the flood's end markers (sent into the
    # same full queue right after the last flood frame; measured once in 5 loaded runs); the
    # markers that did arrive are counted as unknown IDs
    markers_dropped = END_MARKERS - s["rejections"].get("unknown_id", 0)
    assert 0 <= markers_dropped <= END_MARKERS
    dropped_by_hub = _hub_dropped(stats_path, ctrl.pid) - markers_dropped
    received = sent - dropped_by_hub  # flood frames that reached the controller
    assert sent >= 0.5 * seconds * rate
    assert rss1 - rss0 <= RSS_GROWTH_MAX_KB, (rss0, rss1)
    assert latency <= LOCKSTEP_WAIT_S, latency
    assert not int(status2.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
    drops = s["rx_drops"][BURST_FULL]
    if syncs_during_flood:
        # syncs + 2 bursts since the flood began, each SYNC validating at most 3
        # MOTION_SENSORS frames (the flood's and the bursts' own)
        bursts = syncs + 2
        assert received - 2 * bursts <= drops <= received + bursts, (drops, received, syncs)
        last = bool(int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD))
        assert overloaded >= 1 and s["rx_overload_cycles"] == overloaded + last
    else:
        assert int(status.values["FAULT_BITS"]) & (1 << Fault.RX_OVERLOAD)
        # one cycle: the flood's frames and the burst's own, the newest 3 kept
        assert drops == received + 1 - 3, (drops, received, dropped_by_hub)
        assert s["rx_overload_cycles"] == 1
    assert _new_children(before) == []


def test_plant_process_stays_flat_under_a_flood_of_torque_frames(tmp_path: Path) -> None:
    """Plant and controller in lockstep with SecOC; a babbling node floods well-formed
    WHEEL_TORQUE_CMD frames (valid CRC and counter, no authenticator). The plant stays flat,
    every cycle is still commanded by the genuine controller (its frame and authenticator
    come in one packet: no flood frame between them), and every flood frame that reached
    the plant is counted: pushed out of the SecOC receiver's pending queue, or dropped
    unverified when the genuine frame verified."""
    before = _children_now()
    stats_path = tmp_path / "hub.json"
    plant_summary, ctrl_summary = tmp_path / "plant.json", tmp_path / "ctrl.json"
    with LocalHub(stats_path=stats_path) as hub:
        ctrl = _start(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                      hub.spec, "--controller", "passive", "--mode", "lockstep", "--summary",
                      str(ctrl_summary), "--secoc", "--secoc-keys", "ci-test-key")
        plant = None
        try:
            _wait_ready(ctrl, "controller")
            plant = _start(tmp_path / "plant.err", "-m", "plant_sim.process", "--bus",
                           hub.spec, "--scenario", "constant-radius", "--mode", "lockstep",
                           "--speed", "50", "--param", "radius_m=100", "--param", "laps=50",
                           "--param", "speed_ramp_kmhps=0", "--param", "duration_s=1800",
                           "--wait-ms", "2000", "--summary", str(plant_summary),
                           "--secoc", "--secoc-keys", "ci-test-key", "--secoc-state",
                           str(tmp_path / "trip"))
            _wait_ready(plant, "plant")
            listener = _Listener(hub.spec)
            listener.start()
            time.sleep(1.0)
            rss0 = _rss_kb(plant.pid)
            seconds = 3.0
            rate = 20_000.0
            try:
                sent = _flood(hub.spec, seconds, rate, "valid", "WHEEL_TORQUE_CMD")
                _resend_marker_until_seen(hub.spec, listener)
                listener.wait_syncs_after_marker(3)
            finally:
                listener.close()
            rss1 = _rss_kb(plant.pid)
            assert interrupt_and_wait(plant, 30, tmp_path / "plant.err") == 0
            assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
        finally:
            for proc in (plant, ctrl):
                if proc is not None and proc.poll() is None:
                    proc.kill()
    p = json.loads(plant_summary.read_text())
    assert sent >= 0.5 * seconds * rate
    assert rss1 - rss0 <= RSS_GROWTH_MAX_KB, (rss0, rss1)
    assert p["reason"] == "stopped by signal" and p["cycles"] > 100
    assert p["fallback_cycles"] == 0, p  # the genuine command was applied every cycle
    received = sent - _hub_dropped(stats_path, plant.pid)
    unverified = p["secoc"]["rejected_by_frame"]["WHEEL_TORQUE_CMD"]["unauthenticated"]
    assert received - PENDING <= unverified <= received, (unverified, received)
    assert 0 < p["rx_drops"]["secoc_pending_full"] <= unverified
    assert _new_children(before) == []
