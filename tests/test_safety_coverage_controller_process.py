"""The controller process's own error paths, in-process: a timing log or a summary that
cannot be written (disk full) never stops control, a malformed boot counter, and the
diagnostic link's frame filter and its wait for STmin-spaced frames.

The disk-full cases are real: the log's descriptor is moved onto ``/dev/full`` (every write
fails with ENOSPC), or the CSV's temporary name is taken by a directory."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import can
import pytest

from can_db.codec import Codec
from controller.core.params import load_vehicle_params
from controller.runtime import process
from controller.runtime.process import DiagLink, TimingLog, build_run
from controller.runtime.uds import Action
from tests.test_uds_server import _Node, _server

STILL = _Node({"VX_EST": 0.0}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0})


def _node(tmp_path: Path):
    """A real controller node (passive controller, no SecOC) of the process's own build."""
    args = process._parser().parse_args(["--bus", "virtual:t", "--controller", "passive",
                                         "--no-secoc"])
    return build_run(args, load_vehicle_params(), Codec()).node


def _onto_dev_full(fd: int) -> None:
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        os.dup2(full, fd)
    finally:
        os.close(full)


def test_a_full_disk_stops_the_timing_log_not_the_cycles(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    node = _node(tmp_path)
    timing = TimingLog(str(tmp_path / "timing.csv"))
    timing.write(node, 1000, 10_000_000, False)  # opens the row file
    assert timing._log is not None
    _onto_dev_full(timing._log._fd)  # type: ignore[arg-type]
    with caplog.at_level(logging.ERROR, logger="rhonn-controller"):
        for _ in range(3):
            timing.write(node, 1000, 10_000_000, False)
    assert timing.rows == 4  # every cycle counted (the summary's cycles_answered)
    assert timing.write_error == "OSError: [Errno 28] No space left on device"
    assert len(caplog.records) == 1  # one error line, not one a cycle
    assert "control goes on" in caplog.records[0].getMessage()
    timing.close()  # the CSV of the row written before the disk filled
    assert (tmp_path / "timing.csv").read_text().count("\n") == 2  # header + 1 row


def test_a_timing_csv_that_cannot_be_written_keeps_its_rows_and_the_first_error(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    node = _node(tmp_path)
    timing = TimingLog(str(tmp_path / "timing.csv"))
    timing.write(node, 1000, 10_000_000, False)
    (tmp_path / "timing.csv.tmp").mkdir()  # the CSV's temporary name is taken
    with caplog.at_level(logging.ERROR, logger="rhonn-controller"):
        timing.close()
        timing.close()  # idempotent: nothing more is tried or logged
    assert timing.write_error is not None and timing.write_error.startswith("IsADirectoryError")
    assert len(caplog.records) == 1
    assert (tmp_path / "timing.csv.rows").is_file()  # the rows stay, readable
    assert not (tmp_path / "timing.csv").exists()
    # a write error before the close is the one the summary keeps
    other = TimingLog(str(tmp_path / "other.csv"))
    other.write_error = "OSError: earlier"
    (tmp_path / "other.csv.tmp").mkdir()
    other.close()
    assert other.write_error == "OSError: earlier"


def test_a_summary_that_cannot_be_written_is_logged(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "summary.json"
    path.mkdir()
    with caplog.at_level(logging.ERROR, logger="rhonn-controller"):
        process._write_summary(str(path), {"cycles_answered": 1})  # no exception
    assert "cannot be written" in caplog.text and str(path) in caplog.text


@pytest.mark.parametrize(("value", "count"), [(None, 1), ("4", 5), ("-3", 1), ("x", 1),
                                              ("", 1)])
def test_the_boot_counter_of_a_start(value: str | None, count: int,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A hard reset passes its count on; anything else (missing, negative, not a number)
    counts as a first start."""
    if value is None:
        monkeypatch.delenv(process.BOOT_COUNT_ENV, raising=False)
    else:
        monkeypatch.setenv(process.BOOT_COUNT_ENV, value)
    assert process._boot_count() == count


class _Bus:
    def __init__(self) -> None:
        self.sent: list[can.Message] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)


def _diag(link: DiagLink, *data: int, **kw: bool) -> can.Message:
    return can.Message(arbitration_id=link.req_id, data=bytes(data).ljust(8, b"\xcc"),
                       **{"is_extended_id": False, **kw})


@pytest.mark.parametrize("kind", ["is_extended_id", "is_remote_frame", "is_error_frame",
                                  "is_fd"])
def test_a_diagnostic_frame_of_another_kind_is_ignored(kind: str) -> None:
    """Only classical data frames with a standard id are ISO-TP frames: a valid request in
    any other frame gets no answer and leaves no reception open."""
    link = DiagLink(Codec(), _server(), wheel_radius_m=0.3, clock=lambda: 0.0)
    bus = _Bus()
    assert link.on_frame(bus, _diag(link, 0x02, 0x11, 0x03, **{kind: True}), STILL) \
        is Action.NONE
    assert bus.sent == [] and not link.isotp.receiving
    # the same request as a data frame is a soft reset
    assert link.on_frame(bus, _diag(link, 0x02, 0x11, 0x03), STILL) is Action.SOFT_RESET


def test_the_bus_wait_ends_when_the_next_consecutive_frame_is_due() -> None:
    """A segmented response is released STmin apart (the tester's flow control): the loop's
    bus wait is cut to the next release, never below 0."""
    now = [100.0]
    link = DiagLink(Codec(), _server(), wheel_radius_m=0.3, clock=lambda: now[0])
    bus = _Bus()
    assert link.timeout(0.1) == 0.1  # nothing queued
    link.on_frame(bus, _diag(link, 0x03, 0x22, 0xFD, 0x10), STILL)  # the coding: > 7 bytes
    assert [m.data[0] >> 4 for m in bus.sent] == [1]  # first frame out, waiting for FC
    link.on_frame(bus, _diag(link, 0x30, 0x00, 20), STILL)  # CTS, BS 0, STmin 20 ms
    assert [m.data[0] >> 4 for m in bus.sent] == [1, 2]  # the first CF at once
    assert link.timeout(5.0) == pytest.approx(0.020)
    assert link.timeout(0.005) == 0.005
    now[0] += 0.050
    assert link.timeout(5.0) == 0.0  # overdue: no wait
    link.poll(bus)  # the CFs due at +20 ms and +40 ms, in sequence
    assert [m.data[0] for m in bus.sent[1:]] == [0x21, 0x22, 0x23]
