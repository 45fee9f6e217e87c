"""`rhonn-plant --serve` across processes: served runs equal one-shot runs, byte for byte.

A local hub, a real controller process (lockstep, SecOC with the public CI test key) started
the way harness/run/runner.py starts it, restarted for every run (its UDS reset is tested
elsewhere: here only the plant is under test), 1 s runs. Two different runs served back to
back by one plant process give the truth.csv bytes of the same runs made by a fresh one-shot
plant each; a bad run line is one ``error`` line and no file; end of input exits 0; SIGTERM
during a served run writes its summary, prints ``done`` and exits 0.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import can

from can_db.codec import Codec
from can_db.transport.bus import open_bus, resolve_bus
from harness.run.procs import Child
from tests.helpers_proc import spawn

CONTROLLER = "lmpc"
# (scenario, seed) of the two runs; --duration 1.0 s each
RUNS = (("dlc-paper", 1), ("constant-radius", 2))
# Lockstep waits this long for an answer, ms: far beyond any scheduling delay on a loaded
# machine, so no cycle falls back by timeout and the truth depends on the frames alone.
WAIT_MS = 10_000
STALE_FRAMES = 5
LINE_TIMEOUT_S = 60.0  # a plant start or a 1 s run on a loaded 2-core machine, s


def _run_args(out: Path, scenario: str, seed: int, mode: str = "lockstep",
              duration_s: float = 1.0) -> list[str]:
    return ["--scenario", scenario, "--seed", str(seed), "--duration", str(duration_s),
            "--mode", mode, "--wait-ms", str(WAIT_MS),
            "--trace", str(out / "truth.csv"), "--summary", str(out / "plant_summary.json"),
            "--secoc", "--secoc-keys", "ci-test-key", "--secoc-state", str(out / "secoc_trip")]


def _controller(spec: str, out: Path) -> Child:
    out.mkdir(parents=True, exist_ok=True)
    return Child("controller", ["-m", "controller.runtime.process", "--bus", spec,
                                "--controller", CONTROLLER, "--mode", "lockstep",
                                "--summary", str(out / "controller_summary.json"),
                                "--secoc", "--secoc-keys", "ci-test-key"],
                 out / "controller.log").start(timeout_s=LINE_TIMEOUT_S)


def _stop(controller: Child) -> None:
    controller.stop()
    if controller.proc is not None and controller.proc.stdout is not None:
        controller.proc.stdout.close()  # Child reads it to the end, then leaves it open


class _Served:
    """A ``--serve`` plant process: JSON commands in, stdout lines out (with timeouts)."""

    def __init__(self, spec: str, stderr: Path,
                 program: tuple[str, ...] = ("-m", "plant_sim.process")) -> None:
        self._err = stderr.open("w")
        self.proc = spawn(*program, "--bus", spec, "--serve", "--secoc", "--secoc-keys",
                          "ci-test-key", stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                          stderr=self._err, bufsize=1)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def line(self) -> str:
        line = self.lines.get(timeout=LINE_TIMEOUT_S)
        assert line is not None, "the plant closed its stdout"
        return line

    def send(self, command: dict[str, object]) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._pump_thread.join(timeout=5.0)  # the process's end closed its stdout
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None and not pipe.closed:
                # unflushed input for a process that is gone: nothing to flush to
                with contextlib.suppress(BrokenPipeError):
                    pipe.close()
        self._err.close()


def _send_stale_frames(spec: str) -> None:
    """Torque frames that belong to no run (all-zero payload: bad CRC, no authenticator)."""
    bus = open_bus(spec)
    try:
        torque_id = Codec().messages["WHEEL_TORQUE_CMD"].frame_id
        for _ in range(STALE_FRAMES):
            bus.send(can.Message(arbitration_id=torque_id, data=bytes(8),
                                 is_extended_id=False))
    finally:
        bus.shutdown()


def _counters(summary: dict[str, object]) -> dict[str, object]:
    """A plant summary without what depends on the wall clock or the process."""
    return {k: v for k, v in summary.items()
            if k not in ("loop_wall_s", "cpu_affinity", "drained_frames", "stalls")}


def _one_shot(spec: str, out: Path, scenario: str, seed: int) -> dict[str, object]:
    """The reference: a fresh controller and a fresh one-shot plant; the plant's summary."""
    controller = _controller(spec, out)
    try:
        with (out / "plant.err").open("w") as err:
            plant = spawn("-m", "plant_sim.process", "--bus", spec,
                          *_run_args(out, scenario, seed), stdout=subprocess.DEVNULL,
                          stderr=err)
            try:
                code = plant.wait(timeout=LINE_TIMEOUT_S)
            finally:
                plant.kill()
                plant.wait()
        assert code == 0, (out / "plant.err").read_text()
    finally:
        _stop(controller)
    return json.loads((out / "plant_summary.json").read_text())


def _served_run(plant: _Served, spec: str, out: Path, scenario: str, seed: int
                ) -> dict[str, object]:
    """One served run against a fresh controller; its ``done`` summary."""
    controller = _controller(spec, out)
    try:
        plant.send({"run": _run_args(out, scenario, seed)})
        assert plant.line() == f"loaded {scenario}"
        done = plant.line()
        assert done.startswith("done "), done
    finally:
        _stop(controller)
    return json.loads(done[len("done "):])


def test_served_runs_equal_one_shot_runs(tmp_path: Path) -> None:
    spec_ref, hub_ref = resolve_bus("auto")
    spec, hub = resolve_bus("auto")
    plant = _Served(spec, tmp_path / "served.err")
    pool = ThreadPoolExecutor(1)  # the references on their own bus, meanwhile
    try:
        refs_future = pool.submit(lambda: [_one_shot(spec_ref, tmp_path / f"fresh{i}", *run)
                                           for i, run in enumerate(RUNS)])
        assert plant.line() == f"ready serve on {spec}"
        served = []
        for i, (scenario, seed) in enumerate(RUNS):
            served.append(_served_run(plant, spec, tmp_path / f"served{i}", scenario, seed))
            if i == 0:
                _send_stale_frames(spec)  # queued at the idle plant: dropped before run 2
                # a bad run between the two: one error line, no file, still serving
                bad = tmp_path / "bad"
                bad.mkdir()
                plant.send({"run": [*_run_args(bad, "dlc-paper", 1), "--mu", "-1"]})
                line = plant.line()
                assert line.startswith("error ") and "--mu" in line, line
                assert list(bad.iterdir()) == []
        assert plant.proc.stdin is not None
        plant.proc.stdin.close()  # end of input: the plant exits 0
        assert plant.proc.wait(timeout=LINE_TIMEOUT_S) == 0
        refs = refs_future.result(timeout=4 * LINE_TIMEOUT_S)
    finally:
        plant.close()
        pool.shutdown(wait=True)
        hub.stop()
        hub_ref.stop()
    for i, (ref, got) in enumerate(zip(refs, served, strict=True)):
        fresh = (tmp_path / f"fresh{i}" / "truth.csv").read_bytes()
        warm = (tmp_path / f"served{i}" / "truth.csv").read_bytes()
        assert warm == fresh, f"run {i} ({RUNS[i]}): served truth differs from one-shot"
        assert len(fresh.splitlines()) == 102  # header + 101 rows (0 .. 1 s)
        # the controller answered every cycle (else the runs would match as open-loop runs)
        assert got["reason"] == ref["reason"] == "finished"
        assert got["commanded_cycles"] == ref["commanded_cycles"] == 100
        assert got["lockstep_timeouts"] == 0 and got["secoc"]["trip"] == 1  # type: ignore[index]
        assert json.loads((tmp_path / f"served{i}" / "plant_summary.json").read_text()) == got
        # every counter of the run (frames sent on the bus included) as in a fresh process
        assert _counters(got) == _counters(ref)
    assert served[1]["drained_frames"] >= STALE_FRAMES  # type: ignore[operator]
    # two different runs: the comparison is not of one trace with itself
    assert (tmp_path / "fresh0" / "truth.csv").read_bytes() != \
        (tmp_path / "fresh1" / "truth.csv").read_bytes()


def test_sigterm_during_a_served_run_ends_it_and_the_process(tmp_path: Path) -> None:
    spec, hub = resolve_bus("auto")
    plant = _Served(spec, tmp_path / "served.err")
    try:
        assert plant.line() == f"ready serve on {spec}"
        # realtime and no controller: 30 s of paced cycles, stopped long before the end
        plant.send({"run": _run_args(tmp_path, "constant-radius", 3, mode="realtime",
                                     duration_s=30.0)})
        assert plant.line() == "loaded constant-radius"
        time.sleep(0.5)
        plant.proc.send_signal(signal.SIGTERM)
        done = plant.line()
        assert done.startswith("done "), done
        assert plant.proc.wait(timeout=LINE_TIMEOUT_S) == 0
    finally:
        plant.close()
        hub.stop()
    summary = json.loads((tmp_path / "plant_summary.json").read_text())
    assert summary == json.loads(done[len("done "):])
    assert summary["reason"] == "stopped by signal"
    assert 0 < summary["cycles"] < 3000
    rows = (tmp_path / "truth.csv").read_text().splitlines()
    assert len(rows) == summary["cycles"] + 2  # header + the initial row + one a cycle


BAD_COMMANDS = ('{"run": "--scenario dlc-paper"}', "not json", '{"run": ["--help"]}',
                '{"run": ["--scenario", "dlc-paper", "--bus", "local:x"]}', '{"quit": 1}',
                '{"run": ["--scenario", "dlc-paper", "--fault", "bogus:1"]}')


def test_bad_commands_are_one_error_line_each(tmp_path: Path) -> None:
    spec, hub = resolve_bus("auto")
    plant = _Served(spec, tmp_path / "served.err")
    try:
        assert plant.line() == f"ready serve on {spec}"
        assert plant.proc.stdin is not None
        plant.proc.stdin.write("\n".join((*BAD_COMMANDS, "", '{"quit": true}')) + "\n")
        plant.proc.stdin.flush()
        errors = [plant.line() for _ in BAD_COMMANDS]
        assert all(e.startswith("error ") for e in errors), errors
        assert plant.proc.wait(timeout=LINE_TIMEOUT_S) == 0
        assert plant.lines.get(timeout=5.0) is None, "more on stdout than the error lines"
    finally:
        plant.close()
        hub.stop()


CRASHING_PLANT = """
import sys
from plant_sim import process

def crash(*args, **kwargs):
    raise RuntimeError("injected by the test")

process._run_lockstep = crash
sys.exit(process.main(sys.argv[1:]))
"""


def test_a_run_that_raises_ends_the_process_with_code_1(tmp_path: Path) -> None:
    spec, hub = resolve_bus("auto")
    plant = _Served(spec, tmp_path / "served.err", program=("-c", CRASHING_PLANT))
    try:
        assert plant.line() == f"ready serve on {spec}"
        plant.send({"run": ["--scenario", "dlc-paper", "--summary",
                            str(tmp_path / "plant_summary.json"), "--trace",
                            str(tmp_path / "truth.csv")]})
        assert plant.line() == "loaded dlc-paper"
        assert plant.line() == "error run failed: RuntimeError: injected by the test"
        assert plant.proc.wait(timeout=LINE_TIMEOUT_S) == 1
    finally:
        plant.close()
        hub.stop()
    summary = json.loads((tmp_path / "plant_summary.json").read_text())
    assert summary["reason"] == "error: RuntimeError: injected by the test"
    assert len((tmp_path / "truth.csv").read_text().splitlines()) == 2  # header + first row
    assert "RuntimeError: injected by the test" in (tmp_path / "served.err").read_text()
