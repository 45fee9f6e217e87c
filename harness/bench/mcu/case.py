"""A case of the MCU build (:class:`McuCase`) and the C text generated for it: exact float
literals, designated initialisers of the binding's C structs, the case headers of a build."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import _cffi_backend
import numpy as np

from controller.native.build_tools import NATIVE_DIR
from harness.bench.mcu.layout import FlatLayout, flat_layout

MCU_DIR = NATIVE_DIR / "mcu"


class McuError(RuntimeError):
    """A build or run step failed (the message has the command and its output)."""


@dataclasses.dataclass
class McuCase:
    """One controller case for the MCU. ``adapter``: C file defining mcu_case_init/step
    (built with the core's flags, may include core headers and "mcu_case_config.h");
    ``sources``: core sources (names relative to controller/native/src or paths);
    ``config_c``: C text placed in mcu_case_config.h; ``inputs`` (steps, n_in) and
    ``expected`` (steps, n_out) float32; ``tolerance``: absolute bound per output,
    broadcastable to ``expected``; ``bound_text`` states it for the report. ``lib_sources``
    (third-party, e.g. OSQP's embedded code) are built with LIB_FLAGS (no -Werror/-pedantic)
    and reported on their own line."""

    name: str
    adapter: Path
    sources: Sequence[str | Path]
    config_c: str
    inputs: np.ndarray
    expected: np.ndarray
    tolerance: np.ndarray
    bound_text: str = ""
    output_names: Sequence[str] = ()
    lib_sources: Sequence[str | Path] = ()   # third-party C (e.g. OSQP), own size line
    include_dirs: Sequence[str | Path] = ()  # extra -isystem for core, libraries and adapter
    defines: Sequence[str] = ()              # extra -D for core, libraries and adapter
    lib_flags: Sequence[str] = ()            # extra flags for lib_sources only
    # further outputs (steps, n_out) to compare with, e.g. {"host C float32": ...}: the
    # scale-relative error per output and the integer outputs' mismatch count are reported
    others: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    int_outputs: Sequence[int] = ()          # output columns that are counts / flags
    notes: dict[str, Any] = dataclasses.field(default_factory=dict)  # carried to the result


def _c_bits(a: np.ndarray) -> list[str]:
    return [f"0x{int(v):08x}u" for v in np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)]


def c_float_array(name: str, values: np.ndarray, ctype: str = "real_t") -> str:
    """``static const <ctype> name[n] = {...};`` with exact C99 hex-float literals (float32 values;
    for the config preamble of a case)."""
    vals = np.asarray(values, dtype=np.float32).ravel()
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{name}: non-finite value")
    body = ", ".join(f"{float(v).hex()}f" if v != 0 else "0.0f" for v in vals)
    return f"static const {ctype} {name}[{vals.size}] = {{{body}}};\n"


def c_real(value: float) -> str:
    """Exact C99 hex-float literal of ``value`` rounded to float32 (a real_t field)."""
    v = float(np.float32(value))
    if not np.isfinite(v):
        raise ValueError(f"non-finite value {value!r}")
    return f"{v.hex()}f"


def c_double(value: float) -> str:
    """Exact C99 hex-float literal of ``value`` (a double config field)."""
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"non-finite value {value!r}")
    return v.hex()


def _is_zero(text: str) -> bool:
    return re.fullmatch(r"[{}0,\s]*|0x0\.0p\+0|-?0\.0", text.strip()) is not None and \
        not text.strip().startswith("-")


def c_initializer(obj: Any) -> str:
    """C99 designated initialiser of a C struct/array/scalar of the core's binding (e.g. the
    ``rh_ctrl_config_t`` of controller/native/config.py, a cffi cdata): layout-independent,
    so the host's layout need not match the ARM EABI one. Doubles/floats as exact hex
    literals."""
    if isinstance(obj, _cffi_backend._CDataBase):
        t = _cffi_backend.typeof(obj)
        if t.kind == "pointer":
            return c_initializer(obj[0])
        if t.kind == "struct":
            parts = [f".{name} = {c_initializer(getattr(obj, name))}" for name, _ in t.fields]
            return "{" + ", ".join(parts) + "}"
        if t.kind == "array":
            items = [c_initializer(v) for v in obj]
            while items and _is_zero(items[-1]):
                items.pop()  # the rest is zero-initialised: fits arrays shortened by -DRH_N_MAX
            return "{" + (", ".join(items) if items else "0") + "}"
    if isinstance(obj, bool | int | np.integer):
        return str(int(obj))
    if isinstance(obj, float | np.floating):
        return c_double(float(obj))
    raise TypeError(f"no C initialiser for {type(obj).__name__}")


def ctrl_layouts(defines: Sequence[str] = ()) -> tuple[FlatLayout, FlatLayout]:
    """The flat vectors of cases/ctrl_step.c: (rh_inputs_t, rh_outputs_t) as laid out from
    rhonn_core.h in the MCU build with ``defines`` (harness/bench/mcu/layout.py)."""
    return flat_layout("rh_inputs_t", defines), flat_layout("rh_outputs_t", defines)


def ctrl_step_case(config: Any, inputs: np.ndarray, expected: np.ndarray,
                   tolerance: np.ndarray, sources: Sequence[str | Path],
                   lib_sources: Sequence[str | Path] = (),
                   include_dirs: Sequence[str | Path] = (), defines: Sequence[str] = (),
                   bound_text: str = "", name: str = "rh_ctrl_step",
                   lib_flags: Sequence[str] = ()) -> McuCase:
    """The full controller step as a case: ``config`` the ``rh_ctrl_config_t`` (cffi) (or
    the C initialiser text), ``inputs`` (steps, n_in) rh_inputs_t vectors and ``expected``
    (steps, n_out) float32 reference rh_outputs_t vectors as :func:`ctrl_layouts` lays them
    out (NaN where the reference has none; NaN = NaN counts as equal), ``sources`` the core's
    sources (e.g. every src/*.c the step links), ``lib_sources``/``include_dirs``/``defines``
    e.g. the generated OSQP code. The adapter's conversions between the vectors and the
    structs are generated from the same layouts into mcu_case_config.h."""
    init = config if isinstance(config, str) else c_initializer(config)
    lay_in, lay_out = ctrl_layouts(defines)
    config_c = ('#include "rhonn_core.h"\n'
                f"static const rh_ctrl_config_t MCU_CONFIG = {init};\n"
                f"#define MCU_CTRL_N_IN {lay_in.size}u\n#define MCU_CTRL_N_OUT {lay_out.size}u\n"
                + lay_in.c_unpack("mcu_inputs_from") + lay_out.c_pack("mcu_outputs_to"))
    return McuCase(
        name=name, adapter=MCU_DIR / "cases" / "ctrl_step.c", sources=sources,
        config_c=config_c, inputs=inputs, expected=expected, tolerance=tolerance,
        bound_text=bound_text, output_names=lay_out.names, lib_sources=lib_sources,
        include_dirs=include_dirs, defines=defines, lib_flags=lib_flags,
        int_outputs=lay_out.int_columns)


def write_case_headers(case: McuCase, out: Path) -> None:
    inputs = np.asarray(case.inputs, dtype=np.float32)
    n_steps, n_in = inputs.shape
    n_out = np.asarray(case.expected).shape[1]
    (out / "mcu_case_dims.h").write_text(
        "/* generated by harness/bench/mcu/case.py */\n"
        "#ifndef MCU_CASE_DIMS_H\n#define MCU_CASE_DIMS_H\n"
        f"#define MCU_N_STEPS {n_steps}u\n#define MCU_N_IN {n_in}u\n#define MCU_N_OUT {n_out}u\n"
        "#endif\n")
    rows = ",\n".join("  {" + ", ".join(_c_bits(r)) + "}" for r in inputs)
    (out / "mcu_case_inputs.h").write_text(
        "/* generated by harness/bench/mcu/case.py: recorded inputs, float32 bit patterns */\n"
        "#include <stdint.h>\n#include \"mcu_case_dims.h\"\n"
        f"static const uint32_t MCU_INPUT_BITS[MCU_N_STEPS][MCU_N_IN] = {{\n{rows}\n}};\n")
    (out / "mcu_case_config.h").write_text(
        "/* generated by harness/bench/mcu/case.py: case preamble (config initialisers) */\n"
        "#ifndef MCU_CASE_CONFIG_H\n#define MCU_CASE_CONFIG_H\n"
        f"{case.config_c}\n#endif\n")
