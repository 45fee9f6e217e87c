"""A bus that goes away, or never answers, across processes: the controller and the plant
end with exit code 3 and one ``bus lost`` / ``cannot open bus`` line, no traceback, and
leave their files whole (the controller's checkpoint, recording and summary, the served plant's
``done`` line and summary, no half-written row file).

Each process is started with ``--rt`` (the processes ask for SCHED_FIFO; where that is not
permitted they say so and go on) and ``--reconnect-s 0`` (a lost bus is final at once)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import can

from can_db.codec import Codec
from can_db.transport.bus import open_bus, resolve_bus
from controller.runtime.checkpoint import read_checkpoint
from harness.run.procs import Child
from tests.helpers_proc import not_a_bus_server

START_S = 120.0  # a process start on a loaded 2-core machine, wall s
WAIT_S = 60.0


def _controller(bus: str, tmp: Path, *extra: str) -> Child:
    return Child("controller", ["-m", "controller.runtime.process", "--bus", bus,
                                "--controller", "nmpc-rhonn", "--reconnect-s", "0", "--rt",
                                "--summary", str(tmp / "controller_summary.json"), *extra],
                 tmp / "controller.log")


def _wait_exit(child: Child) -> int:
    assert child.proc is not None
    return child.proc.wait(timeout=WAIT_S)


def _output(child: Child) -> str:
    assert child.proc is not None and child._reader is not None
    child._reader.join(timeout=5.0)
    return "\n".join(child.lines)


def _wait_for_answers(bus: can.BusABC, count: int) -> None:
    """Until ``count`` torque frames of the controller have been seen on ``bus``."""
    torque_id = Codec().messages["WHEEL_TORQUE_CMD"].frame_id
    deadline = time.monotonic() + WAIT_S
    seen = 0
    while seen < count:
        msg = bus.recv(timeout=max(0.0, deadline - time.monotonic()))
        assert msg is not None, f"{seen} answers of the controller within {WAIT_S} s"
        seen += msg.arbitration_id == torque_id


def test_a_lost_bus_ends_the_controller_and_the_served_plant_with_code_3(
        tmp_path: Path) -> None:
    spec, hub = resolve_bus("auto")
    assert hub is not None
    ckpt, rrd = tmp_path / "learned.npz", tmp_path / "controller.rrd"
    watch = open_bus(spec)
    ctrl = _controller(spec, tmp_path, "--checkpoint", str(ckpt), "--rerun", str(rrd)).launch()
    plant = Child("plant", ["-m", "plant_sim.process", "--bus", spec, "--serve", "--rt",
                            "--reconnect-s", "0"], tmp_path / "plant.log", stdin=True
                  ).launch("ready serve")
    try:
        ctrl.wait_ready(START_S)
        plant.wait_ready(START_S)
        since = len(plant.lines)
        plant.send(json.dumps({"run": [
            "--scenario", "constant-radius", "--mode", "realtime", "--duration", "60",
            "--trace", str(tmp_path / "truth.csv"),
            "--summary", str(tmp_path / "plant_summary.json")]}))
        assert plant.wait_line(("loaded",), since, WAIT_S) == "loaded constant-radius"
        _wait_for_answers(watch, 5)  # the loop runs: the bus goes mid-run
        hub.stop()
        assert _wait_exit(plant) == 3
        assert _wait_exit(ctrl) == 3
    finally:
        plant.stop(1.0)
        ctrl.stop(1.0)
        hub.stop()
        watch.shutdown()
    plant_out, ctrl_out = _output(plant), _output(ctrl)
    assert "Traceback" not in plant_out + ctrl_out
    assert "rhonn-plant: realtime: SCHED_" in plant_out
    assert "rhonn-controller: realtime: SCHED_" in ctrl_out
    # the plant: the run ends with its reason, its files whole, then the process
    assert "rhonn-plant: error: bus lost: hub of rhonncan channel" in plant_out
    done = next(ln for ln in plant.lines if ln.startswith("done "))
    summary = json.loads(done[len("done "):])
    assert summary["reason"] == "bus lost"
    assert json.loads((tmp_path / "plant_summary.json").read_text()) == summary
    rows = (tmp_path / "truth.csv").read_text().splitlines()
    assert len(rows) == summary["cycles"] + 2  # header + the initial row + one a cycle
    # the controller: its learned state and counters are kept
    assert "rhonn-controller: error: bus lost: hub of rhonncan channel" in ctrl_out
    ctrl_summary = json.loads((tmp_path / "controller_summary.json").read_text())
    assert ctrl_summary["cycles_answered"] > 0
    assert ctrl_summary["checkpoint"]["saves"] >= 1
    assert read_checkpoint(ckpt)[0]["steps"] == ctrl_summary["checkpoint"]["steps"]
    assert rrd.read_bytes()[:4] == b"RRF2"  # its recording flushed (rerun's file)


def test_a_bus_that_cannot_be_opened_is_exit_code_3_and_one_line(tmp_path: Path) -> None:
    with not_a_bus_server() as port:
        bus = f"remote:ws://127.0.0.1:{port}/"
        ctrl = _controller(bus, tmp_path).launch()
        plant = Child("plant", ["-m", "plant_sim.process", "--bus", bus, "--rt",
                                "--scenario", "dlc-paper", "--trace",
                                str(tmp_path / "truth.csv")], tmp_path / "plant.log").launch()
        try:
            assert _wait_exit(ctrl) == 3
            assert _wait_exit(plant) == 3
        finally:
            ctrl.stop(1.0)
            plant.stop(1.0)
    for child, prog in ((ctrl, "rhonn-controller"), (plant, "rhonn-plant")):
        out = _output(child)
        assert "Traceback" not in out
        errors = [ln for ln in child.lines if ln.startswith(f"{prog}: cannot open bus")]
        assert len(errors) == 1, out  # the reason after it is the socket's (reset, closed)
        assert errors[0].startswith(f"{prog}: cannot open bus {bus}: cannot connect to "
                                    f"loopback bus server ws://127.0.0.1:{port}/: "), out
        assert not any(ln.startswith("ready") for ln in child.lines)
    assert not (tmp_path / "controller_summary.json").exists()  # no run, no summary
    assert not (tmp_path / "truth.csv.rows").exists()  # the plant's trace is closed
