"""ctypes mirrors of the C core's configuration structs for the module back-to-back tests,
which load the core's modules through ctypes (headers in controller/native/src; SI units as
documented there). Field order and types follow the headers exactly. The production binding
has no mirror: it is generated from the headers (controller/native/cdef_gen.py);
``ctypes_config`` turns its rh_ctrl_config_t into the mirror byte for byte.

Configuration structs hold doubles and ints only: one layout serves both precisions. The refs
state (``refs_types``) holds ``real_t``: double, or float in the ``-DRH_FLOAT32`` build.
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from controller.core.allocation import AllocationConfig
from controller.core.learning.ekf import EkfConfig
from controller.core.model.tyre import MfCurve, MfTyreSet
from controller.core.params import VehicleParams
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import REFERENCE_KINDS

_D = ctypes.c_double
_I = ctypes.c_int

RealType = type[ctypes.c_double] | type[ctypes.c_float]


# --- vehicle (rh_params.h) ------------------------------------------------------------------
class RhVehicle(ctypes.Structure):
    """rh_vehicle_t: VehicleParams field by field (same names, SI units), doubles."""

    _fields_ = [(n, _D) for n in (
        "mass_kg", "yaw_inertia_kgm2", "lf_m", "lr_m", "track_m", "wheel_inertia_kgm2",
        "wheel_radius_m", "cf_axle_n_per_rad", "cr_axle_n_per_rad", "cg_height_m",
        "steering_ratio", "peak_torque_nm", "peak_power_w", "torque_rate_nm_per_s")]


def vehicle_struct(params: VehicleParams) -> RhVehicle:
    """rh_vehicle_t from the controller's vehicle parameters."""
    return RhVehicle(**{name: float(getattr(params, name)) for name, _ in RhVehicle._fields_})


# --- EKF (ekf_counters.h, ekf.h) ------------------------------------------------------------
N_FILTERS = 3                      # RH_EKF_N: one filter per state (Vx, Vy, wr)


class RhEkfCounters(ctypes.Structure):
    """rh_ekf_counters_t: the counts of EkfCounters (int64 each, same order)."""

    _fields_ = [(name, ctypes.c_int64) for name in (
        "updates", "rejected", "frozen", "trace_resets", "eig_repairs", "weight_clips")]

    def as_dict(self) -> dict[str, int]:
        """Same keys as EkfCounters.as_dict()."""
        return {name: int(getattr(self, name)) for name, _ in self._fields_}


class RhEkfConfig(ctypes.Structure):
    """rh_ekf_config_t (units in ekf.h)."""

    _fields_ = [
        ("p0", _D), ("q", _D), ("r", _D * N_FILTERS), ("zeta", _D * N_FILTERS),
        ("p_floor", _D), ("trace_max", _D), ("w_max", _D), ("eig_check_every", _I)]


def ekf_config(cfg: EkfConfig) -> RhEkfConfig:
    """rh_ekf_config_t from an EkfConfig (cfg.form selects the C type, it is not copied).
    Raises ValueError unless r and zeta have N_FILTERS entries."""
    if len(cfg.r) != N_FILTERS or len(cfg.zeta) != N_FILTERS:
        raise ValueError(f"EKF r and zeta need {N_FILTERS} entries")
    return RhEkfConfig(
        p0=float(cfg.p0), q=float(cfg.q),
        r=(_D * N_FILTERS)(*map(float, cfg.r)),
        zeta=(_D * N_FILTERS)(*map(float, cfg.zeta)),
        p_floor=float(cfg.p_floor), trace_max=float(cfg.trace_max), w_max=float(cfg.w_max),
        eig_check_every=int(cfg.eig_check_every))


# --- allocation (allocation.h) --------------------------------------------------------------
SPLIT_NORMAL_LOAD = 0              # RH_ALLOC_SPLIT_NORMAL_LOAD
SPLIT_EQUAL = 1                    # RH_ALLOC_SPLIT_EQUAL
_SPLITS = {"normal_load": SPLIT_NORMAL_LOAD, "equal": SPLIT_EQUAL}


class RhAllocConfig(ctypes.Structure):
    """rh_alloc_config_t (split: SPLIT_NORMAL_LOAD | SPLIT_EQUAL)."""

    _fields_ = [("split", _I), ("fz_floor_frac", _D), ("acc_clip", _D), ("cycle_s", _D)]


def alloc_config(cfg: AllocationConfig) -> RhAllocConfig:
    """rh_alloc_config_t from an AllocationConfig (ValueError for an unknown split)."""
    if cfg.split not in _SPLITS:
        raise ValueError(f"allocation split must be one of {tuple(_SPLITS)}, not {cfg.split!r}")
    return RhAllocConfig(split=_SPLITS[cfg.split], fz_floor_frac=float(cfg.fz_floor_frac),
                         acc_clip=float(cfg.acc_clip), cycle_s=float(cfg.cycle_s))


# --- MF tyre (mf_tyre.h) and 7-DoF prediction (seven_dof.h) ---------------------------------
H_MAX_S = 0.05
"""Default sub-step bound of the baselines, s (BicycleModel / SevenDofPrediction h_max)."""


class MfCurveConfigC(ctypes.Structure):
    """rh_mf_curve_config_t: one pure-slip MF curve (tyre.MfCurve): fz0_n N, c -, d1 -,
    d2 -, k1 (N/rad)/N, k2 (N/rad)/N, k3 -, e1 -, e2 -."""

    _fields_ = [(name, _D) for name in ("fz0_n", "c", "d1", "d2", "k1", "k2", "k3", "e1", "e2")]


def curve_config(curve: MfCurve) -> MfCurveConfigC:
    """rh_mf_curve_config_t from an MfCurve."""
    return MfCurveConfigC(*(float(getattr(curve, name)) for name, _ in MfCurveConfigC._fields_))


class SevenDofConfigC(ctypes.Structure):
    """rh_seven_dof_config_t: front/rear lateral MF curves, mu_nominal -, rolling_coeff -,
    drag_n_per_mps2 N/(m/s)², ramp_speed_mps m/s, h_max_s s, linear (1: "7dof-li")."""

    _fields_ = [
        ("front_lateral", MfCurveConfigC), ("rear_lateral", MfCurveConfigC),
        ("mu_nominal", _D), ("rolling_coeff", _D), ("drag_n_per_mps2", _D),
        ("ramp_speed_mps", _D), ("h_max_s", _D), ("linear", _I)]


def seven_dof_config(tyres: MfTyreSet, linear: bool = False,
                     h_max_s: float = H_MAX_S) -> SevenDofConfigC:
    """rh_seven_dof_config_t of SevenDofPrediction(params, tyres, linear, h_max_s).
    ``tyres``: load_mf_tyres(), with_mu_estimate applied (the longitudinal curves are not used
    by the reduced model: its longitudinal slip is quasi-steady)."""
    res = tyres.resistance
    return SevenDofConfigC(
        front_lateral=curve_config(tyres.front.lateral),
        rear_lateral=curve_config(tyres.rear.lateral),
        mu_nominal=float(tyres.mu_nominal), rolling_coeff=float(res.rolling_coeff),
        drag_n_per_mps2=float(res.drag_n_per_mps2), ramp_speed_mps=float(res.ramp_speed_mps),
        h_max_s=float(h_max_s), linear=1 if linear else 0)


# --- reference generators (refs*.h, slow_weights.h, sideslip_guard.h) -----------------------
RH_NPHI = 15
RH_NW = 3 * RH_NPHI
RH_REFS_GRID_MAX = 15

# rh_refs_config_t.kind: index in factory.REFERENCE_KINDS (4 = "linear" is rejected by C).
KIND_ALGORITHM1, KIND_INTENT, KIND_BLEND, KIND_DEMAND, KIND_LINEAR = range(5)


class RhRefsConfig(ctypes.Structure):
    """rh_refs_config_t (refs_alg1.h): RhonnRefConfig with kind as an int."""

    _fields_ = [
        ("eta", _D), ("eps_t", _D), ("rs0_vy", _D), ("rs0_r", _D), ("drs_vy", _D),
        ("drs_r", _D), ("grid_n", _I), ("max_rounds", _I), ("newton_iters", _I),
        ("beta_max", _D), ("ay_floor", _D), ("ay_ceiling", _D), ("ay_margin", _D),
        ("ay_decay_s", _D), ("v_min", _D), ("r_kin_factor", _D), ("r_band", _D), ("ts", _D),
        ("kind", _I), ("slow_tau_s", _D), ("intent_lead_s", _D), ("intent_ay_margin", _D),
        ("blend_beta_lo", _D), ("blend_beta_hi", _D), ("guard_beta_rad", _D),
        ("guard_gain_per_s", _D), ("guard_lead_s", _D),
    ]


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


@dataclass(frozen=True)
class RefsTypes:
    """The refs state of one precision: real_t and rh_refs_t (refs.h)."""

    real: RealType
    Refs: type[ctypes.Structure]


@cache
def refs_types(float32: bool = False) -> RefsTypes:
    """rh_refs_t and its members (rh_slow_weights_t, rh_refs_alg1_t, rh_refs_intent_t,
    rh_refs_bicycle_t, rh_sideslip_guard_t) for real_t = float (``float32``) or double."""
    R: RealType = ctypes.c_float if float32 else _D
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
                                       ("lead_s", R), ("enabled", _I), ("active_calls", _I)])
    refs = struct("RhRefs", [
        ("kind", _I), ("status", _I), ("v_min", R), ("blend_beta_lo", R), ("blend_span", R),
        ("weight_last", R), ("alg1", alg1), ("intent", intent), ("demand", bicycle),
        ("guard", guard)])
    return RefsTypes(R, refs)


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
    """The Python generators' get_state() keys (references/algorithm1.py, intent.py,
    slow_weights.py) from an rh_refs_t of the configured kind (the sideslip guard is
    memoryless)."""
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


# --- the controller's configuration (rhonn_core.h, mpc_qp.h, grip*.h, rhonn_model.h) -----
N_MAX = 10   # RH_N_MAX of mpc_qp.h (osqp_gen.N_MAX)



class QpConfigC(ctypes.Structure):
    """rh_qp_config_t (mpc_qp.h)."""

    _fields_ = [
        ("horizon", _I), ("q_yaw", _D * N_MAX), ("r_beta", _D * N_MAX), ("input_reg", _D),
        ("rate_limit_nm_per_s", _D), ("sqp_iterations", _I), ("fallback_decay", _D),
        ("u_scale", _D), ("v_min", _D), ("delta_m_max_nm", _D), ("max_iter", _I),
        ("eps_abs", _D), ("eps_rel", _D), ("eps_prim_inf", _D), ("eps_dual_inf", _D),
        ("alpha", _D), ("check_termination", _I), ("warm_starting", _I),
        ("adaptive_rho_interval", _I), ("scaled_termination", _I),
        ("adaptive_rho_tolerance", _D), ("adaptive_rho_fraction", _D),
        ("delta_rate_weight", _D), ("envelope", _I), ("env_lr_m", _D), ("env_lead_s", _D),
        ("env_slack_linear", _D), ("env_slack_quad", _D), ("env_v_min_mps", _D),
        ("delta_accel_weight", _D)]


class GripConfigC(ctypes.Structure):
    """rh_grip_config_t (grip.h): GripConfig field by field."""

    _fields_ = [(n, _D) for n in (
        "mu_max", "mu_floor", "shown_factor", "hold_tau_s", "tau_s", "slip_excess_lo_rad",
        "slip_excess_hi_rad", "v_min_mps")]


class HandlingConfigC(ctypes.Structure):
    """rh_handling_config_t (grip_demand.h): the HandlingConfig fields the core reads."""

    _fields_ = [("envelope", _I), *[(n, _D) for n in (
        "yaw_margin", "rear_slip_factor", "lead_s", "slack_linear", "slack_quad",
        "demand_margin", "demand_sharpness", "fixed_point_share", "fixed_point_beta_lo",
        "fixed_point_beta_hi", "v_min_mps", "guard_beta_rad", "guard_gain_per_s",
        "guard_lead_s")]]


class RhonnConfigC(ctypes.Structure):
    """rh_rhonn_config_t (rhonn_model.h)."""

    _fields_ = [
        ("mu", _D * 4), ("beta", _D * 4), ("increment", _I), ("dm_dead_time_s", _D),
        ("gate_warmup_s", _D), ("gate_tau_s", _D), ("gate_err_lo", _D), ("gate_err_hi", _D),
        ("ekf_form", _I), ("ekf", RhEkfConfig)]


class CtrlConfigC(ctypes.Structure):
    """rh_ctrl_config_t (rhonn_core.h)."""

    _fields_ = [
        ("kind", _I), ("ts_s", _D), ("v_min_mps", _D), ("vehicle", RhVehicle),
        ("alloc", RhAllocConfig), ("qp", QpConfigC), ("rhonn", RhonnConfigC),
        ("rhonn_w0", _D * 45), ("refs", RhRefsConfig), ("seven_dof", SevenDofConfigC),
        ("bicycle_h_max_s", _D), ("grip", GripConfigC), ("handling", HandlingConfigC),
        ("grip_demand", _I), ("envelope", _I)]




def ctypes_config(name: str, cfg: Any) -> CtrlConfigC:
    """The production rh_ctrl_config_t (controller/native/config.py) as this mirror."""
    from controller.native.backend import core_module
    from controller.native.config import ctrl_config

    module = core_module(False)
    return CtrlConfigC.from_buffer_copy(bytes(module.ffi.buffer(ctrl_config(name, cfg, module))))
