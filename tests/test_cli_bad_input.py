"""Every bad input of the command-line tools ends with one clear line on stderr and exit code
2, before any process, server, file or directory is created.

Table-driven: each row is a command line of one of the five CLIs, a phrase its error must
contain, and the row runs the real ``main`` in-process with process creation watched (plus
one row through the installed console script in a subprocess, which is what a user runs).
The scenario-file rows use the files of the ``inputs`` fixture: each breaks one rule of the
schema (plant_sim/scenario_schema.py, docs/scenarios.md)."""

from __future__ import annotations

import os
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
    ("run-empty-out", "rhonn-harness", "run dlc-paper --controller lmpc --out=",
     "--out: empty path"),
    ("run-unknown-scenario", "rhonn-harness",
     "run no-such-scenario --controller lmpc --out {tmp}/o",
     "unknown scenario 'no-such-scenario'; choose from"),
    ("run-rerun-port-without-live", "rhonn-harness",
     "run dlc-paper --controller lmpc --rerun-port 9100 --out {tmp}/o",
     "--rerun-port needs --rerun-live"),
    ("compare-rerun-hold-without-live", "rhonn-harness",
     "compare dlc-paper --controllers lmpc --rerun-hold 5 --out {tmp}/o",
     "--rerun-hold needs --rerun-live"),
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
     "scenario sine-with-dwell: parameter amplitude_deg: must be a number (deg), got 'abc'"),
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
     "parameter steps[0].mu: must be > 0 and <= 1.5, got -1"),
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
     "--bus local:t --controller lmpc --bench --fault core-exception@later",
     "bad duration 'later'"),
    ("controller-fault-without-bench", "rhonn-controller",
     "--bus local:t --controller lmpc --fault loss:5%",
     "fault injection only on a bench controller"),
    ("run-malformed-config", "rhonn-harness",
     "run dlc-paper --controller lmpc --config {tmp}/bad.toml --out {tmp}/o", "not valid TOML"),
    ("compare-unknown-controller", "rhonn-harness",
     "compare dlc-paper --controllers lmpc,bogus --out {tmp}/o", "unknown controller 'bogus'"),
    ("paper-zero-jobs", "rhonn-harness", "paper --out {tmp}/o --jobs 0", "0 is out of range"),
    ("replay-missing-log", "rhonn-harness", "replay {tmp}/missing.blf", "no such file"),
    ("replay-empty-log", "rhonn-harness", "replay {tmp}/empty.blf", "the file is empty"),
    ("replay-garbage-log", "rhonn-harness", "replay {tmp}/garbage.blf", "not a readable log"),
    # rrd: the recording of a run directory; a directory that holds no run is one line
    ("rrd-missing-dir", "rhonn-harness", "rrd {tmp}/missing",
     "rhonn-harness rrd: error: {tmp}/missing: no such directory"),
    ("rrd-a-file", "rhonn-harness", "rrd {tmp}/file", "{tmp}/file: not a directory"),
    ("rrd-no-truth", "rhonn-harness", "rrd {tmp}",
     "{tmp}: no truth.csv (not a run directory, or a run that stopped before"),
    ("rrd-no-metrics", "rhonn-harness", "rrd {tmp}/killed",
     "{tmp}/killed: no readable metrics.json"),
    ("rrd-empty-out", "rhonn-harness", "rrd {tmp}/killed --out=", "--out: empty path"),
    ("controller-malformed-config", "rhonn-controller",
     "--bus local:t --controller lmpc --config {tmp}/bad.toml", "not valid TOML"),
    ("controller-config-unknown-key", "rhonn-controller",
     "--bus local:t --controller lmpc --config {tmp}/unknown_key.toml", "bogus_key"),
    ("controller-config-wrong-type", "rhonn-controller",
     "--bus local:t --controller lmpc --config {tmp}/wrong_type.toml", "--config"),
    ("controller-unreachable-bus", "rhonn-controller",
     "--bus remote:ws://127.0.0.1:1/ --controller lmpc", "no loopback bus server"),
    ("plant-unknown-scenario", "rhonn-plant", "--bus local:t --scenario nope",
     "unknown scenario 'nope'"),
    ("plant-trace-unwritable", "rhonn-plant",
     "--bus local:t --scenario dlc-paper --trace /proc/x/t.csv", "--trace"),
    # the choices a program takes (python-can's in-process virtual bus is refused by all)
    ("bus-dump-bad-spec", "rhonn-bus", "dump --bus nonsense",
     "bad bus spec 'nonsense': use local:NAME, socketcan:IFACE or remote:ws://127.0.0.1:PORT/ "
     "(rhonn-harness also: auto, remote:new)"),
    # no CAN interface: the hint names the local bus a standalone program can start itself
    ("controller-socketcan-missing", "rhonn-controller",
     "--bus socketcan:vcan9 --controller lmpc",
     "or use this machine's local bus: --bus local:NAME (the first program on a channel "
     "starts its hub"),
    # an empty path would silently mean "no file", as "--out=" would mean the default
    ("controller-empty-timing", "rhonn-controller", "--bus local:t --controller lmpc --timing=",
     "--timing: empty path (give a file)"),
    ("plant-empty-trace", "rhonn-plant", "--bus local:t --scenario dlc-paper --trace=",
     "--trace: empty path (give a file)"),
    ("bench-codec-empty-json", "rhonn-bench", "codec --json=",
     "rhonn-bench codec: error: --json: empty path (give a file)"),
    # python-can's virtual bus never leaves its process: no program here can use it
    ("run-virtual-bus", "rhonn-harness",
     "run dlc-paper --controller lmpc --bus virtual:x --out {tmp}/o",
     "bus virtual:x: python-can's virtual bus stays inside one process, so the other "
     "programs would never see its frames; use local:x (this machine's local bus) or "
     "socketcan:vcan0"),
    ("controller-virtual-bus", "rhonn-controller", "--bus virtual:x --controller lmpc",
     "use local:x"),
    ("plant-virtual-bus", "rhonn-plant", "--bus virtual:x --scenario dlc-paper",
     "use local:x"),
    ("bus-dump-virtual-bus", "rhonn-bus", "dump --bus virtual:x", "use local:x"),
    # a file that is no bus log: a bad argument (exit 2), not a read error (exit 1)
    ("bus-convert-not-a-log", "rhonn-bus", "convert {tmp}/file {tmp}/o.blf",
     "rhonn-bus convert: error: IN {tmp}/file: use a .blf, .asc or .mf4 log"),
    ("bus-decode-not-a-log", "rhonn-bus", "decode {tmp}/file",
     "rhonn-bus decode: error: LOG {tmp}/file: use a .blf, .asc or .mf4 log"),
    ("controller-auto-bus", "rhonn-controller", "--bus auto --controller lmpc",
     "name the bus here (local:NAME, socketcan:IFACE or remote:ws://127.0.0.1:PORT/"),
    ("bench-unknown", "rhonn-bench", "bogus", "unknown benchmark 'bogus'"),
    ("bench-fuzz-unknown-target", "rhonn-bench", "fuzz --only bogus", "unknown target"),
    # --vehicle: checked with everything else, before the bus, the processes or --out
    ("run-vehicle-unknown-key", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle nosuchkey=1 --out {tmp}/o",
     "--vehicle: unknown vehicle override 'nosuchkey'"),
    ("run-vehicle-close-key", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mas_scale=1.1 --out {tmp}/o",
     "did you mean 'mass_scale'?"),
    ("run-vehicle-negative-scale", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mass_scale=-1 --out {tmp}/o",
     "--vehicle: mass_scale must be a factor > 0, got -1"),
    ("run-vehicle-zero-scale", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle yaw_inertia_scale=0 --out {tmp}/o",
     "yaw_inertia_scale must be a factor > 0, got 0"),
    ("run-vehicle-nan", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mass_scale=nan --out {tmp}/o",
     "mass_scale must be a finite number"),
    ("run-vehicle-not-a-number", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mass_scale=heavy --out {tmp}/o",
     "'heavy' is not a number"),
    ("run-vehicle-not-key-value", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mass_scale --out {tmp}/o", "KEY=VALUE"),
    ("run-vehicle-negative-absolute", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle mass_kg=-5 --out {tmp}/o",
     "mass_kg must be > 0, got -5"),
    ("run-vehicle-fixed-period", "rhonn-harness",
     "run dlc-paper --controller lmpc --vehicle comm_period_s=0.02 --out {tmp}/o",
     "fixed by the bus schedule"),
    ("compare-vehicle-negative-scale", "rhonn-harness",
     "compare dlc-paper --controllers lmpc,passive --vehicle mass_scale=-1 --out {tmp}/o",
     "rhonn-harness compare: error: --vehicle: mass_scale must be a factor > 0"),
    ("plant-vehicle-unknown-key", "rhonn-plant",
     "--bus local:t --scenario dlc-paper --vehicle nosuchkey=1",
     "unknown vehicle override 'nosuchkey'"),
    # the scenario: a packaged name or a file, held to one schema
    ("run-scenario-close-name", "rhonn-harness",
     "run dlc-papr --controller lmpc --out {tmp}/o", "did you mean 'dlc-paper'?"),
    ("run-scenario-file-missing", "rhonn-harness",
     "run {tmp}/missing.toml --controller lmpc --out {tmp}/o",
     "rhonn-harness run: error: {tmp}/missing.toml: no such file"),
    ("run-scenario-file-is-a-directory", "rhonn-harness",
     "run {tmp}/folder.toml --controller lmpc --out {tmp}/o", "folder.toml: not a file"),
    ("run-scenario-file-bad-toml", "rhonn-harness",
     "run {tmp}/broken.toml --controller lmpc --out {tmp}/o",
     "{tmp}/broken.toml: not valid TOML"),
    ("run-scenario-file-missing-key", "rhonn-harness",
     "run {tmp}/no_speed.toml --controller lmpc --out {tmp}/o",
     "{tmp}/no_speed.toml: missing key 'speed_kmh'"),
    ("run-scenario-file-missing-table", "rhonn-harness",
     "run {tmp}/no_driver.toml --controller lmpc --out {tmp}/o",
     "no_driver.toml: missing table [driver]"),
    ("run-scenario-file-negative-mu", "rhonn-harness",
     "run {tmp}/negative_mu.toml --controller lmpc --out {tmp}/o",
     "rhonn-harness run: error: {tmp}/negative_mu.toml: road.mu: must be > 0 and <= 1.5, "
     "got -0.2"),
    ("run-scenario-file-unknown-key", "rhonn-harness",
     "run {tmp}/typo.toml --controller lmpc --out {tmp}/o",
     "typo.toml: unknown key 'sped_kmh'; did you mean 'speed_kmh'?"),
    ("run-scenario-file-unknown-table-key", "rhonn-harness",
     "run {tmp}/typo_driver.toml --controller lmpc --out {tmp}/o",
     "typo_driver.toml: unknown key 'driver.brake_pedals'; did you mean 'driver.brake_pedal'?"),
    ("run-scenario-file-wrong-type", "rhonn-harness",
     "run {tmp}/text_speed.toml --controller lmpc --out {tmp}/o",
     "text_speed.toml: speed_kmh: must be a number (km/h), got 'fast'"),
    ("run-scenario-file-wrong-choice", "rhonn-harness",
     "run {tmp}/bad_steer.toml --controller lmpc --out {tmp}/o",
     "bad_steer.toml: driver.steer: must be one of path, sine_dwell, ramp, step, none"),
    ("run-scenario-file-bad-step", "rhonn-harness",
     "run {tmp}/bad_step.toml --controller lmpc --out {tmp}/o",
     "bad_step.toml: road.steps[1]: t_s must not decrease"),
    ("run-scenario-file-param-out-of-range", "rhonn-harness",
     "run {tmp}/good.toml --controller lmpc --param brake_pedal=2 --out {tmp}/o",
     "good.toml: parameter brake_pedal: must be >= 0 and <= 1, got 2"),
    ("run-scenario-file-unknown-param", "rhonn-harness",
     "run {tmp}/good.toml --controller lmpc --param radius=50 --out {tmp}/o",
     "good.toml: no parameter 'radius'; did you mean 'radius_m'?"),
    ("compare-scenario-file-negative-mu", "rhonn-harness",
     "compare {tmp}/negative_mu.toml --controllers lmpc,passive --out {tmp}/o",
     "rhonn-harness compare: error: {tmp}/negative_mu.toml: road.mu: must be > 0"),
    ("plant-scenario-file-negative-mu", "rhonn-plant",
     "--bus local:t --scenario {tmp}/negative_mu.toml",
     "rhonn-plant: error: {tmp}/negative_mu.toml: road.mu: must be > 0 and <= 1.5, got -0.2"),
    ("plant-scenario-file-missing-key", "rhonn-plant",
     "--bus local:t --scenario {tmp}/no_speed.toml", "missing key 'speed_kmh'"),
    # the other options and their combinations
    ("run-config-missing", "rhonn-harness",
     "run dlc-paper --controller lmpc --config {tmp}/nope.toml --out {tmp}/o",
     "--config {tmp}/nope.toml"),
    ("run-secoc-keys-missing-file", "rhonn-harness",
     "run dlc-paper --controller lmpc --secoc-keys {tmp}/no_keys.toml --out {tmp}/o",
     "--secoc-keys: SecOC key file {tmp}/no_keys.toml"),
    ("run-secoc-keys-open-file", "rhonn-harness",
     "run dlc-paper --controller lmpc --secoc-keys {tmp}/open_keys.toml --out {tmp}/o",
     "chmod 600"),
    ("run-secoc-keys-without-secoc", "rhonn-harness",
     "run dlc-paper --controller lmpc --no-secoc --secoc-keys ci-test-key --out {tmp}/o",
     "--secoc-keys is given with --no-secoc"),
    ("campaign-bad-param", "rhonn-harness", "campaign {tmp}/bad_param_campaign.toml --out {tmp}/o",
     "rhonn-harness campaign: error: matrix 'm' (step-steer, passive): scenario step-steer: "
     "parameter amplitude_deg: must be a number"),
    ("campaign-bad-vehicle-scale", "rhonn-harness",
     "campaign {tmp}/bad_vehicle_campaign.toml --out {tmp}/o", "mass_scale must be a factor > 0"),
    ("campaign-scenario-file-negative-mu", "rhonn-harness",
     "campaign {tmp}/file_campaign.toml --out {tmp}/o",
     "negative_mu.toml: road.mu: must be > 0 and <= 1.5, got -0.2"),
    ("run-fault-delay-on-controller-in-lockstep", "rhonn-harness",
     "run dlc-paper --controller lmpc --fault delay:20ms,WHEEL_TORQUE_CMD --out {tmp}/o",
     "needs --mode realtime"),
    # the controller's and the plant's own checks (what the harness does not check first)
    ("controller-secoc-keys-without-secoc", "rhonn-controller",
     "--bus local:t --controller lmpc --no-secoc --secoc-keys ci-test-key",
     "--secoc-keys is given with --no-secoc"),
    ("controller-secoc-keys-open-file", "rhonn-controller",
     "--bus local:t --controller lmpc --secoc-keys {tmp}/open_keys.toml", "chmod 600"),
    ("controller-fault-unknown-signal", "rhonn-controller",
     "--bus local:t --controller lmpc --bench --fault stuck:NOSUCH@1s",
     "stuck:NOSUCH@1s: unknown signal 'NOSUCH'"),
    ("controller-uds-secret-missing", "rhonn-controller",
     "--bus local:t --controller lmpc --uds-secret {tmp}/no_secret",
     "--uds-secret {tmp}/no_secret: No such file"),
    ("controller-uds-secret-short", "rhonn-controller",
     "--bus local:t --controller lmpc --uds-secret {tmp}/short_secret",
     "needs at least 16 bytes"),
    ("plant-secoc-keys-without-secoc", "rhonn-plant",
     "--bus local:t --scenario dlc-paper --no-secoc --secoc-keys ci-test-key",
     "--secoc-keys is given with --no-secoc"),
    ("plant-vehicle-not-key-value", "rhonn-plant",
     "--bus local:t --scenario dlc-paper --vehicle mass_scale", "KEY=VALUE"),
    ("plant-no-scenario", "rhonn-plant", "--bus local:t",
     "the following arguments are required: --scenario"),
    ("plant-serve-with-a-run-option", "rhonn-plant", "--bus local:t --serve --mu 0.5",
     "--serve: give --mu with each run on stdin, not at start"),
    ("plant-serve-bad-bus", "rhonn-plant", "--bus nonsense --serve", "bad bus spec"),
    ("plant-serve-open-key-file", "rhonn-plant",
     "--bus local:t --serve --secoc-keys {tmp}/open_keys.toml", "chmod 600"),
]

# the scenario files of the rows above: a good one and one broken rule each
GOOD_SCENARIO = """\
description = "a good file"
duration_s = 4.0
speed_kmh = 60.0

[course]
type = "circle"
radius_m = 80.0
laps = 0.5

[road]
mu = 0.8

[driver]
steer = "path"
speed = "brake"
"""
SCENARIO_FILES = {
    "good.toml": GOOD_SCENARIO,
    "broken.toml": GOOD_SCENARIO.replace("laps = 0.5", "laps = = 0.5"),
    "no_speed.toml": GOOD_SCENARIO.replace("speed_kmh = 60.0\n", ""),
    "no_driver.toml": GOOD_SCENARIO.split("[driver]")[0],
    "negative_mu.toml": GOOD_SCENARIO.replace("mu = 0.8", "mu = -0.2"),
    "typo.toml": GOOD_SCENARIO.replace("speed_kmh", "sped_kmh"),
    "typo_driver.toml": GOOD_SCENARIO + "brake_pedals = 0.5\n",
    "text_speed.toml": GOOD_SCENARIO.replace("60.0", '"fast"'),
    "bad_steer.toml": GOOD_SCENARIO.replace('"path"', '"wheel"'),
    "bad_step.toml": GOOD_SCENARIO.replace("mu = 0.8",
                                           "mu = 0.8\nsteps = [[3.0, 0.3], [2.0, 0.5]]"),
}


@pytest.fixture
def inputs(tmp_path: Path) -> Path:
    """The bad files the cases name."""
    (tmp_path / "bad.toml").write_text("x = [\n")
    (tmp_path / "unknown_key.toml").write_text("[mpc]\nbogus_key = 1\n")
    (tmp_path / "wrong_type.toml").write_text('[mpc]\nhorizon = "ten"\n')
    (tmp_path / "empty.blf").write_bytes(b"")
    (tmp_path / "garbage.blf").write_bytes(b"this is not a binary logging file" * 10)
    (tmp_path / "file").write_text("a file, not a directory\n")
    for name, text in SCENARIO_FILES.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "folder.toml").mkdir()
    matrix = '[[matrix]]\nname = "m"\ncontrollers = ["passive"]\n'
    (tmp_path / "bad_param_campaign.toml").write_text(
        matrix + 'scenarios = ["step-steer"]\nparams = [{ amplitude_deg = "abc" }]\n')
    (tmp_path / "bad_vehicle_campaign.toml").write_text(
        matrix + 'scenarios = ["step-steer"]\nvehicle = [{ mass_scale = -1.0 }]\n')
    (tmp_path / "file_campaign.toml").write_text(matrix + 'scenarios = ["negative_mu.toml"]\n')
    keys = 'ctrl_to_plant = "{0}"\nplant_to_ctrl = "{0}"\n'.format("00" * 16)
    (tmp_path / "open_keys.toml").write_text(keys)
    (tmp_path / "open_keys.toml").chmod(0o644)
    (tmp_path / "short_secret").write_text("00112233\n")
    (tmp_path / "killed").mkdir()  # a run directory of a harness killed mid-run
    (tmp_path / "killed" / "truth.csv").write_text("t_s,cycle\n0.0,0\n")
    return tmp_path


@pytest.fixture
def no_children(monkeypatch: pytest.MonkeyPatch) -> list[list[str]]:
    """Every process the command would start (none may be): subprocess and fork calls are
    recorded and refused."""
    started: list[list[str]] = []

    class Refused(subprocess.Popen):  # type: ignore[type-arg]
        def __init__(self, args, *a, **kw) -> None:
            started.append([str(x) for x in (args if isinstance(args, list) else [args])])
            raise AssertionError(f"a process was started: {args}")

    def refused_fork() -> int:
        started.append(["fork"])
        raise AssertionError("a process was forked")

    monkeypatch.setattr(subprocess, "Popen", Refused)
    monkeypatch.setattr(os, "fork", refused_fork)
    return started


def _exit_code(main: Callable[[list[str]], int], argv: list[str]) -> int:
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else 1


@pytest.mark.parametrize(("prog", "args", "phrase"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_nothing_written(
        inputs: Path, no_children: list[list[str]], capsys: pytest.CaptureFixture[str],
        prog: str, args: str, phrase: str) -> None:
    before = sorted(str(p) for p in inputs.rglob("*"))
    code = _exit_code(MAINS[prog], args.format(tmp=inputs).split())
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{prog}"), err
    assert phrase.format(tmp=inputs) in lines[0], err
    assert "Traceback" not in err
    assert sorted(str(p) for p in inputs.rglob("*")) == before  # nothing created
    assert no_children == []  # nothing started


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


def test_controller_rerun_without_rerun_sdk_is_one_line(
        inputs: Path, no_children: list[list[str]], capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A core-only install (no rerun-sdk) asked for a recording: one line naming the extra,
    before anything is written."""
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "rerun" else find_spec(name, *a))
    code = _exit_code(controller_process.main, ["--bus", "local:t", "--controller", "lmpc",
                                                "--rerun", str(inputs / "c.rrd")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.strip().splitlines() == [
        "rhonn-controller: error: --rerun needs rerun-sdk: pip install 'rhonn-tv[harness]' "
        "(see rhonn-controller --help)"]
    assert not (inputs / "c.rrd").exists() and no_children == []
