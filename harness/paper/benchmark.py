"""`rhonn-harness benchmark`: a benchmark that tells stability from lane keeping.

Every run is a real closed-loop run over the bus (plant and controller processes, SecOC and
E2E on every control frame), carried out by the campaign engine (harness/campaign: one warm
bench per worker). A section of the benchmark is a *table builder* that asks a run source for
runs (:func:`bench_run` describes one) and for v_max bisections (:func:`vmax_bisections`);
it is called twice: once with :class:`Declared`, which only collects what it asks for, and,
after the campaign has run, with :class:`Measured`, which answers from the campaign's rows.
The collected runs become ``OUT/benchmark.toml`` (one ``[[matrix]]`` per run template, one
``[[study]] kind = "vmax"`` per bisection set; the record of what ran), which
:class:`harness.campaign.runner.CampaignRunner` runs into ``OUT/campaign``. Each run's
verdicts come from its ``stability`` post step (harness/analysis/stability.py). Running the
same command into the same ``OUT`` again reuses the runs already there (same run key).

A seed varies the plant's sensor noise and biases (plant_sim/overrides.py) and the RHONN's
initial weights (the controller override ``rhonn.init_seed``). Tables (see
:func:`build_tables`):

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
   FMVSS 126 pass count, spins and the largest |β| (A from the passive car's
   slowly-increasing-steer run, seed 0, a campaign of its own run first).
5. Slippery curve at the limit (slippery-curve-limit, R = 165 m) and the paper's curve.
6. Ablation of the nmpc-rhonn references (variant → KPIs): Algorithm 1 (the paper's), on
   the slow weight copy, driver intent with steering lead, the default bicycle demand with
   Algorithm 1 from |β| 1–3° or 2–4°, with the sideslip guard (with and without its
   look-ahead, at two gains), without Algorithm 1, with the learned demand, with longer
   horizons (N = 6, 10: the unblocked superset of a move-blocked long horizon), and the
   linear references on the RHONN model; each row also gives the yaw overshoot after a
   friction step in a steady corner.

The adaptation study (harness/paper/adaptation.py) and the Pareto fronts
(harness/paper/pareto.py) are further sections of the same command and the same campaign.
"""

from __future__ import annotations

import hashlib
import json
import math
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import seed_text
from controller.core.params import load_vehicle_params
from controller.core.references.linear import LinearReferences
from harness.analysis.fmvss126 import amplitude_schedule_deg
from harness.campaign.engine import Engine, EngineConfig
from harness.campaign.runner import CampaignResult, CampaignRunner
from harness.campaign.spec import Campaign, StudyDecl, parse_campaign
from harness.paper.report import write_report
from harness.run.controller_config import base_config_text, config_file, overridden_text
from harness.run.inprocess_loop import run_in_process
from harness.run.spec import RunSpec

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


# ------------------------------------------------------------------------ one run
SEED_KEY = "rhonn.init_seed"  # the controller override a seed sets (RHONN initial weights)
POST = "stability"  # the post step that judges a benchmark run


def controller_config_text(seed: int, refs: dict[str, Any] | None = None) -> str:
    """The packaged default.toml with ``[rhonn] init_seed = seed`` and the ``refs``
    overrides (``"SECTION.KEY"``; a bare KEY is in [references]) — the file a benchmark run
    of nmpc-rhonn (or any run with overrides) loads."""
    return overridden_text(base_config_text(None), {SEED_KEY: int(seed), **(refs or {})})


def _param_text(value: Any) -> str:
    """A scenario parameter as the text of ``--param KEY=VALUE`` (lists as JSON)."""
    def plain(v: Any) -> Any:
        return [plain(x) for x in v] if isinstance(v, list | tuple) else v

    return json.dumps(plain(value)) if isinstance(value, list | tuple) else str(value)


def bench_run(scenario: str, controller: str, speed_kmh: float | None = None,
              mu: float | None = None, seed: int = 0,
              vehicle: Iterable[tuple[str, float]] | dict[str, float] = (),
              refs: Iterable[tuple[str, Any]] | dict[str, Any] = (),
              params: Iterable[tuple[str, Any]] | dict[str, Any] = (), kind: str = "dlc",
              a_deg: float | None = None) -> RunSpec:
    """One benchmark run. speed km/h; mu -; vehicle: plant overrides; refs: controller
    overrides (``"SECTION.KEY"``, bare KEY = [references]); params: scenario overrides; kind:
    what the ``stability`` post step evaluates (dlc verdicts, sine FMVSS 126 with A =
    ``a_deg`` deg, path deviation only, mu_step the response to the road's first friction
    step ``params["steps"]``). As in-process runs always did, nmpc-rhonn and any run with
    overrides get ``rhonn.init_seed = seed``."""
    refs = dict(refs)
    overrides = {SEED_KEY: int(seed), **refs} if controller == "nmpc-rhonn" or refs else {}
    info: dict[str, Any] = {"kind": kind}
    if a_deg is not None:
        info["a_deg"] = float(a_deg)
    return RunSpec(scenario=scenario, controller=controller, seed=int(seed), mu=mu,
                   speed_kmh=speed_kmh, vehicle=dict(vehicle),
                   params={k: _param_text(v) for k, v in dict(params).items()},
                   controller_overrides=overrides, post=(POST,), info=info,
                   make_plots=False, make_rrd=False)


def _template(spec: RunSpec) -> tuple[dict[str, Any], list[str]]:
    """A run's controller overrides without the seed's, and the keys set to the seed."""
    ov = dict(spec.controller_overrides)
    by_seed = [SEED_KEY] if ov.get(SEED_KEY) == spec.seed and SEED_KEY in ov else []
    for k in by_seed:
        ov.pop(k)
    return ov, by_seed


# ------------------------------------------------------------------------ run sources
Base = Callable[[str, int, float], RunSpec]


@dataclass(frozen=True)
class VmaxSet:
    """Bisections of the DLC entry speed (km/h) for some controllers × seeds × rules with
    one probe template (what :class:`harness.campaign.studies.VmaxStudy` runs)."""

    controllers: tuple[str, ...]
    seeds: tuple[int, ...]
    rules: tuple[str, ...]
    bracket: tuple[float, float]
    resolution: float
    template: tuple[tuple[str, Any], ...]  # the study's options from the probe template

    @property
    def name(self) -> str:
        """A name that is the hash of the whole set (equal sets share it)."""
        text = json.dumps(asdict(self), sort_keys=True, default=str)
        return f"vmax-{hashlib.sha256(text.encode()).hexdigest()[:12]}"

    def decl(self) -> StudyDecl:
        """The campaign study of the set."""
        opts = {"bracket_kmh": list(self.bracket), "resolution_kmh": self.resolution,
                "verify_offsets_kmh": [], "rules": list(self.rules),
                "coast_duration": False, "post": [POST],
                **{k: v for k, v in self.template if v not in ([], {})}}
        return StudyDecl(self.name, "vmax", self.controllers, self.seeds, opts)


def vmax_sets(base: Base, controllers: Iterable[str], seeds: Iterable[int],
              rules: Iterable[str], bracket: tuple[float, float], resolution: float
              ) -> list[VmaxSet]:
    """The bisection sets of ``base(controller, seed, speed) → probe run``: controllers with
    the same probe template share one set."""
    seeds, rules = tuple(seeds), tuple(rules)
    groups: dict[tuple[tuple[str, Any], ...], list[str]] = {}
    for c in controllers:
        tmpl = None
        for s in seeds:
            spec = base(c, s, float(bracket[0]))
            ov, by_seed = _template(spec)
            if spec.params or spec.faults:
                raise ValueError("a v_max probe template has no scenario parameters or faults")
            t: dict[str, Any] = {"scenario": spec.scenario, "vehicle": dict(spec.vehicle),
                                 "controller_overrides": ov, "seed_overrides": by_seed,
                                 "info": dict(spec.info)}
            if spec.mu is not None:
                t["mu"] = spec.mu
            frozen = tuple(sorted((k, json.dumps(v, sort_keys=True)) for k, v in t.items()))
            if tmpl is not None and frozen != tmpl:
                raise ValueError(f"v_max probes of {c} differ between seeds beyond the seed")
            tmpl = frozen
        assert tmpl is not None
        groups.setdefault(tmpl, []).append(c)
    return [VmaxSet(tuple(cs), seeds, rules, (float(bracket[0]), float(bracket[1])),
                    float(resolution),
                    tuple((k, json.loads(v)) for k, v in tmpl)) for tmpl, cs in groups.items()]


class _Blank(dict):  # type: ignore[type-arg]
    """The result a declaring pass hands back: NaN for every key (never used in a table)."""

    def __missing__(self, key: str) -> float:
        return math.nan


class RunSource:
    """What a table builder asks for runs: ``source(specs)`` → one result dict per spec
    (the ``stability`` post step's), ``source.vmax(...)`` → bisection results."""

    def __call__(self, specs: list[RunSpec]) -> list[dict[str, Any]]:
        raise NotImplementedError

    def vmax(self, base: Base, controllers: Iterable[str], seeds: Iterable[int],
             rules: Iterable[str], bracket: tuple[float, float], resolution: float
             ) -> dict[tuple[str, int, str], dict[str, Any]]:
        """(controller, seed, rule) → the bisection (harness.analysis.vmax.Bisection.to_json
        plus ``max_beta_passing_deg``, the largest max |β| of its passing probes, deg)."""
        raise NotImplementedError


class Declared(RunSource):
    """First pass: collects every run and bisection set asked for; answers blanks."""

    def __init__(self) -> None:
        self.runs: dict[str, RunSpec] = {}
        self.sets: dict[str, VmaxSet] = {}

    def __call__(self, specs: list[RunSpec]) -> list[dict[str, Any]]:
        for s in specs:
            self.runs.setdefault(s.key(), s)
        return [_Blank() for _ in specs]

    def vmax(self, base: Base, controllers: Iterable[str], seeds: Iterable[int],
             rules: Iterable[str], bracket: tuple[float, float], resolution: float
             ) -> dict[tuple[str, int, str], dict[str, Any]]:
        controllers, seeds, rules = tuple(controllers), tuple(seeds), tuple(rules)
        for vs in vmax_sets(base, controllers, seeds, rules, bracket, resolution):
            self.sets.setdefault(vs.name, vs)
        return {(c, s, r): {"vmax_kmh": None, "status": "declared",
                            "max_beta_passing_deg": None}
                for c in controllers for s in seeds for r in rules}


class Measured(RunSource):
    """Second pass: answers from a finished campaign's rows and studies. A run without a
    ``stability`` result (its task failed) answers blanks and is listed in ``missing``."""

    def __init__(self, rows: dict[str, dict[str, Any]], studies: dict[str, Any]) -> None:
        self.rows, self.studies = rows, studies
        self.missing: list[str] = []

    def __call__(self, specs: list[RunSpec]) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        for s in specs:
            row = self.rows.get(s.key()) or {}
            got = json.loads(row.get("post") or "{}").get(POST)
            if not isinstance(got, dict) or "error" in got:
                self.missing.append(s.key())
                out.append(_Blank())
                continue
            out.append({k: (math.nan if v is None and k in _FLOAT_KEYS else v)
                        for k, v in got.items()})
        return out

    def vmax(self, base: Base, controllers: Iterable[str], seeds: Iterable[int],
             rules: Iterable[str], bracket: tuple[float, float], resolution: float
             ) -> dict[tuple[str, int, str], dict[str, Any]]:
        out: dict[tuple[str, int, str], dict[str, Any]] = {}
        for vs in vmax_sets(base, controllers, seeds, rules, bracket, resolution):
            st = self.studies[vs.name]
            for r in vs.rules:
                per = st["rules"][r] if "rules" in st else st["controllers"]
                for c in vs.controllers:
                    for s in vs.seeds:
                        out[(c, s, r)] = per[c]["seeds"][str(s)]
        return out


# post-step numbers a JSON row holds as null when not finite (task._clean)
_FLOAT_KEYS = ("max_abs_beta_deg", "max_abs_dev_m", "phase_area", "motor_limit_share",
               "peak_ay_over_mu_g", "lateral_displacement_m", "yaw_settle_ratio",
               "sideslip_rate_ratio")


def vmax_bisections(base: Base, controllers: Iterable[str], seeds: Iterable[int],
                    rules: Iterable[str], runner: RunSource,
                    bracket: tuple[float, float] = (40.0, 100.0), resolution: float = 0.5
                    ) -> dict[tuple[str, int, str], dict[str, Any]]:
    """One bisection per (controller, seed, rule); a probe run once serves every rule.
    base(controller, seed, speed) → the probe's run (:func:`bench_run`)."""
    return runner.vmax(base, controllers, seeds, rules, bracket, resolution)


# ------------------------------------------------------------------------ campaign file
def _toml(value: Any) -> str:
    """A TOML value (floats written so that they read back exactly)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{json.dumps(str(k), ensure_ascii=False)} = {_toml(v)}"
                                for k, v in value.items()) + " }" if value else "{}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {value!r}")


def _matrices(runs: Iterable[RunSpec]) -> list[dict[str, Any]]:
    """``[[matrix]]`` tables giving exactly ``runs``: one per run template and seed set,
    with the controllers that share both."""
    seeds: dict[tuple[str, str], list[int]] = {}
    tmpls: dict[str, dict[str, Any]] = {}
    for r in runs:
        ov, by_seed = _template(r)
        t: dict[str, Any] = {"scenarios": [r.scenario]}
        if r.mu is not None:
            t["mu"] = [r.mu]
        if r.speed_kmh is not None:
            t["speeds_kmh"] = [r.speed_kmh]
        for key, value in (("params", dict(r.params)), ("vehicle", dict(r.vehicle)),
                           ("controller_overrides", ov)):
            if value:
                t[key] = [value]
        if by_seed:
            t["seed_overrides"] = by_seed
        t["post"] = list(r.post)
        t["info"] = dict(r.info)
        tk = json.dumps(t, sort_keys=True)
        tmpls[tk] = t
        seeds.setdefault((tk, r.controller), []).append(r.seed)
    groups: dict[tuple[str, tuple[int, ...]], list[str]] = {}
    for (tk, c), ss in seeds.items():
        groups.setdefault((tk, tuple(sorted(set(ss)))), []).append(c)
    out = []
    for i, ((tk, ss), cs) in enumerate(sorted(groups.items())):
        t = tmpls[tk]
        out.append({"name": f"m{i + 1:03d}-{t['scenarios'][0]}", "scenarios": t["scenarios"],
                    "controllers": sorted(cs),
                    **{k: v for k, v in t.items() if k != "scenarios"}, "seeds": list(ss)})
    return out


def campaign_text(name: str, description: str, runs: Iterable[RunSpec],
                  sets: Iterable[VmaxSet]) -> str:
    """The campaign file of a benchmark (harness/campaign/spec.py format)."""
    L = [f"# {line}".rstrip() for line in description.splitlines()]
    L += ["", "[campaign]", f"name = {_toml(name)}", "plots = false", "rrd = false"]
    for m in _matrices(runs):
        L += ["", "[[matrix]]", *(f"{k} = {_toml(v)}" for k, v in m.items())]
    for vs in sets:
        d = vs.decl()
        L += ["", "[[study]]", 'kind = "vmax"', f"name = {_toml(d.name)}",
              f"controllers = {_toml(list(d.controllers))}", f"seeds = {_toml(list(d.seeds))}",
              *(f"{k} = {_toml(v)}" for k, v in d.options.items())]
    return "\n".join(L) + "\n"


def benchmark_campaign(name: str, description: str, declared: Declared
                       ) -> tuple[str, Campaign]:
    """The campaign text and the parsed campaign of what ``declared`` collected; the parsed
    runs are checked to be exactly the declared ones (the file is a faithful record)."""
    text = campaign_text(name, description, declared.runs.values(), declared.sets.values())
    camp = parse_campaign(text)
    got = {r.key() for r in camp.runs}
    if got != set(declared.runs):
        lost = sorted(set(declared.runs) - got)[:3]
        raise RuntimeError(f"the benchmark campaign file does not give the declared runs "
                           f"(e.g. {lost})")
    return text, camp


# ------------------------------------------------------------------------ sections
@dataclass
class Section:
    """A part of the benchmark report: ``tables(source)`` builds its tables through a run
    source (called twice, see the module docstring); ``write(out_dir, tables)`` writes its
    files and returns its markdown."""

    name: str
    tables: Callable[[RunSource], dict[str, Any]]
    write: Callable[[Path, dict[str, Any]], str]


SIS_NAME = "benchmark-sis"


def measure_a_deg(out_dir: Path, engine: Engine, progress: bool) -> float:
    """FMVSS 126 A (deg of steering-wheel angle) from the passive car's slowly-increasing-
    steer run (seed 0, μ 1) over the bus: a one-run campaign into ``out_dir``."""
    text = "\n".join(["[campaign]", f'name = "{SIS_NAME}"', "", "[[matrix]]", 'name = "sis"',
                      'scenarios = ["slowly-increasing-steer"]', 'controllers = ["passive"]',
                      'post = ["sis"]', "seeds = [0]"]) + "\n"
    camp = parse_campaign(text)
    res = CampaignRunner(camp, out_dir, engine.cfg, resume=True, progress=progress).run(engine)
    row = res.rows[camp.runs[0].key()]
    a = json.loads(row.get("post") or "{}").get("sis", {}).get("a_deg")
    if a is None:
        raise RuntimeError(f"the slowly-increasing-steer run gave no A: {row.get('error')}")
    return float(a)


def run_benchmark(out_dir: Path, sections: list[Callable[[float], Section]],
                  engine_cfg: EngineConfig | None = None,
                  progress: Callable[[str], None] | None = None, bar: bool = True,
                  a_deg: float | None = None) -> dict[str, dict[str, Any]]:
    """Run the benchmark sections as one campaign; write OUT/benchmark.toml (the campaign),
    OUT/campaign (its runs and rows), each section's files and OUT/benchmark.md; return the
    tables by section. ``sections``: A (deg) → a section; ``a_deg``: FMVSS 126 A, deg
    (None: measured first, :func:`measure_a_deg`)."""
    say = progress or (lambda s: None)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with Engine(engine_cfg or EngineConfig()) as engine:
        if a_deg is None:
            say("FMVSS 126 A: slowly-increasing steer")
            a_deg = measure_a_deg(out_dir / "campaign-sis", engine, bar)
        built = [make(a_deg) for make in sections]
        declared = Declared()
        for sec in built:
            sec.tables(declared)
        desc = (f"rhonn-harness benchmark: sections {', '.join(s.name for s in built)}; "
                f"FMVSS 126 A = {a_deg!r} deg\n(harness/paper/benchmark.py wrote this file; "
                f"{len(declared.runs)} runs and {len(declared.sets)} v_max studies)")
        text, camp = benchmark_campaign("benchmark", desc, declared)
        (out_dir / "benchmark.toml").write_text(text)
        say(f"campaign: {len(camp.runs)} runs and {len(camp.studies)} v_max studies")
        res: CampaignResult = CampaignRunner(camp, out_dir / "campaign", engine.cfg,
                                             resume=True, progress=bar).run(engine)
    measured = Measured(res.rows, res.studies)
    tables: dict[str, dict[str, Any]] = {}
    md: list[str] = []
    for sec in built:
        tables[sec.name] = sec.tables(measured)
        tables[sec.name]["campaign"] = {"runs": len(res.rows), "executed": res.executed,
                                        "resumed": res.cached, "wall_time_s": res.wall_time_s,
                                        "failed": len(res.failed), "a_deg": a_deg}
        md.append(sec.write(out_dir, tables[sec.name]))
    if measured.missing:
        md.append(f"\n{len(set(measured.missing))} runs gave no result (see "
                  "campaign/results.parquet); their cells count them as missing.\n")
    (out_dir / "benchmark.md").write_text("\n".join(md))
    if (out_dir / "tables.json").exists():   # a `paper` output directory: refresh report.md
        write_report(out_dir, json.loads((out_dir / "tables.json").read_text()))
    return tables


def json_section(name: str, build: Callable[[RunSource, float], dict[str, Any]],
                 markdown: Callable[[dict[str, Any]], str], filename: str | None = None
                 ) -> Callable[[float], Section]:
    """A benchmark section whose tables ``build(source, A)`` (A: FMVSS 126 A, deg) go to
    OUT/``filename`` (default ``<name>.json``) and whose report is ``markdown(tables)``."""
    def make(a_deg: float) -> Section:
        def write(out_dir: Path, t: dict[str, Any]) -> str:
            (out_dir / (filename or f"{name}.json")).write_text(
                json.dumps(t, indent=1, default=str))
            return markdown(t)

        return Section(name, lambda src: build(src, a_deg), write)

    return make


def core_section(plan: BenchmarkPlan) -> Callable[[float], Section]:
    """Sections 1–6 (:func:`build_tables`) as a benchmark section."""
    return json_section("core", lambda src, a: build_tables(plan, src, a), report_markdown,
                        "benchmark.json")


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




def build_tables(plan: BenchmarkPlan, runner: RunSource, a_deg: float) -> dict[str, Any]:
    """Sections 1–6 from ``runner`` (see the module docstring); A: FMVSS 126 A, deg of
    steering-wheel angle. The tables as plain data (JSON-serialisable)."""
    tables: dict[str, Any] = {"plan": {k: v for k, v in asdict(plan).items()
                                       if k != "variants"} | {"variants": plan.variants}}
    ctrls = plan.controllers

    def dlc(vehicle: dict[str, float], mu: float | None, refs: dict[str, Any] | None = None
            ) -> Base:
        return lambda c, s, v: bench_run("dlc-paper", c, v, mu, s, tuple(vehicle.items()),
                                       tuple((refs or {}).items()) if c == "nmpc-rhonn" else ())

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
    pa = runner([bench_run("dlc-paper", c, 65.0, None, s) for c in ctrls for s in plan.seeds])
    for i, c in enumerate(ctrls):
        n = len(plan.seeds)
        t1[c]["phase_area_65"] = summarise([p["phase_area"] for p in pa[i * n:(i + 1) * n]])
    tables["dlc_vmax"] = t1

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

    t3: dict[str, Any] = {}
    specs = [bench_run(sc, c, v, mu, s, veh) for sc, mu, v, veh in plan.margin_cases
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

    amps = amplitude_schedule_deg(a_deg, standard_rule=True)
    if plan.quick:
        amps = amps[-1:]
    t4: dict[str, Any] = {"a_deg": a_deg, "amplitudes_deg": amps}
    for mu in plan.sine_mus:
        sc = "sine-with-dwell" if mu >= 1.0 else "sine-with-dwell-low-mu"
        specs = [bench_run(sc, c, None, mu, s, (), (), (("amplitude_deg", a), ("direction", d)),
                         "sine", a_deg)
                 for c in ctrls for s in plan.sine_seeds for a in amps
                 for d in plan.sine_directions]
        res = runner(specs)
        n = len(res) // len(ctrls)
        req = [float(dict(sp.params)["amplitude_deg"]) >= 5.0 * a_deg - 1e-9
               for sp in specs]
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

    t5: dict[str, Any] = {}
    for sc in plan.curves:
        specs = [bench_run(sc, c, None, None, s, kind="path") for c in (*ctrls, "passive")
                 for s in plan.seeds]
        res = runner(specs)
        n = len(plan.seeds)
        t5[sc] = {c: {"max_dev_m": summarise([r["max_abs_dev_m"] for r in res[i*n:(i+1)*n]]),
                      "max_beta_deg": summarise([r["max_abs_beta_deg"]
                                                 for r in res[i*n:(i+1)*n]]),
                      "spun": sum(r["spun"] for r in res[i*n:(i+1)*n])}
                  for i, c in enumerate((*ctrls, "passive"))}
    tables["curves"] = t5

    radii, cs = plan.curve_radii_m, (*ctrls, "passive")
    specs = [bench_run("slippery-curve-limit", c, None, None, s, (), (), (("radius_m", r),),
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

    v = plan.limit_speed_kmh
    res = runner([bench_run("dlc-paper", c, v, None, s) for c in ctrls for s in plan.seeds])
    n = len(plan.seeds)
    tables["dlc_limits"] = {"speed_kmh": v, **{
        c: {k: summarise([r[k] for r in res[i * n:(i + 1) * n]])
            for k in ("max_abs_dev_m", "max_abs_beta_deg", "motor_limit_share",
                      "peak_ay_over_mu_g")}
        for i, c in enumerate(ctrls)}}

    t6: dict[str, Any] = {}
    top_amp = amps[-1]
    five_a = min((a for a in amplitude_schedule_deg(a_deg, standard_rule=True)
                  if a >= 5.0 * a_deg - 1e-9), default=top_amp)
    for name, refs in plan.variants.items():
        rt = tuple(refs.items())
        vv = vmax_bisections(lambda c, s, v, rt=rt: bench_run("dlc-paper", c, v, None, s, (), rt),
                             ("nmpc-rhonn",), plan.ablation_seeds, ("paper",), runner,
                             plan.bracket, plan.resolution)
        specs = [bench_run("dlc-paper", "nmpc-rhonn", 74.0, None, s, (), rt)
                 for s in plan.ablation_seeds]
        specs += [bench_run("dlc-paper", "nmpc-rhonn", 65.0, None, s, tuple(PERTURBED.items()),
                          rt) for s in plan.ablation_seeds]
        specs += [bench_run("sine-with-dwell" if mu >= 1.0 else "sine-with-dwell-low-mu",
                          "nmpc-rhonn", None, mu, s, (), rt,
                          (("amplitude_deg", top_amp), ("direction", "left")), "sine", a_deg)
                  for mu in plan.sine_mus for s in plan.ablation_seeds]
        specs += [bench_run("slippery-curve-limit", "nmpc-rhonn", None, None, s, (), rt,
                          kind="path") for s in plan.ablation_seeds]
        specs += [bench_run("sine-with-dwell-low-mu", "nmpc-rhonn", None, 0.5, s, (), rt,
                          (("amplitude_deg", five_a), ("direction", "left")), "sine", a_deg)
                  for s in plan.ablation_seeds]
        specs += [bench_run("dlc-paper", "nmpc-rhonn", 65.0, 0.2, s, (), rt)
                  for s in plan.ablation_seeds]
        specs += [bench_run("mu-step-corner", "nmpc-rhonn", None, a, s, (), rt,
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
         "Closed-loop runs over the bus (plant and controller processes, SecOC and E2E; "
         f"the campaign in benchmark.toml). Seeds "
         f"{seed_text(plan['seeds'])} (sensor noise + biases + RHONN initial weights); "
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
            n = row["stable"]["above_bracket"]
            st += f" ({n} seed{'s' if n != 1 else ''} ≥ bracket top)"
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
          f"{seed_text(plan['ablation_seeds'])})", "",
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


# ------------------------------------------------------------------------ tuning check
def steady_gain_validation(mus: tuple[float, ...] = (0.35, 0.7, 1.0), seed: int = 1,
                           bands: tuple[tuple[float, float], ...] = (
                               (0.2, 0.5), (0.5, 0.8), (0.8, 1.0))) -> dict[str, Any]:
    """The learned steady-state yaw rate against constant-radius runs.

    nmpc-rhonn with Algorithm 1 (its yaw reference is the learned map's fixed point at the
    driver's steering) on ``constant-radius`` (R = 40 m, speed ramp) at each μ. In bands of
    |ay| / (μ g) the mean ratio of that fixed point to the measured yaw rate, and of the
    nominal bicycle steady state (the baselines' reference) to it. In-process runs (the
    reference is the controller's internal signal, not on the bus)."""
    p = load_vehicle_params()
    lin = LinearReferences(p)
    cfg = config_file(None, {SEED_KEY: int(seed), "kind": "algorithm1"},
                      Path(tempfile.gettempdir()) / "rhonn-bench-configs")
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
