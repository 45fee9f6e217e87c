"""Choose the nmpc-rhonn reference design by configuration (``[references] kind``)."""

from __future__ import annotations

import math

from controller.core.grip import GripEstimator
from controller.core.interfaces import ReferenceGenerator
from controller.core.model.rhonn import RhonnModel
from controller.core.mpc.envelope import HandlingConfig
from controller.core.params import VehicleParams
from controller.core.references.algorithm1 import RhonnRefConfig, RhonnReferences
from controller.core.references.grip_demand import GripDemandReferences
from controller.core.references.intent import BlendedReferences, IntentReferences
from controller.core.references.linear import LinearReferences
from controller.core.references.sideslip_guard import SideslipGuard

REFERENCE_KINDS: tuple[str, ...] = ("algorithm1", "intent", "blend", "demand", "linear", "grip")


def make_rhonn_references(model: RhonnModel, params: VehicleParams,
                          cfg: RhonnRefConfig, grip: GripEstimator | None = None,
                          handling: HandlingConfig | None = None) -> ReferenceGenerator:
    """The reference generator named by ``cfg.kind`` (see REFERENCE_KINDS), wrapped in the
    sideslip guard (references/sideslip_guard.py) when ``cfg.guard_gain_per_s`` > 0. Kind
    "grip" (the bicycle demand limited by the grip estimate, mpc/envelope.py) needs ``grip``
    and ``handling``."""
    if cfg.kind == "grip":
        if grip is None or handling is None:
            raise ValueError('references.kind "grip" needs the grip estimator and [handling]')
        inner: ReferenceGenerator = GripDemandReferences(
            params, grip, handling, cfg.v_min, RhonnReferences(model, params, cfg))
    else:
        inner = _make_kind(model, params, cfg)
    if cfg.guard_gain_per_s > 0.0:
        return SideslipGuard(inner, cfg.guard_beta_rad, cfg.guard_gain_per_s, cfg.v_min,
                             lead_s=cfg.guard_lead_s, beta_per_g=cfg.grip_beta_per_g,
                             beta_max=cfg.grip_beta_max,
                             ay_decay=math.exp(-cfg.ts / cfg.ay_decay_s))
    return inner


def _make_kind(model: RhonnModel, params: VehicleParams,
               cfg: RhonnRefConfig) -> ReferenceGenerator:
    if cfg.kind == "algorithm1":
        return RhonnReferences(model, params, cfg)
    if cfg.kind == "intent":
        return IntentReferences(model, params, cfg)
    if cfg.kind == "blend":
        return BlendedReferences(model, params, cfg)
    if cfg.kind == "demand":
        return BlendedReferences(model, params, cfg, demand="bicycle")
    if cfg.kind == "linear":
        # Ablation only: the baselines' linear bicycle references on the RHONN model.
        return LinearReferences(params)
    raise ValueError(f"references.kind must be one of {REFERENCE_KINDS}, not {cfg.kind!r}")
