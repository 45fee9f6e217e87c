"""ctypes mirrors of the node logic's structs (controller/native/node/node_*.h) for the
back-to-back tests (tests/test_native_node_*.py), and the glue that builds the test library.

The node's structs hold only double, int and int64_t (no real_t), so one layout serves the
double and the ``-DRH_FLOAT32`` build. :func:`check_sizes` compares the mirrors with the
sizes the library reports (``rh_node_logic_sizes``).

The library is the node's sources linked against the installed C core extension
(``controller.native._rhcore64`` / ``_rhcore32``): ``rh_ctrl_step`` and
``rh_ctrl_allocate_only`` are then the very functions the Python node's NativeController
calls, and a core made through that module's cffi binding (``rh_ctrl_init``) is passed to
the node as a plain pointer. Compiling the node needs the generated OSQP workspace header
that rhonn_core.h includes (``osqp_gen.generate``; the workspace is the last member of
``rh_ctrl_t``, the node reads only fields before it).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import asdict
from pathlib import Path
from types import ModuleType
from typing import Any

from can_db.codec import Rejection
from can_db.monitor import RxMonitor
from controller.native import osqp_gen
from controller.native.build_tools import NATIVE_DIR, compile_shared
from controller.runtime.envelope import SafetyEnvelope
from controller.runtime.node import MONITORED
from controller.runtime.plausibility import CHECKED, FrozenSignalMonitor

NODE_DIR = NATIVE_DIR / "node"
NODE_SOURCES = tuple(
    NODE_DIR / f"node_{m}.c" for m in ("monitor", "plaus", "envelope", "fault", "logic")
)
STREAMS = 5
MAX_SIGNALS = 4
REASONS = 10
DATA_STREAMS = 4
BURST_MAX = 6
FAULT_WINDOWS = 4
REASON_LIST = list(Rejection)  # the C reason index is the enum's position
STREAM_NAMES = list(MONITORED)  # the C stream index is the position in node.py MONITORED

c_double, c_int, c_int64 = ctypes.c_double, ctypes.c_int, ctypes.c_int64


class Frame(ctypes.Structure):
    _fields_ = [("counter", c_int), ("values", c_double * MAX_SIGNALS)]


class MonitorConfig(ctypes.Structure):
    _fields_ = [
        ("timeout_s", c_double * STREAMS),
        ("window", c_int * STREAMS),
        ("counter_fault_limit", c_int),
    ]


class MonitorStream(ctypes.Structure):
    _fields_ = [
        ("has_rx", c_int),
        ("last_rx_s", c_double),
        ("has_counter", c_int),
        ("last_counter", c_int),
        ("counter_fault_level", c_int),
        ("timed_out_reported", c_int),
        ("has_latest", c_int),
        ("latest", Frame),
        ("received", c_int64),
        ("accepted", c_int64),
        ("rejections", c_int64 * REASONS),
    ]


class Monitor(ctypes.Structure):
    _fields_ = [
        ("cfg", MonitorConfig),
        ("streams", MonitorStream * STREAMS),
        ("counts", c_int64 * REASONS),
        ("ignored", c_int64),
        ("bad_events", c_int64),
    ]


class PlausConfig(ctypes.Structure):
    _fields_ = [("frozen_frames", c_int), ("min_speed_mps", c_double)]


class Plaus(ctypes.Structure):
    _fields_ = [
        ("cfg", PlausConfig),
        ("has_last", (c_int * MAX_SIGNALS) * STREAMS),
        ("last", (c_double * MAX_SIGNALS) * STREAMS),
        ("repeats", (c_int * MAX_SIGNALS) * STREAMS),
        ("faulty", c_int * STREAMS),
        ("detections", c_int64),
    ]


class EnvelopeConfig(ctypes.Structure):
    _fields_ = [
        ("torque_rate_nm_per_s", c_double),
        ("delta_m_rate_nm_per_s", c_double),
        ("torque_quantum_nm", c_double),
        ("clip_tol_nm", c_double),
    ]


ENVELOPE_COUNTERS = (
    "steps",
    "limited_steps",
    "nonfinite_cmd",
    "torque_limit",
    "power_limit",
    "rate_limit",
    "dm_rate_limit",
    "dm_zeroed",
    "tt_reduced",
    "invalid_speed",
    "bad_prev",
    "conflicts",
)


class EnvelopeCounters(ctypes.Structure):
    _fields_ = [(n, c_int64) for n in ENVELOPE_COUNTERS]


class Envelope(ctypes.Structure):
    _fields_ = [
        ("cfg", EnvelopeConfig),
        ("t_peak", c_double),
        ("p_peak", c_double),
        ("dt", c_double),
        ("d_wheel", c_double),
        ("d_dm", c_double),
        ("counters", EnvelopeCounters),
        ("limits", c_double * 4),
        ("last_zeroed", c_int),
    ]


class Outputs(ctypes.Structure):
    _fields_ = [
        ("torques", c_double * 4),
        ("total_torque", c_double),
        ("delta_m", c_double),
        ("yaw_rate_ref", c_double),
        ("vy_ref", c_double),
        ("beta_ref", c_double),
        ("qp_status", c_int),
        ("qp_iterations", c_int),
        ("fallback", c_int),
    ]


class FaultConfig(ctypes.Structure):
    _fields_ = [
        ("rampdown_nm_per_s", c_double),
        ("n_windows", c_int),
        ("window_start_s", c_double * FAULT_WINDOWS),
        ("window_duration_s", c_double * FAULT_WINDOWS),
    ]


class Fault(ctypes.Structure):
    _fields_ = [
        ("cfg", FaultConfig),
        ("window_end_s", c_double * FAULT_WINDOWS),
        ("ramp_step_nm", c_double),
        ("peak_torque_nm", c_double),
        ("latched", c_int),
        ("exceptions", c_int64),
        ("injected", c_int64),
    ]


class LogicConfig(ctypes.Structure):
    _fields_ = [
        ("comm_period_s", c_double),
        ("mpc_every", c_int),
        ("controller_id", c_int),
        ("peak_torque_nm", c_double),
        ("peak_power_w", c_double),
        ("plant_restart_backstep_s", c_double),
        ("burst_bound", c_int * DATA_STREAMS),
        ("monitor", MonitorConfig),
        ("plaus", PlausConfig),
        ("envelope", EnvelopeConfig),
        ("fault", FaultConfig),
    ]


class Inputs(ctypes.Structure):
    _fields_ = [
        ("swa_rad", c_double),
        ("accel_pedal", c_double),
        ("brake_pedal", c_double),
        ("yaw_rate", c_double),
        ("ax", c_double),
        ("ay", c_double),
        ("wheel_speeds", c_double * 4),
        ("vx", c_double),
        ("vy", c_double),
        ("stab_enable", c_int),
        ("sensors_valid", c_int),
    ]


class Tx(ctypes.Structure):
    _fields_ = [
        ("tq_nm", c_double * 4),
        ("echo_cycle", c_int),
        ("mode", c_int),
        ("fault_bits", c_int),
        ("qp_status", c_int),
        ("qp_iter", c_int),
        ("compute_time_us", c_double),
        ("controller_id", c_int),
        ("delta_m_nm", c_double),
        ("yaw_rate_ref_deg_s", c_double),
        ("beta_ref_deg", c_double),
        ("cycle", c_int64),
        ("sim_time_s", c_double),
        ("mpc_update", c_int),
    ]


class Rx(ctypes.Structure):
    _fields_ = [("kind", c_int), ("stream", c_int), ("reason", c_int), ("frame", Frame)]


class Logic(ctypes.Structure):
    _fields_ = [
        ("cfg", LogicConfig),
        ("monitor", Monitor),
        ("plaus", Plaus),
        ("envelope", Envelope),
        ("fault", Fault),
        ("inputs", Inputs),
        ("out", Outputs),
        ("torques", c_double * 4),
        ("env_prev", c_double * 4),
        ("mode", c_int),
        ("mode_changes", c_int64),
        ("cycles_since_mpc", c_int),
        ("plant_restarts", c_int64),
        ("has_sync", c_int),
        ("last_sync", Frame),
        ("last_stamp_s", c_double),
        ("burst", (Frame * BURST_MAX) * DATA_STREAMS),
        ("burst_n", c_int * DATA_STREAMS),
        ("burst_drops", c_int64),
        ("secoc_evicted", c_int64),
        ("drops_answered", c_int64),
        ("rx_overload_cycles", c_int64),
        ("bad_events", c_int64),
        ("last_tx", Tx),
    ]


_P = ctypes.POINTER
_VP = ctypes.c_void_p
PROTOTYPES: dict[str, tuple[Any, list[Any]]] = {
    # node_monitor
    "rh_node_monitor_default_config": (None, [_P(MonitorConfig)]),
    "rh_node_monitor_init": (c_int, [_P(Monitor), _P(MonitorConfig)]),
    "rh_node_monitor_restart": (None, [_P(Monitor)]),
    "rh_node_monitor_process": (c_int, [_P(Monitor), c_int, _P(Frame), c_double]),
    "rh_node_monitor_reject": (None, [_P(Monitor), c_int, c_int]),
    "rh_node_monitor_ignore": (None, [_P(Monitor)]),
    "rh_node_monitor_valid": (c_int, [_P(Monitor), c_int, c_double]),
    "rh_node_monitor_latest": (_P(Frame), [_P(Monitor), c_int]),
    # node_plaus
    "rh_node_plaus_default_config": (None, [_P(PlausConfig)]),
    "rh_node_plaus_init": (c_int, [_P(Plaus), _P(PlausConfig)]),
    "rh_node_plaus_reset": (None, [_P(Plaus)]),
    "rh_node_plaus_update": (None, [_P(Plaus), c_int, _P(c_double), c_double]),
    "rh_node_plaus_checked": (c_int, [c_int]),
    "rh_node_plaus_faulty": (c_int, [_P(Plaus), c_int]),
    "rh_node_plaus_any_faulty": (c_int, [_P(Plaus)]),
    # node_envelope
    "rh_node_envelope_default_config": (None, [_P(EnvelopeConfig)]),
    "rh_node_envelope_init": (
        c_int,
        [_P(Envelope), _P(EnvelopeConfig), c_double, c_double, c_double],
    ),
    "rh_node_envelope_conflict_free": (c_int, [_P(Envelope)]),
    "rh_node_envelope_wheel_limit": (c_double, [_P(Envelope), c_double]),
    "rh_node_envelope_apply": (
        c_int,
        [_P(Envelope), _P(c_double), _P(c_double), c_int, _P(c_double), _P(c_double)],
    ),
    # node_fault
    "rh_node_fault_default_config": (None, [_P(FaultConfig)]),
    "rh_node_fault_init": (c_int, [_P(Fault), _P(FaultConfig), c_double, c_double]),
    "rh_node_fault_injected": (c_int, [_P(Fault), c_double]),
    "rh_node_fault_latch": (None, [_P(Fault)]),
    "rh_node_fault_outputs": (None, [_P(Fault), c_double, c_double, _P(Outputs)]),
    "rh_node_fault_ramp_down": (None, [_P(Fault), _P(c_double)]),
    # node_logic
    "rh_node_logic_default_config": (None, [_P(LogicConfig)]),
    "rh_node_logic_init": (c_int, [_P(Logic), _P(LogicConfig)]),
    "rh_node_logic_rx": (c_int, [_P(Logic), _P(Rx)]),
    "rh_node_logic_sync": (c_int, [_P(Logic), _VP, _P(Rx), _P(Rx), c_int, _P(Tx)]),
    "rh_node_logic_accept": (c_int, [_P(Logic), _P(Rx), c_double]),
    "rh_node_logic_tick": (None, [_P(Logic), _VP, c_double, _P(Tx)]),
    "rh_node_logic_answer": (None, [_P(Logic), _VP, c_double, _P(Tx)]),
    "rh_node_logic_set_secoc_evicted": (None, [_P(Logic), c_int64]),
    "rh_node_logic_sizes": (None, [_P(c_int64)]),
}


def build(out_dir: Path, core: ModuleType, float32: bool) -> ctypes.CDLL:
    """The node library of that precision, linked against the core extension ``core``
    (its module file), with every prototype set."""
    gen = out_dir / "osqp_gen"
    if not (gen / "rh_qpws.h").exists():
        osqp_gen.generate(gen)
    so = compile_shared(
        [*NODE_SOURCES, Path(core.__file__)],
        out_dir,
        defines=("RH_FLOAT32",) if float32 else (),
        include_dirs=(NATIVE_DIR / "include", *osqp_gen.osqp_include_dirs(gen)),
        name=f"rhnode{'32' if float32 else '64'}",
    )
    lib = ctypes.CDLL(str(so))
    for name, (res, args) in PROTOTYPES.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    return lib


def check_sizes(lib: ctypes.CDLL) -> None:
    """The mirrors' sizes equal the library's (AssertionError naming the struct)."""
    out = (c_int64 * 4)()
    lib.rh_node_logic_sizes(out)
    for struct, size in zip((Logic, LogicConfig, Tx, Rx), out, strict=True):
        assert ctypes.sizeof(struct) == size, (
            f"{struct.__name__}: {ctypes.sizeof(struct)} != {size}"
        )


def doubles(values: Any) -> Any:
    """A ctypes double[4] from up to 4 values."""
    arr = (c_double * 4)()
    for i, v in enumerate(values):
        arr[i] = float(v)
    return arr


# ------------------------------------------- comparisons with the Python references
def assert_same_monitor(py: RxMonitor, m: Monitor) -> None:
    """Counts by reason, the ignored count and every stream's state equal (latest values
    exactly, NaN equal to NaN)."""
    assert [m.counts[i] for i in range(REASONS)] == [py.counts[r.value] for r in REASON_LIST]
    assert m.ignored == py.ignored
    for i, name in enumerate(STREAM_NAMES):
        s, c = py.streams[name], m.streams[i]
        assert bool(c.has_rx) == (s.last_rx_s is not None), name
        if s.last_rx_s is not None:
            assert same(c.last_rx_s, s.last_rx_s), name
        assert bool(c.has_counter) == (s.last_counter is not None), name
        if s.last_counter is not None:
            assert c.last_counter == s.last_counter, name
        assert c.counter_fault_level == s.counter_fault_level, name
        assert bool(c.timed_out_reported) == s.timed_out_reported, name
        assert (c.received, c.accepted) == (s.received, s.accepted), name
        assert [c.rejections[k] for k in range(REASONS)] == [
            s.rejections.get(r.value, 0) for r in REASON_LIST
        ], name
        assert bool(c.has_latest) == (s.latest is not None), name
        if s.latest is not None:
            assert c.latest.counter == s.latest.counter
            got = list(c.latest.values)[: len(s.latest.values)]
            assert all(map(same, got, s.latest.values.values())), name


def same(a: float, b: float) -> bool:
    """Equal, or both NaN."""
    return a == b or (math.isnan(a) and math.isnan(b))


def assert_same_plaus(py: FrozenSignalMonitor, p: Plaus) -> None:
    """Detections, faulty flags, last values and repeat counts equal."""
    assert p.detections == py.detections
    for i, name in enumerate(STREAM_NAMES):
        assert bool(p.faulty[i]) == py.faulty(name), name
        checked = CHECKED.get(name, ())
        for k, sig in enumerate(checked):
            if sig in py._last:
                assert p.has_last[i][k]
                assert same(p.last[i][k], py._last[sig])
                # the C count is held at frozen_frames (no overflow); the verdict is the same
                assert p.repeats[i][k] == min(py._repeats[sig], py.frozen_frames)
            else:
                assert not p.has_last[i][k]


def assert_same_envelope(py: SafetyEnvelope, e: Envelope) -> None:
    """Counters, last limits and the last zero-ΔM flag equal."""
    assert {n: getattr(e.counters, n) for n in ENVELOPE_COUNTERS} == asdict(py.counters)
    assert list(e.limits) == list(py.limits)
    assert bool(e.last_zeroed) == py.last_zeroed
