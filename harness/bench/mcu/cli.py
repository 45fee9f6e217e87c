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

The report has one block per optimisation level.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from can_db.process.argcheck import OneLineParser, number
from harness.bench.mcu.case import McuError
from harness.bench.mcu.run import run_mcu
from harness.bench.mcu.toolchain import missing_tools

FLASH_TARGET_BYTES = 64 * 1024   # core text+rodata ≤ 64 kB
RAM_TARGET_BYTES = 16 * 1024     # core data+bss ≤ 16 kB, controller state included


def _met(v: int, target: int) -> str:
    return f"target {target // 1024} kB {'met' if v <= target else 'NOT met'}"


def _fmt(r: dict[str, Any], names: Sequence[str] = ()) -> list[str]:
    sp = r["stack_static_path"]
    lk = r["linked"]

    def fl(g: str) -> int:
        return lk.get(g, {}).get("text", 0) + lk.get(g, {}).get("rodata", 0)

    def ram(g: str) -> int:
        return lk.get(g, {}).get("data", 0) + lk.get(g, {}).get("bss", 0)

    state = ", ".join(f"{k} {v} B" for k, v in r["state_symbols"].items()) or "none"
    lines = [
        f"  flash (text+rodata, linked): core+OSQP {r['flash_core_total_bytes']} B (core "
        f"{fl('core')}, OSQP {fl('lib')}; {_met(r['flash_core_total_bytes'], FLASH_TARGET_BYTES)}"
        f"); newlib {fl('newlib')} B, libgcc {fl('libgcc')} B, harness {fl('harness')} B, "
        f"case adapter {fl('case')} B (config)",
        f"  RAM (data+bss): core+OSQP statics {r['ram_core_static_bytes']} B + controller "
        f"state {r['state_bytes']} B ({state}) = {r['ram_core_total_bytes']} B "
        f"({_met(r['ram_core_total_bytes'], RAM_TARGET_BYTES)}); newlib {ram('newlib')} B, "
        f"harness {ram('harness')} B",
        f"  objects before section GC: core {r['flash_core_bytes']} B flash, "
        f"{r['ram_core_bytes']} B RAM"
        + (f"; OSQP {r['flash_lib_bytes']} B flash, {r['ram_lib_bytes']} B RAM"
           if "flash_lib_bytes" in r else ""),
        f"  stack: measured max {r['stack_measured_max_bytes']} B (painted, libm included); "
        f"static path {sp['bytes']} B ({' > '.join(sp['path'])}"
        + (f"; not counted: {', '.join(sp['not_counted'])}" if sp["not_counted"] else "")
        + f"); worst function {r.get('stack_worst_function', {}).get('name', '-')} "
        f"{r.get('stack_worst_function', {}).get('bytes', 0)} B",
    ]
    if "insns_per_step_median" in r:
        lines.append(f"  instructions per step: median {r['insns_per_step_median']:.0f}, p99 "
                     f"{r['insns_per_step_p99']:.0f}, max {r['insns_per_step_max']} "
                     f"({r['insn_method']}; {r['dwt']})")
    else:
        lines.append(f"  instructions per step: {r['insn_method']}")
    verdict = ("no bound" if r["ok"] is None else
               f"max err/bound {r['max_err_over_bound']:.3g}, "
               + ("OK" if r["ok"] else "OUT OF BOUND"))
    lines.append(f"  vs the float32 reference: max |error| {r['max_abs_err']:.3g}, bit-exact "
                 f"{100 * r['bitexact_fraction']:.1f} %; {verdict}")
    for label, cmp_ in (("float32 reference", r["vs_expected"]),
                        *((k, v) for k, v in r["vs_others"].items())):
        per = [f"{n} {e:.2g}" for n, e in zip(names, cmp_["rel_err_per_output"], strict=False)
               if e is not None]
        lines.append(f"  max scale-relative error vs {label}: {cmp_['max_rel_err']:.3g} ("
                     + ", ".join(per) + ")")
        if cmp_["int_mismatch_steps"]:
            lines.append("    steps differing: " + ", ".join(
                f"{names[j] if j < len(names) else j} {n}"
                for j, n in cmp_["int_mismatch_steps"].items()))
    callers = r.get("soft_double_callers", {})
    if callers:
        step = sorted(f for f in callers if not f.endswith(("_init", "_set_covariance")))
        lines.append(f"  soft double-precision calls in the core: {len(callers)} functions, "
                     f"{len(callers) - len(step)} of them init/set-state; the others: "
                     + ", ".join(step) + " (--json: helpers per function)")
    if r.get("lib_soft_double_callers"):
        lines.append(f"  soft double-precision calls in OSQP: "
                     f"{len(r['lib_soft_double_callers'])} functions (--json: the list)")
    return lines


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench mcu", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--opt", default="Os,O2",
                        help="optimisation levels, comma separated (Os, O2, O3, O1)")
    parser.add_argument("--case", default="harness.bench.mcu:full_core_case",
                        help="MODULE:FUNCTION returning an McuCase; called with n_steps "
                             "(default: the full nmpc-rhonn step; harness.bench.mcu:demo_case "
                             "is the rhonn.c kernel demo)")
    parser.add_argument("--steps", type=number(int, lo=1, hi=100_000), default=300,
                        help="recorded steps of the case")
    parser.add_argument("--osqp", default="float",
                        help="OSQP precision(s) of the full-step case: float, double or "
                             "float,double")
    parser.add_argument("--out", default=None, help="keep the build in this directory")
    parser.add_argument("--timeout", type=number(float, lo=1, unit="s"), default=120.0,
                        help="QEMU time limit per run, s")
    parser.add_argument("--no-insns", action="store_true", help="skip instruction counting")
    parser.add_argument("--json", default=None, help="write results to this file")
    args = parser.parse_args(argv)
    opts = [o.strip().lstrip("-") for o in args.opt.split(",") if o.strip()]
    bad = [o for o in opts if o not in {"Os", "O1", "O2", "O3", "Oz"}]
    if bad or not opts:
        parser.error(f"--opt: unknown level(s) {', '.join(bad) or '(none)'}")
    precisions = [v.strip() for v in args.osqp.split(",") if v.strip()]
    if not precisions or any(v not in ("float", "double") for v in precisions):
        parser.error(f"--osqp: {args.osqp!r}: choose float, double or float,double")
    why = missing_tools()
    if why is not None:
        print(f"rhonn-bench mcu: {why}", file=sys.stderr)
        return 2
    module, _, func = args.case.partition(":")
    try:
        factory = getattr(importlib.import_module(module), func or "case")
    except (ImportError, AttributeError) as exc:
        print(f"rhonn-bench mcu: error: --case {args.case}: {exc}", file=sys.stderr)
        return 2
    takes_osqp = "osqp" in inspect.signature(factory).parameters
    variants: list[dict[str, Any]] = [{"osqp": v} for v in precisions] if takes_osqp else [{}]
    results = []
    for kw in variants:
        try:
            case = factory(args.steps, **kw)
        except Exception as exc:  # the case's reference side (another module) failed
            print(f"rhonn-bench mcu: error: --case {args.case}: {type(exc).__name__}: {exc}",
                  file=sys.stderr)
            return 1
        out = None if args.out is None else str(Path(args.out) / (kw.get("osqp") or "case"))
        try:
            res = run_mcu(case, opts, out, args.timeout, not args.no_insns)
        except McuError as exc:
            print(f"rhonn-bench mcu: error: {exc}", file=sys.stderr)
            return 1
        results.append(res)
        print(f"mcu: {res['case']} on {res['target']}, {res['steps']} steps, "
              f"{res['inputs']} in / {res['outputs']} out")
        for opt, r in res["levels"].items():
            print(f"-{opt}:")
            for line in _fmt(r, res["output_names"]):
                print(line)
        first = next(iter(res["levels"].values()))
        print(f"  bound: {first['bound']}")
        for k, v in res["others_vs_expected"].items():
            print(f"  {k} vs float32 reference (host, no MCU): max scale-relative error "
                  f"{v['max_rel_err']:.3g}"
                  + (f"; steps differing: {v['int_mismatch_steps']}"
                     if any(v["int_mismatch_steps"].values()) else ""))
        for k, v in res["notes"].items():
            if k.startswith("host"):
                print(f"  {k}: {v}")
    if args.json:
        payload: Any = results[0] if len(results) == 1 else {"variants": results}
        Path(args.json).write_text(json.dumps(payload, indent=2) + "\n")
    return 0 if all(r["ok"] is not False for res in results
                    for r in res["levels"].values()) else 1
