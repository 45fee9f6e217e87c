"""Nothing is lost: logs stay readable and metrics.json is written when processes die."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import can
import psutil

from can_db.process.rowlog import read_rows, rows_path
from harness.analysis.run_data import load_truth_csv
from harness.report.run_report import run_and_report
from harness.run.marker import stale_note
from harness.run.spec import RunSpec
from tests.helpers_proc import live_children, spawn


def _readable(out: Path) -> tuple[int, int]:
    """(truth rows, bus frames) that standard readers get back from the files."""
    truth = load_truth_csv(out / "truth.csv")
    frames = sum(1 for _ in can.LogReader(str(out / "bus.blf")))
    return len(truth.get("t_s", [])), frames


def test_killed_plant_still_gives_readable_logs_and_metrics(tmp_path: Path) -> None:
    result = run_and_report(RunSpec(scenario="dlc-paper", controller="lmpc",
                                       out_dir=tmp_path, mode="realtime", duration_s=4.0,
                                       faults=["kill-plant@1.5s"], make_plots=False,
                                       make_rrd=False))
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert result.reason.startswith("plant exited with code -9")
    assert metrics["reason"] == result.reason and metrics["completed"] is False
    rows, frames = _readable(tmp_path)
    assert 140 <= rows <= 200 and frames > 5 * 140  # everything up to the kill
    assert not live_children()


def test_sigterm_of_the_plant_flushes_its_summary(tmp_path: Path) -> None:
    result = run_and_report(RunSpec(scenario="dlc-paper", controller="passive",
                                       out_dir=tmp_path, duration_s=2.0, make_plots=False,
                                       make_rrd=False))
    summary = json.loads((tmp_path / "plant_summary.json").read_text())
    assert result.reason == "finished" and summary["cycles"] == 200
    # the controller was stopped with SIGTERM by the harness: its summary is complete too
    ctrl = json.loads((tmp_path / "controller_summary.json").read_text())
    assert ctrl["cycles_answered"] == 200


def test_sigkill_of_the_harness_leaves_readable_logs_and_no_orphans(tmp_path: Path) -> None:
    out = tmp_path / "run"
    harness = spawn("-m", "harness.cli", "run", "dlc-paper", "--controller", "lmpc",
                    "--mode", "realtime", "--out", str(out), "--no-plots", "--no-rrd",
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # until about a second of driving is on disk
        # while the plant runs its trace is a row file (can_db/process/rowlog.py)
        if len(read_rows(rows_path(out / "truth.csv")).get("t_s", ())) > 100:
            break
        time.sleep(0.1)
    descendants = psutil.Process(harness.pid).children(recursive=True)
    harness.send_signal(signal.SIGKILL)
    harness.wait(timeout=10)
    gone, alive = psutil.wait_procs(descendants, timeout=10)
    assert not alive, [p.cmdline() for p in alive]  # children die with their parent
    rows, frames = _readable(out)
    # the BLF is flushed every 0.2 s: at most that much of the bus is missing
    assert rows > 100 and frames >= 5 * (rows - 40)
    assert len(gone) >= 3
    # the marker of the killed harness stays; the next look at the directory names it
    note = stale_note(out)
    assert note is not None and note.startswith(f"{out} holds an incomplete run")
    assert f"pid {harness.pid}" in note and "run dlc-paper --controller lmpc" in note
