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

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import importlib
import json
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controller.native.build_tools import CFLAGS, NATIVE_DIR, SRC_DIR

MCU_DIR = NATIVE_DIR / "mcu"
APT_LINE = "apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
GCC, SIZE, NM, OBJDUMP, QEMU = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm",
                                "arm-none-eabi-objdump", "qemu-system-arm")
ARCH_FLAGS: tuple[str, ...] = ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard",
                               "-mfpu=fpv4-sp-d16")
CORE_FLAGS: tuple[str, ...] = (*(f for f in CFLAGS if not f.startswith("-O")), "-DRH_FLOAT32",
                               "-ffunction-sections", "-fdata-sections")
HARNESS_FLAGS: tuple[str, ...] = ("-std=gnu99", "-Wall", "-Wextra", "-Werror", "-O2",
                                  "-ffunction-sections", "-fdata-sections")
# third-party code as setup.py builds OSQP's (OSQP_FLAGS), plus -DRH_FLOAT32 and sections
LIB_FLAGS: tuple[str, ...] = ("-std=gnu99", "-w", "-ffp-contract=off", "-DRH_FLOAT32",
                              "-ffunction-sections", "-fdata-sections")
HARNESS_SOURCES: tuple[str, ...] = ("startup.c", "semihost.c", "main.c")
QEMU_ARGS: tuple[str, ...] = ("-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic",
                              "-monitor", "none", "-serial", "none")
EPS32 = float(np.finfo(np.float32).eps)


class McuError(RuntimeError):
    """A build or run step failed (the message has the command and its output)."""


@dataclasses.dataclass
class McuCase:
    """One controller case for the MCU. ``adapter``: C file defining mcu_case_init/step
    (built with the core's flags, may include core headers and "mcu_case_config.h");
    ``sources``: core sources (names relative to controller/native/src or paths);
    ``config_c``: C text placed in mcu_case_config.h; ``inputs`` (steps, n_in) and
    ``expected`` (steps, n_out) float32; ``tolerance``: absolute bound per output,
    broadcastable to ``expected``; ``bound_text`` states it for the report. ``lib_sources``
    (third-party, e.g. OSQP's embedded code) are built with LIB_FLAGS (no -Werror/-pedantic)
    and reported on their own line."""

    name: str
    adapter: Path
    sources: Sequence[str | Path]
    config_c: str
    inputs: np.ndarray
    expected: np.ndarray
    tolerance: np.ndarray
    bound_text: str = ""
    output_names: Sequence[str] = ()
    lib_sources: Sequence[str | Path] = ()   # third-party C (e.g. OSQP), own size line
    include_dirs: Sequence[str | Path] = ()  # extra -isystem for core, libraries and adapter
    defines: Sequence[str] = ()              # extra -D for core, libraries and adapter
    lib_flags: Sequence[str] = ()            # extra flags for lib_sources only
    # further outputs (steps, n_out) to compare with, e.g. {"host C float32": ...}: the
    # scale-relative error per output and the integer outputs' mismatch count are reported
    others: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    int_outputs: Sequence[int] = ()          # output columns that are counts / flags
    notes: dict[str, Any] = dataclasses.field(default_factory=dict)  # carried to the result


# ---------------------------------------------------------------- toolchain

def missing_tools() -> str | None:
    """None when the cross toolchain, newlib and QEMU are there, else one line naming what
    is missing and how to get it."""
    missing = [t for t in (GCC, SIZE, NM, OBJDUMP, QEMU) if shutil.which(t) is None]
    if shutil.which(GCC) is not None:
        for f in ("libm.a", "nosys.specs", "nano.specs"):
            res = subprocess.run([GCC, *ARCH_FLAGS, f"-print-file-name={f}"],
                                 capture_output=True, text=True)
            if not Path(res.stdout.strip()).is_absolute() or not Path(res.stdout.strip()).exists():
                missing.append("newlib for arm-none-eabi (libnewlib-arm-none-eabi)")
                break
    if not missing:
        return None
    return f"missing {', '.join(missing)}; install with: {APT_LINE}"


def tool_versions() -> dict[str, str]:
    """First line of ``--version`` of the cross compiler and QEMU."""
    out = {}
    for t in (GCC, QEMU):
        res = subprocess.run([t, "--version"], capture_output=True, text=True)
        out[t] = res.stdout.splitlines()[0] if res.stdout else "?"
    return out


def _run(cmd: Sequence[str | Path], cwd: Path | None = None) -> str:
    res = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, cwd=cwd)
    if res.returncode != 0:
        raise McuError(f"failed: {' '.join(map(str, cmd))}\n{res.stdout}{res.stderr}")
    return res.stdout


# ---------------------------------------------------------------- generated headers

def _c_bits(a: np.ndarray) -> list[str]:
    return [f"0x{int(v):08x}u" for v in np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)]


def c_float_array(name: str, values: np.ndarray, ctype: str = "real_t") -> str:
    """``static const <ctype> name[n] = {...};`` with exact C99 hex-float literals (float32 values;
    for the config preamble of a case)."""
    vals = np.asarray(values, dtype=np.float32).ravel()
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{name}: non-finite value")
    body = ", ".join(f"{float(v).hex()}f" if v != 0 else "0.0f" for v in vals)
    return f"static const {ctype} {name}[{vals.size}] = {{{body}}};\n"


def c_real(value: float) -> str:
    """Exact C99 hex-float literal of ``value`` rounded to float32 (a real_t field)."""
    v = float(np.float32(value))
    if not np.isfinite(v):
        raise ValueError(f"non-finite value {value!r}")
    return f"{v.hex()}f"


def c_double(value: float) -> str:
    """Exact C99 hex-float literal of ``value`` (a double config field)."""
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"non-finite value {value!r}")
    return v.hex()


def _is_zero(text: str) -> bool:
    return re.fullmatch(r"[{}0,\s]*|0x0\.0p\+0|-?0\.0", text.strip()) is not None and \
        not text.strip().startswith("-")


def c_initializer(obj: Any) -> str:
    """C99 designated initialiser of a ctypes Structure/array/scalar (e.g. the
    ``rh_ctrl_config_t`` of controller/native/config.py): layout-independent, so the host's
    ctypes layout need not match the ARM EABI one. Doubles/floats as exact hex literals."""
    if isinstance(obj, ctypes.Structure):
        parts = [f".{name} = {c_initializer(getattr(obj, name))}"
                 for name, *_ in obj._fields_ if not name.startswith("_pad")]
        return "{" + ", ".join(parts) + "}"
    if isinstance(obj, ctypes.Array):
        items = [c_initializer(v) for v in obj]
        while items and _is_zero(items[-1]):
            items.pop()  # the rest is zero-initialised: fits arrays shortened by -DRH_N_MAX
        return "{" + (", ".join(items) if items else "0") + "}"
    if isinstance(obj, bool | int | np.integer):
        return str(int(obj))
    if isinstance(obj, float | np.floating):
        return c_double(float(obj))
    raise TypeError(f"no C initialiser for {type(obj).__name__}")


# Flat layouts of cases/ctrl_step.c (ints carried as float values).
CTRL_INPUTS: tuple[str, ...] = (
    "swa_rad", "accel_pedal", "brake_pedal", "yaw_rate", "ax", "ay", "ws0", "ws1", "ws2",
    "ws3", "vx", "vy", "stab_enable", "sensors_valid", "wheel_speeds_usable")
CTRL_OUTPUTS: tuple[str, ...] = (
    "torque0", "torque1", "torque2", "torque3", "total_torque", "delta_m", "yaw_rate_ref",
    "vy_ref", "beta_ref", "qp_status", "qp_iterations", "fallback", "pred_vx", "pred_vy",
    "pred_r")


def ctrl_step_case(config: Any, inputs: np.ndarray, expected: np.ndarray,
                   tolerance: np.ndarray, sources: Sequence[str | Path],
                   lib_sources: Sequence[str | Path] = (),
                   include_dirs: Sequence[str | Path] = (), defines: Sequence[str] = (),
                   bound_text: str = "", name: str = "rh_ctrl_step",
                   lib_flags: Sequence[str] = ()) -> McuCase:
    """The full controller step as a case: ``config`` the ctypes ``rh_ctrl_config_t`` (or
    the C initialiser text), ``inputs`` (steps, 15) in CTRL_INPUTS order, ``expected``
    (steps, 15) float32 reference in CTRL_OUTPUTS order (NaN where the reference has none;
    NaN = NaN counts as equal), ``sources`` the core's sources (e.g. every src/*.c the
    step links), ``lib_sources``/``include_dirs``/``defines`` e.g. the generated OSQP code."""
    init = config if isinstance(config, str) else c_initializer(config)
    return McuCase(
        name=name, adapter=MCU_DIR / "cases" / "ctrl_step.c", sources=sources,
        config_c=f'#include "rhonn_core.h"\nstatic const rh_ctrl_config_t MCU_CONFIG = {init};\n',
        inputs=inputs, expected=expected, tolerance=tolerance, bound_text=bound_text,
        output_names=CTRL_OUTPUTS, lib_sources=lib_sources, include_dirs=include_dirs,
        defines=defines, lib_flags=lib_flags)


def write_case_headers(case: McuCase, out: Path) -> None:
    inputs = np.asarray(case.inputs, dtype=np.float32)
    n_steps, n_in = inputs.shape
    n_out = np.asarray(case.expected).shape[1]
    (out / "mcu_case_dims.h").write_text(
        "/* generated by harness/bench/mcu.py */\n"
        "#ifndef MCU_CASE_DIMS_H\n#define MCU_CASE_DIMS_H\n"
        f"#define MCU_N_STEPS {n_steps}u\n#define MCU_N_IN {n_in}u\n#define MCU_N_OUT {n_out}u\n"
        "#endif\n")
    rows = ",\n".join("  {" + ", ".join(_c_bits(r)) + "}" for r in inputs)
    (out / "mcu_case_inputs.h").write_text(
        "/* generated by harness/bench/mcu.py: recorded inputs, float32 bit patterns */\n"
        "#include <stdint.h>\n#include \"mcu_case_dims.h\"\n"
        f"static const uint32_t MCU_INPUT_BITS[MCU_N_STEPS][MCU_N_IN] = {{\n{rows}\n}};\n")
    (out / "mcu_case_config.h").write_text(
        "/* generated by harness/bench/mcu.py: case preamble (config initialisers) */\n"
        "#ifndef MCU_CASE_CONFIG_H\n#define MCU_CASE_CONFIG_H\n"
        f"{case.config_c}\n#endif\n")


# ---------------------------------------------------------------- build

def _size(objs: Sequence[Path]) -> tuple[int, int]:
    """(text+rodata, data+bss) summed over objects (Berkeley format: text includes rodata)."""
    if not objs:
        return 0, 0
    flash = ram = 0
    for line in _run([SIZE, *objs]).splitlines()[1:]:
        parts = line.split()
        flash += int(parts[0])
        ram += int(parts[1]) + int(parts[2])
    return flash, ram


def _undefined(objs: Sequence[Path]) -> set[str]:
    out: set[str] = set()
    for o in objs:
        out |= {ln.split()[-1] for ln in _run([NM, "-u", o]).splitlines() if ln.strip()}
    return out


def _defined(objs: Sequence[Path]) -> set[str]:
    out: set[str] = set()
    for o in objs:
        out |= {ln.split()[-1] for ln in _run([NM, "--defined-only", o]).splitlines()
                if ln.strip()}
    return out


def _soft_double(undef: set[str]) -> list[str]:
    """Software double-precision helpers (libgcc) among the undefined symbols: the M4F FPU
    is single precision, so every double operation in the step is a library call."""
    return sorted(u for u in undef if re.match(r"__aeabi_(d|f2d|l2d|ul2d|i2d|ui2d)|__\w*df\d", u))


def _soft_double_callers(objs: Sequence[Path]) -> dict[str, list[str]]:
    """function → the soft double-precision helpers it calls (from the relocations)."""
    out: dict[str, set[str]] = {}
    fn = "?"
    for o in objs:
        for line in _run([OBJDUMP, "-dr", o]).splitlines():
            m = re.match(r"^[0-9a-f]+ <([^>]+)>:$", line)
            if m:
                fn = m.group(1)
                continue
            m = re.search(r"R_ARM_THM_(?:CALL|JUMP24)\s+(\S+)", line)
            if m and _soft_double({m.group(1)}):
                out.setdefault(fn, set()).add(m.group(1))
    return {k: sorted(v) for k, v in sorted(out.items())}


_MAP_IN = re.compile(r"^ (\.[\w.$-]+|COMMON)(?:\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S.*))?$")
_MAP_CONT = re.compile(r"^\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S.*)$")


def linked_sizes(map_file: Path, groups: dict[str, Path]) -> dict[str, dict[str, int]]:
    """Bytes that went into the image per group after --gc-sections, from the link map:
    {group: {text, rodata, data, bss}}; ``groups`` maps a group name to the folder of its
    objects; archive members go to "newlib" (libc_nano, libm, libnosys) or "libgcc"."""
    kinds = (("text", (".text", ".glue", ".vfp11", ".ARM.ex", ".init", ".fini")),
             ("rodata", (".rodata",)), ("data", (".data",)), ("bss", (".bss", "COMMON")))
    out: dict[str, dict[str, int]] = {}
    lines = map_file.read_text().splitlines()
    try:
        start = next(i for i, ln in enumerate(lines) if ln.startswith("Linker script and memory"))
    except StopIteration as exc:
        raise McuError(f"{map_file}: no memory map") from exc
    pending: str | None = None
    for line in lines[start:]:
        if line.startswith((" *fill*", " *(")) or not line.strip():
            pending = None
            continue
        sec = size = path = None
        m = _MAP_IN.match(line)
        if m:
            if m.group(2) is None:
                pending = m.group(1)
                continue
            sec, size, path = m.group(1), int(m.group(3), 16), m.group(4)
        elif pending is not None:
            c = _MAP_CONT.match(line)
            if c:
                sec, size, path = pending, int(c.group(2), 16), c.group(3)
            pending = None
        if sec is None or not size or path is None:
            continue
        kind = next((k for k, pre in kinds if sec.startswith(pre)), None)
        if kind is None:
            continue
        path = path.strip()
        group = next((g for g, d in groups.items() if path.startswith(str(d) + "/")), None)
        if group is None:
            group = ("libgcc" if "libgcc" in path else
                     "newlib" if re.search(r"lib(c|c_nano|m|nosys|g_nano)\.a", path) else "other")
        g = out.setdefault(group, {"text": 0, "rodata": 0, "data": 0, "bss": 0})
        g[kind] += size
    return out


def _object_symbols(objs: Sequence[Path]) -> dict[str, int]:
    """Data/bss symbols (name → bytes) defined in the objects (e.g. the controller state)."""
    out: dict[str, int] = {}
    for o in objs:
        for line in _run([NM, "-S", "--defined-only", o]).splitlines():
            parts = line.split()
            if len(parts) == 4 and parts[2].lower() in ("b", "d"):
                out[parts[3]] = int(parts[1], 16)
    return out


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


def _stack_functions(su_files: Sequence[Path]) -> dict[str, tuple[int, str]]:
    """function → (bytes, qualifier) from .su files."""
    out: dict[str, tuple[int, str]] = {}
    for f in su_files:
        for line in f.read_text().splitlines():
            loc, nbytes, kind = line.split("\t")
            name = loc.rsplit(":", 1)[-1]
            if name not in out or int(nbytes) > out[name][0]:
                out[name] = (int(nbytes), kind)
    return out


_CI_NODE = re.compile(
    r'node: \{ title: "([^"]+)" label: "[^"]*?\\n[^"]*?\\n(\d+) bytes \(([^)]*)\)')
_CI_NODE_ANY = re.compile(r'node: \{ title: "([^"]+)"')
_CI_EDGE = re.compile(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"')


def static_stack_path(ci_files: Sequence[Path], entry: str) -> dict[str, Any]:
    """Worst static stack path from ``entry`` over the -fcallgraph-info=su graphs: sum of
    frames along the deepest call chain of functions with known frames; callees without a
    frame (outside the compiled objects, e.g. libm) are listed as not counted."""
    frame: dict[str, int] = {}
    dynamic: set[str] = set()
    edges: dict[str, set[str]] = {}
    for f in ci_files:
        text = f.read_text()
        for m in _CI_NODE.finditer(text):
            frame[m.group(1)] = max(frame.get(m.group(1), 0), int(m.group(2)))
            if "dynamic" in m.group(3):
                dynamic.add(m.group(1))
        for m in _CI_NODE_ANY.finditer(text):
            edges.setdefault(m.group(1), set())
        for m in _CI_EDGE.finditer(text):
            edges.setdefault(m.group(1), set()).add(m.group(2))
    unknown: set[str] = set()
    memo: dict[str, tuple[int, list[str]]] = {}

    def worst(fn: str, seen: tuple[str, ...]) -> tuple[int, list[str]]:
        if fn in seen:
            raise McuError(f"recursion in the call graph: {' -> '.join((*seen, fn))}")
        if fn not in frame:
            unknown.add(fn)
            return 0, []
        if fn in memo:
            return memo[fn]
        best: tuple[int, list[str]] = (0, [])
        for callee in sorted(edges.get(fn, ())):
            best = max(best, worst(callee, (*seen, fn)), key=lambda t: t[0])
        memo[fn] = (frame[fn] + best[0], [fn, *best[1]])
        return memo[fn]

    total, path = worst(entry, ())
    return {"bytes": total, "path": path, "not_counted": sorted(unknown),
            "dynamic": sorted(dynamic & set(path))}


@dataclasses.dataclass
class Build:
    elf: Path
    core_objs: list[Path]
    case_objs: list[Path]
    opt: str
    lib_objs: list[Path] = dataclasses.field(default_factory=list)


def build(case: McuCase, out: Path, opt: str = "Os") -> Build:
    """Compile and link the case at -<opt> into ``out``; returns the ELF and object lists."""
    out.mkdir(parents=True, exist_ok=True)
    write_case_headers(case, out)
    incs = [f"-I{SRC_DIR}", f"-I{NATIVE_DIR / 'include'}", f"-I{MCU_DIR}", f"-I{out}",
            *(f"-isystem{d}" for d in case.include_dirs), *(f"-D{d}" for d in case.defines)]
    aux = ("-fstack-usage", "-fcallgraph-info=su")
    core_objs, lib_objs, case_objs, harness_objs = [], [], [], []
    for group, flags, names, objs in (("core", CORE_FLAGS, case.sources, core_objs),
                                      ("lib", (*LIB_FLAGS, *case.lib_flags), case.lib_sources,
                                       lib_objs)):
        for src in (Path(s) if Path(s).is_absolute() else SRC_DIR / s for s in names):
            obj = out / group / (src.stem + ".o")
            obj.parent.mkdir(exist_ok=True)
            _run([GCC, *flags, *ARCH_FLAGS, f"-{opt}", *aux, *incs, "-c", src, "-o", obj])
            objs.append(obj)
    obj = out / "case" / (Path(case.adapter).stem + ".o")
    obj.parent.mkdir(exist_ok=True)
    _run([GCC, *CORE_FLAGS, *ARCH_FLAGS, f"-{opt}", *aux, *incs, "-c", case.adapter, "-o", obj])
    case_objs.append(obj)
    for name in HARNESS_SOURCES:
        obj = out / "harness" / (Path(name).stem + ".o")
        obj.parent.mkdir(exist_ok=True)
        _run([GCC, *HARNESS_FLAGS, *ARCH_FLAGS, *incs, "-c", MCU_DIR / name, "-o", obj])
        harness_objs.append(obj)
    elf = out / "app.elf"
    _run([GCC, *ARCH_FLAGS, "-T", MCU_DIR / "mps2_an386.ld", "-nostartfiles",
          "--specs=nano.specs", "--specs=nosys.specs", "-Wl,--gc-sections",
          f"-Wl,-Map={out / 'app.map'}", *harness_objs, *case_objs, *core_objs, *lib_objs,
          "-lm", "-o", elf])
    return Build(elf, core_objs, case_objs, opt, lib_objs)


def build_plugin(out: Path, api_version: int = 1) -> Path | None:
    """The instruction-count plugin for the host QEMU (None without a host C compiler)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    so = out / f"qemu_insn_plugin-v{api_version}.so"
    if not so.exists():
        _run([cc, "-shared", "-fPIC", "-O2", "-Wall", f"-DPLUGIN_API_VERSION={api_version}",
              MCU_DIR / "qemu_insn_plugin.c", "-o", so])
    return so


def _symbol(elf: Path, name: str) -> int:
    for line in _run([NM, elf]).splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == name:
            return int(parts[0], 16) & ~1
    raise McuError(f"{name} not found in {elf}")


# ---------------------------------------------------------------- run

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


# ---------------------------------------------------------------- demo case (until rhonn_core.h)

def rhonn_demo_reference(inputs: np.ndarray, mu: np.ndarray, beta: np.ndarray,
                         W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 numpy reference of the demo step (xi, phi, bilinear C) in the C operation order,
    and the magnitude M (same computation on absolute values, float64) for the bound."""
    from controller.core.model.rhonn import MONO_INDEX, PHI_SUBSETS, TFAC_INDEX

    def forward(x: np.ndarray, mu_: np.ndarray, beta_: np.ndarray, W_: np.ndarray,
                dtype: type, absval: bool) -> np.ndarray:
        x = x.astype(dtype)
        xi = mu_.astype(dtype) * np.tanh(beta_.astype(dtype) * x)
        if absval:
            xi = np.abs(xi)
        phi = np.empty((x.shape[0], len(PHI_SUBSETS)), dtype=dtype)
        for k, s in enumerate(PHI_SUBSETS):  # left-to-right products, as rh_rhonn_phi
            p = xi[:, s[0]]
            for j in s[1:]:
                p = p * xi[:, j]
            phi[:, k] = p
        a, d = xi[:, 0], xi[:, 3]
        t = np.stack([np.ones_like(a), a, d, a * d], axis=1)
        w = np.abs(W_).astype(dtype) if absval else W_.astype(dtype)
        C = np.zeros((x.shape[0], 12), dtype=dtype)
        for i in range(3):
            w4 = np.zeros((4, 4), dtype=dtype)
            for k in range(len(PHI_SUBSETS)):
                w4[MONO_INDEX[k], TFAC_INDEX[k]] = w[i * 15 + k]
            for m in range(4):
                s_ = np.zeros(x.shape[0], dtype=dtype)
                for f in range(4):  # s += w4[m][f] * t[f], f = 0..3, as rh_rhonn_bilinear
                    s_ = s_ + w4[m, f] * t[:, f]
                C[:, i * 4 + m] = s_
        return np.concatenate([phi, C], axis=1)

    ref = forward(inputs, mu, beta, W, np.float32, False)
    mag = forward(inputs, mu, beta, W, np.float64, True)
    return ref, mag


def demo_case(n_steps: int = 200, seed: int = 0) -> McuCase:
    """The pipeline proof while the full step is not there: per step, ξ = μ tanh(β x) of the
    recorded x = [Vx, Vy, ωr, δw], φ(ξ) (15) and the bilinear coefficients C (12) of a fixed
    W, i.e. rh_rhonn_xi, rh_rhonn_phi and rh_rhonn_bilinear of src/rhonn.c. Inputs: a smooth
    seeded random manoeuvre (Vx 5–35 m/s, |Vy| ≤ 2 m/s, |ωr| ≤ 1 rad/s, |δw| ≤ 0.1 rad)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps) * 0.01
    ph = rng.uniform(0, 2 * np.pi, 4)
    x = np.stack([20 + 15 * np.sin(0.3 * t + ph[0]), 2.0 * np.sin(1.7 * t + ph[1]),
                  1.0 * np.sin(2.3 * t + ph[2]), 0.1 * np.sin(3.1 * t + ph[3])], axis=1)
    x = (x + rng.normal(0, 1e-3, x.shape)).astype(np.float32)
    mu = np.ones(4, dtype=np.float32)
    beta = np.array([1 / 30, 1 / 3, 1 / 0.6, 1 / 0.15], dtype=np.float32)
    W = rng.normal(0, 0.05, 45).astype(np.float32)
    ref, mag = rhonn_demo_reference(x, mu, beta, W)
    names = [f"phi{k}" for k in range(15)] + [f"C{i}{m}" for i in range(3) for m in range(4)]
    config = ('#include "rh_real.h"\n' + c_float_array("MCU_W", W) + c_float_array("MCU_MU", mu)
              + c_float_array("MCU_BETA", beta))
    return McuCase(
        name="rhonn-demo (xi, phi, bilinear of src/rhonn.c)",
        adapter=MCU_DIR / "cases" / "rhonn_demo.c", sources=["rhonn.c"], config_c=config,
        inputs=x, expected=ref, tolerance=16 * EPS32 * mag + 1e-30,
        bound_text="|err| <= 16 eps32 M, M = the same computation on |operands| (tanhf of "
                   "newlib vs numpy float32 tanh, each within a few ulp; products and sums "
                   "in the C order)", output_names=names)


CTRL_INT_OUTPUTS: tuple[int, ...] = (9, 10, 11)   # qp_status, qp_iterations, fallback
# Bound of the MCU outputs vs the float32 numpy reference, per real output, relative to that
# output's largest magnitude over the sequence (see full_core_case for the derivation).
FULL_CORE_BOUND = 1e-4
# Bound of the MCU outputs vs the host's float32 C core, same scale (see full_core_case).
HOST_C_BOUND = 5e-5
# QP iteration counts may differ on at most this fraction of the steps (status and fallback
# must not differ; see full_core_case).
ITER_MISMATCH_FRACTION = 0.03


def _ctrl_row(o: Any) -> list[float]:
    return [*o.torques, o.total_torque, o.delta_m, o.yaw_rate_ref, o.vy_ref, o.beta_ref,
            int(o.qp_status), o.qp_iterations, float(bool(o.fallback)), *o.model_prediction]


def _ctrl_inputs(row: np.ndarray) -> Any:
    from controller.core.interfaces import ControllerInputs

    x = [float(v) for v in row]
    return ControllerInputs(
        swa_rad=x[0], accel_pedal=x[1], brake_pedal=x[2], yaw_rate=x[3], ax=x[4], ay=x[5],
        wheel_speeds=np.array(x[6:10]), vx=x[10], vy=x[11], stab_enable=bool(x[12]),
        sensors_valid=bool(x[13]))


def replay_outputs(controller: Any, X: np.ndarray) -> np.ndarray:
    """Outputs (steps, 15) in CTRL_OUTPUTS order of ``controller`` stepped on ``X`` (steps, 15)
    in CTRL_INPUTS order."""
    return np.array([_ctrl_row(controller.step(_ctrl_inputs(x))) for x in X], dtype=np.float64)


def qp_shape(cfg: Any) -> tuple[int, bool]:
    """(N, rate rows) of the controller's QP: the one OSQP shape the MCU build needs."""
    return int(cfg.mpc.horizon), float(cfg.mpc.rate_limit_nm_per_s) > 0.0


def full_core_case(n_steps: int = 300, name: str = "nmpc-rhonn", osqp: str = "float",
                   config: str | Path | None = None) -> McuCase:
    """The whole controller step (rh_ctrl_init / rh_ctrl_step of include/rhonn_core.h) as
    deployed: the core in float (-DRH_FLOAT32), OSQP's generated solver for the configured QP
    shape only (N and rate rows of ``config``, None → default.toml: N 3, no rate rows), the
    core built with -DRH_N_MAX=N, OSQP in float (``osqp="float"``, -DOSQP_USE_FLOAT) or in
    double (``osqp="double"``, software-emulated on the M4F's single-precision FPU).

    Inputs: the recorded closed-loop sequence (harness.bench.controller_step.recorded_inputs:
    the numpy reference in float64 on the bench plant, 65 km/h, μ 0.35, DLC steering), rounded
    to float32 (every side gets exactly the MCU's inputs). References, on those inputs, with
    ``precision = "float32"`` and the UD EKF:

    * expected: the float32 numpy reference (backend "numpy"), the oracle;
    * others["host C float32"]: the float32 C core on the host (controller.native._rhcore32,
      same sources, OSQP in double), when it is built.

    Bounds, per real output j, relative to the output's largest magnitude over the
    sequence, S_j = max_k |ref_j(k)| (the scale of tests/test_native_core.py):

    (a) MCU vs the host float32 C core: |err_j| ≤ HOST_C_BOUND = 5e-5 · S_j. Same sources,
        same precision; the differences are newlib's tanhf/expf/sqrtf/sinf vs glibc's (each
        within a few ulp) and, in the float-OSQP build, the QP solved in float to
        eps_abs = eps_rel = 1e-5 instead of double. Measured on this sequence (Os and O2
        alike): 7.7e-6 (OSQP float), 1.3e-6 (OSQP double, libm only) → margin 6.5×.
    (b) MCU vs the float32 numpy reference (the oracle): |err_j| ≤ FULL_CORE_BOUND = 1e-4 ·
        S_j, half the host's own float32 bound (2e-4 in tests/test_native_core.py, on the
        sequence with spliced-in edge cases). Measured here: 4.3e-6 (OSQP float), 9.8e-6
        (OSQP double; the host C core itself: 9.8e-6) → margin ≥ 10×.
    (c) QP status and fallback flags equal at every step; iteration counts may differ on at
        most ITER_MISMATCH_FRACTION = 3 % of the steps (a residual sitting at the 1e-5
        threshold can stop the float solver one termination check, 5 iterations, earlier or
        later). Measured: no step differs, in either variant, against either reference."""
    import atexit

    from controller.core.registry import load_controller_config
    from controller.native import osqp_gen
    from controller.native.backend import core_module
    from controller.native.config import ctrl_config
    from controller.registry import make_controller
    from harness.bench.controller_step import recorded_inputs, set_toml_keys

    if osqp not in ("float", "double"):
        raise ValueError(f"osqp must be 'float' or 'double', not {osqp!r}")
    tmp = Path(tempfile.mkdtemp(prefix="rhonn-mcu-case-"))
    atexit.register(shutil.rmtree, tmp, True)
    if config is None:
        from importlib import resources
        text = resources.files("controller").joinpath("config/default.toml").read_text()
    else:
        text = Path(config).read_text()
    text = set_toml_keys(text, "[mpc]", 'precision = "float32"')
    text = set_toml_keys(text, "[rhonn.ekf]", 'form = "ud"')
    path32 = tmp / "float32.toml"
    path32.write_text(text)
    cfg = load_controller_config(path32)

    rec = recorded_inputs(name, steps=n_steps, config=config)
    X = np.zeros((n_steps, len(CTRL_INPUTS)), np.float32)
    for k, inp in enumerate(rec):
        X[k] = [inp.swa_rad, inp.accel_pedal, inp.brake_pedal, inp.yaw_rate, inp.ax, inp.ay,
                *inp.wheel_speeds, inp.vx, inp.vy, float(inp.stab_enable),
                float(inp.sensors_valid), 1.0]
    exp = replay_outputs(make_controller(name, path32, backend="numpy"), X)
    others: dict[str, np.ndarray] = {}
    notes: dict[str, Any] = {}
    if core_module(True) is not None:
        others["host C float32"] = replay_outputs(
            make_controller(name, path32, backend="native"), X).astype(np.float32)
    else:
        notes["host C float32"] = "not built on this host (no comparison)"

    n, rate = qp_shape(cfg)
    gen = osqp_gen.generate(tmp / "osqp", [(n, rate)])
    defines = [f"RH_N_MAX={n}", *(["OSQP_USE_FLOAT"] if osqp == "float" else [])]
    # OSQP in float: its unsuffixed constants (1e-6, 0.5, ...) as float too, else every
    # expression they appear in is promoted to software double (all fit a float: 1e-20..1e30)
    lib_flags = ["-fsingle-precision-constant"] if osqp == "float" else []
    scale = np.array([max(float(np.nanmax(np.abs(c))) if np.isfinite(c).any() else 0.0, 1e-12)
                      for c in exp.T])
    tol = FULL_CORE_BOUND * scale
    tol[list(CTRL_INT_OUTPUTS)] = np.inf
    notes.update({"qp_shape": f"N {n}, {'with' if rate else 'no'} rate rows",
                  "osqp_precision": osqp, "defines": defines, "osqp_flags": lib_flags,
                  "reference": "numpy float32 (UD EKF), same float32 inputs"})
    case = ctrl_step_case(
        ctrl_config(name, cfg), X, exp.astype(np.float32), tol,
        sources=sorted(p.name for p in SRC_DIR.glob("*.c")),
        lib_sources=osqp_gen.osqp_sources(gen), include_dirs=osqp_gen.osqp_include_dirs(gen),
        defines=defines, lib_flags=lib_flags,
        bound_text=f"|err| <= {FULL_CORE_BOUND:g} x max|ref| per real output vs the float32 "
                   f"numpy reference, {HOST_C_BOUND:g} x max|ref| vs the host float32 C core; "
                   "QP status/fallback equal, iterations differing on <= "
                   f"{100 * ITER_MISMATCH_FRACTION:g} % of steps",
        name=f"{name} full step, core float32, OSQP {osqp} (N={n}{', rate' if rate else ''})")
    case.others = others
    case.int_outputs = CTRL_INT_OUTPUTS
    case.notes = notes
    return case


def full_core_case_osqp_double(n_steps: int = 300, name: str = "nmpc-rhonn") -> McuCase:
    """:func:`full_core_case` with OSQP in double (software floating point on the M4F)."""
    return full_core_case(n_steps, name, osqp="double")


# ---------------------------------------------------------------- CLI

FLASH_TARGET_BYTES = 64 * 1024   # issue: core text+rodata ≤ 64 kB
RAM_TARGET_BYTES = 16 * 1024     # issue: core data+bss ≤ 16 kB, controller state included


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
    import inspect

    from can_db.argcheck import OneLineParser, number

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
