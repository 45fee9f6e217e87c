"""Running a build under QEMU and reading it back (outputs, stack, instructions per step),
the errors against the references, and :func:`run_mcu`, which measures a case end to end."""

from __future__ import annotations

import statistics
import subprocess
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from harness.bench.mcu.build import (
    _defined,
    _object_symbols,
    _size,
    _soft_double,
    _soft_double_callers,
    _stack_functions,
    _symbol,
    _undefined,
    build,
    build_plugin,
    linked_sizes,
    static_stack_path,
)
from harness.bench.mcu.case import McuCase, McuError
from harness.bench.mcu.cases import full_core_case
from harness.bench.mcu.toolchain import QEMU, missing_tools, tool_versions

QEMU_ARGS: tuple[str, ...] = ("-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic",
                              "-monitor", "none", "-serial", "none")


def run_qemu(elf: Path, out: Path, timeout_s: float = 60.0,
             count_insns: bool = True) -> tuple[str, list[int] | None, str]:
    """Run the ELF under QEMU; (semihosting stdout, marker counts or None, method note)."""
    mark = _symbol(elf, "mcu_mark")
    guest = out / "guest.txt"  # semihosting console → file (QEMU's own messages: stderr)
    base = [QEMU, *QEMU_ARGS, "-chardev", f"file,id=shout,path={guest}",
            "-semihosting-config", "enable=on,target=native,chardev=shout", "-kernel", str(elf)]
    plugin_note = "not measured"
    if count_insns:
        for api in (1, 2, 3, 4, 5):
            try:
                so = build_plugin(out, api)
            except McuError as exc:
                plugin_note = f"plugin build failed: {exc}"
                break
            if so is None:
                plugin_note = "not measured (no host C compiler for the QEMU plugin)"
                break
            log = out / "plugin.log"
            log.unlink(missing_ok=True)
            cmd = [*base, "-plugin", f"{so},mark={mark:#x}", "-d", "plugin", "-D", str(log)]
            res = _qemu(cmd, timeout_s, guest)
            if res.returncode != 0 and "plugin" in res.stderr.lower() \
                    and "version" in res.stderr.lower():
                plugin_note = f"plugin not loaded: {res.stderr.strip().splitlines()[-1]}"
                continue
            _check(res, cmd)
            marks = [int(ln.split()[1]) for ln in log.read_text().splitlines()
                     if ln.startswith("M ")]
            return guest.read_text(), marks, f"TCG plugin (API v{api}), executed guest instructions"
    res = _qemu(base, timeout_s, guest)
    _check(res, base)
    return guest.read_text(), None, plugin_note


def _qemu(cmd: Sequence[str], timeout_s: float,
          guest: Path) -> subprocess.CompletedProcess[str]:
    guest.unlink(missing_ok=True)
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as exc:
        raise McuError(f"QEMU timed out after {timeout_s:g} s: {' '.join(cmd)}") from exc
    res.stdout = guest.read_text() if guest.exists() else ""
    return res


def _check(res: subprocess.CompletedProcess[str], cmd: Sequence[str]) -> None:
    if res.returncode != 0 or "MCU end" not in res.stdout:
        raise McuError(f"QEMU run failed (exit {res.returncode}): {' '.join(cmd)}\n"
                       f"guest: {res.stdout[-2000:]}\nqemu: {res.stderr[-2000:]}")


def parse_output(text: str, n_steps: int, n_out: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """(outputs float32 (steps, n_out), stack bytes per step, info) from the guest output."""
    outs = np.full((n_steps, n_out), np.nan, dtype=np.float32)
    stack = np.zeros(n_steps, dtype=np.int64)
    info: dict[str, Any] = {}
    seen = 0
    for line in text.splitlines():
        p = line.split()
        if not p:
            continue
        if p[0] == "O":
            k = int(p[1])
            stack[k] = int(p[2])
            bits = np.array([int(h, 16) for h in p[3:]], dtype=np.uint32)
            if bits.size != n_out:
                raise McuError(f"step {k}: {bits.size} outputs, expected {n_out}")
            outs[k] = bits.view(np.float32)
            seen += 1
        elif p[0] == "DWT":
            info["dwt_ctrl"] = p[1]
            info["dwt_cycles_100_loop"] = int(p[2])
        elif p[:2] == ["MCU", "begin"]:
            info["n_baseline"] = int(p[5])
    if seen != n_steps:
        raise McuError(f"{seen} of {n_steps} steps reported")
    return outs, stack, info


def step_instructions(marks: list[int], n_baseline: int, n_steps: int) -> np.ndarray:
    """Instructions per step: the marker pair difference minus the empty-pair baseline."""
    if len(marks) != 2 * (n_baseline + n_steps):
        raise McuError(f"{len(marks)} marker counts, expected {2 * (n_baseline + n_steps)}")
    m = np.asarray(marks, dtype=np.int64)
    base = m[1:2 * n_baseline:2] - m[0:2 * n_baseline:2]
    if np.ptp(base) != 0:
        raise McuError(f"marker baseline not constant: {base.tolist()}")
    steps = m[2 * n_baseline + 1::2] - m[2 * n_baseline::2]
    return steps - base[0]


def compare(outs: np.ndarray, case: McuCase) -> dict[str, Any]:
    exp = np.asarray(case.expected, dtype=np.float32)
    tol = np.broadcast_to(np.asarray(case.tolerance, dtype=np.float64), exp.shape)
    both_nan = np.isnan(outs) & np.isnan(exp)
    err = np.where(both_nan, 0.0, np.abs(outs.astype(np.float64) - exp.astype(np.float64)))
    err = np.where(np.isnan(err), np.inf, err)
    bounded = np.isfinite(tol)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(~bounded, 0.0, np.where(tol > 0, err / np.where(tol > 0, tol, 1.0),
                                                 np.where(err > 0, np.inf, 0.0)))
    k, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    return {"max_abs_err": float(err.max()), "max_abs_err_per_output": err.max(axis=0).tolist(),
            "max_err_over_bound": float(ratio.max()) if bounded.any() else None,
            "worst_at": {"step": int(k), "output": int(j)},
            "bitexact_fraction": float(np.mean(outs.view(np.uint32) == exp.view(np.uint32))),
            "ok": bool(np.all(err <= tol)) if bounded.any() else None,
            "bound": case.bound_text or "none"}


def scale_relative(outs: np.ndarray, ref: np.ndarray,
                   int_outputs: Sequence[int] = ()) -> dict[str, Any]:
    """Per output: max_k |outs − ref| / max_k |ref| (real outputs; NaN = NaN is equal, a NaN
    against a number is an infinite error), and for ``int_outputs`` the number of steps
    whose value differs."""
    outs = np.asarray(outs, np.float64)
    ref = np.asarray(ref, np.float64)
    rel: list[float | None] = []
    mism: dict[int, int] = {}
    for j in range(ref.shape[1]):
        a, b = outs[:, j], ref[:, j]
        if j in int_outputs:
            mism[j] = int(np.sum(~((a == b) | (np.isnan(a) & np.isnan(b)))))
            rel.append(None)
            continue
        both = np.isnan(a) & np.isnan(b)
        err = np.where(both, 0.0, np.abs(a - b))
        err = np.where(np.isnan(err), np.inf, err)
        fin = np.isfinite(b)
        scale = max(float(np.max(np.abs(b[fin]))) if fin.any() else 0.0, 1e-12)
        rel.append(float(err.max()) / scale)
    real = [v for v in rel if v is not None]
    return {"rel_err_per_output": rel, "max_rel_err": max(real) if real else 0.0,
            "int_mismatch_steps": mism}


def run_mcu(case: McuCase | None = None, opts: Sequence[str] = ("Os", "O2"),
            out_dir: str | Path | None = None, timeout_s: float = 60.0,
            count_insns: bool = True) -> dict[str, Any]:
    """Build, run under QEMU and measure ``case`` (default: :func:`full_core_case`) at each
    optimisation level. Raises McuError (toolchain missing, build or run failure)."""
    why = missing_tools()
    if why is not None:
        raise McuError(why)
    case = full_core_case() if case is None else case
    tmp = None
    if out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="rhonn-mcu-")
        out_dir = tmp.name
    out_root = Path(out_dir)
    n_steps, n_out = np.asarray(case.expected).shape
    result: dict[str, Any] = {"case": case.name, "steps": int(n_steps), "notes": case.notes,
                              "others_vs_expected": {
                                  k: scale_relative(v, case.expected, case.int_outputs)
                                  for k, v in case.others.items()},
                              "inputs": int(np.asarray(case.inputs).shape[1]),
                              "outputs": int(n_out), "output_names": list(case.output_names),
                              "target": "QEMU mps2-an386 Cortex-M4F",
                              "tools": tool_versions(), "levels": {}}
    try:
        for opt in opts:
            t0 = time.perf_counter()
            out = out_root / opt
            b = build(case, out, opt)
            text, marks, method = run_qemu(b.elf, out, timeout_s, count_insns)
            outs, stack, info = parse_output(text, n_steps, n_out)
            r: dict[str, Any] = {}
            r["flash_core_bytes"], r["ram_core_bytes"] = _size(b.core_objs)
            r["flash_case_bytes"], r["ram_case_bytes"] = _size(b.case_objs)
            if b.lib_objs:
                r["flash_lib_bytes"], r["ram_lib_bytes"] = _size(b.lib_objs)
            r["state_symbols"] = _object_symbols(b.case_objs)
            r["linked"] = linked_sizes(out / "app.map", {
                "core": out / "core", "lib": out / "lib", "case": out / "case",
                "harness": out / "harness"})
            lk = r["linked"]
            core_lk = [lk.get(g, {}) for g in ("core", "lib")]
            r["flash_core_total_bytes"] = sum(g.get("text", 0) + g.get("rodata", 0)
                                              for g in core_lk)
            r["ram_core_static_bytes"] = sum(g.get("data", 0) + g.get("bss", 0) for g in core_lk)
            r["state_bytes"] = sum(r["state_symbols"].values())
            r["ram_core_total_bytes"] = r["ram_core_static_bytes"] + r["state_bytes"]
            su = _stack_functions([o.with_suffix(".su") for o in (*b.core_objs, *b.lib_objs)])
            if su:
                name = max(su, key=lambda n: su[n][0])
                r["stack_worst_function"] = {"name": name, "bytes": su[name][0],
                                             "kind": su[name][1]}
            r["stack_static_path"] = static_stack_path(
                [o.with_suffix(".ci") for o in (*b.case_objs, *b.core_objs, *b.lib_objs)],
                "mcu_case_step")
            r["stack_measured_max_bytes"] = int(stack.max())
            undef = _undefined(b.core_objs)
            r["soft_double_helpers"] = _soft_double(undef)
            r["soft_double_callers"] = _soft_double_callers(b.core_objs)
            if b.lib_objs:
                r["lib_soft_double_callers"] = _soft_double_callers(b.lib_objs)
            r["external_calls"] = sorted(undef - _defined([*b.core_objs, *b.lib_objs]))
            if b.lib_objs:
                r["lib_soft_double_helpers"] = _soft_double(_undefined(b.lib_objs))
            r["dwt"] = ("cycle counter modelled" if info.get("dwt_cycles_100_loop", 0) > 0
                        else "no DWT cycle counter in the QEMU model")
            r["insn_method"] = method
            if marks is not None:
                ins = step_instructions(marks, info.get("n_baseline", 4), n_steps)
                r["insns_per_step_median"] = float(statistics.median(ins.tolist()))
                r["insns_per_step_max"] = int(ins.max())
                r["insns_per_step_p99"] = float(np.percentile(ins, 99))
                r["insns_per_step_min"] = int(ins.min())
            r.update(compare(outs, case))
            r["vs_expected"] = scale_relative(outs, case.expected, case.int_outputs)
            r["vs_others"] = {k: scale_relative(outs, v, case.int_outputs)
                              for k, v in case.others.items()}
            r["elapsed_s"] = round(time.perf_counter() - t0, 2)
            result["levels"][opt] = r
    finally:
        if tmp is not None:
            tmp.cleanup()
    return result
