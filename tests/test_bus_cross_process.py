"""The websocket bus server across real OS processes: completeness, order, server loss,
specs (the local bus has its own tests in test_localbus.py)."""

from __future__ import annotations

import subprocess

import pytest

from can_db.codec import Codec, Decoded
from can_db.monitor import RxMonitor
from can_db.transport.bus import (
    BusDisconnected,
    BusSpecError,
    open_bus,
    parse_spec,
    resolve_auto,
    resolve_bus,
)
from can_db.transport.server import BusServer
from tests.helpers_proc import live_children, spawn

CODEC = Codec()


def test_1000_frames_between_two_processes_arrive_complete_and_in_order() -> None:
    cycles = 200  # 5 frames per cycle -> 1000 frames, paced at 10 ms like the plant
    with BusServer() as server:
        bus = open_bus(server.spec)
        try:
            sender = spawn("-m", "can_db.cli", "demo-tx", "--bus", server.spec,
                           "--cycles", str(cycles))
            monitor = RxMonitor(CODEC, ["DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS",
                                        "VEHICLE_EST", "SYNC"])
            names, sync_cycles = [], []
            while len(names) < cycles * 5:
                msg = bus.recv(timeout=10.0)
                assert msg is not None, f"timed out after {len(names)} frames"
                result = monitor.process(msg, now_s=len(names) * 0.002)
                assert isinstance(result, Decoded), result
                names.append(result.name)
                if result.name == "SYNC":
                    sync_cycles.append(int(result.values["CYCLE"]))
            assert sender.wait(timeout=20) == 0
        finally:
            bus.shutdown()
    assert sync_cycles == list(range(cycles))
    assert names[:5] == ["DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST",
                         "SYNC"] and names == names[:5] * cycles
    assert monitor.rejection_counts() == {}  # no CRC, counter or range fault on the way
    assert not live_children()


def test_client_gets_a_clear_error_when_the_server_dies() -> None:
    server = BusServer().start()
    bus = open_bus(server.spec)
    try:
        server.process.kill()  # type: ignore[union-attr]  # SIGKILL: no goodbye
        server.process.wait()  # type: ignore[union-attr]
        # An error, not a wait for the timeout: a recv that waited its 5 s out returns None,
        # so every call before the error must have returned a frame (there are none).
        timed_out = 0
        with pytest.raises(BusDisconnected):
            for _ in range(3):
                if bus.recv(timeout=5.0) is None:
                    timed_out += 1
        assert timed_out == 0
        with pytest.raises(BusDisconnected):
            for _ in range(3):
                bus.send(CODEC.message("SYNC", {}, 0))
    finally:
        bus.shutdown()
        server.stop()


def test_connecting_to_no_server_is_a_clear_error() -> None:
    with BusServer() as server:
        port = server.port
    with pytest.raises(BusDisconnected, match="cannot connect"):
        open_bus(f"remote:ws://127.0.0.1:{port}/")


def test_server_cli_serves_and_stops_cleanly() -> None:
    proc = spawn("-m", "can_db.cli", "serve", stdout=subprocess.PIPE)
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        spec = line.split("spec: ")[1].rstrip(")\n")
        bus_a, bus_b = open_bus(spec), open_bus(spec)
        bus_a.send(CODEC.message("SYNC", {"CYCLE": 42}, 0))
        msg = bus_b.recv(timeout=5.0)
        assert msg is not None and CODEC.decode_message(msg).values["CYCLE"] == 42
        bus_a.shutdown()
        bus_b.shutdown()
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0
    assert not live_children()  # the server child went down with the CLI


def test_bus_specs() -> None:
    assert parse_spec("socketcan:vcan0") == ("socketcan", "vcan0")
    assert parse_spec("remote:ws://127.0.0.1:5000/") == ("remote", "ws://127.0.0.1:5000/")
    assert parse_spec("virtual:unit") == ("virtual", "unit")
    assert parse_spec("auto") == ("auto", "")
    for bad in ("", "vcan0", "pcan:1", "remote:ws://10.0.0.1:5000/", "socketcan:"):
        with pytest.raises(BusSpecError):
            parse_spec(bad)


def test_remote_new_starts_a_websocket_server_and_auto_a_local_hub() -> None:
    spec, server = resolve_bus("remote:new")
    try:
        assert server is not None and spec == server.spec and server.alive()
        bus = open_bus(spec)
        bus.shutdown()
    finally:
        if server is not None:
            server.stop()
    spec, hub = resolve_auto(vcan="rhonn_no_such_if")
    try:
        assert hub is not None and spec == hub.spec and spec.startswith("local:")
    finally:
        if hub is not None:
            hub.stop()
    with pytest.raises(BusSpecError, match="resolve"):
        open_bus("remote:new")
