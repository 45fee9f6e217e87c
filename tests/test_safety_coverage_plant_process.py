"""The plant process's own error paths, in-process: a run whose files cannot be written (disk
full) ends with that reason and exit code 1, no traceback, its summary written; a summary
that cannot be written is named on stderr; a served run's parser never exits the process;
a command line without an end is cut at its bound and the next command is read.

The disk-full cases are real: the trace's descriptor is moved onto ``/dev/full`` (every
write fails with ENOSPC), or a name the plant writes is taken by a directory. The runs are
20 ms real-time runs on python-can's in-process virtual bus, without a controller."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import can
import pytest

from can_db.codec import Codec
from can_db.process.argcheck import UsageError
from plant_sim import process
from plant_sim.process import COMMAND_MAX_BYTES, PlantRun, _CommandLines, run_one


def _run(tmp_path: Path) -> PlantRun:
    args = process._parser().parse_args([
        "--bus", "virtual:plant-edges", "--scenario", "dlc-paper", "--mode", "realtime",
        "--duration", "0.02", "--no-secoc", "--trace", str(tmp_path / "truth.csv"),
        "--summary", str(tmp_path / "summary.json")])
    return PlantRun(args, Codec())


def _run_one(run: PlantRun, prepare=None) -> tuple[int, dict]:
    node, trace = run.start()
    if prepare is not None:
        prepare(trace)
    bus = can.Bus(interface="virtual", channel="plant-edges")
    try:
        return run_one(bus, run, node, trace, lambda: False, "loaded")
    finally:
        bus.shutdown()


def test_a_full_disk_ends_the_run_with_its_reason(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def disk_full(trace: process.TraceWriter) -> None:
        full = os.open("/dev/full", os.O_WRONLY)
        os.dup2(full, trace._log._fd)  # type: ignore[union-attr, arg-type]
        os.close(full)

    code, stats = _run_one(_run(tmp_path), disk_full)
    reason = "error: cannot write the run's files: No space left on device"
    assert (code, stats["reason"]) == (1, reason)
    err = capsys.readouterr().err
    assert err == f"rhonn-plant: {reason}\n"  # one line, no traceback
    assert json.loads((tmp_path / "summary.json").read_text())["reason"] == reason
    assert (tmp_path / "truth.csv").read_text().count("\n") == 1  # the header only


def test_a_trace_that_cannot_be_finished_keeps_its_rows(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(tmp_path)
    (tmp_path / "truth.csv.tmp").mkdir()  # the CSV's temporary name is taken
    code, stats = _run_one(run)
    where = tmp_path / "truth.csv.tmp"
    reason = f"error: cannot write the run's files: Is a directory ({where})"
    assert (code, stats["reason"]) == (1, reason)
    assert stats["cycles"] == 2  # the run itself finished
    assert capsys.readouterr().err == f"rhonn-plant: {reason}\n"
    assert json.loads((tmp_path / "summary.json").read_text())["reason"] == reason
    assert (tmp_path / "truth.csv.rows").is_file() and not (tmp_path / "truth.csv").exists()


def test_a_summary_that_cannot_be_written_is_named_and_the_run_counts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(tmp_path)
    (tmp_path / "summary.json").mkdir()
    code, stats = _run_one(run)
    assert (code, stats["reason"]) == (0, "finished")
    err = capsys.readouterr().err
    assert err.startswith("rhonn-plant: error: cannot write the run's files: Is a directory")
    assert err.rstrip("\n").endswith(f"({tmp_path / 'summary.json'})")
    assert err.count("\n") == 1
    assert (tmp_path / "truth.csv").read_text().count("\n") == 4  # header + 3 rows


def test_a_served_runs_parser_raises_instead_of_exiting() -> None:
    """stdout is the control channel: argparse's exit (help, version) must not end a
    serving process or print there."""
    parser = process._run_parser(process._parser().parse_args(["--bus", "virtual:t",
                                                               "--serve"]))
    with pytest.raises(UsageError, match="exit 0"):
        parser.exit(0)
    with pytest.raises(UsageError, match="bye"):
        parser.exit(2, "bye")


def test_a_command_line_without_an_end_is_cut_at_its_bound() -> None:
    """1.5 MiB without a newline: the first MiB (and a read) is returned as ``<too long>``
    (one error line), the rest as its own line, then the next command as sent; the buffer
    never holds more than the bound and a read."""
    read_fd, write_fd = os.pipe()
    text = b"x" * (COMMAND_MAX_BYTES * 3 // 2) + b"\n" + b'{"quit": true}\n'
    writer = threading.Thread(target=lambda: (os.write(write_fd, text), os.close(write_fd)))
    writer.start()
    try:
        lines = _CommandLines(read_fd)
        first = lines.next(lambda: False)
        assert first == b"<too long>"
        rest = lines.next(lambda: False)
        assert rest is not None and 0 < len(rest) < COMMAND_MAX_BYTES and set(rest) == {ord("x")}
        assert lines.next(lambda: False) == b'{"quit": true}'
        assert lines.next(lambda: False) is None  # end of input
    finally:
        writer.join()
        os.close(read_fd)
