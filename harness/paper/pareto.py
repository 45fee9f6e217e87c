"""Pareto view of each controller: max |β| against path deviation over its trade-off knob.

Each MPC controller is swept over one knob that trades sideslip against path keeping. A
point of a plane is one knob setting; each axis is the median over seeds (a seed sets the
plant's sensor noise and biases and the RHONN's initial weights). Both axes are
lower-is-better:

- y: max |β| over the point's runs, °;
- x, limit curve (slippery-curve-limit: μ 0.35, 85 km/h held, R = 165 and 170 m): max
  |lateral deviation|, m;
- x, sine with dwell (μ 0.5 and 1.0; the benchmark's amplitudes from 5A to its top, both
  directions): 1.83 m − the smallest lateral displacement at BOS + 1.07 s over the runs, m
  (the FMVSS 126 deficit; negative = margin);
- x, DLC (dlc-paper, μ 0.35, 74 km/h): max |lateral deviation|, m.

The passive car is one reference point per plane. A point with a spun run in any seed stays
in the tables but not in the fronts or verdicts. Verdicts: nmpc-rhonn's front dominates a
baseline when every valid point of the baseline is weakly dominated by an nmpc-rhonn point
(on the medians, and counted seed by seed on each seed's own points); on the limit curve,
every point within 0.5 m of the best baseline deviation with max |β| ≤ 5°.

Knob choice, measured with :func:`sensitivity_tables` (seed 1, the five planes above, each
candidate knob swept alone). The width of a knob in a plane is min(path span, β span) along
the knob's own non-dominated front, each span as a fraction of the plane's spread over every
sensitivity point; its score is the sum over the planes (:func:`knob_scores`):

- nmpc-rhonn: θ, both sideslip thresholds of the references together (blend_beta_lo = θ/3,
  blend_beta_hi = guard_beta_rad = θ; packaged θ = 3°), score 1.29. θ 1.5° → 6° moves the
  R 165 m curve from 16.5 m / 1.8° to 3.6 m / 5.6° (R 170 m: 12.5 m / 1.8° → 1.6 m / 5.0°),
  the sine μ 1 max |β| 9.9 → 12.8° and the DLC 0.91 m / 1.9° → 0.87 m / 2.5°. Each part
  alone moves less: guard_beta_rad 1°–4° (0.72) R 165 m 19.0 m / 2.0° → 5.7 m / 3.4°, and
  4° is nearly off (the blend keeps |β| below it); blend_beta_lo/hi 0.5–2.5° …
  4–6° (0.10) R 165 m 6.8 → 4.8 m at 3.2–3.4°. mpc.r_beta (0.97) and mpc.q_yaw (0.79) score
  on the sine planes only: r_beta 0 → 1e4 at μ 0.5 max |β| 3.0 → 20.2° for a deficit
  0.24 → −0.03 m (1e5 spins); q_yaw 10 → 3000 16.2 → 2.9° for 0.06 → 0.26 m; on the R 165 m
  curve (5.4–6.7 m) and the DLC (0.85–1.09 m) neither trades.
- nmpc-mf and lmpc: mpc.r_beta, score 0.29 and 0.23. nmpc-mf 0 → 1e5: R 165 m 3.83 m /
  12.0° → 4.93 m / 7.0°, R 170 m 1.49 m / 4.9° → 2.56 m / 4.2°, DLC 0.84 m / 2.9° → 1.06 m
  / 2.1°; lmpc alike up to 1e4 (R 165 m 3.79 m / 10.9° → 4.23 m / 7.5°) and spun on the
  limit curve at 1e5, so the sweep ends at 3e4 (where one of three lmpc seeds still spun on
  R 165 m in the sweep). mpc.q_yaw sets the same q/r ratio the other
  way (q_yaw 10 ≈ r_beta 1e4: nmpc-mf R 165 m 4.16 m / 7.3° against 4.29 m / 7.2°) but its
  3–1000 sweep spans less (0.10, 0.07); mpc.input_reg moves neither axis on the curve
  (3.79–3.84 m, 9.4–10.0°) and at 1.0 worsens the DLC on both (1.28 m / 5.9°; scores 0.05,
  0.09). No baseline knob moves the sine displacement (deficit −0.05 to −0.06 m at μ 0.5,
  −1.13 to −1.17 m at μ 1, at every setting).

Every run is a run over the bus in the benchmark's campaign (harness/paper/benchmark.py).
API: :func:`pareto_specs`, :func:`pareto_tables` (runner: a benchmark run source),
:func:`pareto_markdown`, :func:`pareto_figure`, :func:`pareto_section`; sizes in
:class:`ParetoPlan`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import seed_text
from harness.analysis.fmvss126 import amplitude_schedule_deg
from harness.paper.benchmark import RunSource, Section, bench_run, summarise
from harness.run.spec import RunSpec

Point = tuple[float, float]
"""(path metric m, max |β| °): lower is better on both axes."""
Refs = tuple[tuple[str, Any], ...]
Runner = RunSource

FMVSS_MIN_DISPLACEMENT_M = 1.83
"""FMVSS 126 lateral displacement required at BOS + 1.07 s from 5A on, m."""
NEAR_BEST_M = 0.5
"""Path margin to the best baseline for the limit-curve check, m."""
BETA_OK_DEG = 5.0
"""Sideslip bound of the limit-curve check, °."""
DEG = math.pi / 180.0
"""rad per °."""
BASELINES = ("nmpc-mf", "lmpc")
SECTION_TITLE = "Pareto view: max |β| against path deviation"


# ------------------------------------------------------------------------ knobs
@dataclass(frozen=True)
class Knob:
    """A controller-config knob swept as one axis. key: what it changes (a config key or a
    short description); unit: of the labels; settings: (label, config overrides as
    bench_run refs) in sweep order; default: the label of the packaged setting; note: what a
    label means when it is not the key's own value."""

    key: str
    unit: str
    settings: tuple[tuple[str, Refs], ...]
    default: str
    note: str = ""

    @property
    def labels(self) -> list[str]:
        """The setting labels in sweep order."""
        return [label for label, _ in self.settings]

    def subset(self, labels: Sequence[str]) -> Knob:
        """The same knob with only ``labels`` (kept in sweep order)."""
        keep = tuple(s for s in self.settings if s[0] in set(labels))
        return dataclasses.replace(self, settings=keep)


def _label(value: float) -> str:
    """Compact label of a weight: 0, 300, 1e4, 3e4 (-)."""
    short = f"{value:.0e}"
    if value >= 1e4 and float(short) == value:
        mant, exp = short.split("e")
        return f"{mant}e{int(exp)}"
    return f"{value:g}"


def scalar_knob(key: str, values: Sequence[float], default: float, unit: str = "-") -> Knob:
    """One config key (``"SECTION.KEY"`` or a [references] key) set to each of ``values``."""
    return Knob(key, unit, tuple((_label(v), ((key, float(v)),)) for v in values),
                _label(default))


def guard_knob(thresholds_deg: Sequence[float], default_deg: float = 3.0) -> Knob:
    """The sideslip guard threshold ``guard_beta_rad`` at each of ``thresholds_deg`` (°),
    then the guard off (``guard_gain_per_s`` = 0, i.e. an infinite threshold)."""
    settings = tuple((f"{d:g}°", (("guard_beta_rad", round(d * DEG, 5)),))
                     for d in thresholds_deg)
    return Knob("references.guard_beta_rad", "°",
                (*settings, ("off", (("guard_gain_per_s", 0.0),))), f"{default_deg:g}°",
                "off: guard_gain_per_s = 0")


def blend_knob(lo_deg: Sequence[float], width_deg: float = 2.0, default_lo_deg: float = 1.0
               ) -> Knob:
    """Where Algorithm 1 takes over from the driver's demand: ``blend_beta_lo`` = lo (°) and
    ``blend_beta_hi`` = lo + ``width_deg`` (°); labels name lo–hi in °."""
    return Knob("references.blend_beta_lo/hi", "°", tuple(
        (f"{lo:g}–{lo + width_deg:g}°", (("blend_beta_lo", round(lo * DEG, 5)),
                                         ("blend_beta_hi", round((lo + width_deg) * DEG, 5))))
        for lo in lo_deg), f"{default_lo_deg:g}–{default_lo_deg + width_deg:g}°")


def threshold_knob(thresholds_deg: Sequence[float], default_deg: float = 3.0) -> Knob:
    """Both sideslip thresholds of the nmpc-rhonn references scaled together: Algorithm 1
    blends in from θ/3 to θ and the guard acts from θ (θ in °; packaged: θ = 3°)."""
    return Knob("references.blend_beta_lo/hi + guard_beta_rad", "°", tuple(
        (f"{d:g}°", (("blend_beta_lo", round(d / 3.0 * DEG, 5)),
                     ("blend_beta_hi", round(d * DEG, 5)), ("guard_beta_rad", round(d * DEG, 5))))
        for d in thresholds_deg), f"{default_deg:g}°",
        "label θ: blend_beta_lo = θ/3, blend_beta_hi = θ, guard_beta_rad = θ")


def candidate_knobs() -> dict[str, list[Knob]]:
    """The knobs the sensitivity table measures, per MPC controller."""
    base = [scalar_knob("mpc.r_beta", (0.0, 100.0, 1000.0, 1e4, 1e5), 1000.0),
            scalar_knob("mpc.q_yaw", (3.0, 10.0, 30.0, 100.0, 300.0, 1000.0), 100.0),
            scalar_knob("mpc.input_reg", (0.01, 0.03, 0.1, 0.3, 1.0), 0.1)]
    rhonn = [guard_knob((1.0, 2.0, 3.0, 4.0)),
             blend_knob((0.5, 1.0, 2.0, 3.0, 4.0)),
             threshold_knob((1.5, 2.0, 3.0, 4.0, 5.0, 6.0)),
             scalar_knob("mpc.q_yaw", (10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0), 100.0),
             scalar_knob("mpc.r_beta", (0.0, 1000.0, 1e4, 1e5), 1000.0)]
    return {"nmpc-rhonn": rhonn, "nmpc-mf": list(base), "lmpc": list(base)}


def default_knobs() -> dict[str, Knob]:
    """The trade-off knob chosen per MPC controller (the widest by ``knob_scores``; see the
    module docstring)."""
    weights = scalar_knob("mpc.r_beta", (0.0, 300.0, 1000.0, 3000.0, 1e4, 3e4), 1000.0)
    return {"nmpc-rhonn": threshold_knob((1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0)),
            "nmpc-mf": weights, "lmpc": weights}


# ------------------------------------------------------------------------ planes
@dataclass(frozen=True)
class Plane:
    """One trade-off plane. kind: "curve" (slippery-curve-limit, value = radius m),
    "sine" (sine with dwell, value = road μ -) or "dlc" (dlc-paper, value = speed km/h,
    mu = road μ -)."""

    kind: str
    value: float
    mu: float | None = None

    @property
    def key(self) -> str:
        """Name of the plane in the tables."""
        if self.kind == "curve":
            return f"limit curve R {self.value:g} m"
        if self.kind == "sine":
            return f"sine with dwell μ {self.value:g}"
        return f"DLC μ {self.mu:g} {self.value:g} km/h"

    @property
    def x_label(self) -> str:
        """Meaning and unit of the plane's path axis (lower is better)."""
        if self.kind == "sine":
            return (f"displacement deficit {FMVSS_MIN_DISPLACEMENT_M} m − min lateral "
                    "displacement, m (< 0: margin)")
        return "max |lateral deviation|, m"


@dataclass
class ParetoPlan:
    """Sizes of the sweep. seeds: plant noise + RHONN initial weights; knobs: controller →
    Knob; curve_radii_m: m; sine_mus: road μ (-); sine_from_a: lowest amplitude in units of
    A (-); sine_top_only: only the top amplitude; sine_directions: first-lobe sides;
    dlc_speed_kmh: km/h; dlc_mu: road μ (-); a_deg: FMVSS 126 A, ° (the benchmark sets it
    from the passive car's slowly-increasing-steer run)."""

    seeds: tuple[int, ...] = (1, 2, 3)
    knobs: dict[str, Knob] = field(default_factory=default_knobs)
    curve_radii_m: tuple[float, ...] = (165.0, 170.0)
    sine_mus: tuple[float, ...] = (0.5, 1.0)
    sine_from_a: float = 5.0
    sine_top_only: bool = False
    sine_directions: tuple[str, ...] = ("left", "right")
    dlc_speed_kmh: float = 74.0
    dlc_mu: float = 0.35
    passive: bool = True
    a_deg: float | None = None

    @classmethod
    def full(cls, seeds: tuple[int, ...] = (1, 2, 3)) -> ParetoPlan:
        """Every plane, the chosen knobs with all their settings."""
        return cls(seeds=seeds)

    @classmethod
    def quick(cls) -> ParetoPlan:
        """One seed, two settings per knob, one curve radius, one sine road at the top
        amplitude in one direction (a test-suite smoke version)."""
        knobs = {c: k.subset([k.default, k.labels[0]]) for c, k in default_knobs().items()}
        return cls(seeds=(1,), knobs=knobs, curve_radii_m=(165.0,), sine_mus=(0.5,),
                   sine_top_only=True, sine_directions=("left",))

    def planes(self) -> list[Plane]:
        """The planes in report order."""
        return ([Plane("curve", r) for r in self.curve_radii_m]
                + [Plane("sine", m) for m in self.sine_mus]
                + [Plane("dlc", self.dlc_speed_kmh, self.dlc_mu)])


def plan_a_deg(plan: ParetoPlan) -> float:
    """FMVSS 126 A of the plan, ° (a ValueError when the plan has none)."""
    if plan.a_deg is None:
        raise ValueError("the Pareto plan needs FMVSS 126 A (a_deg, deg)")
    return plan.a_deg


def sine_amplitudes_deg(plan: ParetoPlan) -> list[float]:
    """Steering-wheel amplitudes of the sine planes, °: the benchmark's schedule from
    ``sine_from_a``·A on (or its top amplitude only)."""
    a = plan_a_deg(plan)
    amps = amplitude_schedule_deg(a, standard_rule=True)
    return amps[-1:] if plan.sine_top_only else [x for x in amps
                                                 if x >= plan.sine_from_a * a - 1e-9]


def plane_specs(plane: Plane, plan: ParetoPlan, controller: str, refs: Refs, seed: int
                ) -> list[RunSpec]:
    """The runs behind one point of ``plane`` for one seed (as the benchmark specifies
    them)."""
    if plane.kind == "curve":
        return [bench_run("slippery-curve-limit", controller, None, None, seed, (), refs,
                          (("radius_m", plane.value),), kind="path")]
    if plane.kind == "sine":
        sc = "sine-with-dwell" if plane.value >= 1.0 else "sine-with-dwell-low-mu"
        return [bench_run(sc, controller, None, plane.value, seed, (), refs,
                          (("amplitude_deg", a), ("direction", d)), "sine",
                          plan_a_deg(plan))
                for a in sine_amplitudes_deg(plan) for d in plan.sine_directions]
    return [bench_run("dlc-paper", controller, plane.value, plane.mu, seed, (), refs)]


def seed_point(plane: Plane, results: list[dict[str, Any]]) -> dict[str, Any]:
    """One seed's point from its runs: x (path metric, m), y (max |β| over the runs, °),
    spun (any run spun), missing (sine runs without a displacement)."""
    beta = max(r["max_abs_beta_deg"] for r in results)
    spun = any(r["spun"] for r in results)
    if plane.kind != "sine":
        return {"x": max(r["max_abs_dev_m"] for r in results), "y": beta, "spun": spun,
                "missing": 0}
    disp = [r["lateral_displacement_m"] for r in results]
    ok = [d for d in disp if d is not None and math.isfinite(d)]
    x = FMVSS_MIN_DISPLACEMENT_M - min(ok) if ok else math.nan
    return {"x": x, "y": beta, "spun": spun, "missing": len(disp) - len(ok)}


def merge_seeds(points: list[dict[str, Any]]) -> dict[str, Any]:
    """The median point over seeds (each axis separately) with min–max per axis."""
    xs, ys = summarise([p["x"] for p in points]), summarise([p["y"] for p in points])
    return {"x": xs["median"], "y": ys["median"], "x_range": [xs["min"], xs["max"]],
            "y_range": [ys["min"], ys["max"]], "spun": sum(p["spun"] for p in points),
            "missing": sum(p["missing"] for p in points), "n": len(points),
            "per_seed": [[p["x"], p["y"], p["spun"]] for p in points]}


# ------------------------------------------------------------------------ dominance
def weakly_dominates(a: Point, b: Point) -> bool:
    """a is at least as good as b on both axes (lower is better)."""
    return a[0] <= b[0] and a[1] <= b[1]


def strictly_dominates(a: Point, b: Point) -> bool:
    """a weakly dominates b and is better on at least one axis."""
    return weakly_dominates(a, b) and (a[0] < b[0] or a[1] < b[1])


def non_dominated(points: Sequence[Point]) -> list[int]:
    """Indices of the points no other point strictly dominates (ties all kept), ordered by
    the path axis then the β axis."""
    keep = [i for i, p in enumerate(points)
            if not any(strictly_dominates(q, p) for j, q in enumerate(points) if j != i)]
    return sorted(keep, key=lambda i: (points[i][0], points[i][1]))


def undominated_by(front: Sequence[Point], others: Sequence[Point]) -> list[int]:
    """Indices of ``others`` that no point of ``front`` weakly dominates."""
    return [i for i, o in enumerate(others) if not any(weakly_dominates(f, o) for f in front)]


def front_dominates(front: Sequence[Point], others: Sequence[Point]) -> bool:
    """Every point of ``others`` is weakly dominated by some point of ``front``."""
    return not undominated_by(front, others)


# ------------------------------------------------------------------------ tables
def _valid(p: dict[str, Any]) -> bool:
    """A point that counts for fronts: finite on both axes and no seed spun."""
    return (p["x"] is not None and p["y"] is not None and math.isfinite(p["x"])
            and math.isfinite(p["y"]) and not p["spun"])


def _front(points: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The non-dominated valid points, by path metric."""
    valid = [p for p in points if _valid(p)]
    return [valid[i] for i in non_dominated([(p["x"], p["y"]) for p in valid])]


def _xy(points: list[dict[str, Any]]) -> list[Point]:
    return [(p["x"], p["y"]) for p in points]


def dominance(points: dict[str, list[dict[str, Any]]], leader: str = "nmpc-rhonn"
              ) -> dict[str, Any]:
    """Does ``leader``'s front weakly dominate every valid point of each other controller
    (median points); the labels of the points it does not; and, when the points carry
    ``per_seed``, in how many seeds the same holds on that seed's own points."""
    lead = _xy(_front(points[leader]))
    out: dict[str, Any] = {}
    for c, pts in points.items():
        if c == leader:
            continue
        valid = [p for p in pts if _valid(p)]
        miss = undominated_by(lead, _xy(valid))
        out[c] = {"dominates": not miss, "undominated": [valid[i]["label"] for i in miss]}
        seeds = _seed_verdicts(points[leader], pts)
        if seeds is not None:
            out[c]["seeds_dominating"], out[c]["n_seeds"] = sum(seeds), len(seeds)
    return out


def _seed_points(pts: list[dict[str, Any]], i: int) -> list[dict[str, Any]]:
    """Seed i's own points (x, y, spun of that seed only)."""
    return [{"label": p["label"], "x": p["per_seed"][i][0], "y": p["per_seed"][i][1],
             "spun": p["per_seed"][i][2]} for p in pts]


def _seed_verdicts(lead: list[dict[str, Any]], other: list[dict[str, Any]]
                   ) -> list[bool] | None:
    """Per seed: does ``lead``'s front of that seed dominate ``other``'s valid points of
    that seed (None without per-seed data)."""
    every = lead + other
    if not every or any("per_seed" not in p for p in every):
        return None
    n = min(len(p["per_seed"]) for p in every)
    return [front_dominates(_xy(_front(_seed_points(lead, i))),
                            _xy([p for p in _seed_points(other, i) if _valid(p)]))
            for i in range(n)]


def near_best_baseline(points: dict[str, list[dict[str, Any]]],
                       passive: dict[str, Any] | None = None) -> dict[str, Any]:
    """Limit-curve check: the best baseline deviation (m) and every valid point of any
    controller within NEAR_BEST_M of it with max |β| ≤ BETA_OK_DEG."""
    base = [(c, p) for c in BASELINES if c in points for p in points[c] if _valid(p)]
    if not base:
        return {"best": None, "points": []}
    bc, bp = min(base, key=lambda cp: (cp[1]["x"], cp[1]["y"]))
    pool = [(c, p) for c, ps in points.items() for p in ps]
    pool += [("passive", passive)] if passive else []
    hits = [{"controller": c, "label": p["label"], "x": p["x"], "y": p["y"]} for c, p in pool
            if _valid(p) and p["x"] <= bp["x"] + NEAR_BEST_M and p["y"] <= BETA_OK_DEG]
    return {"best": {"controller": bc, "label": bp["label"], "x": bp["x"], "y": bp["y"]},
            "within_m": NEAR_BEST_M, "beta_max_deg": BETA_OK_DEG, "points": hits}


def _groups(plan: ParetoPlan, knobs: dict[str, Knob]
            ) -> list[tuple[str, str, Plane, int, list[RunSpec]]]:
    """(group, setting label, plane, seed, runs) for every point of every seed. A group is
    a key of ``knobs``: the controller name, or "controller|anything" (several knobs of
    one controller); the passive car is group "passive" with label "—"."""
    cases = [(g, label, refs) for g, k in knobs.items() for label, refs in k.settings]
    cases += [("passive", "—", ())] if plan.passive else []
    return [(g, label, pl, s, plane_specs(pl, plan, g.partition("|")[0], refs, s))
            for pl in plan.planes() for g, label, refs in cases for s in plan.seeds]


def _points(plan: ParetoPlan, knobs: dict[str, Knob], runner: Runner
            ) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """plane key → group → [median point per setting, in sweep order]."""
    groups = _groups(plan, knobs)
    res = iter(runner([s for g in groups for s in g[4]]))
    per: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for g, label, pl, _, specs in groups:
        rs = [next(res) for _ in specs]
        per.setdefault((pl.key, g, label), []).append(seed_point(pl, rs))
    out: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for (pk, g, label), pts in per.items():
        out.setdefault(pk, {}).setdefault(g, []).append({"label": label, **merge_seeds(pts)})
    return out


def _plane_table(plane: Plane, pts: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Points, fronts and verdicts of one plane."""
    passive = pts.pop("passive", [None])[0]
    t: dict[str, Any] = {"kind": plane.kind, "x_label": plane.x_label,
                         "y_label": "max |β|, °", "points": pts, "passive": passive,
                         "fronts": {c: [p["label"] for p in _front(v)] for c, v in pts.items()}}
    if "nmpc-rhonn" in pts and len(pts) > 1:
        t["dominance"] = dominance(pts)
    if plane.kind == "curve":
        t["near_best_baseline"] = near_best_baseline(pts, passive)
    return t


def _knob_json(k: Knob) -> dict[str, Any]:
    """A knob as plain data."""
    return {"key": k.key, "unit": k.unit, "labels": k.labels, "default": k.default,
            "note": k.note, "refs": {lab: [list(r) for r in refs] for lab, refs in k.settings}}


def _plan_json(plan: ParetoPlan) -> dict[str, Any]:
    """The plan as plain data."""
    return {"seeds": list(plan.seeds), "curve_radii_m": list(plan.curve_radii_m),
            "sine_mus": list(plan.sine_mus), "sine_directions": list(plan.sine_directions),
            "sine_amplitudes_deg": sine_amplitudes_deg(plan), "a_deg": plan_a_deg(plan),
            "dlc_speed_kmh": plan.dlc_speed_kmh, "dlc_mu": plan.dlc_mu,
            "knobs": {c: _knob_json(k) for c, k in plan.knobs.items()}}


def pareto_specs(plan: ParetoPlan) -> list[RunSpec]:
    """Every run of the sweep (controllers × settings × planes × seeds, plus passive)."""
    return [s for g in _groups(plan, plan.knobs) for s in g[4]]


def pareto_tables(plan: ParetoPlan, runner: Runner) -> dict[str, Any]:
    """Run the sweep through ``runner`` (a benchmark run source); the points (median
    over seeds), fronts and verdicts per plane as plain data."""
    pts = _points(plan, plan.knobs, runner)
    return {"plan": _plan_json(plan),
            "planes": {pl.key: _plane_table(pl, pts[pl.key]) for pl in plan.planes()}}


# ------------------------------------------------------------------------ sensitivity
def knob_extent(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Extent of one knob's own front in a plane: its size (settings), the span of the
    path metric (m) and of max |β| (°) along it, and the settings that spun."""
    f = _front(points)
    return {"front": [p["label"] for p in f], "size": len(f),
            "dx_m": (f[-1]["x"] - f[0]["x"]) if f else 0.0,
            "dbeta_deg": (f[0]["y"] - f[-1]["y"]) if f else 0.0,
            "spun": [p["label"] for p in points if p["spun"]]}


def sensitivity_tables(plan: ParetoPlan, runner: Runner,
                       candidates: dict[str, list[Knob]] | None = None) -> dict[str, Any]:
    """Each candidate knob swept alone on the plan's planes (first seed only): controller →
    knob key → {"labels", "default", "points": plane → points, "extent": plane →
    knob_extent, "score": knob_scores}."""
    cands = candidates or candidate_knobs()
    one = dataclasses.replace(plan, seeds=plan.seeds[:1], passive=False)
    out: dict[str, Any] = {}
    flat = {f"{c}|{k.key}": k for c, ks in cands.items() for k in ks}
    got = _points(one, flat, runner)
    for ck, k in flat.items():
        c, _, key = ck.partition("|")
        pts = {pk: got[pk][ck] for pk in got}
        out.setdefault(c, {})[key] = {
            "labels": k.labels, "default": k.default, "points": pts,
            "extent": {pk: knob_extent(v) for pk, v in pts.items()}}
    for c, ks in knob_scores(out).items():
        for key, score in ks.items():
            out[c][key]["score"] = score
    return out


def plane_spreads(sens: dict[str, Any]) -> dict[str, tuple[float, float]]:
    """Per plane, the spread (max − min) of the path metric (m) and of max |β| (°) over
    every valid point of a sensitivity table."""
    pts: dict[str, list[Point]] = {}
    for ks in sens.values():
        for k in ks.values():
            for pk, v in k["points"].items():
                pts.setdefault(pk, []).extend(_xy([p for p in v if _valid(p)]))
    return {pk: (float(np.ptp([p[0] for p in v])), float(np.ptp([p[1] for p in v])))
            for pk, v in pts.items()}


def knob_scores(sens: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Width of each knob's trade-off (-): over the planes, the sum of min(path span, β span)
    along the knob's own front, each span as a fraction of the plane's spread
    (plane_spreads). A knob that moves one axis only, or makes both worse, scores 0."""
    spread = plane_spreads(sens)
    return {c: {key: float(sum(min(e["dx_m"] / max(spread[pk][0], 1e-9),
                                   e["dbeta_deg"] / max(spread[pk][1], 1e-9))
                               for pk, e in k["extent"].items()))
                for key, k in ks.items()}
            for c, ks in sens.items()}


# ------------------------------------------------------------------------ markdown
def _f(v: float | None, fmt: str = "{:.2f}") -> str:
    return "—" if v is None or not math.isfinite(v) else fmt.format(v)


def _point_cell(p: dict[str, Any]) -> str:
    """'x m / y °' with the seed range when it is wider than the rounding."""
    def one(v: float, rng: list[float], fmt: str) -> str:
        s = _f(v, fmt)
        if rng[0] is not None and fmt.format(rng[0]) != fmt.format(rng[1]):
            s += f" [{_f(rng[0], fmt)}–{_f(rng[1], fmt)}]"
        return s
    return f"{one(p['x'], p['x_range'], '{:.2f}')} | {one(p['y'], p['y_range'], '{:.1f}')}"


def _plane_markdown(key: str, t: dict[str, Any], knobs: dict[str, Any]) -> list[str]:
    L = [f"### {key}", "", f"x: {t['x_label']}; y: {t['y_label']}. ★ = on the "
         "controller's front.", "", "| controller | knob setting | x | max \\|β\\|, ° | spun "
         "seeds |", "|---|---|---|---|---|"]
    for c, pts in t["points"].items():
        front = set(t["fronts"][c])
        for p in pts:
            star = " ★" if p["label"] in front else ""
            dflt = " (default)" if p["label"] == knobs[c]["default"] else ""
            L.append(f"| {c} | {p['label']}{dflt}{star} | {_point_cell(p)} | {p['spun']} |")
    if t["passive"]:
        L.append(f"| passive | — | {_point_cell(t['passive'])} | {t['passive']['spun']} |")
    L.append("")
    for c, d in t.get("dominance", {}).items():
        seeds = (f" Seed by seed: {d['seeds_dominating']}/{d['n_seeds']} seeds."
                 if "n_seeds" in d else "")
        if d["dominates"]:
            L.append(f"- nmpc-rhonn's front dominates {c}'s: **yes** (every {c} point is "
                     f"weakly dominated by an nmpc-rhonn point).{seeds}")
        else:
            miss = ", ".join(_named(t, c, lab) for lab in d["undominated"])
            L.append(f"- nmpc-rhonn's front dominates {c}'s: **no** — not dominated: "
                     f"{miss}.{seeds}")
    nb = t.get("near_best_baseline")
    if nb and nb["best"]:
        b = nb["best"]
        hits = ", ".join(f"{h['controller']} {h['label']} ({h['x']:.2f} m, {h['y']:.1f}°)"
                         for h in nb["points"]) or "none"
        L.append(f"- Best baseline deviation {b['x']:.2f} m ({b['controller']} "
                 f"{b['label']}, max |β| {b['y']:.1f}°); points with deviation ≤ "
                 f"{b['x'] + nb['within_m']:.2f} m and max |β| ≤ {nb['beta_max_deg']:g}°: "
                 f"{hits}.")
    return [*L, ""]


def _named(t: dict[str, Any], c: str, label: str) -> str:
    """'label (x, y)' of controller c's point ``label`` in plane table t."""
    p = next(p for p in t["points"][c] if p["label"] == label)
    return f"{label} ({p['x']:.2f} m, {p['y']:.1f}°)"


def _sensitivity_markdown(sens: dict[str, Any]) -> list[str]:
    planes = list(next(iter(next(iter(sens.values())).values()))["extent"])
    L = ["### Knob sensitivity (seed 1): extent of each knob's own front", "",
         "Per plane: front size / path span (m) / max |β| span (°) along the front; spun "
         "settings in brackets. Score: the sum over the planes of min(path span, β span), "
         "each as a fraction of the plane's spread over every point of this table; the "
         "highest score per controller is the swept knob (✓).", "",
         "| controller | knob | settings | " + " | ".join(planes) + " | score |",
         "|---|---|---|" + "---|" * (len(planes) + 1)]
    for c, ks in sens.items():
        for key, k in ks.items():
            cells = []
            for pk in planes:
                e = k["extent"][pk]
                spun = f" [spun {', '.join(e['spun'])}]" if e["spun"] else ""
                cells.append(f"{e['size']} / {e['dx_m']:.2f} / {e['dbeta_deg']:.1f}{spun}")
            best = max(ks.values(), key=lambda v: v.get("score", 0.0)) is k
            score = f"{k['score']:.2f}" + (" ✓" if best else "") if "score" in k else "—"
            L.append(f"| {c} | {key} | {', '.join(k['labels'])} | " + " | ".join(cells)
                     + f" | {score} |")
    return [*L, ""]


def pareto_markdown(tables: dict[str, Any]) -> str:
    """The Pareto section of the report, generated from the tables only."""
    plan = tables["plan"]
    amps = ", ".join(f"{a:.0f}" for a in plan["sine_amplitudes_deg"])
    L = [f"## {SECTION_TITLE}", "",
         "Each point is one setting of the controller's trade-off knob, the median over seeds "
         f"{seed_text(plan['seeds'])} of each axis separately (seed range in brackets). "
         "Lower is better "
         "on both axes. A point counts for the fronts and verdicts only if no seed spun. "
         f"Limit curve: slippery-curve-limit (μ 0.35, 85 km/h held). Sine with dwell: "
         f"A = {plan['a_deg']:.1f}°, amplitudes {amps}°, directions "
         f"{', '.join(plan['sine_directions'])}; per seed the smallest lateral displacement "
         f"and the largest |β| over those runs; x = {FMVSS_MIN_DISPLACEMENT_M} m − that "
         f"displacement (negative = margin to FMVSS 126). DLC: dlc-paper at "
         f"{plan['dlc_speed_kmh']:g} km/h, μ {plan['dlc_mu']:g}.", "",
         "| controller | knob | settings (sweep order) | packaged |", "|---|---|---|---|"]
    for c, k in plan["knobs"].items():
        note = f" ({k['note']})" if k.get("note") else ""
        L.append(f"| {c} | {k['key']}{note} | {', '.join(k['labels'])} | {k['default']} |")
    L.append("")
    for key, t in tables["planes"].items():
        L += _plane_markdown(key, t, plan["knobs"])
    if tables.get("sensitivity"):
        L += _sensitivity_markdown(tables["sensitivity"])
    return "\n".join(L) + "\n"


# ------------------------------------------------------------------------ figure
COLOURS = {"nmpc-rhonn": "tab:blue", "nmpc-mf": "tab:orange", "lmpc": "tab:green"}
MARKERS = {"nmpc-rhonn": "o", "nmpc-mf": "s", "lmpc": "^"}
LABEL_OFFSETS = {"nmpc-rhonn": (3, 3, "left"), "nmpc-mf": (-4, 2, "right"),
                 "lmpc": (4, -7, "left")}
"""Setting labels: offset (points) and alignment per controller, so clusters stay legible."""


def _draw_plane(ax: Any, key: str, t: dict[str, Any]) -> None:
    """Points (markers, annotated with the setting), fronts (lines), passive (star)."""
    shown: list[Point] = []
    for c, pts in t["points"].items():
        col, mk = COLOURS.get(c, "tab:gray"), MARKERS.get(c, "o")
        ok = [p for p in pts if _valid(p)]
        ax.scatter([p["x"] for p in ok], [p["y"] for p in ok], color=col, marker=mk, s=22,
                   zorder=3)
        dx, dy, ha = LABEL_OFFSETS.get(c, (3, 3, "left"))
        for p in ok:
            ax.annotate(p["label"], (p["x"], p["y"]), textcoords="offset points",
                        xytext=(dx, dy), ha=ha, fontsize=6, color=col)
        shown += _xy(ok)
        fr = [p for p in pts if p["label"] in set(t["fronts"][c])]
        ax.plot([p["x"] for p in fr], [p["y"] for p in fr], color=col, lw=1.2, zorder=2)
        bad = [p["label"] for p in pts if not _valid(p)]
        if bad:
            ax.text(0.99, 0.99 - 0.06 * list(t["points"]).index(c), f"{c} spun (not shown):"
                    f" {', '.join(bad)}", transform=ax.transAxes, ha="right", va="top",
                    fontsize=6, color=col)
    pv = t.get("passive")
    if pv and _valid(pv) and _in_view(pv, shown):
        ax.scatter([pv["x"]], [pv["y"]], color="black", marker="*", s=60, zorder=4)
    elif pv:
        why = "spun" if pv["spun"] else "off view"
        ax.text(0.01, 0.99, f"passive ({why}): {_f(pv['x'])} m, {_f(pv['y'], '{:.1f}')}°",
                transform=ax.transAxes, ha="left", va="top", fontsize=6)
    ax.set_title(key, fontsize=9)
    ax.set_xlabel(t["x_label"], fontsize=7)
    ax.set_ylabel(t["y_label"], fontsize=7)
    ax.tick_params(labelsize=7)
    ax.grid(True, lw=0.3)
    ax.margins(0.12)


def _in_view(p: dict[str, Any], shown: list[Point], factor: float = 1.0) -> bool:
    """The passive point lies within ``factor`` × the controllers' extent on both axes."""
    if not shown:
        return True
    xs, ys = np.array([s[0] for s in shown]), np.array([s[1] for s in shown])
    span_x, span_y = max(np.ptp(xs), 0.2), max(np.ptp(ys), 1.0)
    return (xs.min() - factor * span_x <= p["x"] <= xs.max() + factor * span_x
            and ys.min() - factor * span_y <= p["y"] <= ys.max() + factor * span_y)


def pareto_figure(tables: dict[str, Any], path: Path | str) -> Path:
    """One PNG, one subplot per plane, every panel alike: path metric on x, max |β| on y,
    both linear, lower-is-better and with the same margins; one colour and marker per
    controller throughout, fronts as lines, every valid setting a marker labelled with it,
    the passive car a star when in view (else named in the corner), spun settings named;
    the legend in its own panel outside the data. Returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    planes = tables["planes"]
    ncol = 3
    nrow = (len(planes) + 1 + ncol - 1) // ncol
    fig = Figure(figsize=(4.2 * ncol, 3.5 * nrow), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    for ax, (key, t) in zip(axes, planes.items(), strict=False):
        _draw_plane(ax, key, t)
    knobs = tables["plan"]["knobs"]
    handles = [Line2D([], [], color=COLOURS[c], marker=MARKERS[c], lw=1.2,
                      label=f"{c}: {knobs[c]['key']}"
                      + (f"\n  ({knobs[c]['note']})" if knobs[c].get("note") else ""))
               for c in knobs]
    handles.append(Line2D([], [], color="black", marker="*", lw=0, ms=9, label="passive"))
    leg_ax = axes[len(planes)]
    leg_ax.axis("off")
    leg_ax.legend(handles=handles, loc="center", fontsize=7, frameon=False,
                  title="markers: settings (median over seeds)\nlines: non-dominated fronts",
                  title_fontsize=7)
    for ax in axes[len(planes) + 1:]:
        ax.axis("off")
    fig.suptitle(SECTION_TITLE + " (lower-left is better)", fontsize=10)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=130)
    return out


def pareto_section(plan: ParetoPlan) -> Callable[[float], Section]:
    """The sweep as a section of ``rhonn-harness benchmark`` (A from the benchmark's
    slowly-increasing-steer run unless the plan has one; writes pareto.json, pareto.png)."""
    def make(a_deg: float) -> Section:
        full = plan if plan.a_deg is not None else dataclasses.replace(plan, a_deg=a_deg)

        def write(out_dir: Path, t: dict[str, Any]) -> str:
            (out_dir / "pareto.json").write_text(json.dumps(t, indent=1, default=str))
            pareto_figure(t, out_dir / "pareto.png")
            return pareto_markdown(t) + "\n![Pareto fronts](pareto.png)\n"

        return Section("pareto", lambda src: pareto_tables(full, src), write)

    return make


__all__ = ["Knob", "ParetoPlan", "Plane", "front_dominates", "non_dominated",
           "pareto_figure", "pareto_markdown", "pareto_section", "pareto_specs",
           "pareto_tables",
           "sensitivity_tables", "strictly_dominates", "undominated_by", "weakly_dominates"]
