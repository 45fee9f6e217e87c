"""The stability benchmark's verdicts of one run (post step ``stability`` of a campaign run).

:func:`evaluate` judges a run's plant truth by what the run is for (``kind``):

* ``dlc``: the three verdicts of harness.analysis.verdicts (paper rule, course rule, stable)
  and their numbers, over the verdict window;
* ``sine``: FMVSS 126 sine with dwell (pass, lateral displacement at BOS + 1.07 s, m);
* ``path``: path deviation and sideslip only;
* ``mu_step``: the response to the road's first friction step (harness.analysis.adaptation)
  and the learned model's re-learning time.

Every kind also gives spun, max |β| (deg), max |lateral deviation| (m), the (β, β̇) phase area
(rad·rad/s), :func:`authority_use` and the smoothness KPIs of the commanded wheel torques
(harness/analysis/smoothness.py, from the truth's ``tcmd_*`` columns). A run whose scenario
has friction steps also gets the model's re-learning time (s) after the first step.

:func:`stability_of_run` reads what a run left in its directory: ``truth.csv`` (10 ms rows),
``metrics.json`` (scenario, μ, speed, scenario parameters) and ``controller_timing.csv``, whose
``model_err_rms`` column (rad/s; NaN for a controller without a learned model) is the learned
model's filtered RMS one-step yaw-rate error at each cycle.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from harness.analysis.adaptation import adaptation_kpis, relearn_time
from harness.analysis.course import scenario_for
from harness.analysis.fmvss126 import evaluate_sine_with_dwell
from harness.analysis.footprint import Footprint
from harness.analysis.kpi import phase_area
from harness.analysis.run_data import load_timing_csv, load_truth_csv
from harness.analysis.smoothness import delta_m_of, smoothness
from harness.analysis.verdicts import dlc_verdicts
from plant_sim.overrides import apply_vehicle_overrides
from plant_sim.params import load_vehicle_params

KINDS = ("dlc", "sine", "path", "mu_step")
TIMING_FILE = "controller_timing.csv"


def authority_use(truth: dict[str, np.ndarray], peak_torque_nm: float) -> dict[str, float]:
    """How close a run came to the actuator and grip limits, over the manoeuvre (the cycles
    whose |ay| is ≥ 50 % of the run's peak |ay|):

    motor_limit_share: fraction of those cycles with at least one motor command at its
    torque limit (|T| ≥ 98 % of ``peak_torque_nm``, N·m) — the yaw moment the motors can
    add is exhausted there; peak_ay_over_mu_g: max |ay| / (μ g), μ = the median road
    friction under the front-left tyre over the same cycles (-)."""
    ay = np.abs(truth["ay_mps2"])
    peak = float(np.max(ay)) if ay.size else 0.0
    if peak <= 0.0:
        return {"motor_limit_share": 0.0, "peak_ay_over_mu_g": 0.0}
    win = ay >= 0.5 * peak
    tcmd = np.abs(np.stack([truth[f"tcmd_{w}"] for w in ("fl", "fr", "rl", "rr")]))
    at_limit = np.any(tcmd >= 0.98 * peak_torque_nm, axis=0)
    mu = float(np.median(truth["mu_fl"][win]))
    return {"motor_limit_share": float(np.mean(at_limit[win])),
            "peak_ay_over_mu_g": peak / (mu * 9.81) if mu > 0.0 else math.nan}


def torque_smoothness(truth: dict[str, np.ndarray]) -> dict[str, float | None]:
    """harness.analysis.smoothness of the commanded torques ``tcmd_*`` (N·m) at the truth's
    10 ms rows and of their ΔM = T_FR + T_RR − T_FL − T_RL (N·m); cycle = the median row
    spacing, s; MPC period 50 ms."""
    t = np.asarray(truth["t_s"], dtype=float)
    cycle = float(np.median(np.diff(t))) if t.size > 1 else 0.01
    tq = np.stack([truth[f"tcmd_{w}"] for w in ("fl", "fr", "rl", "rr")], axis=1)[1:]
    return smoothness(delta_m_of(tq), tq, cycle_s=cycle)  # row 0: before any command


def scenario_params(params: dict[str, Any]) -> dict[str, Any]:
    """Scenario parameters as the plant parses ``--param`` (numbers as float, a value in
    brackets as a JSON list, anything else as text)."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, str) and value.strip().startswith("["):
            out[key] = json.loads(value)
            continue
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            out[key] = value
    return out


def evaluate(kind: str, truth: dict[str, np.ndarray], *, scenario: str,
             mu: float | None = None, speed_kmh: float | None = None,
             params: dict[str, Any] | None = None, vehicle: dict[str, float] | None = None,
             a_deg: float | None = None) -> dict[str, Any]:
    """Verdicts / KPIs of one run's truth (see the module docstring). ``truth`` may hold
    ``model_err_rms`` (rad/s per row, NaN where none); ``a_deg``: FMVSS 126 A, deg of
    steering-wheel angle (kind ``sine``)."""
    if kind not in KINDS:
        raise ValueError(f"stability: unknown kind {kind!r} (known: {', '.join(KINDS)})")
    par = scenario_params(params or {})
    vp = apply_vehicle_overrides(load_vehicle_params(), dict(vehicle or {}))
    sc = scenario_for(scenario, mu, speed_kmh, par)
    out: dict[str, Any] = {
        "spun": bool(np.any(truth["spun"] > 0.5)),
        "max_abs_beta_deg": float(np.degrees(np.max(np.abs(truth["beta_rad"])))),
        "max_abs_dev_m": float(np.max(np.abs(truth["lateral_dev_m"]))),
        "phase_area": phase_area(truth["beta_rad"], truth["t_s"]),
        **authority_use(truth, vp.peak_torque_nm),
        **torque_smoothness(truth),
    }
    err = truth.get("model_err_rms")
    if kind == "dlc":
        fp = Footprint.for_vehicle(vp.lf_m, vp.lr_m, vp.vehicle_width_m)
        out.update(dlc_verdicts(truth, cones=sc.cones, lanes=sc.lanes,
                                course_end_arc_m=sc.course_end_s, footprint=fp))
    elif kind == "mu_step":
        out.update(adaptation_kpis(truth, float(par["steps"][0][0]), err))
    if kind != "mu_step" and "steps" in par:
        t_step = float(par["steps"][0][0])
        out.update(relearn_time(truth["t_s"], err, t_step) if err is not None
                   else {"relearn_time_s": None, "err_band_radps": None})
    if kind == "sine":
        try:
            r = evaluate_sine_with_dwell(
                truth["t_s"], np.degrees(truth["swa_rad"]), truth["yaw_rate_radps"],
                truth["x_m"], truth["y_m"], truth["yaw_rad"],
                amplitude_deg=par.get("amplitude_deg"), a_deg=a_deg)
            out["fmvss_pass"] = bool(r.passed) and not out["spun"]
            out["lateral_displacement_m"] = float(r.lateral_displacement_m)
        except (ValueError, IndexError):
            out["fmvss_pass"] = False
            out["lateral_displacement_m"] = math.nan
    return out


def model_error_per_row(run_dir: Path, n_rows: int) -> np.ndarray:
    """The learned model's error (rad/s) of the cycle that ended at each truth row: truth row
    k + 1 follows controller cycle k (row 0 is the start: NaN); NaN where the timing CSV has
    no value or no ``model_err_rms`` column."""
    out = np.full(n_rows, math.nan)
    path = Path(run_dir) / TIMING_FILE
    if not path.is_file():
        return out
    timing = load_timing_csv(path)
    if "model_err_rms" not in timing or "cycle" not in timing:
        return out
    rows = timing["cycle"].astype(np.int64) + 1
    keep = (rows >= 0) & (rows < n_rows)
    out[rows[keep]] = timing["model_err_rms"][keep]
    return out


def stability_of_run(run_dir: Path, info: dict[str, Any],
                     vehicle: dict[str, float] | None = None) -> dict[str, Any]:
    """:func:`evaluate` of a run directory; ``info``: ``kind`` (default dlc) and ``a_deg``
    (sine); ``vehicle``: the run's plant overrides."""
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "metrics.json").read_text())
    truth = load_truth_csv(run_dir / "truth.csv")
    truth["model_err_rms"] = model_error_per_row(run_dir, truth["t_s"].size)
    a = info.get("a_deg")
    return evaluate(str(info.get("kind", "dlc")), truth, scenario=str(meta["scenario"]),
                    mu=meta.get("mu"), speed_kmh=meta.get("speed_kmh"),
                    params=dict(meta.get("params") or {}), vehicle=vehicle,
                    a_deg=None if a is None else float(a))
