"""Interop with the standard python-can and cantools tools on our bus, logs and DBC."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import cantools
import pytest

from can_db.codec import Codec, Decoded, Transmitter, default_dbc_path
from can_db.transport.bus import open_bus
from can_db.transport.server import BusServer
from tests.helpers_proc import interrupt_and_wait, spawn

CODEC = Codec()


def _frames(n: int) -> list[can.Message]:
    tx = Transmitter(CODEC)
    out = []
    for k in range(n):
        out.append(tx.message("DRIVER_INPUTS", {"SWA": 1.5 * k, "STAB_ENABLE": 1}))
        out.append(tx.message("SYNC", {"CYCLE": k, "SIM_TIME": k * 0.01}))
    return out


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_logger_files_from_our_bus_read_back_and_decode(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"bus{suffix}"
    sent = _frames(50)
    with BusServer() as server:
        tx_bus, rx_bus = open_bus(server.spec), open_bus(server.spec)
        logger = can.Logger(str(path))
        try:
            for msg in sent:
                tx_bus.send(msg)
            for _ in sent:
                msg = rx_bus.recv(timeout=5.0)
                assert msg is not None
                logger(msg)
        finally:
            logger.stop()
            tx_bus.shutdown()
            rx_bus.shutdown()
    db = cantools.database.load_file(str(default_dbc_path()))
    read = list(can.LogReader(str(path)))
    assert [m.arbitration_id for m in read] == [m.arbitration_id for m in sent]
    for original, logged in zip(sent, read, strict=True):
        assert bytes(logged.data) == bytes(original.data)
        ours = CODEC.decode_message(logged)
        assert isinstance(ours, Decoded)
        theirs = db.decode_message(logged.arbitration_id, logged.data, decode_choices=False)
        assert all(abs(theirs[k] - v) < 1e-9 for k, v in ours.values.items())


def test_cantools_dump_reads_our_dbc() -> None:
    out = subprocess.run([sys.executable, "-m", "cantools", "dump", str(default_dbc_path())],
                         capture_output=True, text=True, timeout=60, check=True).stdout
    # Parse the dump's message blocks and compare them field by field with our codec's view
    # of the same DBC (name, id, length, cycle time, senders, signal set incl. CRC/counter).
    blocks = {}
    for block in out.split("Name:")[1:]:
        fields = dict(re.findall(r"^\s*(Id|Length|Cycle time|Senders):\s+(.+)$", block, re.M))
        tree = block.split("Signal tree:")[1]
        blocks[block.split()[0]] = (fields, re.findall(r"\+-- (\w+)", tree))
    assert set(blocks) == set(CODEC.messages) | set(CODEC.diagnostic)
    for name, frame_id in CODEC.diagnostic.items():  # UDS over ISO-TP: one raw 64-bit signal
        fields, signals = blocks[name]
        assert int(fields["Id"], 16) == frame_id and fields["Length"] == "8 bytes", name
        assert fields["Cycle time"] in ("- ms", "0 ms") and len(signals) == 1, name
    for name, spec in CODEC.messages.items():
        fields, signals = blocks[name]
        assert int(fields["Id"], 16) == spec.frame_id, name
        assert fields["Length"] == f"{spec.length} bytes", name
        assert fields["Cycle time"] == f"{round(spec.cycle_time_s * 1000)} ms", name
        assert fields["Senders"].split(",")[0].strip() == spec.senders[0], name
        crc = "CRC16" if spec.crc_bits == 16 else "CRC8"
        assert set(signals) == {s.name for s in spec.signals} | {crc, "ALIVE"}, name


def test_python_can_logger_attaches_to_the_loopback_bus(tmp_path) -> None:
    sent = _frames(20)
    lines: list[str] = []
    with BusServer() as server:
        err_path = tmp_path / "logger.err"
        logger = spawn("-m", "can.logger", "-i", "remote", "-c", server.url,
                       stdout=subprocess.PIPE, stderr=err_path.open("w"),
                       env={**os.environ, "PYTHONUNBUFFERED": "1",
                            "PYTHONFAULTHANDLER": "1"})
        reader = threading.Thread(target=lambda: lines.extend(logger.stdout), daemon=True)
        reader.start()
        bus = open_bus(server.spec)
        try:
            # Probe until the logger prints a frame: it is attached (no fixed sleep).
            probe = CODEC.message("CTRL_STATUS", {}, 0)
            probe_hex = " ".join(f"{b:02x}" for b in probe.data)
            deadline = time.monotonic() + 20
            while not any(probe_hex in line.lower() for line in lines):
                assert time.monotonic() < deadline, "can.logger never attached"
                bus.send(probe)
                time.sleep(0.1)
            for msg in sent:
                bus.send(msg)
            expected_hex = [" ".join(f"{b:02x}" for b in m.data) for m in sent]
            deadline = time.monotonic() + 10
            while not any(expected_hex[-1] in line.lower() for line in lines):
                assert time.monotonic() < deadline, "frames missing in the logger output"
                time.sleep(0.05)
        finally:
            bus.shutdown()
            interrupt_and_wait(logger, 10, err_path)
    printed = [line.lower() for line in lines if probe_hex not in line.lower()]
    order = [next(i for i, line in enumerate(printed) if h in line) for h in expected_hex]
    assert order == sorted(order)  # all 20 frames, in the order sent
