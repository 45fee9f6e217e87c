"""Adaptation as a benchmark result: the road's grip changes mid-manoeuvre, the car is not
the nominal one, the friction a controller is told is wrong.

Every case runs for every controller over the plan's seeds (runs over the bus, in the
benchmark's campaign: harness/paper/benchmark.py) and reports median [min–max]:

1. Friction steps (plant_sim/road.py ``steps``): in a steady corner held by the
   path-following driver (mu-step-corner: R = 100 m, 65 km/h), under a held steering angle
   (mu-step-steer: no driver in the loop) and in the paper's DLC (dlc-paper, 72 km/h, a
   60 m lead-in, the step at the first gate or between the lane changes); down and up, at several
   levels and times. KPIs (harness/analysis/adaptation.py): yaw-rate overshoot and
   undershoot against the steady value before the step (deg/s), max |β| (deg) and max
   |lateral dev| (m) after it, spins; DLC: the paper and stability verdicts; nmpc-rhonn: the
   re-learning time of its model (s).
2. A car that is not the nominal one: DLC v_max (paper rule, bisection) with each
   perturbation of the benchmark's perturbed car alone and all together, and the loss
   against the nominal car.
3. Friction mis-estimation: DLC v_max on the μ 0.35 road with the controllers told
   ``[controller] mu_estimate`` ∈ plan.mu_estimates (0 = not told). Only a controller with a
   friction parameter in its model (nmpc-mf's Magic-Formula tyres) can be misled; the others
   run the same every time, which the table shows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from can_db.process.argcheck import seed_text
from harness.paper.benchmark import (
    Base,
    RunSource,
    Section,
    bench_run,
    json_section,
    median_range,
    summarise,
    vmax_bisections,
)
from harness.run.spec import RunSpec

Runner = RunSource

CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
PERTURBATIONS: dict[str, dict[str, float]] = {
    "mass +15 %": {"mass_scale": 1.15},
    "Iz +20 %": {"yaw_inertia_scale": 1.20},
    "Cα −20 %": {"cornering_stiffness_scale": 0.80},
    "all three": {"mass_scale": 1.15, "yaw_inertia_scale": 1.20,
                  "cornering_stiffness_scale": 0.80},
}
STEP_KPIS = ("yaw_overshoot_degps", "yaw_undershoot_degps", "max_abs_beta_after_deg",
             "max_abs_dev_after_m", "relearn_time_s")


@dataclass(frozen=True)
class StepCase:
    """One friction-step case: scenario, base μ (-), μ after the step (-), step time (s),
    speed (km/h, None = the scenario's), what to evaluate ("mu_step" or "dlc"), further
    scenario parameters, and whether a driver follows a path (a steering robot's run has no
    path deviation to report)."""

    scenario: str
    mu_before: float
    mu_after: float
    t_step_s: float
    speed_kmh: float | None = None
    kind: str = "mu_step"
    params: tuple[tuple[str, Any], ...] = ()
    follows_path: bool = True

    @property
    def label(self) -> str:
        """Table row label."""
        where = {"mu-step-corner": "corner", "mu-step-steer": "held steer",
                 "dlc-paper": "DLC"}.get(self.scenario, self.scenario)
        sp = "" if self.speed_kmh is None else f" {self.speed_kmh:g} km/h"
        return f"{where}{sp}: μ {self.mu_before:g} → {self.mu_after:g} at {self.t_step_s:g} s"


# 60 m of straight before the DLC's first gate (the paper's course: 20 m), so that the
# learned model has converged (≈ 1 s, gate warm-up 0.5 s) when the grip changes: at 72 km/h
# the car reaches the first gate at ≈ 3 s and is between the lane changes at ≈ 5.5 s.
_DLC_LEAD_IN = (("lead_in_m", 60.0),)


def _default_steps() -> tuple[StepCase, ...]:
    corner = (*(StepCase("mu-step-corner", 1.0, m, t)
                for t in (6.0, 9.0) for m in (0.5, 0.42, 0.36)),
              StepCase("mu-step-corner", 0.6, 0.35, 6.0),
              StepCase("mu-step-corner", 0.45, 1.0, 6.0))
    steer = tuple(StepCase("mu-step-steer", a, b, 6.0, follows_path=False)
                  for a, b in ((1.0, 0.42), (1.0, 0.36), (0.45, 1.0)))
    dlc = tuple(StepCase("dlc-paper", a, b, t, 72.0, "dlc", _DLC_LEAD_IN)
                for t in (3.0, 5.5) for a, b in ((0.7, 0.35), (0.35, 0.7)))
    return corner + steer + dlc


@dataclass
class AdaptationPlan:
    """Sizes of the adaptation study (``quick()`` is the test-suite smoke version)."""

    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    controllers: tuple[str, ...] = CONTROLLERS
    steps: tuple[StepCase, ...] = field(default_factory=_default_steps)
    perturbations: dict[str, dict[str, float]] = field(default_factory=lambda: dict(
        PERTURBATIONS))
    mu_estimates: tuple[float, ...] = (0.0, 0.25, 0.35, 0.5, 1.0)
    bracket: tuple[float, float] = (50.0, 95.0)
    resolution: float = 0.5
    refs: dict[str, Any] = field(default_factory=dict)   # nmpc-rhonn config overrides

    @classmethod
    def quick(cls) -> AdaptationPlan:
        """One seed, two step cases, one perturbation, two friction estimates, coarse v_max."""
        return cls(seeds=(1,), steps=(StepCase("mu-step-corner", 1.0, 0.42, 6.0),
                                      StepCase("dlc-paper", 0.7, 0.35, 3.0, 72.0, "dlc",
                                               _DLC_LEAD_IN)),
                   perturbations={"mass +15 %": {"mass_scale": 1.15}},
                   mu_estimates=(0.0, 0.35), bracket=(60.0, 84.0), resolution=4.0)


def _refs(plan: AdaptationPlan, controller: str, extra: dict[str, Any] | None = None
          ) -> tuple[tuple[str, Any], ...]:
    d = dict(plan.refs) if controller == "nmpc-rhonn" else {}
    d.update(extra or {})
    return tuple(d.items())


def step_spec(case: StepCase, controller: str, seed: int,
              refs: tuple[tuple[str, Any], ...] = ()) -> RunSpec:
    """The RunSpec of one friction-step run."""
    return bench_run(case.scenario, controller, case.speed_kmh, case.mu_before, seed, (), refs,
                     (("steps", ((case.t_step_s, case.mu_after),)), *case.params), case.kind)


def step_tables(plan: AdaptationPlan, runner: Runner) -> dict[str, Any]:
    """Section 1: per case and controller, the step KPIs summarised over the seeds."""
    specs = [step_spec(k, c, s, _refs(plan, c)) for k in plan.steps
             for c in plan.controllers for s in plan.seeds]
    res = iter(runner(specs))
    out: dict[str, Any] = {}
    for k in plan.steps:
        row: dict[str, Any] = {}
        for c in plan.controllers:
            runs = [next(res) for _ in plan.seeds]
            cell: dict[str, Any] = {"n": len(runs), "spun": sum(bool(r["spun"]) for r in runs),
                                    "max_abs_beta_deg": summarise(
                                        [r["max_abs_beta_deg"] for r in runs]),
                                    "max_abs_dev_m": summarise([r["max_abs_dev_m"] for r in runs])}
            if k.kind == "dlc":
                cell["paper"] = sum(bool(r.get("paper")) for r in runs)
                cell["stable"] = sum(bool(r.get("stable")) for r in runs)
                cell["relearn_time_s"] = summarise([r.get("relearn_time_s") for r in runs])
            else:
                for key in STEP_KPIS:
                    cell[key] = summarise([r.get(key) for r in runs])
            cell["not_relearned"] = sum(r.get("relearn_time_s") is None
                                            and r.get("err_band_radps") is not None
                                            for r in runs)
            row[c] = cell
        out[k.label] = {"case": k.__dict__, "by_controller": row}
    return out


def _dlc_base(vehicle: dict[str, float], plan: AdaptationPlan,
              extra: dict[str, Any] | None = None) -> Base:
    return lambda c, s, v: bench_run("dlc-paper", c, v, None, s, tuple(vehicle.items()),
                                     _refs(plan, c, extra))


def vmax_table(plan: AdaptationPlan, runner: Runner, cases: dict[str, Base],
               controllers: tuple[str, ...]) -> dict[str, Any]:
    """DLC v_max (paper rule) per case and controller, median [min–max] over the seeds."""
    out: dict[str, Any] = {}
    for name, base in cases.items():
        vm = vmax_bisections(base, controllers, plan.seeds, ("paper",), runner, plan.bracket,
                             plan.resolution)
        out[name] = {c: summarise([vm[(c, s, "paper")]["vmax_kmh"] for s in plan.seeds])
                     for c in controllers}
    return out


def adaptation_tables(plan: AdaptationPlan, runner: Runner,
                      progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the study; the tables as plain JSON-serialisable data."""
    say = progress or (lambda s: None)
    mpcs = tuple(c for c in plan.controllers if c != "passive")
    say("adaptation: friction steps")
    steps = step_tables(plan, runner)
    say("adaptation: perturbed cars")
    cars = vmax_table(plan, runner, {"nominal": _dlc_base({}, plan)} | {
        k: _dlc_base(v, plan) for k, v in plan.perturbations.items()}, mpcs)
    for row in cars.values():
        for c, s in row.items():
            nom = cars["nominal"][c]["median"]
            s["loss_kmh"] = None if nom is None or s["median"] is None else nom - s["median"]
    say("adaptation: friction estimates")
    est = vmax_table(plan, runner, {
        ("not told" if m == 0.0 else f"told μ {m:g}"): _dlc_base(
            {}, plan, {"controller.mu_estimate": m} if m > 0.0 else None)
        for m in plan.mu_estimates}, mpcs)
    return {"plan": {"seeds": list(plan.seeds), "controllers": list(plan.controllers),
                     "refs": plan.refs, "bracket": list(plan.bracket),
                     "resolution": plan.resolution},
            "steps": steps, "perturbed": cars, "mu_estimate": est}


def _mm(s: dict[str, Any] | None) -> str:
    return median_range(s, "{:.2f}")


def _relearn_cell(controller: str, r: dict[str, Any]) -> str:
    """The re-learning cell: nmpc-rhonn's time (s) and how many seeds were not back."""
    if controller != "nmpc-rhonn":
        return "—"
    back = f" ({r['not_relearned']} not back)" if r["not_relearned"] else ""
    return _mm(r["relearn_time_s"]) + back


def adaptation_markdown(t: dict[str, Any]) -> str:
    """The adaptation section of the benchmark report, from the measured tables only."""
    seeds = t["plan"]["seeds"]
    L = ["## Adaptation: grip that changes, a car that is not the nominal one", "",
         f"Seeds {seed_text(seeds)}; median [min–max] over the seeds. Friction steps change "
         "the grip "
         "of the whole road at the step time (plant_sim/road.py).", "",
         "### Friction steps: yaw overshoot / undershoot (deg/s), max |β| (°) and max "
         "|lateral dev| (m; — under held steering: no path) in the 5 s after the step; "
         "nmpc-rhonn's model re-learning time (s)",
         "", "| case | controller | overshoot | undershoot | max β | max dev | spun | "
         "re-learning |", "|---|---|---|---|---|---|---|---|"]
    for label, row in t["steps"].items():
        if row["case"]["kind"] == "dlc":
            continue
        follows = row["case"]["follows_path"]
        for c, r in row["by_controller"].items():
            L.append(f"| {label} | {c} | {_mm(r['yaw_overshoot_degps'])} | "
                     f"{_mm(r['yaw_undershoot_degps'])} | {_mm(r['max_abs_beta_after_deg'])} | "
                     f"{_mm(r['max_abs_dev_after_m']) if follows else '—'} | "
                     f"{r['spun']}/{r['n']} | "
                     f"{_relearn_cell(c, r)} |")
    L += ["", "### Friction steps in the DLC: verdicts out of the seeds (paper rule / stable), "
          "max |β| (°) and max |lateral dev| (m) over the run; nmpc-rhonn's re-learning time (s)",
          "", "| case | controller | paper | stable | spun | max β | max dev | re-learning |",
          "|---|---|---|---|---|---|---|---|"]
    for label, row in t["steps"].items():
        if row["case"]["kind"] != "dlc":
            continue
        for c, r in row["by_controller"].items():
            L.append(f"| {label} | {c} | {r['paper']}/{r['n']} | {r['stable']}/{r['n']} | "
                     f"{r['spun']} | {_mm(r['max_abs_beta_deg'])} | {_mm(r['max_abs_dev_m'])} | "
                     f"{_relearn_cell(c, r)} |")
    for title, key, loss in (("A car that is not the nominal one: DLC v_max (paper rule), "
                              "km/h (loss against the nominal car)", "perturbed", True),
                             ("Friction mis-estimation: DLC v_max (paper rule) on the μ 0.35 "
                              "road, km/h, by the friction the controllers are told",
                              "mu_estimate", False)):
        rows = t[key]
        ctrls = list(next(iter(rows.values())))
        L += ["", f"### {title}", "", "| case | " + " | ".join(ctrls) + " |",
              "|---|" + "---|" * len(ctrls)]
        for name, row in rows.items():
            cells = []
            for c in ctrls:
                s = row[c]
                cell = median_range(s)
                if loss and name != "nominal" and s.get("loss_kmh") is not None:
                    cell += f" ({s['loss_kmh']:+.1f})"
                cells.append(cell)
            L.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(L) + "\n"


def adaptation_section(plan: AdaptationPlan) -> Callable[[float], Section]:
    """The study as a section of ``rhonn-harness benchmark`` (writes adaptation.json)."""
    return json_section("adaptation", lambda src, a: adaptation_tables(plan, src),
                        adaptation_markdown)
