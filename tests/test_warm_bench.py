"""The warm bench (harness/run/hil_bench.py) across real processes: a run on a bench that has
carried out other runs — with frame faults, a SecOC attack, a killed controller, another
controller — equals the same run on newly started processes, bit for bit: the truth trace's
bytes and the bus log's frames (id, data, order; the time stamps aside, and the one wall-clock
field, the controller's compute time, harness/analysis/log_compare.py). And a process that
dies unexpectedly is replaced and the run retried once, counted."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from harness.analysis.log_compare import first_difference, log_frames
from harness.run.hil_bench import Bench, BenchError
from harness.run.runner import run_closed_loop
from harness.run.spec import RunSpec

DURATION_S = 1.5  # simulated s of each compared run: the lane change's approach


def _spec(out: Path, controller: str, **kw: object) -> RunSpec:
    base = dict(scenario="dlc-paper", controller=controller, out_dir=out, seed=3,
                duration_s=DURATION_S, make_plots=False, make_rrd=False)
    base.update(kw)
    return RunSpec(**base)  # type: ignore[arg-type]


def _same_run(warm: Path, fresh: Path) -> None:
    assert (warm / "truth.csv").read_bytes() == (fresh / "truth.csv").read_bytes()
    assert len(log_frames(warm / "bus.blf")) > 100 * DURATION_S  # the whole run is logged
    assert first_difference(warm / "bus.blf", fresh / "bus.blf") is None


# an earlier run on the same bench, then the compared run: every controller, each after
# another kind of disturbance
SEQUENCE = (
    ("nmpc-rhonn", dict(controller="nmpc-rhonn", faults=("loss:5%", "crc:2%"))),
    ("lmpc", dict(controller="lmpc", faults=("rogue-inject@0.3s",))),
    ("nmpc-mf", dict(controller="nmpc-mf", faults=("kill-controller@0.5s",))),
    ("passive", dict(controller="nmpc-mf", seed=9, mu=0.6)),
)


def test_a_warm_run_equals_a_fresh_run_for_every_controller(tmp_path: Path) -> None:
    warm_dirs = {}
    with Bench(tmp_path / "bench") as bench:
        for controller, before in SEQUENCE:
            disturb = _spec(tmp_path / f"before-{controller}", **before)  # type: ignore[arg-type]
            first = run_closed_loop(disturb, bench=bench)
            assert first.metrics["bench"]["warm"] is True
            warm_dirs[controller] = tmp_path / f"warm-{controller}"
            res = run_closed_loop(_spec(warm_dirs[controller], controller), bench=bench)
            assert res.reason == "finished", res.metrics
        counters = bench.counters
    # the controller was reset over UDS, not restarted, where nothing forced a new process
    assert counters.soft_resets >= 4 and counters.hard_resets >= 3 and counters.recodings >= 1
    assert counters.retries == 0  # the killed controller was asked for: replaced, no retry
    for controller, _ in SEQUENCE:
        fresh = tmp_path / f"fresh-{controller}"
        res = run_closed_loop(_spec(fresh, controller))
        assert res.reason == "finished" and res.metrics["bench"]["warm"] is False
        _same_run(warm_dirs[controller], fresh)


def test_a_controller_that_dies_unasked_is_replaced_and_the_run_retried_once(
        tmp_path: Path) -> None:
    killed: list[int] = []
    with Bench(tmp_path / "bench") as bench:

        def kill_once(_sim_time_s: float) -> None:
            if not killed and bench.controller is not None and bench.controller.proc:
                killed.append(bench.controller.proc.pid)
                os.kill(bench.controller.proc.pid, signal.SIGKILL)

        spec = _spec(tmp_path / "warm", "nmpc-rhonn", duration_s=6.0,
                     plant_extra_args=("--wait-ms", "2000"))
        res = bench.run(spec, progress=kill_once)
    assert killed, "the run ended before the first progress call"
    assert res.reason == "finished"
    assert res.bench["retries"] == 1
    # the first attempt's true reason (the plant itself finished that run without it) and
    # its files, kept beside the retry's
    assert res.bench["first_attempt_reason"].startswith("the controller process died at ")
    assert "exit code -9" in res.bench["first_attempt_reason"]
    first = tmp_path / "warm" / res.bench["first_attempt_dir"]
    assert (first / "controller.log").is_file() and (first / "truth.csv").is_file()
    assert (tmp_path / "warm" / "controller.log").is_file()  # the retry's own
    fresh = run_closed_loop(_spec(tmp_path / "fresh", "nmpc-rhonn", duration_s=6.0,
                                  plant_extra_args=("--wait-ms", "2000")))
    assert fresh.reason == "finished"
    assert (tmp_path / "warm" / "truth.csv").read_bytes() == \
        (tmp_path / "fresh" / "truth.csv").read_bytes()


def test_a_bench_refuses_a_run_on_another_bus(tmp_path: Path) -> None:
    with Bench(tmp_path / "bench") as bench, pytest.raises(BenchError, match="bus"):
        bench.run(_spec(tmp_path / "x", "passive", bus="socketcan:vcan0"))


def test_a_run_repeated_into_its_own_folder_starts_a_new_vehicle(tmp_path: Path) -> None:
    """The SecOC trip counter lives in the run's folder: a run carried out again into the
    same folder on a warm bench starts at trip 1 again, so its bus log (MACs included) equals
    the first one frame for frame."""
    import json
    import shutil

    out = tmp_path / "run"
    with Bench(tmp_path / "bench") as bench:
        first = run_closed_loop(_spec(out, "lmpc"), bench=bench)
        shutil.copytree(out, tmp_path / "first")
        again = run_closed_loop(_spec(out, "lmpc"), bench=bench)
    assert first.reason == again.reason == "finished"
    for folder in (tmp_path / "first", out):
        plant = json.loads((folder / "plant_summary.json").read_text())
        assert plant["secoc"]["trip"] == 1, folder
    _same_run(out, tmp_path / "first")
