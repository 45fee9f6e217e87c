"""OSQP's generated solver, once per QP shape, as instance memory of the C core.

``OSQP.codegen`` (embedded mode 2: q, l, u and the values of P may change every step)
writes a problem's workspace as C globals. The core keeps one workspace per controller,
inside the controller's state struct, so this module turns each generated
``<prefix>workspace.c`` into

* a struct type ``rh_qpws_<tag>_t`` whose members are the generated objects (same types,
  same sizes, prefix dropped), and
* ``rh_qpws_<tag>_init(w)``: fills the struct with the generated values; the pointers
  between the objects point into ``w`` (C99 allows non-constant initialisers for automatic
  aggregates, so every generated struct initialiser is kept verbatim with its references
  rewritten to ``w->``);
* ``rh_qpws_<tag>_copy(dst, src)``: a byte copy whose internal pointers are moved to
  ``dst`` (the pointer members are the words where a fresh initialiser of ``dst`` points
  into ``dst``; each is moved by ``dst − src``, wherever in ``src`` it points: OSQP swaps
  its iterate vectors at run time).

Shapes: horizon N = 1..``N_MAX`` with the box rows only, with the rate-limit rows (m = N or
2N), and with the rate and stable-handling envelope rows (n = N + 2, m = 6N + 2). The
QP is set up exactly as ``controller.core.mpc.qp.LinearizedMpc._setup`` sets up the Python
solver (P = upper triangle of ones, q = 0, A = I or [I; I − shift], l = −1, u = 1, the
default [mpc.osqp] settings), so the first solve starts from the same state.

Used by setup.py at install (into the build folder) and by the microcontroller build.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

N_MAX = 10
# OSQP settings the template is generated with (QpConfig's defaults). Settings that only
# steer the iteration (max_iter, eps_*, check_termination, warm_starting, alpha,
# adaptive_rho_*) and the number of Ruiz passes (scaling >= 1: the template has the scaling
# vectors, every data update equilibrates anew) may differ at run time: the core writes them
# into its workspace.
TEMPLATE_SETTINGS: dict[str, Any] = {
    "warm_starting": True, "polishing": False, "verbose": False, "max_iter": 200,
    "eps_abs": 1e-4, "eps_rel": 1e-4, "check_termination": 5, "adaptive_rho": 1,
    "adaptive_rho_interval": 25, "scaling": 4,
}
RUNTIME_SETTINGS = ("warm_starting", "polishing", "verbose", "max_iter", "eps_abs", "eps_rel",
                    "eps_prim_inf", "eps_dual_inf", "check_termination", "alpha",
                    "adaptive_rho_interval", "adaptive_rho_tolerance",
                    "adaptive_rho_fraction", "scaled_termination", "time_limit", "scaling")

_DECL = re.compile(r"^([A-Za-z_]\w*)\s+([A-Za-z_]\w*)(\[\d+\])?\s*(=\s*\{)?\s*;?\s*$")


BOX, RATE, ENVELOPE = 0, 1, 2   # QP shapes: box rows; + rate rows; + rate + envelope rows


def shape_tag(n: int, rate: int) -> str:
    """Tag of a QP shape: horizon n and its rows (BOX, RATE, ENVELOPE; e.g. "3n", "3r",
    "3e")."""
    return f"{n}{'nre'[int(rate)]}"


def shapes(n_max: int = N_MAX) -> list[tuple[int, int]]:
    """Every (N, shape) the install builds."""
    return [(n, rate) for n in range(1, n_max + 1) for rate in (BOX, RATE, ENVELOPE)]


def envelope_pattern(n: int) -> tuple[Any, Any]:
    """(P, A) patterns (ones) of the envelope shape, as controller/core/mpc/qp.py's
    envelope_pattern builds them (kept free of the controller package: setup.py runs this
    before the package is installed; tests/test_handling.py checks both are equal): P = the
    full upper triangle of the n ΔM decisions + the two slack diagonals; A = box I, rate
    [I − shift], 4n envelope rows dense in ΔM with −1/+1 on their slack, the slack rows."""
    iu = np.triu_indices(n)
    P = sp.csc_matrix((np.ones(len(iu[0]) + 2), (np.concatenate([iu[0], [n, n + 1]]),
                                                  np.concatenate([iu[1], [n, n + 1]]))),
                      shape=(n + 2, n + 2))
    mask = np.zeros((6 * n + 2, n + 2), dtype=bool)
    mask[:n, :n] = np.eye(n, dtype=bool)
    mask[n:2 * n, :n] = (np.eye(n) - np.eye(n, k=-1)) != 0
    mask[2 * n:6 * n, :n] = True
    mask[2 * n:4 * n, n] = True
    mask[4 * n:6 * n, n + 1] = True
    mask[6 * n, n] = mask[6 * n + 1, n + 1] = True
    rr, cc = np.nonzero(mask)
    return P, sp.csc_matrix((np.ones(len(rr)), (rr, cc)), shape=mask.shape)


def _problem(n: int, rate: int) -> tuple[Any, Any, Any, Any, Any]:
    if int(rate) == ENVELOPE:   # as LinearizedMpc._new_solver sets it up (mpc/qp.py)
        P, A = envelope_pattern(n)
        m = A.shape[0]
        return P, np.zeros(n + 2), A, -np.ones(m), np.ones(m)
    iu = np.triu_indices(n)
    order = np.lexsort((iu[0], iu[1]))
    P = sp.csc_matrix((np.ones(len(iu[0])), (iu[0][order], iu[1][order])), shape=(n, n))
    rows = [sp.eye(n, format="csc")]
    if rate:
        rows.append((sp.eye(n) - sp.eye(n, k=-1)).tocsc())
    A = sp.vstack(rows, format="csc")
    m = A.shape[0]
    return P, np.zeros(n), A, -np.ones(m), np.ones(m)


def _parse_workspace(text: str) -> list[tuple[str, str, str, str | None]]:
    """[(type, name, array suffix or "", initialiser body or None)] in file order."""
    out: list[tuple[str, str, str, str | None]] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        m = _DECL.match(line)
        if m is None or line.startswith(("#", "/*", " ")):
            i += 1
            continue
        typ, name, arr, has_init = m.group(1), m.group(2), m.group(3) or "", m.group(4)
        if has_init:
            body: list[str] = []
            i += 1
            while not lines[i].startswith("};"):
                body.append(lines[i])
                i += 1
            out.append((typ, name, arr, "\n".join(body)))
        else:
            out.append((typ, name, arr, None))
        i += 1
    return out


def transform_workspace(text: str, prefix: str, tag: str) -> tuple[str, str]:
    """(header, source) of the instance form of one generated workspace file."""
    decls = _parse_workspace(text)
    if not decls or decls[-1][1] != f"{prefix}solver":
        raise ValueError("unexpected workspace layout (no trailing solver object)")
    names = {d[1] for d in decls}
    ident = re.compile(r"\b(" + re.escape(prefix) + r"\w+)\b")

    def member(name: str) -> str:
        return name[len(prefix):]

    def rewrite(body: str, base: str) -> str:
        def sub(m: re.Match[str]) -> str:
            nm = m.group(1)
            if nm not in names:
                raise ValueError(f"reference to unknown object {nm}")
            return f"{base}->{member(nm)}"
        return ident.sub(sub, body)

    t = f"rh_qpws_{tag}_t"
    guard = f"RH_QPWS_{tag.upper()}_H"
    fields = "\n".join(f"  {typ} {member(name)}{arr};" for typ, name, arr, _ in decls)
    header = (f"/* OSQP workspace of QP shape {tag} as instance memory (generated by\n"
              f" * controller/native/osqp_gen.py from OSQP's codegen; do not edit). */\n"
              f"#ifndef {guard}\n#define {guard}\n\n"
              f'#include "types.h"\n#include "algebra_impl.h"\n#include "qdldl_interface.h"\n\n'
              f"typedef struct {{\n{fields}\n}} {t};\n\n"
              f"void rh_qpws_{tag}_init({t} *w);\n"
              f"void rh_qpws_{tag}_copy({t} *dst, const {t} *src);\n\n#endif\n")
    init_parts: list[str] = []
    copy_parts: list[str] = []
    for typ, name, arr, body in decls:
        mem = member(name)
        if body is None:
            continue
        if arr:
            if ident.search(body):
                raise ValueError(f"array {name} initialised with references")
            init_parts.append(f"  {{\n    static const {typ} v{arr} = {{\n{body}\n    }};\n"
                              f"    memcpy(w->{mem}, v, sizeof v);\n  }}")
        else:
            init_parts.append(f"  {{\n    const {typ} v = {{\n{rewrite(body, 'w')}\n    }};\n"
                              f"    w->{mem} = v;\n  }}")
            if ident.search(body):
                copy_parts.append(
                    f"  {{\n    const {typ} a = {{\n{rewrite(body, 'dst')}\n    }};\n"
                    f"    rh_qpws_relink(&dst->{mem}, &a, sizeof a, dst, src, sizeof *dst);\n  }}")
    source = (f"/* Generated by controller/native/osqp_gen.py from OSQP's codegen (shape {tag});\n"
              f" * do not edit. */\n#include <string.h>\n#include \"rh_qpws_{tag}.h\"\n"
              f'#include "rh_qpws_relink.h"\n\n'
              f"void rh_qpws_{tag}_init({t} *w) {{\n  memset(w, 0, sizeof *w);\n"
              + "\n".join(init_parts) + "\n}\n\n"
              f"void rh_qpws_{tag}_copy({t} *dst, const {t} *src) {{\n"
              f"  memcpy(dst, src, sizeof *dst);\n" + "\n".join(copy_parts) + "\n}\n")
    return header, source


RELINK_H = r"""/* Pointer relocation for copied OSQP workspaces (generated code calls it). */
#ifndef RH_QPWS_RELINK_H
#define RH_QPWS_RELINK_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

/* obj: a member of dst (already a byte copy of the same member of src); fresh: the same
 * member initialised for dst. A pointer-sized word where fresh points into dst is an internal
 * pointer member; it may point elsewhere in src than at init (OSQP swaps its iterate
 * vectors), so it is moved by the offset src -> dst wherever it points into src. */
static inline void rh_qpws_relink(void *obj, const void *fresh, size_t size, const void *dst,
                                  const void *src, size_t ws_size) {
  size_t k;
  for (k = 0; k + sizeof(uintptr_t) <= size; k += sizeof(uintptr_t)) {
    uintptr_t f, o;
    memcpy(&f, (const char *)fresh + k, sizeof f);
    memcpy(&o, (const char *)obj + k, sizeof o);
    if (f >= (uintptr_t)dst && f < (uintptr_t)dst + ws_size && o >= (uintptr_t)src &&
        o < (uintptr_t)src + ws_size) {
      uintptr_t moved = (uintptr_t)dst + (o - (uintptr_t)src);
      memcpy((char *)obj + k, &moved, sizeof moved);
    }
  }
}

#endif
"""


def _dispatch(tags: Iterable[str]) -> tuple[str, str]:
    """rh_qpws.h / rh_qpws.c: the union of every shape and init/copy/solver by shape."""
    tags = list(tags)
    inc = "\n".join(f'#include "rh_qpws_{t}.h"' for t in tags)
    members = "\n".join(f"  rh_qpws_{t}_t s{t};" for t in tags)
    header = ("/* Every generated OSQP workspace shape (controller/native/osqp_gen.py). */\n"
              "#ifndef RH_QPWS_H\n#define RH_QPWS_H\n\n" + inc + "\n\n"
              "typedef union {\n" + members + "\n} rh_qpws_t;\n\n"
              "/* Initialise the workspace of horizon n (rate: 0 box, 1 + rate rows, 2 + rate\n"
              " * and envelope rows); 0 on success, -1 when this build has no such shape. */\n"
              "int rh_qpws_init(rh_qpws_t *w, int n, int rate);\n"
              "/* The OSQP solver object inside w for shape (n, rate) (NULL if absent). */\n"
              "OSQPSolver *rh_qpws_solver(rh_qpws_t *w, int n, int rate);\n"
              "void rh_qpws_copy(rh_qpws_t *dst, const rh_qpws_t *src, int n, int rate);\n"
              "#endif\n")
    cases_init, cases_solver, cases_copy = [], [], []
    for t in tags:
        n, r = int(t[:-1]), "nre".index(t[-1])
        key = f"{n * 3 + r}"
        cases_init.append(f"    case {key}: rh_qpws_{t}_init(&w->s{t}); return 0;")
        cases_solver.append(f"    case {key}: return &w->s{t}.solver;")
        cases_copy.append(f"    case {key}: rh_qpws_{t}_copy(&dst->s{t}, &src->s{t}); return;")
    source = ("/* Generated by controller/native/osqp_gen.py; do not edit. */\n"
              '#include "rh_qpws.h"\n\n'
              "int rh_qpws_init(rh_qpws_t *w, int n, int rate) {\n"
              "  switch (n * 3 + rate) {\n" + "\n".join(cases_init) +
              "\n    default: return -1;\n  }\n}\n\n"
              "OSQPSolver *rh_qpws_solver(rh_qpws_t *w, int n, int rate) {\n"
              "  switch (n * 3 + rate) {\n" + "\n".join(cases_solver) +
              "\n    default: return 0;\n  }\n}\n\n"
              "void rh_qpws_copy(rh_qpws_t *dst, const rh_qpws_t *src, int n, int rate) {\n"
              "  switch (n * 3 + rate) {\n" + "\n".join(cases_copy) +
              "\n    default: return;\n  }\n}\n")
    return header, source


def generate(out_dir: str | Path, shape_list: Iterable[tuple[int, bool]] | None = None,
             settings: dict[str, Any] | None = None) -> Path:
    """Generate OSQP's sources and the instance workspaces of ``shape_list`` into
    ``out_dir`` (``src/``, ``inc/``, ``osqp_configure.h``, ``rh_qpws*.{c,h}``). Returns
    out_dir. Needs the ``osqp`` Python package (a build requirement)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shape_list = list(shape_list or shapes())
    st = dict(TEMPLATE_SETTINGS if settings is None else settings)
    tags = []
    with tempfile.TemporaryDirectory(prefix="rhonn-osqpgen-") as tmp:
        for k, (n, rate) in enumerate(shape_list):
            tag = shape_tag(n, rate)
            prefix = f"rhq{tag}_"
            gen = Path(tmp) / tag
            solver = osqp.OSQP()
            solver.setup(*_problem(n, rate), **st)
            solver.codegen(str(gen), parameters="matrices", prefix=prefix, compile=False,
                           force_rewrite=True)
            if k == 0:
                for sub in ("src", "inc"):
                    shutil.rmtree(out / sub, ignore_errors=True)
                    shutil.copytree(gen / sub, out / sub)
                shutil.copy(gen / "osqp_configure.h", out / "osqp_configure.h")
            text = (gen / f"{prefix}workspace.c").read_text()
            header, source = transform_workspace(text, prefix, tag)
            (out / f"rh_qpws_{tag}.h").write_text(header)
            (out / f"rh_qpws_{tag}.c").write_text(source)
            tags.append(tag)
    (out / "rh_qpws_relink.h").write_text(RELINK_H)
    header, source = _dispatch(tags)
    (out / "rh_qpws.h").write_text(header)
    (out / "rh_qpws.c").write_text(source)
    return out


def osqp_sources(gen_dir: str | Path) -> list[Path]:
    """C files to compile from a generate() folder (OSQP's and the workspaces)."""
    g = Path(gen_dir)
    return sorted(g.glob("src/*.c")) + sorted(g.glob("rh_qpws*.c"))


def osqp_include_dirs(gen_dir: str | Path) -> list[Path]:
    """Include folders of a generate() folder."""
    g = Path(gen_dir)
    return [g, g / "inc" / "public", g / "inc" / "private"]
