"""Bus log files a user opens: the MF4 of a cross-process lockstep run (zero-based simulated
time, one channel per signal named MESSAGE.SIGNAL, one group per message, values as cantools
decodes them), its recovery after a SIGKILL of the harness, the time base of ASC/BLF through
conversion, and ``rhonn-bus decode``."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import cantools
import numpy as np
import psutil
import pytest

from can_db import cli as bus_cli
from can_db.cli import main as bus_main
from can_db.codec import Codec, Transmitter
from can_db.logfiles import (
    FRAMES_SUFFIX,
    FrameFile,
    LogFileError,
    convert,
    frames_path,
    read_frame_file,
    read_log,
    recover,
    set_asc_date,
)
from harness.run.bus_logger import FRAME_SLOT_S, PERIOD_S, BusRecorder
from tests.helpers_proc import spawn

asammdf = pytest.importorskip("asammdf")
DBC = cantools.database.load_file(str(Path(__file__).parents[1] / "can_db" / "rhonn_tv.dbc"))
BURST = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")


def _bus(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "can_db.cli", *args], capture_output=True,
                          text=True, timeout=120)


@pytest.fixture(scope="module")
def lockstep_mf4(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("mf4run")
    done = subprocess.run(
        [sys.executable, "-m", "harness.cli", "run", "dlc-paper", "--controller", "lmpc",
         "--duration", "2", "--log-format", "mf4", "--no-plots", "--no-rrd", "--out", str(out)],
        capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return out / "bus.mf4"


def test_lockstep_mf4_is_zero_based_in_simulated_time(lockstep_mf4: Path) -> None:
    assert not frames_path(lockstep_mf4).exists()  # built and the frame file removed
    with asammdf.MDF(lockstep_mf4) as mdf:
        firsts = [g.channel_group.cycles_nr and mdf.get_master(i)[0]
                  for i, g in enumerate(mdf.groups) if g.channel_group.cycles_nr]
        assert 0.0 <= min(firsts) < 0.02
        sim = mdf.get("SYNC.SIM_TIME")
        first_of_cycle = mdf.get("DRIVER_INPUTS.SWA")  # slot 0 of every burst
        # every cycle's first frame sits at the simulated time its SYNC carries
        np.testing.assert_allclose(first_of_cycle.timestamps, sim.samples, rtol=0, atol=1e-9)
        assert np.allclose(np.diff(sim.samples), PERIOD_S, atol=1e-9)
        slot = sim.timestamps - sim.samples  # SYNC ends the burst: a fixed in-cycle slot
        assert np.ptp(slot) < 1e-9 and 0 < slot[0] <= 8 * FRAME_SLOT_S + 1e-9
        assert sim.samples[-1] == pytest.approx(1.99, abs=0.011)
        assert "simulated time" in mdf.header.comment
        start = mdf.header.start_time.timestamp()
    # python-can's reader adds the header's start: the same absolute stamps as a BLF's
    read = list(can.LogReader(str(lockstep_mf4)))
    assert read[0].timestamp == pytest.approx(start + min(firsts), abs=1e-6)


def test_mf4_has_one_group_per_message_and_one_channel_per_signal(lockstep_mf4: Path) -> None:
    with asammdf.MDF(lockstep_mf4) as mdf:
        groups = {g.channel_group.acq_name: g for g in mdf.groups}
        assert {"MOTION_SENSORS", "SYNC", "WHEEL_TORQUE_CMD", "CTRL_STATUS",
                "CAN"} <= set(groups)
        assert len(groups) == len(mdf.groups)  # every group once
        for name, group in groups.items():
            if name != "CAN":
                assert all(c.name.startswith(f"{name}.") for c in group.channels[1:]), name
        yaw = mdf.get("MOTION_SENSORS.YAW_RATE")  # unique: no "Multiple occurrences"
        assert yaw.unit == "deg/s" and len(yaw) == 200
        np.testing.assert_array_equal(mdf.get("YAW_RATE").samples, yaw.samples)
        with pytest.raises(asammdf.blocks.utils.MdfException, match="not found"):
            mdf.get("ALIVE")  # shared by every message: only MESSAGE.ALIVE names one
        assert mdf.get("CTRL_STATUS.MODE").samples[0] == b"ACTIVE"  # value table


def test_mf4_values_equal_cantools_decode_of_the_same_frames(lockstep_mf4: Path) -> None:
    frames = list(can.LogReader(str(lockstep_mf4)))  # the raw CAN_DataFrame group
    with asammdf.MDF(lockstep_mf4) as mdf:
        start = mdf.header.start_time.timestamp()
        for msg in DBC.messages:
            mine = [f for f in frames if f.arbitration_id == msg.frame_id]
            if not mine:
                continue
            want = [msg.decode(bytes(f.data), decode_choices=False) for f in mine]
            for sig in msg.signals:
                got = mdf.get(f"{msg.name}.{sig.name}", raw=bool(sig.choices))
                np.testing.assert_array_equal(got.samples, [w[sig.name] for w in want],
                                              err_msg=f"{msg.name}.{sig.name}")
                np.testing.assert_allclose(got.timestamps, [f.timestamp - start for f in mine],
                                           rtol=0, atol=1e-6)


def test_mf4_after_sigkill_of_the_harness_is_recovered(tmp_path: Path) -> None:
    out = tmp_path / "run"
    harness = spawn("-m", "harness.cli", "run", "dlc-paper", "--controller", "passive",
                    "--duration", "600", "--log-format", "mf4", "--out", str(out),
                    "--no-plots", "--no-rrd",
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    src = frames_path(out / "bus.mf4")
    seen, descendants = 0, []
    deadline = time.monotonic() + 90
    try:
        while time.monotonic() < deadline and seen < 15 * 50:  # ≈ 0.5 s of the loop on disk
            time.sleep(0.1)
            with contextlib.suppress(LogFileError):  # not created yet, or no header yet
                seen = len(read_frame_file(src).frames)
        descendants = psutil.Process(harness.pid).children(recursive=True)
    finally:
        harness.send_signal(signal.SIGKILL)
        harness.wait(timeout=10)
    psutil.wait_procs(descendants, timeout=10)
    assert seen >= 750, "the frame file did not grow"
    assert not (out / "bus.mf4").exists() and src.exists()

    done = _bus("recover", str(out))
    assert done.returncode == 0, done.stderr
    assert not src.exists()
    with asammdf.MDF(out / "bus.mf4") as mdf:
        sim = mdf.get("SYNC.SIM_TIME").samples
        assert sim[0] < 0.02 and np.allclose(np.diff(sim), PERIOD_S, atol=1e-9)  # no gap
        assert "simulated time" in mdf.header.comment
    frames = list(can.LogReader(str(out / "bus.mf4")))
    assert len(frames) >= seen  # every frame on disk before the kill (and what followed)
    assert recover(out) == []  # nothing left to recover


def test_a_torn_last_record_is_dropped(tmp_path: Path) -> None:
    path = tmp_path / f"bus.mf4{FRAMES_SUFFIX}"
    ff = FrameFile(path, start_s=1000.0, note="rhonn-tv bus log; test")
    for k in range(10):
        ff.add(can.Message(arbitration_id=0x101, data=bytes([k] * 8)), k * 0.01)
    ff.close()
    with open(path, "ab") as f:
        f.write(b"\x00" * 7)  # a writer killed in the middle of a record
    log = read_frame_file(path)
    assert len(log.frames) == 10 and log.start_s == 1000.0
    assert [m.data[0] for m in log.frames] == list(range(10))
    assert log.frames[-1].timestamp == pytest.approx(0.09)


def test_mf4_keeps_remote_error_and_extended_frames(tmp_path: Path) -> None:
    def std(t: float, **kw: object) -> can.Message:
        return can.Message(timestamp=t, is_extended_id=False, check=False, **kw)

    yaw = Transmitter(Codec()).message("MOTION_SENSORS", {"YAW_RATE": 1.5, "AX": 0.0, "AY": 0.0})
    frames = [std(0.0, arbitration_id=0x101, data=yaw.data),
              std(0.01, arbitration_id=0x055, is_remote_frame=True, dlc=3),
              can.Message(timestamp=0.02, arbitration_id=0x101, is_extended_id=True,
                          data=yaw.data),  # 29-bit: not the DBC's MOTION_SENSORS
              can.Message(timestamp=0.03, is_error_frame=True, data=b"\x01\x02", check=False)]
    ff = FrameFile(tmp_path / "bus.mf4.frames", 1000.0, "rhonn-tv bus log; test")
    for m in frames:
        ff.add(m, m.timestamp)
    ff.close()
    assert recover(tmp_path) == [tmp_path / "bus.mf4"]
    back = read_log(tmp_path / "bus.mf4").frames
    assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_error_frame)
            for m in back] == [(0x101, False, False, False), (0x055, False, True, False),
                               (0x101, True, False, False), (0, True, False, True)]
    assert [m.timestamp for m in back] == pytest.approx([0.0, 0.01, 0.02, 0.03])
    with asammdf.MDF(tmp_path / "bus.mf4") as mdf:
        assert list(mdf.get("MOTION_SENSORS.YAW_RATE").samples) == [1.5]  # the 11-bit one


def _record(path: Path, cycles: int, stamp: str = "sim") -> BusRecorder:
    """A recorder writing ``cycles`` plant bursts sent on a virtual bus to ``path``."""
    tx = Transmitter(Codec())
    channel = f"h4-{path.name}-{stamp}"
    rec = BusRecorder(f"virtual:{channel}", path, stamp=stamp).start()
    sent = 0
    with can.Bus(channel=channel, interface="virtual") as sender:
        for k in range(cycles):
            values = {"DRIVER_INPUTS": {"SWA": k * 0.5, "ACCEL_PEDAL": 0.0, "BRAKE_PEDAL": 0.0,
                                        "STAB_ENABLE": 1},
                      "MOTION_SENSORS": {"YAW_RATE": 0.1 * k, "AX": 0.0, "AY": -0.2},
                      "WHEEL_SPEEDS": {f"WS_{w}": 50.0 for w in ("FL", "FR", "RL", "RR")},
                      "VEHICLE_EST": {"VX_EST": 18.0, "VY_EST": 0.0},
                      "SYNC": {"CYCLE": k, "SIM_TIME": k * PERIOD_S}}
            for name in BURST:
                sender.send(tx.message(name, values[name]))
                sent += 1
        deadline = time.monotonic() + 60.0  # a loaded machine may starve the thread a while
        while rec.frames < sent and time.monotonic() < deadline:
            time.sleep(0.05)
    rec.stop()
    return rec


def test_asc_time_base_survives_conversion_to_blf_and_back(tmp_path: Path) -> None:
    rec = _record(tmp_path / "bus.asc", 20)
    orig = read_log(tmp_path / "bus.asc")
    assert orig.start_s == rec.epoch_s and orig.note == rec.time_base
    assert orig.frames[0].timestamp == 0.0  # simulated time from the start
    done = _bus("convert", str(tmp_path / "bus.asc"), str(tmp_path / "c.blf"))
    assert done.returncode == 0, done.stderr
    convert(tmp_path / "c.blf", tmp_path / "c.mf4")
    convert(tmp_path / "c.mf4", tmp_path / "back.asc")
    for b in ("c.blf", "c.mf4", "back.asc"):
        log = read_log(tmp_path / b)
        assert log.start_s == pytest.approx(orig.start_s, abs=1e-6), b
        assert log.note == rec.time_base, b
        np.testing.assert_allclose([m.timestamp for m in log.frames],
                                   [m.timestamp for m in orig.frames], rtol=0, atol=1e-6)
        assert [bytes(m.data) for m in log.frames] == [bytes(m.data) for m in orig.frames]
    head = (tmp_path / "back.asc").read_text().splitlines()[:6]
    stamp = time.strftime("%H:%M:%S", time.localtime(rec.epoch_s))
    assert stamp in head[0] and stamp in head[3]  # "date …" and "Begin Triggerblock …"
    assert any(rec.time_base in line for line in head)


@pytest.mark.parametrize("millis", [0, 25, 500])
def test_asc_date_line_is_the_start_whatever_the_width_of_its_milliseconds(
        tmp_path: Path, millis: int) -> None:
    """python-can writes the ASC ``date`` line at opening time with 1–3 millisecond digits;
    the start put there instead must be whole and equal the ``Begin Triggerblock`` line."""
    start = float(int(time.time())) - 3600.0 + millis / 1000.0
    path = tmp_path / "x.asc"
    with can.ASCWriter(str(path)) as writer:
        writer.log_event("note", start)
    set_asc_date(path, start)
    head = path.read_text().splitlines()
    assert head[0].removeprefix("date ") == head[3].removeprefix("Begin Triggerblock ")
    assert time.strftime("%H:%M:%S", time.localtime(start)) in head[0]
    assert read_log(path).start_s == pytest.approx(start, abs=1e-3)  # read back as written


def test_realtime_mf4_counts_from_the_start_in_its_header(tmp_path: Path) -> None:
    rec = _record(tmp_path / "bus.mf4", 5, stamp="wall")
    with asammdf.MDF(tmp_path / "bus.mf4") as mdf:
        assert mdf.header.start_time.timestamp() == pytest.approx(rec.epoch_s, abs=1e-6)
        t = mdf.get("SYNC.SIM_TIME").timestamps
        assert 0.0 <= t[0] < 30.0 and np.all(np.diff(t) >= 0)
        assert "wall clock at reception" in mdf.header.comment


def test_decode_prints_a_blf_as_decoded_frames(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    _record(tmp_path / "bus.blf", 10)
    done = _bus("decode", str(tmp_path / "bus.blf"), "--messages", "MOTION_SENSORS,SYNC")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("# ") and "simulated time" in lines[1]
    rows = lines[2:]
    assert len(rows) == 20
    frames = [m for m in can.LogReader(str(tmp_path / "bus.blf"))
              if m.arbitration_id in (0x101, 0x10F)]
    for row, frame, k in zip(rows[::2], frames[::2], range(10), strict=True):
        t, arb, name, rest = row.split(None, 3)
        assert (arb, name) == ("0x101", "MOTION_SENSORS")
        assert float(t) == pytest.approx(k * PERIOD_S + 1 * FRAME_SLOT_S, abs=1e-6)
        want = DBC.decode_message(frame.arbitration_id, bytes(frame.data))
        assert f"YAW_RATE={want['YAW_RATE']:g} deg/s" in rest
    assert rows[1].split()[2] == "SYNC" and "SIM_TIME=0 s" in rows[1]
    with pytest.raises(SystemExit) as bad:
        bus_main(["decode", str(tmp_path / "bus.blf"), "--messages", "NOPE"])
    assert bad.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_decode_of_an_unfinished_mf4_says_how_to_recover_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ff = FrameFile(frames_path(tmp_path / "bus.mf4"), 0.0, "rhonn-tv bus log; test")
    ff.close()
    assert bus_main(["decode", str(tmp_path / "bus.mf4")]) == 1
    err = capsys.readouterr().err
    assert "rhonn-bus recover" in err and len(err.strip().splitlines()) == 1


def test_decode_prints_a_mac_in_hex_as_the_dump_does(tmp_path: Path) -> None:
    """An authenticator's 32-bit MAC reads the same in ``decode`` and in ``dump``: hex."""
    codec = Codec()
    auth = Transmitter(codec).message("SYNC_AUTH", {"TRIP": 1, "MAC": 0xDEADBEEF})
    path = tmp_path / "auth.blf"
    with can.BLFWriter(str(path)) as writer:
        writer.on_message_received(auth)
    done = _bus("decode", str(path))
    assert done.returncode == 0, done.stderr
    assert "MAC=0xDEADBEEF" in done.stdout and "3735928559" not in done.stdout, done.stdout
    assert "MAC=0xDEADBEEF" in bus_cli.format_frame(codec.decode_message(auth),
                                                    bus_cli.signal_formats(codec))
