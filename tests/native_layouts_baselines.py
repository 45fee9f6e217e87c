"""ctypes mirrors of the physics baselines' state structs, for the back-to-back tests
(tests/test_native_baselines.py): controller/native/src bicycle.h, seven_dof.h, mf_tyre.h,
linear_refs.h and rh_params.h's rh_ctx_t.

The structs hold ``real_t`` and therefore come from factories taking the real type
(``ctypes.c_double`` for the float64 build, ``ctypes.c_float`` for ``-DRH_FLOAT32``);
``declare(lib, real)`` sets the argtypes of every baseline function of a library built in
that precision. The configuration structs (rh_vehicle_t, rh_mf_curve_config_t,
rh_seven_dof_config_t) are production's: controller/native/layouts.py.

Units are SI as documented in the C headers.
"""

from __future__ import annotations

import ctypes
import functools
from typing import Any

from tests.native_layouts_config import MfCurveConfigC, RealType, RhVehicle, SevenDofConfigC


@functools.cache
def ctx_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_ctx_t (rh_params.h) in precision ``real``: delta_w rad, total_torque N·m, ts s,
    wheel_speeds (4) rad/s, delta_m_prev N·m."""
    return type("CtxC", (ctypes.Structure,), {"_fields_": [
        ("delta_w", real), ("total_torque", real), ("ts", real),
        ("wheel_speeds", real * 4), ("delta_m_prev", real)]})


def make_ctx(real: RealType, delta_w: float, total_torque: float, ts: float,
             wheel_speeds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
             delta_m_prev: float = 0.0) -> ctypes.Structure:
    """An rh_ctx_t of precision ``real`` (values rounded to it by ctypes)."""
    ctx_t = ctx_struct(real)
    return ctx_t(delta_w, total_torque, ts, (real * 4)(*wheel_speeds), delta_m_prev)


# --- MF tyre (mf_tyre.h) -------------------------------------------------------------------
@functools.cache
def mf_curve_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_mf_curve_t: the curve in working precision (fields as MfCurveConfigC)."""
    return type("MfCurveC", (ctypes.Structure,),
                {"_fields_": [(name, real) for name, _ in MfCurveConfigC._fields_]})


# --- 7-DoF prediction (seven_dof.h) ---------------------------------------------------------
@functools.cache
def seven_dof_wheel_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_seven_dof_wheel_t: x m, y m, fz_static N, kx_ax, ky_ay N/(m/s²), c_lin N/rad,
    side ±1, fz_cap N, front (int), lateral curve."""
    fields: list[tuple[str, Any]] = [(name, real) for name in (
        "x", "y", "fz_static", "kx_ax", "ky_ay", "c_lin", "side", "fz_cap")]
    fields += [("front", ctypes.c_int), ("lateral", mf_curve_struct(real))]
    return type("SevenDofWheelC", (ctypes.Structure,), {"_fields_": fields})


@functools.cache
def seven_dof_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_seven_dof_t (filled by rh_seven_dof_init; treat as opaque)."""
    fields: list[tuple[str, Any]] = [("h_max_s", ctypes.c_double),
                                     ("stiff_rate", ctypes.c_double)]
    fields += [(name, real) for name in ("m", "iz", "radius", "mu", "rr", "rr_ramp", "kd")]
    fields += [("mf", ctypes.c_int), ("w", seven_dof_wheel_struct(real) * 4)]
    return type("SevenDofC", (ctypes.Structure,), {"_fields_": fields})


# --- bicycle (bicycle.h) --------------------------------------------------------------------
@functools.cache
def bicycle_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_bicycle_t (filled by rh_bicycle_init; treat as opaque): h_max_s s, stiff_rate m/s²,
    m kg, iz kg·m², lf m, lr m, cf N/rad, cr N/rad, kdm 1/(kg·m²), radius m."""
    fields: list[tuple[str, Any]] = [("h_max_s", ctypes.c_double),
                                     ("stiff_rate", ctypes.c_double)]
    fields += [(name, real) for name in ("m", "iz", "lf", "lr", "cf", "cr", "kdm", "radius")]
    return type("BicycleC", (ctypes.Structure,), {"_fields_": fields})


# --- linear references (linear_refs.h) ------------------------------------------------------
@functools.cache
def linear_refs_struct(real: RealType) -> type[ctypes.Structure]:
    """rh_linear_refs_t (filled by rh_linear_refs_init): critical/guard speed m/s (double),
    wheelbase m, understeer_gradient s²/m², lr m, beta_k s²/m."""
    fields: list[tuple[str, Any]] = [("critical_speed_mps", ctypes.c_double),
                                     ("guard_speed_mps", ctypes.c_double)]
    fields += [(name, real) for name in ("wheelbase", "understeer_gradient", "lr", "beta_k")]
    return type("LinearRefsC", (ctypes.Structure,), {"_fields_": fields})


# --- sub-step right-hand sides (substep.h) --------------------------------------------------
@functools.cache
def rhs_fn_type(real: RealType) -> Any:
    """rh_substep_rhs_fn and rh_substep_rhs_jac_fn (same C signature; g has 3 or 15 entries):
    (const void *call, real_t vx, real_t vy, real_t r, real_t *g)."""
    return ctypes.CFUNCTYPE(None, ctypes.c_void_p, real, real, real, ctypes.POINTER(real))


# --- function prototypes --------------------------------------------------------------------
def declare(lib: ctypes.CDLL, real: RealType) -> None:
    """Set restype/argtypes of the baseline functions of ``lib`` (built with real_t = real).
    Arrays (x, xn, A, B, out) are passed as pointers to ``real``."""
    rp = ctypes.POINTER(real)
    ctx_p = ctypes.POINTER(ctx_struct(real))
    veh_p = ctypes.POINTER(RhVehicle)
    bic_p = ctypes.POINTER(bicycle_struct(real))
    sev_p = ctypes.POINTER(seven_dof_struct(real))
    ref_p = ctypes.POINTER(linear_refs_struct(real))
    curve_p = ctypes.POINTER(mf_curve_struct(real))
    fn_t = rhs_fn_type(real)
    protos: dict[str, tuple[Any, list[Any]]] = {
        "rh_bicycle_init": (None, [bic_p, veh_p, ctypes.c_double]),
        "rh_bicycle_predict": (None, [bic_p, rp, real, ctx_p, rp]),
        "rh_bicycle_predict_linearize": (None, [bic_p, rp, real, ctx_p, rp, rp, rp]),
        "rh_bicycle_sizeof": (ctypes.c_size_t, []),
        "rh_seven_dof_init": (None, [sev_p, veh_p, ctypes.POINTER(SevenDofConfigC)]),
        "rh_seven_dof_predict": (None, [sev_p, rp, real, ctx_p, rp]),
        "rh_seven_dof_predict_linearize": (None, [sev_p, rp, real, ctx_p, rp, rp, rp]),
        "rh_seven_dof_sizeof": (ctypes.c_size_t, []),
        "rh_linear_refs_init": (None, [ref_p, veh_p]),
        "rh_linear_refs_reset": (None, [ref_p]),
        "rh_linear_refs_compute": (None, [ref_p, real, real, real, real, real, real, rp]),
        "rh_linear_refs_sizeof": (ctypes.c_size_t, []),
        "rh_substep_initial_state": (None, [real, real, real, rp]),
        "rh_substep_predict": (None, [fn_t, ctypes.c_void_p, ctypes.c_int, real, rp, rp]),
        "rh_substep_propagate": (None, [fn_t, ctypes.c_void_p, ctypes.c_int, real, rp, rp, rp,
                                        rp]),
        "rh_mf_eval": (None, [curve_p, real, real, real, rp]),
        "rh_mf_force": (real, [curve_p, real, real, real]),
    }
    for name, (res, args) in protos.items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args
