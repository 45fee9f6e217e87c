"""ctypes glue of the C reference generators for the back-to-back tests
(tests/test_native_refs.py). The structs themselves (rh_refs_config_t, rh_vehicle_t,
rh_refs_t and members) and get_state / set_state are production's:
controller/native/layouts.py.

* :func:`view_struct` mirrors rhonn.h's per-call ``rh_rhonn_view_t`` (``float32=False``:
  double, ``True``: float, the ``-DRH_FLOAT32`` build); :func:`model_view` builds it for a
  ``RhonnModel``.
* :func:`init_structs` fills the two structs ``rh_refs_init`` reads.
* :func:`check_sizes` compares the mirrors with the sizes the C library reports
  (``rh_refs_sizeof_state``, ``rh_refs_sizeof_config``).
"""

from __future__ import annotations

import ctypes
from functools import cache
from typing import Any

import numpy as np

from controller.core.params import VehicleParams
from controller.core.references.algorithm1 import RhonnRefConfig
from tests.native_layouts_config import (
    RH_NW,
    RH_REFS_GRID_MAX,
    RhRefsConfig,
    RhVehicle,
    refs_config,
    refs_types,
    vehicle_struct,
)

RH_NXI = 4
RH_REFS_ROUNDS_MAX = 16
RH_REFS_NEWTON_MAX = 16

# rh_refs_init results.
INIT_ERRORS: dict[int, str] = {
    0: "ok",
    -1: "references.kind not supported by the C core (unknown or 'linear')",
    -2: f"references.grid_n must be odd, >= 3 and <= {RH_REFS_GRID_MAX}",
    -3: f"references.max_rounds must be in [0, {RH_REFS_ROUNDS_MAX}]",
    -4: f"references.newton_iters must be in [0, {RH_REFS_NEWTON_MAX}]",
    -5: "references.ts and references.ay_decay_s must be > 0",
}


def np_dtype(float32: bool = False) -> type[np.floating[Any]]:
    """numpy's real_t of the build."""
    return np.float32 if float32 else np.float64


@cache
def view_struct(float32: bool = False) -> type[ctypes.Structure]:
    """rh_rhonn_view_t: W (pointer to real_t[45]), mu, beta, increment (int)."""
    R = refs_types(float32).real
    return type(f"RhRhonnView{'F32' if float32 else 'F64'}", (ctypes.Structure,), {
        "_fields_": [("W", ctypes.POINTER(R)), ("mu", R * RH_NXI), ("beta", R * RH_NXI),
                     ("increment", ctypes.c_int)]})


def init_structs(cfg: RhonnRefConfig, params: VehicleParams) -> tuple[RhRefsConfig, RhVehicle]:
    """The two structs rh_refs_init reads (config, vehicle)."""
    return refs_config(cfg), vehicle_struct(params)


def model_view(model: Any, w: np.ndarray, float32: bool = False) -> ctypes.Structure:
    """rh_rhonn_view_t of a RhonnModel (its mu, beta, form) reading the weights ``w``, a
    C-contiguous (3, 15) array of the build's real_t that the caller keeps alive (e.g. the
    model's own W when its dtype matches)."""
    dt = np_dtype(float32)
    if w.dtype != dt or not w.flags.c_contiguous or w.size != RH_NW:
        raise ValueError(f"W must be a C-contiguous (3, 15) {np.dtype(dt)} array")
    v = view_struct(float32)()
    v.W = w.ctypes.data_as(ctypes.POINTER(refs_types(float32).real))
    v.mu[:] = [float(x) for x in model._mu]
    v.beta[:] = [float(x) for x in model._beta]
    v.increment = 1 if model.increment else 0
    return v


def check_sizes(lib: ctypes.CDLL, float32: bool = False) -> None:
    """AssertionError unless the ctypes mirrors have the C library's struct sizes."""
    t = refs_types(float32)
    lib.rh_refs_sizeof_state.restype = ctypes.c_ulong
    lib.rh_refs_sizeof_config.restype = ctypes.c_ulong
    got = (int(lib.rh_refs_sizeof_state()), int(lib.rh_refs_sizeof_config()))
    want = (ctypes.sizeof(t.Refs), ctypes.sizeof(RhRefsConfig))
    if got != want:
        raise AssertionError(f"struct sizes C {got} vs ctypes {want}")
