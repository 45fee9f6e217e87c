"""Name → controller / estimator factories, configured from TOML.

Controllers (paper IV-B): ``nmpc-rhonn`` (RHONN model + RHONN references), ``nmpc-mf``
(7-DoF Magic-Formula model + linear references), ``lmpc`` (linear bicycle + linear
references), ``passive`` (ΔM = 0). All MPCs share the QP machinery, limits and allocation.
Estimators (Tables 2–3): ``rhonn``, ``7dof-li``, ``7dof-mf``.

The physics baselines live in ``controller.core.model.baselines`` and
``controller.core.references.linear``;
they are imported lazily, so the RHONN controller works without them.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from controller.core.allocation import AllocationConfig, TorqueAllocator
from controller.core.interfaces import Controller, StateEstimator
from controller.core.model.rhonn import RhonnConfig, RhonnEstimator, RhonnModel
from controller.core.mpc.controller import MpcController
from controller.core.mpc.qp import QpConfig
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.passive import PassiveController
from controller.core.references.algorithm1 import RhonnRefConfig
from controller.core.references.factory import make_rhonn_references

CONTROLLER_NAMES: tuple[str, ...] = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
ESTIMATOR_NAMES: tuple[str, ...] = ("rhonn", "7dof-li", "7dof-mf")
_BASELINE_MODEL = {"nmpc-mf": "7dof-mf", "lmpc": "bicycle"}


@dataclass(slots=True)
class ControllerConfig:
    """Everything a controller needs, parsed from one TOML file."""

    ts: float
    v_min: float
    params: VehicleParams
    mpc: QpConfig
    rhonn: RhonnConfig
    references: RhonnRefConfig
    allocation: AllocationConfig
    raw: dict[str, Any]


def load_controller_config(config: str | Path | None = None) -> ControllerConfig:
    """Parse a controller TOML (None → the packaged default.toml; a bare name such as
    "100hz" or "100hz.toml" → the packaged file of that name)."""
    base: Path | None = None
    if config is None:
        text = resources.files("controller").joinpath("config/default.toml").read_text()
    else:
        path = Path(config)
        if not path.exists():
            name = path.name if path.suffix == ".toml" else f"{path.name}.toml"
            packaged = resources.files("controller").joinpath(f"config/{name}")
            if not packaged.is_file():
                raise FileNotFoundError(f"controller config {config!s} not found")
            text = packaged.read_text()
        else:
            text = path.read_text()
            base = path.parent
    raw = tomllib.loads(text)
    c = dict(raw.get("controller", {}))
    ts = float(c.get("ts_s", 0.05))
    if not ts > 0.0:
        raise ValueError("controller.ts_s must be > 0")
    vfile = c.get("vehicle_file")
    if vfile is not None:
        vpath = Path(vfile)
        params = load_vehicle_params(vpath if vpath.is_absolute() or base is None
                                     else base / vpath)
    else:
        params = load_vehicle_params()
    refs = RhonnRefConfig.from_dict(raw.get("references", {}))
    refs.ts = ts
    return ControllerConfig(
        ts=ts, v_min=float(c.get("v_min_mps", 3.0)), params=params,
        mpc=QpConfig.from_dict(raw.get("mpc", {})),
        rhonn=RhonnConfig.from_dict(raw.get("rhonn", {})),
        references=refs,
        allocation=AllocationConfig.from_dict(raw.get("allocation", {})),
        raw=raw,
    )


def make_controller(name: str, config: str | Path | None = None) -> Controller:
    """Build a controller by name (see CONTROLLER_NAMES) from a TOML configuration."""
    if name not in CONTROLLER_NAMES:
        raise ValueError(f"unknown controller {name!r}; choose from {CONTROLLER_NAMES}")
    cfg = load_controller_config(config)
    p = cfg.params
    allocator = TorqueAllocator(p, cfg.allocation)
    if name == "passive":
        return PassiveController(p, allocator, cfg.ts)
    if name == "nmpc-rhonn":
        model = RhonnModel(p, cfg.rhonn, cfg.ts)
        refs = make_rhonn_references(model, p, cfg.references)
        return MpcController(name, p, model, refs, cfg.mpc, allocator, cfg.ts, cfg.v_min)
    # Baselines: imported lazily (a colleague's modules; may not exist yet).
    from controller.core.model.baselines import make_model
    from controller.core.references.linear import LinearReferences

    model = make_model(_BASELINE_MODEL[name], p)
    if hasattr(model, "ts"):
        model.ts = cfg.ts
    return MpcController(name, p, model, LinearReferences(p), cfg.mpc, allocator, cfg.ts,
                         cfg.v_min)


def make_estimator(name: str, config: str | Path | None = None) -> StateEstimator:
    """Build a fidelity-study estimator by name (see ESTIMATOR_NAMES)."""
    if name not in ESTIMATOR_NAMES:
        raise ValueError(f"unknown estimator {name!r}; choose from {ESTIMATOR_NAMES}")
    cfg = load_controller_config(config)
    if name == "rhonn":
        return RhonnEstimator(cfg.params, cfg.rhonn, cfg.ts)
    from controller.core.model.baselines import make_estimator as _make

    return _make(name, cfg.params)
