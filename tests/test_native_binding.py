"""The C core's binding is generated from its headers (controller/native/cdef_gen.py): every
struct, constant and prototype Python sees is the compiler's.

The main test builds a copy of the core with a field added to ``rh_ctrl_t`` (and counted in
``rh_ctrl_step``), one to ``rh_inputs_t`` and one to ``rh_outputs_t``, touching no Python
file, and runs a NativeController of the copy: the state field reads through cffi, the step
path (the generated Stepper) reads the new input from the inputs object by its C name and
writes the new output to an outputs object that has an attribute of that name, and the
fields after the new ones (moved by them) still read right.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from controller.native import cdef_gen
from controller.native.backend import core_module

ROOT = Path(__file__).resolve().parents[1]
NATIVE = ROOT / "controller" / "native"
needs_core = pytest.mark.skipif(core_module(False) is None, reason="the C core is not built")


def test_cdef_comes_from_the_headers() -> None:
    """Struct fields and integer constants are in the cdef as the headers state them."""
    cdef = cdef_gen.generate([NATIVE / "include", NATIVE / "src"])
    assert "rh_ctrl_config_t;" in cdef and "int sensors_valid;" in cdef
    for name in ("RH_N_MAX", "RH_CTRL_PASSIVE", "RH_QP_FALLBACK", "RH_EKF_UD", "RH_NW"):
        assert f"#define {name} ..." in cdef
    assert "RH_GRIP_G" not in cdef   # a float macro is no cffi integer constant
    assert "...;" in cdef            # OSQP's workspace: size and place from the compiler


@needs_core
def test_constants_are_the_compiled_values() -> None:
    """A few constants read through the binding (values from the compiled headers)."""
    lib = core_module(False).lib
    assert (lib.RH_CTRL_NMPC_RHONN, lib.RH_CTRL_PASSIVE) == (0, 3)
    assert lib.RH_N_MAX >= 1 and lib.RH_NW == 3 * lib.RH_NPHI
    assert lib.RH_QP_NOT_RUN == 4 and lib.RH_REFS_LINEAR == 4


@needs_core
def test_the_step_path_follows_the_struct_fields() -> None:
    """The Stepper's attribute names are rh_inputs_t's and rh_outputs_t's field names."""
    m = core_module(False)
    source = cdef_gen.step_source([NATIVE / "include", NATIVE / "src"])
    for typ in ("rh_inputs_t", "rh_outputs_t"):
        for name, _ in m.ffi.typeof(typ).fields:
            if not name.endswith("_usable"):
                assert f'"{name}"' in source, name


@needs_core
@pytest.mark.timeout(900)
def test_a_field_added_in_c_reaches_python(tmp_path: Path) -> None:
    """Add ``probe_steps`` to rh_ctrl_t before the QP state, ``probe_in`` to rh_inputs_t
    before vx and ``probe_out`` to rh_outputs_t before everything, set them in
    rh_ctrl_step, build the copy with setup.py, and read them from Python: no Python file
    changed."""
    for name in ("setup.py", "pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, tmp_path / name)
    shutil.copytree(ROOT / "controller", tmp_path / "controller",
                    ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    header = tmp_path / "controller/native/include/rhonn_core.h"
    text = header.read_text()
    edits = (("  rh_qp_t qp;                 /* last", "  int64_t probe_steps;\n"),
             ("  real_t vx, vy;           /* estimated", "  real_t probe_in;\n"),
             ("  real_t torques[4];          /* wheel", "  real_t probe_out;\n"))
    for anchor, field in edits:
        assert text.count(anchor) == 1, anchor
        text = text.replace(anchor, field + anchor)
    header.write_text(text)
    source = tmp_path / "controller/native/src/controller.c"
    text = source.read_text()
    assert "  c->steps += 1;\n" in text
    source.write_text(text.replace(
        "  c->steps += 1;\n",
        "  c->steps += 1;\n  c->probe_steps += 2;\n"
        "  o->probe_out = in->probe_in + (real_t)c->probe_steps;\n"))
    build = subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--inplace"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=840)
    assert "C core not built" not in build.stdout, build.stdout + build.stderr
    script = textwrap.dedent("""
        import numpy as np
        from controller.core.interfaces import ControllerInputs, ControllerOutputs
        from controller.registry import make_controller
        import controller.native.backend as b
        assert b.__file__.startswith(ROOT), b.__file__
        c = make_controller("lmpc", backend="native")
        x = ControllerInputs(swa_rad=0.05, accel_pedal=0.2, yaw_rate=0.1, vx=20.0,
                             wheel_speeds=np.full(4, 20.0 / 0.3), sensors_valid=True,
                             stab_enable=True)
        class In:   # an inputs object with the new attribute (ControllerInputs has slots)
            pass
        i = In()
        for k in ControllerInputs.__slots__:
            setattr(i, k, getattr(x, k))
        i.probe_in = 0.5
        class Out:  # an outputs object with the new attribute
            pass
        o = Out()
        for k in ControllerOutputs.__slots__:
            setattr(o, k, getattr(ControllerOutputs(), k))
        o.probe_out = 0.0
        for _ in range(3):
            out = c.step(i)
        first = (int(c._c.probe_steps), float(c._c.out.probe_out), c.steps)
        m = c._module
        s = m.Stepper(o)   # a second step path writing to o, on a copy of c's state
        state = m.ffi.from_buffer("rh_ctrl_t *", s, require_writable=True)
        m.lib.rh_ctrl_copy(state, c._c)
        s.step(i)
        last = state.out   # the core's copy of the outputs of the step just made
        ok = (out is c.out and o.qp_iterations == last.qp_iterations > 0
              and o.total_torque == last.total_torque and o.beta_ref == last.beta_ref
              and list(o.torques) == [last.torques[k] for k in range(4)]
              and abs(o.model_prediction[0] - 20.0) < 1.0)
        ok = ok and int(state.probe_steps) == 8 and c.steps == 3
        print(*first, o.probe_out, ok)
    """)
    script = f"ROOT = {str(tmp_path)!r}\n" + script
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["6", "6.5", "3", "8.5", "True"]
