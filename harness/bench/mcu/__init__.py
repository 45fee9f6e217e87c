"""`rhonn-bench mcu`: the C core on a Cortex-M4F (QEMU MPS2 AN386): flash/RAM/stack, instructions
per step, and outputs against the float32 numpy reference.

Build: the core's sources with the core's flags (``build_tools.CFLAGS`` minus -O, -DRH_FLOAT32)
for ``-mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16`` at -Os and/or -O2, with
-fstack-usage and -fcallgraph-info=su; the harness of controller/native/mcu (vector table,
reset handler, semihosting, test main) and newlib's libm (nano libc, nosys stubs).

A case (:class:`McuCase`) is: an adapter C file implementing ``mcu_case_init`` /
``mcu_case_step`` of ``mcu/mcu_case.h`` (it owns the controller's config and state), the core
sources it needs, a C preamble generated in Python (e.g. the config initialiser), the recorded
inputs (steps, n_in) and the float32 reference outputs (steps, n_out) with an absolute bound.
The harness writes the inputs as float32 bit patterns into a header, runs all steps under
QEMU and reads the outputs back as bit patterns (exact round trip).

Default case: :func:`full_core_case` (nmpc-rhonn's whole step, 300 recorded steps, OSQP
generated for the configured QP shape only, -DRH_N_MAX=N, OSQP in float; ``--osqp double``).

Figures (per optimisation level):
* flash = text+rodata, RAM = data+bss of the core's objects plus the generated OSQP objects
  as linked (link map, after --gc-sections), newlib, libgcc, harness and case adapter on
  their own; the controller state (the adapter's ``static rh_ctrl_t ctrl``, ``nm -S``)
  counted in the core's RAM; object sizes before section GC as well;
* stack: worst function (.su), worst static call path from ``mcu_case_step`` through the core
  (.ci call graph; callees outside the core, e.g. libm, listed as not counted), and the
  measured high-water mark of each step (stack painted before every step, libm included);
* instructions per step (median, p99, max over the sequence): a QEMU TCG plugin
  (mcu/qemu_insn_plugin.c, built with the host cc) counts executed guest instructions between
  marker calls around each step, minus the marker baseline. QEMU's Cortex-M model has no DWT
  cycle counter (the harness probes it and reports it), so these are instructions, not cycles;
* max |error| against the reference, the largest error/bound ratio, bit-exact fraction, and
  the scale-relative error per output (max |err| / max |ref|) against the reference and
  every further output set of the case (e.g. the host float32 C core), integer outputs'
  mismatching steps.

Needs arm-none-eabi-gcc with newlib and qemu-system-arm; installs nothing (prints the
apt-get line and exits 2 when something is missing). Nothing is asserted here; the test is
tests/test_mcu.py.
"""

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
