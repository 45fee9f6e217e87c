"""Worst-case stack per public entry point of the C core (include/rhonn_core.h), from gcc's
-fstack-usage / -fcallgraph-info=su, on the host (x86-64, the install build's flags) and on
the Cortex-M4F (the `rhonn-bench mcu` full-core build), beside the high-water mark measured
on the Cortex-M4F under QEMU (stack painted before every step, libm included).

    python -m harness.bench.mcu.stack     # prints the table of docs/core.md

The static bound is the deepest call chain of known frames (static_stack_path); calls into
the C library (libm, memcpy) are outside the compiled objects and listed as not counted.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from controller.native import osqp_gen
from controller.native.build_tools import CFLAGS, NATIVE_DIR, SRC_DIR
from harness.bench.mcu.build import static_stack_path
from harness.bench.mcu.cases import full_core_case
from harness.bench.mcu.run import run_mcu

ENTRY_POINTS: tuple[str, ...] = ("rh_ctrl_init", "rh_ctrl_step", "rh_ctrl_allocate_only",
                                 "rh_ctrl_reset", "rh_ctrl_copy")
# setup.py's groups (the core at -O3; OSQP's generated code with its own flags)
HOST_CORE_FLAGS: tuple[str, ...] = (*(f for f in CFLAGS if not f.startswith("-O")), "-O3")
HOST_OSQP_FLAGS: tuple[str, ...] = ("-std=gnu99", "-O3", "-w", "-ffp-contract=off")
AUX_FLAGS: tuple[str, ...] = ("-fstack-usage", "-fcallgraph-info=su")


def host_stack(out_dir: Path, defines: Sequence[str] = ()) -> dict[str, dict[str, Any]]:
    """{entry: static_stack_path} of the host build (double; ``defines`` e.g. RH_FLOAT32)
    compiled (not linked) into ``out_dir`` with the host ``cc``."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise RuntimeError("no host C compiler (cc)")
    gen = out_dir / "osqp_gen"
    osqp_gen.generate(gen)
    inc_osqp = [str(p) for p in osqp_gen.osqp_include_dirs(gen)]
    dflags = [f"-D{d}" for d in defines]
    cis: list[Path] = []
    groups = (
        (sorted(SRC_DIR.glob("*.c")), [*HOST_CORE_FLAGS, f"-I{SRC_DIR}",
                                       f"-I{NATIVE_DIR / 'include'}",
                                       *(f"-isystem{p}" for p in inc_osqp)], "core"),
        (list(osqp_gen.osqp_sources(gen)), [*HOST_OSQP_FLAGS,
                                            *(f"-I{p}" for p in inc_osqp)], "osqp"))
    for sources, flags, group in groups:
        (out_dir / group).mkdir(parents=True, exist_ok=True)
        for src in sources:
            obj = out_dir / group / (Path(src).stem + ".o")
            subprocess.run([cc, *flags, *dflags, *AUX_FLAGS, "-c", str(src), "-o", str(obj)],
                           check=True, capture_output=True, text=True)
            cis.append(obj.with_suffix(".ci"))
    return {e: static_stack_path(cis, e) for e in ENTRY_POINTS}


def mcu_stack(out_dir: Path, n_steps: int = 300) -> dict[str, Any]:
    """{"entries": {entry: static_stack_path}, "measured_step_bytes": high-water mark of
    rh_ctrl_step's call (incl. the harness's own call frame), "case": name} of the
    `rhonn-bench mcu` full-core case at -Os (default configuration)."""
    case = full_core_case(n_steps=n_steps)
    res = run_mcu(case, opts=("Os",), out_dir=out_dir, timeout_s=120.0, count_insns=False)
    r = res["levels"]["Os"]
    cis = [p for g in ("case", "core", "lib") for p in sorted((out_dir / "Os" / g).glob("*.ci"))]
    entries = {e: static_stack_path(cis, e) for e in ENTRY_POINTS}
    return {"entries": entries, "measured_step_bytes": r["stack_measured_max_bytes"],
            "static_case_step": r["stack_static_path"]}


def main(argv: Sequence[str] | None = None) -> int:
    del argv
    with tempfile.TemporaryDirectory() as tmp:
        host64 = host_stack(Path(tmp) / "host64")
        host32 = host_stack(Path(tmp) / "host32", ("RH_FLOAT32",))
        try:
            mcu: dict[str, Any] | None = mcu_stack(Path(tmp) / "mcu")
        except Exception as exc:  # no cross toolchain: the host columns only
            print(f"MCU build not measured: {exc}", file=sys.stderr)
            mcu = None
    print("| entry point | host double (B) | host float (B) | Cortex-M4F -Os static (B) | "
          "Cortex-M4F measured (B) | deepest chain (Cortex-M4F) |")
    print("|---|---:|---:|---:|---:|---|")
    for e in ENTRY_POINTS:
        m = mcu["entries"][e] if mcu else None
        measured = (str(mcu["measured_step_bytes"]) if mcu and e == "rh_ctrl_step" else "–")
        chain = " → ".join(m["path"]) if m else "–"
        print(f"| `{e}` | {host64[e]['bytes']} | {host32[e]['bytes']} | "
              f"{m['bytes'] if m else '–'} | {measured} | {chain} |")
    nc = sorted({n for d in (host64, host32, *([mcu["entries"]] if mcu else []))
                 for v in d.values() for n in v["not_counted"]})
    dyn = sorted({n for d in (host64, host32, *([mcu["entries"]] if mcu else []))
                  for v in d.values() for n in v["dynamic"]})
    print(f"\nnot counted (outside the compiled objects): {', '.join(nc) or 'none'}")
    print(f"dynamic frames on a worst path: {', '.join(dyn) or 'none'}")
    if mcu:
        sp = mcu["static_case_step"]
        print(f"harness step (mcu_case_step) static: {sp['bytes']} B; "
              f"measured {mcu['measured_step_bytes']} B")
    return 0


if __name__ == "__main__":
    sys.exit(main())
