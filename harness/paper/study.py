"""`rhonn-harness paper`: the paper's experiments (Section IV) and FMVSS 126, in one command.

Every number comes from a real cross-process closed-loop run over the loopback bus (one
bus server, plant process and controller process per run), run on the campaign engine
(:mod:`harness.campaign.engine`: a dask LocalCluster of ``--jobs`` workers, default 2, or a
running dask scheduler). Experiments (see :func:`plan`):

* model fidelity (Tables 2–3, Figs 5–6): passive car on ``dlc-paper-high-mu`` (65 km/h) and
  on ``dlc-paper`` at :data:`FIDELITY_LOW_MU_SPEED_KMH` (the passive car spins at 65 km/h on
  μ = 0.35, the paper's low-μ fidelity run does not), plus the closed-loop nmpc-rhonn DLC at
  65 km/h; evaluated offline by :mod:`harness.analysis.fidelity`;
* closed-loop DLC, μ 0.35, 65 km/h, every controller (Figs 7–8);
* maximum DLC entry speed by bisection (Table 4, :mod:`harness.paper.vmax`);
* slippery curve, μ 0.35, 85 km/h, every controller (Figs 9–10);
* controller step time on the DLC and the curve (Table 5), measured in the controller process
  (these eight runs go last, one at a time, so no concurrent run preempts the controller);
* FMVSS 126 sine with dwell (μ 1, 80 km/h): A from a slowly-increasing-steer run of the
  passive car, amplitudes 1.5A … 6.5A (≤ 270°), left and right, every controller.

Output: ``DIR/runs/<experiment>/<run>/`` (every run's files), ``DIR/figures/*.png``,
``DIR/tables.json`` and ``DIR/report.md`` (:mod:`harness.paper.report`). One controller tuning
(the packaged config) for every scenario. Seeds are fixed (seed 0 for every run).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from harness.analysis.fmvss126_runs import fmvss_of_run, sis_of_run

CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
MPC_CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc")
FIDELITY_LOW_MU_SPEED_KMH = 50.0  # passive car completes dlc-paper (spins from ~55 km/h)
DLC_SPEED_KMH = 65.0
CURVE_SPEED_KMH = 85.0
FMVSS_DIRECTIONS = ("left", "right")
VMAX_BRACKET_KMH = (30.0, 90.0)
VMAX_RESOLUTION_KMH = 0.5
SEED = 0
KEEP_KEYS = (
    "completed", "spun", "max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m",
    "phase_area", "max_abs_swa_deg", "steering_effort_deg", "max_abs_dM_Nm",
    "dM_total_variation_Nm", "yaw_rate_rmse_degps", "beta_rmse_deg", "step_us_p50",
    "step_us_p99", "deadline_misses", "frames_rejected", "fallback_events", "passed_dlc",
    "reason", "wall_time_s", "analysis_error", "controller_exit_code", "plant_exit_code",
)


@dataclass(frozen=True)
class Job:
    """One closed-loop run and its offline post-processing.

    key: unique, also the run directory below DIR/runs. speed_kmh, mu, duration_s: scenario
    overrides (None = scenario value). post: names of post-processing steps run in the
    worker ("timing", "fidelity", "fmvss", "sis"). info: free data for the caller/post step.
    """

    key: str
    scenario: str
    controller: str
    speed_kmh: float | None = None
    mu: float | None = None
    duration_s: float | None = None
    params: tuple[tuple[str, str], ...] = ()
    plots: bool = False
    rrd: bool = False
    post: tuple[str, ...] = ()
    info: tuple[tuple[str, Any], ...] = ()


# ------------------------------------------------------------------------------ worker side
def timing_stats(run_dir: Path) -> dict[str, Any]:
    """Controller step time (µs, measured in the controller process) over all answered
    cycles, the MPC-update cycles (full step: learning, references, QP) and the others
    (re-allocation of the held ΔM)."""
    from harness.analysis.run_data import load_timing_csv

    t = load_timing_csv(run_dir / "controller_timing.csv")
    step = np.asarray(t.get("step_us", np.zeros(0)), dtype=float)
    upd = np.asarray(t.get("mpc_update", np.zeros(step.size)), dtype=float) > 0.5
    out: dict[str, Any] = {}
    for name, sel in (("all", np.ones(step.size, dtype=bool)), ("mpc_update", upd),
                      ("hold", ~upd)):
        s = step[sel & np.isfinite(step)] if step.size else step
        out[name] = {"n": int(s.size),
                     "mean_us": float(s.mean()) if s.size else None,
                     "p50_us": float(np.percentile(s, 50)) if s.size else None,
                     "p99_us": float(np.percentile(s, 99)) if s.size else None,
                     "max_us": float(s.max()) if s.size else None}
    return out


def run_diagnostics(run_dir: Path) -> dict[str, Any]:
    """Numbers for the discussion: reference roughness (total variation of the CTRL_REFS
    yaw-rate deg/s and β deg references), the share of cycles with |ΔM| ≥ 95 % of its
    bound (1800 N·m), where the largest deviation happened (s) and the peak references."""
    from harness.analysis.run_data import load_run

    run = load_run(run_dir)
    out: dict[str, Any] = {}
    for sig, key in (("YAW_RATE_REF", "yaw_ref"), ("BETA_REF", "beta_ref")):
        v = run.bus_sig("CTRL_REFS", sig).astype(float)
        v = v[np.isfinite(v)]
        out[f"{key}_total_variation"] = float(np.sum(np.abs(np.diff(v)))) if v.size else None
        out[f"{key}_max_abs"] = float(np.max(np.abs(v))) if v.size else None
    dm = run.bus_sig("CTRL_REFS", "DELTA_M").astype(float)
    out["dM_saturated_share"] = float(np.mean(np.abs(dm) >= 0.95 * 1800.0)) if dm.size else None
    t, dev = run.truth_col("t_s"), run.truth_col("lateral_dev_m")
    if dev.size and dev.size == t.size:
        i = int(np.nanargmax(np.abs(dev)))
        out["t_max_dev_s"] = float(t[i])
        out["speed_at_max_dev_kmh"] = float(run.truth_col("speed_mps")[i] * 3.6)
    return out


def execute_job(job: Job, root: str, attempts: int = 3) -> dict[str, Any]:
    """Run one job (in a pool worker): the bus run, then its post-processing steps.

    A run whose processes did not start (e.g. a loopback port taken between probing and
    binding) is retried up to ``attempts`` times.
    """
    from harness.run.runner import RunConfig, run_closed_loop

    run_dir = Path(root) / "runs" / job.key
    info = dict(job.info)
    result = None
    err = ""
    for _ in range(attempts):
        cfg = RunConfig(scenario=job.scenario, controller=job.controller, out_dir=run_dir,
                        bus="auto", mode="lockstep", mu=job.mu, speed_kmh=job.speed_kmh,
                        seed=SEED, duration_s=job.duration_s, params=dict(job.params),
                        make_plots=job.plots, make_rrd=job.rrd)
        try:
            result = run_closed_loop(cfg)
        except Exception as exc:  # BusServerError etc.: retry, then report
            result = None
            err = repr(exc)
            continue
        if not result.reason.startswith("start failed"):
            break
        err = result.reason
    out: dict[str, Any] = {"key": job.key, "run_dir": str(run_dir), "info": info}
    if result is None:
        out.update(error=err, metrics={})
        return out
    out["metrics"] = {k: result.metrics.get(k) for k in KEEP_KEYS}
    out["metrics"]["plots"] = result.metrics.get("plots", [])
    post: dict[str, Any] = {}
    try:
        for step in job.post:
            if step == "timing":
                post["timing"] = timing_stats(run_dir)
            elif step == "diag":
                post["diag"] = run_diagnostics(run_dir)
            elif step == "fidelity":
                post["fidelity"] = _fidelity(run_dir, info)
            elif step == "fmvss":
                post["fmvss"] = fmvss_of_run(run_dir, info["amplitude_deg"], info["a_deg"])
            elif step == "sis":
                post["sis"] = sis_of_run(run_dir)
    except Exception as exc:  # keep the run; say what failed
        post["error"] = repr(exc)
    out["post"] = post
    return out


def _fidelity(run_dir: Path, info: dict[str, Any]) -> dict[str, Any]:
    from harness.analysis.fidelity import fidelity_of_run

    return fidelity_of_run(run_dir, plot_path=run_dir / "fidelity.png",
                           title=str(info.get("title", "")))


# ------------------------------------------------------------------------------ scheduler
class Progress:
    """Paper progress on stderr: a tqdm bar on a terminal, else one line per finished run
    (harness/tools/progress.py)."""

    def __init__(self, stream: Any = None) -> None:
        from harness.tools.progress import Bar

        self.bar = Bar("paper", unit="run", stream=stream)

    def update(self, done: int, total: int, pending: int, last: str) -> None:
        """Show done/total runs (total includes the expected further bisection/FMVSS runs),
        the submitted runs not yet finished and the last finished run."""
        self.bar.set(done, total, f"{pending} pending, last {last}")

    def close(self) -> None:
        """End the bar."""
        self.bar.close()


@dataclass
class Scheduler:
    """Runs jobs on the campaign engine; a job's callback may submit further jobs."""

    root: Path
    jobs: int = 2
    expected_extra: Callable[[], int] = lambda: 0
    progress: Progress = field(default_factory=Progress)
    results: dict[str, dict[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from harness.campaign.engine import DaskPoolExecutor

        self._pool = DaskPoolExecutor(max_workers=max(1, self.jobs))
        self._futures: dict[Future[dict[str, Any]], tuple[Job, Callable[..., None]]] = {}
        self._done = 0

    def submit(self, job: Job, callback: Callable[[Job, dict[str, Any]], None]) -> None:
        """Queue ``job``; ``callback(job, result)`` runs in this process when it is done."""
        if job.key in self.results or any(j.key == job.key for j, _ in self._futures.values()):
            raise ValueError(f"duplicate job key {job.key}")
        fut = self._pool.submit(execute_job, job, str(self.root))
        self._futures[fut] = (job, callback)

    def run(self) -> None:
        """Until every job (including those submitted by callbacks) has finished."""
        try:
            while self._futures:
                done, _ = wait(list(self._futures), return_when=FIRST_COMPLETED)
                for fut in done:
                    job, cb = self._futures.pop(fut)
                    try:
                        res = fut.result()
                    except Exception as exc:  # a crashed worker: record, carry on
                        res = {"key": job.key, "error": repr(exc), "metrics": {}, "post": {}}
                    self.results[job.key] = res
                    self._done += 1
                    cb(job, res)
                    self.progress.update(self._done,
                                         self._done + len(self._futures) + self.expected_extra(),
                                         len(self._futures), job.key)
        except BaseException:
            self._pool.shutdown(wait=True, cancel_futures=True)
            raise
        finally:
            self.progress.close()
        self._pool.shutdown(wait=True)


# ------------------------------------------------------------------------------ the plan
@dataclass
class Plan:
    """What to run (speeds km/h, durations s); :func:`plan` gives the full or quick set."""

    quick: bool
    fidelity: list[tuple[str, str, float, float | None]]  # (name, scenario, speed, duration)
    dlc_controllers: tuple[str, ...]
    curve_controllers: tuple[str, ...]
    curve_duration_s: float | None
    vmax_controllers: tuple[str, ...]
    vmax_bracket: tuple[float, float]
    vmax_resolution: float
    vmax_verify: tuple[float, ...]
    sis_duration_s: float | None
    fmvss_controllers: tuple[str, ...]
    fmvss_directions: tuple[str, ...]
    fmvss_amplitude_factors: tuple[float, ...] | None  # None = the full schedule


def plan(quick: bool) -> Plan:
    """The full experiment set, or the reduced ``--quick`` smoke set."""
    if quick:
        return Plan(
            quick=True,
            fidelity=[("high_mu", "dlc-paper-high-mu", DLC_SPEED_KMH, 6.0),
                      ("low_mu", "dlc-paper", FIDELITY_LOW_MU_SPEED_KMH, 6.0)],
            dlc_controllers=("nmpc-rhonn", "passive"),
            curve_controllers=("nmpc-rhonn",), curve_duration_s=8.0,
            vmax_controllers=("nmpc-rhonn", "passive"), vmax_bracket=(40.0, 80.0),
            vmax_resolution=20.0, vmax_verify=(),
            sis_duration_s=5.0, fmvss_controllers=("nmpc-rhonn",),
            fmvss_directions=("left",), fmvss_amplitude_factors=(1.5,))
    return Plan(
        quick=False,
        fidelity=[("high_mu", "dlc-paper-high-mu", DLC_SPEED_KMH, None),
                  ("low_mu", "dlc-paper", FIDELITY_LOW_MU_SPEED_KMH, None)],
        dlc_controllers=CONTROLLERS, curve_controllers=CONTROLLERS, curve_duration_s=None,
        vmax_controllers=CONTROLLERS, vmax_bracket=VMAX_BRACKET_KMH,
        vmax_resolution=VMAX_RESOLUTION_KMH, vmax_verify=(2.0, 5.0),
        sis_duration_s=None, fmvss_controllers=CONTROLLERS,
        fmvss_directions=FMVSS_DIRECTIONS, fmvss_amplitude_factors=None)


def _dlc_duration_s(speed_kmh: float) -> float:
    """Long enough to coast the whole DLC path (≈ 191 m) from ``speed_kmh`` (coasting loses
    ~25 % of 30 km/h over the path, hence the factor 1.5) plus 3 s, ≥ 18 s (the plant stops
    at the end of the path anyway); the pass rule needs the course end + 2 s."""
    from plant_sim.scenario import load_scenario

    p = load_scenario("dlc-paper").reference_path_xy
    length = float(np.sum(np.hypot(*np.diff(p, axis=0).T)))
    return max(18.0, 1.5 * length / (speed_kmh / 3.6) + 3.0)


def _git_rev() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, cwd=Path(__file__).resolve().parent.parent,
                              timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def run_paper(out: Path, jobs: int = 2, quick: bool = False) -> dict[str, Any]:
    """Run every experiment, write figures, tables.json and report.md; return the tables."""
    from harness.analysis.fmvss126 import amplitude_schedule_deg
    from harness.paper.vmax import Bisection

    t0 = time.monotonic()
    out = Path(out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    p = plan(quick)
    bis = {c: Bisection(c, *p.vmax_bracket, p.vmax_resolution, p.vmax_verify)
           for c in p.vmax_controllers}
    fmvss_state: dict[str, Any] = {"a_deg": None, "amplitudes": [], "pending": True}

    def expected() -> int:
        n = sum(b.expected_remaining() for b in bis.values())
        if fmvss_state["pending"]:
            n += (11 if p.fmvss_amplitude_factors is None else len(p.fmvss_amplitude_factors)
                  ) * len(p.fmvss_controllers) * len(p.fmvss_directions)
        return n

    sched = Scheduler(out, jobs, expected)

    def noop(job: Job, res: dict[str, Any]) -> None:
        pass

    def submit_vmax(c: str) -> None:
        for v in bis[c].pending():
            # duration_s as a scenario parameter: --duration can only cut a run short
            sched.submit(Job(f"vmax/{c}/v{v:05.1f}", "dlc-paper", c, speed_kmh=v,
                             params=(("duration_s", f"{_dlc_duration_s(v):.1f}"),),
                             info=(("v", v),)), on_vmax)

    def on_vmax(job: Job, res: dict[str, Any]) -> None:
        bis[job.controller].record(dict(job.info)["v"], res.get("metrics", {}))
        submit_vmax(job.controller)

    def on_sis(job: Job, res: dict[str, Any]) -> None:
        a = res.get("post", {}).get("sis", {}).get("a_deg")
        fmvss_state["pending"] = False
        if a is None:
            return
        sched_amps = amplitude_schedule_deg(a)
        if p.fmvss_amplitude_factors is not None:
            sched_amps = [min(f * a, 270.0) for f in p.fmvss_amplitude_factors]
        fmvss_state["a_deg"], fmvss_state["amplitudes"] = a, sched_amps
        for c in p.fmvss_controllers:
            for d in p.fmvss_directions:
                for amp in sched_amps:
                    sched.submit(Job(f"fmvss/{c}/{d}/a{amp:05.1f}", "sine-with-dwell", c,
                                     params=(("amplitude_deg", f"{amp:.3f}"),
                                             ("direction", d)),
                                     post=("fmvss",),
                                     info=(("amplitude_deg", amp), ("a_deg", a),
                                           ("direction", d))), noop)

    # Longest chains first: the SIS unlocks the FMVSS runs, the bisections are sequential.
    sched.submit(Job("fmvss/sis-passive", "slowly-increasing-steer", "passive",
                     duration_s=p.sis_duration_s, post=("sis",)), on_sis)
    for c in p.vmax_controllers:
        submit_vmax(c)
    for name, scen, v, dur in p.fidelity:
        mu = "0.7" if "high" in scen else "0.35"
        sched.submit(Job(f"fidelity/{name}", scen, "passive", speed_kmh=v, duration_s=dur,
                         plots=True, post=("fidelity",),
                         info=(("title", f"Fidelity: passive car on {scen} (μ {mu}, "
                                         f"{v:.0f} km/h)"),)), noop)
    sched.run()

    # Table 5 runs alone, one at a time: the step time is wall-clock time inside the
    # controller process and would include preemption by concurrent runs on a busy machine.
    solo = Scheduler(out, 1)
    for c in p.dlc_controllers:
        # the passive car's DLC (it spins) doubles as the strongly nonlinear fidelity set
        post = ("timing", "diag", "fidelity") if c in ("nmpc-rhonn", "passive") else (
            "timing", "diag")
        solo.submit(Job(f"dlc/{c}", "dlc-paper", c, speed_kmh=DLC_SPEED_KMH, plots=True,
                         rrd=not quick, post=post,
                         info=(("title", f"Fidelity: {c} on dlc-paper μ 0.35 "
                                         f"{DLC_SPEED_KMH:.0f} km/h"),)), noop)
    for c in p.curve_controllers:
        solo.submit(Job(f"curve/{c}", "slippery-curve", c, speed_kmh=CURVE_SPEED_KMH,
                         duration_s=p.curve_duration_s, plots=True, rrd=not quick,
                         post=("timing", "diag")), noop)
    solo.run()
    res = {**sched.results, **solo.results}
    tables = collect_tables(out, p, res, bis, fmvss_state)
    tables["meta"] = {
        "quick": quick, "jobs": jobs, "seed": SEED, "git_rev": _git_rev(),
        "wall_time_s": time.monotonic() - t0, "runs": len(res),
        "failed_runs": sorted(k for k, r in res.items()
                              if r.get("error") or r.get("metrics", {}).get("reason")
                              != "finished"),
        "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
    }
    write_figures(out, p, tables)
    from harness.paper.report import write_report

    (out / "tables.json").write_text(json.dumps(tables, indent=2, default=_json_default) + "\n")
    write_report(out, tables)
    return tables


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def collect_tables(out: Path, p: Plan, res: dict[str, dict[str, Any]],
                   bis: dict[str, Any], fmvss_state: dict[str, Any]) -> dict[str, Any]:
    """The machine-readable results (tables.json) from the finished jobs."""
    t: dict[str, Any] = {"fidelity": {}, "dlc": {}, "curve": {}, "timing": {}, "vmax": {},
                         "fmvss": {}}
    for name, scen, v, dur in p.fidelity:
        r = res.get(f"fidelity/{name}", {})
        f = dict(r.get("post", {}).get("fidelity", {}))
        f.update(scenario=scen, driver="passive", speed_kmh=v, duration_s_limit=dur,
                 run=f"runs/fidelity/{name}", run_metrics=r.get("metrics", {}))
        t["fidelity"][name] = f
    for name, c, driver in (("low_mu_closed_loop", "nmpc-rhonn", "nmpc-rhonn (closed loop)"),
                            ("low_mu_spin", "passive", "passive (spins)")):
        r = res.get(f"dlc/{c}", {})
        if "fidelity" in r.get("post", {}):
            f = dict(r["post"]["fidelity"])
            f.update(scenario="dlc-paper", driver=driver, speed_kmh=DLC_SPEED_KMH,
                     run=f"runs/dlc/{c}", run_metrics=r.get("metrics", {}))
            t["fidelity"][name] = f
    for exp, ctrls in (("dlc", p.dlc_controllers), ("curve", p.curve_controllers)):
        t[exp] = {c: {**res.get(f"{exp}/{c}", {}).get("metrics", {}),
                      "run": f"runs/{exp}/{c}"} for c in ctrls}
        t["timing"][exp] = {c: res.get(f"{exp}/{c}", {}).get("post", {}).get("timing", {})
                            for c in ctrls}
        for c in ctrls:
            t[exp][c]["diag"] = res.get(f"{exp}/{c}", {}).get("post", {}).get("diag", {})
    t["vmax"] = {c: b.to_json() for c, b in bis.items()}
    runs = []
    for key, r in sorted(res.items()):
        if not key.startswith("fmvss/") or key == "fmvss/sis-passive":
            continue
        _, c, d, _ = key.split("/")
        ev = r.get("post", {}).get("fmvss", {"error": r.get("error", "no result")})
        m = r.get("metrics", {})
        runs.append({"controller": c, "direction": d,
                     "amplitude_deg": r.get("info", {}).get("amplitude_deg"),
                     **ev, "max_abs_beta_deg": m.get("max_abs_beta_deg"),
                     "max_abs_dM_Nm": m.get("max_abs_dM_Nm"), "spun": m.get("spun"),
                     "run": f"runs/{key}"})
    summary = {}
    for c in p.fmvss_controllers:
        mine = [x for x in runs if x["controller"] == c]
        fails = [x for x in mine if not x.get("passed")]
        summary[c] = {"runs": len(mine), "failed": len(fails),
                      "passed_all": bool(mine) and not fails,
                      "first_fail_amplitude_deg": min((x["amplitude_deg"] for x in fails),
                                                      default=None),
                      "fail_criteria": sorted({k for x in fails for k in
                                               ("pass_yrr_1s", "pass_yrr_175s",
                                                "pass_lateral")
                                               if x.get(k) is False
                                               and (k != "pass_lateral"
                                                    or x.get("lateral_required"))})}
    sis = res.get("fmvss/sis-passive", {})
    t["fmvss"] = {"a_deg": fmvss_state["a_deg"], "amplitudes_deg": fmvss_state["amplitudes"],
                  "sis": {**sis.get("post", {}).get("sis", {}),
                          "run": "runs/fmvss/sis-passive"},
                  "runs": runs, "summary": summary}
    return t


def write_figures(out: Path, p: Plan, tables: dict[str, Any]) -> None:
    """Overlay/tracking figures of the DLC and the curve, the v_max probes, the FMVSS
    ratios, and copies of the fidelity figures, into DIR/figures."""
    import shutil

    from harness.analysis.course import course_geometry, scenario_for
    from harness.analysis.run_data import load_run
    from harness.paper.figures import fmvss_figure, tracking_figure, vmax_figure
    from harness.viz.plots import write_overlay_plots

    fig = out / "figures"
    made: dict[str, list[str]] = {}
    for exp, scen, v, ctrls in (("dlc", "dlc-paper", DLC_SPEED_KMH, p.dlc_controllers),
                                ("curve", "slippery-curve", CURVE_SPEED_KMH,
                                 p.curve_controllers)):
        runs = {c: load_run(out / "runs" / exp / c) for c in ctrls
                if (out / "runs" / exp / c / "truth.csv").is_file()}
        if not runs:
            continue
        geo = course_geometry(scenario_for(scen, None, v, {}))
        tmp = out / "runs" / exp / "_overlay"
        paths = write_overlay_plots(runs, geo.boundaries, geo.ref_path, tmp, cones=geo.cones,
                                    lanes=geo.lanes,
                                    course_end_arc_m=geo.course_end_arc_m or None)
        names = []
        for path in paths:
            dst = fig / f"{exp}_{path.name.removeprefix('overlay_')}"
            shutil.move(str(path), dst)
            names.append(dst.name)
        tmp.rmdir()
        title = ("Fig. 8: DLC μ 0.35 65 km/h — tracking of the references" if exp == "dlc"
                 else "Fig. 10: slippery curve μ 0.35 85 km/h — tracking of the references")
        names.append(tracking_figure({c: r for c, r in runs.items() if c != "passive"}
                                     or runs, fig / f"{exp}_tracking.png", title).name)
        made[exp] = names
    for name, f in tables["fidelity"].items():
        src = out / f.get("run", "") / "fidelity.png"
        if src.is_file():
            shutil.copy(src, fig / f"fidelity_{name}.png")
            made.setdefault("fidelity", []).append(f"fidelity_{name}.png")
    if tables["vmax"]:
        made["vmax"] = [vmax_figure(tables["vmax"], fig / "vmax_probes.png").name]
    if tables["fmvss"]["runs"]:
        made["fmvss"] = [fmvss_figure(tables["fmvss"]["runs"], fig / "fmvss_ratios.png").name]
    tables["figures"] = made
