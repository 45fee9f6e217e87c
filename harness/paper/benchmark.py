"""`rhonn-harness benchmark`: a benchmark that tells stability from lane keeping.

Every experiment is a list of :class:`RunSpec` (one closed-loop run each) handed to
:func:`run_specs`, which returns one result dict per spec — so a campaign runner can take
the lists over later. Runs go through the in-process lockstep loop
(harness/run/inprocess_loop.py: the same frames, codec and node logic as a bus run, whose
torque frames are bit-identical to a lockstep bus run with the same seed) in a process pool;
:func:`confirm_on_bus` repeats chosen runs as real cross-process bus runs.

A seed varies the plant's sensor noise and biases (plant_sim/overrides.py) and the RHONN's
initial weights (``[rhonn] init_seed``). Tables (see :func:`build_tables`):

1. DLC μ 0.35 (dlc-paper): v_max per rule — *paper* (CG ≤ 1.0 m, |β| ≤ 8°), *course*
   (footprint, no cone, ISO 3888) and *stable* (no spin, |β| ≤ 8°, yaw rate settles) —
   one bisection per controller, seed and rule; median [min–max] over the seeds; the
   largest max |β| at any speed that passes the paper rule; phase area at 65 km/h.
2. Perturbed car: v_max (paper rule) with mass +15 %, Iz +20 %, cornering stiffness −20 %,
   and on a road of μ 0.30 (no controller knows μ: the model-based baselines keep their
   nominal tyre model, the RHONN relearns), and the loss against the nominal car.
3. Stability margins: runs where a car can be lost with control — DLC at μ 0.2 / 0.35 / 0.5
   well above v_max, the same with the plant's motor torque limit halved (less ΔM
   authority), ISO 3888-2 at μ 0.5; stable verdicts out of the seeds and max |β|.
4. Sine with dwell at μ 1.0 and 0.5, amplitudes 1.5A … max(6.5A, 270°), both directions:
   FMVSS 126 pass count, spins and the largest |β|.
5. Slippery curve at the limit (slippery-curve-limit, R = 165 m) and the paper's curve.
6. Ablation of the nmpc-rhonn references (variant → KPIs): Algorithm 1 (the paper's), on
   the slow weight copy, driver intent with steering lead, the default bicycle demand with
   Algorithm 1 from |β| 1–3° or 2–4°, with the sideslip guard (with and without its
   look-ahead, at two gains), without Algorithm 1, with the learned demand, with longer
   horizons (N = 6, 10: the unblocked superset of a move-blocked long horizon), and the
   linear references on the RHONN model; each row also gives the yaw overshoot after a
   friction step in a steady corner.

The adaptation study (harness/paper/adaptation.py) and the Pareto fronts
(harness/paper/pareto.py) are further sections of the same command.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

MPCS = ("nmpc-rhonn", "nmpc-mf", "lmpc")
RULES = ("paper", "course", "stable")
PERTURBED = {"mass_scale": 1.15, "yaw_inertia_scale": 1.20, "cornering_stiffness_scale": 0.80}
HALF_TORQUE = {"peak_torque_nm": 225.0}
_OFF = {"guard_gain_per_s": 0.0}   # variants without the sideslip guard
_A1 = {"kind": "algorithm1", **_OFF}
# friction steps in the steady corner (mu-step-corner at 6 s) of the ablation: (μ before, after)
ABLATION_MU_STEPS = ((1.0, 0.36), (0.6, 0.35))
_NO_A1 = {"blend_beta_lo": 0.52, "blend_beta_hi": 0.7}   # Algorithm 1 never takes over
VARIANTS: dict[str, dict[str, Any]] = {
    "algorithm1 (paper)": _A1,
    "algorithm1, slow weights τ=1 s": {**_A1, "slow_tau_s": 1.0},
    "intent + lead 0.1 s + grip limit": {"kind": "intent", "intent_lead_s": 0.1,
                                         "intent_ay_margin": 1.15, **_OFF},
    "demand, Algorithm 1 from |β| 1–3°, no guard": {"kind": "demand", **_OFF},
    "demand, Algorithm 1 from |β| 2–4°, no guard": {"kind": "demand", "blend_beta_lo": 0.0349,
                                                    "blend_beta_hi": 0.0698, **_OFF},
    "demand + guard on β alone, 5/s": {"kind": "demand", "guard_lead_s": 0.0,
                                       "guard_gain_per_s": 5.0},
    "demand + guard on β + 0.4 s·β̇, 2.5/s (default)": {"kind": "demand"},
    "demand + guard on β + 0.4 s·β̇, 5/s": {"kind": "demand", "guard_gain_per_s": 5.0},
    "demand + guard on β + 0.2 s·β̇, 2.5/s": {"kind": "demand", "guard_lead_s": 0.2},
    "demand without Algorithm 1 + guard (default)": {"kind": "demand", **_NO_A1},
    "learned demand (blend) + guard (default)": {"kind": "blend"},
    "demand + guard, thresholds scaled with the grip (14°/g, 3–5°)": {
        "kind": "demand", "grip_beta_per_g": 0.2443, "grip_beta_max": 0.0873},
    "default + innovation-adaptive EKF process noise (e²/s > 9)": {
        "kind": "demand", "rhonn.ekf.q_nis": 9.0},
    "demand + guard (default) from 2°": {"kind": "demand", "guard_beta_rad": 0.0349},
    "demand + guard, horizon N = 6 (0.3 s)": {"kind": "demand", "mpc.horizon": 6},
    "demand + guard, horizon N = 10 (0.5 s)": {"kind": "demand", "mpc.horizon": 10},
    "linear refs on the RHONN model": {"kind": "linear", **_OFF},
}


@dataclass(frozen=True)
class RunSpec:
    """One closed-loop run. speed km/h; mu -; vehicle: plant overrides; refs: [references]
    overrides of the controller config ("SECTION.KEY" for another section; any controller);
    params: scenario overrides; kind: what to evaluate
    ("dlc" verdicts, "sine" FMVSS 126, "path" deviation only, "mu_step" the response to
    the road's first friction step ``params["steps"]`` and the model's re-learning time)."""

    scenario: str
    controller: str
    speed_kmh: float | None = None
    mu: float | None = None
    seed: int = 0
    vehicle: tuple[tuple[str, float], ...] = ()
    refs: tuple[tuple[str, Any], ...] = ()
    params: tuple[tuple[str, Any], ...] = ()
    kind: str = "dlc"
    a_deg: float | None = None


# ------------------------------------------------------------------------ configs
def controller_config_text(seed: int, refs: dict[str, Any] | None = None) -> str:
    """The packaged default.toml with ``[rhonn] init_seed = seed`` and ``[references]``
    overrides (a key set here replaces the packaged line of that section; a key written
    ``"SECTION.KEY"``, e.g. ``"mpc.horizon"``, overrides KEY in [SECTION] instead)."""
    text = resources.files("controller").joinpath("config/default.toml").read_text()
    over: dict[str, dict[str, Any]] = {"rhonn": {"init_seed": int(seed)}, "references": {}}
    for k, v in (refs or {}).items():
        section, _, key = k.rpartition(".")
        over.setdefault(section or "references", {})[key] = v
    out: list[str] = []
    section = ""
    for line in text.splitlines():
        m = re.match(r"^\[([^\]]+)\]", line)
        if m:
            section = m.group(1)
            out.append(line)
            for k, v in over.get(section, {}).items():
                out.append(f"{k} = {json.dumps(v) if isinstance(v, str) else repr(v)}")
            continue
        km = re.match(r"^(\w+)\s*=", line)
        if km and km.group(1) in over.get(section, {}):
            continue
        out.append(line)
    return "\n".join(out) + "\n"


def _config_path(cache: Path, seed: int, refs: tuple[tuple[str, Any], ...]) -> str:
    """A controller TOML for (seed, refs) in ``cache``, named by the hash of its text (a
    changed packaged default.toml never reuses a stale file)."""
    text = controller_config_text(seed, dict(refs))
    path = cache / f"ctrl-{hashlib.sha1(text.encode()).hexdigest()[:16]}.toml"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        tmp.replace(path)
    return str(path)


# ------------------------------------------------------------------------ one run
def evaluate(spec: RunSpec, truth: dict[str, np.ndarray]) -> dict[str, Any]:
    """Verdicts / KPIs of one run's truth (see RunSpec.kind)."""
    from harness.analysis.course import scenario_for
    from harness.analysis.footprint import Footprint
    from harness.analysis.kpi import phase_area
    from harness.analysis.verdicts import dlc_verdicts
    from plant_sim.overrides import apply_vehicle_overrides
    from plant_sim.params import load_vehicle_params

    vp = apply_vehicle_overrides(load_vehicle_params(), dict(spec.vehicle))
    sc = scenario_for(spec.scenario, spec.mu, spec.speed_kmh, dict(spec.params))
    out: dict[str, Any] = {
        "spun": bool(np.any(truth["spun"] > 0.5)),
        "max_abs_beta_deg": float(np.degrees(np.max(np.abs(truth["beta_rad"])))),
        "max_abs_dev_m": float(np.max(np.abs(truth["lateral_dev_m"]))),
        "phase_area": phase_area(truth["beta_rad"], truth["t_s"]),
        **authority_use(truth, vp.peak_torque_nm),
    }
    if spec.kind == "dlc":
        fp = Footprint.for_vehicle(vp.lf_m, vp.lr_m, vp.vehicle_width_m)
        out.update(dlc_verdicts(truth, cones=sc.cones, lanes=sc.lanes,
                                course_end_arc_m=sc.course_end_s, footprint=fp))
    elif spec.kind == "mu_step":
        from harness.analysis.adaptation import adaptation_kpis

        t_step = float(dict(spec.params)["steps"][0][0])
        out.update(adaptation_kpis(truth, t_step, truth.get("model_err_rms")))
    if spec.kind != "mu_step" and "steps" in dict(spec.params):
        from harness.analysis.adaptation import relearn_time

        err = truth.get("model_err_rms")
        t_step = float(dict(spec.params)["steps"][0][0])
        out.update(relearn_time(truth["t_s"], err, t_step) if err is not None
                   else {"relearn_time_s": None, "err_band_radps": None})
    if spec.kind == "sine":
        from harness.analysis.fmvss126 import evaluate_sine_with_dwell

        try:
            r = evaluate_sine_with_dwell(
                truth["t_s"], np.degrees(truth["swa_rad"]), truth["yaw_rate_radps"],
                truth["x_m"], truth["y_m"], truth["yaw_rad"],
                amplitude_deg=dict(spec.params).get("amplitude_deg"), a_deg=spec.a_deg)
            out["fmvss_pass"] = bool(r.passed) and not out["spun"]
            out["lateral_displacement_m"] = float(r.lateral_displacement_m)
        except (ValueError, IndexError):
            out["fmvss_pass"] = False
            out["lateral_displacement_m"] = math.nan
    return out


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


def run_spec(spec: RunSpec, cache_dir: str) -> dict[str, Any]:
    """Run one spec in this process (pool worker entry) and evaluate it."""
    from harness.run.inprocess_loop import run_in_process

    config = _config_path(Path(cache_dir), spec.seed, spec.refs) \
        if spec.controller == "nmpc-rhonn" or spec.refs else None
    res = run_in_process(spec.scenario, spec.controller, mu=spec.mu, speed_kmh=spec.speed_kmh,
                         seed=spec.seed, config=config, vehicle=dict(spec.vehicle),
                         **dict(spec.params))
    truth = dict(res.truth)
    # the model error of the cycle that ended at each truth row (none for row 0)
    truth["model_err_rms"] = np.concatenate([[math.nan], res.model_err_rms])
    return evaluate(spec, truth)


def run_specs(specs: list[RunSpec], jobs: int = 2, cache_dir: str | None = None
              ) -> list[dict[str, Any]]:
    """Results in the order of ``specs`` (a process pool of ``jobs`` workers; jobs ≤ 1 runs
    in this process). Identical specs are run once."""
    cache = cache_dir or str(Path(os.environ.get("TMPDIR", "/tmp")) / "rhonn-bench-configs")
    uniq = list(dict.fromkeys(specs))
    if jobs <= 1 or len(uniq) == 1:
        got = [run_spec(s, cache) for s in uniq]
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            try:
                got = list(pool.map(run_spec, uniq, [cache] * len(uniq), chunksize=1))
            except KeyboardInterrupt:  # SIGINT/SIGTERM: the workers stop now, not after a run
                from harness.run.procs import stop_descendants

                stop_descendants(grace_s=1.0)
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    by = dict(zip(uniq, got, strict=True))
    return [by[s] for s in specs]


# ------------------------------------------------------------------------ v_max
def vmax_bisections(base: Callable[[str, int, float], RunSpec], controllers: Iterable[str],
                    seeds: Iterable[int], rules: Iterable[str], runner: Callable[
                        [list[RunSpec]], list[dict[str, Any]]],
                    bracket: tuple[float, float] = (40.0, 100.0), resolution: float = 0.5
                    ) -> dict[tuple[str, int, str], dict[str, Any]]:
    """One bisection per (controller, seed, rule), all driven together; a probe run once
    serves every rule. base(controller, seed, speed) → the probe's RunSpec."""
    from harness.paper.vmax import Bisection

    bis = {(c, s, r): Bisection(c, lo_kmh=bracket[0], hi_kmh=bracket[1],
                                resolution_kmh=resolution, verify_offsets_kmh=(), rule=r)
           for c in controllers for s in seeds for r in rules}
    done: dict[tuple[str, int, float], dict[str, Any]] = {}
    while True:
        want: dict[tuple[str, int, str], list[float]] = {k: b.pending() for k, b in bis.items()
                                                        if not b.done}
        todo = sorted({(k[0], k[1], v) for k, vs in want.items() for v in vs} - set(done))
        if todo:
            res = runner([base(c, s, v) for c, s, v in todo])
            done.update(dict(zip(todo, res, strict=True)))
        fed = False
        for k, vs in want.items():
            for v in vs:
                b = bis[k]
                b.record(v, done[(k[0], k[1], v)])
                fed = True
        if not fed:
            break
    out = {}
    for k, b in bis.items():
        j = b.to_json()
        passing = [done[(k[0], k[1], p["speed_kmh"])] for p in b.probes if p["passed"]]
        j["max_beta_passing_deg"] = max((p["max_abs_beta_deg"] for p in passing), default=None)
        out[k] = j
    return out


def summarise(values: list[float | None]) -> dict[str, Any]:
    """Median and min–max of the finite values (None entries counted as missing)."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    if not v:
        return {"median": None, "min": None, "max": None, "n": 0}
    return {"median": float(np.median(v)), "min": min(v), "max": max(v), "n": len(v)}


# ------------------------------------------------------------------------ plan
@dataclass
class BenchmarkPlan:
    """Sizes of the benchmark (the quick one is the test-suite smoke version)."""

    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    ablation_seeds: tuple[int, ...] = (1, 2, 3)
    sine_seeds: tuple[int, ...] = (1,)
    controllers: tuple[str, ...] = MPCS
    bracket: tuple[float, float] = (50.0, 95.0)
    resolution: float = 0.5
    margin_cases: tuple[tuple[str, float, float, tuple[tuple[str, float], ...]], ...] = (
        ("dlc-paper", 0.2, 65.0, ()), ("dlc-paper", 0.5, 100.0, ()),
        ("dlc-paper", 0.35, 80.0, tuple(HALF_TORQUE.items())),
        ("iso3888-2-low-mu", 0.5, 60.0, ()))
    sine_mus: tuple[float, ...] = (1.0, 0.5)
    sine_directions: tuple[str, ...] = ("left", "right")
    perturbed_cases: tuple[str, ...] = ("car", "mu")
    curves: tuple[str, ...] = ("slippery-curve-limit",)
    curve_radii_m: tuple[float, ...] = (165.0, 170.0, 175.0, 185.0, 200.0, 220.0)
    limit_speed_kmh: float = 77.0
    variants: dict[str, dict[str, Any]] = field(default_factory=lambda: dict(VARIANTS))
    quick: bool = False

    @classmethod
    def smoke(cls) -> BenchmarkPlan:
        """A few runs only (tests): 1 seed, 2 controllers, coarse bisection."""
        return cls(seeds=(1,), ablation_seeds=(1,), sine_seeds=(1,),
                   controllers=("nmpc-rhonn", "nmpc-mf"), bracket=(50.0, 90.0),
                   resolution=5.0, margin_cases=(("dlc-paper", 0.35, 90.0, ()),),
                   sine_mus=(0.5,), sine_directions=("left",), curve_radii_m=(165.0, 200.0),
                   perturbed_cases=("car",),
                   variants={"algorithm1 (paper)": _A1,
                             "linear refs on the RHONN model": {"kind": "linear"}},
                   quick=True)


def _sis_a_deg() -> float:
    """A (deg) from the passive car's slowly-increasing-steer run at μ 1 (FMVSS 126)."""
    from harness.analysis.fmvss126 import find_a_deg
    from harness.run.inprocess_loop import run_in_process

    res = run_in_process("slowly-increasing-steer", "passive", seed=0)
    return find_a_deg(np.degrees(res.truth["swa_rad"]), res.truth["ay_mps2"])


def build_tables(plan: BenchmarkPlan, jobs: int = 2,
                 progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the whole benchmark; returns the tables as plain data (JSON-serialisable)."""
    say = progress or (lambda s: None)

    def runner(specs: list[RunSpec]) -> list[dict[str, Any]]:
        return run_specs(specs, jobs)

    tables: dict[str, Any] = {"plan": {k: v for k, v in asdict(plan).items()
                                       if k != "variants"} | {"variants": plan.variants}}
    ctrls = plan.controllers

    def dlc(vehicle: dict[str, float], mu: float | None, refs: dict[str, Any] | None = None
            ) -> Callable[[str, int, float], RunSpec]:
        return lambda c, s, v: RunSpec("dlc-paper", c, v, mu, s, tuple(vehicle.items()),
                                       tuple((refs or {}).items()) if c == "nmpc-rhonn" else ())

    say("DLC v_max per rule")
    vm = vmax_bisections(dlc({}, None), ctrls, plan.seeds, RULES, runner, plan.bracket,
                         plan.resolution)
    t1: dict[str, Any] = {}
    for c in ctrls:
        row: dict[str, Any] = {}
        for r in RULES:
            row[r] = summarise([vm[(c, s, r)]["vmax_kmh"] for s in plan.seeds])
            row[r]["above_bracket"] = sum(vm[(c, s, r)]["status"] == "above_bracket"
                                          for s in plan.seeds)
        row["max_beta_passing_deg"] = max(
            (vm[(c, s, "paper")]["max_beta_passing_deg"] or 0.0 for s in plan.seeds),
            default=None)
        t1[c] = row
    pa = runner([RunSpec("dlc-paper", c, 65.0, None, s) for c in ctrls for s in plan.seeds])
    for i, c in enumerate(ctrls):
        n = len(plan.seeds)
        t1[c]["phase_area_65"] = summarise([p["phase_area"] for p in pa[i * n:(i + 1) * n]])
    tables["dlc_vmax"] = t1

    say("perturbed car")
    t2: dict[str, Any] = {}
    cases = {"car": ("mass +15 %, Iz +20 %, Cα −20 %", PERTURBED, None),
             "mu": ("road μ 0.30 (no controller knows μ)", {}, 0.30)}
    for name, veh, mu in (cases[k] for k in plan.perturbed_cases):
        vp = vmax_bisections(dlc(veh, mu), ctrls, plan.seeds, ("paper",), runner,
                             plan.bracket, plan.resolution)
        t2[name] = {}
        for c in ctrls:
            s = summarise([vp[(c, sd, "paper")]["vmax_kmh"] for sd in plan.seeds])
            nom = t1[c]["paper"]["median"]
            s["loss_kmh"] = None if s["median"] is None or nom is None else nom - s["median"]
            t2[name][c] = s
    tables["perturbed"] = t2

    say("stability margins")
    t3: dict[str, Any] = {}
    specs = [RunSpec(sc, c, v, mu, s, veh) for sc, mu, v, veh in plan.margin_cases
             for c in (*ctrls, "passive") for s in plan.seeds]
    res = iter(runner(specs))
    for sc, mu, v, veh in plan.margin_cases:
        key = f"{sc} μ {mu:g} {v:g} km/h" + (" motor torque halved" if veh else "")
        t3[key] = {}
        for c in (*ctrls, "passive"):
            rs = [next(res) for _ in plan.seeds]
            t3[key][c] = {"stable": sum(r["stable"] for r in rs),
                          "course": sum(r["course"] for r in rs),
                          "spun": sum(r["spun"] for r in rs), "n": len(rs),
                          "max_beta_deg": summarise([r["max_abs_beta_deg"] for r in rs])}
    tables["margins"] = t3

    say("sine with dwell")
    from harness.analysis.fmvss126 import amplitude_schedule_deg

    a_deg = _sis_a_deg()
    amps = amplitude_schedule_deg(a_deg, standard_rule=True)
    if plan.quick:
        amps = amps[-1:]
    t4: dict[str, Any] = {"a_deg": a_deg, "amplitudes_deg": amps}
    for mu in plan.sine_mus:
        sc = "sine-with-dwell" if mu >= 1.0 else "sine-with-dwell-low-mu"
        specs = [RunSpec(sc, c, None, mu, s, (), (), (("amplitude_deg", a), ("direction", d)),
                         "sine", a_deg)
                 for c in ctrls for s in plan.sine_seeds for a in amps
                 for d in plan.sine_directions]
        res = runner(specs)
        n = len(res) // len(ctrls)
        req = [dict(sp.params)["amplitude_deg"] >= 5.0 * a_deg - 1e-9 for sp in specs]
        t4[f"μ {mu:g}"] = {}
        for i, c in enumerate(ctrls):
            rs, rq = res[i * n:(i + 1) * n], req[i * n:(i + 1) * n]
            disp = [r["lateral_displacement_m"] for r, q in zip(rs, rq, strict=True) if q]
            t4[f"μ {mu:g}"][c] = {
                "runs": n, "fmvss_pass": sum(r["fmvss_pass"] for r in rs),
                "spun": sum(r["spun"] for r in rs),
                "max_beta_deg": max(r["max_abs_beta_deg"] for r in rs),
                "beta_le_5": all(r["max_abs_beta_deg"] <= 5.0 for r in rs),
                "min_displacement_m": min(disp) if disp else None,
                "motor_limit_share": summarise([r["motor_limit_share"] for r in rs])}
    tables["sine_with_dwell"] = t4

    say("slippery curves")
    t5: dict[str, Any] = {}
    for sc in plan.curves:
        specs = [RunSpec(sc, c, None, None, s, kind="path") for c in (*ctrls, "passive")
                 for s in plan.seeds]
        res = runner(specs)
        n = len(plan.seeds)
        t5[sc] = {c: {"max_dev_m": summarise([r["max_abs_dev_m"] for r in res[i*n:(i+1)*n]]),
                      "max_beta_deg": summarise([r["max_abs_beta_deg"]
                                                 for r in res[i*n:(i+1)*n]]),
                      "spun": sum(r["spun"] for r in res[i*n:(i+1)*n])}
                  for i, c in enumerate((*ctrls, "passive"))}
    tables["curves"] = t5

    say("limit curve radius sweep")
    radii, cs = plan.curve_radii_m, (*ctrls, "passive")
    specs = [RunSpec("slippery-curve-limit", c, None, None, s, (), (), (("radius_m", r),),
                     kind="path") for r in radii for c in cs for s in plan.seeds]
    res = iter(runner(specs))
    t5b: dict[str, Any] = {}
    for r in radii:
        t5b[f"{r:g}"] = {}
        for c in cs:
            rs = [next(res) for _ in plan.seeds]
            t5b[f"{r:g}"][c] = {"max_dev_m": summarise([x["max_abs_dev_m"] for x in rs]),
                                "max_beta_deg": summarise([x["max_abs_beta_deg"] for x in rs]),
                                "spun": sum(x["spun"] for x in rs)}
    tables["curve_sweep"] = t5b

    say("actuator and grip use at the DLC limit")
    v = plan.limit_speed_kmh
    res = runner([RunSpec("dlc-paper", c, v, None, s) for c in ctrls for s in plan.seeds])
    n = len(plan.seeds)
    tables["dlc_limits"] = {"speed_kmh": v, **{
        c: {k: summarise([r[k] for r in res[i * n:(i + 1) * n]])
            for k in ("max_abs_dev_m", "max_abs_beta_deg", "motor_limit_share",
                      "peak_ay_over_mu_g")}
        for i, c in enumerate(ctrls)}}

    say("ablation")
    t6: dict[str, Any] = {}
    top_amp = amps[-1]
    five_a = min((a for a in amplitude_schedule_deg(a_deg, standard_rule=True)
                  if a >= 5.0 * a_deg - 1e-9), default=top_amp)
    for name, refs in plan.variants.items():
        rt = tuple(refs.items())
        vv = vmax_bisections(lambda c, s, v, rt=rt: RunSpec("dlc-paper", c, v, None, s, (), rt),
                             ("nmpc-rhonn",), plan.ablation_seeds, ("paper",), runner,
                             plan.bracket, plan.resolution)
        specs = [RunSpec("dlc-paper", "nmpc-rhonn", 74.0, None, s, (), rt)
                 for s in plan.ablation_seeds]
        specs += [RunSpec("dlc-paper", "nmpc-rhonn", 65.0, None, s, tuple(PERTURBED.items()),
                          rt) for s in plan.ablation_seeds]
        specs += [RunSpec("sine-with-dwell" if mu >= 1.0 else "sine-with-dwell-low-mu",
                          "nmpc-rhonn", None, mu, s, (), rt,
                          (("amplitude_deg", top_amp), ("direction", "left")), "sine", a_deg)
                  for mu in plan.sine_mus for s in plan.ablation_seeds]
        specs += [RunSpec("slippery-curve-limit", "nmpc-rhonn", None, None, s, (), rt,
                          kind="path") for s in plan.ablation_seeds]
        specs += [RunSpec("sine-with-dwell-low-mu", "nmpc-rhonn", None, 0.5, s, (), rt,
                          (("amplitude_deg", five_a), ("direction", "left")), "sine", a_deg)
                  for s in plan.ablation_seeds]
        specs += [RunSpec("dlc-paper", "nmpc-rhonn", 65.0, 0.2, s, (), rt)
                  for s in plan.ablation_seeds]
        specs += [RunSpec("mu-step-corner", "nmpc-rhonn", None, a, s, (), rt,
                          (("steps", ((6.0, b),)),), "mu_step")
                  for a, b in ABLATION_MU_STEPS for s in plan.ablation_seeds]
        res = runner(specs)
        n = len(plan.ablation_seeds)
        steps = res[len(res) - len(ABLATION_MU_STEPS) * n:]
        res = res[:len(res) - len(ABLATION_MU_STEPS) * n]
        dl, pert, rest = res[:n], res[n:2 * n], res[2 * n:]
        sine = {f"μ {mu:g}": rest[i * n:(i + 1) * n] for i, mu in enumerate(plan.sine_mus)}
        k = len(plan.sine_mus) * n
        curve, sine5a, low_mu = rest[k:k + n], rest[k + n:k + 2 * n], rest[k + 2 * n:]
        t6[name] = {
            "vmax_paper": summarise([vv[("nmpc-rhonn", s, "paper")]["vmax_kmh"]
                                     for s in plan.ablation_seeds]),
            "perturbed65_max_dev_m": summarise([r["max_abs_dev_m"] for r in pert]),
            "dlc74_max_dev_m": summarise([r["max_abs_dev_m"] for r in dl]),
            "dlc74_max_beta_deg": summarise([r["max_abs_beta_deg"] for r in dl]),
            "sine_top_max_beta_deg": {k: summarise([r["max_abs_beta_deg"] for r in v])
                                      for k, v in sine.items()},
            "sine_top_spun": {k: sum(r["spun"] for r in v) for k, v in sine.items()},
            "curve_limit_max_dev_m": summarise([r["max_abs_dev_m"] for r in curve]),
            "curve_limit_max_beta_deg": summarise([r["max_abs_beta_deg"] for r in curve]),
            "sine05_5a_displacement_m": summarise([r["lateral_displacement_m"]
                                                   for r in sine5a]),
            "sine05_5a_max_beta_deg": summarise([r["max_abs_beta_deg"] for r in sine5a]),
            "dlc_mu02_stable": sum(r["stable"] for r in low_mu), "dlc_mu02_n": len(low_mu),
            "dlc_mu02_max_beta_deg": summarise([r["max_abs_beta_deg"] for r in low_mu]),
            "mu_step_overshoot_degps": {
                f"μ {a:g} → {b:g}": summarise([r["yaw_overshoot_degps"]
                                              for r in steps[i * n:(i + 1) * n]])
                for i, (a, b) in enumerate(ABLATION_MU_STEPS)},
        }
    tables["ablation"] = t6
    return tables


# ------------------------------------------------------------------------ bus check
def confirm_on_bus(specs: list[RunSpec], out_dir: Path) -> list[dict[str, Any]]:
    """Repeat ``specs`` as real cross-process lockstep bus runs (one after the other) and
    evaluate them the same way; adds ``bus_reason``."""
    from harness.analysis.run_data import load_truth_csv
    from harness.run.runner import RunConfig, run_closed_loop

    out = []
    for i, spec in enumerate(specs):
        d = out_dir / f"bus{i:02d}-{spec.controller}-{spec.speed_kmh}-s{spec.seed}"
        cfg_path = _config_path(out_dir / "configs", spec.seed, spec.refs) \
            if spec.controller == "nmpc-rhonn" or spec.refs else None
        r = run_closed_loop(RunConfig(
            scenario=spec.scenario, controller=spec.controller, out_dir=d,
            controller_config=cfg_path, mu=spec.mu, speed_kmh=spec.speed_kmh, seed=spec.seed,
            params=dict(spec.params), vehicle=dict(spec.vehicle), make_plots=False,
            make_rrd=False))
        tr = load_truth_csv(d / "truth.csv")
        ev = evaluate(spec, {k: np.asarray(v, dtype=float) for k, v in tr.items()})
        ev["bus_reason"] = r.reason
        out.append(ev)
    return out


# ------------------------------------------------------------------------ report
def median_range(s: dict[str, Any] | None, fmt: str = "{:.1f}") -> str:
    """'median [min–max]' of a summarise() dict ("—" when it has no values)."""
    if not s or s.get("median") is None:
        return "—"
    if s["min"] == s["max"]:
        return fmt.format(s["median"])
    return f"{fmt.format(s['median'])} [{fmt.format(s['min'])}–{fmt.format(s['max'])}]"


def report_markdown(t: dict[str, Any]) -> str:
    """The benchmark section of the report, generated from the measured tables only."""
    plan = t["plan"]
    L = ["# Benchmark: stability vs lane keeping", "",
         f"In-process lockstep loop (bit-identical frames to a lockstep bus run). Seeds "
         f"{list(plan['seeds'])} (sensor noise + biases + RHONN initial weights); "
         "median [min–max] over the seeds. v_max by bisection "
         f"{plan['bracket'][0]:g}–{plan['bracket'][1]:g} km/h at {plan['resolution']:g} km/h, "
         "one bisection per controller, seed and rule.", "",
         "## 1. DLC μ 0.35 (dlc-paper): v_max per rule, km/h", "",
         "| controller | paper rule (CG ≤ 1 m, β ≤ 8°) | course rule (cones: footprint "
         "touches none) | stable (no spin, β ≤ 8°, yaw settles) | max β at paper-passing "
         "speeds, ° | phase area 65 km/h |", "|---|---|---|---|---|---|"]
    for c, row in t["dlc_vmax"].items():
        st = median_range(row["stable"])
        if row["stable"].get("above_bracket"):
            st += f" ({row['stable']['above_bracket']} seeds ≥ bracket top)"
        L.append(f"| {c} | {median_range(row['paper'])} | {median_range(row['course'])} | "
                 f"{st} | {row['max_beta_passing_deg']:.2f} | "
                 f"{median_range(row['phase_area_65'], '{:.4f}')} |")
    L += ["", "## 2. Perturbed car / road: v_max (paper rule), km/h, and loss vs nominal", "",
          "| case | " + " | ".join(t["dlc_vmax"]) + " |", "|---|" + "---|" * len(t["dlc_vmax"])]
    for case, row in t["perturbed"].items():
        cells = []
        for c in t["dlc_vmax"]:
            s = row[c]
            loss = "—" if s.get("loss_kmh") is None else f"{s['loss_kmh']:+.1f}"
            cells.append(f"{median_range(s)} (loss {loss})")
        L.append(f"| {case} | " + " | ".join(cells) + " |")
    L += ["", "## 3. Stability margins (stable verdicts / seeds, spins, median max \\|β\\| °)",
          "",
          "| case | " + " | ".join(next(iter(t["margins"].values()))) + " |",
          "|---|" + "---|" * len(next(iter(t["margins"].values())))]
    for case, row in t["margins"].items():
        L.append(f"| {case} | " + " | ".join(
            f"{r['stable']}/{r['n']} stable, {r['spun']} spun, β {median_range(r['max_beta_deg'])}"
            for r in row.values()) + " |")
    sd = t["sine_with_dwell"]
    L += ["", f"## 4. Sine with dwell (A = {sd['a_deg']:.1f}°, amplitudes "
          f"{', '.join(f'{a:.0f}' for a in sd['amplitudes_deg'])}°, both directions)", "",
          "| road | controller | FMVSS 126 passes | spins | max \\|β\\| ° | all \\|β\\| ≤ 5° |",
          "|---|---|---|---|---|---|"]
    for mu, row in sd.items():
        if not mu.startswith("μ"):
            continue
        for c, r in row.items():
            L.append(f"| {mu} | {c} | {r['fmvss_pass']}/{r['runs']} | {r['spun']} | "
                     f"{r['max_beta_deg']:.1f} | {'yes' if r['beta_le_5'] else 'no'} |")
    L += ["", "Lateral displacement (FMVSS 126: ≥ 1.83 m at BOS + 1.07 s, required from 5A) and "
          "the share of the manoeuvre (|ay| ≥ 50 % of its peak) with a motor at its torque "
          "limit:", "", "| road | controller | min displacement at ≥ 5A, m | motor-limit share "
          "(median [min–max] over runs) |", "|---|---|---|---|"]
    for mu, row in sd.items():
        if not mu.startswith("μ"):
            continue
        for c, r in row.items():
            d = "—" if r.get("min_displacement_m") is None else f"{r['min_displacement_m']:.2f}"
            L.append(f"| {mu} | {c} | {d} | {median_range(r.get('motor_limit_share'), '{:.2f}')} |")
    if "dlc_limits" in t:
        lim = t["dlc_limits"]
        L += ["", f"## 4b. Actuator and grip use at the DLC limit ({lim['speed_kmh']:g} km/h, "
              "μ 0.35)", "", "| controller | max dev, m | max β, ° | motor-limit share | "
              "peak \\|ay\\| / μg |", "|---|---|---|---|---|"]
        for c, r in lim.items():
            if c == "speed_kmh":
                continue
            L.append(f"| {c} | {median_range(r['max_abs_dev_m'], '{:.3f}')} | "
                     f"{median_range(r['max_abs_beta_deg'], '{:.2f}')} | "
                     f"{median_range(r['motor_limit_share'], '{:.3f}')} | "
                     f"{median_range(r['peak_ay_over_mu_g'], '{:.2f}')} |")
    L += ["", "## 5. Slippery curves, μ 0.35, 85 km/h held (max |lateral dev| m, max |β| °)", "",
          "| scenario | controller | max dev, m | max β, ° | spins |", "|---|---|---|---|---|"]
    for sc, row in t["curves"].items():
        for c, r in row.items():
            L.append(f"| {sc} | {c} | {median_range(r['max_dev_m'], '{:.2f}')} | "
                     f"{median_range(r['max_beta_deg'])} | {r['spun']} |")
    if "curve_sweep" in t:
        cs = list(next(iter(t["curve_sweep"].values())))
        L += ["", "## 5b. Limit curve radius sweep (μ 0.35, 85 km/h held): max dev m / max β °",
              "", "| R, m | ay needed / μg | " + " | ".join(cs) + " |",
              "|---|---|" + "---|" * len(cs)]
        for r, row in t["curve_sweep"].items():
            need = (85.0 / 3.6) ** 2 / float(r) / (0.35 * 9.81)
            L.append(f"| {r} | {need:.2f} | " + " | ".join(
                f"{median_range(x['max_dev_m'], '{:.2f}')} / {median_range(x['max_beta_deg'])}"
                + (f" ({x['spun']} spun)" if x["spun"] else "") for x in row.values()) + " |")
    L += ["", "## 6. Ablation of the nmpc-rhonn references (seeds "
          f"{list(plan['ablation_seeds'])})", "",
          "| variant | v_max paper, km/h | perturbed car DLC 65 km/h max dev, m | "
          "DLC 74 km/h max dev, m | "
          "DLC 74 max β, ° | " + " | ".join(f"SWD top amp. {k} max β °"
                                            for k in next(iter(t["ablation"].values()))
                                            ["sine_top_max_beta_deg"])
          + " | curve-limit max dev, m | curve-limit max β, ° | SWD μ 0.5 at 5A: "
          "displacement m / max β ° | DLC μ 0.2 65 km/h: stable, max β ° | "
          + " | ".join(f"corner μ {a:g} → {b:g} at 6 s: yaw overshoot °/s"
                       for a, b in ABLATION_MU_STEPS) + " |",
          "|---|---|---|---|---|" + "---|" * len(plan["sine_mus"]) + "---|---|---|---|"
          + "---|" * len(ABLATION_MU_STEPS)]
    for name, r in t["ablation"].items():
        sine = " | ".join(f"{median_range(v)} ({r['sine_top_spun'][k]} spun)"
                          for k, v in r["sine_top_max_beta_deg"].items())
        cell = name.replace("|", "\\|")
        L.append(f"| {cell} | {median_range(r['vmax_paper'])} | "
                 f"{median_range(r['perturbed65_max_dev_m'], '{:.2f}')} | "
                 f"{median_range(r['dlc74_max_dev_m'], '{:.2f}')} | "
                 f"{median_range(r['dlc74_max_beta_deg'])} | "
                 f"{sine} | {median_range(r['curve_limit_max_dev_m'], '{:.2f}')} | "
                 f"{median_range(r['curve_limit_max_beta_deg'])} | "
                 f"{median_range(r.get('sine05_5a_displacement_m'), '{:.2f}')} / "
                 f"{median_range(r.get('sine05_5a_max_beta_deg'))} | "
                 f"{r.get('dlc_mu02_stable', '—')}/{r.get('dlc_mu02_n', '—')}, "
                 f"{median_range(r.get('dlc_mu02_max_beta_deg'))} | "
                 + " | ".join(median_range(v, "{:.2f}") for v in r.get(
                     "mu_step_overshoot_degps", {}).values()) + " |")
    return "\n".join(L) + "\n"


def run_benchmark(out_dir: Path, plan: BenchmarkPlan, jobs: int = 2,
                  progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the benchmark, write OUT/benchmark.json and OUT/benchmark.md; return the tables."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = build_tables(plan, jobs, progress)
    (out_dir / "benchmark.json").write_text(json.dumps(tables, indent=1, default=str))
    (out_dir / "benchmark.md").write_text(report_markdown(tables))
    if (out_dir / "tables.json").exists():   # a `paper` output directory: refresh report.md
        from harness.paper.report import write_report

        write_report(out_dir, json.loads((out_dir / "tables.json").read_text()))
    return tables


def bus_confirmation(tables: dict[str, Any], out_dir: Path, seed: int = 1
                     ) -> list[dict[str, Any]]:
    """Repeat the DLC probes at each MPC's median paper-rule v_max and 0.5 km/h above it
    (seed ``seed``) and the limit curve as real bus runs; each row holds both verdicts."""
    specs: list[RunSpec] = []
    for c, row in tables["dlc_vmax"].items():
        v = row["paper"]["median"]
        if v is None:
            continue
        v = round(v * 2.0) / 2.0
        specs += [RunSpec("dlc-paper", c, v, None, seed), RunSpec("dlc-paper", c, v + 0.5,
                                                                  None, seed)]
    specs += [RunSpec("slippery-curve-limit", c, None, None, seed, kind="path")
              for c in tables["dlc_vmax"]]
    bus = confirm_on_bus(specs, out_dir / "bus")
    ref = run_specs(specs, jobs=1)
    rows = []
    for s, b, r in zip(specs, bus, ref, strict=True):
        rows.append({"scenario": s.scenario, "controller": s.controller, "speed_kmh": s.speed_kmh,
                     "seed": s.seed, "bus_reason": b["bus_reason"],
                     "bus": {k: b.get(k) for k in ("paper", "course", "stable", "max_abs_dev_m",
                                                   "max_abs_beta_deg")},
                     "inprocess": {k: r.get(k) for k in ("paper", "course", "stable",
                                                         "max_abs_dev_m", "max_abs_beta_deg")}})
    return rows


def bus_markdown(rows: list[dict[str, Any]]) -> str:
    """Section 7: the bus confirmation table."""
    L = ["", "## 7. Confirmation over the bus (cross-process lockstep runs vs in-process)", "",
         "| scenario | controller | speed km/h | seed | bus: paper / course / stable | "
         "bus max dev m, max β ° | in-process max dev m, max β ° |",
         "|---|---|---|---|---|---|---|"]
    for r in rows:
        b, i = r["bus"], r["inprocess"]
        verdict = " / ".join("—" if b.get(k) is None else ("pass" if b[k] else "fail")
                             for k in ("paper", "course", "stable"))
        sp = "—" if r["speed_kmh"] is None else f"{r['speed_kmh']:g}"
        L.append(f"| {r['scenario']} | {r['controller']} | {sp} | {r['seed']} | {verdict} | "
                 f"{b['max_abs_dev_m']:.3f}, {b['max_abs_beta_deg']:.2f} | "
                 f"{i['max_abs_dev_m']:.3f}, {i['max_abs_beta_deg']:.2f} |")
    return "\n".join(L) + "\n"


def steady_gain_validation(mus: tuple[float, ...] = (0.35, 0.7, 1.0), seed: int = 1,
                           bands: tuple[tuple[float, float], ...] = (
                               (0.2, 0.5), (0.5, 0.8), (0.8, 1.0))) -> dict[str, Any]:
    """The learned steady-state yaw rate against constant-radius runs.

    nmpc-rhonn with Algorithm 1 (its yaw reference is the learned map's fixed point at the
    driver's steering) on ``constant-radius`` (R = 40 m, speed ramp) at each μ. In bands of
    |ay| / (μ g) the mean ratio of that fixed point to the measured yaw rate, and of the
    nominal bicycle steady state (the baselines' reference) to it."""
    from controller.core.params import load_vehicle_params
    from controller.core.references.linear import LinearReferences
    from harness.run.inprocess_loop import run_in_process

    p = load_vehicle_params()
    lin = LinearReferences(p)
    cfg = _config_path(Path(os.environ.get("TMPDIR", "/tmp")) / "rhonn-bench-configs", seed,
                       (("kind", "algorithm1"),))
    out: dict[str, Any] = {}
    for mu in mus:
        res = run_in_process("constant-radius", "nmpc-rhonn", mu=mu, seed=seed, config=cfg)
        tr = res.truth
        n = min(res.yaw_rate_ref.size, tr["t_s"].size - 1)
        r = tr["yaw_rate_radps"][1:n + 1]
        ay = np.abs(tr["ay_mps2"][1:n + 1]) / (mu * 9.81)
        ref = res.yaw_rate_ref[:n]
        vx = tr["vx_mps"][1:n + 1]
        dw = tr["swa_rad"][1:n + 1] / p.steering_ratio
        rl = np.array([lin.steady_state(v, d)[0] for v, d in zip(vx, dw, strict=True)])
        spun = np.flatnonzero(tr["spun"][1:n + 1] > 0.5)
        valid = np.arange(n) < (spun[0] if spun.size else n)
        row = {}
        for lo, hi in bands:
            m = valid & (ay >= lo) & (ay < hi) & (np.abs(r) > 0.02)
            row[f"{lo:g}-{hi:g}"] = None if not m.any() else {
                "n": int(m.sum()),
                "learned_over_measured": float(np.mean(ref[m]) / np.mean(r[m])),
                "bicycle_over_measured": float(np.mean(rl[m]) / np.mean(r[m]))}
        out[f"μ {mu:g}"] = row
    return out


def gain_markdown(g: dict[str, Any]) -> str:
    """Section 8: learned steady-state yaw gain vs constant-radius runs."""
    L = ["", "## 8. Learned steady-state yaw rate vs constant-radius runs (R = 40 m, seed 1)",
         "", "Ratio of the mean reference to the mean measured yaw rate, by |ay| / (μ g) band: "
         "learned = Algorithm 1's fixed point of the RHONN map; bicycle = the nominal linear "
         "steady state the baselines use.", "",
         "| road | band | samples | learned / measured | bicycle / measured |",
         "|---|---|---|---|---|"]
    for mu, row in g.items():
        for band, v in row.items():
            if v is None:
                L.append(f"| {mu} | {band} | 0 | — | — |")
            else:
                L.append(f"| {mu} | {band} | {v['n']} | {v['learned_over_measured']:.3f} | "
                         f"{v['bicycle_over_measured']:.3f} |")
    return "\n".join(L) + "\n"
