"""Screen controller variants on the near-limit cases, in-process, in seconds.

    python -m harness.tools.handling_screen [--variant NAME:KEY=VALUE[,KEY=VALUE...]]...
        [--seeds 1-5] [--cases TEXT[,TEXT...]] [--vehicle KEY=VALUE]... [--vmax] [--jobs 2]
        [--a-deg DEG] [--json FILE]

Runs the cases of the benchmark's near-limit section (``harness.paper.handling.
default_cases``) for the paper's baselines (nmpc-mf, lmpc), the packaged nmpc-rhonn and
every ``--variant`` (nmpc-rhonn with controller overrides, ``SECTION.KEY=VALUE``; a bare KEY
is in [references]), each seed in lockstep **in this process** (plant and controller node
without a bus: ``harness.run.inprocess_loop``), and evaluates each run with the benchmark's
own post step (``harness.analysis.stability.evaluate``: the same smoothness, verdict and
adaptation KPIs). A run takes well under a second with the C core, so a few variants over
all cases and five seeds take about a minute — a screen before the benchmark over the bus
(``rhonn-harness benchmark --sections handling``), which remains the measurement of record.

Per case and who: median over the seeds of ΔM total variation per second (kN·m/s) and its
ratio to the smaller baseline's, ΔM-increment sign reversals per second, max |β| (deg),
max |lateral dev| (m), spins, and for friction steps the yaw overshoot (deg/s) and the
model's re-learning time (s, max over the seeds; ∞: not back in its band in the window).
``--a-deg``: FMVSS 126 A (deg of steering-wheel angle) for the low-μ sine's amplitude; by
default measured from the passive car's slowly-increasing-steer run, in-process, as the
benchmark does over the bus.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import seed_spec
from harness.analysis.fmvss126 import find_a_deg
from harness.analysis.stability import evaluate
from harness.analysis.vmax import Bisection
from harness.paper.benchmark import PERTURBED, controller_config_text, summarise
from harness.paper.handling import Case, default_cases
from harness.run.inprocess_loop import run_in_process
from plant_sim.overrides import RELATIVE_KEYS, apply_vehicle_overrides, parse_key_values
from plant_sim.params import load_vehicle_params as load_plant_params

BASELINES = ("nmpc-mf", "lmpc")
DEFAULT = "nmpc-rhonn"
VMAX_BRACKET = (60.0, 90.0)   # km/h, the near-limit section's bracket
VMAX_RESOLUTION = 0.5         # km/h


@dataclass(frozen=True)
class Job:
    """One run: the case, who (a label), the controller, its overrides, the seed, the FMVSS
    126 A (deg) and the plant overrides."""

    case: Case
    who: str
    controller: str
    overrides: tuple[tuple[str, Any], ...]
    seed: int
    a_deg: float
    vehicle: tuple[tuple[str, float], ...] = ()


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME:KEY=VALUE[,KEY=VALUE...]`` → (name, overrides); values parsed as JSON when
    they are (numbers, true/false, lists), else kept as text."""
    name, sep, body = text.partition(":")
    if not sep or not name.strip() or not body.strip():
        raise ValueError(f"variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE...]")
    out: dict[str, Any] = {}
    for item in body.split(","):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"variant {name!r}: {item!r} is not KEY=VALUE")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value.strip()
    return name.strip(), out


def measured_a_deg() -> float:
    """FMVSS 126 A, deg, from the passive car's slowly-increasing-steer run (seed 0, μ 1)."""
    res = run_in_process("slowly-increasing-steer", "passive", mu=1.0, seed=0)
    return find_a_deg(np.degrees(res.truth["swa_rad"]), res.truth["ay_mps2"])


@dataclass(frozen=True)
class VmaxJob:
    """One DLC v_max bisection: who, the controller, its overrides, the seed, the car."""

    who: str
    controller: str
    overrides: tuple[tuple[str, Any], ...]
    seed: int
    perturbed: bool
    vehicle: tuple[tuple[str, float], ...] = ()


def _evaluated(case: Case, controller: str, overrides: dict[str, Any], seed: int,
               a_deg: float | None, vehicle: dict[str, float] | None = None) -> dict[str, Any]:
    """The benchmark's post-step result (``evaluate``) of one in-process run of ``case``."""
    config = None
    if controller == DEFAULT or overrides:  # as the benchmark: init_seed = seed
        with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
            f.write(controller_config_text(seed, overrides))
        config = f.name
    params = dict(case.params)
    try:
        res = run_in_process(case.scenario, controller, mu=case.mu, speed_kmh=case.speed_kmh,
                             seed=seed, config=config, vehicle=vehicle, **params)
    finally:
        if config is not None:
            os.unlink(config)
    truth = dict(res.truth)
    err = np.full(truth["t_s"].size, np.nan)  # one model error per cycle, none for row 0
    n = min(res.model_err_rms.size, err.size - 1)
    err[1:n + 1] = res.model_err_rms[:n]
    truth["model_err_rms"] = err
    return evaluate(case.kind, truth, scenario=case.scenario, mu=case.mu,
                    speed_kmh=case.speed_kmh, params=params, vehicle=vehicle,
                    a_deg=a_deg if case.kind == "sine" else None)


def run_job(job: Job) -> dict[str, Any]:
    """The benchmark's post-step result of one in-process run (plus case, who, seed)."""
    out = _evaluated(job.case, job.controller, dict(job.overrides), job.seed, job.a_deg,
                     dict(job.vehicle) or None)
    return {"case": job.case.label, "who": job.who, "seed": job.seed, **out}


def run_vmax(job: VmaxJob) -> dict[str, Any]:
    """DLC v_max (paper rule), km/h, of one who, seed and car: None when the bisection did
    not complete (the bracket's low end fails)."""
    bis = Bisection(job.who, VMAX_BRACKET[0], VMAX_BRACKET[1], VMAX_RESOLUTION, rule="paper")
    vehicle = perturbed_car(dict(job.vehicle)) if job.perturbed else dict(job.vehicle) or None
    while not bis.done:
        for v in bis.pending():
            case = Case("DLC probe", "dlc-paper", None, v)
            bis.record(v, _evaluated(case, job.controller, dict(job.overrides), job.seed,
                                     None, vehicle))
    return {"who": job.who, "seed": job.seed, "perturbed": job.perturbed,
            "vmax_kmh": bis.vmax_kmh}


def perturbed_car(vehicle: dict[str, float]) -> dict[str, float]:
    """``vehicle`` with the benchmark's perturbation on top (relative factors multiplied)."""
    out = dict(vehicle)
    for key, value in PERTURBED.items():
        out[key] = out.get(key, 1.0) * value if key in RELATIVE_KEYS else value
    return out


def vmax_summary(results: list[dict[str, Any]], who: list[str]) -> str:
    """Median [min–max] v_max over the seeds per who and car, and the loss, as Markdown."""
    def cell(vals: list[float | None]) -> tuple[str, float]:
        got = [v for v in vals if v is not None]
        if not got:
            return "—", math.nan
        med = float(np.median(got))
        rng = "" if min(got) == max(got) else f" [{min(got):g}–{max(got):g}]"
        miss = "" if len(got) == len(vals) else f", {len(vals) - len(got)} below the bracket"
        return f"{med:g}{rng}{miss}", med

    lines = ["| who | nominal car | perturbed car | loss |", "|---|---|---|---|"]
    for w in who:
        nom, vn = cell([r["vmax_kmh"] for r in results if r["who"] == w and not r["perturbed"]])
        per, vp = cell([r["vmax_kmh"] for r in results if r["who"] == w and r["perturbed"]])
        loss = "—" if math.isnan(vn - vp) else f"{vn - vp:g}"
        lines.append(f"| {w} | {nom} | {per} | {loss} |")
    return "\n".join(lines)


def _median(rows: list[dict[str, Any]], key: str) -> float:
    """The benchmark's median over the seeds (``summarise``); NaN when no run has the KPI."""
    med = summarise([r.get(key) for r in rows])["median"]
    return math.nan if med is None else med


def summary(results: list[dict[str, Any]], cases: list[str], who: list[str]
            ) -> list[dict[str, Any]]:
    """One row per (case, who): medians over the seeds and the TV ratio to the smaller
    baseline's median."""
    rows = []
    for case in cases:
        by = {w: [r for r in results if r["case"] == case and r["who"] == w] for w in who}
        base = [_median(by[b], "dM_tv_per_s_Nm_per_s") for b in BASELINES if by.get(b)]
        smaller = min(base) if base else math.nan
        for w in who:
            rs = by[w]
            tv = _median(rs, "dM_tv_per_s_Nm_per_s")
            # a learned model's re-learning time; None: not back in its band (∞ here)
            relearn = [r.get("relearn_time_s") for r in rs if r.get("err_band_radps") is not None]
            rows.append({
                "case": case, "who": w, "n": len(rs),
                "tv_kNm_per_s": tv / 1e3,
                "tv_ratio": tv / smaller if smaller > 0 else math.nan,
                "chatter_per_s": _median(rs, "dM_chatter_per_s"),
                "max_beta_deg": _median(rs, "max_abs_beta_deg"),
                "max_dev_m": _median(rs, "max_abs_dev_m"),
                "spun": sum(bool(r.get("spun")) for r in rs),
                "overshoot_degps": _median(rs, "yaw_overshoot_degps"),
                "relearn_max_s": (math.nan if not relearn else math.inf if None in relearn
                                  else max(relearn)),
            })
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """The summary as a Markdown table (— for a value the case does not have)."""
    def f(x: float, d: int) -> str:
        return "—" if isinstance(x, float) and math.isnan(x) else f"{x:.{d}f}"

    lines = ["| case | who | ΔM TV/s kN·m/s | ÷ smaller baseline | chatter 1/s | max β ° "
             "| max dev m | spun | overshoot °/s | re-learning max s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['who']} | {f(r['tv_kNm_per_s'], 2)} | "
                     f"{f(r['tv_ratio'], 2)} | {f(r['chatter_per_s'], 1)} | "
                     f"{f(r['max_beta_deg'], 1)} | {f(r['max_dev_m'], 2)} | "
                     f"{r['spun']}/{r['n']} | {f(r['overshoot_degps'], 2)} | "
                     f"{f(r['relearn_max_s'], 2)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m harness.tools.handling_screen",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                   help="nmpc-rhonn with these controller overrides (repeatable)")
    p.add_argument("--seeds", type=seed_spec, default=(1, 2, 3, 4, 5), metavar="SPEC",
                   help="seed list, e.g. 1-5 or 1,3 (default 1-5)")
    p.add_argument("--cases", default="", metavar="TEXT,...",
                   help="only the cases whose label contains one of these texts")
    p.add_argument("--vehicle", action="append", default=[], metavar="KEY=VALUE",
                   help="plant override on every run (repeatable), e.g. tyre_peak_scale=0.8")
    p.add_argument("--vmax", action="store_true",
                   help="also DLC v_max (paper rule) on the nominal and the perturbed car")
    p.add_argument("--jobs", type=int, default=2, help="worker processes")
    p.add_argument("--a-deg", type=float, default=None, help="FMVSS 126 A, deg")
    p.add_argument("--json", type=Path, default=None, help="write every run's KPIs here")
    args = p.parse_args(argv)
    try:
        variants = dict(parse_variant(v) for v in args.variant)
        vehicle = parse_key_values(args.vehicle)
        apply_vehicle_overrides(load_plant_params(), vehicle)  # refuses a bad key or value
    except ValueError as exc:
        print(f"handling_screen: {exc}", file=sys.stderr)
        return 2
    if args.jobs < 1:
        print("handling_screen: --jobs must be ≥ 1", file=sys.stderr)
        return 2
    a_deg = args.a_deg if args.a_deg is not None else measured_a_deg()
    wanted = [t for t in args.cases.split(",") if t]
    cases = [c for c in default_cases(a_deg) if not wanted or any(t in c.label for t in wanted)]
    if not cases:
        print(f"handling_screen: no case matches {args.cases!r}", file=sys.stderr)
        return 2
    who: dict[str, tuple[str, dict[str, Any]]] = {
        **{b: (b, {}) for b in BASELINES}, DEFAULT: (DEFAULT, {}),
        **{name: (DEFAULT, ov) for name, ov in variants.items()}}
    car = tuple(vehicle.items())
    jobs = [Job(c, w, ctrl, tuple(ov.items()), s, a_deg, car)
            for c in cases for w, (ctrl, ov) in who.items() for s in args.seeds]
    vjobs = [VmaxJob(w, ctrl, tuple(ov.items()), s, pert, car)
             for w, (ctrl, ov) in who.items() for s in args.seeds for pert in (False, True)
             ] if args.vmax else []
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(run_job, jobs))
        vmax = list(pool.map(run_vmax, vjobs))
    if args.json is not None:
        args.json.write_text(json.dumps({"runs": results, "vmax": vmax}, indent=1,
                                        default=float))
    print(f"in-process screen, seeds {list(args.seeds)}, A = {a_deg:.1f}°, "
          f"plant {vehicle or 'nominal'}, medians over the seeds")
    print(format_table(summary(results, [c.label for c in cases], list(who))))
    if vmax:
        print("\nDLC v_max (paper rule), km/h, median [min–max] over the seeds")
        print(vmax_summary(vmax, list(who)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
