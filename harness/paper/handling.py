"""Near-limit handling as a benchmark section: smoothness, adaptation and stability of every
controller on the cases where a car is lost or a road changes, against the paper's
baselines and the same baselines held to the same standard, and the ablation of the
nmpc-rhonn design piece by piece.

Runs over the bus in the benchmark's campaign (harness/paper/benchmark.py), median
[min–max] over the plan's seeds. "Who" is a controller with configuration overrides:

* nmpc-rhonn (the packaged default: grip-limited demand, envelope rows, move weight);
* nmpc-mf, lmpc: the paper's baselines (with the motor torque rate and the ΔM rate rows every
  MPC has in the packaged configuration);
* nmpc-mf + grip, lmpc + grip: the same baselines whose yaw reference is bounded by the grip
  estimate (``[handling] baselines_grip_demand``), as a production ESC bounds its reference;
* passive (margins only).

Per case: max |β| (deg), max |lateral dev| (m), spins, the smoothness KPIs of the commanded
torques (harness/analysis/smoothness.py via the ``stability`` post step: ΔM total variation per
second, N·m/s; largest ΔM change in one MPC period, N·m; largest and p99 wheel-torque rate,
N·m/s; ΔM-increment sign reversals per second), and the kind's verdicts (DLC paper/stable,
FMVSS 126 pass and displacement, friction-step overshoot and re-learning time). v_max: DLC
paper rule by bisection, nominal car and the perturbed car (mass +15 %, Iz +20 %, Cα −20 %).
The ablation rows run the same cases for nmpc-rhonn variants (controller overrides).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from can_db.process.argcheck import seed_text
from harness.analysis.fmvss126 import amplitude_schedule_deg
from harness.paper.benchmark import (
    PERTURBED,
    RunSource,
    Section,
    bench_run,
    json_section,
    median_range,
    summarise,
    vmax_bisections,
)
from harness.run.spec import RunSpec

GRIP_BASELINE = {"handling.baselines_grip_demand": True}
WHO: dict[str, tuple[str, dict[str, Any]]] = {
    "nmpc-rhonn": ("nmpc-rhonn", {}),
    "nmpc-mf": ("nmpc-mf", {}),
    "lmpc": ("lmpc", {}),
    "nmpc-mf + grip": ("nmpc-mf", GRIP_BASELINE),
    "lmpc + grip": ("lmpc", GRIP_BASELINE),
}
SMOOTH_KEYS = ("dM_tv_per_s_Nm_per_s", "dM_max_change_per_period_Nm",
               "wheel_torque_rate_max_Nm_per_s", "wheel_torque_rate_p99_Nm_per_s",
               "dM_chatter_per_s")
_PAPER_QP = {"handling.envelope": False}
ABLATION: dict[str, dict[str, Any]] = {
    "previous design: demand + Algorithm 1 by |β| + sideslip guard, paper QP": {
        "kind": "demand", "guard_gain_per_s": 2.5, **_PAPER_QP},
    "smoothness only: previous references + jerk weight": {
        "kind": "demand", "guard_gain_per_s": 2.5, **_PAPER_QP, "mpc.delta_accel_weight": 1.0},
    "+ envelope rows instead of the guard (previous references)": {
        "kind": "demand", "guard_gain_per_s": 0.0},
    "+ grip estimate: grip-limited demand (default)": {},
    "default without Algorithm 1": {"handling.fixed_point_share": 0.0},
    "default without envelope rows (jerk weight kept)": {
        **_PAPER_QP, "mpc.delta_accel_weight": 1.0},
    "default without jerk weight": {"handling.jerk_weight": 0.0},
    "default, move weight 1 instead of the jerk weight": {
        "handling.move_weight": 1.0, "handling.jerk_weight": 0.0},
    "default, move weight 0.25 instead of the jerk weight": {
        "handling.move_weight": 0.25, "handling.jerk_weight": 0.0},
    "bicycle references on the RHONN model, paper QP": {
        "kind": "linear", "guard_gain_per_s": 0.0, **_PAPER_QP},
    "default, a road credited 0.6 g before it has shown grip (grip mu_floor 0.6)": {
        "grip.mu_floor": 0.6},
}


@dataclass(frozen=True)
class Case:
    """One near-limit run case: table label, scenario, μ (None = the scenario's), speed km/h
    (None = the scenario's), scenario parameters, what the post step evaluates."""

    label: str
    scenario: str
    mu: float | None
    speed_kmh: float | None
    params: tuple[tuple[str, Any], ...] = ()
    kind: str = "dlc"


def default_cases(a_deg: float) -> tuple[Case, ...]:
    """The cases (A: FMVSS 126 A, deg, sets the low-μ sine amplitude to its 6.5A)."""
    top = max(amplitude_schedule_deg(a_deg, standard_rule=True))
    return (
        Case("DLC μ 0.35 65 km/h (main job)", "dlc-paper", None, 65.0),
        Case("DLC μ 0.35 77 km/h", "dlc-paper", None, 77.0),
        Case("DLC μ 0.2 65 km/h", "dlc-paper", 0.2, 65.0),
        Case("ISO 3888-2 μ 0.5 60 km/h", "iso3888-2-low-mu", 0.5, 60.0),
        Case("step steer 90° μ 0.5 80 km/h", "step-steer", 0.5, 80.0,
             (("amplitude_deg", 90.0),), "path"),
        Case("sine with dwell 270° μ 1", "sine-with-dwell", 1.0, None,
             (("amplitude_deg", 270.0), ("direction", "left")), "sine"),
        Case(f"sine with dwell {top:g}° μ 0.5", "sine-with-dwell-low-mu", 0.5, None,
             (("amplitude_deg", top), ("direction", "left")), "sine"),
        Case("slippery curve at the limit", "slippery-curve-limit", None, None, (), "path"),
        *(Case(f"corner: μ {a:g} → {b:g} at 6 s", "mu-step-corner", a, None,
               (("steps", ((6.0, b),)),), "mu_step")
          for a, b in ((1.0, 0.36), (0.6, 0.35), (1.0, 0.42), (1.0, 0.5))),
    )


@dataclass
class HandlingPlan:
    """Sizes of the section (``quick()`` is the test-suite smoke version)."""

    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    who: tuple[str, ...] = tuple(WHO)
    ablation: dict[str, dict[str, Any]] = field(default_factory=lambda: dict(ABLATION))
    bracket: tuple[float, float] = (60.0, 90.0)
    resolution: float = 0.5
    case_filter: tuple[str, ...] = ()      # labels to keep (empty: all)
    sine_seeds: tuple[int, ...] = (1,)
    sine_mus: tuple[float, ...] = (1.0, 0.5)
    sine_directions: tuple[str, ...] = ("left", "right")

    @classmethod
    def quick(cls) -> HandlingPlan:
        """One seed, two controllers, one ablation row, two cases, coarse v_max."""
        return cls(seeds=(1,), who=("nmpc-rhonn", "lmpc"),
                   ablation={"default without Algorithm 1": ABLATION[
                       "default without Algorithm 1"]},
                   bracket=(60.0, 84.0), resolution=4.0,
                   case_filter=("DLC μ 0.35 65 km/h (main job)", "corner: μ 1 → 0.36 at 6 s"),
                   sine_mus=(0.5,), sine_directions=("left",))


def _spec(case: Case, controller: str, seed: int, overrides: dict[str, Any],
          a_deg: float) -> RunSpec:
    return bench_run(case.scenario, controller, case.speed_kmh, case.mu, seed, (),
                     tuple(overrides.items()), case.params, case.kind,
                     a_deg if case.kind == "sine" else None)


def _cell(runs: list[dict[str, Any]], kind: str) -> dict[str, Any]:
    """Summaries of one (case, who) over the seeds."""
    cell: dict[str, Any] = {"n": len(runs), "spun": sum(bool(r.get("spun")) for r in runs)}
    for key in ("max_abs_beta_deg", "max_abs_dev_m", *SMOOTH_KEYS):
        cell[key] = summarise([r.get(key) for r in runs])
    if kind == "dlc":
        cell["paper"] = sum(bool(r.get("paper")) for r in runs)
        cell["stable"] = sum(bool(r.get("stable")) for r in runs)
    elif kind == "sine":
        cell["fmvss_pass"] = sum(bool(r.get("fmvss_pass")) for r in runs)
        cell["lateral_displacement_m"] = summarise([r.get("lateral_displacement_m")
                                                    for r in runs])
    elif kind == "mu_step":
        for key in ("yaw_overshoot_degps", "yaw_undershoot_degps", "relearn_time_s"):
            cell[key] = summarise([r.get(key) for r in runs])
        cell["not_relearned"] = sum(r.get("relearn_time_s") is None
                                    and r.get("err_band_radps") is not None for r in runs)
    return cell


def _rows(cases: tuple[Case, ...], who: dict[str, tuple[str, dict[str, Any]]],
          seeds: tuple[int, ...], runner: RunSource, a_deg: float) -> dict[str, Any]:
    specs = [_spec(k, c, s, ov, a_deg) for k in cases for c, ov in who.values() for s in seeds]
    res = iter(runner(specs))
    return {k.label: {name: _cell([next(res) for _ in seeds], k.kind) for name in who}
            for k in cases}


def _vmax(who: dict[str, tuple[str, dict[str, Any]]], plan: HandlingPlan, runner: RunSource,
          vehicle: dict[str, float]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, (c, ov) in who.items():
        base = (lambda ctrl, s, v, ov=ov: bench_run(  # noqa: E731
            "dlc-paper", ctrl, v, None, s, tuple(vehicle.items()), tuple(ov.items())))
        vm = vmax_bisections(base, (c,), plan.seeds, ("paper",), runner, plan.bracket,
                             plan.resolution)
        out[name] = summarise([vm[(c, s, "paper")]["vmax_kmh"] for s in plan.seeds])
    return out


def sine_schedule(plan: HandlingPlan, who: dict[str, tuple[str, dict[str, Any]]],
                  runner: RunSource, a_deg: float) -> dict[str, Any]:
    """FMVSS 126 over the whole amplitude schedule (1.5A … max(6.5A, 270°), both
    directions) per road and who: passes, spins, largest |β| (deg), smallest displacement
    at ≥ 5A (m), largest wheel-torque rate (N·m/s)."""
    amps = amplitude_schedule_deg(a_deg, standard_rule=True)
    if plan.case_filter:          # the smoke plan: the top amplitude only
        amps = amps[-1:]
    out: dict[str, Any] = {"amplitudes_deg": amps}
    for mu in plan.sine_mus:
        sc = "sine-with-dwell" if mu >= 1.0 else "sine-with-dwell-low-mu"
        grid = [(a, d, s) for a in amps for d in plan.sine_directions for s in plan.sine_seeds]
        specs = [bench_run(sc, c, None, mu, s, (), tuple(ov.items()),
                           (("amplitude_deg", a), ("direction", d)), "sine", a_deg)
                 for c, ov in who.values() for a, d, s in grid]
        res = iter(runner(specs))
        row: dict[str, Any] = {}
        for name in who:
            rs = [next(res) for _ in grid]
            disp = [r.get("lateral_displacement_m") for r, (a, _, _) in zip(rs, grid, strict=True)
                    if a >= 5.0 * a_deg - 1e-9]
            disp = [x for x in disp if x is not None]
            row[name] = {"runs": len(rs), "fmvss_pass": sum(bool(r.get("fmvss_pass")) for r in rs),
                         "spun": sum(bool(r.get("spun")) for r in rs),
                         "max_beta_deg": max((r.get("max_abs_beta_deg") or 0.0) for r in rs),
                         "min_displacement_m": min(disp) if disp else None,
                         "wheel_torque_rate_max_Nm_per_s": max(
                             (r.get("wheel_torque_rate_max_Nm_per_s") or 0.0) for r in rs),
                         "dM_tv_per_s_Nm_per_s": summarise([r.get("dM_tv_per_s_Nm_per_s")
                                                            for r in rs])}
        out[f"μ {mu:g}"] = row
    return out


def handling_tables(plan: HandlingPlan, runner: RunSource, a_deg: float) -> dict[str, Any]:
    """The section's tables as plain JSON-serialisable data."""
    cases = tuple(k for k in default_cases(a_deg)
                  if not plan.case_filter or k.label in plan.case_filter)
    who = {n: WHO[n] for n in plan.who}
    t: dict[str, Any] = {"plan": {"seeds": list(plan.seeds), "who": list(plan.who),
                                  "bracket": list(plan.bracket),
                                  "resolution": plan.resolution, "a_deg": a_deg},
                         "cases": _rows(cases, who, plan.seeds, runner, a_deg)}
    nominal = _vmax(who, plan, runner, {})
    perturbed = _vmax(who, plan, runner, PERTURBED)
    for name in who:
        n, p = nominal[name]["median"], perturbed[name]["median"]
        perturbed[name]["loss_kmh"] = None if n is None or p is None else n - p
    t["vmax"] = {"nominal": nominal, "perturbed car": perturbed}
    t["sine_schedule"] = sine_schedule(plan, who, runner, a_deg)
    variants = {name: ("nmpc-rhonn", ov) for name, ov in plan.ablation.items()}
    t["ablation"] = {"cases": _rows(cases, variants, plan.seeds, runner, a_deg),
                     "vmax": _vmax(variants, plan, runner, {}),
                     "vmax_perturbed": _vmax(variants, plan, runner, PERTURBED)}
    return t


# ------------------------------------------------------------------------ report
def _kn(s: dict[str, Any] | None) -> str:
    """kN·m/s (or kN·m) from N·m/s, median [min–max]."""
    if not s or s.get("median") is None:
        return "—"
    return median_range({k: (v / 1000.0 if isinstance(v, float) else v)
                         for k, v in s.items()}, "{:.2f}")


def _verdict(cell: dict[str, Any]) -> str:
    n = cell["n"]
    if "paper" in cell:
        return f"paper {cell['paper']}/{n}, stable {cell['stable']}/{n}"
    if "fmvss_pass" in cell:
        return (f"FMVSS {cell['fmvss_pass']}/{n}, "
                f"{median_range(cell['lateral_displacement_m'], '{:.2f}')} m")
    if "yaw_overshoot_degps" in cell:
        nb = f", {cell['not_relearned']} not back" if cell["not_relearned"] else ""
        return (f"overshoot {median_range(cell['yaw_overshoot_degps'], '{:.2f}')} °/s, "
                f"re-learning {median_range(cell['relearn_time_s'], '{:.2f}')} s{nb}")
    return "—"


def _case_table(rows: dict[str, Any]) -> list[str]:
    L = ["| case | who | ΔM TV/s, kN·m/s | max ΔM change per period, kN·m | wheel-torque rate "
         "max / p99, kN·m/s | chatter, 1/s | max β, ° | max dev, m | spun | verdicts |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for label, by_who in rows.items():
        for name, c in by_who.items():
            L.append(f"| {label} | {name} | {_kn(c['dM_tv_per_s_Nm_per_s'])} | "
                     f"{_kn(c['dM_max_change_per_period_Nm'])} | "
                     f"{_kn(c['wheel_torque_rate_max_Nm_per_s'])} / "
                     f"{_kn(c['wheel_torque_rate_p99_Nm_per_s'])} | "
                     f"{median_range(c['dM_chatter_per_s'], '{:.1f}')} | "
                     f"{median_range(c['max_abs_beta_deg'])} | "
                     f"{median_range(c['max_abs_dev_m'], '{:.2f}')} | "
                     f"{c['spun']}/{c['n']} | {_verdict(c)} |")
    return L


def handling_markdown(t: dict[str, Any]) -> str:
    """The section as markdown."""
    seeds = t["plan"]["seeds"]
    L = ["", "## Near-limit handling: smoothness, adaptation, stability", "",
         f"Seeds {seed_text(seeds)}; median [min–max] over the seeds; over the bus. "
         "Smoothness from the "
         "commanded wheel torques (harness/analysis/smoothness.py). \"+ grip\": the baseline's "
         "yaw reference bounded by the grip estimate.", "", *_case_table(t["cases"]), "",
         "### DLC v_max (paper rule), km/h", "",
         "| who | nominal car | perturbed car (mass +15 %, Iz +20 %, Cα −20 %) | loss |",
         "|---|---|---|---|"]
    vm = t["vmax"]
    for name, s in vm["nominal"].items():
        p = vm["perturbed car"][name]
        loss = "—" if p.get("loss_kmh") is None else f"{p['loss_kmh']:.1f}"
        L.append(f"| {name} | {median_range(s)} | {median_range(p)} | {loss} |")
    sw = t["sine_schedule"]
    L += ["", f"### Sine with dwell over the amplitude schedule ({len(sw['amplitudes_deg'])} "
          "amplitudes × directions × seeds)", "",
          "| road | who | FMVSS 126 passes | spins | max \\|β\\|, ° | min displacement at ≥ 5A, m "
          "| max wheel-torque rate, kN·m/s | ΔM TV/s, kN·m/s |",
          "|---|---|---|---|---|---|---|---|"]
    for road, row in sw.items():
        if road == "amplitudes_deg":
            continue
        for name, c in row.items():
            d = "—" if c["min_displacement_m"] is None else f"{c['min_displacement_m']:.2f}"
            L.append(f"| {road} | {name} | {c['fmvss_pass']}/{c['runs']} | {c['spun']} | "
                     f"{c['max_beta_deg']:.1f} | {d} | "
                     f"{c['wheel_torque_rate_max_Nm_per_s'] / 1000.0:.1f} | "
                     f"{_kn(c['dM_tv_per_s_Nm_per_s'])} |")
    L += ["", "### Ablation of the nmpc-rhonn design (same cases)", "",
          "| variant | DLC v_max (paper rule), km/h | perturbed car | loss |", "|---|---|---|---|"]
    perturbed = t["ablation"].get("vmax_perturbed", {})
    for name, s in t["ablation"]["vmax"].items():
        p = perturbed.get(name)
        loss = ("—" if p is None or p["median"] is None or s["median"] is None
                else f"{s['median'] - p['median']:.1f}")
        L.append(f"| {name} | {median_range(s)} | {median_range(p)} | {loss} |")
    L += ["", *_case_table(t["ablation"]["cases"])]
    return "\n".join(L) + "\n"


def handling_section(plan: HandlingPlan) -> Callable[[float], Section]:
    """The study as a section of ``rhonn-harness benchmark`` (writes handling.json)."""
    return json_section("handling", lambda src, a: handling_tables(plan, src, a),
                        handling_markdown)
