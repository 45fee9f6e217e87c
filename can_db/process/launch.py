"""The console scripts' entry points: answer ``--version`` and announce a first start's
cache builds before a program's heavy imports (numpy, scipy, python-can: seconds on a cold
start), then run the program's ``main``.

Ctrl-C before a program has its own stop handling (during the imports: seconds on a loaded
machine) ends it with one line, ``PROG: interrupted``, exit code 130, not a traceback. SIGINT
raises KeyboardInterrupt from the first line on even when the program was started in the
background by a script, which hands it SIGINT as *ignored* (Python would leave it ignored and
``kill -INT PID`` would do nothing); the programs then install their own handlers.

The programs are named by module path, so this lowest layer imports none of them until one
is asked for.
"""

from __future__ import annotations

import importlib
import signal
import sys

from can_db.process.logsetup import early_start

PROGRAMS = {
    "rhonn-bus": "can_db.cli",
    "rhonn-plant": "plant_sim.process",
    "rhonn-controller": "controller.runtime.process",
    "rhonn-harness": "harness.cli",
    "rhonn-bench": "harness.bench.cli",
}

# Installed packages a program never uses that its libraries import when present: python-can
# imports asammdf (and pandas) for MF4 logs, numba imports scipy to look for BLAS (the plant's
# kernel calls none; neither process writes MF4). Refused before the program's imports: ~0.5 s
# of a plant or controller start.
UNUSED = {"rhonn-plant": ("asammdf", "scipy"), "rhonn-controller": ("asammdf",)}


def refuse_unused(prog: str) -> None:
    """Make importing the packages ``prog`` never uses (:data:`UNUSED`) fail as if they were
    not installed (a None entry in ``sys.modules``); the libraries treat them as optional.
    Call it before the program's imports."""
    for name in UNUSED.get(prog, ()):
        if name not in sys.modules:
            sys.modules[name] = None  # type: ignore[assignment]


# The optional packages (top-level module) and the pip extra each comes with (pyproject.toml):
# a core-only install lacks them, and a program that needs one says which extra to install.
EXTRA_OF = {"numba": "plant", **{m: "harness" for m in (
    "rerun", "matplotlib", "asammdf", "tqdm", "distributed", "dask", "pyarrow", "pandas",
    "crcmod", "udsoncan", "isotp")}}


def run_program(prog: str) -> int:
    """Run the console program ``prog`` (a key of :data:`PROGRAMS`); its exit code. A missing
    optional package (:data:`EXTRA_OF`) is one line naming the extra, exit code 2; a stop
    signal the program leaves unhandled (Ctrl-C during its imports) one line, exit code 128 +
    the signal number (130 for SIGINT)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)  # even if inherited as ignored
    try:
        early_start(prog)
        refuse_unused(prog)
        return int(importlib.import_module(PROGRAMS[prog]).main() or 0)
    except KeyboardInterrupt as exc:
        print(f"{prog}: interrupted", file=sys.stderr, flush=True)
        return 128 + int(getattr(exc, "signum", signal.SIGINT))
    except ModuleNotFoundError as exc:
        top = (exc.name or "").partition(".")[0]
        if top not in EXTRA_OF or top in UNUSED.get(prog, ()):
            raise
        extra = EXTRA_OF[top]
        print(f"{prog}: error: {top} not installed: this needs the '{extra}' extra "
              f"(pip install 'rhonn-tv[{extra}]')", file=sys.stderr, flush=True)
        return 2


def rhonn_bus() -> int:
    return run_program("rhonn-bus")


def rhonn_plant() -> int:
    return run_program("rhonn-plant")


def rhonn_controller() -> int:
    return run_program("rhonn-controller")


def rhonn_harness() -> int:
    return run_program("rhonn-harness")


def rhonn_bench() -> int:
    return run_program("rhonn-bench")
