"""Row logs (can_db/process/rowlog.py): the CSV they become equals a line-by-line CSV writer's,
a SIGKILLed writer loses no finished row, the live tail sees rows as they come."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from can_db.process.rowlog import RowLog, RowTail, finish_all, finish_rows, read_rows, rows_path
from controller.runtime.process import TIMING_COLUMNS, TIMING_FORMATS
from tests.helpers_proc import spawn


def _line_by_line(columns, formats, rows) -> str:
    """What the writers did before: one formatted line per row."""
    line = ",".join(formats) + "\n"
    return ",".join(columns) + "\n" + "".join(line % tuple(r) for r in rows)


def test_closed_log_is_the_csv_a_line_writer_gives(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cols = ["t_s", "x", "tiny", "huge"]
    rows = [(k * 0.01, float(rng.normal()), float(rng.normal()) * 1e-12,
             float(rng.normal()) * 1e15) for k in range(500)]
    rows.append((5.0, float("nan"), float("inf"), -0.0))
    log = RowLog(tmp_path / "t.csv", cols, ["%.9g"] * 4)
    for r in rows:
        log.write(r)
    assert log.path.is_file() and not (tmp_path / "t.csv").exists()  # row file while open
    log.close()
    log.close()  # idempotent
    assert not log.path.exists()
    assert (tmp_path / "t.csv").read_text() == _line_by_line(cols, ["%.9g"] * 4, rows)


def test_timing_formats_match_the_old_f_strings(tmp_path: Path) -> None:
    log = RowLog(tmp_path / "timing.csv", TIMING_COLUMNS, TIMING_FORMATS)
    log.write((-1, 0.0149999, 344.71, 791.55, 0.0, True, 15, 0, 1, False, 0.25))
    log.close()
    old = (f"{-1},{0.0149999:.3f},{344.71:.1f},{791.55:.1f},{0.0:.1f},{int(True)},{15},"
           f"{0},{1},{int(False)},{0.25!r}\n")
    assert (tmp_path / "timing.csv").read_text().splitlines()[1] + "\n" == old


def test_wrong_number_of_formats_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="2 columns but 1 formats"):
        RowLog(tmp_path / "x.csv", ["a", "b"], ["%d"])


def test_torn_last_row_is_dropped_and_junk_is_not_a_row_file(tmp_path: Path) -> None:
    log = RowLog(tmp_path / "t.csv", ["a", "b"], ["%d", "%.1f"])
    for k in range(3):
        log.write((k, k / 2))
    with open(log.path, "ab") as fh:
        fh.write(b"\x00" * 11)  # a row cut mid-write
    assert read_rows(log.path)["a"].tolist() == [0.0, 1.0, 2.0]
    (tmp_path / "junk.csv.rows").write_bytes(b"not a row file")
    assert read_rows(tmp_path / "junk.csv.rows") == {}
    assert finish_rows(tmp_path / "junk.csv") is False
    assert finish_rows(tmp_path / "missing.csv") is False


def test_sigkilled_writer_loses_no_finished_row(tmp_path: Path) -> None:
    csv_path = tmp_path / "trace.csv"
    code = ("import sys, time\n"
            "from can_db.process.rowlog import RowLog\n"
            "log = RowLog(sys.argv[1], ['k', 'v'], ['%d', '%.9g'])\n"
            "k = 0\n"
            "while True:\n"
            "    log.write((k, k * 0.5))\n"
            "    k += 1\n"
            "    time.sleep(0.0005)\n")
    child = spawn("-c", code, str(csv_path), stderr=subprocess.PIPE)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and len(read_rows(rows_path(csv_path)).get("k", ())) < 200:
        time.sleep(0.02)
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=10)
    on_disk = read_rows(rows_path(csv_path))
    n = len(on_disk["k"])
    assert n >= 200
    assert on_disk["k"].tolist() == list(range(n))  # every row, in order, none torn
    assert finish_all(tmp_path) == [csv_path]
    lines = csv_path.read_text().splitlines()
    assert lines[0] == "k,v" and len(lines) == n + 1 and lines[-1] == f"{n - 1},{(n - 1) * 0.5:.9g}"
    assert not rows_path(csv_path).exists()


def test_command_line_turns_a_left_row_file_into_its_csv(tmp_path: Path) -> None:
    log = RowLog(tmp_path / "t.csv", ["a"], ["%d"])
    log.write((7,))
    (tmp_path / "junk.csv.rows").write_bytes(b"junk")
    child = spawn("-m", "can_db.process.rowlog", str(log.path), str(tmp_path / "junk.csv.rows"),
                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = child.communicate(timeout=60)
    assert child.returncode == 1 and "written" in out and "not a row file" in err
    assert (tmp_path / "t.csv").read_text() == "a\n7\n"


def test_tail_sees_new_rows_follows_a_new_file_and_reads_past_the_finish(tmp_path: Path) -> None:
    csv_path = tmp_path / "truth.csv"
    tail = RowTail(rows_path(csv_path))
    assert tail.rows() == {} and not tail.opened
    log = RowLog(csv_path, ["t_s"], ["%.9g"])
    assert tail.rows() == {}  # header only
    for k in range(3):
        log.write((k,))
    assert tail.rows()["t_s"].tolist() == [0, 1, 2]
    log.write((3,))
    log.close()  # row file finished and removed: the open descriptor still has row 3
    assert tail.rows()["t_s"].tolist() == [3]
    assert tail.rows() == {}
    log2 = RowLog(csv_path, ["t_s"], ["%.9g"])  # a restarted writer: a new file
    log2.write((0.5,))
    assert tail.rows()["t_s"].tolist() == [0.5]
    log2.close()
    tail.close()


def test_plant_and_controller_leave_csv_files_after_a_normal_stop(tmp_path: Path) -> None:
    """Cross-process: a lockstep run over the bus ends with the CSV files and no row files."""
    from harness.analysis.run_data import load_timing_csv, load_truth_csv
    from harness.report.run_report import run_and_report
    from harness.run.spec import RunSpec

    res = run_and_report(RunSpec(scenario="dlc-paper", controller="passive",
                                    out_dir=tmp_path, duration_s=1.0, make_plots=False,
                                    make_rrd=False))
    assert res.reason == "finished"
    assert not list(tmp_path.glob("*.rows"))
    truth = load_truth_csv(tmp_path / "truth.csv")
    assert len(truth["t_s"]) == 101 and truth["t_s"][-1] == pytest.approx(1.0)  # t = 0 … 1 s
    assert load_timing_csv(tmp_path / "controller_timing.csv")["cycle"].tolist() == \
        list(range(100))  # one row per answered SYNC
