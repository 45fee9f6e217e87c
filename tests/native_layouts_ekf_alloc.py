"""ctypes mirrors of the EKF and allocation modules' state structs, and the argtype setter,
for the back-to-back tests (tests/test_native_ekf_alloc.py).

C headers mirrored (controller/native/src): ``ekf.h`` (rh_ekf_t), ``ud_ekf.h`` (rh_ud_ekf_t),
``allocation.h`` (rh_alloc_t) and ``passive.h`` (rh_passive_out_t). These hold ``real_t`` and
exist in two variants, one per build precision: ``layouts(np.float64)`` for the default
build, ``layouts(np.float32)`` for a ``-DRH_FLOAT32`` build. The configuration structs and
their fillers (rh_ekf_config_t, rh_ekf_counters_t, rh_alloc_config_t, rh_vehicle_t) are
production's: controller/native/layouts.py.

``bind(lib, dtype)`` sets argtypes/restype of every public function of those modules on a
loaded ``ctypes.CDLL``; ``check_sizes(lib, dtype)`` compares the mirrors' sizes with the
sizeofs the library exports (rh_ekf_sizes, ...).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from tests.native_layouts_config import (
    N_FILTERS,
    RhAllocConfig,
    RhEkfConfig,
    RhEkfCounters,
    RhVehicle,
)

N_PHI = 15                         # RH_NPHI: weights per filter
N_W = N_FILTERS * N_PHI            # RH_NW
N_P = N_FILTERS * N_PHI * N_PHI    # RH_EKF_NP
QP_NOT_RUN = 4                     # RH_QP_NOT_RUN (QpStatus.NOT_RUN)


@dataclass(frozen=True)
class Layouts:
    """The real_t-dependent structs of one build precision."""

    dtype: Any                 # np.float64 or np.float32
    real: Any                  # ctypes.c_double or ctypes.c_float
    Ekf: type[ctypes.Structure]        # rh_ekf_t
    UdEkf: type[ctypes.Structure]      # rh_ud_ekf_t
    Alloc: type[ctypes.Structure]      # rh_alloc_t
    PassiveOut: type[ctypes.Structure]  # rh_passive_out_t


def _real_of(dtype: Any) -> Any:
    dt = np.dtype(dtype)
    if dt == np.float64:
        return ctypes.c_double
    if dt == np.float32:
        return ctypes.c_float
    raise ValueError(f"real_t is float64 or float32, not {dt}")


@cache
def layouts(dtype: Any = np.float64) -> Layouts:
    """Struct mirrors for a build with real_t = dtype (float32: built with RH_FLOAT32)."""
    real = _real_of(dtype)

    class Tuning(ctypes.Structure):
        """rh_ekf_tuning_t (ekf.h): the config in real_t."""

        _fields_ = [("R", real * N_FILTERS), ("zeta", real * N_FILTERS),
                    *[(s, real) for s in ("q", "p_floor", "trace_max", "p0", "w_max")]]

    class Ekf(ctypes.Structure):
        """rh_ekf_t (ekf.h): W (3, 15) u, P (3, 15, 15) u², w0; config in real_t."""

        _fields_ = [
            ("W", real * N_W), ("P", real * N_P), ("w0", real * N_W), ("t", Tuning),
            ("counters", RhEkfCounters), ("cfg", RhEkfConfig), ("since_eig", ctypes.c_int),
        ]

    class UdEkf(ctypes.Structure):
        """rh_ud_ekf_t (ud_ekf.h): W (3, 15) u, U (3, 15, 15) -, D (3, 15) u², w0."""

        _fields_ = [
            ("W", real * N_W), ("U", real * N_P), ("D", real * N_W), ("w0", real * N_W),
            ("t", Tuning), ("counters", RhEkfCounters), ("cfg", RhEkfConfig),
        ]

    class Alloc(ctypes.Structure):
        """rh_alloc_t (allocation.h): parameters in real_t, then limits/out/applied."""

        _fields_ = [
            *[(s, real) for s in (
                "peak_torque", "peak_power", "acc_clip", "mass", "wheelbase", "cg_height",
                "track", "lf", "lr", "fzf_static", "fzr_static", "fz_floor_frac",
                "rate_step")],
            ("split", ctypes.c_int),
            ("limits", real * 4), ("out", real * 4),
            ("tt_applied", real), ("dm_applied", real),
            ("prev", real * 4), ("rate_limited_calls", ctypes.c_int64),
        ]

    class PassiveOut(ctypes.Structure):
        """rh_passive_out_t (passive.h)."""

        _fields_ = [
            ("torques", real * 4), ("total_torque", real), ("delta_m", real),
            ("qp_status", ctypes.c_int), ("qp_iterations", ctypes.c_int),
            ("fallback", ctypes.c_int),
        ]

    return Layouts(np.dtype(dtype).type, real, Ekf, UdEkf, Alloc, PassiveOut)


def w0_array(w0: np.ndarray | None, dtype: Any) -> Any:
    """real_t[45] initial weights (None: NULL, i.e. zeros) from a (3, 15) array."""
    if w0 is None:
        return None
    a = np.ascontiguousarray(np.asarray(w0, dtype=dtype).reshape(N_W))
    return (_real_of(dtype) * N_W)(*a.tolist())


def bind(lib: ctypes.CDLL, dtype: Any = np.float64) -> Layouts:
    """Set argtypes/restype of the ekf, ud_ekf, allocation, pedal_map and passive functions
    of ``lib`` (built with real_t = dtype); returns the layouts of that precision. Functions
    missing from lib (a build of a subset of the modules) are skipped."""
    lay = layouts(dtype)
    real = lay.real
    rp = ctypes.POINTER(real)
    dp = ctypes.POINTER(ctypes.c_double)
    P = ctypes.POINTER
    i = ctypes.c_int
    sigs: dict[str, tuple[list[Any], Any]] = {
        "rh_ekf_init": ([P(lay.Ekf), P(RhEkfConfig), rp], None),
        "rh_ekf_reset": ([P(lay.Ekf)], None),
        "rh_ekf_update": ([P(lay.Ekf), rp, rp], i),
        "rh_ekf_update_error": ([P(lay.Ekf), rp, rp, rp, rp], i),
        "rh_ekf_freeze": ([P(lay.Ekf)], None),
        "rh_ekf_enforce_spd": ([P(lay.Ekf)], i),
        "rh_ekf_jacobi_eig": ([rp, rp, rp], i),
        "rh_ud_ekf_init": ([P(lay.UdEkf), P(RhEkfConfig), rp], None),
        "rh_ud_ekf_reset": ([P(lay.UdEkf)], None),
        "rh_ud_ekf_update": ([P(lay.UdEkf), rp, rp], i),
        "rh_ud_ekf_update_error": ([P(lay.UdEkf), rp, rp, rp, rp], i),
        "rh_ud_ekf_freeze": ([P(lay.UdEkf)], None),
        "rh_ud_ekf_covariance": ([P(lay.UdEkf), dp], None),
        "rh_ud_ekf_set_covariance": ([P(lay.UdEkf), dp], i),
        "rh_alloc_init": ([P(lay.Alloc), P(RhVehicle), P(RhAllocConfig)], None),
        "rh_alloc_reset": ([P(lay.Alloc)], None),
        "rh_alloc_motor_limits": ([P(lay.Alloc), rp], None),
        "rh_alloc_dm_capacity": ([P(lay.Alloc), rp], real),
        "rh_alloc_front_share": ([P(lay.Alloc), real, real, rp, rp], None),
        "rh_alloc_allocate": ([P(lay.Alloc), real, real, real, real, rp, i, rp], None),
        "rh_pedal_clip": ([real], real),
        "rh_pedal_total_torque": ([real, real, real], real),
        "rh_passive_reset": ([P(lay.PassiveOut)], None),
        "rh_passive_step": ([P(lay.Alloc), real, real, real, real, rp, P(lay.PassiveOut)],
                            None),
        "rh_ekf_sizes": ([P(i)], None),
        "rh_ud_ekf_size": ([], i),
        "rh_alloc_sizes": ([P(i)], None),
        "rh_passive_out_size": ([], i),
    }
    bind_signatures(lib, sigs)
    return lay


def bind_signatures(lib: ctypes.CDLL, sigs: dict[str, tuple[list[Any], Any]]) -> None:
    """Set argtypes / restype of every function of ``sigs`` that ``lib`` has (the others are
    modules not compiled into it)."""
    for name, (args, res) in sigs.items():
        fn = getattr(lib, name, None)
        if fn is None:
            continue
        fn.argtypes = args
        fn.restype = res


def check_sizes(lib: ctypes.CDLL, dtype: Any = np.float64) -> None:
    """Raise RuntimeError when a mirror's size differs from the C sizeof of ``lib`` (bound
    with ``bind``; modules absent from lib are skipped)."""
    lay = layouts(dtype)
    pairs: list[tuple[str, int, int]] = []
    triples: dict[str, tuple[tuple[str, Any], ...]] = {   # C function filling int[3]
        "rh_ekf_sizes": (("rh_ekf_t", lay.Ekf), ("rh_ekf_config_t", RhEkfConfig),
                         ("rh_ekf_counters_t", RhEkfCounters)),
        "rh_alloc_sizes": (("rh_alloc_t", lay.Alloc), ("rh_alloc_config_t", RhAllocConfig),
                           ("rh_vehicle_t", RhVehicle)),
    }
    for fn, mirrors in triples.items():
        if hasattr(lib, fn):
            out = (ctypes.c_int * 3)()
            getattr(lib, fn)(out)
            pairs += [(n, c, ctypes.sizeof(t)) for (n, t), c in zip(mirrors, out, strict=True)]
    if hasattr(lib, "rh_ud_ekf_size"):
        pairs.append(("rh_ud_ekf_t", lib.rh_ud_ekf_size(), ctypes.sizeof(lay.UdEkf)))
    if hasattr(lib, "rh_passive_out_size"):
        pairs.append(("rh_passive_out_t", lib.rh_passive_out_size(),
                      ctypes.sizeof(lay.PassiveOut)))
    bad = [f"{n}: C {c} B, ctypes {m} B" for n, c, m in pairs if c != m]
    if bad:
        raise RuntimeError("struct layout mismatch: " + "; ".join(bad))
