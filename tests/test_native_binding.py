"""The C core's binding is generated from its headers (controller/native/cdef_gen.py): every
struct, constant and prototype Python sees is the compiler's.

The main test builds a copy of the core with a field added to ``rh_ctrl_t`` (and counted in
``rh_ctrl_step``), one to ``rh_inputs_t`` and one to ``rh_outputs_t``, touching no Python
file, and runs a NativeController of the copy: the state field reads through cffi, the step
path (the generated Stepper) reads the new input from the inputs object by its C name and
writes the new output to an outputs object that has an attribute of that name, and the
fields after the new ones (moved by them) still read right.

The same holds for the two other ways C structs reach Python: the module back-to-back tests
(controller/native/module_ffi.py builds a module with a field added to ``rh_alloc_t``) and
the MCU harness's flat vectors (harness/bench/mcu/layout.py lays out a ``rhonn_core.h`` with
fields added to ``rh_inputs_t`` and ``rh_outputs_t``, and the generated conversions
compile against it).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from controller.core.params import load_vehicle_params
from controller.native import cdef_gen
from controller.native import config as native_config
from controller.native.backend import core_module
from controller.native.build_tools import CFLAGS, SRC_DIR, find_compiler
from controller.native.module_ffi import build_module, copy_struct
from harness.bench.mcu.layout import flat_layout

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
        ok = (out is c.out and o.qp_iterations == last.qp_iterations
              and o.qp_status == last.qp_status == 0
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


def _insert_before(path: Path, anchor: str, text: str) -> None:
    """Insert ``text`` before the one occurrence of ``anchor`` in the file."""
    src = path.read_text()
    assert src.count(anchor) == 1, anchor
    path.write_text(src.replace(anchor, text + anchor))


@pytest.mark.parametrize("defines", [(), ("RH_FLOAT32",)], ids=["f64", "f32"])
def test_a_field_added_to_a_module_struct_reaches_the_module_tests(tmp_path: Path,
                                                                   defines: tuple) -> None:
    """A copy of src/ with ``probe_dm_sum`` (real_t) added to rh_alloc_t before its state
    (every state field moves by one real_t) and summed in rh_alloc_allocate: built by
    module_ffi.build_module as the module tests build theirs, the new field reads through
    the binding, and every field after it reads what the unmodified module's does, bit for
    bit, in both precisions; the library's own sizes are the binding's. No Python file
    changed."""
    src = tmp_path / "src"
    shutil.copytree(SRC_DIR, src)
    _insert_before(src / "allocation.h", "  real_t limits[4];",
                   "  real_t probe_dm_sum;      /* sum of the dM asked for, N m */\n")
    _insert_before(src / "allocation.c", "  if (!limits_current) rh_alloc_motor_limits(a, ws);",
                   "  a->probe_dm_sum += dm;\n")
    probe = build_module(["allocation.c"], tmp_path / "probe", defines, src_dir=src)
    plain = build_module(["allocation.c"], tmp_path / "plain", defines)
    params, cfg = load_vehicle_params(), SimpleNamespace(fz_floor_frac=0.1, acc_clip=12.0,
                                                         cycle_s=0.01, split=0)
    dt = np.float32 if defines else np.float64
    states = []
    for m in (probe, plain):
        ffi = m.ffi
        out = ffi.new("int[3]")
        m.lib.rh_alloc_sizes(out)
        assert list(out) == [ffi.sizeof(t) for t in ("rh_alloc_t", "rh_alloc_config_t",
                                                      "rh_vehicle_t")]
        a, veh, c = (ffi.new(f"{t} *") for t in ("rh_alloc_t", "rh_vehicle_t",
                                                  "rh_alloc_config_t"))
        native_config.fill(m, veh[0], params)
        native_config.fill(m, c[0], cfg)
        m.lib.rh_alloc_init(a, veh, c)
        ws, tq = np.full(4, 50.0, dt), np.zeros(4, dt)
        for tt, dm in ((800.0, 100.0), (-300.0, -37.5), (2500.0, 250.25)):
            m.lib.rh_alloc_allocate(a, tt, dm, 1.0, -2.0, ffi.from_buffer("real_t[]", ws), 0,
                                    ffi.from_buffer("real_t[]", tq))
        states.append({n: list(v) if isinstance(v := getattr(a, n), ffi.CData) else v
                       for n, _ in ffi.typeof("rh_alloc_t").fields})
    got, want = states
    assert got.pop("probe_dm_sum") == 100.0 - 37.5 + 250.25
    assert got == want and want["tt_applied"] != 0.0
    step = probe.ffi.sizeof("real_t")
    assert probe.ffi.offsetof("rh_alloc_t", "limits") == \
        plain.ffi.offsetof("rh_alloc_t", "limits") + step
    # bytes are copied between builds only where both lay the struct out alike
    with pytest.raises(ValueError, match="rh_alloc_t is laid out differently"):
        copy_struct(probe, "rh_alloc_t", plain, plain.ffi.new("rh_alloc_t *"))
    cfg_copy = copy_struct(probe, "rh_alloc_config_t", plain, plain.ffi.new(
        "rh_alloc_config_t *", {"split": 1, "cycle_s": 0.02}))
    assert (cfg_copy.split, cfg_copy.cycle_s) == (1, 0.02)


def test_a_module_that_does_not_compile_is_a_clear_error(tmp_path: Path) -> None:
    """A source that fails the core's flags: RuntimeError with the compiler's message."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "broken.h").write_text("int rh_broken(int x);\n")
    (src / "broken.c").write_text('#include "broken.h"\nint rh_broken(int x) { return y; }\n')
    with pytest.raises(RuntimeError, match=r"(?s)broken\.c.*undeclared"):
        build_module(["broken.c"], tmp_path / "out", src_dir=src)


def test_fields_added_to_the_step_structs_reach_the_mcu_vectors(tmp_path: Path) -> None:
    """A copy of rhonn_core.h with ``probe_out`` (real_t) added to rh_outputs_t before
    total_torque and ``probe_flag`` (int) at the end of rh_inputs_t: the MCU harness's flat
    vectors (harness/bench/mcu/layout.py) take them in the header's order, the columns after
    them move, the int columns follow, a Python object's attribute of that name is packed
    into its column, and the generated C conversions compile against the header with the
    core's flags. No Python or C file of the harness changed."""
    inc = tmp_path / "include"
    inc.mkdir()
    core_h = inc / "rhonn_core.h"
    shutil.copy(SRC_DIR.parent / "include" / "rhonn_core.h", core_h)
    _insert_before(core_h, "  real_t total_torque;        /* driver's Tt, N m */",
                   "  real_t probe_out;\n")
    _insert_before(core_h, "} rh_inputs_t;", "  int probe_flag;\n")
    dirs = (inc, SRC_DIR)
    lin, lout = flat_layout("rh_inputs_t", include_dirs=dirs), flat_layout("rh_outputs_t",
                                                                          include_dirs=dirs)
    lin0, lout0 = flat_layout("rh_inputs_t"), flat_layout("rh_outputs_t")
    assert lout.names[4] == "probe_out" and lout.size == lout0.size + 1
    assert lout.names[:4] + lout.names[5:] == lout0.names
    assert lout.int_columns == tuple(j + 1 for j in lout0.int_columns)
    assert lin.names == (*lin0.names, "probe_flag") and lin.int_columns[-1] == lin0.size
    outputs = SimpleNamespace(torques=np.arange(4.0), probe_out=0.5, total_torque=7.0,
                              qp_status=2)
    row = lout.pack(outputs)
    assert row[4] == 0.5 and row[5] == 7.0 and row[lout.names.index("qp_status")] == 2.0
    stub = tmp_path / "stub"   # OSQP's generated workspace header, as cdef_gen stubs it
    stub.mkdir()
    (stub / "rh_qpws.h").write_text("typedef double OSQPFloat;\n"
                                    "typedef struct { int opaque; } rh_qpws_t;\n")
    tu = tmp_path / "adapter.c"
    tu.write_text('#include "rhonn_core.h"\n' + lin.c_unpack("mcu_inputs_from")
                  + lout.c_pack("mcu_outputs_to") + textwrap.dedent("""
        void mcu_probe(const float *i, float *o);
        void mcu_probe(const float *i, float *o) {
          static const rh_outputs_t zero;
          rh_inputs_t x;
          rh_outputs_t y = zero;
          mcu_inputs_from(i, &x);
          y.probe_out = (real_t)x.probe_flag;
          mcu_outputs_to(&y, o);
        }
        """))
    assert "s->probe_out" in tu.read_text() and "s->probe_flag = (int)v[15]" in tu.read_text()
    res = subprocess.run([find_compiler(), *CFLAGS, "-DRH_FLOAT32", f"-I{inc}", f"-I{SRC_DIR}",
                          f"-I{stub}", "-fsyntax-only", str(tu)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
