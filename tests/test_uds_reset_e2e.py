"""UDS ECUReset across processes: a real controller process on a local hub, reset by the
harness's tester (harness/run/uds_tester.py: udsoncan + can-isotp) over the bus.

Positive responses to soft and hard resets; hard vs soft (boot counter and a new ``ready``
line after a hard reset, the soft-reset counter and no new line after a soft one); a coding
write + hard reset into another controller; NRC 0x22 while the vehicle moves (a VEHICLE_EST
of 60 km/h that passes the controller's E2E checks) and the same reset accepted with
``--bench``; after a soft reset, a replayed lockstep SYNC sequence answered with the same
frames as by the newly started process.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from can_db.codec import Codec, Decoded, Transmitter
from can_db.transport.bus import open_bus, resolve_bus
from controller.runtime.checkpoint import read_checkpoint
from controller.runtime.uds import DID_BOOT_COUNT, DID_SOFT_RESETS
from harness.run.uds_tester import UdsNegativeResponse, UdsTester
from tests.helpers_proc import interrupt_and_wait, spawn

pytestmark = pytest.mark.timeout(120)

CODEC = Codec()
ANSWER_IDS = {CODEC.messages[n].frame_id for n in ("WHEEL_TORQUE_CMD", "CTRL_STATUS",
                                                   "CTRL_REFS")}
STATUS_ID = CODEC.messages["CTRL_STATUS"].frame_id
START_S = 60.0  # a first start on a loaded 2-core box writes caches
COVERAGE_ENV = ("COVERAGE_PROCESS_CONFIG", "COVERAGE_PROCESS_START")  # coverage's subprocesses


class Controller:
    """A controller process whose stdout lines are collected by a thread."""

    def __init__(self, spec: str, tmp: Path, *args: str,
                 file_size_limit: int | None = None) -> None:
        """``file_size_limit``: RLIMIT_FSIZE of the process, bytes (a write past it fails
        with EFBIG, as on a full disk)."""
        self.stderr_path = tmp / f"controller{len(list(tmp.iterdir()))}.err"
        start = ("-m", "controller.runtime.process") if file_size_limit is None else (
            "-c", "import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_FSIZE, "
                  f"({file_size_limit}, {file_size_limit})); sys.argv[0] = 'rhonn-controller'; "
                  "runpy.run_module('controller.runtime.process', run_name='__main__')")
        # --no-secoc: the test's own bursts are unauthenticated (SecOC is on by default)
        self.proc = spawn(*start, "--bus", spec, "--no-secoc", *args,
                          stdout=subprocess.PIPE, stderr=self.stderr_path.open("w"),
                          env={**{k: v for k, v in os.environ.items()
                                  if k != "RHONN_BOOT_COUNT"  # a first boot
                                  # not measured under a file-size limit: coverage's data
                                  # file would be cut short (a corrupt file, a warning)
                                  and (file_size_limit is None or k not in COVERAGE_ENV)},
                               "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"})
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.wait_ready(1)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def readies(self) -> list[str]:
        return [ln for ln in self.lines if ln.startswith("ready")]

    def wait_ready(self, count: int, timeout_s: float = START_S) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            readies = self.readies()
            if len(readies) >= count:
                return readies[count - 1]
            assert self.proc.poll() is None, self.stderr_path.read_text()[-3000:]
            time.sleep(0.02)
        raise AssertionError(f"no ready line #{count}: {self.lines}\n"
                             f"{self.stderr_path.read_text()[-3000:]}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            interrupt_and_wait(self.proc, 20, self.stderr_path)


class Plant:
    """The plant's side of the bus, by hand: bursts of E2E-protected frames + SYNC, and the
    controller's answers."""

    def __init__(self, spec: str) -> None:
        self.bus = open_bus(spec)
        self.tx = Transmitter(CODEC)

    def close(self) -> None:
        self.bus.shutdown()

    def burst(self, cycle: int, vx_mps: float, swa_deg: float = 0.0) -> list:
        """The frames of one 10 ms cycle (values vary with ``cycle``), SYNC last."""
        ws = vx_mps / 0.358
        t = self.tx
        return [
            t.message("DRIVER_INPUTS", {"SWA": swa_deg, "ACCEL_PEDAL": 20.0,
                                        "BRAKE_PEDAL": 0.0, "STAB_ENABLE": 1}),
            t.message("MOTION_SENSORS", {"YAW_RATE": 0.5 * swa_deg, "AX": 0.1,
                                         "AY": 0.05 * swa_deg}),
            t.message("WHEEL_SPEEDS", {"WS_FL": ws, "WS_FR": ws, "WS_RL": ws, "WS_RR": ws}),
            t.message("VEHICLE_EST", {"VX_EST": vx_mps, "VY_EST": 0.0}),
            t.message("SYNC", {"CYCLE": cycle, "SIM_TIME": cycle * 0.01}),
        ]

    def exchange(self, frames: list, cycle: int, timeout_s: float = 10.0) -> list:
        """Send a burst; the controller's three answer frames of ``cycle`` (bus order)."""
        for frame in frames:
            self.bus.send(frame)
        got: list = []
        deadline = time.monotonic() + timeout_s
        while len(got) < 3:
            msg = self.bus.recv(timeout=max(0.0, deadline - time.monotonic()))
            assert msg is not None, f"no answer to cycle {cycle} (got {len(got)})"
            if msg.arbitration_id in ANSWER_IDS and _echo(msg) == cycle % 256:
                got.append(msg)
        return got


def _echo(msg) -> int:
    decoded = CODEC.decode_message(msg)
    assert isinstance(decoded, Decoded), decoded
    return int(decoded.values["ECHO_CYCLE"])


def _comparable(msg) -> bytes:
    """A frame's ID and data; CTRL_STATUS's wall-clock COMPUTE_TIME (and so its CRC) is the
    one field a replay cannot repeat: it is replaced by its decoded other values."""
    if msg.arbitration_id != STATUS_ID:
        return msg.arbitration_id.to_bytes(2, "big") + bytes(msg.data)
    decoded = CODEC.decode_message(msg)
    assert isinstance(decoded, Decoded)
    values = {k: v for k, v in decoded.values.items() if k != "COMPUTE_TIME"}
    return repr((msg.arbitration_id, decoded.counter, sorted(values.items()))).encode()


@pytest.fixture
def hub() -> Iterator[str]:
    spec, server = resolve_bus("auto")
    try:
        yield spec
    finally:
        if server is not None:
            server.stop()


def _sequence(plant: Plant, cycles: int) -> list[list[bytes]]:
    """A lockstep run of ``cycles`` cycles at 60 km/h with a steering sine."""
    return [[_comparable(m) for m in
             plant.exchange(plant.burst(k, 60 / 3.6, 60.0 * math.sin(0.08 * k)), k)]
            for k in range(cycles)]


def test_soft_and_hard_reset_across_processes(hub: str, tmp_path: Path) -> None:
    timing, summary = tmp_path / "timing.csv", tmp_path / "summary.json"
    ctrl = Controller(hub, tmp_path, "--controller", "lmpc", "--timing", str(timing),
                      "--summary", str(summary))
    plant = Plant(hub)
    try:
        assert ctrl.readies()[0].startswith("ready lmpc")
        plant.exchange(plant.burst(0, 0.0), 0)  # a standing car: resets allowed
        with UdsTester(hub) as tester:
            assert tester.tester_present() == b"\x7e\x00"
            assert tester.read_did(0xFD11) == b"\x00\x01"  # first boot
            assert tester.read_did(0xFD12) == b"\x00\x00"
            tester.unlock()
            assert tester.ecu_reset("soft") == b"\x51\x03"
            # the run's files are whole when the response arrives
            assert summary.is_file() and timing.read_text().count("\n") == 2  # header, 1 row
            assert tester.read_did(0xFD12) == b"\x00\x01"
            assert tester.read_did(0xFD11) == b"\x00\x01"
            plant.exchange(plant.burst(0, 0.0), 0)   # the new run has seen no frame yet
            tester.unlock()                      # a reset ends the session: again
            assert tester.ecu_reset("soft", suppress=True) is None
            deadline = time.monotonic() + 10
            while tester.read_did(0xFD12) != b"\x00\x02":
                assert time.monotonic() < deadline
            assert len(ctrl.readies()) == 1  # a soft reset is no restart
            # the per-run files are opened again by the next run only
            summary.unlink()
            timing.unlink()
            plant.exchange(plant.burst(0, 0.0), 0)
            tester.unlock()
            assert tester.write_coding({"controller": "passive"}) == b"\x6e\xfd\x10"
            assert tester.read_coding()["controller"] == "lmpc"  # active after the reset
            pid = ctrl.proc.pid
            assert tester.ecu_reset("hard") == b"\x51\x01"
        assert summary.is_file() and timing.is_file()
        assert ctrl.wait_ready(2).startswith("ready passive")
        assert ctrl.proc.pid == pid and ctrl.proc.poll() is None  # exec: same process
        # a restarted controller has seen no frame: it counts the car as moving until then
        status = CODEC.decode_message(plant.exchange(plant.burst(1, 0.0), 1)[1])
        with UdsTester(hub) as tester:
            assert tester.read_did(0xFD11) == b"\x00\x02"  # boot counter carried over
            assert tester.read_did(0xFD12) == b"\x00\x00"
            assert tester.read_coding() == {"controller": "passive", "config": None,
                                            "faults": [], "fault_seed": 2}
            tester.unlock()
            with pytest.raises(UdsNegativeResponse) as err:
                tester.write_coding({"controller": "no-such-controller"})
            assert (err.value.service, err.value.nrc) == (0x2E, 0x31)
        assert isinstance(status, Decoded) and status.name == "CTRL_STATUS"
        assert status.values["CONTROLLER_ID"] == 0  # passive answers now
    finally:
        plant.close()
        ctrl.stop()


def test_reset_refused_while_moving_unless_bench(hub: str, tmp_path: Path) -> None:
    plant = Plant(hub)
    try:
        for bench in (False, True):
            ctrl = Controller(hub, tmp_path, "--controller", "passive",
                              *(("--bench",) if bench else ()))
            try:
                for k in range(3):  # 60 km/h, accepted by the controller's E2E checks
                    plant.exchange(plant.burst(k, 60 / 3.6), k)
                with UdsTester(hub) as tester:
                    tester.unlock()
                    if bench:
                        assert tester.ecu_reset("soft") == b"\x51\x03"
                        tester.unlock()
                        assert tester.write_coding({"fault_seed": 3}) == b"\x6e\xfd\x10"
                        continue
                    for call in (lambda: tester.ecu_reset("soft"),
                                 lambda: tester.ecu_reset("hard"),
                                 lambda: tester.write_coding({"fault_seed": 3})):
                        with pytest.raises(UdsNegativeResponse) as err:
                            call()
                        assert err.value.nrc == 0x22
                    assert tester.read_did(0xFD12) == b"\x00\x00"  # reading is allowed
                # a refused request leaves the cycle alone: the next burst is answered
                plant.exchange(plant.burst(3, 60 / 3.6), 3)
            finally:
                ctrl.stop()
            plant = _fresh_plant(plant, hub)
    finally:
        plant.close()


def _fresh_plant(plant: Plant, hub: str) -> Plant:
    plant.close()
    return Plant(hub)


def test_soft_reset_replays_bit_identical(hub: str, tmp_path: Path) -> None:
    """nmpc-rhonn learns from every cycle: a soft reset must bring back the core (RHONN
    weights, OSQP warm start), the monitors and the alive counters of a new process."""
    ctrl = Controller(hub, tmp_path, "--controller", "nmpc-rhonn", "--bench")
    plant = Plant(hub)
    cycles = 40
    try:
        first = _sequence(plant, cycles)
        assert len({tuple(a) for a in first}) > cycles // 2  # the answers do vary
        with UdsTester(hub) as tester:
            tester.unlock()
            assert tester.ecu_reset("soft") == b"\x51\x03"
        plant = _fresh_plant(plant, hub)  # the plant's counters restart with it
        assert _sequence(plant, cycles) == first
        # and a newly started process gives the same frames again
        ctrl.stop()
        ctrl = Controller(hub, tmp_path, "--controller", "nmpc-rhonn", "--bench")
        plant = _fresh_plant(plant, hub)
        assert _sequence(plant, cycles) == first
        assert len(ctrl.readies()) == 1
    finally:
        plant.close()
        ctrl.stop()


def test_a_keyless_or_wrong_key_tester_cannot_recode_or_reset(hub: str, tmp_path: Path) -> None:
    """A bench controller (resets allowed while moving) against testers without the key: a
    raw coding write or reset in the default session gets 0x7F, in the extended session
    0x33; a tester with another secret gets 0x35 (invalid key); the coding stays, the
    controller keeps answering as itself, and the summary counts each refusal."""
    summary = tmp_path / "summary.json"
    ctrl = Controller(hub, tmp_path, "--controller", "lmpc", "--bench", "--summary",
                      str(summary))
    plant = Plant(hub)
    try:
        for k in range(3):
            plant.exchange(plant.burst(k, 60 / 3.6), k)
        with UdsTester(hub) as tester:
            for call, service in ((lambda: tester.write_coding({"controller": "passive"}),
                                   0x2E), (lambda: tester.ecu_reset("hard"), 0x11)):
                with pytest.raises(UdsNegativeResponse) as err:
                    call()
                assert (err.value.service, err.value.nrc) == (service, 0x7F)
        with UdsTester(hub, secret=bytes(32)) as rogue:
            with pytest.raises(UdsNegativeResponse) as err:
                rogue.unlock()
            assert (err.value.service, err.value.nrc) == (0x27, 0x35)
            with pytest.raises(UdsNegativeResponse) as err:
                rogue.write_coding({"controller": "passive"})
            assert (err.value.service, err.value.nrc) == (0x2E, 0x33)
            assert rogue.read_coding()["controller"] == "lmpc"
        status = CODEC.decode_message(plant.exchange(plant.burst(3, 60 / 3.6), 3)[1])
        assert isinstance(status, Decoded) and status.values["CONTROLLER_ID"] != 0
    finally:
        plant.close()
        ctrl.stop()
    refused = json.loads(summary.read_text())["uds"]["refused"]
    assert refused == {"2E/7F": 1, "11/7F": 1, "27/35": 1, "2E/33": 1}


def test_a_controller_that_has_seen_no_frame_refuses_a_reset(hub: str, tmp_path: Path) -> None:
    """Fails closed: before the first accepted VEHICLE_EST and WHEEL_SPEEDS a production
    controller counts the car as moving (0x22), even an authenticated tester's reset; after
    a standing car's burst it accepts."""
    ctrl = Controller(hub, tmp_path, "--controller", "lmpc")
    plant = Plant(hub)
    try:
        with UdsTester(hub) as tester:
            tester.unlock()
            with pytest.raises(UdsNegativeResponse) as err:
                tester.ecu_reset("soft")
            assert (err.value.service, err.value.nrc) == (0x11, 0x22)
            plant.exchange(plant.burst(0, 0.0), 0)
            assert tester.ecu_reset("soft") == b"\x51\x03"
    finally:
        plant.close()
        ctrl.stop()


# keyless single-frame requests: resets, session changes, a seed request, a made-up key
STORM = [bytes((2, 0x11, 0x01)), bytes((2, 0x10, 0x03)), bytes((2, 0x11, 0x03)),
         bytes((2, 0x27, 0x01)), bytes((2, 0x10, 0x02)), bytes((3, 0x27, 0x02, 0x00))]


def test_a_storm_of_keyless_requests_while_driving_changes_nothing(hub: str,
                                                                   tmp_path: Path) -> None:
    """A bench controller (resets allowed while moving, for a tester with the key) at
    60 km/h, 8 keyless diagnostic requests before each of 150 cycles: every cycle is
    answered, by the same controller process (no second ready line: no reset), the coding
    stays, and the summary counts the requests and refuses every reset and key."""
    summary = tmp_path / "summary.json"
    ctrl = Controller(hub, tmp_path, "--controller", "lmpc", "--bench", "--summary",
                      str(summary))
    plant = Plant(hub)
    req_id = CODEC.diagnostic["DIAG_REQ_CTRL"]
    cycles, per_cycle = 150, 8
    try:
        first = CODEC.decode_message(plant.exchange(plant.burst(0, 60 / 3.6), 0)[1])
        assert isinstance(first, Decoded) and first.values["CONTROLLER_ID"] != 0
        for k in range(1, cycles + 1):
            for i in range(per_cycle):
                data = STORM[(k * per_cycle + i) % len(STORM)]
                plant.bus.send(can.Message(arbitration_id=req_id, is_extended_id=False,
                                           data=data + bytes((0xCC,)) * (8 - len(data))))
            answers = plant.exchange(plant.burst(k, 60 / 3.6, 10.0), k)
            status = next(CODEC.decode_message(m) for m in answers
                          if m.arbitration_id == STATUS_ID)
            assert isinstance(status, Decoded)
            assert status.values["CONTROLLER_ID"] == first.values["CONTROLLER_ID"], k
        with UdsTester(hub) as tester:
            assert tester.read_coding()["controller"] == "lmpc"
            assert tester.read_did(DID_BOOT_COUNT) == b"\x00\x01"  # no hard reset
            assert tester.read_did(DID_SOFT_RESETS) == b"\x00\x00"  # no soft reset
        assert len(ctrl.readies()) == 1
    finally:
        plant.close()
        ctrl.stop()
    uds = json.loads(summary.read_text())["uds"]
    # a request whose answer was still queued may be replaced by the next one in the ISO-TP
    # endpoint (never executed); each one handled is refused or harmless (session changes;
    # 10/12: the programming session is not supported)
    assert uds["requests"] > cycles * per_cycle // 2
    assert uds["refused"].get("11/7F", 0) + uds["refused"].get("11/33", 0) > 0
    assert set(uds["refused"]) <= {"11/7F", "11/33", "27/7F", "27/24", "27/35", "27/36",
                                   "27/37", "27/13", "10/7E", "10/12"}, uds["refused"]


def _read_coding_stmin(bus: can.BusABC, stmin_ms: int) -> bytes:
    """ReadDataByIdentifier 0xFD10 by hand, asking for consecutive frames ``stmin_ms``
    apart in the flow control: the whole response."""
    req_id, resp_id = CODEC.diagnostic["DIAG_REQ_CTRL"], CODEC.diagnostic["DIAG_RESP_CTRL"]

    def request(*data: int) -> None:
        bus.send(can.Message(arbitration_id=req_id, is_extended_id=False,
                             data=bytes(data).ljust(8, b"\xcc")))

    def response() -> bytes:
        deadline = time.monotonic() + 10.0
        while True:
            msg = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
            assert msg is not None, "no diagnostic response"
            if msg.arbitration_id == resp_id:
                return bytes(msg.data)

    request(0x03, 0x22, 0xFD, 0x10)
    first = response()
    assert first[0] >> 4 == 1, first.hex()  # a first frame: the coding is > 7 bytes
    size = ((first[0] & 0x0F) << 8) | first[1]
    payload = first[2:]
    request(0x30, 0x00, stmin_ms)  # continue to send, no block limit, STmin
    seq = 1
    while len(payload) < size:
        frame = response()
        assert frame[0] == 0x20 | seq, frame.hex()
        payload += frame[1:]
        seq = (seq + 1) % 16
    return payload[:size]


def test_a_free_running_controller_answers_diagnostics_between_ticks(
        hub: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The free-running loop's diagnostic paths: a segmented response released STmin apart
    while the controller keeps ticking, a soft reset (the run's checkpoint and summary
    written whole before its response), and the run's recording; the numpy reference named
    in the ready line."""
    monkeypatch.setenv("RHONN_BACKEND", "numpy")
    rrd, ckpt, summary = tmp_path / "c.rrd", tmp_path / "learned.npz", tmp_path / "s.json"
    ctrl = Controller(hub, tmp_path, "--controller", "lmpc", "--mode", "freerun",
                      "--rerun", str(rrd), "--checkpoint", str(ckpt),
                      "--summary", str(summary))
    plant = Plant(hub)
    try:
        assert "(freerun, numpy reference float64," in ctrl.readies()[0]
        for k in range(3):  # a standing car: resets allowed
            for frame in plant.burst(k, 0.0):
                plant.bus.send(frame)
        coding = json.loads(_read_coding_stmin(plant.bus, stmin_ms=20)[3:])
        assert coding == {"controller": "lmpc", "config": None, "faults": [],
                          "fault_seed": 2}
        with UdsTester(hub) as tester:
            tester.unlock()
            assert tester.ecu_reset("soft") == b"\x51\x03"
            first_run = json.loads(summary.read_text())
            assert read_checkpoint(ckpt)[0]["controller"] == "lmpc"
            assert tester.read_did(DID_SOFT_RESETS) == b"\x00\x01"
    finally:
        plant.close()
        ctrl.stop()
    assert ctrl.proc.returncode == 0
    assert first_run["cycles_answered"] > 0 and first_run["checkpoint"]["saves"] >= 1
    assert first_run["uds"]["refused"] == {}
    assert rrd.read_bytes()[:4] == b"RRF2"  # rerun's file; flushed at the stop
    assert len(ctrl.readies()) == 1  # a soft reset is no restart
