"""SIGINT and SIGTERM stop the harness commands cleanly (harness/run/signals.py).

Cross-process: a real ``rhonn-harness run`` (plant, controller, bus hub as OS processes) gets
the signal as a terminal (the whole process group) or a supervisor (the harness pid alone)
sends it, in the loop and while the children start; a ``benchmark`` (process pool) gets
SIGTERM (a ``campaign`` gets it in tests/test_campaign.py, then ``--resume``). In-process:
the handler, the shield around cleanup, the deadline, the run-directory marker and the
partial-run wording.
The bound on the time to exit is a liveness bound, not a speed figure.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType

import can
import psutil
import pytest

from can_db.process.rowlog import read_rows, rows_path
from harness.analysis.run_status import partial_note, with_partial_note
from harness.report import run_report
from harness.run import marker
from harness.run.spec import RunSpec
from tests.helpers_proc import _child_setup

EXIT_BOUND_S = 10.0  # liveness: the harness must be gone this long after the signal


def _ignore_sigint() -> None:
    """As a non-interactive shell starts a background job (``rhonn-harness run ... &``)."""
    _child_setup()
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _start(out: Path, sigint_ignored: bool = False) -> subprocess.Popen[str]:
    """``rhonn-harness run`` of a 20 s real-time run in a session (process group) of its own."""
    log = open(out.parent / f"{out.name}.log", "w")  # noqa: SIM115
    return subprocess.Popen(
        [sys.executable, "-m", "harness.cli", "run", "constant-radius", "--controller",
         "passive", "--mode", "realtime", "--duration", "20", "--out", str(out),
         "--no-plots", "--no-rrd"],
        stdout=log, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        preexec_fn=_ignore_sigint if sigint_ignored else _child_setup)


def _wait_for(check: Callable[[], bool], timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, "the run did not get there"
        time.sleep(0.05)


def _driving(out: Path, rows: int = 30) -> bool:
    """True once the plant wrote ``rows`` cycles (its trace is a row file while it runs)."""
    return len(read_rows(rows_path(out / "truth.csv")).get("t_s", ())) >= rows


def _signal_and_wait(proc: subprocess.Popen[str], sig: int, group: bool) -> tuple[int, list]:
    """Send ``sig``; return the exit code and the descendants the harness had then."""
    kids = psutil.Process(proc.pid).children(recursive=True)
    (os.killpg if group else os.kill)(proc.pid, sig)
    try:
        code = proc.wait(timeout=EXIT_BOUND_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise AssertionError(f"harness still running {EXIT_BOUND_S} s after {sig!r}") from None
    return code, kids


def _assert_stopped_cleanly(out: Path, code: int, sig: int, kids: list) -> dict:
    assert code == 128 + sig
    _, alive = psutil.wait_procs(kids, timeout=5)
    assert not alive, [p.cmdline() for p in alive]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["interrupted"] is True and metrics["reason"] == "interrupted"
    assert metrics["duration_planned_s"] == 20.0
    assert 0.0 <= metrics["sim_time_reached_s"] < 20.0
    assert not (out / marker.MARKER).exists()
    return metrics


@pytest.mark.parametrize(("sig", "group", "ignored"),
                         [(signal.SIGINT, False, True), (signal.SIGTERM, False, False),
                          (signal.SIGINT, True, False)],
                         ids=["sigint-pid-background-job", "sigterm-pid", "sigint-group"])
def test_signal_stops_a_realtime_run_with_partial_results(tmp_path: Path, sig: int,
                                                          group: bool, ignored: bool) -> None:
    """A supervisor's signal to the harness alone, or a terminal's Ctrl-C to the group. The
    first case starts the harness with SIGINT ignored, as a shell's background job is: the
    harness sets its own handler."""
    out = tmp_path / "run"
    proc = _start(out, sigint_ignored=ignored)
    _wait_for(lambda: _driving(out))
    code, kids = _signal_and_wait(proc, sig, group)
    metrics = _assert_stopped_cleanly(out, code, sig, kids)
    assert metrics["sim_time_reached_s"] >= 0.3  # the rows seen before the signal
    frames = list(can.LogReader(str(out / "bus.blf")))  # closed, readable
    assert len(frames) > 30 and metrics["bus_frames_recorded"] == len(frames)
    rows = (out / "truth.csv").read_text().splitlines()  # the row log became a CSV
    assert len(rows) > 30
    printed = (tmp_path / "run.log").read_text()
    assert "PARTIAL RUN — interrupted at" in printed and "run: interrupted" in printed


def test_sigterm_while_the_children_start(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = _start(out)
    _wait_for(lambda: (out / "controller.log").exists())  # the controller process starts
    code, kids = _signal_and_wait(proc, signal.SIGTERM, group=False)
    _assert_stopped_cleanly(out, code, signal.SIGTERM, kids)


def test_stale_marker_is_reported_and_a_live_one_refused(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    (tmp_path / marker.MARKER).write_text(json.dumps(
        {"pid": gone.pid, "pid_start": 0.0, "started_utc": "2026-01-01 10:00:00 UTC",
         "command": "rhonn-harness run dlc-paper"}))
    note = marker.stale_note(tmp_path)
    assert note is not None and note.startswith(f"{tmp_path} holds an incomplete run")
    assert "rhonn-harness run dlc-paper" in note
    from harness.analysis.run_data import load_run

    load_run(tmp_path)  # the analysis loader names it on stderr, once
    load_run(tmp_path)
    assert capsys.readouterr().err.count("holds an incomplete run") == 1
    own = marker.claim(tmp_path, command="test")  # a stale marker is replaced
    assert json.loads(own.read_text())["pid"] == os.getpid() and marker.stale_note(tmp_path) is None
    marker.release(own)
    assert not own.exists()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        (tmp_path / marker.MARKER).write_text(json.dumps(
            {"pid": live.pid, "pid_start": psutil.Process(live.pid).create_time()}))
        with pytest.raises(marker.RunDirBusyError, match="in use by a running harness"):
            marker.claim(tmp_path)
    finally:
        live.kill()
        live.wait()


def test_partial_note_wording() -> None:
    assert partial_note({"interrupted": False, "sim_time_reached_s": 3.0}) is None
    assert partial_note(None) is None
    m = {"interrupted": True, "sim_time_reached_s": 3.24, "duration_planned_s": 20}
    assert partial_note(m) == "PARTIAL RUN — interrupted at 3.2 s of 20.0 s"
    assert partial_note({"interrupted": True}) == "PARTIAL RUN — interrupted at ? s of ? s"
    assert with_partial_note("β", m) == "β\nPARTIAL RUN — interrupted at 3.2 s of 20.0 s"
    assert with_partial_note("β", {}) == "β"


def test_kpi_table_names_a_partial_run(capsys: pytest.CaptureFixture[str]) -> None:
    from harness.cli import print_table

    print_table({"lmpc": {"interrupted": True, "sim_time_reached_s": 1.0,
                          "duration_planned_s": 4.0}, "passive": {"interrupted": False}})
    out = capsys.readouterr().out
    assert "lmpc: PARTIAL RUN — interrupted at 1.0 s of 4.0 s" in out
    assert "passive: PARTIAL" not in out


def test_sigterm_stops_a_benchmark_and_its_pool(tmp_path: Path) -> None:
    """A study: the process pool's workers go with it, the output says it is incomplete."""
    out = tmp_path / "bench"
    log = open(tmp_path / "bench.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness.cli", "benchmark", "--quick", "--sections", "core",
         "--jobs", "2", "--out", str(out)],
        stdout=log, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        preexec_fn=_child_setup)
    # the pool is up: its workers run in-process runs
    _wait_for(lambda: len(psutil.Process(proc.pid).children(recursive=True)) >= 2)
    time.sleep(1.0)
    code, kids = _signal_and_wait(proc, signal.SIGTERM, group=False)
    assert code == 143
    assert not psutil.wait_procs(kids, timeout=5)[1]
    info = json.loads((out / marker.INTERRUPTED).read_text())
    assert info["signal"] == "SIGTERM" and "benchmark" in info["command"]
    assert "interrupted" in (tmp_path / "bench.log").read_text()


@pytest.fixture
def handlers() -> Iterator[ModuleType]:
    """The stop-signal handlers of harness/run/signals.py in this process, then restored."""
    from harness.run import signals

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signals.reset()
    signals.install()
    yield signals
    signals.disarm_deadline()
    signals.reset()
    for s, h in saved.items():
        signal.signal(s, h)


def test_sigterm_takes_the_keyboard_interrupt_path(handlers: ModuleType) -> None:
    with pytest.raises(KeyboardInterrupt) as caught:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises before this ends
    assert isinstance(caught.value, handlers.Interrupted) and caught.value.signum == 15
    assert handlers.received() == signal.SIGTERM and handlers.exit_code() == 143


def test_shielded_cleanup_is_not_cut_and_the_signal_is_kept(handlers: ModuleType) -> None:
    done = False
    with handlers.shielded():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        done = True
    assert done and handlers.received() == signal.SIGINT and handlers.exit_code() == 130
    with pytest.raises(handlers.Interrupted):  # a loop's check() raises it afterwards
        handlers.check()


def test_deadline_cuts_work_after_a_signal(handlers: ModuleType) -> None:
    assert handlers.arm_deadline(time.monotonic() + 0.05)
    with pytest.raises(handlers.DeadlineReached):
        time.sleep(5)
    assert handlers.received() is None  # a deadline is no stop signal




def test_a_deadline_landing_before_the_analysis_still_writes_the_partial_report(
        handlers: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On a loaded machine the cleanup after a signal can outlast the analysis budget: the
    deadline is then armed already spent and lands wherever the main thread is, here before
    the analysis starts. The report still ends normally, metrics.json naming the cut."""
    handlers._received.append((signal.SIGTERM, time.monotonic() - 10.0))  # long past budget
    arm = handlers.arm_deadline

    def arm_then_stall(at_s: float) -> bool:
        armed = arm(at_s)
        time.sleep(1.0)  # the spent deadline (1 ms) lands here, outside the analysis
        return armed

    monkeypatch.setattr(handlers, "arm_deadline", arm_then_stall)
    monkeypatch.setattr(run_report, "with_summaries",
                        lambda _out, meta: dict(meta, interrupted=True, reason="interrupted"))
    monkeypatch.setattr(run_report, "analyse_run", lambda *_: pytest.fail("not reached"))
    spec = RunSpec("constant-radius", "passive", out_dir=tmp_path)
    metrics = run_report.report_run(spec, {"duration_planned_s": 20.0})
    assert metrics["analysis_cut"].startswith("the analysis of the partial run stopped")
    written = json.loads((tmp_path / "metrics.json").read_text())
    assert written["analysis_cut"] == metrics["analysis_cut"] and written["interrupted"]


# ----------------------------------------------- the bus tool and the entry points (Ctrl-C)
def _sigint_after_first_line(argv: list[str], preexec: Callable[[], None]
                             ) -> tuple[subprocess.Popen[str], str, str, str]:
    """Start ``argv``, read its first stdout line, send SIGINT, wait up to EXIT_BOUND_S (kill
    on the way out if it is still running); the process, the first line, stdout, stderr."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=preexec)
    try:
        first = proc.stdout.readline()  # type: ignore[union-attr]
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=EXIT_BOUND_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc, first, out, err


@pytest.mark.parametrize("command", [["dump", "--bus", "local:sigint_ignored"], ["serve"]])
def test_bus_tool_stops_on_sigint_inherited_as_ignored(command: list[str]) -> None:
    """``rhonn-bus dump`` / ``serve`` started in the background by a script (SIGINT ignored)
    stop on ``kill -INT`` as on SIGTERM: the dump with its summary line, exit 0."""
    proc, first, out, err = _sigint_after_first_line(
        [sys.executable, "-m", "can_db.cli", *command], _ignore_sigint)
    assert first.startswith(("ready", "loopback bus server on")), first
    assert proc.returncode == 0, err
    if command[0] == "dump":
        assert out.startswith("frames: 0"), out


IMPORT_SLOWLY = """
import sys, time
print("importing", flush=True)
time.sleep(60)
"""


def test_ctrl_c_during_the_imports_is_one_line_exit_130(tmp_path: Path) -> None:
    """A console script interrupted while its program imports (``import rerun`` and the
    like: seconds) ends with one line, exit 130 — also when started with SIGINT ignored."""
    (tmp_path / "slow_program.py").write_text(IMPORT_SLOWLY)
    code = ("import sys; sys.path.insert(0, sys.argv[1]); "
            "from can_db.process import launch; "
            "launch.PROGRAMS['rhonn-harness'] = 'slow_program'; "
            "raise SystemExit(launch.rhonn_harness())")
    for preexec in (_child_setup, _ignore_sigint):
        proc, first, _, err = _sigint_after_first_line(
            [sys.executable, "-c", code, str(tmp_path)], preexec)
        assert first == "importing\n"
        assert proc.returncode == 130
        assert err == "rhonn-harness: interrupted\n"
