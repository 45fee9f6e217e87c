"""One command-line convention over the five entry points (docs/cli.md).

Table-driven over rhonn-harness, rhonn-bench, rhonn-plant, rhonn-controller and rhonn-bus:
``--version`` (exit 0, the package version and the backends), ``--help`` naming every command,
``-v``/``-q`` on every entry point (DEBUG shown / INFO suppressed, passed down to the plant
and controller processes a harness run starts), one error style ``PROG [COMMAND]: error:``
with exit code 2, ``--jobs N`` on paper/benchmark/campaign and ``--seeds SPEC`` parsed by one
function. Version and logging rows run the installed console scripts as OS processes, as a
user does; the parser rows run the real ``main`` in-process.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_db import cli as bus_cli
from can_db.process.argcheck import seed_spec, seed_text
from can_db.process.parent import die_with_parent
from can_db.transport.server import BusServer
from controller.runtime import process as controller_process
from harness import cli as harness_cli
from harness.bench import cli as bench_cli
from harness.campaign import cli as campaign_cli
from plant_sim import process as plant_process

BIN = Path(sys.executable).parent
PROGS = ("rhonn-harness", "rhonn-bench", "rhonn-plant", "rhonn-controller", "rhonn-bus")
MAINS: dict[str, Callable[[list[str]], int]] = {
    "rhonn-harness": harness_cli.main, "rhonn-bench": bench_cli.main,
    "rhonn-plant": plant_process.main, "rhonn-controller": controller_process.main,
    "rhonn-bus": bus_cli.main,
}
# every command of the programs that have commands, as --help must list them
COMMANDS = {
    "rhonn-harness": ("run", "compare", "replay", "rrd", "paper", "benchmark", "campaign"),
    "rhonn-bus": ("serve", "dump", "demo", "decode", "convert", "recover"),
    "rhonn-bench": tuple(bench_cli.BENCHMARKS),
    "rhonn-plant": (),
    "rhonn-controller": (),
}
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} (DEBUG|INFO|WARNING|ERROR) ")


def _exit_code(main: Callable[[list[str]], int], argv: list[str]) -> int:
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else 1


def _levels(text: str) -> set[str]:
    """Levels of the log lines in ``text``."""
    return {m.group(1) for line in text.splitlines() if (m := LOG_LINE.match(line))}


# --- --version and --help --------------------------------------------------------------------

@pytest.mark.parametrize("prog", PROGS)
def test_version_names_program_package_and_backends(prog: str) -> None:
    proc = subprocess.run([str(BIN / prog), "--version"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    line = proc.stdout.strip()
    assert line.startswith(f"{prog} rhonn-tv {version('rhonn-tv')} ("), line
    assert re.search(r"controller core: (C|numpy)", line), line
    assert re.search(r"plant kernel: (numba|python)", line), line
    assert proc.stderr == ""


@pytest.mark.parametrize("prog", PROGS)
def test_help_lists_every_command_and_the_common_options(
        prog: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(MAINS[prog], ["--help"]) == 0
    out = capsys.readouterr().out
    for command in COMMANDS[prog]:
        assert re.search(rf"\b{re.escape(command)}\b", out), f"{prog} --help misses {command}"
    for option in ("--version", "-v", "--verbose", "-q", "--quiet"):
        assert option in out, f"{prog} --help misses {option}"


def test_harness_synopsis_names_every_command() -> None:
    """The synopsis at the top of ``rhonn-harness --help`` (the module docstring)."""
    for command in COMMANDS["rhonn-harness"]:
        assert f"rhonn-harness {command}" in (harness_cli.__doc__ or "")


# --- one error style -------------------------------------------------------------------------

# (program, arguments, the prefix of the one error line)
BAD: list[tuple[str, str, str]] = [
    ("rhonn-harness", "paper --out {tmp}/o --jobs 0",
     "rhonn-harness paper: error: argument --jobs"),
    ("rhonn-harness", "benchmark --out {tmp}/o --jobs 0",
     "rhonn-harness benchmark: error: argument --jobs"),
    ("rhonn-harness", "campaign {tmp}/c.toml --jobs 0",
     "rhonn-harness campaign: error: argument --jobs"),
    ("rhonn-harness", "benchmark --out {tmp}/o --seeds x",
     "rhonn-harness benchmark: error: argument --seeds"),
    ("rhonn-harness", "campaign {tmp}/c.toml --seeds x",
     "rhonn-harness campaign: error: argument --seeds"),
    # errors found after parsing name the command too
    ("rhonn-harness", "campaign {tmp}/missing.toml", "rhonn-harness campaign: error: "),
    ("rhonn-harness", "replay {tmp}/missing.blf", "rhonn-harness replay: error: "),
    ("rhonn-harness", "--bogus", "rhonn-harness: error: "),
    ("rhonn-bus", "dump --bus nonsense", "rhonn-bus dump: error: "),
    ("rhonn-bus", "serve --bogus", "rhonn-bus serve: error: "),
    ("rhonn-plant", "--bus local:t --scenario dlc-paper --seed x", "rhonn-plant: error: "),
    ("rhonn-controller", "--bus local:t --controller lmpc --bogus",
     "rhonn-controller: error: "),
    ("rhonn-bench", "bogus", "rhonn-bench: error: "),
    ("rhonn-bench", "secoc --frames 0", "rhonn-bench secoc: error: "),
    ("rhonn-bench", "ranges --bogus", "rhonn-bench ranges: error: "),
]


@pytest.mark.parametrize(("prog", "args", "prefix"), BAD,
                         ids=[f"{p}-{a.split()[0]}-{i}" for i, (p, a, _) in enumerate(BAD)])
def test_bad_input_is_one_error_line_with_the_command_exit_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], prog: str, args: str,
        prefix: str) -> None:
    (tmp_path / "c.toml").write_text('name = "c"\n')
    code = _exit_code(MAINS[prog], args.format(tmp=tmp_path).split())
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert code == 2, captured.err
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(prefix), lines[0]
    assert not (tmp_path / "o").exists()


# --- --jobs and --seeds ----------------------------------------------------------------------

def _parsed(monkeypatch: pytest.MonkeyPatch, argv: list[str]) -> argparse.Namespace:
    """The namespace ``rhonn-harness ARGV`` hands its command (the command does not run)."""
    seen: list[argparse.Namespace] = []

    def capture(args: argparse.Namespace) -> int:
        seen.append(args)
        return 0

    for module, name in ((harness_cli, "cmd_paper"), (harness_cli, "cmd_benchmark"),
                         (campaign_cli, "cmd_campaign")):
        monkeypatch.setattr(module, name, capture)
    assert harness_cli.main(argv) == 0
    return seen[0]


@pytest.mark.parametrize("command", ["paper", "benchmark", "campaign"])
def test_parallelism_is_jobs_everywhere(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                        command: str) -> None:
    head = [command, str(tmp_path / "c.toml")] if command == "campaign" \
        else [command, "--out", str(tmp_path / "o")]
    assert _parsed(monkeypatch, [*head, "--jobs", "3"]).jobs == 3


def test_workers_is_a_deprecated_spelling_of_jobs(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    args = _parsed(monkeypatch, ["campaign", str(tmp_path / "c.toml"), "--workers", "3"])
    assert args.jobs == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["rhonn-harness campaign: warning: --workers is deprecated, use --jobs"]
    assert _exit_code(harness_cli.main, ["campaign", "--help"]) == 0
    assert "--workers" not in capsys.readouterr().out  # hidden from the help


@pytest.mark.parametrize(("text", "seeds"), [
    ("0,3,7", (0, 3, 7)), ("1-5", (1, 2, 3, 4, 5)), ("5", (5,)), ("1-3,9", (1, 2, 3, 9)),
    (" 2 , 4-5", (2, 4, 5)), ("7-7", (7,)), ("9,1", (9, 1)),
])
def test_seed_spec_values(text: str, seeds: tuple[int, ...]) -> None:
    assert seed_spec(text) == seeds


@pytest.mark.parametrize(("text", "phrase"), [
    ("x", "not a seed or range"), ("", "no seeds given"), ("-1", "not a seed or range"),
    ("3-1", "not a seed or range"), ("1,,2", "not a seed or range"), ("1.5", "not a seed"),
    ("1,1", "seed 1 given twice"), ("1-3,2", "seed 2 given twice"),
    ("0-20000", "more than 10000 seeds"),
])
def test_seed_spec_rejects(text: str, phrase: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=phrase):
        seed_spec(text)


@pytest.mark.parametrize(("seeds", "text"), [
    ((1, 2, 3, 4, 5), "1-5"), ((0, 3, 7), "0,3,7"), ((4,), "4"), ((1, 2, 3, 9), "1-3,9"),
    ((9, 1), "9,1"), ((3, 2, 1), "3,2,1"), ((), ""),
])
def test_seed_text_is_how_seeds_are_typed(seeds: tuple[int, ...], text: str) -> None:
    """Reports write their seeds as --seeds takes them, never as a Python list."""
    assert seed_text(seeds) == text
    if seeds:
        assert seed_spec(text) == seeds


@given(st.lists(st.integers(0, 60), unique=True, max_size=30))
def test_seed_text_round_trips_through_seed_spec(seeds: list[int]) -> None:
    text = seed_text(seeds)
    assert "[" not in text and " " not in text
    if seeds:
        assert seed_spec(text) == tuple(seeds)


@pytest.mark.parametrize("spec", ["1-5", "0,3,7", "2"])
def test_seeds_mean_the_same_in_benchmark_and_campaign(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spec: str) -> None:
    bench = _parsed(monkeypatch, ["benchmark", "--out", str(tmp_path / "o"), "--seeds", spec])
    camp = _parsed(monkeypatch, ["campaign", str(tmp_path / "c.toml"), "--seeds", spec])
    assert bench.seeds == camp.seeds == seed_spec(spec)


def test_benchmark_default_seeds_are_one_to_five(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    assert _parsed(monkeypatch, ["benchmark", "--out", str(tmp_path / "o")]).seeds \
        == (1, 2, 3, 4, 5)


# --- -v / -q on every entry point, as OS processes -------------------------------------------

@pytest.fixture(scope="module")
def server() -> BusServer:
    with BusServer() as srv:
        yield srv


def _until_ready(argv: list[str], timeout_s: float = 120.0) -> tuple[str, str]:
    """Start ``argv``, wait for its ``ready`` line on stdout, stop it; (stdout, stderr)."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=die_with_parent)
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.startswith("ready"):
            break
    proc.terminate()
    out, err = proc.communicate(timeout=timeout_s)
    return "".join(lines) + out, err


def _cases(tmp: Path, bus: str) -> dict[str, Callable[[str], tuple[str, str]]]:
    """Per program: a short real invocation with a logging flag → (stdout, stderr)."""
    def run(argv: list[str], code: int = 0) -> tuple[str, str]:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=300)
        assert proc.returncode == code, proc.stderr
        return proc.stdout, proc.stderr

    return {
        "rhonn-harness": lambda flag: run(
            [str(BIN / "rhonn-harness"), "run", "dlc-paper", "--controller", "passive",
             "--duration", "0.2", "--no-plots", "--no-rrd", "--out", str(tmp / f"run{flag}"),
             flag]),
        "rhonn-bench": lambda flag: run(
            [str(BIN / "rhonn-bench"), flag, "codec", "--frames", "200"]),
        "rhonn-plant": lambda flag: run(
            [str(BIN / "rhonn-plant"), "--bus", bus, "--scenario", "dlc-paper",
             "--duration", "0.05", "--wait-ms", "1", "--lost-after", "1", flag],
            code=4),  # no controller: every cycle on the fallback, "degraded"
        "rhonn-controller": lambda flag: _until_ready(
            [str(BIN / "rhonn-controller"), "--bus", bus, "--controller", "passive", flag]),
        # an idle bus: the dump waits for a first frame (its idle time-out starts there)
        "rhonn-bus": lambda flag: _until_ready([str(BIN / "rhonn-bus"), "dump", "--bus", bus,
                                                "--count", "1", "--timeout", "0.1", flag]),
    }


@pytest.mark.parametrize("prog", PROGS)
def test_quiet_hides_info_and_verbose_shows_debug(tmp_path: Path, server: BusServer,
                                                  prog: str) -> None:
    case = _cases(tmp_path, server.spec)[prog]
    out_v, err_v = case("-v")
    out_q, err_q = case("-q")
    assert {"DEBUG", "INFO"} <= _levels(err_v), err_v
    assert not _levels(err_q) & {"DEBUG", "INFO"}, err_q
    # diagnostics go to stderr only: stdout holds results and handshake lines, never log lines
    assert not _levels(out_v) and not _levels(out_q)
    if prog == "rhonn-bus":  # its ready line names what it dumps, as the others do
        assert out_q.splitlines()[0] == f"ready dump on {server.spec}", out_q
    if prog == "rhonn-controller":  # the handshake line stays as the harness reads it
        assert out_q.splitlines()[0].startswith("ready passive on ")
        assert re.search(r"INFO rhonn-controller: starting controller passive ", err_v)
        assert re.search(r"INFO rhonn-controller: controller ready in \d+\.\d s", err_v)
    if prog == "rhonn-harness":
        # what the user waits for is named at once, then how long it took
        assert re.search(r"INFO harness\.run: starting controller passive \(.*\) \.\.\.",
                         err_v), err_v
        assert re.search(r"INFO harness\.run: controller ready in \d+\.\d s", err_v), err_v
        assert re.search(r"INFO harness\.run: plant ready in \d+\.\d s", err_v), err_v
        # the two processes start side by side: both are launched before either is awaited
        assert err_v.index("starting plant") < err_v.index("controller ready in"), err_v
        assert "KPI" in out_q  # the result table stays on stdout
        # the level is passed down to the plant and controller processes (their logs)
        assert "DEBUG" in _levels((tmp_path / "run-v" / "controller.log").read_text())
        for log in ("controller.log", "plant.log"):
            assert not _levels((tmp_path / "run-q" / log).read_text()) & {"DEBUG", "INFO"}


# --- metavars --------------------------------------------------------------------------------

@pytest.mark.parametrize(("prog", "command", "expected"), [
    ("rhonn-harness", ["run", "--help"],
     ("--duration S", "--speed KMH", "--mu MU", "--seed N", "--bus SPEC", "--out DIR",
      "--config FILE")),
    ("rhonn-harness", ["benchmark", "--help"], ("--jobs N", "--seeds SPEC", "--out DIR")),
    ("rhonn-harness", ["campaign", "--help"],
     ("--jobs N", "--seeds SPEC", "--duration S", "--connect-timeout S")),
    ("rhonn-harness", ["paper", "--help"], ("--jobs N", "--out DIR")),
    ("rhonn-plant", ["--help"],
     ("--duration S", "--speed KMH", "--mu MU", "--seed N", "--bus SPEC", "--wait-ms MS",
      "--trace FILE")),
    ("rhonn-controller", ["--help"], ("--bus SPEC", "--period-ms MS", "--timing FILE")),
    ("rhonn-bus", ["dump", "--help"], ("--bus SPEC", "--count N", "--timeout S")),
])
def test_metavars_name_the_unit(prog: str, command: list[str], expected: tuple[str, ...],
                                capsys: pytest.CaptureFixture[str]) -> None:
    assert _exit_code(MAINS[prog], command) == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps long usage lines
    for text in expected:
        assert text in out, f"{prog} {' '.join(command)}: {text!r} missing"


# --- the first-start note --------------------------------------------------------------------

def test_first_start_note_only_when_a_cache_is_missing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from can_db.process import logsetup

    def early(prog: str, *args: str, tty: bool = True) -> str:
        monkeypatch.setattr(logsetup, "_noted_first_start", [])
        monkeypatch.setattr(sys, "argv", [f"/venv/bin/{prog}", *args])
        monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)  # a user at a terminal
        logsetup.early_start(prog)
        return capsys.readouterr().err

    monkeypatch.delenv(logsetup.ENV_LEVEL, raising=False)
    monkeypatch.setattr(sys, "dont_write_bytecode", False)
    monkeypatch.setattr(sys, "pycache_prefix", str(tmp_path / "pyc"))  # no bytecode cache
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))  # no numba cache
    note = early("rhonn-harness", "run", "dlc-paper", "--controller", "lmpc")
    assert LOG_LINE.match(note) and "INFO rhonn-harness: first start after install" in note
    assert "Python bytecode caches and the numba-compiled vehicle step" in note
    assert early("rhonn-harness", "run", tty=False) == ""  # a pipe: errors stay one line
    assert early("rhonn-harness", "-q", "run") == ""  # quiet
    assert early("rhonn-harness", "run", "--help") == ""  # help
    assert early("python", "run") == ""  # another program
    with pytest.raises(SystemExit) as exc:
        early("rhonn-plant", "--version")
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("rhonn-plant rhonn-tv ")
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # nothing to build
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(Path(__file__).parent))  # no kernel index here
    assert early("rhonn-controller", "--bus", "x") == ""  # the controller has no numba step


# --- help texts carry no speed figure measured elsewhere --------------------------------------

#: "≈ 1-2 µs", "~5 ms": a time figure stated as a fact about this machine's speed
SPEED_CLAIM = re.compile(r"[≈~]\s*[\d.,·⁰¹²³⁴⁵⁶⁷⁸⁹–-]+\s*(ns|µs|us|ms)\b")


@pytest.mark.parametrize("bench", tuple(bench_cli.BENCHMARKS))
def test_bench_help_states_no_speed_it_did_not_measure(
        bench: str, capsys: pytest.CaptureFixture[str]) -> None:
    """A benchmark's help may set targets and criteria, but a time it claims for this machine
    is either measured by the command or named by the command that measures it."""
    assert _exit_code(bench_cli.main, [bench, "--help"]) == 0
    out = capsys.readouterr().out
    assert not SPEED_CLAIM.search(out), SPEED_CLAIM.search(out)


def test_e2e_measures_its_own_time_per_payload(capsys: pytest.CaptureFixture[str]) -> None:
    """`rhonn-bench e2e`: the time per payload is a column of its own table, and its help
    points to the benchmark of the monitor's time per frame."""
    assert _exit_code(bench_cli.main, ["e2e", "--help"]) == 0
    assert "rhonn-bench codec --messages SYNC" in " ".join(capsys.readouterr().out.split())
    assert _exit_code(bench_cli.main, ["e2e", "--payloads", "300", "--messages", "SYNC",
                                       "--streams", "random"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split()[-1] == "µs/payload"
    assert float(lines[2].split()[-1]) > 0.0
