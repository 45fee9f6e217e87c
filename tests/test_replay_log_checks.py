"""`rhonn-harness replay` checks the log first (harness/run/log_check.py): a truncated file,
several runs in one capture, a capture that starts inside a run and torque frames from
outside the run are refused with one line and exit code 2, instead of a BIT-IDENTICAL on part
of the log; a plant restart within one run is not mistaken for a second run."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import can
import pytest

from can_db.codec import Codec
from can_db.secoc_keys import load_keys, resolve_key_source
from harness.report.run_report import run_and_report
from harness.run.log_check import check_file_complete, check_frames
from harness.run.replay import (
    PartialLogError,
    genuine_frames,
    replay_log,
    split_at_restarts,
)
from harness.run.spec import RunSpec


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two recorded runs: a clean SecOC one, and one without SecOC with a plant restart."""
    root = tmp_path_factory.mktemp("replay-checks")
    out = {}
    for name, faults, secoc, duration in (("clean", [], True, 1.5),
                                          ("restart", ["restart-plant@1s"], False, 2.0)):
        res = run_and_report(RunSpec(scenario="dlc-paper", controller="lmpc",
                                     out_dir=root / name, duration_s=duration, faults=faults,
                                     secoc=secoc, make_plots=False, make_rrd=False))
        assert res.reason == "finished"
        out[name] = root / name / "bus.blf"
    return out


def frames_of(path: Path) -> list[can.Message]:
    with can.BLFReader(str(path)) as reader:
        return list(reader)


def write_blf(path: Path, frames: list[can.Message]) -> Path:
    with can.BLFWriter(str(path)) as writer:
        for msg in frames:
            writer.on_message_received(msg)
    return path


def twice(frames: list[can.Message]) -> list[can.Message]:
    """The run captured twice, back to back (as a capture of two runs of one command)."""
    span = frames[-1].timestamp - frames[0].timestamp + 1.0
    again = [copy.copy(m) for m in frames]
    for m in again:
        m.timestamp += span
    return frames + again


def replay_cli(log: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "harness.cli", "replay", str(log)],
                          capture_output=True, text=True, timeout=300)


def test_a_whole_log_and_a_plant_restart_replay_bit_identical(runs: dict[str, Path]) -> None:
    for log in runs.values():
        assert check_file_complete(log) == [] and check_frames(frames_of(log), Codec()) == []
    result = replay_log(runs["restart"])  # the plant restarted: one run, two plant starts
    assert result.bit_identical and result.uncompared == 0 and result.recorded > 150
    res = replay_cli(runs["clean"])  # no mismatch: said in words, not as Python's None
    assert res.returncode == 0 and ": BIT-IDENTICAL" in res.stdout, res.stdout + res.stderr
    assert res.stdout.rstrip().endswith("first mismatch none"), res.stdout


def test_a_capture_of_two_runs_is_refused_with_and_without_secoc(runs: dict[str, Path],
                                                                 tmp_path: Path) -> None:
    secured = write_blf(tmp_path / "twice-secoc.blf", twice(frames_of(runs["clean"])))
    res = replay_cli(secured)  # across processes, as a user runs it
    assert res.returncode == 2, res.stdout + res.stderr
    assert "more than one run" in res.stderr and "BIT-IDENTICAL" not in res.stdout
    plain = write_blf(tmp_path / "twice.blf", twice(frames_of(runs["restart"])))
    with pytest.raises(PartialLogError, match="more than one run"):
        replay_log(plain)


def test_a_truncated_blf_and_asc_are_refused(runs: dict[str, Path], tmp_path: Path) -> None:
    cut = tmp_path / "cut.blf"
    cut.write_bytes(runs["clean"].read_bytes()[:5000])
    res = replay_cli(cut)
    assert res.returncode == 2 and "truncated" in res.stderr, res.stderr
    asc = tmp_path / "run.asc"
    with can.ASCWriter(str(asc)) as writer:
        for msg in frames_of(runs["restart"]):
            writer.on_message_received(msg)
    assert check_file_complete(asc) == []
    text = asc.read_text().splitlines()
    asc.write_text("\n".join(text[: len(text) // 2]) + "\n")
    assert "truncated" in check_file_complete(asc)[0]


def test_a_capture_that_starts_inside_the_run_is_refused(runs: dict[str, Path],
                                                         tmp_path: Path) -> None:
    frames = frames_of(runs["clean"])
    late = write_blf(tmp_path / "late.blf", frames[len(frames) // 3:])
    with pytest.raises(PartialLogError, match="starts inside a run: its first SYNC is cycle"):
        replay_log(late)


def test_torque_frames_from_outside_the_run_are_refused(runs: dict[str, Path]) -> None:
    codec = Codec()
    frames = frames_of(runs["restart"])
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    stray = copy.copy(next(m for m in frames if m.arbitration_id == torque_id))
    problems = check_frames([stray, *frames], codec)  # an answer before the first SYNC
    assert problems and "outside the run" in problems[0]


def test_an_asc_cut_short_and_closed_again_is_refused_in_its_run_directory(
        runs: dict[str, Path]) -> None:
    """Half of a run's frames written as a well-formed ASC (``End TriggerBlock`` and all)
    beside the run's metrics.json: fewer frames than the run recorded, refused."""
    frames = frames_of(runs["clean"])
    cut = runs["clean"].parent / "cut.asc"
    try:
        with can.ASCWriter(str(cut)) as writer:
            for msg in frames[: len(frames) // 2]:
                writer.on_message_received(msg)
        assert check_file_complete(cut) == []  # the file itself looks whole
        res = replay_cli(cut)
        assert res.returncode == 2, res.stdout + res.stderr
        assert f"it holds {len(frames) // 2} frames, fewer than the {len(frames)} its run " \
               "recorded" in res.stderr and "BIT-IDENTICAL" not in res.stdout, res.stderr
    finally:
        cut.unlink(missing_ok=True)


def test_a_run_with_lost_torque_frames_replays_bit_identical_as_one_process(
        tmp_path: Path) -> None:
    """A lockstep run whose torque frames are lost on the bus (``loss`` on the controller's
    frames, SecOC on): the log lacks some answers, and a lost frame with alive counter 15
    makes the next one look like a new process's first (counter 0). The replay matches the
    recorded frames in order, counts the missing answers as lost, keeps one process, and
    says BIT-IDENTICAL (before: DIFFERENT, split into a "controller process" at every such
    frame, and a hundred SecOC warning lines)."""
    res = run_and_report(RunSpec(scenario="dlc-paper", controller="lmpc",
                                 out_dir=tmp_path / "lossy", duration_s=2.0,
                                 faults=["loss:30%,WHEEL_TORQUE_CMD"], make_plots=False,
                                 make_rrd=False))
    assert res.reason == "finished"
    log = tmp_path / "lossy" / "bus.blf"
    codec = Codec()
    frames = frames_of(log)
    keys = load_keys(resolve_key_source("ci-test-key"))
    # the log does hold what looks like a restart to the alive-counter rule alone
    assert len(split_at_restarts(frames, codec, genuine_frames(frames, codec, keys))) > 1
    result = replay_log(log, keys=keys)
    assert len(result.segments) == 1 and result.bit_identical, result
    assert result.lost_in_log > 0 and result.uncompared == 0
    cli = replay_cli(log)
    assert cli.returncode == 0, cli.stdout + cli.stderr
    assert ": BIT-IDENTICAL" in cli.stdout and "controller process" not in cli.stdout
    assert f"({result.lost_in_log} not in the log: lost on the bus)" in cli.stdout
    assert "SecOC: first rejected" not in cli.stderr, cli.stderr
