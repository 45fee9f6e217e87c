"""The C core's configuration struct ``rh_ctrl_config_t`` (include/rhonn_core.h), filled from
the controller TOML (``controller.core.registry.ControllerConfig``).

Every field is double or int, so one layout serves both precisions. The binding checks the
byte size against the compiled struct at construction; the layout tests compare the field
offsets with the compiler's (tests/test_native_core.py).
"""

from __future__ import annotations

import ctypes
from dataclasses import replace
from typing import Any

import numpy as np

from controller.core.model.tyre import load_mf_tyres, with_mu_estimate
from controller.core.registry import ControllerConfig, effective_qp_config
from controller.native.layouts import (
    RhAllocConfig,
    RhEkfConfig,
    RhRefsConfig,
    RhVehicle,
    SevenDofConfigC,
    alloc_config,
    ekf_config,
    refs_config,
    seven_dof_config,
    vehicle_struct,
)
from controller.native.osqp_gen import RUNTIME_SETTINGS, TEMPLATE_SETTINGS

N_MAX = 10   # RH_N_MAX of mpc_qp.h (osqp_gen.N_MAX)
KINDS = {"nmpc-rhonn": 0, "nmpc-mf": 1, "lmpc": 2, "passive": 3}
EKF_FORMS = {"standard": 0, "ud": 1}
# OSQP's defaults for the settings the TOML does not name (osqp 1.1)
OSQP_DEFAULTS: dict[str, Any] = {"eps_prim_inf": 1e-4, "eps_dual_inf": 1e-4, "alpha": 1.6,
                                 "adaptive_rho_tolerance": 5.0,
                                 "adaptive_rho_fraction": 0.4, "scaled_termination": False}
BICYCLE_H_MAX_S = 0.05   # BicycleModel's sub-step bound, s

_D, _I = ctypes.c_double, ctypes.c_int


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


class NotSupportedError(ValueError):
    """The configuration asks for something the C core does not do (the message says
    what); the registry then builds the numpy reference."""


def osqp_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """The run-time OSQP settings for the core; NotSupportedError when a setting that shapes the
    generated template (rho, sigma, scaling, ...) differs from it."""
    for key, value in settings.items():
        if key in RUNTIME_SETTINGS:
            continue
        if TEMPLATE_SETTINGS.get(key, _Missing) != value:
            raise NotSupportedError(f"[mpc.osqp] {key} = {value!r} (the generated solver is built "
                               f"with {TEMPLATE_SETTINGS.get(key, 'the OSQP default')!r})")
    if settings.get("polishing"):
        raise NotSupportedError("[mpc.osqp] polishing = true (not in OSQP's embedded mode)")
    return {**OSQP_DEFAULTS, **settings}


class _Missing:
    pass


def qp_config(cfg: ControllerConfig, name: str = "nmpc-rhonn") -> QpConfigC:
    """rh_qp_config_t from [mpc] as controller ``name`` runs it (effective_qp_config), with
    the envelope shape when its [handling] asks for it."""
    m = effective_qp_config(name, cfg)
    if not 1 <= m.horizon <= N_MAX:
        raise NotSupportedError(f"[mpc] horizon = {m.horizon} (the core is built for 1..{N_MAX})")
    st = osqp_settings(m.osqp)
    q = QpConfigC(horizon=m.horizon, input_reg=m.input_reg,
                  rate_limit_nm_per_s=m.rate_limit_nm_per_s, sqp_iterations=m.sqp_iterations,
                  fallback_decay=m.fallback_decay, u_scale=m.u_scale, v_min=m.v_min,
                  delta_m_max_nm=m.delta_m_max_nm, max_iter=int(st["max_iter"]),
                  eps_abs=st["eps_abs"], eps_rel=st["eps_rel"],
                  eps_prim_inf=st["eps_prim_inf"], eps_dual_inf=st["eps_dual_inf"],
                  alpha=st["alpha"], check_termination=int(st["check_termination"]),
                  warm_starting=int(bool(st["warm_starting"])),
                  adaptive_rho_interval=int(st["adaptive_rho_interval"]),
                  scaled_termination=int(bool(st["scaled_termination"])),
                  adaptive_rho_tolerance=st["adaptive_rho_tolerance"],
                  adaptive_rho_fraction=st["adaptive_rho_fraction"])
    for i in range(m.horizon):
        q.q_yaw[i] = float(m.q_yaw[i])
        q.r_beta[i] = float(m.r_beta[i])
    h = cfg.handling
    q.delta_rate_weight = float(m.delta_rate_weight)
    q.delta_accel_weight = float(m.delta_accel_weight)
    q.envelope = int(uses_envelope(name, cfg))
    q.env_lr_m, q.env_lead_s = float(cfg.params.lr_m), float(h.lead_s)
    q.env_slack_linear, q.env_slack_quad = float(h.slack_linear), float(h.slack_quad)
    q.env_v_min_mps = float(h.v_min_mps)
    return q


def uses_envelope(name: str, cfg: ControllerConfig) -> bool:
    """Controller ``name`` has the envelope rows (registry.build_reference's choice)."""
    h = cfg.handling
    return bool(h.envelope if name == "nmpc-rhonn" else h.baselines_envelope)


def uses_grip_demand(name: str, cfg: ControllerConfig) -> bool:
    """Controller ``name``'s yaw reference is the grip-limited demand."""
    if name == "nmpc-rhonn":
        return cfg.references.kind == "grip"
    return bool(cfg.handling.baselines_grip_demand)


def rhonn_config(cfg: ControllerConfig) -> tuple[RhonnConfigC, np.ndarray]:
    """rh_rhonn_config_t and the initial weights (3, 15) (RhonnModel's draw from init_seed)."""
    r = cfg.rhonn
    c = RhonnConfigC(increment=1 if r.form == "increment" else 0,
                     dm_dead_time_s=r.dm_dead_time_s, gate_warmup_s=r.gate_warmup_s,
                     gate_tau_s=r.gate_tau_s, gate_err_lo=r.gate_err_lo,
                     gate_err_hi=r.gate_err_hi, ekf_form=EKF_FORMS[r.ekf.form],
                     ekf=ekf_config(r.ekf))
    c.mu[:] = [float(v) for v in r.mu]
    c.beta[:] = [float(v) for v in r.beta]
    w0 = np.zeros((3, 15))
    if int(r.init_seed) != 0:   # the same draw as RhonnModel.__init__
        rng = np.random.default_rng(int(r.init_seed))
        w0[:] = rng.normal(0.0, float(r.init_w_std), w0.shape)
    return c, w0


def ctrl_config(name: str, cfg: ControllerConfig) -> CtrlConfigC:
    """rh_ctrl_config_t of controller ``name`` (see KINDS); NotSupportedError when the core cannot
    run this configuration."""
    if name not in KINDS:
        raise NotSupportedError(f"unknown controller {name!r}")
    c = CtrlConfigC(kind=KINDS[name], ts_s=cfg.ts, v_min_mps=cfg.v_min,
                    vehicle=vehicle_struct(cfg.params), alloc=alloc_config(cfg.allocation),
                    bicycle_h_max_s=BICYCLE_H_MAX_S)
    if name == "passive":
        return c
    c.qp = qp_config(cfg, name)
    h = cfg.handling
    c.grip = GripConfigC(**{n: float(getattr(cfg.grip, n)) for n, _ in GripConfigC._fields_})
    r = cfg.references
    # the sideslip guard ([references] guard_*) wraps nmpc-rhonn's references only: the
    # baselines' grip-limited demand has none (registry.build_reference)
    gain = float(r.guard_gain_per_s) if name == "nmpc-rhonn" else 0.0
    c.handling = HandlingConfigC(
        envelope=int(uses_envelope(name, cfg)), guard_beta_rad=float(r.guard_beta_rad),
        guard_gain_per_s=gain, guard_lead_s=float(r.guard_lead_s),
        **{n: float(getattr(h, n)) for n, _ in HandlingConfigC._fields_
           if n not in ("envelope", "guard_beta_rad", "guard_gain_per_s", "guard_lead_s")})
    c.grip_demand = int(uses_grip_demand(name, cfg))
    c.envelope = int(uses_envelope(name, cfg))
    if name == "nmpc-rhonn":
        rc, w0 = rhonn_config(cfg)
        c.rhonn = rc
        c.rhonn_w0[:] = [float(v) for v in w0.ravel()]
        if cfg.rhonn.ekf.q_nis != 0.0:
            raise NotSupportedError("[rhonn.ekf] q_nis (numpy reference only)")
        if cfg.references.grip_beta_per_g != 0.0:
            raise NotSupportedError("[references] grip_beta_per_g (numpy reference only)")
        # the grip demand reads Algorithm 1 (its fixed point) from the refs module; the guard
        # wraps the whole demand (grip_demand.c), so the module runs without one
        refs = cfg.references
        if refs.kind == "grip":
            refs = replace(refs, kind="algorithm1", guard_gain_per_s=0.0)
        c.refs = refs_config(refs)
    else:
        # the baselines' grip-limited demand reads [references] v_min (rh_ctrl_init passes
        # refs.v_min; registry.build_reference: GripDemandReferences(..., references.v_min))
        c.refs.v_min = float(cfg.references.v_min)
        if name == "nmpc-mf":
            # the same tyre set as registry.build_reference → baselines.make_model
            c.seven_dof = seven_dof_config(with_mu_estimate(load_mf_tyres(), cfg.mu_estimate))
    return c
