"""`rhonn-harness paper`: the paper's experiments (Section IV) and FMVSS 126, in one command.

The runs are a campaign file, ``harness/campaign/campaigns/paper.toml`` (``--quick``:
``paper-quick.toml``), carried out by the campaign engine (:class:`CampaignRunner`: a dask
LocalCluster of ``--jobs`` workers or a running dask scheduler, one warm bench per worker — one
bus hub, plant and controller kept across the worker's runs, the controller reset over UDS
between them) into ``DIR/campaign/``. Every number comes from a real cross-process closed-loop
run over the bus. Experiments (matrix and study names of the campaign file):

* model fidelity (Tables 2–3, Figs 5–6; ``fidelity-high-mu``, ``fidelity-low-mu``): passive
  car on ``dlc-paper-high-mu`` (65 km/h) and on ``dlc-paper`` at 50 km/h (the passive car
  spins at 65 km/h on μ = 0.35, the paper's low-μ fidelity run does not), plus the closed-loop
  nmpc-rhonn DLC and the spinning passive car at 65 km/h; evaluated by the campaign's post step
  ``fidelity`` (:mod:`harness.analysis.fidelity`);
* closed-loop DLC, μ 0.35, 65 km/h, every controller (Figs 7–8; ``dlc``, ``dlc-*``);
* maximum DLC entry speed by bisection (Table 4; study ``vmax``, :mod:`harness.analysis.vmax`);
* slippery curve, μ 0.35, 85 km/h, every controller (Figs 9–10; ``curve``);
* controller step time on the DLC and the curve (Table 5), measured in the controller process
  (these matrices are ``exclusive``: they run last, one at a time, so no concurrent run
  preempts the controller);
* FMVSS 126 sine with dwell (μ 1, 80 km/h; study ``fmvss``): A from a slowly-increasing-steer
  run of the passive car, amplitudes 1.5A … 6.5A (≤ 270°), left and right, every controller.

This module is the table writer: from the campaign's rows and study summaries it builds
``DIR/tables.json``, ``DIR/figures/*.png`` and ``DIR/report.md`` (:mod:`harness.paper.report`).
One controller tuning (the packaged config) for every scenario; seed 0 for every run.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import harness.campaign
from harness.analysis.course import course_geometry, scenario_for
from harness.analysis.run_data import load_run
from harness.analysis.smoothness import SMOOTHNESS_KEYS
from harness.campaign.engine import EngineConfig
from harness.campaign.runner import CampaignResult, CampaignRunner
from harness.campaign.spec import Campaign, RunSpec, load_campaign
from harness.campaign.task import check_runs
from harness.paper.figures import fmvss_figure, tracking_figure, vmax_figure
from harness.paper.report import write_report
from harness.viz.plots import write_overlay_plots

CAMPAIGNS = Path(harness.campaign.__file__).resolve().parent / "campaigns"
SEED = 0
# matrix names of the campaign files → tables.json entries
FIDELITY_GROUPS = {"high_mu": "fidelity-high-mu", "low_mu": "fidelity-low-mu"}
CLOSED_LOOP_FIDELITY = (("low_mu_closed_loop", "nmpc-rhonn", "nmpc-rhonn (closed loop)"),
                        ("low_mu_spin", "passive", "passive (spins)"))
EXPERIMENTS = ("dlc", "curve")  # a matrix named EXP or EXP-*, one run per controller
FIGURE_TITLES = {"dlc": "Fig. 8: DLC μ 0.35 65 km/h — tracking of the references",
                 "curve": "Fig. 10: slippery curve μ 0.35 85 km/h — tracking of the references"}
VMAX_STUDY, FMVSS_STUDY = "vmax", "fmvss"
KEEP_KEYS = (
    "completed", "spun", "max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m",
    "phase_area", "max_abs_swa_deg", "steering_effort_deg", "max_abs_dM_Nm",
    "dM_total_variation_Nm", *SMOOTHNESS_KEYS, "yaw_rate_rmse_degps", "beta_rmse_deg",
    "step_us_p50",
    "step_us_p99", "deadline_misses", "frames_rejected", "fallback_events", "passed_dlc",
    "reason", "wall_time_s", "analysis_error", "controller_exit_code", "plant_exit_code",
)


def campaign_file(quick: bool) -> Path:
    """The campaign file of the full study or of the ``--quick`` smoke set."""
    return CAMPAIGNS / ("paper-quick.toml" if quick else "paper.toml")


def _git_rev() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, cwd=Path(__file__).resolve().parent.parent,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def run_paper(out: Path, jobs: int = 2, quick: bool = False, engine: EngineConfig | None = None,
              resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run the campaign into ``out/campaign`` (``resume``: only the runs it does not hold yet,
    as ``rhonn-harness campaign --resume``), then write figures, tables.json and report.md;
    return the tables. ``engine``: where the runs go (default a LocalCluster of ``jobs``
    workers)."""
    t0 = time.monotonic()
    out = Path(out)
    campaign = load_campaign(campaign_file(quick))
    root = out / "campaign"
    check_runs(campaign.runs, root)  # every run as `rhonn-harness run` checks it, first
    result = CampaignRunner(campaign, root, engine or EngineConfig("local", max(1, jobs)),
                            resume=resume, progress=progress).run()
    meta = {"quick": quick, "jobs": jobs, "seed": SEED, "git_rev": _git_rev(),
            "wall_time_s": time.monotonic() - t0, "runs": len(result.rows),
            "executed": result.executed, "resumed": result.cached,
            "campaign": os.path.relpath(root.resolve(), out.resolve()),
            "campaign_file": campaign_file(quick).name,
            "cpu_count": os.cpu_count(), "python": sys.version.split()[0]}
    return write_paper(out, campaign, result, meta)


def write_paper(out: Path, campaign: Campaign, result: CampaignResult,
                meta: dict[str, Any]) -> dict[str, Any]:
    """tables.json, figures and report.md from a finished campaign; returns the tables."""
    out = Path(out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    tables = collect_tables(out, campaign, result.rows, result.studies)
    tables["meta"] = {**meta, "failed_runs": sorted(
        _label(r) for r in result.rows.values() if r.get("reason") != "finished")}
    write_figures(out, campaign, tables)
    (out / "tables.json").write_text(json.dumps(tables, indent=2, default=_json_default) + "\n")
    write_report(out, tables)
    return tables


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ------------------------------------------------------------------------------ rows
def _info(row: dict[str, Any]) -> dict[str, Any]:
    """The run's ``info`` (free data of the campaign file or study) from the row's config."""
    return dict(json.loads(row.get("config") or "{}").get("info", []))


def _post(row: dict[str, Any]) -> dict[str, Any]:
    post = json.loads(row.get("post") or "{}")
    return post if isinstance(post, dict) else {}


def _label(row: dict[str, Any]) -> str:
    """A readable name of a run: group/controller[/v<km/h>][/direction/a<deg>]."""
    info = _info(row)
    label = f"{row.get('group')}/{row.get('controller')}"
    if row.get("scenario") == "slowly-increasing-steer":
        label += "/sis"
    if "v" in info:
        label += f"/v{float(info['v']):05.1f}"
    if "amplitude_deg" in info:
        label += f"/{info.get('direction')}/a{float(info['amplitude_deg']):05.1f}"
    return label


def _rel(out: Path, row: dict[str, Any]) -> str:
    """The row's run directory relative to the study's output directory."""
    run_dir = row.get("run_dir")
    return os.path.relpath(run_dir, out.resolve()) if run_dir else ""


def _metrics(row: dict[str, Any]) -> dict[str, Any]:
    """The KPIs and process outcome of a run (its metrics.json; the row if that is missing)."""
    try:
        m = json.loads((Path(row["run_dir"]) / "metrics.json").read_text())
    except (KeyError, OSError, ValueError):
        m = {k: row.get(k) for k in KEEP_KEYS}
    keep = {k: m.get(k) for k in KEEP_KEYS}
    keep["plots"] = m.get("plots", [])
    return keep


def _matrix_rows(campaign: Campaign, rows: dict[str, dict[str, Any]],
                 match: Any) -> list[tuple[RunSpec, dict[str, Any]]]:
    """(spec, row) of the matrix runs whose group ``match(group)`` accepts, in file order
    (a run without a row gets an empty row)."""
    return [(s, rows.get(s.key(), {})) for s in campaign.runs if match(s.group)]


def _experiment(exp: str) -> Any:
    return lambda group: group == exp or group.startswith(f"{exp}-")


# ------------------------------------------------------------------------------ tables
def collect_tables(out: Path, campaign: Campaign, rows: dict[str, dict[str, Any]],
                   studies: dict[str, Any]) -> dict[str, Any]:
    """The machine-readable results (tables.json) from the campaign's rows (by run key) and
    its study summaries (:meth:`CampaignResult.studies`)."""
    out = Path(out)
    t: dict[str, Any] = {"fidelity": {}, "dlc": {}, "curve": {}, "timing": {}, "vmax": {},
                         "fmvss": {}}
    for name, group in FIDELITY_GROUPS.items():
        for spec, r in _matrix_rows(campaign, rows, lambda g, group=group: g == group)[:1]:
            f = dict(_post(r).get("fidelity", {}))
            f.update(scenario=spec.scenario, driver=spec.controller, speed_kmh=spec.speed_kmh,
                     duration_s_limit=spec.duration_s, run=_rel(out, r),
                     run_metrics=_metrics(r))
            t["fidelity"][name] = f
    dlc = {s.controller: (s, r) for s, r in _matrix_rows(campaign, rows, _experiment("dlc"))}
    for name, c, driver in CLOSED_LOOP_FIDELITY:
        spec, r = dlc.get(c, (None, {}))
        if spec is not None and "fidelity" in _post(r):
            f = dict(_post(r)["fidelity"])
            f.update(scenario=spec.scenario, driver=driver, speed_kmh=spec.speed_kmh,
                     run=_rel(out, r), run_metrics=_metrics(r))
            t["fidelity"][name] = f
    for exp in EXPERIMENTS:
        runs = {s.controller: r for s, r in _matrix_rows(campaign, rows, _experiment(exp))}
        t[exp] = {c: {**_metrics(r), "run": _rel(out, r)} for c, r in runs.items()}
        t["timing"][exp] = {c: _post(r).get("timing", {}) for c, r in runs.items()}
        for c, r in runs.items():
            t[exp][c]["diag"] = _post(r).get("diag", {})
    vm = studies.get(VMAX_STUDY, {}).get("controllers", {})
    t["vmax"] = {c: s["seeds"][str(SEED)] for c, s in vm.items() if str(SEED) in s["seeds"]}
    t["fmvss"] = _fmvss_tables(out, campaign, rows, studies.get(FMVSS_STUDY, {}))
    return t


def _fmvss_tables(out: Path, campaign: Campaign, rows: dict[str, dict[str, Any]],
                  study: dict[str, Any]) -> dict[str, Any]:
    """A (deg), the amplitudes, the SIS run, every sine-with-dwell run's verdict and a
    summary per controller."""
    mine = [r for r in rows.values() if r.get("group") == FMVSS_STUDY
            and r.get("seed") == SEED]
    runs = []
    for r in mine:
        if r.get("scenario") != "sine-with-dwell":
            continue
        info = _info(r)
        ev = _post(r).get("fmvss") or {"error": r.get("error") or "no result"}
        runs.append({"controller": r.get("controller"), "direction": info.get("direction"),
                     "amplitude_deg": info.get("amplitude_deg"), **ev,
                     "max_abs_beta_deg": r.get("max_abs_beta_deg"),
                     "max_abs_dM_Nm": r.get("max_abs_dM_Nm"), "spun": r.get("spun"),
                     "run": _rel(out, r)})
    runs.sort(key=lambda x: (x["controller"], x["direction"], x["amplitude_deg"]))
    decl = next((d for d in campaign.studies if d.name == FMVSS_STUDY), None)
    summary = {}
    for c in decl.controllers if decl else ():
        mc = [x for x in runs if x["controller"] == c]
        fails = [x for x in mc if not x.get("passed")]
        summary[c] = {"runs": len(mc), "failed": len(fails),
                      "passed_all": bool(mc) and not fails,
                      "first_fail_amplitude_deg": min((x["amplitude_deg"] for x in fails),
                                                      default=None),
                      "fail_criteria": sorted({k for x in fails for k in
                                               ("pass_yrr_1s", "pass_yrr_175s",
                                                "pass_lateral")
                                               if x.get(k) is False
                                               and (k != "pass_lateral"
                                                    or x.get("lateral_required"))})}
    sis = next((r for r in mine if r.get("scenario") == "slowly-increasing-steer"), {})
    return {"a_deg": study.get("a_deg", {}).get(str(SEED)),
            "amplitudes_deg": study.get("amplitudes_deg", {}).get(str(SEED), []),
            "sis": {**_post(sis).get("sis", {}), "run": _rel(out, sis)},
            "runs": runs, "summary": summary}


# ------------------------------------------------------------------------------ figures
def write_figures(out: Path, campaign: Campaign, tables: dict[str, Any]) -> None:
    """Overlay/tracking figures of the DLC and the curve, the v_max probes, the FMVSS
    ratios, and copies of the fidelity figures, into DIR/figures."""
    fig = out / "figures"
    made: dict[str, list[str]] = {}
    for exp in EXPERIMENTS:
        specs = {s.controller: s for s in campaign.runs if _experiment(exp)(s.group)}
        runs = {c: load_run(out / m["run"]) for c, m in tables[exp].items()
                if m.get("run") and (out / m["run"] / "truth.csv").is_file()}
        if not runs:
            continue
        spec = specs[next(iter(runs))]
        geo = course_geometry(scenario_for(spec.scenario, spec.mu, spec.speed_kmh,
                                           dict(spec.params)))
        tmp = fig / f".{exp}_overlay"
        paths = write_overlay_plots(runs, geo.boundaries, geo.ref_path, tmp, cones=geo.cones,
                                    lanes=geo.lanes,
                                    course_end_arc_m=geo.course_end_arc_m or None)
        names = []
        for path in paths:
            dst = fig / f"{exp}_{path.name.removeprefix('overlay_')}"
            shutil.move(str(path), dst)
            names.append(dst.name)
        shutil.rmtree(tmp, ignore_errors=True)
        names.append(tracking_figure({c: r for c, r in runs.items() if c != "passive"}
                                     or runs, fig / f"{exp}_tracking.png",
                                     FIGURE_TITLES[exp]).name)
        made[exp] = names
    for name, f in tables["fidelity"].items():
        src = out / f.get("run", "") / "fidelity.png"
        if f.get("run") and src.is_file():
            shutil.copy(src, fig / f"fidelity_{name}.png")
            made.setdefault("fidelity", []).append(f"fidelity_{name}.png")
    if tables["vmax"]:
        made["vmax"] = [vmax_figure(tables["vmax"], fig / "vmax_probes.png").name]
    if tables["fmvss"]["runs"]:
        made["fmvss"] = [fmvss_figure(tables["fmvss"]["runs"], fig / "fmvss_ratios.png").name]
    tables["figures"] = made
