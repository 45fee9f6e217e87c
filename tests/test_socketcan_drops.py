"""Drops counted where SocketCAN drops them: the kernel's per-socket count, read with
SO_MEMINFO (can_db/transport/socketcan.py), reported per node in ``metrics.json``.

This kernel has no CAN, so the counter is checked on the same kernel path with UDP on
127.0.0.1 (a full receive buffer drops and counts per socket the same way); the SocketCAN
bus itself is exercised on vcan0 by the SocketCAN check (docs/vcan.md: its flood step)."""

from __future__ import annotations

import socket
import time

from can_db.transport.socketcan import size_receive_buffer, socket_drops
from harness.analysis.run_metrics import rx_drops


def _udp_pair() -> tuple[socket.socket, socket.socket]:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    return rx, socket.socket(socket.AF_INET, socket.SOCK_DGRAM)


def test_the_kernels_drop_count_is_every_datagram_the_full_buffer_refused() -> None:
    rx, tx = _udp_pair()
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a few datagrams
        assert socket_drops(rx) == 0
        sent = 400
        for i in range(sent):
            tx.sendto(i.to_bytes(16, "little"), rx.getsockname())
        received = 0
        idle = 0
        while idle < 3:  # until 3 reads 20 ms apart find nothing (a deferred softirq)
            try:
                rx.recv(64)
            except BlockingIOError:
                idle += 1
                time.sleep(0.02)
                continue
            received, idle = received + 1, 0
        assert 0 < received < sent
        assert socket_drops(rx) == sent - received
    finally:
        rx.close()
        tx.close()


def test_a_closed_socket_reports_no_count() -> None:
    rx, tx = _udp_pair()
    tx.close()
    rx.close()
    assert socket_drops(rx) is None


def test_the_receive_buffer_is_sized_as_asked_or_capped_by_the_kernel() -> None:
    rx, tx = _udp_pair()
    try:
        got = size_receive_buffer(rx, 1 << 20)
        default = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        base = default.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        default.close()
        # root: forced to 1 MiB (the kernel reports twice what it was given); otherwise
        # capped at rmem_max, never below the default
        assert got >= base and (got == 2 << 20 or got <= 2 * _rmem_max())
    finally:
        rx.close()
        tx.close()


def _rmem_max() -> int:
    with open("/proc/sys/net/core/rmem_max") as f:
        return int(f.read())


def test_metrics_report_each_nodes_socket_drops_beside_the_hubs() -> None:
    plant = {"rx_drops": {"secoc_pending_full": 0}, "bus_stats": {"rx_dropped": 3}}
    controller = {"rx_drops": {}, "bus_stats": {"rx_dropped": 0}}
    out = rx_drops(plant, controller, None, recorder_socket=41)
    assert out["socket"] == {"controller": 0, "plant": 3, "bus-recorder": 41}
    assert out["hub"] == {}
    # the local bus: no socket counts, the hub's per node
    local = rx_drops({"bus_stats": {"sent": 9}}, {}, {"nodes": [{"name": "n:1", "dropped": 2}]})
    assert "socket" not in local and local["hub"] == {"n:1": 2}


def test_the_count_outlives_the_socket_for_the_summary_written_after_shutdown(
        monkeypatch) -> None:
    """A process writes its summary after closing its bus: ``stats()`` then gives the count
    the socket had at ``shutdown`` (the socket itself is gone). The bus object is built
    around a UDP socket here (this kernel has no CAN); python-can's own shutdown is
    replaced by a plain close."""
    from can.interfaces.socketcan import SocketcanBus

    from can_db.transport.socketcan import CountingSocketcanBus

    rx, tx = _udp_pair()
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    for i in range(300):
        tx.sendto(i.to_bytes(16, "little"), rx.getsockname())
    tx.close()
    bus = object.__new__(CountingSocketcanBus)
    bus.socket, bus._closed, bus._drops_at_shutdown = rx, False, None
    monkeypatch.setattr(SocketcanBus, "shutdown", lambda self: self.socket.close())
    open_count = bus.stats()["rx_dropped"]
    assert open_count > 0
    bus.shutdown()
    assert socket_drops(rx) is None and bus.stats() == {"rx_dropped": open_count}
    bus.shutdown()  # twice: the kept count stays
    assert bus.stats() == {"rx_dropped": open_count}


def test_the_dump_batches_its_lines_off_a_terminal() -> None:
    import io

    from can_db.cli import LineBatcher

    class Stream(io.StringIO):
        flushes = 0

        def flush(self) -> None:
            self.flushes += 1

    stream = Stream()
    out = LineBatcher(stream, every_s=3600.0)
    for i in range(100):
        out.add(f"line {i}")
    assert stream.flushes == 0 and out.pending  # written, not flushed yet
    out.flush()
    assert stream.flushes == 1 and not out.pending
    assert stream.getvalue().splitlines() == [f"line {i}" for i in range(100)]
    at_once = LineBatcher(stream, every_s=0.0)  # a terminal: every line flushed
    at_once.add("x")
    assert stream.flushes == 2 and not at_once.pending


def test_a_bus_without_a_kernel_count_reports_none() -> None:
    from can_db.transport.socketcan import rx_dropped

    class LocalLike:
        def stats(self) -> dict:
            return {"sent": 3, "reconnects": 0}

    assert rx_dropped(LocalLike()) is None and rx_dropped(object()) is None
