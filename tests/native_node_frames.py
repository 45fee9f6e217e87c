"""Build the node's C frame layer (controller/native/node) into a test-only cffi API-mode
module.

The DBC tables are generated into the build directory (``dbc_gen.frame_layer_sources``), the
sources compiled with the core's flags, and the cffi declarations are the frame layer's own
headers as the C preprocessor sees them (``module_ffi.build_module``, declarations by
``cdef_gen``): the compiler checks every field offset of the API-mode glue, and the integer
``RH_*`` macros of the headers are constants of ``lib``, so no declaration, layout or
constant is written twice.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from controller.native.module_ffi import build_module
from controller.native.node.dbc_gen import FRAME_MODULES, NODE_DIR, frame_layer_sources


@dataclass(frozen=True)
class FrameLayer:
    """The compiled frame layer: cffi's ``ffi`` and ``lib``, and message indices by name."""

    ffi: Any
    lib: Any
    message_index: dict[str, int]


def build_frame_layer(build_dir: Path, defines: tuple[str, ...] = ()) -> FrameLayer:
    """Generate, compile and load the frame layer in ``build_dir`` (``defines``: e.g.
    ("RH_FLOAT32",)); the module is cached by a hash of the sources, the headers of the node
    folder and of the generated folder, and the defines."""
    gen_dir = build_dir / "generated"
    module = build_module(
        frame_layer_sources(gen_dir),
        build_dir,
        defines=defines,
        headers=[f"{m}.h" for m in FRAME_MODULES],
        name="rhnode_frames",
        src_dir=NODE_DIR,
        include_dirs=[gen_dir],
    )
    ffi, lib = module.ffi, module.lib
    count = len(lib.rh_node_dbc_messages)
    names = {ffi.string(lib.rh_node_dbc_messages[i].name).decode(): i for i in range(count)}
    return FrameLayer(ffi, lib, names)
