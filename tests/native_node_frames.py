"""Build the node's C frame layer (controller/native/node) into a test-only shared library
and open it with cffi in ABI mode.

The DBC tables are generated into the build directory (``dbc_gen.frame_layer_sources``), the
sources compiled with the core's flags (``build_tools.compile_shared``), and the cffi
declarations are the frame layer's own headers as the C preprocessor sees them (system
headers stubbed out: cffi knows the fixed-width types), so no declaration is written twice.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cffi

from controller.native.build_tools import compile_shared, find_compiler
from controller.native.node.dbc_gen import FRAME_MODULES, NODE_DIR, frame_layer_sources

_SYSTEM_HEADERS = ("stdint.h", "stddef.h", "string.h", "math.h")


@dataclass(frozen=True)
class FrameLayer:
    """The compiled frame layer: cffi's ``ffi`` and ``lib``, and message indices by name."""

    ffi: Any
    lib: Any
    message_index: dict[str, int]


def _declarations(build_dir: Path, include_dirs: list[Path], defines: tuple[str, ...]) -> str:
    stubs = build_dir / "stubs"
    stubs.mkdir(parents=True, exist_ok=True)
    for name in _SYSTEM_HEADERS:
        (stubs / name).write_text("")
    source = "".join(f'#include "{m}.h"\n' for m in FRAME_MODULES)
    cmd = [
        find_compiler(),
        "-E",
        "-P",
        "-nostdinc",
        "-std=c99",
        f"-I{stubs}",
        *(f"-I{d}" for d in include_dirs),
        *(f"-D{d}" for d in defines),
        "-",
    ]
    res = subprocess.run(cmd, input=source, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"preprocessing the frame layer's headers failed: {res.stderr}")
    return res.stdout


def build_frame_layer(build_dir: Path, defines: tuple[str, ...] = ()) -> FrameLayer:
    """Generate, compile and open the frame layer in ``build_dir`` (a fresh directory per
    build: the compile cache of build_tools hashes the core's headers, not these)."""
    gen_dir = build_dir / "generated"
    sources = frame_layer_sources(gen_dir)
    include_dirs = [NODE_DIR, gen_dir]
    so = compile_shared(
        sources, build_dir, defines=defines, include_dirs=include_dirs, name="rhnode_frames"
    )
    ffi = cffi.FFI()
    ffi.cdef(_declarations(build_dir, include_dirs, defines))
    lib = ffi.dlopen(str(so))
    count = int(ffi.sizeof(lib.rh_node_dbc_messages) // ffi.sizeof("rh_node_dbc_message_t"))
    names = {ffi.string(lib.rh_node_dbc_messages[i].name).decode(): i for i in range(count)}
    return FrameLayer(ffi, lib, names)
