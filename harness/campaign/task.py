"""The worker side: one campaign run → one result row (a flat dict).

:func:`execute_run` runs in a Dask worker. It is exactly ``rhonn-harness run``: a new
loopback bus server, a controller process and a plant process of their own
(:func:`harness.run.runner.run_closed_loop`), then the run's post-processing steps. It never
raises: whatever goes wrong becomes the row's ``status``/``error``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from harness.campaign.spec import RunSpec

if TYPE_CHECKING:  # the runner is imported in the worker, when a run starts
    from harness.run.runner import RunConfig

# KPI columns of the results table (float64; flags as bool)
KPI_FLOATS = ("max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m", "phase_area",
              "max_abs_swa_deg", "steering_effort_deg", "max_abs_dM_Nm",
              "dM_total_variation_Nm", "yaw_rate_rmse_degps", "beta_rmse_deg", "step_us_p50",
              "step_us_p99", "deadline_misses", "frames_rejected", "fallback_events")
KPI_FLAGS = ("completed", "spun", "passed_dlc")
START_ATTEMPTS = 3  # a loopback port taken between probing and binding: start again


def _clean(v: Any) -> Any:
    """JSON-safe value (non-finite floats and numpy scalars handled)."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def _float(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _post(step: str, run_dir: Path, info: dict[str, Any]) -> dict[str, Any]:
    from harness.analysis.fmvss126_runs import fmvss_of_run, sis_of_run

    if step == "timing":
        from harness.paper.study import timing_stats

        return timing_stats(run_dir)
    if step == "diag":
        from harness.paper.study import run_diagnostics

        return run_diagnostics(run_dir)
    if step == "fidelity":
        from harness.analysis.fidelity import fidelity_of_run

        return fidelity_of_run(run_dir, plot_path=run_dir / "fidelity.png",
                               title=str(info.get("title", "")))
    if step == "fmvss":
        return fmvss_of_run(run_dir, info["amplitude_deg"], info["a_deg"])
    if step == "sis":
        return sis_of_run(run_dir)
    raise ValueError(f"unknown post step {step!r}")


def run_config(spec: RunSpec, run_dir: Path) -> RunConfig:
    """The :class:`harness.run.runner.RunConfig` of a campaign run (a fresh loopback bus)."""
    from harness.run.runner import RunConfig

    return RunConfig(scenario=spec.scenario, controller=spec.controller, out_dir=run_dir,
                     bus="auto", mode=spec.mode, controller_mode=spec.controller_mode,
                     controller_config=spec.controller_config, mu=spec.mu,
                     speed_kmh=spec.speed_kmh, seed=spec.seed, duration_s=spec.duration_s,
                     params=dict(spec.params), wall_timeout_s=spec.wall_timeout_s,
                     faults=list(spec.faults), make_plots=spec.plots, make_rrd=spec.rrd,
                     vehicle=dict(spec.vehicle))


def check_runs(runs: list[RunSpec], root: Path) -> None:
    """Every run of a campaign's matrix meets the checks of ``rhonn-harness run``
    (harness/run/validate.py) before the first starts; the first that does not is a
    CampaignError naming its group, scenario and controller."""
    from can_db.process.argcheck import UsageError
    from harness.campaign.spec import CampaignError
    from harness.run.validate import check_run_config

    seen: set[str] = set()
    for spec in runs:
        # the seed and the run's directory cannot make a run invalid: check the rest once
        ident = {k: v for k, v in spec.identity().items() if k != "seed"}
        key = json.dumps(ident, sort_keys=True, default=str)
        if key in seen:
            continue
        seen.add(key)
        try:
            check_run_config(run_config(spec, spec.run_dir(root)), bus=False)
        except UsageError as exc:
            raise CampaignError(f"matrix {spec.group!r} ({spec.scenario}, {spec.controller}): "
                                f"{exc}") from None


def base_row(spec: RunSpec, root: Path) -> dict[str, Any]:
    """The configuration columns of a row."""
    return {"key": spec.key(), "group": spec.group, "scenario": spec.scenario,
            "controller": spec.controller, "seed": spec.seed, "mu": spec.mu,
            "speed_kmh": spec.speed_kmh, "duration_s": spec.duration_s,
            "params": json.dumps(dict(spec.params), sort_keys=True),
            "faults": json.dumps(list(spec.faults)),
            "controller_config": spec.controller_config or "",
            "mode": spec.mode, "run_dir": str(spec.run_dir(root)),
            "config": json.dumps(spec.identity(), sort_keys=True)}


def execute_run(spec_json: dict[str, Any], root: str) -> dict[str, Any]:
    """Run one campaign run (in a worker) and return its row; never raises."""
    t0 = time.monotonic()
    spec = RunSpec.from_json(spec_json)
    row = base_row(spec, Path(root))
    row.update(host=socket.gethostname(), worker_pid=os.getpid(), status="error", reason="",
               error="", started_at=time.time())
    run_dir = spec.run_dir(Path(root))
    try:
        from harness.run.runner import run_closed_loop

        if run_dir.exists():  # a run cut short by a killed campaign: start it afresh
            shutil.rmtree(run_dir)
        result = None
        for _ in range(START_ATTEMPTS):
            result = run_closed_loop(run_config(spec, run_dir))
            if not result.reason.startswith("start failed"):
                break
        assert result is not None
        m = result.metrics
        row["reason"] = result.reason
        row["run_wall_s"] = _float(m.get("wall_time_s"))
        for k in KPI_FLOATS:
            row[k] = _float(m.get(k))
        for k in KPI_FLAGS:
            row[k] = None if m.get(k) is None else bool(m.get(k))
        err = m.get("analysis_error")
        post: dict[str, Any] = {}
        info = dict(spec.info)
        for step in spec.post:
            try:
                post[step] = _clean(_post(step, run_dir, info))
            except Exception as exc:  # keep the run; say which step failed
                post[step] = {"error": repr(exc)}
                err = err or f"post {step}: {exc!r}"
        row["post"] = json.dumps(post, sort_keys=True, default=str)
        row["error"] = err or ""
        row["status"] = "ok" if result.reason == "finished" and not err else "failed"
    except Exception as exc:  # bad fault spec, bus server error ...: a row, not a lost campaign
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["task_wall_s"] = time.monotonic() - t0
    return row


def error_row(spec: RunSpec, root: Path, error: str) -> dict[str, Any]:
    """The row of a run whose task never returned (its worker died, the engine failed)."""
    row = base_row(spec, root)
    row.update(status="error", error=error, reason="", host="", worker_pid=None,
               started_at=None, task_wall_s=None, post="{}")
    return row
