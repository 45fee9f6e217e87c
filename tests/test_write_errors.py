"""A run whose files cannot be written (disk full, a file-size limit) ends with the real
reason, no traceback, and a metrics.json that says it.

The write error is made real with RLIMIT_FSIZE on the harness and its children: a write
past the limit fails with EFBIG ("File too large"; Python ignores SIGXFSZ), through the same
OSError paths as ENOSPC, without a mount or root."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from can_db.process.errors import error_text
from can_db.transport.bus import resolve_bus
from harness.report import run_report
from harness.run.runner import write_metrics
from harness.run.spec import RunSpec
from tests.test_uds_reset_e2e import COVERAGE_ENV, Controller, Plant

pytestmark = pytest.mark.timeout(180)

TRUTH_LIMIT_BYTES = 300_000  # truth.csv of the 11 s main job: 680 kB; metrics.json: 7 kB


def _limit_file_size() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (TRUTH_LIMIT_BYTES, TRUTH_LIMIT_BYTES))


def test_a_run_that_cannot_write_its_truth_ends_with_that_reason(tmp_path: Path) -> None:
    out = tmp_path / "run"
    # not measured by coverage: its data files would be cut short by the limit
    env = {k: v for k, v in os.environ.items() if k not in COVERAGE_ENV}
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "run", "dlc-paper", "--controller", "lmpc",
         "--out", str(out), "--no-plots", "--no-rrd"], capture_output=True, text=True,
        preexec_fn=_limit_file_size, timeout=150, check=False, env=env)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert "run: plant error: run failed: cannot write the run's files: File too large" \
        in proc.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["reason"].endswith("cannot write the run's files: File too large")
    # the plant's trace stays as rows (readable), named in the metrics
    assert set(metrics["files_not_written"]) == {"truth.csv"}
    assert (out / "truth.csv.rows").is_file() and not (out / "truth.csv").exists()
    assert not (out / "RUN_IN_PROGRESS").exists()
    plant_log = (out / "plant.log").read_text()
    assert "Traceback" not in plant_log and "cannot write the run's files" in plant_log


def test_an_analysis_that_fails_is_named_in_metrics_as_a_user_reads_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The run is kept and metrics.json says why its analysis failed: the error's type and
    message, not Python's repr of it."""
    def broken_analysis(*_: object) -> None:
        raise ValueError("truth.csv has no rows")

    monkeypatch.setattr(run_report, "with_summaries",
                        lambda _out, meta: dict(meta, interrupted=False, reason="finished"))
    monkeypatch.setattr(run_report, "analyse_run", broken_analysis)
    metrics = run_report.report_run(RunSpec("dlc-paper", "lmpc", out_dir=tmp_path), {})
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["analysis_error"] == written["analysis_error"] == \
        "ValueError: truth.csv has no rows"
    assert error_text(KeyError()) == "KeyError"  # no message: the type alone


def test_metrics_that_cannot_be_written_are_logged_with_the_runs_reason(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "metrics.json.tmp").mkdir()  # the write fails (IsADirectoryError)
    metrics = {"reason": "plant error: run failed: disk full"}
    assert write_metrics(tmp_path, metrics) is False
    assert metrics["metrics_not_written"].startswith("IsADirectoryError")
    assert not (tmp_path / "metrics.json").exists()
    assert "cannot write" in caplog.text and "plant error: run failed: disk full" in caplog.text
    (tmp_path / "metrics.json.tmp").rmdir()
    assert write_metrics(tmp_path, {"reason": "finished"}) is True
    assert json.loads((tmp_path / "metrics.json").read_text()) == {"reason": "finished"}


def test_a_controller_that_cannot_write_its_timing_log_keeps_controlling(
        tmp_path: Path) -> None:
    """Its timing rows hit the file-size limit after about 40 cycles: the log stops (one
    error line), every one of 100 cycles is still answered, the summary names the error."""
    spec, server = resolve_bus("auto")
    summary = tmp_path / "summary.json"
    ctrl = Controller(spec, tmp_path, "--controller", "lmpc", "--timing",
                      str(tmp_path / "timing.csv"), "--summary", str(summary),
                      file_size_limit=4_000)  # the summary (~2 kB) fits
    plant = Plant(spec)
    try:
        for k in range(100):
            assert len(plant.exchange(plant.burst(k, 60 / 3.6, 5.0), k)) == 3
    finally:
        plant.close()
        ctrl.stop()
        if server is not None:
            server.stop()
    assert ctrl.proc.returncode == 0
    s = json.loads(summary.read_text())
    assert s["cycles_answered"] == 100
    assert s["timing_log_error"] == "OSError: [Errno 27] File too large"
    err = ctrl.stderr_path.read_text()
    assert "Traceback" not in err and err.count("cannot be written") >= 1
