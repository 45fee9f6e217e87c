"""ctypes mirrors of the grip estimate and the grip-limited demand (controller/native/src
grip.h, grip_demand.h, linear_refs.h) for the back-to-back tests
(tests/test_native_handling.py).

The configuration structs (rh_grip_config_t, rh_handling_config_t, rh_vehicle_t, rh_refs_t
with its sideslip guard) are in tests/native_layouts_config.py.
``rh_grip_t`` holds doubles only (the estimate is computed in double in both builds);
``rh_grip_demand_t`` holds real_t (its linear references and guard) and exists in two
variants: ``demand_types(False)`` for the default build, ``demand_types(True)`` for a
``-DRH_FLOAT32`` build.

``bind(lib, float32)`` sets argtypes/restype of grip.c's and grip_demand.c's functions on a
loaded ``ctypes.CDLL``; ``check_sizes(lib, float32)`` compares the mirrors with the sizes the
library reports (rh_grip_sizes, rh_grip_demand_sizes).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from functools import cache
from typing import Any

from tests.native_layouts_config import GripConfigC, HandlingConfigC, RhVehicle, refs_types
from tests.native_layouts_ekf_alloc import bind_signatures
from tests.native_layouts_refs import view_struct

_D = ctypes.c_double


class GripC(ctypes.Structure):
    """rh_grip_t (grip.h): the configuration, constants and state, doubles."""

    _fields_ = [("cfg", GripConfigC), *[(n, _D) for n in (
        "lf", "lr", "k_front", "k_rear", "hold", "gain", "mu", "shown", "saturation",
        "grip_used")]]


@dataclass(frozen=True)
class DemandTypes:
    """The real_t-dependent structs of one build precision."""

    real: Any                              # ctypes.c_double or ctypes.c_float
    Refs: type[ctypes.Structure]           # rh_refs_t (production's mirror)
    LinearRefs: type[ctypes.Structure]     # rh_linear_refs_t
    GripDemand: type[ctypes.Structure]     # rh_grip_demand_t


@cache
def demand_types(float32: bool = False) -> DemandTypes:
    """rh_linear_refs_t and rh_grip_demand_t for real_t = float (``float32``) or double."""
    t = refs_types(float32)
    R = t.real
    sfx = "F32" if float32 else "F64"
    guard = dict(t.Refs._fields_)["guard"]     # rh_sideslip_guard_t, production's mirror
    linear = type(f"RhLinearRefs{sfx}", (ctypes.Structure,), {"_fields_": [
        ("critical_speed_mps", _D), ("guard_speed_mps", _D),
        *[(n, R) for n in ("wheelbase", "understeer_gradient", "lr", "beta_k")]]})
    demand = type(f"RhGripDemand{sfx}", (ctypes.Structure,), {"_fields_": [
        ("linear", linear),
        *[(n, _D) for n in ("margin", "sharpness", "share", "beta_lo", "beta_hi", "v_min")],
        ("guard", guard), ("factor_last", _D), ("weight_last", _D)]})
    return DemandTypes(R, t.Refs, linear, demand)


def bind(lib: ctypes.CDLL, float32: bool = False) -> DemandTypes:
    """Set argtypes/restype of the grip and grip-demand functions of ``lib`` (built with
    real_t = float when ``float32``); functions missing from lib are skipped."""
    t = demand_types(float32)
    P, R = ctypes.POINTER, t.real
    sigs: dict[str, tuple[list[Any], Any]] = {
        "rh_grip_init": ([P(GripC), P(GripConfigC), P(RhVehicle), _D], None),
        "rh_grip_reset": ([P(GripC)], None),
        "rh_grip_update": ([P(GripC), *[_D] * 6], _D),
        "rh_grip_sizes": ([P(ctypes.c_int)], None),
        "rh_grip_demand_init": ([P(t.GripDemand), P(HandlingConfigC), P(RhVehicle), _D],
                                None),
        "rh_grip_demand_reset": ([P(t.GripDemand)], None),
        "rh_grip_demand_compute": ([P(t.GripDemand), _D, P(t.Refs), P(view_struct(float32)),
                                    *[R] * 6, P(R)], None),
        "rh_grip_demand_sizes": ([P(ctypes.c_int)], None),
    }
    bind_signatures(lib, sigs)
    return t


def check_sizes(lib: ctypes.CDLL, float32: bool = False) -> None:
    """AssertionError unless the mirrors have the C library's struct sizes (modules absent
    from lib are skipped)."""
    t = demand_types(float32)
    pairs = {"rh_grip_sizes": (GripC, GripConfigC),
             "rh_grip_demand_sizes": (t.GripDemand, HandlingConfigC)}
    for fn, mirrors in pairs.items():
        if not hasattr(lib, fn):
            continue
        out = (ctypes.c_int * 2)()
        getattr(lib, fn)(out)
        want = tuple(ctypes.sizeof(m) for m in mirrors)
        if tuple(out) != want:
            raise AssertionError(f"{fn}: C {tuple(out)} vs ctypes {want}")
