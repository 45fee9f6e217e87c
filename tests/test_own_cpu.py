"""The controller on a CPU of its own (can_db/process/cpu.py, rhonn-harness run --controller-cpu).

Across processes: the controller runs pinned to its CPU with a SCHED_IDLE spinner there,
the plant and the harness's other children stay off it, the harness gets its CPUs back,
and the spinner never outlives the controller (clean stop or SIGKILL)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from can_db.process.argcheck import UsageError
from can_db.process.cpu import CpuChoiceError, allowed_cpus, choose_cpu
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from harness.run.validate import check_run_config
from tests.helpers_proc import spawn


def _gone(pid: int, timeout_s: float = 5.0) -> bool:
    """True when ``pid`` has exited (or is a zombie nobody reaped yet) within the time."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.05)
    return False


def test_choose_cpu_leaves_a_cpu_for_the_rest_and_names_what_is_wrong() -> None:
    assert choose_cpu("auto", {0, 1, 3}) == 3
    assert choose_cpu("1", {0, 1}) == 1
    assert choose_cpu(0, {0, 1}) == 0
    assert choose_cpu("2", {2}, leave_one=False) == 2
    for text, allowed, words in (("auto", {0}, "at least 2"), ("5", {0, 1}, "CPU 5"),
                                 ("fast", {0, 1}, "'auto' or a CPU number")):
        with pytest.raises(CpuChoiceError, match=words):
            choose_cpu(text, allowed)


def test_bad_controller_cpu_is_a_usage_error_before_anything_starts(tmp_path: Path) -> None:
    cfg = RunSpec(scenario="dlc-paper", controller="lmpc", out_dir=tmp_path / "r",
                  controller_cpu="99")
    with pytest.raises(UsageError, match="--controller-cpu: CPU 99"):
        check_run_config(cfg, bus=False)
    cfg = replace(cfg, controller_cpu="auto", rt=True)
    with pytest.raises(UsageError, match="not combined"):
        check_run_config(cfg, bus=False)
    for argv, words in ((["--keep-cpu-awake"], "needs --cpu"), (["--cpu", "99"], "CPU 99")):
        res = subprocess.run([sys.executable, "-m", "controller.runtime.process", "--bus",
                              "local:never-opened", "--controller", "lmpc", *argv],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 2 and words in res.stderr, res.stderr


def test_spinner_is_idle_class_pinned_and_dies_with_its_parent() -> None:
    cpu = max(allowed_cpus())
    parent = spawn("-c", "import time; from can_db.process.cpu import KeepAwake; "
                   f"k = KeepAwake({cpu}); print(k.pid, flush=True); time.sleep(120)",
                   stdout=subprocess.PIPE)
    try:
        assert parent.stdout is not None
        pid = int(parent.stdout.readline())
        deadline = time.monotonic() + 10.0  # the child sets its class right after start
        while os.sched_getscheduler(pid) != os.SCHED_IDLE and time.monotonic() < deadline:
            time.sleep(0.02)
        assert os.sched_getscheduler(pid) == os.SCHED_IDLE
        assert os.sched_getaffinity(pid) == {cpu}
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        assert _gone(pid), "the spinner outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()


def test_closed_loop_with_the_controller_on_its_own_cpu(tmp_path: Path) -> None:
    before = allowed_cpus()
    cfg = RunSpec(scenario="dlc-paper", controller="lmpc", out_dir=tmp_path / "run",
                    duration_s=1.0, make_plots=False, make_rrd=False, controller_cpu="auto")
    if len(before) < 2:  # defined behaviour on a one-CPU machine: refused, nothing started
        with pytest.raises(CpuChoiceError):
            run_and_report(cfg)
        return
    own = max(before)
    res = run_and_report(cfg)
    assert res.reason == "finished", res.reason
    ctrl = json.loads((tmp_path / "run" / "controller_summary.json").read_text())
    plant = json.loads((tmp_path / "run" / "plant_summary.json").read_text())
    assert ctrl["cpu"]["affinity"] == [own]
    assert own not in plant["cpu_affinity"] and plant["cpu_affinity"]
    assert res.metrics["controller_cpu"] == own
    assert allowed_cpus() == before, "the harness did not get its CPUs back"
    assert _gone(ctrl["cpu"]["keep_awake_pid"]), "the spinner outlived the controller"
    assert ctrl["cycles_answered"] >= 99 and plant["commanded_cycles"] >= 99
