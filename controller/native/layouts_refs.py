"""ctypes mirrors of the C reference generators' structs (src/refs*.h, sideslip_guard.h,
slow_weights.h, rhonn.h's view, rh_params.h's vehicle) and the glue to fill them.

* :class:`RhRefsConfig` (``rh_refs_config_t``) and :class:`RhVehicle` (``rh_vehicle_t``)
  hold doubles and ints only: one layout for both precisions.
* The state structs hold ``real_t``: :func:`refs_types` returns the classes for one
  precision (``float32=False``: double, ``True``: float, the ``-DRH_FLOAT32`` build).
* :func:`refs_config` / :func:`vehicle_struct` fill the init structs from the Python
  configuration (``RhonnRefConfig``, ``VehicleParams``); :func:`model_view` builds the
  per-call ``rh_rhonn_view_t`` of a ``RhonnModel``.
* :func:`get_state` / :func:`set_state` map the C state to the keys of the Python
  generators' ``get_state()`` (references/algorithm1.py, intent.py, slow_weights.py).

Field order and types must follow the C headers exactly; the C library reports its sizes
(``rh_refs_sizeof_state``, ``rh_refs_sizeof_config``) so a binding can check them
(:func:`check_sizes`).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from controller.core.params import VehicleParams
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import REFERENCE_KINDS

RH_NPHI = 15
RH_NXI = 4
RH_NW = 3 * RH_NPHI
RH_REFS_GRID_MAX = 15
RH_REFS_ROUNDS_MAX = 16
RH_REFS_NEWTON_MAX = 16

# rh_refs_config_t.kind: index in factory.REFERENCE_KINDS (4 = "linear" is rejected by C).
KIND_ALGORITHM1, KIND_INTENT, KIND_BLEND, KIND_DEMAND, KIND_LINEAR = range(5)

# rh_refs_init results.
INIT_ERRORS: dict[int, str] = {
    0: "ok",
    -1: "references.kind not supported by the C core (unknown or 'linear')",
    -2: f"references.grid_n must be odd, >= 3 and <= {RH_REFS_GRID_MAX}",
    -3: f"references.max_rounds must be in [0, {RH_REFS_ROUNDS_MAX}]",
    -4: f"references.newton_iters must be in [0, {RH_REFS_NEWTON_MAX}]",
    -5: "references.ts and references.ay_decay_s must be > 0",
}

_D = ctypes.c_double
_I = ctypes.c_int


class RhVehicle(ctypes.Structure):
    """rh_vehicle_t (rh_params.h), SI units."""

    _fields_ = [(n, _D) for n in (
        "mass_kg", "yaw_inertia_kgm2", "lf_m", "lr_m", "track_m", "wheel_inertia_kgm2",
        "wheel_radius_m", "cf_axle_n_per_rad", "cr_axle_n_per_rad", "cg_height_m",
        "steering_ratio", "peak_torque_nm", "peak_power_w")]


class RhRefsConfig(ctypes.Structure):
    """rh_refs_config_t (refs_alg1.h): RhonnRefConfig with kind as an int."""

    _fields_ = [
        ("eta", _D), ("eps_t", _D), ("rs0_vy", _D), ("rs0_r", _D), ("drs_vy", _D),
        ("drs_r", _D), ("grid_n", _I), ("max_rounds", _I), ("newton_iters", _I),
        ("beta_max", _D), ("ay_floor", _D), ("ay_ceiling", _D), ("ay_margin", _D),
        ("ay_decay_s", _D), ("v_min", _D), ("r_kin_factor", _D), ("r_band", _D), ("ts", _D),
        ("kind", _I), ("slow_tau_s", _D), ("intent_lead_s", _D), ("intent_ay_margin", _D),
        ("blend_beta_lo", _D), ("blend_beta_hi", _D), ("guard_beta_rad", _D),
        ("guard_gain_per_s", _D),
    ]


@dataclass(frozen=True)
class RefsTypes:
    """The real_t-dependent struct classes of one precision."""

    real: type[ctypes.c_double] | type[ctypes.c_float]
    np_dtype: type[np.floating[Any]]
    SlowWeights: type[ctypes.Structure]  # rh_slow_weights_t
    Alg1: type[ctypes.Structure]         # rh_refs_alg1_t
    Intent: type[ctypes.Structure]       # rh_refs_intent_t
    Bicycle: type[ctypes.Structure]      # rh_refs_bicycle_t
    Guard: type[ctypes.Structure]        # rh_sideslip_guard_t
    Refs: type[ctypes.Structure]         # rh_refs_t
    View: type[ctypes.Structure]         # rh_rhonn_view_t


@cache
def refs_types(float32: bool = False) -> RefsTypes:
    """Struct classes for real_t = float (``float32``) or double."""
    R: type[ctypes.c_double] | type[ctypes.c_float] = ctypes.c_float if float32 else _D
    sfx = "F32" if float32 else "F64"

    def struct(name: str, fields: list[tuple[str, Any]]) -> type[ctypes.Structure]:
        return type(f"{name}{sfx}", (ctypes.Structure,), {"_fields_": fields})

    slow = struct("RhSlowWeights", [("copy", R * RH_NW), ("alpha", R), ("tau_s", R),
                                    ("started", _I)])
    alg1 = struct("RhRefsAlg1", [
        *[(n, R) for n in ("eta", "eps_t", "rs0_vy", "rs0_r", "drs_vy", "drs_r",
                           "tan_beta_max", "ay_floor", "ay_ceiling", "ay_margin", "decay",
                           "v_min", "r_kin_factor", "r_band", "wheelbase_m", "lr_m")],
        ("unit", R * RH_REFS_GRID_MAX), ("grid_n", _I), ("max_rounds", _I),
        ("newton_iters", _I), ("weights", slow), ("ay_envelope", R), ("cost_last", R),
        ("rounds_last", _I), ("not_converged", _I)])
    intent = struct("RhRefsIntent", [
        *[(n, R) for n in ("ts", "v_min", "intent_lead_s", "intent_ay_margin", "ay_floor",
                           "ay_ceiling", "r_kin_factor", "r_band", "tan_beta_max", "decay",
                           "wheelbase_m", "lr_m")],
        ("weights", slow), ("ay_envelope", R), ("dw_prev", R), ("gain_last", R),
        ("fallbacks", _I)])
    bicycle = struct("RhRefsBicycle", [(n, R) for n in (
        "ts", "v_min", "intent_lead_s", "intent_ay_margin", "ay_floor", "ay_ceiling", "decay",
        "understeer_gradient", "wheelbase_m", "lr_m", "beta_k", "ay_envelope", "dw_prev")])
    guard = struct("RhSideslipGuard", [("beta_rad", R), ("gain_per_s", R), ("v_min", R),
                                       ("enabled", _I), ("active_calls", _I)])
    refs = struct("RhRefs", [
        ("kind", _I), ("status", _I), ("v_min", R), ("blend_beta_lo", R), ("blend_span", R),
        ("weight_last", R), ("alg1", alg1), ("intent", intent), ("demand", bicycle),
        ("guard", guard)])
    view = struct("RhRhonnView", [("W", ctypes.POINTER(R)), ("mu", R * RH_NXI),
                                  ("beta", R * RH_NXI), ("increment", _I)])
    return RefsTypes(R, np.float32 if float32 else np.float64, slow, alg1, intent, bicycle,
                     guard, refs, view)


def refs_config(cfg: RhonnRefConfig) -> RhRefsConfig:
    """rh_refs_config_t from the [references] configuration. ValueError for an unknown
    kind ("linear" is passed on as KIND_LINEAR; rh_refs_init rejects it)."""
    if cfg.kind not in REFERENCE_KINDS:
        raise ValueError(f"references.kind must be one of {REFERENCE_KINDS}, not {cfg.kind!r}")
    out = RhRefsConfig()
    for name, ctype in RhRefsConfig._fields_:
        if name == "kind":
            out.kind = REFERENCE_KINDS.index(cfg.kind)
        elif ctype is _I:
            setattr(out, name, int(getattr(cfg, name)))
        else:
            setattr(out, name, float(getattr(cfg, name)))
    return out


def vehicle_struct(params: VehicleParams) -> RhVehicle:
    """rh_vehicle_t from the controller's vehicle parameters."""
    return RhVehicle(**{name: float(getattr(params, name)) for name, _ in RhVehicle._fields_})


def init_structs(cfg: RhonnRefConfig, params: VehicleParams) -> tuple[RhRefsConfig, RhVehicle]:
    """The two structs rh_refs_init reads (config, vehicle)."""
    return refs_config(cfg), vehicle_struct(params)


def model_view(model: Any, w: np.ndarray, float32: bool = False) -> ctypes.Structure:
    """rh_rhonn_view_t of a RhonnModel (its mu, beta, form) reading the weights ``w``, a
    C-contiguous (3, 15) array of the build's real_t that the caller keeps alive (e.g. the
    model's own W when its dtype matches)."""
    t = refs_types(float32)
    if w.dtype != t.np_dtype or not w.flags.c_contiguous or w.size != RH_NW:
        raise ValueError(f"W must be a C-contiguous (3, 15) {np.dtype(t.np_dtype)} array")
    v = t.View()
    v.W = w.ctypes.data_as(ctypes.POINTER(t.real))
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


def _w_get(s: ctypes.Structure, key: str) -> dict[str, np.ndarray | float]:
    return {key: np.array(s.copy[:], dtype=float).reshape(3, RH_NPHI),
            f"{key}_started": float(s.started)}


def _w_set(s: ctypes.Structure, key: str, d: dict[str, Any]) -> None:
    if key in d:
        s.copy[:] = [float(x) for x in np.asarray(d[key], dtype=float).ravel()]
        s.started = int(bool(d.get(f"{key}_started", 1.0)))
    else:   # SlowWeights.set_state without the key: restart the copy
        s.started = 0


def get_state(st: ctypes.Structure) -> dict[str, np.ndarray | float]:
    """The Python generators' get_state() keys from an rh_refs_t of the configured kind
    (the sideslip guard is memoryless)."""
    d: dict[str, np.ndarray | float] = {}
    k = int(st.kind)
    if k in (KIND_ALGORITHM1, KIND_BLEND, KIND_DEMAND):
        d["ref.ay_envelope"] = float(st.alg1.ay_envelope)
        d.update(_w_get(st.alg1.weights, "ref.w_slow"))
    if k in (KIND_INTENT, KIND_BLEND):
        d.update(_w_get(st.intent.weights, "ref.intent.w_slow"))
        d["ref.intent.ay_envelope"] = float(st.intent.ay_envelope)
        d["ref.intent.dw_prev"] = float(st.intent.dw_prev)
    if k == KIND_DEMAND:
        d["ref.demand.ay_envelope"] = float(st.demand.ay_envelope)
        d["ref.demand.dw_prev"] = float(st.demand.dw_prev)
    return d


def set_state(st: ctypes.Structure, d: dict[str, Any]) -> None:
    """Restore get_state() into an rh_refs_t (defaults of the Python set_state for the keys
    those treat as optional; "ref.ay_envelope" is required as in RhonnReferences)."""
    k = int(st.kind)
    if k in (KIND_ALGORITHM1, KIND_BLEND, KIND_DEMAND):
        st.alg1.ay_envelope = float(d["ref.ay_envelope"])
        _w_set(st.alg1.weights, "ref.w_slow", d)
    if k in (KIND_INTENT, KIND_BLEND):
        _w_set(st.intent.weights, "ref.intent.w_slow", d)
        st.intent.ay_envelope = float(d.get("ref.intent.ay_envelope", 0.0))
        st.intent.dw_prev = float(d.get("ref.intent.dw_prev", math.nan))
    if k == KIND_DEMAND:
        st.demand.ay_envelope = float(d.get("ref.demand.ay_envelope", 0.0))
        st.demand.dw_prev = float(d.get("ref.demand.dw_prev", math.nan))
