"""Name → controller / estimator factories, configured from TOML.

Controllers (paper IV-B): ``nmpc-rhonn`` (RHONN model + RHONN references), ``nmpc-mf``
(7-DoF Magic-Formula model + linear references), ``lmpc`` (linear bicycle + linear
references), ``passive`` (ΔM = 0). All MPCs share the QP machinery, limits and allocation.
Estimators (Tables 2–3): ``rhonn``, ``7dof-li``, ``7dof-mf``.

The physics baselines live in ``controller.core.model.baselines`` and
``controller.core.references.linear``.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

from controller.core.allocation import AllocationConfig, TorqueAllocator
from controller.core.config_schema import (
    ConfigError,
    build_section,
    merge_tables,
    require_nonnegative,
    require_positive,
)
from controller.core.grip import GripConfig, GripEstimator
from controller.core.interfaces import Controller, StateEstimator
from controller.core.model.baselines import make_estimator as make_baseline_estimator
from controller.core.model.baselines import make_model
from controller.core.model.rhonn import RhonnConfig, RhonnEstimator, RhonnModel
from controller.core.mpc.controller import MpcController
from controller.core.mpc.envelope import HandlingConfig, HandlingEnvelope
from controller.core.mpc.qp import QpConfig
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.passive import PassiveController
from controller.core.precision import dtype_of
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import make_rhonn_references
from controller.core.references.grip_demand import GripDemandReferences
from controller.core.references.linear import LinearReferences

CONTROLLER_NAMES: tuple[str, ...] = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
ESTIMATOR_NAMES: tuple[str, ...] = ("rhonn", "7dof-li", "7dof-mf")
_BASELINE_MODEL = {"nmpc-mf": "7dof-mf", "lmpc": "bicycle"}
MU_ESTIMATE_MAX = 1.5
"""Largest road friction a controller may be told ([controller] mu_estimate), -."""


@dataclass(slots=True)
class ControllerSection:
    """The [controller] table. ts_s: MPC period Ts, s. v_min_mps: below this speed ΔM = 0
    and references are kinematic, m/s. vehicle_file: optional vehicle TOML, relative to the
    config file ("" = the packaged vehicle.toml). backend: "auto" (the C core when it is
    built and supports the configuration, else the numpy reference, said once on the log),
    "native" (the C core or an error) or "numpy" (the reference; controller/registry.py).
    mu_estimate: road friction the controller is told, -; 0 = not told (the MF tyre model keeps
    mu_nominal of mf_tyre_fit.toml), else 0 < μ ≤ MU_ESTIMATE_MAX; it replaces mu_nominal in
    nmpc-mf's 7-DoF model and the 7-DoF estimators (lmpc and nmpc-rhonn have no friction
    parameter)."""

    ts_s: float = 0.05
    v_min_mps: float = 3.0
    vehicle_file: str = ""
    backend: str = "auto"
    mu_estimate: float = 0.0


@dataclass(slots=True)
class ControllerConfig:
    """Everything a controller needs, parsed from one TOML file. mu_estimate: road friction
    the controller is told, - (0 = not told; see ControllerSection)."""

    ts: float
    v_min: float
    params: VehicleParams
    mpc: QpConfig
    rhonn: RhonnConfig
    references: RhonnRefConfig
    allocation: AllocationConfig
    grip: GripConfig
    handling: HandlingConfig
    raw: dict[str, Any]
    source: str = "default.toml"
    backend: str = "auto"
    mu_estimate: float = 0.0


SECTIONS = ("controller", "mpc", "rhonn", "references", "allocation", "grip", "handling")
_MAX_EXTENDS_DEPTH = 4


def _read_config_text(config: str | Path | None) -> tuple[str, Path | None, str]:
    """(TOML text, folder of the file or None when packaged, name for messages)."""
    if config is None:
        return resources.files("controller").joinpath("config/default.toml").read_text(), \
            None, "default.toml"
    path = Path(config)
    if path.is_file():
        return path.read_text(), path.parent, str(path)
    name = path.name if path.suffix == ".toml" else f"{path.name}.toml"
    packaged = resources.files("controller").joinpath(f"config/{name}")
    if not packaged.is_file():
        raise FileNotFoundError(f"controller config {config!s} not found (neither a file nor "
                                f"a packaged config)")
    return packaged.read_text(), None, name


def load_raw_config(config: str | Path | None = None, _depth: int = 0) -> tuple[dict, str,
                                                                                Path | None]:
    """The merged TOML tables of ``config`` after following ``extends`` (a packaged name
    such as "default" or a path relative to the file), the name for messages and the
    folder relative paths refer to."""
    text, base, source = _read_config_text(config)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("", "", f"not valid TOML: {exc}", source) from None
    parent = raw.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError("", "extends", "expected a config name or path", source)
        if _depth >= _MAX_EXTENDS_DEPTH:
            raise ConfigError("", "extends", f"chain deeper than {_MAX_EXTENDS_DEPTH}", source)
        target: str | Path = parent
        if base is not None and (base / parent).is_file():
            target = base / parent
        parent_raw, _, _ = load_raw_config(target, _depth + 1)
        raw = merge_tables(parent_raw, raw)
    for key in raw:
        if key not in SECTIONS:
            raise ConfigError(key, "", f"unknown section (known: {', '.join(SECTIONS)})", source)
    return raw, source, base


def load_controller_config(config: str | Path | None = None) -> ControllerConfig:
    """Parse a controller TOML (None → the packaged default.toml; a bare name such as
    "100hz" or "100hz.toml" → the packaged file of that name). A file may start with
    ``extends = "default"`` and give only what differs. Unknown sections or keys and values
    of the wrong type raise ConfigError naming the file, the section and the key."""
    raw, source, base = load_raw_config(config)
    try:
        c = build_section(ControllerSection, raw.get("controller", {}), "controller")
        require_positive(c, "controller", ("ts_s",))
        require_nonnegative(c, "controller", ("v_min_mps",))
        if c.backend not in ("auto", "native", "numpy"):
            raise ConfigError("controller", "backend", "must be 'auto', 'native' or 'numpy'")
        if not (c.mu_estimate == 0.0 or 0.0 < c.mu_estimate <= MU_ESTIMATE_MAX):
            raise ConfigError("controller", "mu_estimate",
                              f"must be 0 (not told) or a road friction in "
                              f"(0, {MU_ESTIMATE_MAX}], got {c.mu_estimate!r}")
        if c.vehicle_file:
            vpath = Path(c.vehicle_file)
            params = load_vehicle_params(vpath if vpath.is_absolute() or base is None
                                         else base / vpath)
        else:
            params = load_vehicle_params()
        refs = RhonnRefConfig.from_dict(raw.get("references", {}))
        refs.ts = c.ts_s
        return ControllerConfig(
            ts=c.ts_s, v_min=c.v_min_mps, params=params,
            mpc=QpConfig.from_dict(raw.get("mpc", {})),
            rhonn=RhonnConfig.from_dict(raw.get("rhonn", {})),
            references=refs,
            allocation=AllocationConfig.from_dict(raw.get("allocation", {})),
            grip=GripConfig.from_dict(raw.get("grip", {})),
            handling=HandlingConfig.from_dict(raw.get("handling", {})),
            raw=raw, source=source, backend=c.backend, mu_estimate=c.mu_estimate,
        )
    except ConfigError as exc:
        raise exc.with_source(source) from None


def make_reference_controller(name: str, config: str | Path | None = None) -> Controller:
    """The numpy reference of controller ``name`` (see CONTROLLER_NAMES) from a TOML
    configuration (controller/registry.py chooses between it and the C core)."""
    if name not in CONTROLLER_NAMES:
        raise ValueError(f"unknown controller {name!r}; choose from {CONTROLLER_NAMES}")
    return build_reference(name, load_controller_config(config))


def build_reference(name: str, cfg: ControllerConfig) -> Controller:
    """The numpy reference of controller ``name`` for a parsed configuration."""
    p = cfg.params
    if name == "passive":
        # the car without a controller: the driver's torque straight to the motors (no slew)
        return PassiveController(p, TorqueAllocator(replace(p, torque_rate_nm_per_s=0.0),
                                                    cfg.allocation), cfg.ts)
    dtype = dtype_of(cfg.mpc.precision)
    allocator = TorqueAllocator(p, cfg.allocation, dtype=dtype)
    h = cfg.handling
    grip = GripEstimator(p, cfg.grip, cfg.ts)
    if name == "nmpc-rhonn":
        model = RhonnModel(p, cfg.rhonn, cfg.ts, dtype=dtype)
        refs = make_rhonn_references(model, p, cfg.references, grip, h)
        env = HandlingEnvelope(p, h) if h.envelope else None
        uses_grip = env is not None or cfg.references.kind == "grip"
        return MpcController(name, p, model, refs, effective_qp_config(name, cfg), allocator,
                             cfg.ts, cfg.v_min, grip if uses_grip else None, env)
    # the baselines: a physics model and the linear references (the grip-limited demand and
    # the envelope rows as options, [handling] baselines_*)
    model = make_model(_BASELINE_MODEL[name], p, mu_estimate=cfg.mu_estimate)
    if hasattr(model, "ts"):
        model.ts = cfg.ts
    base_refs: Any = (GripDemandReferences(p, grip, h, cfg.references.v_min)
                      if h.baselines_grip_demand else LinearReferences(p))
    env = HandlingEnvelope(p, h) if h.baselines_envelope else None
    uses_grip = env is not None or h.baselines_grip_demand
    return MpcController(name, p, model, base_refs, effective_qp_config(name, cfg), allocator,
                         cfg.ts, cfg.v_min, grip if uses_grip else None, env)


def effective_qp_config(name: str, cfg: ControllerConfig) -> QpConfig:
    """The QP tuning controller ``name`` runs: [mpc], plus [handling] move_weight on the ΔM
    increment penalty and jerk_weight on its second-difference penalty for nmpc-rhonn (and for
    the baselines with baselines_envelope)."""
    h = cfg.handling
    handled = h.envelope if name == "nmpc-rhonn" else h.baselines_envelope
    if not handled or (h.move_weight == 0.0 and h.jerk_weight == 0.0):
        return cfg.mpc
    return replace(cfg.mpc, delta_rate_weight=cfg.mpc.delta_rate_weight + h.move_weight,
                   delta_accel_weight=cfg.mpc.delta_accel_weight + h.jerk_weight)


def make_estimator(name: str, config: str | Path | None = None) -> StateEstimator:
    """Build a fidelity-study estimator by name (see ESTIMATOR_NAMES); the 7-DoF MF one runs at
    [controller] mu_estimate when that is > 0."""
    if name not in ESTIMATOR_NAMES:
        raise ValueError(f"unknown estimator {name!r}; choose from {ESTIMATOR_NAMES}")
    cfg = load_controller_config(config)
    if name == "rhonn":
        return RhonnEstimator(cfg.params, cfg.rhonn, cfg.ts)
    return make_baseline_estimator(name, cfg.params, mu_estimate=cfg.mu_estimate)
