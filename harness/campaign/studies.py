"""Derived studies: runs whose configuration depends on earlier runs' results.

* :class:`VmaxStudy`: maximum DLC entry speed (km/h) by bisection, one
  :class:`harness.analysis.vmax.Bisection` per controller and seed;
* :class:`FmvssStudy`: FMVSS 126 sine with dwell: per seed, the passive car's
  slowly-increasing-steer run gives A (deg), then every controller × direction × amplitude.

A study hands out :class:`RunSpec` s (``initial``), is fed each finished row (``feed``, which
returns the next runs) and summarises over seeds (``to_json``). Rows from a resumed campaign
are fed exactly like fresh ones, so a resumed bisection replays to the same point.
"""

from __future__ import annotations

import json
import statistics
from typing import Any

import numpy as np

from harness.analysis.fmvss126 import amplitude_schedule_deg
from harness.analysis.vmax import Bisection
from harness.campaign.spec import RunSpec, StudyDecl
from plant_sim.scenario import load_scenario

FMVSS_FULL_SCHEDULE_RUNS = 11  # 1.5A … 6.5A in 0.5A steps (harness.analysis.fmvss126)


def _spread(values: list[float]) -> dict[str, Any]:
    """Median and min–max of a list (None entries dropped)."""
    v = [x for x in values if x is not None]
    if not v:
        return {"n": 0, "median": None, "min": None, "max": None}
    return {"n": len(v), "median": float(statistics.median(v)), "min": float(min(v)),
            "max": float(max(v))}


def coast_duration_s(scenario: str, speed_kmh: float) -> float:
    """Simulated s to coast the scenario's whole reference path from ``speed_kmh`` (×1.5 for
    the speed lost while coasting) plus 3 s, at least 18 s (as the paper study's v_max runs)."""
    p = load_scenario(scenario).reference_path_xy
    length = float(np.sum(np.hypot(*np.diff(p, axis=0).T)))
    return max(18.0, 1.5 * length / (speed_kmh / 3.6) + 3.0)


class VmaxStudy:
    """v_max bisection per controller, seed and rule; one probe run serves every rule.

    Options (campaign ``[[study]]`` keys): ``scenario``, ``mu``, ``bracket_kmh``,
    ``resolution_kmh``, ``verify_offsets_kmh``; ``rules``: what decides a probe (default
    ``["passed_dlc"]``, the run's KPI; ``paper``, ``course``, ``stable``: the verdicts of the
    probe's ``stability`` post step); ``vehicle`` (plant overrides), ``controller_overrides``
    (``"SECTION.KEY" = value``), ``seed_overrides`` (config keys set to the probe's seed),
    ``post`` and ``info`` of every probe; ``coast_duration`` (default true: a probe runs long
    enough to coast the whole path, :func:`coast_duration_s`; false: the scenario's
    duration).
    """

    def __init__(self, decl: StudyDecl) -> None:
        o = decl.options
        self.decl = decl
        self.scenario = str(o.get("scenario", "dlc-paper"))
        self.mu = None if o.get("mu") is None else float(o["mu"])
        self.cap = o.get("duration_cap_s")
        self.rules = tuple(str(r) for r in o.get("rules", ["passed_dlc"]))
        self.vehicle = tuple(sorted((str(k), float(v)) for k, v in
                                    dict(o.get("vehicle", {})).items()))
        self.overrides = dict(o.get("controller_overrides", {}))
        self.seed_overrides = tuple(str(k) for k in o.get("seed_overrides", []))
        self.post = tuple(str(p) for p in o.get("post", []))
        self.info = dict(o.get("info", {}))
        self.coast = bool(o.get("coast_duration", True))
        lo, hi = (float(x) for x in o.get("bracket_kmh", [30.0, 90.0]))
        res = float(o.get("resolution_kmh", 0.5))
        verify = tuple(float(x) for x in o.get("verify_offsets_kmh", [2.0, 5.0]))
        self.bis = {(c, s, r): Bisection(c, lo, hi, res, verify, rule=r)
                    for c in decl.controllers for s in decl.seeds for r in self.rules}
        # per (controller, seed, speed km/h): the probe's metrics (row KPIs + post verdicts)
        self.probes: dict[tuple[str, int, float], dict[str, Any]] = {}

    def _spec(self, c: str, seed: int, v: float) -> RunSpec:
        params: tuple[tuple[str, str], ...] = ()
        duration = None
        if self.cap is not None:
            duration = float(self.cap)
        elif self.coast:  # a scenario parameter: --duration can only cut a run short
            params = (("duration_s", f"{coast_duration_s(self.scenario, v):.1f}"),)
        return RunSpec(group=self.decl.name, scenario=self.scenario, controller=c, seed=seed,
                       mu=self.mu, speed_kmh=v, duration_s=duration, params=params,
                       vehicle=self.vehicle, post=self.post,
                       controller_overrides={**self.overrides,
                                             **{k: int(seed) for k in self.seed_overrides}},
                       info={**self.info, "study": "vmax", "v": v},
                       make_plots=False, make_rrd=False)  # probes: numbers, no pictures

    def _pending(self, c: str, seed: int) -> list[RunSpec]:
        """The next probes of (controller, seed) over every rule, each speed once."""
        want = {v for r in self.rules for v in self.bis[(c, seed, r)].pending()}
        return [self._spec(c, seed, v) for v in sorted(want)]

    def initial(self) -> list[RunSpec]:
        """The bracket ends of every bisection."""
        return [spec for c in self.decl.controllers for s in self.decl.seeds
                for spec in self._pending(c, s)]

    def feed(self, spec: RunSpec, row: dict[str, Any]) -> list[RunSpec]:
        """Record a probe in every bisection of its controller and seed waiting for its
        speed (a probe asked for by several rules is fed once per asking rule: the others
        are no longer waiting); return their next probes."""
        v = float(dict(spec.info)["v"])
        metrics = dict(row)
        for step in self.post:  # verdicts of the post steps (e.g. stability: paper, stable)
            got = json.loads(row.get("post") or "{}").get(step)
            if isinstance(got, dict) and "error" not in got:
                metrics.update(got)
        if row.get("status") == "error":  # no run: count it as a failed probe
            metrics["reason"] = row.get("error")
            for r in self.rules:
                metrics[r] = False
        self.probes[(spec.controller, spec.seed, round(v, 6))] = metrics
        for r in self.rules:
            b = self.bis[(spec.controller, spec.seed, r)]
            if round(v, 6) in b._waiting:
                b.record(v, metrics)
        return self._pending(spec.controller, spec.seed)

    def expected_remaining(self) -> int:
        """Rough number of probes still to come."""
        return sum(max((self.bis[(c, s, r)].expected_remaining() for r in self.rules),
                       default=0) for c in self.decl.controllers for s in self.decl.seeds)

    def _rule_json(self, rule: str) -> dict[str, Any]:
        """Per controller: every seed's bisection (with the largest max |β|, deg, of its
        passing probes) and v_max median/min–max over seeds."""
        out: dict[str, Any] = {}
        for c in self.decl.controllers:
            per_seed = {}
            for s in self.decl.seeds:
                j = self.bis[(c, s, rule)].to_json()
                betas = [p.get("max_abs_beta_deg") for p in j["probes"] if p["passed"]]
                j["max_beta_passing_deg"] = max((b for b in betas if b is not None),
                                                default=None)
                per_seed[str(s)] = j
            out[c] = {"vmax_kmh": _spread([r["vmax_kmh"] for r in per_seed.values()]),
                      "statuses": sorted({r["status"] for r in per_seed.values()}),
                      "seeds": per_seed}
        return out

    def to_json(self) -> dict[str, Any]:
        """Per controller the first rule's result (see :meth:`_rule_json`); with several
        rules, every rule's under ``rules``."""
        out: dict[str, Any] = {"kind": "vmax", "scenario": self.scenario,
                               "controllers": self._rule_json(self.rules[0])}
        if len(self.rules) > 1:
            out["rules"] = {r: self._rule_json(r) for r in self.rules}
        return out


class FmvssStudy:
    """FMVSS 126 amplitude series per controller, direction and seed."""

    def __init__(self, decl: StudyDecl) -> None:
        o = decl.options
        self.decl = decl
        self.directions = tuple(o.get("directions", ["left", "right"]))
        f = o.get("amplitude_factors")
        self.factors = None if not f else tuple(float(x) for x in f)
        cap = o.get("duration_cap_s")
        self.sis_duration = o.get("sis_duration_s", cap)
        self.duration = o.get("duration_s", cap)
        self.a_deg: dict[int, float | None] = {}
        self.amplitudes: dict[int, list[float]] = {}
        self.results: dict[tuple[str, int], list[dict[str, Any]]] = {
            (c, s): [] for c in decl.controllers for s in decl.seeds}

    def initial(self) -> list[RunSpec]:
        """One slowly-increasing-steer run of the passive car per seed."""
        return [RunSpec(group=self.decl.name, scenario="slowly-increasing-steer",
                        controller="passive", seed=s,
                        duration_s=None if self.sis_duration is None
                        else float(self.sis_duration), post=("sis",),
                        info=(("study", "fmvss-sis"),), make_plots=False, make_rrd=False)
                for s in self.decl.seeds]

    def feed(self, spec: RunSpec, row: dict[str, Any]) -> list[RunSpec]:
        """A from the SIS run → the amplitude series; an amplitude run → its verdict."""
        post = json.loads(row.get("post") or "{}")
        if spec.scenario == "slowly-increasing-steer":
            a = post.get("sis", {}).get("a_deg")
            self.a_deg[spec.seed] = a
            if a is None:
                self.amplitudes[spec.seed] = []
                return []
            amps = (amplitude_schedule_deg(a) if self.factors is None
                    else [min(f * a, 270.0) for f in self.factors])
            self.amplitudes[spec.seed] = [round(float(x), 3) for x in amps]
            return [RunSpec(group=self.decl.name, scenario="sine-with-dwell", controller=c,
                            seed=spec.seed,
                            duration_s=None if self.duration is None else float(self.duration),
                            params=(("amplitude_deg", f"{amp:.3f}"), ("direction", d)),
                            post=("fmvss",),
                            info=(("a_deg", a), ("amplitude_deg", amp), ("direction", d),
                                  ("study", "fmvss")), make_plots=False, make_rrd=False)
                    for c in self.decl.controllers for d in self.directions
                    for amp in self.amplitudes[spec.seed]]
        info = dict(spec.info)
        verdict = post.get("fmvss") or {"error": row.get("error") or "no result",
                                         "passed": False}
        self.results[(spec.controller, spec.seed)].append(
            {"direction": info["direction"], "amplitude_deg": info["amplitude_deg"],
             "status": row.get("status"), **verdict,
             "max_abs_beta_deg": row.get("max_abs_beta_deg"), "spun": row.get("spun"),
             "run_dir": row.get("run_dir")})
        return []

    def expected_remaining(self) -> int:
        """Amplitude runs still to be unlocked by SIS runs."""
        per_seed = (FMVSS_FULL_SCHEDULE_RUNS if self.factors is None else len(self.factors)
                    ) * len(self.decl.controllers) * len(self.directions)
        return per_seed * sum(1 for s in self.decl.seeds if s not in self.a_deg)

    def to_json(self) -> dict[str, Any]:
        """Per controller: each seed's runs and verdict, and over seeds the number of seeds
        passing every amplitude and the first failing amplitude (deg) median/min–max."""
        out: dict[str, Any] = {"kind": "fmvss126", "a_deg": {str(s): a for s, a in
                                                             self.a_deg.items()},
                               "amplitudes_deg": {str(s): v for s, v in
                                                  self.amplitudes.items()},
                               "controllers": {}}
        for c in self.decl.controllers:
            seeds = {}
            for s in self.decl.seeds:
                runs = sorted(self.results[(c, s)],
                              key=lambda r: (r["direction"], r["amplitude_deg"]))
                fails = [r for r in runs if not r.get("passed")]
                seeds[str(s)] = {"runs": runs, "n_runs": len(runs), "failed": len(fails),
                                 "passed_all": bool(runs) and not fails,
                                 "first_fail_amplitude_deg": min(
                                     (r["amplitude_deg"] for r in fails), default=None)}
            out["controllers"][c] = {
                "seeds_passing_all": sum(v["passed_all"] for v in seeds.values()),
                "n_seeds": len(seeds),
                "first_fail_amplitude_deg": _spread(
                    [v["first_fail_amplitude_deg"] for v in seeds.values()]),
                "seeds": seeds}
        return out


def make_study(decl: StudyDecl) -> VmaxStudy | FmvssStudy:
    """The study object of a declaration."""
    return VmaxStudy(decl) if decl.kind == "vmax" else FmvssStudy(decl)
