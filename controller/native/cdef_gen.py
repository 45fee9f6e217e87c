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

import cffi

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
# the object-like integer macros of these name prefixes become cffi constants
MACRO_PREFIXES: tuple[str, ...] = ("RH_",)


def _preprocess(include_dirs: list[Path], defines: list[str], cc: str, stubs: Path,
                extra: list[str], headers: tuple[str, ...] = (HEADER,)) -> str:
    cmd = [cc, "-E", "-nostdinc", "-std=c99", "-I", str(stubs),
           *(f"-I{d}" for d in include_dirs), *(f"-D{d}" for d in defines), *extra, "-"]
    r = subprocess.run(cmd, input="".join(f'#include "{h}"\n' for h in headers),
                       capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"preprocessing {', '.join(headers)} failed: {r.stderr.strip()}")
    return r.stdout


def _stub_dir(tmp: Path) -> Path:
    stubs = tmp / "stubs"
    stubs.mkdir(parents=True, exist_ok=True)
    for name in _SYSTEM:
        (stubs / name).write_text("")
    (stubs / "rh_qpws.h").write_text(_QPWS_STUB)
    return stubs


def _declarations(text: str, functions: frozenset[str] | None = None) -> str:
    """The declarations of the preprocessed headers as cdef text (pycparser round trip);
    ``functions``: the prototypes to keep (None: all)."""
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
        if (functions is not None and isinstance(node, c_ast.Decl)
                and isinstance(node.type, c_ast.FuncDecl) and node.name not in functions):
            continue   # declared in a header, defined in a module not compiled in
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
    floats = "".join(f"typedef double... {t};\n" for t in _FLOAT_TYPEDEFS
                     if re.search(rf"\b{t}\b", text))   # only where OSQP's header is in
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
                extra: list[str], headers: tuple[str, ...] = (HEADER,),
                prefixes: tuple[str, ...] = MACRO_PREFIXES) -> list[str]:
    """Names of the object-like macros of these name prefixes whose value is an integer
    expression (decimal or hex literals, with or without a u/l suffix)."""
    text = _preprocess(include_dirs, defines, cc, stubs, ["-dM", *extra], headers)
    name = "(?:" + "|".join(re.escape(p) for p in prefixes) + r")\w+"
    macros = {}
    for line in text.splitlines():
        m = re.match(rf"#define ({name}) (.+)$", line)
        if m and not m.group(1).endswith("_H"):
            macros[m.group(1)] = m.group(2).strip()

    def is_int(value: str, depth: int = 0) -> bool:
        if depth > 20:
            return False
        expr = re.sub(rf"\b{name}\b", lambda k: "1" if k.group(0) in macros and is_int(
            macros[k.group(0)], depth + 1) else "x", value)
        expr = re.sub(r"\b(?:0[xX][0-9a-fA-F]+|\d+)[uUlL]*\b", "1", expr)
        return re.fullmatch(r"[\d\s()+\-*/]+", expr) is not None

    return sorted(n for n, v in macros.items() if is_int(v))


def _parse(include_dirs: list[Path], defines: list[str], cc: str, extra: list[str],
           headers: tuple[str, ...] = (HEADER,),
           prefixes: tuple[str, ...] = MACRO_PREFIXES) -> tuple[str, list[str]]:
    """The preprocessed headers and the names of their integer macros (``prefixes``)."""
    with tempfile.TemporaryDirectory() as tmp:
        stubs = _stub_dir(Path(tmp))
        text = _preprocess(list(include_dirs), list(defines), cc, stubs, ["-P", *extra],
                           tuple(headers))
        consts = _int_macros(list(include_dirs), list(defines), cc, stubs, list(extra),
                             tuple(headers), tuple(prefixes))
    return text, consts


def generate(include_dirs: list[Path], defines: list[str] = (), cc: str = "cc",
             extra: list[str] = (), headers: tuple[str, ...] = (HEADER,),
             functions: frozenset[str] | None = None,
             macro_prefixes: tuple[str, ...] = MACRO_PREFIXES) -> str:
    """The cdef of ``headers`` (default rhonn_core.h, the whole core) for a build with these
    include folders and -D defines; ``functions``: the prototypes to keep (None: all; a
    build of some modules keeps those its objects define); ``macro_prefixes``: the name
    prefixes of the integer macros declared as constants."""
    text, consts = _parse(include_dirs, defines, cc, extra, headers, tuple(macro_prefixes))
    return _declarations(text, functions) + "".join(f"#define {n} ...\n" for n in consts)


# --- the step's own path: ControllerInputs -> rh_inputs_t, rh_outputs_t -> ControllerOutputs
#
# cffi cannot take a Python object as a C argument, and a step written in Python on cffi
# structs costs microseconds (a field at a time); so the binding adds one function type
# generated from the same headers: Stepper(outputs), which holds one rh_ctrl_t (exposed
# through the buffer protocol: ``ffi.from_buffer("rh_ctrl_t *", stepper)``), with
# step(inputs) and allocate_only(inputs), each one C call. The attribute names are the
# C field names of rh_inputs_t and rh_outputs_t, in the header's order, read here from the
# parsed headers: a real_t field is a float attribute (NaN when missing or not a number), an
# int field a flag (its truth value, 0 when unreadable), a real_t array a float64 array or
# sequence of that length (zeros when unusable; the int field ``<array>_usable``, when the
# struct has one, says whether it was read). On the way out a real_t field becomes a float,
# an int field a bool or an int as the outputs object's attribute is when bound, a real_t
# array is copied into the outputs object's float64 array; a field the outputs object lacks
# stays in C only (readable through cffi).
_IN, _OUT = "rh_inputs_t", "rh_outputs_t"
_REAL = "real_t"


def struct_fields(text: str, typedef: str) -> list[tuple[str, str, bool]]:
    """(name, C type name, is an array) of each field of ``typedef`` in preprocessed text."""
    from pycparser import c_ast, c_parser

    prologue = "".join(f"typedef int {t};\n" for t in _PYCPARSER_TYPES)
    ast = c_parser.CParser().parse(prologue + text, filename=HEADER)
    for node in ast.ext:
        if isinstance(node, c_ast.Typedef) and node.name == typedef:
            out = []
            for d in node.type.type.decls:
                arr = isinstance(d.type, c_ast.ArrayDecl)
                out.append((d.name, _type_name(d.type), arr))
            return out
    raise RuntimeError(f"{typedef} not found in {HEADER}")


def _step_code(fin: list[tuple[str, str, bool]], fout: list[tuple[str, str, bool]]) -> str:
    """The generated C of the step path (see above) for these field lists."""
    arrays_in = {n for n, t, a in fin if a}
    usable = {f"{n}_usable": n for n in arrays_in}
    for name, t, arr in fin + fout:
        if t not in (_REAL, "int") or (arr and t != _REAL):
            raise RuntimeError(f"{name}: a step field must be real_t, real_t[] or int ({t})")
    in_attrs = [n for n, _, _ in fin if n not in usable]
    attrs = in_attrs + [n for n, _, _ in fout]
    k = {("in", n): i for i, n in enumerate(in_attrs)}
    k.update({("out", n): len(in_attrs) + i for i, (n, _, _) in enumerate(fout)})
    n_in_arr = max(1, sum(1 for _, _, a in fin if a))
    n_out_arr = max(1, sum(1 for _, _, a in fout if a))
    lines = [f"#define RH_PY_NATTR {len(attrs)}",
             f"#define RH_PY_IN_FIRST 0\n#define RH_PY_IN_LAST {len(in_attrs) - 1}",
             f"#define RH_PY_OUT_FIRST {len(in_attrs)}\n#define RH_PY_OUT_LAST {len(attrs) - 1}",
             f"#define RH_PY_IN_ARRAYS {n_in_arr}\n#define RH_PY_OUT_ARRAYS {n_out_arr}",
             "static const char *const rh_py_attr_names[RH_PY_NATTR] = {",
             *(f'  "{n}",' for n in attrs), "};", _STEP_RUNTIME]
    # inputs
    body = ["static void rh_py_read_inputs(rh_py_stepper_t *s, PyObject *obj, rh_inputs_t *in) {",
            "  const rh_py_slots_t *m = &s->in_map;",
            "  if (Py_TYPE(obj) != m->type)",
            "    rh_py_map_slots(&s->in_map, Py_TYPE(obj), RH_PY_IN_FIRST, RH_PY_IN_LAST);"]
    j = 0
    for name, t, arr in fin:
        if name in usable:
            continue
        i = k[("in", name)]
        if arr:
            call = (f"rh_py_read_array(s, {j}, obj, {i}, in->{name}, "
                    f"(Py_ssize_t)(sizeof in->{name} / sizeof in->{name}[0]))")
            j += 1
            flag = f"{name}_usable"
            body.append(f"  in->{flag} = {call};" if flag in usable
                        else f"  (void){call};")
        elif t == _REAL:
            body.append(f"  in->{name} = (real_t)rh_py_read_float(m, obj, {i});")
        else:
            body.append(f"  in->{name} = rh_py_read_flag(m, obj, {i});")
    body.append("}")
    # outputs
    body += ["static int rh_py_bind_outputs(rh_py_stepper_t *s, PyObject *o) {",
             "  rh_outputs_t *out = NULL;",
             "  (void)out;",
             "  rh_py_map_slots(&s->out_map, Py_TYPE(o), RH_PY_OUT_FIRST, RH_PY_OUT_LAST);"]
    j = 0
    for name, _t, arr in fout:
        i = k[("out", name)]
        if arr:
            body.append(f"  if (rh_py_bind_array(s, {j}, o, {i}, "
                        f"(Py_ssize_t)(sizeof out->{name} / sizeof out->{name}[0])) < 0) "
                        "return -1;")
            j += 1
        else:
            body.append(f"  rh_py_bind_scalar(s, o, {i});")
    body += ["  return 0;", "}",
             "static PyObject *rh_py_write_outputs(rh_py_stepper_t *s, const rh_outputs_t *out) {"]
    j = 0
    for name, t, arr in fout:
        i = k[("out", name)]
        if arr:
            body.append(f"  rh_py_put_array(s, {j}, out->{name}, "
                        f"(Py_ssize_t)(sizeof out->{name} / sizeof out->{name}[0]));")
            j += 1
        elif t == _REAL:
            body.append(f"  if (rh_py_put_float(s, {i}, (double)out->{name}) < 0) return NULL;")
        else:
            body.append(f"  if (rh_py_put_int(s, {i}, (long)out->{name}) < 0) return NULL;")
    body += ["  Py_INCREF(s->outputs);", "  return s->outputs;", "}"]
    return "\n".join(lines + body) + "\n" + _STEP_TYPE


def step_source(include_dirs: list[Path], defines: list[str] = (), cc: str = "cc",
                extra: list[str] = ()) -> str:
    """The generated C of the step path for a build with these include folders/defines."""
    text, _ = _parse(include_dirs, defines, cc, extra)
    return _step_code(struct_fields(text, _IN), struct_fields(text, _OUT))


def emit_binding(module_name: str, include_dirs: list[Path], defines: list[str],
                 c_file: Path, cc: str = "cc") -> Path:
    """Write cffi's API-mode extension source of the core (``module_name``, e.g.
    ``controller.native._rhcore64``) with the step path (``Stepper``) to ``c_file``; the
    caller compiles and links it with the core's objects."""
    ffi = cffi.FFI()
    ffi.cdef(generate(include_dirs, defines, cc))
    init = "PyInit_" + module_name.rsplit(".", 1)[-1]
    # cffi's module init is renamed and wrapped: the wrapper adds Stepper to the module
    source = (f'#include "{HEADER}"\n#define {init} rh_py_cffi_init\n'
              + step_source(include_dirs, defines, cc))
    ffi.set_source(module_name, source)
    c_file.parent.mkdir(parents=True, exist_ok=True)
    ffi.emit_c_code(str(c_file))
    text = c_file.read_text()
    # the step path reads __slots__ descriptors: the full C API, not the limited one
    c_file.write_text("#define _CFFI_NO_LIMITED_API\n" + text + _INIT.replace("@INIT@", init))
    return c_file


_INIT = r"""
#undef @INIT@
PyMODINIT_FUNC @INIT@(void) {
  PyObject *m = rh_py_cffi_init();
  if (m != NULL && rh_py_add_to_module(m) < 0) Py_CLEAR(m);
  return m;
}
"""

# The field-independent part of the step path (attribute access, conversions, the type).
_STEP_RUNTIME = r"""
#include <structmember.h>
#include <string.h>

static PyObject *rh_py_attr[RH_PY_NATTR];
#if defined(__GNUC__)
#define RH_PY_HOT static inline __attribute__((always_inline))
#else
#define RH_PY_HOT static inline
#endif
#define RH_PY_ABSENT (-2) /* an outputs attribute that does not exist: the field stays in C */

/* Slot offsets of a __slots__ class's attributes (ControllerInputs / ControllerOutputs are
 * slotted dataclasses): reading and writing those slots directly skips the attribute
 * lookup; any other type goes through getattr/setattr. off[k] == -1: not a plain slot. */
typedef struct {
  PyTypeObject *type;
  Py_ssize_t off[RH_PY_NATTR];
} rh_py_slots_t;

typedef struct {
  PyObject_HEAD
  rh_py_slots_t in_map;     /* slots of the last inputs type seen */
  rh_py_slots_t out_map;    /* slots of the outputs type */
  PyObject *in_arr[RH_PY_IN_ARRAYS];   /* the last input arrays read (buffers held) */
  Py_buffer in_buf[RH_PY_IN_ARRAYS];
  PyObject *outputs;        /* the object step() fills */
  Py_buffer out_buf[RH_PY_OUT_ARRAYS]; /* its float64 arrays (buf NULL: absent) */
  char out_bool[RH_PY_NATTR];          /* an int field written as a bool */
  rh_ctrl_t ctrl;           /* the state (zeroed; rh_ctrl_init through cffi) */
} rh_py_stepper_t;

static void rh_py_map_slots(rh_py_slots_t *m, PyTypeObject *type, int first, int last) {
  int k;
  Py_INCREF(type); /* held: a freed type's address must not match a later one */
  Py_XSETREF(m->type, type);
  for (k = 0; k < RH_PY_NATTR; k++) m->off[k] = -1;
  for (k = first; k <= last; k++) {
    PyObject *d = PyObject_GetAttr((PyObject *)type, rh_py_attr[k]);
    if (d == NULL) {
      PyErr_Clear();
      continue;
    }
    if (Py_IS_TYPE(d, &PyMemberDescr_Type)) {
      PyMemberDef *md = ((PyMemberDescrObject *)d)->d_member;
      if (md->type == T_OBJECT_EX && !(md->flags & READONLY)) m->off[k] = md->offset;
    }
    Py_DECREF(d);
  }
}

/* New reference to attribute k of obj, or NULL (no error set) when it is missing. */
RH_PY_HOT PyObject *rh_py_get(const rh_py_slots_t *m, PyObject *obj, int k) {
  PyObject *v;
  if (Py_TYPE(obj) == m->type && m->off[k] >= 0) {
    v = *(PyObject **)((char *)obj + m->off[k]);
    Py_XINCREF(v);
    return v;
  }
  v = PyObject_GetAttr(obj, rh_py_attr[k]);
  if (v == NULL) PyErr_Clear();
  return v;
}

/* Set attribute k of obj to v (steals the reference); -1 on error. */
RH_PY_HOT int rh_py_set(const rh_py_slots_t *m, PyObject *obj, int k, PyObject *v) {
  int rc;
  if (v == NULL) return -1;
  if (m->off[k] >= 0) { /* the outputs map is of the outputs object's own type */
    Py_XSETREF(*(PyObject **)((char *)obj + m->off[k]), v);
    return 0;
  }
  rc = PyObject_SetAttr(obj, rh_py_attr[k], v);
  Py_DECREF(v);
  return rc;
}

static double rh_py_read_float(const rh_py_slots_t *m, PyObject *obj, int k) {
  PyObject *v = rh_py_get(m, obj, k);
  double d;
  if (v == NULL) return (double)NAN;
  if (PyFloat_CheckExact(v)) {
    d = PyFloat_AS_DOUBLE(v);
  } else {
    d = PyFloat_AsDouble(v);
    if (d == -1.0 && PyErr_Occurred()) {
      PyErr_Clear();
      d = (double)NAN;
    }
  }
  Py_DECREF(v);
  return d;
}

static int rh_py_read_flag(const rh_py_slots_t *m, PyObject *obj, int k) {
  PyObject *v = rh_py_get(m, obj, k);
  int b;
  if (v == NULL) return 0;
  b = v == Py_True ? 1 : (v == Py_False ? 0 : PyObject_IsTrue(v));
  Py_DECREF(v);
  if (b < 0) {
    PyErr_Clear();
    return 0;
  }
  return b;
}

static void rh_py_release_in(rh_py_stepper_t *s, int j) {
  if (s->in_arr[j] != NULL) {
    PyBuffer_Release(&s->in_buf[j]);
    s->in_arr[j] = NULL;
  }
}

/* n numbers from a float64 buffer or any sequence of n numbers; 1 if read, else 0 and
 * zeros. The caller writes its array in place, so the buffer of the last array is kept (a
 * held buffer also stops numpy from resizing it) and re-read while the attribute is the
 * same object. */
static int rh_py_read_array(rh_py_stepper_t *s, int j, PyObject *obj, int k, real_t *dst,
                            Py_ssize_t n) {
  PyObject *v = rh_py_get(&s->in_map, obj, k);
  int ok = 0;
  Py_ssize_t i;
  if (v == NULL) goto done;
  if (v != s->in_arr[j]) {
    rh_py_release_in(s, j);
    if (PyObject_CheckBuffer(v) &&
        PyObject_GetBuffer(v, &s->in_buf[j], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) == 0) {
      if (s->in_buf[j].format && strcmp(s->in_buf[j].format, "d") == 0 &&
          s->in_buf[j].len == n * (Py_ssize_t)sizeof(double))
        s->in_arr[j] = v; /* held through in_buf[j].obj */
      else
        PyBuffer_Release(&s->in_buf[j]);
    } else {
      PyErr_Clear();
    }
  }
  if (v == s->in_arr[j]) {
    const double *d = (const double *)s->in_buf[j].buf;
    for (i = 0; i < n; i++) dst[i] = (real_t)d[i];
    ok = 1;
  } else {
    PyObject *seq = PySequence_Fast(v, "");
    if (seq != NULL && PySequence_Fast_GET_SIZE(seq) == n) {
      ok = 1;
      for (i = 0; i < n; i++) {
        double d = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(seq, i));
        if (d == -1.0 && PyErr_Occurred()) {
          ok = 0;
          break;
        }
        dst[i] = (real_t)d;
      }
    }
    Py_XDECREF(seq);
    PyErr_Clear();
  }
  Py_DECREF(v);
done:
  if (!ok)
    for (i = 0; i < n; i++) dst[i] = (real_t)0.0;
  return ok;
}

static void rh_py_bind_scalar(rh_py_stepper_t *s, PyObject *o, int k) {
  PyObject *v = PyObject_GetAttr(o, rh_py_attr[k]);
  if (v == NULL) {
    PyErr_Clear();
    s->out_map.off[k] = RH_PY_ABSENT;
    return;
  }
  s->out_bool[k] = (char)PyBool_Check(v);
  Py_DECREF(v);
}

static int rh_py_bind_array(rh_py_stepper_t *s, int j, PyObject *o, int k, Py_ssize_t n) {
  Py_buffer *b = &s->out_buf[j];
  PyObject *a = PyObject_GetAttr(o, rh_py_attr[k]);
  int rc;
  if (a == NULL) { /* absent: the field stays in C */
    PyErr_Clear();
    s->out_map.off[k] = RH_PY_ABSENT;
    return 0;
  }
  rc = PyObject_GetBuffer(a, b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE);
  Py_DECREF(a);
  if (rc < 0) {
    b->buf = NULL;
    return -1;
  }
  if (b->format == NULL || strcmp(b->format, "d") != 0 ||
      b->len != n * (Py_ssize_t)sizeof(double)) {
    PyBuffer_Release(b);
    b->buf = NULL;
    PyErr_Format(PyExc_TypeError, "outputs.%U must be a writable float64 array of %zd",
                 rh_py_attr[k], n);
    return -1;
  }
  return 0;
}

RH_PY_HOT void rh_py_put_array(rh_py_stepper_t *s, int j, const real_t *src, Py_ssize_t n) {
  double *d = (double *)s->out_buf[j].buf;
  Py_ssize_t i;
  if (d != NULL)
    for (i = 0; i < n; i++) d[i] = (double)src[i];
}

RH_PY_HOT int rh_py_put_float(rh_py_stepper_t *s, int k, double x) {
  if (s->out_map.off[k] == RH_PY_ABSENT) return 0;
  return rh_py_set(&s->out_map, s->outputs, k, PyFloat_FromDouble(x));
}

RH_PY_HOT int rh_py_put_int(rh_py_stepper_t *s, int k, long x) {
  if (s->out_map.off[k] == RH_PY_ABSENT) return 0;
  return rh_py_set(&s->out_map, s->outputs, k,
                   s->out_bool[k] ? Py_NewRef(x ? Py_True : Py_False) : PyLong_FromLong(x));
}
"""

_STEP_TYPE = r"""
static PyTypeObject rh_py_stepper_type;

static void rh_py_stepper_dealloc(rh_py_stepper_t *s) {
  int j;
  for (j = 0; j < RH_PY_IN_ARRAYS; j++) rh_py_release_in(s, j);
  for (j = 0; j < RH_PY_OUT_ARRAYS; j++)
    if (s->out_buf[j].buf != NULL) {
      PyBuffer_Release(&s->out_buf[j]);
      s->out_buf[j].buf = NULL;
    }
  Py_CLEAR(s->in_map.type);
  Py_CLEAR(s->out_map.type);
  Py_CLEAR(s->outputs);
  Py_TYPE(s)->tp_free((PyObject *)s);
}

/* Stepper(outputs): a zeroed rh_ctrl_t (to be initialised through cffi) and the object
 * step() fills and returns. */
static PyObject *rh_py_stepper_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
  rh_py_stepper_t *s;
  PyObject *outputs;
  static char *kwlist[] = {"outputs", NULL};
  if (!PyArg_ParseTupleAndKeywords(args, kwds, "O", kwlist, &outputs)) return NULL;
  s = (rh_py_stepper_t *)type->tp_alloc(type, 0);
  if (s == NULL) return NULL;
  s->outputs = Py_NewRef(outputs);
  if (rh_py_bind_outputs(s, outputs) < 0) {
    Py_DECREF(s);
    return NULL;
  }
  return (PyObject *)s;
}

/* The state's bytes (read/write), for cffi's from_buffer. */
static int rh_py_stepper_getbuffer(rh_py_stepper_t *s, Py_buffer *view, int flags) {
  return PyBuffer_FillInfo(view, (PyObject *)s, &s->ctrl, (Py_ssize_t)sizeof(rh_ctrl_t), 0,
                           flags);
}

static PyBufferProcs rh_py_stepper_buffer = {(getbufferproc)rh_py_stepper_getbuffer, NULL};

static PyObject *rh_py_stepper_step(rh_py_stepper_t *s, PyObject *inputs) {
  rh_inputs_t in;
  rh_outputs_t out;
  rh_py_read_inputs(s, inputs, &in);
  rh_ctrl_step(&s->ctrl, &in, &out);
  return rh_py_write_outputs(s, &out);
}

static PyObject *rh_py_stepper_allocate_only(rh_py_stepper_t *s, PyObject *inputs) {
  rh_inputs_t in;
  rh_outputs_t out;
  rh_py_read_inputs(s, inputs, &in);
  rh_ctrl_allocate_only(&s->ctrl, &in, &out);
  return rh_py_write_outputs(s, &out);
}

static PyMethodDef rh_py_stepper_methods[] = {
    {"step", (PyCFunction)rh_py_stepper_step, METH_O,
     "rh_ctrl_step from an inputs object; fills and returns the outputs object."},
    {"allocate_only", (PyCFunction)rh_py_stepper_allocate_only, METH_O,
     "rh_ctrl_allocate_only, as step."},
    {NULL, NULL, 0, NULL}};

static PyTypeObject rh_py_stepper_type = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "rhcore.Stepper",
    .tp_basicsize = sizeof(rh_py_stepper_t),
    .tp_dealloc = (destructor)rh_py_stepper_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Stepper(outputs): one rh_ctrl_t (buffer) and its step path: step(inputs), "
               "allocate_only(inputs).",
    .tp_methods = rh_py_stepper_methods,
    .tp_as_buffer = &rh_py_stepper_buffer,
    .tp_new = rh_py_stepper_new,
};

static int rh_py_add_to_module(PyObject *m) {
  int k;
  for (k = 0; k < RH_PY_NATTR; k++)
    if (rh_py_attr[k] == NULL &&
        (rh_py_attr[k] = PyUnicode_InternFromString(rh_py_attr_names[k])) == NULL)
      return -1;
  if (PyType_Ready(&rh_py_stepper_type) < 0) return -1;
  Py_INCREF(&rh_py_stepper_type);
  if (PyModule_AddObject(m, "Stepper", (PyObject *)&rh_py_stepper_type) < 0) {
    Py_DECREF(&rh_py_stepper_type);
    return -1;
  }
  return 0;
}
"""
