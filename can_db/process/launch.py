"""The console scripts' entry points: answer ``--version`` and announce a first start's
cache builds before a program's heavy imports (numpy, scipy, python-can: seconds on a cold
start), then run the program's ``main``.

The programs are named by module path, so this lowest layer imports none of them until one
is asked for.
"""

from __future__ import annotations

import importlib

from can_db.process.logsetup import early_start

PROGRAMS = {
    "rhonn-bus": "can_db.cli",
    "rhonn-plant": "plant_sim.process",
    "rhonn-controller": "controller.runtime.process",
    "rhonn-harness": "harness.cli",
    "rhonn-bench": "harness.bench.cli",
}


def run_program(prog: str) -> int:
    """Run the console program ``prog`` (a key of :data:`PROGRAMS`); its exit code."""
    early_start(prog)
    return int(importlib.import_module(PROGRAMS[prog]).main() or 0)


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
