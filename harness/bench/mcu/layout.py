"""The flat float32 vectors in which the MCU harness carries a C struct (``rh_inputs_t`` in,
``rh_outputs_t`` out, include/rhonn_core.h), laid out from the header itself.

The header is parsed as the MCU build sees it (cdef_gen: the C preprocessor with
-DRH_FLOAT32 and the case's defines, then cffi's parser), and every field takes the next
slots of the vector in the header's order: one for a scalar, one per element for an array;
an int field is carried as a float value. From that one parse come the C functions the case
adapter calls (:meth:`FlatLayout.c_unpack`, :meth:`FlatLayout.c_pack`, generated into
mcu_case_config.h) and the Python side (:meth:`FlatLayout.pack`, :meth:`FlatLayout.unpack`,
the column names and the int columns): no index is written by hand, and a field added to the
struct becomes a column at the next build.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cffi
import numpy as np

from controller.native import cdef_gen
from controller.native.build_tools import NATIVE_DIR, find_compiler

_INTS = ("int", "int64_t", "int32_t", "unsigned int", "long")


@dataclasses.dataclass(frozen=True)
class Field:
    """One field of the struct: C name, number of values (1: a scalar), int (else real_t),
    and the index of its first value in the flat vector."""

    name: str
    length: int
    is_int: bool
    first: int
    is_array: bool


@dataclasses.dataclass(frozen=True)
class FlatLayout:
    """The flat vector of the C struct ``ctype`` (see the module docstring)."""

    ctype: str
    fields: tuple[Field, ...]

    @property
    def size(self) -> int:
        """Number of float values."""
        return sum(f.length for f in self.fields)

    @property
    def names(self) -> tuple[str, ...]:
        """Column names: the field name, ``name[i]`` for an array's elements."""
        return tuple(n for f in self.fields
                     for n in ([f"{f.name}[{i}]" for i in range(f.length)] if f.is_array
                               else [f.name]))

    @property
    def int_columns(self) -> tuple[int, ...]:
        """Columns of the int fields (counts and flags)."""
        return tuple(f.first + i for f in self.fields if f.is_int for i in range(f.length))

    def pack(self, obj: Any) -> list[float]:
        """The vector of ``obj``, an object with the fields as attributes (e.g.
        ControllerInputs / ControllerOutputs), read as the core's step path reads them
        (cdef_gen's Stepper): a real field missing → NaN, an int one → 0; an array → its
        values (zeros when missing or of another length), with ``<array>_usable`` → 1 when
        the array was read, else 0."""
        out = [0.0] * self.size
        usable: dict[str, float] = {}
        for f in self.fields:
            if f.is_array:
                v = np.asarray(getattr(obj, f.name, ()), dtype=float).ravel()
                ok = v.size == f.length
                usable[f"{f.name}_usable"] = 1.0 if ok else 0.0
                out[f.first:f.first + f.length] = v.tolist() if ok else [0.0] * f.length
        for f in self.fields:
            if f.is_array:
                continue
            if f.name in usable:
                out[f.first] = usable[f.name]
            elif f.is_int:
                out[f.first] = float(int(getattr(obj, f.name, 0)))
            else:
                out[f.first] = float(getattr(obj, f.name, math.nan))
        return out

    def unpack(self, row: Sequence[float]) -> dict[str, Any]:
        """{field name: value} of a vector: a float, an int, or a float64 array."""
        out: dict[str, Any] = {}
        for f in self.fields:
            vals = [float(v) for v in row[f.first:f.first + f.length]]
            if f.is_array:
                out[f.name] = np.array(vals)
            else:
                out[f.name] = int(vals[0]) if f.is_int else vals[0]
        return out

    def _c_function(self, head: str, statement: Any) -> str:
        lines = [head + " {"]
        if any(f.is_array for f in self.fields):
            lines.append("  int j;")
        for f in self.fields:
            if f.is_array:
                lines.append(f"  for (j = 0; j < {f.length}; j++) "
                             + statement(f, f"[{f.first} + j]", "[j]"))
            else:
                lines.append("  " + statement(f, f"[{f.first}]", ""))
        return "\n".join([*lines, "}"]) + "\n"

    def c_unpack(self, fn: str) -> str:
        """C99 ``static void fn(const float v[], <ctype> *s)``: the struct from its vector."""
        return self._c_function(
            f"static void {fn}(const float v[{self.size}], {self.ctype} *s)",
            lambda f, at, idx: f"s->{f.name}{idx} = {'(int)' if f.is_int else ''}v{at};")

    def c_pack(self, fn: str) -> str:
        """C99 ``static void fn(const <ctype> *s, float v[])``: the vector of the struct."""
        return self._c_function(
            f"static void {fn}(const {self.ctype} *s, float v[{self.size}])",
            lambda f, at, idx: f"v{at} = {'(float)' if f.is_int else ''}s->{f.name}{idx};")


CORE_INCLUDE_DIRS: tuple[Path, ...] = (NATIVE_DIR / "include", NATIVE_DIR / "src")


@functools.cache
def _ffi(defines: tuple[str, ...], include_dirs: tuple[Path, ...]) -> cffi.FFI:
    ffi = cffi.FFI()
    ffi.cdef(cdef_gen.generate(list(include_dirs), ["RH_FLOAT32", *defines], find_compiler()))
    return ffi


def flat_layout(ctype: str, defines: Sequence[str] = (),
                include_dirs: Sequence[str | Path] = CORE_INCLUDE_DIRS) -> FlatLayout:
    """The flat layout of ``ctype`` (a struct of rhonn_core.h whose fields are real_t, int
    or arrays of those) in the MCU build (-DRH_FLOAT32 and ``defines``; the headers found
    in ``include_dirs``, default the core's). ValueError for a field of another type."""
    ffi = _ffi(tuple(defines), tuple(Path(d) for d in include_dirs))
    fields, k = [], 0
    for name, fld in ffi.typeof(ctype).fields:
        t = fld.type
        item = t.item if t.kind == "array" else t
        if item.kind != "primitive" or (item.cname not in _INTS and item.cname != "float"):
            raise ValueError(f"{ctype}.{name}: {t.cname} has no place in a float vector")
        n = t.length if t.kind == "array" else 1
        fields.append(Field(name, n, item.cname in _INTS, k, t.kind == "array"))
        k += n
    return FlatLayout(ctype, tuple(fields))
