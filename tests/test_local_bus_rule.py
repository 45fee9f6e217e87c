"""One rule for a local bus everywhere: the first node of a ``local:NAME`` channel starts its
hub, whichever program it is (rhonn-controller, rhonn-plant, rhonn-bus dump, or python-can's
``rhonncan`` interface), and the hub exits 3 s after the last node left.

Cross-process: on a fresh channel with no hub, the controller starts it; a dump and a plant
run join the same channel; the plant's run is answered every cycle and the dump decodes
frames of it (its idle time-out counting from the first frame, MACs in hex); the hub is gone
once everyone left.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path

import can

from can_db.transport.localbus import socket_path
from tests.helpers_proc import interrupt_and_wait, spawn


def _ready(proc: subprocess.Popen[str], timeout_s: float = 90.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("ready"):
            return line
        if not line and proc.poll() is not None:
            raise AssertionError(f"exited with {proc.returncode}")
    raise AssertionError("not ready")


def _spawn_logged(err: Path, *args: str) -> subprocess.Popen[str]:
    with open(err, "w") as f:  # the child has its own copy of the descriptor
        return spawn(*args, stdout=subprocess.PIPE, stderr=f)


def test_every_program_starts_the_hub_of_a_fresh_local_channel(tmp_path: Path) -> None:
    channel = f"rule{os.getpid()}"
    spec = f"local:{channel}"
    assert not socket_path(channel).exists()
    summary = tmp_path / "plant.json"
    ctrl = _spawn_logged(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                         spec, "--controller", "passive")
    dump = plant = None
    try:
        _ready(ctrl)  # it found no hub and started one
        # an idle time-out of 1 s: it counts from a frame, not from the dump's start
        dump = spawn("-m", "can_db.cli", "dump", "--bus", spec, "--count", "300",
                     "--timeout", "1", "--secoc-keys", "ci-test-key", stdout=subprocess.PIPE,
                     stderr=subprocess.PIPE)
        time.sleep(3.0)  # longer than the time-out before the plant's first frame
        plant = _spawn_logged(tmp_path / "plant.err", "-m", "plant_sim.process", "--bus", spec,
                              "--scenario", "dlc-paper", "--duration", "0.5", "--summary",
                              str(summary), "--secoc-state", str(tmp_path / "trip"))
        assert plant.wait(120) == 0, (tmp_path / "plant.err").read_text()
        out, err = dump.communicate(timeout=60)
        assert dump.returncode == 0, err
        assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
    finally:
        for proc in (plant, dump, ctrl):
            if proc is not None and proc.poll() is None:
                proc.kill()
    stats = json.loads(summary.read_text())
    assert stats["fallback_cycles"] == 0 and stats["cycles"] == 50, stats
    frames = [ln for ln in out.splitlines() if ln[:1].isdigit()]
    assert len(frames) == 300, out
    macs = [ln for ln in frames if "MAC=" in ln]
    assert macs and all(re.search(r"MAC=0x[0-9A-F]{8}(,|$)", ln) for ln in macs), macs
    assert "frames: 300  rejections: 0" in out, out
    # every secured frame's line waits for its authenticator and says what it found: none
    # is left "pending"; only frames whose authenticator came after the 300th may be
    # unverified (the last burst)
    assert not [ln for ln in frames if "[pending]" in ln]
    data = [ln for ln in frames if re.search(r" (DRIVER_INPUTS|MOTION_SENSORS|WHEEL_SPEEDS|"
                                             r"VEHICLE_EST|SYNC|WHEEL_TORQUE_CMD|CTRL_STATUS) ",
                                             ln)]
    verified = [ln for ln in data if "[authenticated]" in ln]
    assert len(data) > 100 and len(data) - len(verified) <= 7, \
        [ln for ln in data if "[authenticated]" not in ln]
    deadline = time.monotonic() + 30
    while socket_path(channel).exists() and time.monotonic() < deadline:
        time.sleep(0.2)  # the hub leaves 3 s after its last node
    assert not socket_path(channel).exists()


def test_a_dump_names_why_it_rejects_frames_of_other_tools(tmp_path: Path) -> None:
    """python-can's ``rhonncan`` interface and a dump on one fresh channel (the dump starts
    the hub): frames the DBC does not define are each one line that says why, in words
    (before: ``REJECTED Rejected(reason=<Rejection.NOT_DATA_FRAME: ...>, ...)``)."""
    channel = f"other{os.getpid()}"
    dump = spawn("-m", "can_db.cli", "dump", "--bus", f"local:{channel}", "--count", "2",
                 "--timeout", "5", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert _ready(dump).strip() == f"ready dump on local:{channel}"
        with can.Bus(interface="rhonncan", channel=channel) as bus:
            bus.send(can.Message(arbitration_id=0x123, data=[1], is_extended_id=True))
            bus.send(can.Message(arbitration_id=0x7A5, data=[2], is_extended_id=False))
        out, err = dump.communicate(timeout=60)
    finally:
        if dump.poll() is None:
            dump.kill()
    assert dump.returncode == 0, err
    frames = [ln for ln in out.splitlines() if ln[:1].isdigit()]
    assert len(frames) == 2, out
    assert frames[0].endswith("0x123 [unsecured] REJECTED not_data_frame: not a classical "
                              "data frame"), frames
    assert " 0x7A5 " in frames[1] and "REJECTED unknown_id: " in frames[1], frames
    assert not re.search(r"Rejected\(|<Rejection|None", out), out
