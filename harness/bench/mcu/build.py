"""Compiling and linking a case for the Cortex-M4F, and what the objects and the link map
say: sizes, soft double-precision calls, stack frames and the worst static stack path."""

from __future__ import annotations

import dataclasses
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from controller.native.build_tools import CFLAGS, NATIVE_DIR, SRC_DIR
from harness.bench.mcu.case import MCU_DIR, McuCase, McuError, write_case_headers
from harness.bench.mcu.toolchain import ARCH_FLAGS, GCC, NM, OBJDUMP, SIZE, _run

CORE_FLAGS: tuple[str, ...] = (*(f for f in CFLAGS if not f.startswith("-O")), "-DRH_FLOAT32",
                               "-ffunction-sections", "-fdata-sections")
HARNESS_FLAGS: tuple[str, ...] = ("-std=gnu99", "-Wall", "-Wextra", "-Werror", "-O2",
                                  "-ffunction-sections", "-fdata-sections")
# third-party code as setup.py builds OSQP's (OSQP_FLAGS), plus -DRH_FLOAT32 and sections
LIB_FLAGS: tuple[str, ...] = ("-std=gnu99", "-w", "-ffp-contract=off", "-DRH_FLOAT32",
                              "-ffunction-sections", "-fdata-sections")
HARNESS_SOURCES: tuple[str, ...] = ("startup.c", "semihost.c", "main.c")


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
