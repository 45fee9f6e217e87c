"""The C core's configuration struct ``rh_ctrl_config_t`` (include/rhonn_core.h), filled from
the controller TOML (``controller.core.registry.ControllerConfig``).

The struct, its field names and the constants (controller kinds ``RH_CTRL_*``, EKF forms
``RH_EKF_*``, reference designs ``RH_REFS_*``, allocation splits ``RH_ALLOC_SPLIT_*``,
``RH_N_MAX``) come from the C headers through the generated binding (cdef_gen.py); a section
whose C field names equal the Python configuration's is copied field by field, so a field
added to both reaches the core without an edit here. Every field is double or int, so one
layout serves both precisions.
"""

from __future__ import annotations

import math
from dataclasses import replace
from types import ModuleType
from typing import Any

import numpy as np

from controller.core.model.tyre import MfTyreSet, load_mf_tyres, with_mu_estimate
from controller.core.references.factory import REFERENCE_KINDS
from controller.core.registry import ControllerConfig, effective_qp_config
from controller.native.backend import core_module
from controller.native.osqp_gen import RUNTIME_SETTINGS, TEMPLATE_SETTINGS

KINDS = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")   # RH_CTRL_<NAME>
# OSQP's defaults for the settings the TOML does not name (osqp 1.1)
OSQP_DEFAULTS: dict[str, Any] = {"eps_prim_inf": 1e-4, "eps_dual_inf": 1e-4, "alpha": 1.6,
                                 "adaptive_rho_tolerance": 5.0,
                                 "adaptive_rho_fraction": 0.4, "scaled_termination": False}
BICYCLE_H_MAX_S = 0.05   # BicycleModel's / SevenDofPrediction's sub-step bound, s


def constant(module: ModuleType, prefix: str, name: str) -> int:
    """The C constant ``<prefix><NAME>`` (``-`` read as ``_``) of the core's headers."""
    return int(getattr(module.lib, prefix + name.upper().replace("-", "_")))


def fill(module: ModuleType, dst: Any, src: Any, skip: tuple[str, ...] = (),
         **values: Any) -> None:
    """Copy every field of the C struct ``dst`` from ``values`` or else the attribute of the
    same name of ``src`` (numbers; arrays from sequences), except those in ``skip``."""
    for name, field in module.ffi.typeof(dst).fields:
        if name in skip:
            continue
        v = values[name] if name in values else getattr(src, name)
        t = field.type
        if t.kind == "array":
            arr = getattr(dst, name)
            conv = int if t.item.cname in ("int", "int64_t") else float
            for i, x in enumerate(np.asarray(v).ravel()):
                arr[i] = conv(x)
        elif t.cname in ("double", "float"):
            setattr(dst, name, float(v))
        else:
            setattr(dst, name, int(v))


def default_module() -> ModuleType:
    """The double build (the configuration structs are the same in both)."""
    module = core_module(False)
    if module is None:
        raise NotSupportedError("the C core is not built here")
    return module


class NotSupportedError(ValueError):
    """The configuration asks for something the C core does not do (the message says
    what); the registry then builds the numpy reference."""


def osqp_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """The run-time OSQP settings for the core; NotSupportedError when a setting that shapes the
    generated template (rho, sigma, scaling, ...) differs from it."""
    if not int(settings.get("scaling", TEMPLATE_SETTINGS["scaling"])) >= 1:
        raise NotSupportedError("[mpc.osqp] scaling = 0 (the generated solver keeps its data "
                                "equilibrated: 1 or more Ruiz passes)")
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


def uses_envelope(name: str, cfg: ControllerConfig) -> bool:
    """Controller ``name`` has the envelope rows (registry.build_reference's choice)."""
    h = cfg.handling
    return bool(h.envelope if name == "nmpc-rhonn" else h.baselines_envelope)


def uses_grip_demand(name: str, cfg: ControllerConfig) -> bool:
    """Controller ``name``'s yaw reference is the grip-limited demand."""
    if name == "nmpc-rhonn":
        return cfg.references.kind == "grip"
    return bool(cfg.handling.baselines_grip_demand)


def qp_config(module: ModuleType, q: Any, cfg: ControllerConfig,
              name: str = "nmpc-rhonn") -> None:
    """Fill rh_qp_config_t ``q`` from [mpc] as controller ``name`` runs it
    (effective_qp_config), with the envelope shape when its [handling] asks for it."""
    m = effective_qp_config(name, cfg)
    n_max = int(module.lib.RH_N_MAX)
    if not 1 <= m.horizon <= n_max:
        raise NotSupportedError(f"[mpc] horizon = {m.horizon} (the core is built for 1..{n_max})")
    st = osqp_settings(m.osqp)
    h = cfg.handling
    fill(module, q, m, skip=("q_yaw", "r_beta"), **{k: st[k] for k in st if hasattr(q, k)},
         envelope=uses_envelope(name, cfg), env_lr_m=cfg.params.lr_m, env_lead_s=h.lead_s,
         env_slack_linear=h.slack_linear, env_slack_quad=h.slack_quad,
         env_v_min_mps=h.v_min_mps)
    for i in range(m.horizon):
        q.q_yaw[i] = float(m.q_yaw[i])
        q.r_beta[i] = float(m.r_beta[i])


def rhonn_config(module: ModuleType, c: Any, cfg: ControllerConfig) -> np.ndarray:
    """Fill rh_rhonn_config_t ``c``; the initial weights (3, 15) (RhonnModel's draw from
    init_seed)."""
    r = cfg.rhonn
    n = int(module.lib.RH_EKF_N)
    if len(r.ekf.r) != n or len(r.ekf.zeta) != n:
        raise ValueError(f"EKF r and zeta need {n} entries")
    fill(module, c, r, skip=("ekf",), increment=r.form == "increment",
         ekf_form=constant(module, "RH_EKF_", r.ekf.form))
    fill(module, c.ekf, r.ekf)
    w0 = np.zeros((3, 15))
    if int(r.init_seed) != 0:   # the same draw as RhonnModel.__init__
        rng = np.random.default_rng(int(r.init_seed))
        w0[:] = rng.normal(0.0, float(r.init_w_std), w0.shape)
    return w0


def refs_config(module: ModuleType, dst: Any, refs: Any) -> None:
    """Fill rh_refs_config_t from the [references] configuration. ValueError for an unknown
    kind ("linear" is passed on as RH_REFS_LINEAR; rh_refs_init rejects it)."""
    if refs.kind not in REFERENCE_KINDS:
        raise ValueError(f"references.kind must be one of {REFERENCE_KINDS}, not {refs.kind!r}")
    fill(module, dst, refs, kind=constant(module, "RH_REFS_", refs.kind),
         tan_beta_max=math.tan(refs.beta_max))


def seven_dof_config(module: ModuleType, dst: Any, tyres: MfTyreSet, linear: bool = False,
                     h_max_s: float = BICYCLE_H_MAX_S) -> None:
    """Fill rh_seven_dof_config_t as SevenDofPrediction(params, tyres, linear, h_max_s).
    ``tyres``: load_mf_tyres(), with_mu_estimate applied (the longitudinal curves are not used
    by the reduced model: its longitudinal slip is quasi-steady)."""
    fill(module, dst.front_lateral, tyres.front.lateral)
    fill(module, dst.rear_lateral, tyres.rear.lateral)
    fill(module, dst, tyres.resistance, skip=("front_lateral", "rear_lateral"),
         mu_nominal=tyres.mu_nominal, h_max_s=h_max_s, linear=linear)


def ctrl_config(name: str, cfg: ControllerConfig, module: ModuleType | None = None) -> Any:
    """rh_ctrl_config_t of controller ``name`` (see KINDS), a cffi ``rh_ctrl_config_t *`` of
    ``module`` (default: the double build); NotSupportedError when the core cannot run this
    configuration."""
    if name not in KINDS:
        raise NotSupportedError(f"unknown controller {name!r}")
    module = module or default_module()
    c = module.ffi.new("rh_ctrl_config_t *")
    c.kind = constant(module, "RH_CTRL_", name)
    c.ts_s, c.v_min_mps, c.bicycle_h_max_s = cfg.ts, cfg.v_min, BICYCLE_H_MAX_S
    fill(module, c.vehicle, cfg.params)
    a = cfg.allocation
    if not hasattr(module.lib, "RH_ALLOC_SPLIT_" + a.split.upper()):
        raise ValueError(f"allocation split must be 'normal_load' or 'equal', not {a.split!r}")
    fill(module, c.alloc, a, split=constant(module, "RH_ALLOC_SPLIT_", a.split))
    if name == "passive":
        return c
    qp_config(module, c.qp, cfg, name)
    h = cfg.handling
    fill(module, c.grip, cfg.grip)
    r = cfg.references
    # the sideslip guard ([references] guard_*) wraps nmpc-rhonn's references only: the
    # baselines' grip-limited demand has none (registry.build_reference)
    fill(module, c.handling, h, envelope=uses_envelope(name, cfg),
         guard_beta_rad=r.guard_beta_rad,
         guard_gain_per_s=r.guard_gain_per_s if name == "nmpc-rhonn" else 0.0,
         guard_lead_s=r.guard_lead_s)
    c.grip_demand = int(uses_grip_demand(name, cfg))
    c.envelope = int(uses_envelope(name, cfg))
    if name == "nmpc-rhonn":
        w0 = rhonn_config(module, c.rhonn, cfg)
        fill(module, c.rhonn_dm_gain, cfg.rhonn)   # [rhonn] dm_gain_* (yaw_gain.h)
        for i, w in enumerate(w0.ravel()):
            c.rhonn_w0[i] = float(w)
        if cfg.rhonn.ekf.q_nis != 0.0:
            raise NotSupportedError("[rhonn.ekf] q_nis (numpy reference only)")
        if cfg.references.grip_beta_per_g != 0.0:
            raise NotSupportedError("[references] grip_beta_per_g (numpy reference only)")
        # the grip demand reads Algorithm 1 (its fixed point) from the refs module; the guard
        # wraps the whole demand (grip_demand.c), so the module runs without one
        refs = cfg.references
        if refs.kind == "grip":
            refs = replace(refs, kind="algorithm1", guard_gain_per_s=0.0)
        refs_config(module, c.refs, refs)
    else:
        # the baselines' grip-limited demand reads [references] v_min (rh_ctrl_init passes
        # refs.v_min; registry.build_reference: GripDemandReferences(..., references.v_min))
        c.refs.v_min = float(cfg.references.v_min)
        if name == "nmpc-mf":
            # the same tyre set as registry.build_reference → baselines.make_model
            seven_dof_config(module, c.seven_dof,
                             with_mu_estimate(load_mf_tyres(), cfg.mu_estimate))
    return c
