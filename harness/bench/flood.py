"""`rhonn-bench flood`: memory and SYNC-answer latency of the loop's processes under a flood
of frames on the IDs they receive (docs/safety/queues.md).

Two phases, each on a fresh local bus (hub process), each with ``--seconds`` of flood at
``--rate`` frames/s in all of well-formed frames (correct E2E CRC and alive counter):

1. **controller alone** (lockstep, this process sends the plant's bursts): a flood of the
   four sensor/driver IDs with no SYNC at all; then ``--syncs`` cycles, each answer timed from
   this process's send of the burst to the CTRL_STATUS that echoes it (the first one is the
   answer right after the flood, reported apart).
2. **closed loop** (lockstep plant and controller, SecOC on with the public CI test key): the
   sensor flood towards the controller and a WHEEL_TORQUE_CMD flood towards the plant, half
   the rate each; SYNC → CTRL_STATUS latency as this process sees it on the bus.

Printed: RSS (VmRSS) of controller and plant at the flood's start and end, frames sent, the
drops each process counted (``rx_drops``) and the hub's per-node drops, and the latencies
(p50/p99). Nothing here asserts a threshold.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can

from can_db.codec import Codec, Decoded, Transmitter
from can_db.process.argcheck import OneLineParser, UsageError, check_out_file, number
from can_db.process.parent import die_with_parent
from can_db.transport.bus import open_bus
from can_db.transport.hub import LocalHub
from controller.registry import CONTROLLER_NAMES
from harness.bench.stats import summarize_us, write_json
from harness.run.flood import END_MARKER_ID

CODEC = Codec()
SENSOR_MESSAGES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")
STATUS_ID = CODEC.messages["CTRL_STATUS"].frame_id
SYNC_ID = CODEC.messages["SYNC"].frame_id


def rss_kb(pid: int) -> int:
    """VmRSS of process ``pid``, kB (/proc/PID/status); 0 if it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _child(args: list[str], err: Path) -> subprocess.Popen[str]:
    with open(err, "w") as f:  # the child keeps its own descriptor
        return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=f,
                                text=True, preexec_fn=die_with_parent)


def _ready(proc: subprocess.Popen[str], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("ready"):
            return
        if not line and proc.poll() is not None:
            raise RuntimeError(f"{what} exited with code {proc.returncode}")
    raise RuntimeError(f"{what} not ready within {timeout_s:g} s")


def _stop(proc: subprocess.Popen[str] | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _flood(spec: str, seconds: float, rate: float, messages: tuple[str, ...],
           err: Path) -> subprocess.Popen[str]:
    args = ["-m", "harness.run.flood", "--bus", spec, "--rate", str(rate), "--kind", "valid",
            "--duration", str(seconds), "--end-marker"]
    for m in messages:
        args += ["--message", m]
    return _child(args, err)


def _flood_sent(proc: subprocess.Popen[str]) -> int:
    out, _ = proc.communicate(timeout=120)
    return int(out.split("flood sent ")[1].split()[0]) if "flood sent " in out else 0


def _hub_drops(stats_path: Path, pids: dict[str, int]) -> dict[str, int]:
    """Frames the hub dropped for each named process (its queue to it was full)."""
    try:
        nodes = json.loads(stats_path.read_text())["nodes"]
    except (OSError, ValueError, KeyError):
        return {}
    return {what: sum(n["dropped"] for n in nodes if n["name"].endswith(f":{pid}"))
            for what, pid in pids.items()}


def _burst(tx: Transmitter, cycle: int) -> list[can.Message]:
    return [tx.message("DRIVER_INPUTS", {"SWA": 0.0, "ACCEL_PEDAL": 10.0, "BRAKE_PEDAL": 0.0,
                                         "STAB_ENABLE": 1.0}),
            tx.message("MOTION_SENSORS", {"YAW_RATE": 0.01 * (cycle % 7), "AX": 0.0,
                                          "AY": 0.0}),
            tx.message("WHEEL_SPEEDS", {f"WS_{w}": 60.0 for w in ("FL", "FR", "RL", "RR")}),
            tx.message("VEHICLE_EST", {"VX_EST": 20.0, "VY_EST": 0.002 * (cycle % 5)}),
            tx.message("SYNC", {"CYCLE": float(cycle), "SIM_TIME": cycle * 0.01})]


def _answer_ns(bus: can.BusABC, tx: Transmitter, cycle: int, timeout_s: float = 10.0
               ) -> int | None:
    """Send cycle ``cycle``'s burst; ns until the CTRL_STATUS echoing it (None: none came)."""
    while bus.recv(timeout=0.0) is not None:  # flood frames read so far: not the answer's
        pass
    bus.send_many(_burst(tx, cycle))
    start = time.perf_counter_ns()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = bus.recv(timeout=0.5)
        if msg is None or msg.arbitration_id != STATUS_ID:
            continue
        status = CODEC.decode_message(msg)
        if isinstance(status, Decoded) and int(status.values["ECHO_CYCLE"]) == cycle % 256:
            return time.perf_counter_ns() - start
    return None


def controller_alone(tmp: Path, controller: str, seconds: float, rate: float,
                     syncs: int) -> dict[str, Any]:
    """Phase 1 (see the module doc)."""
    hub_stats = tmp / "hub1.json"
    summary = tmp / "controller1.json"
    ctrl = bus = None
    with LocalHub(stats_path=hub_stats) as hub:
        try:
            ctrl = _child(["-m", "controller.runtime.process", "--bus", hub.spec,
                           "--controller", controller, "--mode", "lockstep",
                           "--summary", str(summary), "--no-secoc"],  # our SYNCs: plain
                          tmp / "controller1.err")
            _ready(ctrl, "controller")
            bus, tx = open_bus(hub.spec), Transmitter(CODEC)
            for cycle in range(50):  # warm-up
                _answer_ns(bus, tx, cycle)
            rss_start = rss_kb(ctrl.pid)
            flood = _flood(hub.spec, seconds, rate, SENSOR_MESSAGES, tmp / "flood1.err")
            marker = False
            deadline = time.monotonic() + seconds + 60.0
            # read along (our own queue at the hub stays short) until the flood's end
            # marker: the hub has then forwarded every flood frame, so the timed SYNCs
            # reach the controller after all of them
            while not marker and time.monotonic() < deadline:
                msg = bus.recv(timeout=0.05)
                marker = msg is not None and msg.arbitration_id == END_MARKER_ID
            sent = _flood_sent(flood)
            rss_end_flood = rss_kb(ctrl.pid)
            latencies = [_answer_ns(bus, tx, 50 + k) for k in range(syncs)]
            rss_end = rss_kb(ctrl.pid)
        finally:
            if bus is not None:
                bus.shutdown()
            _stop(ctrl)
    answered = [x for x in latencies if x is not None]
    s = json.loads(summary.read_text()) if summary.exists() else {}
    return {"frames_sent": sent, "rss_kb": {"flood_start": rss_start,
                                            "flood_end": rss_end_flood,
                                            "syncs_end": rss_end},
            "first_answer_us": None if latencies[0] is None else latencies[0] / 1000.0,
            "answer_latency": summarize_us(answered) if answered else None,
            "unanswered": len(latencies) - len(answered),
            "rx_drops": s.get("rx_drops"), "rx_overload_cycles": s.get("rx_overload_cycles"),
            "hub_dropped": _hub_drops(hub_stats, {"controller": ctrl.pid}) if ctrl else {}}


def closed_loop(tmp: Path, controller: str, seconds: float, rate: float) -> dict[str, Any]:
    """Phase 2 (see the module doc)."""
    hub_stats = tmp / "hub2.json"
    c_summary, p_summary = tmp / "controller2.json", tmp / "plant2.json"
    ctrl = plant = bus = None
    keys = ["--secoc", "--secoc-keys", "ci-test-key"]
    with LocalHub(stats_path=hub_stats) as hub:
        try:
            ctrl = _child(["-m", "controller.runtime.process", "--bus", hub.spec,
                           "--controller", controller, "--mode", "lockstep",
                           "--summary", str(c_summary), *keys], tmp / "controller2.err")
            _ready(ctrl, "controller")
            bus = open_bus(hub.spec)
            plant = _child(["-m", "plant_sim.process", "--bus", hub.spec, "--scenario",
                            "constant-radius", "--mode", "lockstep", "--speed", "50",
                            "--param", "radius_m=100", "--param", "laps=400", "--param",
                            "speed_ramp_kmhps=0", "--param", "duration_s=3600",
                            "--summary", str(p_summary), *keys, "--secoc-state",
                            str(tmp / "trip")], tmp / "plant2.err")
            _ready(plant, "plant")
            _watch(bus, 1.0)  # warm-up
            rss_start = {"controller": rss_kb(ctrl.pid), "plant": rss_kb(plant.pid)}
            floods = [_flood(hub.spec, seconds, rate / 2, SENSOR_MESSAGES,
                             tmp / "flood2a.err"),
                      _flood(hub.spec, seconds, rate / 2, ("WHEEL_TORQUE_CMD",),
                             tmp / "flood2b.err")]
            latencies = _watch(bus, seconds, until=lambda: all(f.poll() is not None
                                                               for f in floods))
            sent = sum(_flood_sent(f) for f in floods)
            rss_end_flood = {"controller": rss_kb(ctrl.pid), "plant": rss_kb(plant.pid)}
        finally:
            if bus is not None:
                bus.shutdown()
            _stop(plant)
            _stop(ctrl)
    c = json.loads(c_summary.read_text()) if c_summary.exists() else {}
    p = json.loads(p_summary.read_text()) if p_summary.exists() else {}
    return {"frames_sent": sent, "rss_kb": {"flood_start": rss_start,
                                                        "flood_end": rss_end_flood},
            "answer_latency": summarize_us(latencies) if latencies else None,
            "controller": {"rx_drops": c.get("rx_drops"),
                           "rx_overload_cycles": c.get("rx_overload_cycles")},
            "plant": {"rx_drops": p.get("rx_drops"), "cycles": p.get("cycles"),
                      "fallback_cycles": p.get("fallback_cycles"),
                      "waits_cut_by_flood": p.get("waits_cut_by_flood")},
            "hub_dropped": _hub_drops(hub_stats, {"controller": ctrl.pid, "plant": plant.pid})
            if ctrl and plant else {}}


def _watch(bus: can.BusABC, seconds: float, until=None) -> list[int]:
    """SYNC → CTRL_STATUS (same cycle) latencies seen on the bus, ns, for ``seconds`` (or
    until ``until()`` is true)."""
    out: list[int] = []
    pending: dict[int, int] = {}  # echo -> SYNC seen at, ns
    end = time.monotonic() + seconds
    while time.monotonic() < end + 30.0:
        if time.monotonic() >= end and (until is None or until()):
            break
        msg = bus.recv(timeout=0.1)
        if msg is None:
            continue
        if msg.arbitration_id == SYNC_ID:
            sync = CODEC.decode_message(msg)
            if isinstance(sync, Decoded):
                pending[int(sync.values["CYCLE"]) % 256] = time.perf_counter_ns()
        elif msg.arbitration_id == STATUS_ID:
            status = CODEC.decode_message(msg)
            if isinstance(status, Decoded):
                seen = pending.pop(int(status.values["ECHO_CYCLE"]), None)
                if seen is not None:
                    out.append(time.perf_counter_ns() - seen)
    return out


def _line(name: str, phase: dict[str, Any]) -> None:
    lat = phase.get("answer_latency") or {}
    print(f"{name}: frames sent {phase['frames_sent']}, RSS kB {phase['rss_kb']}, "
          f"answer latency p50 {lat.get('p50_us', float('nan')):.0f} µs, p99 "
          f"{lat.get('p99_us', float('nan')):.0f} µs ({lat.get('samples', 0)} cycles)")


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench flood", description=__doc__)
    parser.add_argument("--seconds", type=number(lo=0.0, lo_open=True, unit="s"), default=15.0,
                        help="flood duration of each phase, s")
    parser.add_argument("--rate", type=number(lo=0.0, lo_open=True), default=24_000.0,
                        help="flood frames per second (phase 2: half on the sensor IDs, half "
                             "on the torque ID)")
    parser.add_argument("--syncs", type=number(int, lo=1), default=50,
                        help="phase 1: cycles timed after the flood")
    parser.add_argument("--controller", default="passive", choices=CONTROLLER_NAMES,
                        help="controller of both phases (the queues are the node's)")
    parser.add_argument("--json", default=None, help="write the results to this file")
    args = parser.parse_args(argv)
    try:
        if args.json:
            check_out_file(args.json, "--json")
    except UsageError as exc:
        parser.error(str(exc))
    with tempfile.TemporaryDirectory(prefix="rhonn-bench-flood-") as name:
        tmp = Path(name)
        alone = controller_alone(tmp, args.controller, args.seconds, args.rate, args.syncs)
        _line("controller alone, SYNC-less flood", alone)
        print(f"  first answer after the flood {alone['first_answer_us']} µs, unanswered "
              f"{alone['unanswered']}; controller rx_drops {alone['rx_drops']}, "
              f"overload cycles {alone['rx_overload_cycles']}; hub dropped "
              f"{alone['hub_dropped']}", flush=True)
        loop = closed_loop(tmp, args.controller, args.seconds, args.rate)
        _line("closed loop, sensor + torque floods", loop)
        print(f"  controller {loop['controller']}; plant {loop['plant']}; hub dropped "
              f"{loop['hub_dropped']}", flush=True)
    write_json(args.json, {"seconds": args.seconds, "rate": args.rate,
                           "controller_alone": alone, "closed_loop": loop})
    return 0
