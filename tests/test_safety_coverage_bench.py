"""The bench's decisions on its error and edge paths (harness/run/hil_bench.py).

Unit tests use small stand-ins for a process (``_Proc``), a UDS tester and a recorder: what
the bench decides when a reset is not answered, a plant ends without ``done``, a hub dies,
a start fails. The command lines the bench builds are parsed by the plant's and the
controller's own parsers. Real short-lived processes show that a failed start does not
poison the next one; two bench runs across processes show a start failure (retried once)
and a wall-clock timeout with a live view polled."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from can_db.codec import Codec
from can_db.faults import FaultSpecError, parse_faults
from can_db.process.rowlog import RowLog
from controller.runtime import process as controller_process
from harness.run import hil_bench
from harness.run.hil_bench import (
    SOFT_RESET_RESPONSE,
    Bench,
    RunOutcome,
    _failure_of,
    _keep_attempt_files,
    plant_run_args,
    route_frame_faults,
    run_faults,
)
from harness.run.procs import Child, ChildStartError
from harness.run.spec import RunSpec
from harness.run.uds_tester import UdsError
from plant_sim import process as plant_process
from tests.helpers_proc import live_children, not_a_bus_server


class _Proc:
    """A bench process stand-in: its exit code (None: running), lines, what was asked."""

    def __init__(self, name: str, code: int | None = None, lines: list[str] | None = None,
                 line: str | None = None) -> None:
        self.name, self.code, self.lines = name, code, list(lines or [])
        self.line = line  # what wait_line answers
        self.stopped = False
        self.sent: list[str] = []

    def poll(self) -> int | None:
        return self.code

    def stop(self, grace_s: float = 5.0) -> int | None:
        self.stopped, self.grace_s = True, grace_s
        if self.code is None:
            self.code = -15
        return self.code

    def send(self, line: str) -> None:
        self.sent.append(line)

    def wait_line(self, prefixes: tuple[str, ...], since: int, timeout_s: float,
                  poll: Any = None) -> str | None:
        return self.line


class _Recorder:
    def __init__(self, barrier_reached: bool = True) -> None:
        self.calls: list[str] = []
        self._reached = barrier_reached

    def arm_barrier(self, ids: Any, resp_id: int, data: bytes) -> None:
        assert data == SOFT_RESET_RESPONSE
        self.calls.append("arm")

    def wait_barrier(self, timeout_s: float) -> bool:
        self.calls.append("wait")
        return self._reached

    def drain(self, idle_s: float) -> None:
        self.calls.append(f"drain {idle_s}")

    def stop(self) -> None:
        self.calls.append("stop")


def _tester(fail_on: str | None) -> type:
    """A UDS tester class whose ``fail_on`` service gets no answer (UdsError)."""
    class Tester:
        def __init__(self, bus_spec: str, timeout_s: float) -> None:
            pass

        def __enter__(self) -> Tester:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def _do(self, what: str) -> None:
            if what == fail_on:
                raise UdsError(f"{what}: no response within 10 s")

        def unlock(self) -> None:
            self._do("unlock")

        def write_coding(self, coding: dict) -> None:
            self._do("write_coding")

        def ecu_reset(self, kind: str) -> None:
            self._do(f"reset {kind}")

    return Tester


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    b = Bench(tmp_path / "bench")
    b.bus_spec = "local:bench-edges"
    yield b
    b.plant = b.controller = None  # stand-ins: nothing to stop
    b.close()


# ---------------------------------------------------------------- command lines
def test_every_run_option_reaches_the_plant_as_its_parser_reads_it(tmp_path: Path) -> None:
    spec = RunSpec("mu-step-corner", "lmpc", speed_kmh=70.0, duration_s=3.0,
                   vehicle={"mass_scale": 1.1}, params={"steps": [[1.0, 0.4]]},
                   secoc=False, command_hold_ms=45.0, lockstep_wait_ms=300.0,
                   plant_extra_args=("--lost-after", "9"))
    argv = plant_run_args(spec, tmp_path, ["loss:5%"])
    parser = plant_process._run_parser(plant_process._parser().parse_args(
        ["--bus", "virtual:t", "--serve"]))
    args = parser.parse_args(argv)
    assert (args.speed, args.duration, args.vehicle) == (70.0, 3.0, ["mass_scale=1.1"])
    assert args.param == ["steps=[[1.0, 0.4]]"]  # a list as JSON, not Python's repr
    assert (args.secoc, args.secoc_keys, args.secoc_state) == (False, None, None)
    assert (args.command_hold_ms, args.wait_ms, args.lost_after) == (45.0, 300.0, 9)
    assert args.fault == ["loss:5%"]
    plant_process.PlantRun(args, Codec())  # the plant accepts the whole run


def test_the_controller_and_plant_command_lines(bench: Bench, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """--config of the coding, --rt and --no-secoc reach the controller; --rt the plant."""
    class Launch:
        def __init__(self, name: str, args: list[str], log_path: Path,
                     stdin: bool = False) -> None:
            self.name, self.args = name, args

        def launch(self) -> Launch:
            return self

    monkeypatch.setattr(hil_bench, "Child", Launch)
    spec = RunSpec("dlc-paper", "lmpc", rt=True, secoc=False)
    coding = {"controller": "lmpc", "config": "100hz", "faults": ["loss:1%"]}
    ctrl = bench._start_controller(spec, coding, tmp_path, wait=False)
    args = controller_process._parser().parse_args(ctrl.args[2:])
    assert ctrl.args[:2] == ["-m", "controller.runtime.process"]
    assert (args.config, args.fault, args.rt, args.secoc, args.bench) == (
        "100hz", ["loss:1%"], True, False, True)
    bench.rt = True
    plant = bench._start_plant(tmp_path, wait=False)
    assert plant.args[:2] == ["-m", "plant_sim.process"]
    pargs = plant_process._parser().parse_args(plant.args[2:])
    assert pargs.serve and pargs.rt
    assert [name for name, _ in bench._starting] == ["controller", "plant"]
    bench._starting = []


def test_process_faults_and_core_faults_are_routed() -> None:
    spec = RunSpec("dlc-paper", "lmpc", kill_controller_at_s=1.5,
                   faults=("core-exception:100ms@1s", "loss:5%"))
    faults = run_faults(spec)
    assert [f.text for f in faults][-1] == "kill-controller@1.5s"
    assert faults[-1].kind == "kill-controller" and faults[-1].at_s == 1.5
    plant, ctrl = route_frame_faults(faults, Codec(), lockstep=True)
    assert plant == ["loss:5%"]
    assert ctrl == ["core-exception:100ms@1s", "loss:5%"]  # the core fault: the controller's
    assert route_frame_faults(parse_faults(["restart-bus@1s"]), Codec(), True) == ([], [])


# ---------------------------------------------------------------- life of the processes
def test_a_bench_without_a_work_dir_removes_its_own(tmp_path: Path) -> None:
    b = Bench()
    work = b.work_dir
    assert work.is_dir() and work.name.startswith("rhonn-bench-")
    (work / "controller").mkdir()
    b.close()
    assert not work.exists()
    b.close()  # idempotent


def test_a_dead_hub_takes_its_processes_with_it(bench: Bench,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    class Server:
        def __init__(self, alive: bool) -> None:
            self._alive = alive

        def alive(self) -> bool:
            return self._alive

        def stop(self) -> None:
            self._alive = False

    new = Server(True)
    monkeypatch.setattr(hil_bench, "resolve_bus", lambda *a, **kw: ("local:new", new))
    plant, ctrl = _Proc("plant"), _Proc("controller")
    bench.server, bench.plant, bench.controller = Server(False), plant, ctrl  # type: ignore
    bench._ensure_bus(None)
    assert plant.stopped and ctrl.stopped
    assert bench.plant is None and bench.controller is None
    assert (bench.server, bench.bus_spec, bench.counters.replaced) == (new, "local:new", 1)
    bench._ensure_bus(None)  # alive: kept
    assert bench.server is new and bench.counters.replaced == 1


def _python(code: str, **kw: Any) -> Child:
    return Child("proc", ["-c", code], **kw)


def test_a_failed_start_is_not_awaited_again(tmp_path: Path) -> None:
    """The controller fails to start while the plant is still starting: the plant is
    stopped with the run, and the next start waits for the new plant only (a stale launch
    in the list failed every later start of the bench)."""
    b = Bench(tmp_path / "bench")
    try:
        ctrl = _python("import sys; print('no bus'); sys.exit(3)").launch()
        slow = _python("import sys; sys.stdin.read()", stdin=True).launch("ready serve")
        b.controller, b.plant = ctrl, slow
        b._starting = [("controller", ctrl), ("plant", slow)]
        with pytest.raises(ChildStartError, match="did not become ready:\nno bus"):
            b._await_starts()
        assert b.controller is None and b.plant is slow
        assert b._starting == [("plant", slow)]  # still to be seen ready before any use
        b._stop_plant(1.0)  # what the end of the failed run does with a dirty plant
        good = _python("import sys; print('ready serve'); sys.stdin.read()",
                       stdin=True).launch("ready serve")
        b.plant = good
        b._starting.append(("plant", good))
        b._await_starts()  # the new plant's start only
        assert b._starting == []
        assert b.counters.plant_starts == 1 and b.counters.controller_starts == 0
    finally:
        b.close(1.0)
    assert live_children() == []


def test_a_dirty_or_reconfigured_controller_is_replaced(
        bench: Bench, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    launched: list[list[str]] = []
    monkeypatch.setattr(bench, "_start_controller",
                        lambda spec, coding, out, wait=True: launched.append(coding)
                        or _Proc("controller"))
    spec = RunSpec("dlc-paper", "lmpc")
    coding = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}
    old = _Proc("controller")
    bench.controller, bench.coding = old, coding  # type: ignore[assignment]
    bench.setup = hil_bench.controller_setup(spec)
    bench._dirty.add("controller")  # a fault touched it
    bench._prepare_controller(spec, coding, tmp_path)
    assert old.stopped and launched == [coding] and bench.counters.replaced == 1
    assert old.grace_s == 5.0  # a live one: time to write its files before SIGKILL
    assert "controller" not in bench._dirty
    # another process setup (here: SecOC off) is a new process too
    other = RunSpec("dlc-paper", "lmpc", secoc=False)
    kept = bench.controller
    bench._prepare_controller(other, coding, tmp_path)
    assert kept.stopped and len(launched) == 2 and bench.counters.replaced == 2  # type: ignore
    assert bench.setup == hil_bench.controller_setup(other)


# ---------------------------------------------------------------- resets
def test_an_unanswered_soft_reset_marks_the_controller_for_replacement(
        bench: Bench, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(hil_bench, "UdsTester", _tester("reset soft"))
    bench.controller = _Proc("controller")  # type: ignore[assignment]
    with caplog.at_level(logging.WARNING, logger="harness.run"):
        assert bench._soft_reset() is False
    assert bench.counters.reset_failures == 1 and bench.counters.soft_resets == 0
    assert "controller" in bench._dirty
    assert "controller reset failed (soft reset: reset soft: no response" in caplog.text


@pytest.mark.parametrize(("kind", "fail_on", "ready", "error"), [
    ("soft", "write_coding", None, "controller coding and soft reset failed: write_coding"),
    ("hard", "unlock", None, "controller coding and hard reset failed: unlock"),
    ("hard", None, None, "controller did not come back after a hard reset"),
])
def test_a_failed_recoding_is_a_start_failure(
        bench: Bench, monkeypatch: pytest.MonkeyPatch, kind: str, fail_on: str | None,
        ready: str | None, error: str) -> None:
    monkeypatch.setattr(hil_bench, "UdsTester", _tester(fail_on))
    old = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}
    bench.controller = _Proc("controller", line=ready)  # type: ignore[assignment]
    bench.coding = old
    with pytest.raises(ChildStartError, match=error):
        bench._recode({**old, "config": "100hz"}, kind)
    assert bench.coding == old  # not applied
    assert bench.counters.reset_failures == 1 and "controller" in bench._dirty
    assert bench.counters.hard_resets == bench.counters.soft_resets == 0


# ---------------------------------------------------------------- the end of a run
def _summary(out: Path, reason: str) -> None:
    (out / "plant_summary.json").write_text(json.dumps({"reason": reason}))


@pytest.mark.parametrize(("line", "code", "summary", "result", "dirty"), [
    (None, 1, None, ("plant exited with code 1", False), True),
    ("error run failed: RuntimeError: x", 1, None,
     ("plant error: run failed: RuntimeError: x", False), True),
    ("done {}", None, "stopped by signal", ("interrupted", True), True),
    ("done {}", None, "bus lost", ("plant exited with code 3", False), True),
    ("done {}", None, "finished", ("finished", False), False),
])
def test_the_reason_of_a_run_from_the_plants_end(
        bench: Bench, tmp_path: Path, line: str | None, code: int | None,
        summary: str | None, result: tuple[str, bool], dirty: bool) -> None:
    bench.plant = _Proc("plant", code=code)  # type: ignore[assignment]
    if summary is not None:
        _summary(tmp_path, summary)
    assert bench._plant_end(line, tmp_path) == result
    assert ("plant" in bench._dirty) is dirty


@pytest.mark.parametrize(("line", "error"), [
    (None, "plant did not load the run:\nTraceback"),
    ("error --mu: 7 is out of range", "plant refused the run: --mu: 7 is out of range"),
])
def test_a_run_the_plant_does_not_load_is_a_start_failure(
        bench: Bench, tmp_path: Path, line: str | None, error: str) -> None:
    class Plant(_Proc):
        def send(self, text: str) -> None:  # the plant's answer: a crash, or a refusal
            super().send(text)
            self.lines.append("Traceback (most recent call last):" if line is None else line)

    plant = Plant("plant", lines=["ready serve on x"], line=line)
    bench.plant = plant  # type: ignore[assignment]
    with pytest.raises(ChildStartError, match=error.replace("(", r"\(")):
        bench._send_run(RunSpec("dlc-paper", "lmpc"), tmp_path, [])
    assert json.loads(plant.sent[0])["run"][:2] == ["--scenario", "dlc-paper"]


def _rows(out: Path) -> None:
    """A killed plant's row file whose CSV cannot be written (its name is taken)."""
    log = RowLog(out / "truth.csv", ["t_s"], ["%.9g"])
    log.write((0.0,))
    log._fd = None  # type: ignore[assignment]  # killed: never closed by its writer
    (out / "truth.csv.tmp").mkdir()


def test_an_unanswered_reset_after_a_run_replaces_the_controller_and_keeps_the_log_whole(
        bench: Bench, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(hil_bench, "UdsTester", _tester("unlock"))
    ctrl = _Proc("controller", lines=["ready", "run line"])
    bench.controller = ctrl  # type: ignore[assignment]
    recorder = _Recorder()
    _rows(tmp_path)
    with caplog.at_level(logging.WARNING, logger="harness.run"):
        codes = bench._end_run(tmp_path, recorder, False, "finished",  # type: ignore[arg-type]
                               {"plant": 0, "controller": 1})
    assert codes == (None, -15)  # stopped: it writes its files now
    assert ctrl.stopped and bench.controller is None
    assert bench.counters.replaced == 1 and bench.counters.reset_failures == 1
    # the barrier was armed for the reset; without its response: the idle wait instead
    assert recorder.calls == ["arm", "drain 0.3", "stop"]
    assert (tmp_path / "controller.log").read_text() == "run line\n"
    # the killed plant's rows stay, named (the metrics' files_not_written)
    assert set(bench._unwritten) == {"truth.csv"}
    assert "truth.csv could not be written" in caplog.text
    assert (tmp_path / "truth.csv.rows").is_file()


def test_a_reset_response_the_recorder_misses_costs_an_idle_wait(
        bench: Bench, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hil_bench, "UdsTester", _tester(None))
    bench.controller = _Proc("controller")  # type: ignore[assignment]
    recorder = _Recorder(barrier_reached=False)
    codes = bench._end_run(tmp_path, recorder, False, "finished",  # type: ignore[arg-type]
                           {"plant": 0, "controller": 0})
    assert codes == (None, 0) and bench.counters.soft_resets == 1
    assert recorder.calls == ["arm", "wait", "drain 0.3", "stop"]


def _outcome(reason: str, lost_at: float | None = None, code: int | None = None,
             events: list[dict[str, Any]] | None = None) -> RunOutcome:
    return RunOutcome(reason=reason, interrupted=False, plant_code=0, controller_code=code,
                      controller_lost_at_s=lost_at, fault_events=events or [],
                      frames_recorded=0, released_early=0, log_time_base=None,
                      sim_time_s=0.0, bus_spec="local:x", own_cpu=None)


def test_what_is_retried_and_how_it_is_named(bench: Bench) -> None:
    start = _outcome("start failed: controller did not become ready")
    assert bench._died_unexpectedly(start)
    assert _failure_of(start) == start.reason
    died = _outcome("finished", lost_at=2.5, code=-9)
    assert bench._died_unexpectedly(died)
    assert _failure_of(died) == ("the controller process died at 2.50 s simulated (exit "
                                 "code -9); the plant ended: finished")
    # without a lost controller, or when the plant's end explains it, the plant's reason
    assert _failure_of(_outcome("plant error: run failed")) == "plant error: run failed"
    assert _failure_of(_outcome("plant exited with code 1", lost_at=1.0)) == (
        "plant exited with code 1")
    asked = _outcome("finished", lost_at=2.5, events=[{"fault": "kill-controller@2.5s"}])
    assert not bench._died_unexpectedly(asked)
    assert not bench._died_unexpectedly(_outcome("plant exited with code 1", events=[
        {"fault": "restart-plant@1s"}]))


def test_a_retry_replaces_an_older_first_attempt(tmp_path: Path) -> None:
    (tmp_path / "attempt1").mkdir()
    (tmp_path / "attempt1" / "stale.txt").write_text("an older retry's\n")
    for name in ("truth.csv", "controller_summary.json", "bus.blf", "rogue0.log"):
        (tmp_path / name).write_text(name)
    assert _keep_attempt_files(tmp_path, "attempt1") == "attempt1"
    assert sorted(p.name for p in (tmp_path / "attempt1").iterdir()) == [
        "bus.blf", "controller_summary.json", "rogue0.log", "truth.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["attempt1"]


def test_a_bus_restart_without_a_bus_server_is_skipped_and_said(
        bench: Bench, tmp_path: Path) -> None:
    bench.server = None
    (fault,) = parse_faults(["restart-bus@1s"])
    bench._events = []
    bench._apply_fault(fault, tmp_path, 1.0)
    assert bench._events == [{"fault": "restart-bus@1s", "sim_time_s": 1.0,
                              "skipped": "no bus server to restart (SocketCAN bus)"}]


# ---------------------------------------------------------------- across processes


def test_a_bench_that_cannot_start_its_processes_retries_once_and_says_why(
        tmp_path: Path) -> None:
    with not_a_bus_server() as port:
        bus = f"remote:ws://127.0.0.1:{port}/"
        with Bench(tmp_path / "bench", bus=bus) as b:
            outcome = b.run(RunSpec("dlc-paper", "lmpc", bus=bus, out_dir=tmp_path / "run"))
            assert b._starting == []
    assert outcome.reason.startswith("start failed: ")
    assert "did not become ready" in outcome.reason and "cannot open bus" in outcome.reason
    assert outcome.bench["retries"] == 1
    assert outcome.bench["first_attempt_reason"].startswith("start failed: ")
    assert outcome.frames_recorded == 0 and outcome.sim_time_s == 0.0
    assert live_children() == []


class _Tap:
    def __init__(self) -> None:
        self.frames = 0
        self.polls = 0

    def tap(self, msg: Any) -> None:
        self.frames += 1

    def poll(self) -> None:
        self.polls += 1


def test_a_run_past_its_wall_clock_limit_ends_and_its_plant_is_replaced(
        tmp_path: Path) -> None:
    """A real-time run of 30 s with a limit of 1 wall s: the bench ends it (the live view
    was polled meanwhile); the plant, stopped mid-run, is not kept."""
    tap = _Tap()
    spec = RunSpec("constant-radius", "lmpc", mode="realtime", duration_s=30.0,
                   wall_timeout_s=1.0, out_dir=tmp_path / "run", make_plots=False,
                   make_rrd=False)
    with Bench(tmp_path / "bench", warm=False) as b:
        outcome = b.run(spec, tap=tap)
        assert b.plant is None and b.controller is None
    assert outcome.reason == "wall timeout after 1 s"
    assert not outcome.interrupted and outcome.bench["retries"] == 0
    assert tap.polls >= 1
    summary = json.loads((tmp_path / "run" / "plant_summary.json").read_text())
    assert summary["reason"] == "stopped by signal"  # the bench stopped it
    assert live_children() == []



# ---------------------------------------------------------------- decisions between runs
def test_frame_faults_go_to_the_sender_of_the_message_or_signal_they_name() -> None:
    """A fault naming a message or one of its signals is injected by that frame's sender
    only; an untargeted one by both."""
    faults = parse_faults(["kill-plant@1s", "loss:5%,WHEEL_SPEEDS", "stuck:TQ_FL",
                           "crc:1%,WHEEL_TORQUE_CMD", "stuck:WS_FL", "loss:1%"])
    plant, ctrl = route_frame_faults(faults, Codec(), lockstep=False)
    assert plant == ["loss:5%,WHEEL_SPEEDS", "stuck:WS_FL", "loss:1%"]
    assert ctrl == ["stuck:TQ_FL", "crc:1%,WHEEL_TORQUE_CMD", "loss:1%"]


def test_a_process_fault_is_due_at_its_time_and_only_once(bench: Bench) -> None:
    bench._pending = sorted(parse_faults(["kill-plant@0.5s", "restart-bus@1s"]),
                            key=lambda f: f.at_s)
    assert bench._due(0.4) == []
    assert [f.text for f in bench._due(0.5)] == ["kill-plant@0.5s"]  # exactly at its time
    assert bench._due(0.5) == []                                       # once
    assert [f.text for f in bench._due(1.0 - 1e-12)] == ["restart-bus@1s"]  # rounding
    assert bench._pending == []


def test_a_live_controller_with_the_same_coding_is_kept_and_a_dead_one_replaced(
        bench: Bench, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    launched: list[dict[str, Any]] = []
    waits: list[bool] = []
    monkeypatch.setattr(bench, "_start_controller",
                        lambda spec, coding, out, wait=True: launched.append(coding)
                        or waits.append(wait) or _Proc("controller"))
    monkeypatch.setattr(hil_bench, "UdsTester", _tester("unlock"))  # no recoding expected
    spec = RunSpec("dlc-paper", "lmpc")
    coding = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}
    live = _Proc("controller")
    bench.controller, bench.coding = live, coding  # type: ignore[assignment]
    bench.setup = hil_bench.controller_setup(spec)
    bench._prepare_controller(spec, coding, tmp_path)      # the run before ended in a reset
    assert bench.controller is live and not live.stopped and launched == []
    assert bench.counters.replaced == bench.counters.soft_resets == 0
    assert bench.counters.reset_failures == 0
    dead = _Proc("controller", code=-9)                     # died in the last run
    bench.controller = dead  # type: ignore[assignment]
    bench._prepare_controller(spec, coding, tmp_path)
    assert dead.stopped and launched == [coding] and bench.counters.replaced == 1
    assert bench.controller is not dead
    assert waits == [False]  # launched only: the plant starts beside it, run() awaits both


@pytest.mark.parametrize(("kind", "hard", "soft", "recodings"), [
    ("soft", 0, 1, 1), ("hard", 1, 0, 0)])
def test_a_recoding_counts_its_reset_once(bench: Bench, monkeypatch: pytest.MonkeyPatch,
                                          kind: str, hard: int, soft: int,
                                          recodings: int) -> None:
    monkeypatch.setattr(hil_bench, "UdsTester", _tester(None))
    old = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}
    new = {**old, "config": "100hz"}
    # a hard reset's new process says "ready"; a soft reset prints no such line
    bench.controller = _Proc("controller",  # type: ignore[assignment]
                             line="ready" if kind == "hard" else None)
    bench.coding = old
    bench._recode(new, kind)
    assert bench.coding == new and "controller" not in bench._dirty
    c = bench.counters
    assert (c.hard_resets, c.soft_resets, c.recodings, c.reset_failures) == (
        hard, soft, recodings, 0)


def test_the_controller_setup_names_the_keys_only_when_secoc_is_on(tmp_path: Path) -> None:
    """Other SecOC keys are another controller process (its keys are read at its start); with
    SecOC off the key source is no part of the setup."""
    setup = hil_bench.controller_setup
    on = [RunSpec("dlc-paper", "lmpc", secoc=True, secoc_keys=k)
          for k in ("ci-test-key", str(tmp_path / "k.json"))]
    off = [RunSpec("dlc-paper", "lmpc", secoc=False, secoc_keys=k)
           for k in ("ci-test-key", str(tmp_path / "k.json"))]
    assert setup(on[0]) != setup(on[1])
    assert setup(on[0])[1:3] == (True, "ci-test-key")
    assert setup(off[0]) == setup(off[1]) and setup(off[0])[1:3] == (False, None)


def test_in_lockstep_delays_act_on_the_plants_frames_only() -> None:
    """A held-back torque frame cannot answer its cycle in lockstep: an untargeted delay goes
    to the plant only, one naming a controller frame needs --mode realtime; in realtime both
    senders delay."""
    jitter = parse_faults(["jitter:5ms"])
    assert route_frame_faults(jitter, Codec(), lockstep=True) == (["jitter:5ms"], [])
    assert route_frame_faults(jitter, Codec(), lockstep=False) == (["jitter:5ms"],
                                                                   ["jitter:5ms"])
    ctrl_delay = parse_faults(["delay:100ms,WHEEL_TORQUE_CMD"])
    with pytest.raises(FaultSpecError, match="needs --mode realtime"):
        route_frame_faults(ctrl_delay, Codec(), lockstep=True)
    assert route_frame_faults(ctrl_delay, Codec(), lockstep=False) == (
        [], ["delay:100ms,WHEEL_TORQUE_CMD"])


def test_a_fault_due_within_the_rounding_tolerance_is_taken_once(bench: Bench) -> None:
    bench._pending = parse_faults(["kill-plant@0.5s"])
    assert [f.text for f in bench._due(0.5 - 1e-9)] == ["kill-plant@0.5s"]
    assert bench._due(0.6) == [] and bench._pending == []


def test_the_benchs_coding_has_the_controllers_default_fault_seed(tmp_path: Path) -> None:
    """A fresh controller (no --fault-seed) and a recoded one inject the same faults."""
    coding = hil_bench.controller_coding(RunSpec("dlc-paper", "lmpc"), [], tmp_path)
    default = controller_process._parser().parse_args(
        ["--bus", "virtual:t", "--controller", "lmpc"]).fault_seed
    assert coding["fault_seed"] == default


@pytest.mark.parametrize(("change", "kind"), [({"config": "100hz"}, "soft"),
                                              ({"faults": ["loss:1%"]}, "soft"),
                                              ({"controller": "nmpc-rhonn"}, "hard")])
def test_another_coding_is_applied_in_place_or_by_a_restart(
        bench: Bench, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        change: dict[str, Any], kind: str) -> None:
    """The same controller with another configuration or faults: a soft reset applies the
    coding in place; another controller: a hard reset (a new process image)."""
    recoded: list[tuple[dict[str, Any], str]] = []
    monkeypatch.setattr(bench, "_recode", lambda coding, k: recoded.append((coding, k)))
    spec = RunSpec("dlc-paper", "lmpc")
    old = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}
    live = _Proc("controller")
    bench.controller, bench.coding = live, old  # type: ignore[assignment]
    bench.setup = hil_bench.controller_setup(spec)
    bench._prepare_controller(spec, {**old, **change}, tmp_path)
    assert recoded == [({**old, **change}, kind)]
    assert bench.controller is live and not live.stopped
