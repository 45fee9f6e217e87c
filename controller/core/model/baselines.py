"""Physics-based baseline models of the controller (paper Section IV-B, Tables 2–3).

* make_model(kind, params) -> PredictionModel for the NMPC horizon:
  "bicycle" (LMPC: linear 2-DoF), "7dof-mf" (NMPC-MF: 7-DoF, Magic Formula tyres),
  "7dof-li" (7-DoF, linear tyres). All have nx = 3, x = [vx m/s, vy m/s, r rad/s], and
  besides the protocol offer predict_linearize(x, ΔM, ctx, out, a_out, b_out) (one pass).
* make_estimator(kind, params) -> StateEstimator: open-loop "7dof-mf" / "7dof-li"
  estimators with initialise(vx, vy, r) for the paper's known initial state.

MF parameters come from controller/config/mf_tyre_fit.toml (fitted to the plant's tyre by
`python -m harness.tools.fit_tyre`); the controller never imports plant_sim. Both factories
take mu_estimate ([controller] mu_estimate): the road μ the controller is told, which replaces
the file's mu_nominal when > 0.
"""

from __future__ import annotations

from pathlib import Path

from controller.core.interfaces import PredictionModel, StateEstimator
from controller.core.model.bicycle import BicycleModel
from controller.core.model.estimator import SevenDofEstimator
from controller.core.model.seven_dof import SevenDofPrediction
from controller.core.model.tyre import MfTyreSet, load_mf_tyres, with_mu_estimate
from controller.core.params import VehicleParams

MODEL_KINDS = ("bicycle", "7dof-mf", "7dof-li")
ESTIMATOR_KINDS = ("7dof-li", "7dof-mf")

__all__ = ["ESTIMATOR_KINDS", "MODEL_KINDS", "make_estimator", "make_model"]


def make_model(kind: str, params: VehicleParams, tyre_path: str | Path | None = None,
               mu_estimate: float = 0.0) -> PredictionModel:
    """Prediction model `kind` for vehicle `params` (tyre_path: optional MF TOML override).
    mu_estimate: road friction the controller is told, -; > 0 replaces the MF's mu_nominal
    (0 = not told). The bicycle and the 7dof-li lateral tyres have no friction parameter."""
    if kind == "bicycle":
        return BicycleModel(params)
    if kind in ("7dof-mf", "7dof-li"):
        tyres = with_mu_estimate(load_mf_tyres(tyre_path), mu_estimate)
        return SevenDofPrediction(params, tyres, linear=(kind == "7dof-li"))
    raise ValueError(f"unknown prediction model {kind!r}; expected one of {MODEL_KINDS}")


def make_estimator(kind: str, params: VehicleParams, tyre_path: str | Path | None = None,
                   mu_estimate: float = 0.0) -> StateEstimator:
    """Open-loop 7-DoF estimator `kind` ("7dof-li" or "7dof-mf") for vehicle `params`.
    mu_estimate: road friction the estimator is told, -; > 0 replaces the MF's mu_nominal
    (0 = not told; "7dof-li" has linear tyres and does not use it)."""
    if kind not in ESTIMATOR_KINDS:
        raise ValueError(f"unknown estimator {kind!r}; expected one of {ESTIMATOR_KINDS}")
    tyres: MfTyreSet = with_mu_estimate(load_mf_tyres(tyre_path), mu_estimate)
    return SevenDofEstimator(params, tyres, linear=(kind == "7dof-li"))
