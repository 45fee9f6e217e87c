"""The cffi declarations of the C core, generated from its headers at build time (setup.py).

Every struct, enum, typedef and function prototype the binding knows comes from
``include/rhonn_core.h`` and the headers it includes, as the C preprocessor sees them; every
integer ``RH_*`` macro becomes a cffi constant whose value the compiler fills (``#define X
...``). In cffi's API mode the compiler also checks every field offset, so no layout is
written twice. A field added to a C struct therefore reaches Python at the next build.

Two things are not spelled out, on purpose: OSQP's workspace (the generated ``rh_qpws.h``,
replaced while preprocessing by a stub, so a struct member of its type becomes cffi's
``...;``, its size and place fixed by the compiler) and OSQP's float type (``typedef
double... OSQPFloat``: the compiler decides). Static inline helpers are dropped (no body in
a cdef). This module is loaded by setup.py without the package (no package imports).
"""

from __future__ import annotations

import re
import subprocess
import tempfile
from pathlib import Path

HEADER = "rhonn_core.h"
# system headers the core's headers include: empty while preprocessing (cffi knows the types)
_SYSTEM = ("stdint.h", "stddef.h", "math.h", "float.h", "string.h", "stdlib.h")
_PYCPARSER_TYPES = ("int8_t", "int16_t", "int32_t", "int64_t", "uint8_t", "uint16_t",
                    "uint32_t", "uint64_t", "size_t", "uintptr_t", "intptr_t")
# OSQP's side of mpc_qp.h: an opaque workspace and OSQP's float type
_QPWS_STUB = "typedef double OSQPFloat;\ntypedef struct rh_qpws_opaque rh_qpws_t;\n"
_OPAQUE = ("rh_qpws_t",)
_FLOAT_TYPEDEFS = ("OSQPFloat",)
_PARTIAL = "__rh_cffi_partial__"


def _preprocess(include_dirs: list[Path], defines: list[str], cc: str, stubs: Path,
                extra: list[str]) -> str:
    cmd = [cc, "-E", "-nostdinc", "-std=c99", "-I", str(stubs),
           *(f"-I{d}" for d in include_dirs), *(f"-D{d}" for d in defines), *extra, "-"]
    r = subprocess.run(cmd, input=f'#include "{HEADER}"\n', capture_output=True, text=True,
                       check=False)
    if r.returncode != 0:
        raise RuntimeError(f"preprocessing {HEADER} failed: {r.stderr.strip()}")
    return r.stdout


def _stub_dir(tmp: Path) -> Path:
    stubs = tmp / "stubs"
    stubs.mkdir(parents=True, exist_ok=True)
    for name in _SYSTEM:
        (stubs / name).write_text("")
    (stubs / "rh_qpws.h").write_text(_QPWS_STUB)
    return stubs


def _declarations(text: str) -> str:
    """The declarations of the preprocessed headers as cdef text (pycparser round trip)."""
    from pycparser import c_ast, c_generator, c_parser

    prologue = "".join(f"typedef int {t};\n" for t in _PYCPARSER_TYPES)
    ast = c_parser.CParser().parse(prologue + text, filename=HEADER)
    gen = c_generator.CGenerator()
    out: list[str] = []
    n_pro = len(_PYCPARSER_TYPES)
    for node in ast.ext[n_pro:]:
        if isinstance(node, c_ast.FuncDef):   # static inline helpers: no body in a cdef
            continue
        if isinstance(node, c_ast.Typedef) and node.name in _OPAQUE + _FLOAT_TYPEDEFS:
            continue
        for struct in _structs(node):
            kept = []
            for d in struct.decls or []:
                if _type_name(d.type) in _OPAQUE:
                    kept.append(c_ast.Decl(_PARTIAL, [], [], [], [], c_ast.TypeDecl(
                        _PARTIAL, [], None, c_ast.IdentifierType(["int"])), None, None))
                else:
                    kept.append(d)
            struct.decls = kept
        out.append(gen.visit(node) + ";")
    body = "\n".join(out)
    body = re.sub(rf"int {_PARTIAL};", "...;", body)
    floats = "".join(f"typedef double... {t};\n" for t in _FLOAT_TYPEDEFS)
    return floats + body + "\n"


def _structs(node):
    """Struct and union definitions inside a declaration (nested ones included)."""
    from pycparser import c_ast

    found = []

    class V(c_ast.NodeVisitor):
        def visit_Struct(self, n):
            if n.decls is not None:
                found.append(n)
            self.generic_visit(n)

        def visit_Union(self, n):
            self.visit_Struct(n)

    V().visit(node)
    return found


def _type_name(t) -> str | None:
    while not hasattr(t, "names") and hasattr(t, "type"):
        t = t.type
    return " ".join(t.names) if hasattr(t, "names") else None


def _int_macros(include_dirs: list[Path], defines: list[str], cc: str, stubs: Path,
                extra: list[str]) -> list[str]:
    """Names of the object-like RH_* macros whose value is an integer expression."""
    text = _preprocess(include_dirs, defines, cc, stubs, ["-dM", *extra])
    macros = {}
    for line in text.splitlines():
        m = re.match(r"#define (RH_\w+) (.+)$", line)
        if m and not m.group(1).endswith("_H"):
            macros[m.group(1)] = m.group(2).strip()

    def is_int(value: str, depth: int = 0) -> bool:
        if depth > 20:
            return False
        expr = re.sub(r"\bRH_\w+\b", lambda k: "1" if k.group(0) in macros and is_int(
            macros[k.group(0)], depth + 1) else "x", value)
        return re.fullmatch(r"[\d\s()+\-*/]+", expr) is not None

    return sorted(n for n, v in macros.items() if is_int(v))


def generate(include_dirs: list[Path], defines: list[str] = (), cc: str = "cc",
             extra: list[str] = ()) -> str:
    """The cdef of rhonn_core.h for a build with these include folders and -D defines."""
    with tempfile.TemporaryDirectory() as tmp:
        stubs = _stub_dir(Path(tmp))
        text = _preprocess(list(include_dirs), list(defines), cc, stubs, ["-P", *extra])
        consts = _int_macros(list(include_dirs), list(defines), cc, stubs, list(extra))
    return _declarations(text) + "".join(f"#define {n} ...\n" for n in consts)


def emit_binding(module_name: str, include_dirs: list[Path], defines: list[str],
                 c_file: Path, cc: str = "cc") -> Path:
    """Write cffi's API-mode extension source of the core (``module_name``, e.g.
    ``controller.native._rhcore64``) to ``c_file``; the caller compiles and links it with the
    core's objects."""
    import cffi

    ffi = cffi.FFI()
    ffi.cdef(generate(include_dirs, defines, cc))
    ffi.set_source(module_name, f'#include "{HEADER}"\n')
    c_file.parent.mkdir(parents=True, exist_ok=True)
    ffi.emit_c_code(str(c_file))
    return c_file
