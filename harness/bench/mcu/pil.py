"""The processor-in-the-loop firmware (controller/native/mcu/pil/): building it for the
Cortex-M4F, and the instructions the SLCAN link spends per frame, counted by the QEMU plugin
while the echo firmware answers frames over the link (harness/run/pil_link.py)."""

from __future__ import annotations

import random
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import can

from harness.bench.mcu.build import CORE_FLAGS, HARNESS_FLAGS, LIB_FLAGS, _symbol, build_plugin
from harness.bench.mcu.case import MCU_DIR, McuError
from harness.bench.mcu.toolchain import ARCH_FLAGS, GCC, SIZE, _run
from harness.run.pil_link import PilLink, PilLinkError

PIL_DIR = MCU_DIR / "pil"
PIL_SOURCES: tuple[str, ...] = ("cmsdk_uart.c", "slcan.c", "pil.c")  # C99, the core's flags
ECHO_MAIN = PIL_DIR / "pil_echo.c"
N_BASELINE = 4  # empty marker pairs at the echo firmware's start (pil_echo.c)
ANSWER_TIMEOUT_S = 10.0  # wall s for one echoed frame (QEMU on a loaded machine)


def build_pil_firmware(
    out: Path,
    main: str | Path = ECHO_MAIN,
    opt: str = "Os",
    insn_marks: bool = True,
    extra_sources: Sequence[str | Path] = (),
    *,
    include_dirs: Sequence[str | Path] = (),
    system_include_dirs: Sequence[str | Path] = (),
    defines: Sequence[str] = (),
    lib_sources: Sequence[str | Path] = (),
    lib_flags: Sequence[str] = (),
    source_groups: Mapping[str, Sequence[str | Path]] | None = None,
) -> Path:
    """Compile the PIL link (C99, the core's flags at -<opt>) with ``main`` (a firmware main:
    harness C, like main.c) and the MCU start-up and semihosting files; link ``out/pil.elf``
    (and its map ``out/pil.map``).
    ``insn_marks``: the link calls ``mcu_mark()`` around its work (-DPIL_INSN_MARKS; the
    main must define it). ``extra_sources``: further C99 sources (e.g. a node), the core's
    flags. ``include_dirs``, ``system_include_dirs`` (-isystem: third-party headers, no
    warnings) and ``defines`` (``NAME`` or ``NAME=VALUE``): for every file, the main included
    (it must see the structs as the core's objects do). ``lib_sources``:
    third-party C (e.g. OSQP's generated solver), built with the MCU build's LIB_FLAGS plus
    ``lib_flags`` into ``out/lib``. ``source_groups``: further C99 sources by group name, the
    core's flags, each group's objects in ``out/<group>`` (so the link map tells their sizes
    apart; the link's own objects are group "pil")."""
    out.mkdir(parents=True, exist_ok=True)
    marks = ("-DPIL_INSN_MARKS",) if insn_marks else ()
    incs = (
        f"-I{PIL_DIR}",
        f"-I{MCU_DIR}",
        *(f"-I{d}" for d in include_dirs),
        *(f"-isystem{d}" for d in system_include_dirs),
        *(f"-D{d}" for d in defines),
    )
    objs: list[Path] = []
    groups = {"pil": [*(PIL_DIR / s for s in PIL_SOURCES), *map(Path, extra_sources)]}
    for name, sources in (source_groups or {}).items():
        groups.setdefault(name, []).extend(map(Path, sources))
    for name, sources in groups.items():
        for src in sources:
            obj = out / name / (src.stem + ".o")
            obj.parent.mkdir(exist_ok=True)
            _run([GCC, *CORE_FLAGS, *ARCH_FLAGS, f"-{opt}", *marks, *incs, "-c", src, "-o", obj])
            objs.append(obj)
    for src in map(Path, lib_sources):
        obj = out / "lib" / (src.stem + ".o")
        obj.parent.mkdir(exist_ok=True)
        _run([GCC, *LIB_FLAGS, *lib_flags, *ARCH_FLAGS, f"-{opt}", *incs, "-c", src, "-o", obj])
        objs.append(obj)
    for src in (MCU_DIR / "startup.c", MCU_DIR / "semihost.c", Path(main)):
        obj = out / "harness" / (src.stem + ".o")
        obj.parent.mkdir(exist_ok=True)
        _run([GCC, *HARNESS_FLAGS, *ARCH_FLAGS, *incs, "-c", src, "-o", obj])
        objs.append(obj)
    elf = out / "pil.elf"
    _run(
        [
            GCC,
            *ARCH_FLAGS,
            "-T",
            MCU_DIR / "mps2_an386.ld",
            "-nostartfiles",
            "--specs=nano.specs",
            "--specs=nosys.specs",
            "-Wl,--gc-sections",
            f"-Wl,-Map={out / 'pil.map'}",
            *objs,
            "-lm",
            "-o",
            elf,
        ]
    )
    return elf


def echo_answer(msg: can.Message) -> can.Message:
    """What the echo firmware answers to ``msg``: identifier + 1 (wrapping in 11 / 29 bits),
    each data byte + 1 (mod 256), same format and DLC."""
    mask = 0x1FFFFFFF if msg.is_extended_id else 0x7FF
    return can.Message(
        arbitration_id=(msg.arbitration_id + 1) & mask,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        dlc=msg.dlc,
        data=bytes((b + 1) & 0xFF for b in msg.data),
    )


def random_frames(n: int, seed: int) -> list[can.Message]:
    """``n`` standard data frames, DLC cycling 0..8, seeded random identifiers and payloads."""
    rng = random.Random(seed)
    return [
        can.Message(
            arbitration_id=rng.randrange(0x800),
            is_extended_id=False,
            data=bytes(rng.randrange(256) for _ in range(k % 9)),
        )
        for k in range(n)
    ]


def slcan_line(msg: can.Message) -> bytes:
    """The line python-can's slcan interface writes for a standard data frame."""
    return f"t{msg.arbitration_id:03X}{msg.dlc:d}{msg.data.hex().upper()}\r".encode()


def frame_instructions(
    marks: Sequence[int], host_bytes: Sequence[bytes], n_baseline: int = N_BASELINE
) -> list[int]:
    """Instructions the link spent per echoed frame, from the plugin's marker counts.

    The firmware marks each received byte's handling and each pil_tx_frame as a pair; the
    host's stream is known (``host_bytes``: its lines in order, frames as ``t...`` lines),
    so pair k belongs to byte k, and a frame line's last byte is followed by the answer's
    transmit pair. Per frame: its bytes' pairs + its answer's pair, each less the empty-pair
    baseline (the marker's own cost). The idle polling between bytes is not counted."""
    m = list(marks)
    base = [m[2 * i + 1] - m[2 * i] for i in range(n_baseline)]
    if len(m) < 2 * n_baseline or len(set(base)) != 1:
        raise McuError(f"marker baseline not constant: {base}")
    pairs = [m[i + 1] - m[i] - base[0] for i in range(2 * n_baseline, len(m) - 1, 2)]
    out: list[int] = []
    k = 0
    for line in host_bytes:
        need = len(line) + (1 if line[:1] == b"t" else 0)
        if k + need > len(pairs):
            raise McuError(f"{len(pairs)} marker pairs: the host's stream needs more")
        if line[:1] == b"t":
            out.append(sum(pairs[k : k + need]))
        k += need
    return out


def boot_with_plugin(
    elf: Path, plugin_dir: Path, work_dir: Path, start_timeout_s: float
) -> tuple[PilLink, Path, int]:
    """QEMU running ``elf`` with the instruction-count plugin (built in ``plugin_dir``) and the
    link started; (link, the plugin's log in ``work_dir``, the plugin API version). Tries the
    plugin API versions 1..5 as the QEMU at hand wants."""
    mark = _symbol(elf, "mcu_mark")
    log = work_dir / "plugin.log"
    for api in (1, 2, 3, 4, 5):
        so = build_plugin(plugin_dir, api)
        if so is None:
            raise McuError("no host C compiler for the QEMU plugin")
        log.unlink(missing_ok=True)
        link = PilLink(
            elf,
            work_dir,
            start_timeout_s=start_timeout_s,
            qemu_extra=("-plugin", f"{so},mark={mark:#x}", "-d", "plugin", "-D", str(log)),
        )
        try:
            link.start()
        except PilLinkError as exc:
            text = str(exc).lower()
            if "version" in text and "plugin" in text:
                continue  # this QEMU wants another plugin API version
            raise
        return link, log, api
    raise McuError("the QEMU plugin loaded with no API version 1..5")


def measure_echo(
    out: Path, n_frames: int = 100, seed: int = 1, opt: str = "Os", start_timeout_s: float = 30.0
) -> dict[str, Any]:
    """Build the echo firmware with markers, boot it with the instruction-count plugin, echo
    ``n_frames`` seeded frames one at a time (each answer checked) and count the link's
    instructions per frame. Raises McuError (no plugin, a wrong answer, a lost marker)."""
    elf = build_pil_firmware(out, opt=opt, insn_marks=True)
    frames = random_frames(n_frames, seed)
    link, log, api = boot_with_plugin(elf, out, out, start_timeout_s)
    with link:
        for msg in frames:
            link.send(msg)
            got = link.recv(ANSWER_TIMEOUT_S)
            want = echo_answer(msg)
            if (
                got is None
                or got.arbitration_id != want.arbitration_id
                or bytes(got.data) != bytes(want.data)
            ):
                raise McuError(f"echo of {msg} is {got}, expected {want}")
    marks = [int(ln.split()[1]) for ln in log.read_text().splitlines() if ln.startswith("M ")]
    host = [b"O\r", b"V\r", *(slcan_line(f) for f in frames)]
    per = frame_instructions(marks, host)
    by_dlc = {
        d: statistics.median(p for f, p in zip(frames, per, strict=True) if f.dlc == d)
        for d in sorted({f.dlc for f in frames})
    }
    return {
        "frames": n_frames,
        "opt": opt,
        "plugin_api": api,
        "insns_per_frame_median": statistics.median(per),
        "insns_per_frame_max": max(per),
        "insns_per_frame_min": min(per),
        "insns_per_frame_by_dlc": by_dlc,
        "flash_bytes": _text_size(elf),
    }


def _text_size(elf: Path) -> int:
    """Flash bytes of the linked image (text + rodata, Berkeley format)."""
    return int(_run([SIZE, elf]).splitlines()[1].split()[0])
