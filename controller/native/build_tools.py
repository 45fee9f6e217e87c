"""Compile C sources of the controller core into a shared library (tests, dev builds).

One place for the compiler flags of the core: C99, warnings as errors, no -ffast-math
(the numpy reference is the oracle, so IEEE semantics are kept). The install build
(setup.py) and the module back-to-back tests both use ``CFLAGS``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

NATIVE_DIR = Path(__file__).resolve().parent
SRC_DIR = NATIVE_DIR / "src"
CFLAGS: tuple[str, ...] = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2",
                           "-fno-fast-math", "-ffp-contract=off")


class NoCompilerError(RuntimeError):
    """No usable C compiler (the message says why)."""


def find_compiler() -> str:
    """``$CC`` or ``cc`` on PATH; NoCompilerError when absent."""
    cc = os.environ.get("CC") or "cc"
    path = shutil.which(cc)
    if path is None:
        raise NoCompilerError(f"no C compiler ({cc!r} not found)")
    return path


def compile_shared(sources: Sequence[str | Path], out_dir: str | Path,
                   defines: Sequence[str] = (), include_dirs: Sequence[str | Path] = (),
                   name: str = "rhcore_test") -> Path:
    """Compile ``sources`` (paths, or names relative to src/) into ``out_dir/name-<hash>.so``
    with CFLAGS + -fPIC -shared; cached by a hash of the sources, flags and defines.
    ``defines``: e.g. ("RH_FLOAT32",). Raises NoCompilerError or CalledProcessError."""
    cc = find_compiler()
    paths = [Path(s) if Path(s).is_absolute() else SRC_DIR / s for s in sources]
    h = hashlib.sha256()
    for p in paths:
        h.update(p.read_bytes())
    for hdr in sorted(SRC_DIR.glob("*.h")):
        h.update(hdr.read_bytes())
    h.update(" ".join((*CFLAGS, *defines, *map(str, include_dirs))).encode())
    out = Path(out_dir) / f"{name}-{h.hexdigest()[:16]}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [cc, *CFLAGS, "-fPIC", "-shared", f"-I{SRC_DIR}",
           *(f"-I{d}" for d in include_dirs), *(f"-D{d}" for d in defines),
           *map(str, paths), "-o", str(out) + ".tmp", "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"compile failed: {' '.join(cmd)}\n{res.stderr}")
    os.replace(str(out) + ".tmp", out)
    return out
