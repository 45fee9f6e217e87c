"""`rhonn-bench mcu`: the C core on a Cortex-M4F under QEMU (the command and its report:
cli.py; cases: cases.py; build, run and comparison: build.py, run.py)."""


from harness.bench.mcu.cases import (
    FULL_CORE_BOUND,
    HOST_C_BOUND,
    ITER_MISMATCH_FRACTION,
    demo_case,
    full_core_case,
)
from harness.bench.mcu.cli import FLASH_TARGET_BYTES, RAM_TARGET_BYTES, main
from harness.bench.mcu.run import run_mcu
from harness.bench.mcu.toolchain import APT_LINE, missing_tools

__all__ = [
    "APT_LINE",
    "FLASH_TARGET_BYTES",
    "FULL_CORE_BOUND",
    "HOST_C_BOUND",
    "ITER_MISMATCH_FRACTION",
    "RAM_TARGET_BYTES",
    "demo_case",
    "full_core_case",
    "main",
    "missing_tools",
    "run_mcu",
]
