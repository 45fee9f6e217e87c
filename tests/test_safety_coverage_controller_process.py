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


def test_a_refused_request_is_a_warning_once_per_service_and_code_then_debug(
        caplog: pytest.LogCaptureFixture) -> None:
    """Every refusal is counted by "service/NRC"; the first of each is a warning (what a
    storm of requests cannot flood), the following ones debug lines with the count."""
    server = _server(unlocked=False)
    link = DiagLink(Codec(), server, wheel_radius_m=0.3, clock=lambda: 0.0)
    bus = _Bus()
    with caplog.at_level(logging.DEBUG, logger="rhonn-controller"):
        link.on_frame(bus, _diag(link, 0x02, 0x10, 0x03), STILL)   # extended session: 50 03
        assert [r for r in caplog.records if "refused" in r.getMessage()] == []
        for _ in range(2):                                        # locked: 7F 11 33
            link.on_frame(bus, _diag(link, 0x02, 0x11, 0x01), STILL)
        link.on_frame(bus, _diag(link, 0x02, 0x3E, 0x05), STILL)   # 7F 3E 12
        link.on_frame(bus, _diag(link, 0x05, 0x2E, 0xFD, 0x10, 0x7B, 0x7D), STILL)  # 7F 2E 33
    refusals = [(r.levelno, r.getMessage()) for r in caplog.records
                if "refused" in r.getMessage()]
    assert refusals == [
        (logging.WARNING, "UDS request 11 01 refused: NRC 0x33 (1 so far)"),
        (logging.DEBUG, "UDS request 11 01 refused: NRC 0x33 (2 so far)"),
        (logging.WARNING, "UDS request 3e 05 refused: NRC 0x12 (1 so far)"),
        (logging.WARNING, "UDS request 2e fd 10 refused: NRC 0x33 (1 so far)"),
    ]
    assert server.refused == {"11/33": 2, "3E/12": 1, "2E/33": 1}
    assert [bytes(m.data[:4]) for m in bus.sent] == [
        b"\x06\x50\x03\x00", b"\x03\x7f\x11\x33", b"\x03\x7f\x11\x33", b"\x03\x7f\x3e\x12",
        b"\x03\x7f\x2e\x33"]


@pytest.mark.parametrize("response", [None, b"", b"\x7f", b"\x7f\x11", b"\x7e\x00",
                                      b"\x51\x01\x7f"])
def test_only_a_whole_negative_response_is_logged_as_a_refusal(
        response: bytes | None, caplog: pytest.LogCaptureFixture) -> None:
    """A suppressed, positive or truncated response is no refusal: nothing is logged and
    nothing is looked up."""
    from controller.runtime.uds import UdsReply

    link = DiagLink(Codec(), _server(), wheel_radius_m=0.3, clock=lambda: 0.0)
    with caplog.at_level(logging.DEBUG, logger="rhonn-controller"):
        link._log_refusal(b"\x11\x01", UdsReply(response))
    assert caplog.records == []


@pytest.mark.parametrize(("sub", "action", "answer"), [
    (0x01, Action.HARD_RESET, b"\x02\x51\x01"), (0x03, Action.SOFT_RESET, b"\x02\x51\x03"),
    (0x81, Action.HARD_RESET, None), (0x83, Action.SOFT_RESET, None)])
def test_a_reset_is_answered_only_once_its_work_is_done(
        sub: int, action: Action, answer: bytes | None) -> None:
    """The reset's response is held (the caller resets first) and sent once by
    respond_pending; a suppressed one is never sent."""
    link = DiagLink(Codec(), _server(), wheel_radius_m=0.3, clock=lambda: 0.0)
    bus = _Bus()
    assert link.on_frame(bus, _diag(link, 0x02, 0x11, sub), STILL) is action
    assert bus.sent == []
    link.respond_pending(bus)
    assert [bytes(m.data[:3]) for m in bus.sent] == ([answer] if answer else [])
    link.respond_pending(bus)  # nothing held any more
    assert len(bus.sent) == (1 if answer else 0)


def test_a_coding_without_a_fault_seed_runs_with_the_default_seed() -> None:
    """The coded options are replaced in the command line a hard reset execs; a coding
    without ``fault_seed`` gives the seed a start without --fault-seed has."""
    base = ["--bus", "virtual:t", "--no-secoc", "--fault-seed", "9", "--controller", "lmpc"]
    default = process._parser().parse_args(["--bus", "virtual:t", "--controller",
                                            "lmpc"]).fault_seed
    args = process._parser().parse_args(process.apply_coding(base, {"controller": "passive"}))
    assert (args.controller, args.fault_seed, args.fault) == ("passive", default, [])
    assert default == 2
