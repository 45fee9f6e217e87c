"""The SecOC trip counter across real OS processes: every run is a trip of its own, so a
recording of an earlier run replayed into a later one is rejected as stale.

* A run on a warm bench is recorded (bus log). The next run on the same bench — the same
  plant process, served — has the next trip; a rogue process replays the first run's
  recorded secured frames into it (``harness/run/rogue.py --attack recording``, 20 cycles
  ahead of the live bus, where within one trip they would be fresher than the genuine ones
  and win). The controller rejects every replayed SYNC as ``stale_freshness`` (its trip is
  on the wire, below the live one) and accepts every genuine one; no genuine frame is taken
  for a replay. A run on a new bench after it has the trip after that: the counter outlives
  the processes. This test fails when the bench or the served plant stops advancing the
  counter between runs (e.g. a counter kept in, and removed with, the run's folder).
* ``rhonn-plant`` refuses to start with a counter it cannot use (one line, exit 5) and a
  trace it cannot open (one line, exit 1), never a traceback; served, both are one
  ``error`` line and the plant keeps serving.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from can_db.transport.bus import resolve_bus
from harness.run.hil_bench import Bench
from harness.run.runner import run_closed_loop
from harness.run.spec import RunSpec
from plant_sim.process import EXIT_FILES, EXIT_TRIP_COUNTER
from tests.helpers_proc import spawn

AHEAD = 20  # cycles the replay runs ahead of the live bus
TIMEOUT_S = 120.0  # wall s for a process start or a short run on a loaded 2-core machine


def _spec(out: Path, duration_s: float, **kw: object) -> RunSpec:
    base = dict(scenario="dlc-paper", controller="lmpc", out_dir=out, seed=3,
                duration_s=duration_s, make_plots=False, make_rrd=False,
                secoc_keys="ci-test-key")
    base.update(kw)
    return RunSpec(**base)  # type: ignore[arg-type]


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _start_rogue(bus_spec: str, log: Path, summary: Path) -> subprocess.Popen[str]:
    """The rogue, its log read and its bus open (it has said how many cycles it holds)."""
    rogue = spawn("-m", "harness.run.rogue", "--bus", bus_spec, "--attack", "recording",
                  "--log", str(log), "--ahead", str(AHEAD), "--summary", str(summary),
                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    assert rogue.stdout is not None
    for line in rogue.stdout:
        if line.startswith("rogue recorded"):
            return rogue
    raise AssertionError(f"the rogue ended before its recording was read: {rogue.wait()}")


def test_a_recording_of_an_earlier_run_is_rejected_as_stale_in_the_next(
        tmp_path: Path) -> None:
    with Bench(tmp_path / "bench") as bench:
        # run A: recorded, with another friction so its frames are not the next run's
        first = run_closed_loop(_spec(tmp_path / "a", 1.5, mu=0.6), bench=bench)
        assert first.reason == "finished", first.metrics
        assert bench.bus_spec is not None
        rogue = _start_rogue(bench.bus_spec, tmp_path / "a" / "bus.blf",
                             tmp_path / "rogue.json")
        try:
            # run B on the same bench, long enough for the whole replay to reach it
            second = run_closed_loop(_spec(tmp_path / "b", 2.5), bench=bench)
            assert rogue.wait(timeout=TIMEOUT_S) == 0  # done: once through the log
        finally:
            if rogue.poll() is None:
                rogue.kill()
                rogue.wait()
            assert rogue.stdout is not None
            rogue.stdout.close()
        assert second.reason == "finished", second.metrics
        assert second.metrics["bench"]["warm"] is True
        assert bench.counters.plant_starts == 1  # one plant process served both runs
    trip_a = _json(tmp_path / "a" / "plant_summary.json")["secoc"]["trip"]
    plant = _json(tmp_path / "b" / "plant_summary.json")
    ctrl = _json(tmp_path / "b" / "controller_summary.json")["secoc"]
    bursts = _json(tmp_path / "rogue.json")["bursts_sent"]
    # every run its own trip: the served plant advanced the counter for run B
    assert plant["secoc"]["trip"] == trip_a + 1 and ctrl["trip"] == trip_a + 1
    cycles = plant["cycles"]
    assert cycles == 250 and bursts == 150 - AHEAD  # A's 150 bursts (1.5 s) less the skipped
    # the replayed bursts the controller received (the one sent as its run ends may not be)
    replayed = ctrl["received"]["SYNC"] - cycles
    assert bursts - 2 <= replayed <= bursts
    # every replayed SYNC is authentic but of the older trip: rejected, each counted once —
    # stale when its own authenticator verified it, unauthenticated when a genuine SYNC that
    # arrived between the two verified first and pushed it out (its authenticator is then
    # an orphan); nearly all are judged stale
    sync_rejected = ctrl["rejected_by_frame"]["SYNC"]
    assert set(sync_rejected) <= {"stale_freshness", "unauthenticated", "orphan_auth"}
    assert sync_rejected["stale_freshness"] + sync_rejected.get("unauthenticated", 0) \
        == replayed
    assert sync_rejected["stale_freshness"] >= replayed - 5, sync_rejected
    # every genuine SYNC accepted, none taken for a replay: no freshness of the old trip got
    # above the live one (in one trip the replay, 20 cycles ahead, would win)
    assert ctrl["accepted"]["SYNC"] == cycles and ctrl["resyncs"] == 0
    assert "replay" not in ctrl["rejected"] and "replay" not in plant["secoc"]["rejected"]
    # the replayed driver and sensor frames fail their MACs under the live trip (the MAC
    # covers the whole freshness value): all received, none used; every genuine one used
    for name in ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST"):
        # (as for SYNC, the burst sent as the run ends may be cut between its frames)
        assert cycles + bursts - 2 <= ctrl["received"][name] <= cycles + bursts, name
        assert ctrl["accepted"][name] == cycles, name
        assert ctrl["rejected_by_frame"][name].get("bad_mac", 0) >= replayed - 5, name
    # the plant: the replayed torque commands fail their MACs, every genuine one is obeyed
    torque = "WHEEL_TORQUE_CMD"
    assert cycles + bursts - 2 <= plant["secoc"]["received"][torque] <= cycles + bursts
    assert plant["secoc"]["accepted"][torque] == plant["commanded_cycles"] == cycles
    assert plant["secoc"]["rejected_by_frame"][torque]["bad_mac"] >= bursts - 5
    assert plant["fallback_cycles"] == 0
    # a new bench (new processes) goes on counting: the counter outlives the plant process
    third = run_closed_loop(_spec(tmp_path / "c", 0.3))
    assert third.reason == "finished" and third.metrics["bench"]["warm"] is False
    assert _json(tmp_path / "c" / "plant_summary.json")["secoc"]["trip"] == trip_a + 2


# ------------------------------------------------------------------ refused starts
def _plant(*args: str, env_dir: Path | None = None) -> subprocess.CompletedProcess[str]:
    proc = spawn("-m", "plant_sim.process", "--bus", "local:trip-refusal", "--scenario",
                 "dlc-paper", *args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=TIMEOUT_S)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.parametrize(("content", "words"), [
    (b"garbage\n", "corrupt ('garbage\\n' is not a trip 1 .. 1048575)"),
    (b"\xff\n", "unreadable (UnicodeDecodeError)"),
])
def test_a_plant_with_a_counter_it_cannot_use_does_not_start(
        tmp_path: Path, content: bytes, words: str) -> None:
    state = tmp_path / "secoc_trip"
    state.write_bytes(content)
    res = _plant("--secoc-state", str(state), "--trace", str(tmp_path / "truth.csv"))
    assert res.returncode == EXIT_TRIP_COUNTER == 5, res.stderr
    assert res.stderr == (f"rhonn-plant: error: SecOC trip counter {state}: {words}; "
                          "refusing to start: a counter that starts again would accept "
                          "recordings of earlier trips (restore the file, or rotate the keys "
                          "and remove it)\n")
    assert state.read_bytes() == content and res.stdout == ""
    assert not (tmp_path / "truth.csv").exists() and not (tmp_path / "truth.csv.rows").exists()


def test_a_plant_whose_trace_cannot_be_opened_ends_with_one_line(tmp_path: Path) -> None:
    (tmp_path / "truth.csv.rows").mkdir()  # the trace's row file is taken by a directory
    res = _plant("--no-secoc", "--trace", str(tmp_path / "truth.csv"))
    assert res.returncode == EXIT_FILES == 1, res.stderr
    assert res.stderr == ("rhonn-plant: error: cannot write the run's files: Is a directory "
                          f"({tmp_path / 'truth.csv.rows'})\n")


def test_a_served_plant_refuses_such_runs_and_goes_on_serving(tmp_path: Path) -> None:
    spec, hub = resolve_bus("auto")
    corrupt = tmp_path / "corrupt_trip"
    corrupt.write_text("-1\n")
    (tmp_path / "t.csv.rows").mkdir()
    runs = [["--scenario", "dlc-paper", "--secoc-state", str(corrupt)],
            ["--scenario", "dlc-paper", "--secoc-state", str(tmp_path / "trip"), "--trace",
             str(tmp_path / "t.csv")]]
    try:
        proc = spawn("-m", "plant_sim.process", "--bus", spec, "--serve", "--secoc-keys",
                     "ci-test-key", stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                     stderr=subprocess.PIPE)
        commands = "".join(json.dumps({"run": r}) + "\n" for r in runs) + '{"quit": true}\n'
        out, err = proc.communicate(commands, timeout=TIMEOUT_S)
    finally:
        hub.stop()
    assert proc.returncode == 0, err
    assert out.splitlines() == [
        f"ready serve on {spec}",
        f"error SecOC trip counter {corrupt}: corrupt ('-1\\n' is not a trip 1 .. 1048575); "
        "refusing to start: a counter that starts again would accept recordings of earlier "
        "trips (restore the file, or rotate the keys and remove it)",
        f"error cannot write the run's files: Is a directory ({tmp_path / 't.csv.rows'})"]
    assert "Traceback" not in err and corrupt.read_text() == "-1\n"
