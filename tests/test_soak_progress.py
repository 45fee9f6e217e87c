"""`rhonn-bench soak` progress lines come from the controller's growing timing row file."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from can_db.process.rowlog import RowLog
from controller.runtime.process import TIMING_COLUMNS, TIMING_FORMATS
from harness.bench import soak


def test_progress_counts_cycles_misses_and_worst_turnaround(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(soak, "PROGRESS_EVERY_S", 0.05)
    csv_path = tmp_path / "controller_timing.csv"
    log = RowLog(csv_path, TIMING_COLUMNS, TIMING_FORMATS)
    for k in range(30):  # 2 misses, worst turnaround 4.5 ms
        log.write((k, k * 0.01, 20.0, 4500.0 if k == 7 else 300.0, 10000.0, 0, 0, 0, 1,
                   k in (7, 20), float("nan")))
    stop = threading.Event()
    ticker = threading.Thread(target=soak._progress, args=(csv_path, 1.0, stop))
    ticker.start()
    time.sleep(0.3)
    stop.set()
    ticker.join(timeout=5)
    log.close()
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert "30 cycles, deadline misses 2, turnaround max 4.50 ms" in last
