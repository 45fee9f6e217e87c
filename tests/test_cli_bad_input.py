"""Every bad input a user met (issue 16) ends with one clear line on stderr and exit code 2,
before any process, server, file or directory is created.

Table-driven: each row is a command line of one of the five CLIs, a phrase its error must
contain, and the row runs the real ``main`` in-process (plus one row through the installed
console script in a subprocess, which is what a user runs)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from can_db import cli as bus_cli
from controller.runtime import process as controller_process
from harness import cli as harness_cli
from harness.bench import cli as bench_cli
from plant_sim import process as plant_process

MAINS: dict[str, Callable[[list[str]], int]] = {
    "rhonn-harness": harness_cli.main,
    "rhonn-bus": bus_cli.main,
    "rhonn-plant": plant_process.main,
    "rhonn-controller": controller_process.main,
    "rhonn-bench": bench_cli.main,
}

# (id, program, arguments with {tmp} for the test's directory, phrase in the error line)
CASES: list[tuple[str, str, str, str]] = [
    ("run-unknown-scenario", "rhonn-harness",
     "run no-such-scenario --controller lmpc --out {tmp}/o", "invalid choice: 'no-such-scenario'"),
    ("run-negative-speed", "rhonn-harness",
     "run dlc-paper --controller lmpc --speed -10 --out {tmp}/o", "-10 km/h is out of range"),
    ("run-mu-too-high", "rhonn-harness",
     "run dlc-paper --controller lmpc --mu 5 --out {tmp}/o", "5 is out of range"),
    ("run-unknown-param", "rhonn-harness",
     "run dlc-paper --controller lmpc --param foo=1 --out {tmp}/o", "no parameter 'foo'"),
    ("run-param-not-key-value", "rhonn-harness",
     "run dlc-paper --controller lmpc --param nonsense --out {tmp}/o", "KEY=VALUE"),
    ("run-param-wrong-type", "rhonn-harness",
     "run sine-with-dwell --controller lmpc --param amplitude_deg=abc --out {tmp}/o",
     "needs a number"),
    ("run-unknown-controller", "rhonn-harness",
     "run dlc-paper --controller nope --out {tmp}/o", "invalid choice: 'nope'"),
    ("run-out-not-writable", "rhonn-harness",
     "run dlc-paper --controller lmpc --out /proc/x", "--out /proc/x"),
    ("run-out-is-a-file", "rhonn-harness",
     "run dlc-paper --controller lmpc --out {tmp}/file", "not a directory"),
    ("run-remote-bus-unreachable", "rhonn-harness",
     "run dlc-paper --controller lmpc --bus remote:ws://127.0.0.1:1/ --out {tmp}/o",
     "rhonn-bus serve"),
    ("run-socketcan-missing", "rhonn-harness",
     "run dlc-paper --controller lmpc --bus socketcan:vcan9 --out {tmp}/o", "modprobe vcan"),
    ("run-bus-spec-nonsense", "rhonn-harness",
     "run dlc-paper --controller lmpc --bus nonsense --out {tmp}/o", "bad bus spec"),
    ("run-negative-duration", "rhonn-harness",
     "run dlc-paper --controller lmpc --duration -1 --out {tmp}/o", "-1 s is out of range"),
    ("run-negative-friction-step", "rhonn-harness",
     "run mu-step-corner --controller lmpc --param steps=[[8,-1]] --out {tmp}/o",
     "road mu must be in (0, 2]"),
    ("run-malformed-friction-steps", "rhonn-harness",
     "run mu-step-corner --controller lmpc --param steps=[[8,0.3 --out {tmp}/o",
     "not a JSON list"),
    ("benchmark-unknown-section", "rhonn-harness",
     "benchmark --out {tmp}/o --sections core,bogus", "unknown section 'bogus'"),
    ("run-bad-fault", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault bogus:1 --out {tmp}/o", "unknown fault kind"),
    ("run-core-exception-bad-duration", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault core-exception:soon@2s --out {tmp}/o",
     "bad duration 'soon'"),
    ("run-core-exception-zero-duration", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault core-exception:0ms@2s --out {tmp}/o",
     "duration must be > 0"),
    ("run-core-exception-two-arguments", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault core-exception:1s,SYNC@2s --out {tmp}/o",
     "takes at most a duration"),
    ("run-core-exception-bad-time", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault core-exception@1.2.3s --out {tmp}/o",
     "bad duration '1.2.3s'"),
    ("controller-core-exception-bad-time", "rhonn-controller",
     "--bus virtual:t --controller lmpc --fault core-exception@later", "bad duration 'later'"),
    ("run-malformed-config", "rhonn-harness",
     "run dlc-paper --controller lmpc --config {tmp}/bad.toml --out {tmp}/o", "not valid TOML"),
    ("compare-unknown-controller", "rhonn-harness",
     "compare dlc-paper --controllers lmpc,bogus --out {tmp}/o", "unknown controller 'bogus'"),
    ("paper-zero-jobs", "rhonn-harness", "paper --out {tmp}/o --jobs 0", "0 is out of range"),
    ("replay-missing-log", "rhonn-harness", "replay {tmp}/missing.blf", "no such file"),
    ("replay-empty-log", "rhonn-harness", "replay {tmp}/empty.blf", "the file is empty"),
    ("replay-garbage-log", "rhonn-harness", "replay {tmp}/garbage.blf", "not a readable log"),
    ("controller-malformed-config", "rhonn-controller",
     "--bus virtual:t --controller lmpc --config {tmp}/bad.toml", "not valid TOML"),
    ("controller-config-unknown-key", "rhonn-controller",
     "--bus virtual:t --controller lmpc --config {tmp}/unknown_key.toml", "bogus_key"),
    ("controller-config-wrong-type", "rhonn-controller",
     "--bus virtual:t --controller lmpc --config {tmp}/wrong_type.toml", "--config"),
    ("controller-unreachable-bus", "rhonn-controller",
     "--bus remote:ws://127.0.0.1:1/ --controller lmpc", "no loopback bus server"),
    ("plant-unknown-scenario", "rhonn-plant", "--bus virtual:t --scenario nope",
     "invalid choice: 'nope'"),
    ("plant-trace-unwritable", "rhonn-plant",
     "--bus virtual:t --scenario dlc-paper --trace /proc/x/t.csv", "--trace"),
    ("bus-dump-bad-spec", "rhonn-bus", "dump --bus nonsense", "bad bus spec"),
    ("bench-unknown", "rhonn-bench", "bogus", "unknown benchmark 'bogus'"),
    ("bench-fuzz-unknown-target", "rhonn-bench", "fuzz --only bogus", "unknown target"),
]


@pytest.fixture
def inputs(tmp_path: Path) -> Path:
    """The bad files the cases name."""
    (tmp_path / "bad.toml").write_text("x = [\n")
    (tmp_path / "unknown_key.toml").write_text("[mpc]\nbogus_key = 1\n")
    (tmp_path / "wrong_type.toml").write_text('[mpc]\nhorizon = "ten"\n')
    (tmp_path / "empty.blf").write_bytes(b"")
    (tmp_path / "garbage.blf").write_bytes(b"this is not a binary logging file" * 10)
    (tmp_path / "file").write_text("a file, not a directory\n")
    return tmp_path


def _exit_code(main: Callable[[list[str]], int], argv: list[str]) -> int:
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else 1


@pytest.mark.parametrize(("prog", "args", "phrase"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_nothing_written(
        inputs: Path, capsys: pytest.CaptureFixture[str], prog: str, args: str,
        phrase: str) -> None:
    before = sorted(p.name for p in inputs.iterdir())
    code = _exit_code(MAINS[prog], args.format(tmp=inputs).split())
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}"), err
    assert phrase in lines[0], err
    assert "Traceback" not in err
    assert sorted(p.name for p in inputs.iterdir()) == before  # nothing created


def test_console_script_reports_the_same_single_line(inputs: Path) -> None:
    """What a user types: the installed ``rhonn-harness`` in its own process."""
    exe = Path(sys.executable).with_name("rhonn-harness")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "harness.cli"]
    proc = subprocess.run([*cmd, "run", "dlc-paper", "--controller", "lmpc", "--mu", "5",
                           "--out", str(inputs / "o")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "--mu: 5 is out of range" in proc.stderr
    assert not (inputs / "o").exists()
