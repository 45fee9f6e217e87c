"""A core-only install (no ``plant`` or ``harness`` extra): every program either works or
says in one line which extra it needs, exit code 2 — never a traceback.

Each program runs as its own process through its console entry point
(can_db/process/launch.py) with every optional package made unimportable, as in a core-only
install (a None entry in ``sys.modules``: ``import`` fails, ``find_spec`` finds nothing).
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from can_db.process.launch import EXTRA_OF

CORE_ONLY = (
    "import sys\n"
    "from can_db.process import launch\n"
    "for name in launch.EXTRA_OF:\n"
    "    sys.modules[name] = None\n"
    "prog = sys.argv[1]\n"
    "sys.argv = [prog, *sys.argv[2:]]\n"
    "raise SystemExit(launch.run_program(prog))\n")


def _core_only(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", CORE_ONLY, *argv], capture_output=True,
                          text=True, timeout=180)


@pytest.mark.parametrize("argv", [
    ("rhonn-harness", "run", "dlc-paper", "--controller", "passive"),
    ("rhonn-harness", "campaign", "x.toml"),
    ("rhonn-bench", "codec"),
    ("rhonn-bench", "e2e"),
])
def test_a_program_needing_the_harness_extra_says_so_in_one_line(argv: tuple[str, ...]
                                                                 ) -> None:
    done = _core_only(*argv)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"{argv[0]}: error: ")
    assert "needs the 'harness' extra (pip install 'rhonn-tv[harness]')" in lines[0]


@pytest.mark.parametrize("prog", ["rhonn-controller", "rhonn-plant", "rhonn-bus"])
def test_the_deployable_programs_start_without_the_extras(prog: str) -> None:
    done = _core_only(prog, "--version")
    assert done.returncode == 0 and "rhonn-tv" in done.stdout, done.stderr


def test_the_extras_map_names_only_optional_packages() -> None:
    """Every module the guard turns into an extra's line is outside the core dependencies."""
    core = {"can", "cantools", "numpy", "scipy", "osqp", "psutil", "cryptography"}
    assert not core & set(EXTRA_OF)
