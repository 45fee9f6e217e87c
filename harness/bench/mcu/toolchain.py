"""The cross toolchain and QEMU: what is missing, their versions, running a tool."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

from harness.bench.mcu.case import McuError

APT_LINE = "apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
GCC, SIZE, NM, OBJDUMP, QEMU = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm",
                                "arm-none-eabi-objdump", "qemu-system-arm")
ARCH_FLAGS: tuple[str, ...] = ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard",
                               "-mfpu=fpv4-sp-d16")


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
