"""The near-limit section of `rhonn-harness benchmark` (harness/paper/handling.py) on a tiny
plan over the bus: every table is filled from real runs, the ablation reports the nominal
and the perturbed car's v_max, and the markdown shows them."""

from __future__ import annotations

import json
from pathlib import Path

from harness.campaign.engine import EngineConfig
from harness.paper.benchmark import run_benchmark
from harness.paper.handling import ABLATION, SMOOTH_KEYS, HandlingPlan, handling_section

MAIN_JOB = "DLC μ 0.35 65 km/h (main job)"
ROW = "default, move weight 0.25 instead of the jerk weight"


def test_handling_section_small_plan_over_the_bus(tmp_path: Path) -> None:
    plan = HandlingPlan(seeds=(1,), who=("nmpc-rhonn",), ablation={ROW: ABLATION[ROW]},
                        bracket=(60.0, 84.0), resolution=12.0, case_filter=(MAIN_JOB,),
                        sine_mus=(0.5,), sine_directions=("left",))
    t = run_benchmark(tmp_path, [handling_section(plan)], EngineConfig("local", 2),
                      bar=False, a_deg=40.0)["handling"]
    assert t["campaign"]["failed"] == 0
    cell = t["cases"][MAIN_JOB]["nmpc-rhonn"]
    for key in SMOOTH_KEYS:
        assert cell[key]["n"] == 1 and cell[key]["median"] >= 0.0, key
    assert cell["wheel_torque_rate_max_Nm_per_s"]["median"] <= 10_000.0 + 1e-6
    for who in (t["vmax"]["nominal"]["nmpc-rhonn"], t["vmax"]["perturbed car"]["nmpc-rhonn"],
                t["ablation"]["vmax"][ROW], t["ablation"]["vmax_perturbed"][ROW]):
        assert who["median"] in (60.0, 72.0, 84.0) or who["median"] is None
    assert t["vmax"]["nominal"]["nmpc-rhonn"]["median"] is not None   # passes at 60 km/h
    assert t["ablation"]["vmax"][ROW]["n"] == 1
    assert t["sine_schedule"]["μ 0.5"]["nmpc-rhonn"]["runs"] == 1
    written = json.loads((tmp_path / "handling.json").read_text())
    assert written["ablation"]["vmax_perturbed"] == json.loads(
        json.dumps(t["ablation"]["vmax_perturbed"], default=str))
    md = (tmp_path / "benchmark.md").read_text()
    assert f"| {ROW} |" in md and "| variant | DLC v_max (paper rule), km/h | perturbed car |" in md
