"""Grip that changes in time (the road's friction steps), the step-response and re-learning
KPIs, the adaptation study end to end, and a friction step across real processes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from harness.analysis.adaptation import relearn_time, step_response
from harness.analysis.run_data import load_truth_csv
from harness.campaign.engine import EngineConfig
from harness.paper.adaptation import (
    AdaptationPlan,
    StepCase,
    adaptation_markdown,
    adaptation_section,
)
from harness.paper.benchmark import run_benchmark
from plant_sim.road import FrictionField, friction_from_spec
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation

G = 9.81


# ------------------------------------------------------------------ the road
def test_friction_steps_change_the_base_and_scale_the_patches() -> None:
    road = friction_from_spec({"mu": 1.0, "patches": [{"x0": 10.0, "mu": 0.5}],
                               "steps": [[2.0, 0.4], {"t_s": 5.0, "mu": 0.8}]})
    assert road.base_mu_at_time(1.99) == 1.0
    assert road.base_mu_at_time(2.0) == 0.4
    assert road.base_mu_at_time(7.0) == 0.8
    now = road.at_time(3.0)
    assert now.mu_at(0.0, 0.0) == pytest.approx(0.4)
    assert now.mu_at(20.0, 0.0) == pytest.approx(0.2)          # the patch keeps its ratio
    # a run's μ override sets the grip before the first step; the steps stay absolute
    assert road.scaled(0.6).base_mu_at_time(3.0) == 0.4


@pytest.mark.parametrize("steps", [((1.0, 0.0),), ((1.0, 2.5),), ((2.0, 0.5), (1.0, 0.4)),
                                   ((-1.0, 0.5),)])
def test_bad_friction_steps_are_refused(steps: tuple[tuple[float, float], ...]) -> None:
    with pytest.raises(ValueError, match="road"):
        FrictionField(1.0, (), steps)


def test_a_friction_step_reaches_the_tyres_and_caps_the_lateral_acceleration() -> None:
    """Held steering at 0.36 g on μ 1, then μ 0.3: the truth's friction changes at the
    first plant cycle at or after the step time, and the lateral acceleration the tyres
    can carry afterwards is bounded by μ g (friction circle, a closed-form bound)."""
    sc = load_scenario("mu-step-steer", steps=[[4.0, 0.3]], duration_s=8.0)
    sim = Simulation(sc, seed=1)
    rows = [sim.truth_row()]
    while not sim.finished:
        sim.step_comm(None)
        rows.append(sim.truth_row())
    t = np.array([r["t_s"] for r in rows])
    mu = np.array([r["mu_fl"] for r in rows])
    ay = np.abs(np.array([r["ay_mps2"] for r in rows]))
    assert np.all(mu[t < 4.0 - 1e-9] == 1.0)
    assert np.all(mu[t > 4.0 + 0.011] == 0.3)
    assert np.mean(ay[(t > 3.0) & (t < 4.0)]) > 0.33 * G        # the corner before the step
    assert np.max(ay[t > 5.0]) <= 0.3 * G * 1.05                # after it: ≤ μ g


# ------------------------------------------------------------------ KPIs
def _corner(r_pre: float, r_peak: float, r_low: float, direction: float = 1.0
            ) -> dict[str, np.ndarray]:
    t = np.arange(0.0, 12.0, 0.01)
    r = np.full(t.size, r_pre)
    r[(t >= 7.0) & (t < 7.5)] = r_peak
    r[(t >= 8.0) & (t < 8.5)] = r_low
    return {"t_s": t, "yaw_rate_radps": np.radians(direction * r),
            "beta_rad": np.where(t > 6.0, np.radians(2.0), np.radians(1.0)),
            "lateral_dev_m": np.where(t > 9.0, 0.7, 0.1)}


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_step_response_measures_overshoot_and_undershoot_in_the_turning_direction(
        direction: float) -> None:
    k = step_response(_corner(10.0, 12.5, 9.0, direction), t_step_s=6.0)
    assert k["yaw_overshoot_degps"] == pytest.approx(2.5)
    assert k["yaw_undershoot_degps"] == pytest.approx(1.0)
    assert k["max_abs_beta_after_deg"] == pytest.approx(2.0)
    assert k["max_abs_dev_after_m"] == pytest.approx(0.7)


def test_relearn_time_is_the_settling_time_of_the_model_error() -> None:
    # e = e0 before the step, then e0 + A exp(−(t − ts)/τ): back inside the band
    # b = 1.5 e0 at ts + τ ln(A / (b − e0)) (closed form).
    t = np.arange(0.0, 12.0, 0.01)
    e0, amp, tau, ts = 0.004, 0.03, 0.4, 6.0
    e = np.where(t < ts, e0, e0 + amp * np.exp(-(t - ts) / tau))
    got = relearn_time(t, e, ts)
    expect = tau * math.log(amp / (1.5 * e0 - e0))
    assert got["err_band_radps"] == pytest.approx(1.5 * e0)
    assert got["relearn_time_s"] == pytest.approx(expect, abs=0.011)
    # an error that never leaves the band: 0; one still above it at the end: None
    assert relearn_time(t, np.full(t.size, e0), ts)["relearn_time_s"] == 0.0
    assert relearn_time(t, np.where(t < ts, e0, 0.05), ts)["relearn_time_s"] is None


# ------------------------------------------------------------------ the study
def test_adaptation_study_small_plan_over_the_bus(tmp_path: Path) -> None:
    # one campaign of real bus runs (two workers); a coarse v_max (60, 72 or 84 km/h)
    plan = AdaptationPlan(seeds=(1,), controllers=("nmpc-rhonn", "nmpc-mf"),
                          steps=(StepCase("mu-step-corner", 1.0, 0.42, 6.0),),
                          perturbations={"mass +15 %": {"mass_scale": 1.15}},
                          mu_estimates=(0.0, 0.35), bracket=(60.0, 84.0), resolution=12.0)
    t = run_benchmark(tmp_path, [adaptation_section(plan)], EngineConfig("local", 2),
                      bar=False, a_deg=40.0)["adaptation"]
    assert t["campaign"]["failed"] == 0
    written = json.loads((tmp_path / "adaptation.json").read_text())
    assert written["steps"] == json.loads(json.dumps(t["steps"], default=str))
    cell = t["steps"]["corner: μ 1 → 0.42 at 6 s"]["by_controller"]
    assert cell["nmpc-rhonn"]["relearn_time_s"]["n"] == 1     # the learned model is timed
    assert cell["nmpc-mf"]["relearn_time_s"]["n"] == 0        # a fixed model is not
    for c in ("nmpc-rhonn", "nmpc-mf"):
        assert cell[c]["yaw_overshoot_degps"]["median"] is not None
        assert t["perturbed"]["mass +15 %"][c]["loss_kmh"] is not None
    # nmpc-rhonn has no friction parameter: telling it μ changes nothing
    est = t["mu_estimate"]
    assert est["told μ 0.35"]["nmpc-rhonn"] == est["not told"]["nmpc-rhonn"]
    md = adaptation_markdown(t)
    assert "re-learning" in md and "told μ 0.35" in md


# ------------------------------------------------------------------ across processes
def test_a_friction_step_over_the_bus(tmp_path: Path) -> None:
    """The packaged friction-step scenario run by the harness across real processes: the
    plant process applies the road's step, and the controller keeps the car in the lane."""
    from harness.report.run_report import run_and_report
    from harness.run.spec import RunSpec

    out = tmp_path / "run"
    res = run_and_report(RunSpec(scenario="mu-step-corner", controller="nmpc-rhonn",
                                    out_dir=out, duration_s=9.0, make_plots=False,
                                    make_rrd=False, plant_extra_args=["--wait-ms", "2000"]))
    assert res.reason == "finished", res.reason
    tr = load_truth_csv(out / "truth.csv")
    t, mu = np.asarray(tr["t_s"]), np.asarray(tr["mu_fl"])
    assert np.all(mu[t < 8.0 - 1e-9] == 1.0) and np.all(mu[t > 8.0 + 0.011] == 0.45)
    assert np.max(np.abs(tr["lateral_dev_m"])) < 1.0
    assert not np.any(np.asarray(tr["spun"]) > 0.5)
