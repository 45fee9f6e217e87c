"""The worker side: one campaign run → one result row (a flat dict).

:func:`execute_run` runs in a Dask worker. It is ``rhonn-harness run`` on the worker's warm
bench (harness/run/hil_bench.py: one bus, plant and controller kept across the worker's runs, the
controller reset over UDS between them), then the run's post-processing steps. It never
raises: whatever goes wrong becomes the row's ``status``/``error``.
"""

from __future__ import annotations

import atexit
import json
import math
import os
import shutil
import socket
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import UsageError
from can_db.process.errors import error_text
from harness.analysis.diagnostics import run_diagnostics, timing_stats
from harness.analysis.fmvss126_runs import fmvss_of_run, sis_of_run
from harness.analysis.smoothness import SMOOTHNESS_KEYS
from harness.analysis.stability import stability_of_run
from harness.campaign.spec import CampaignError, RunSpec
from harness.report.run_report import run_and_report
from harness.run.hil_bench import Bench
from harness.run.validate import check_run_config
from harness.viz.fidelity_plot import fidelity_of_run

# KPI columns of the results table (float64; flags as bool)
KPI_FLOATS = ("max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m", "phase_area",
              "max_abs_swa_deg", "steering_effort_deg", "max_abs_dM_Nm",
              "dM_total_variation_Nm", *SMOOTHNESS_KEYS, "yaw_rate_rmse_degps",
              "beta_rmse_deg", "step_us_p50", "step_us_p99", "deadline_misses",
              "frames_rejected", "fallback_events")
KPI_FLAGS = ("completed", "spun", "passed_dlc")


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


def _post(step: str, run_dir: Path, info: dict[str, Any],
          vehicle: dict[str, float] | None = None) -> dict[str, Any]:
    if step == "timing":
        return timing_stats(run_dir)
    if step == "diag":
        return run_diagnostics(run_dir)
    if step == "fidelity":
        return fidelity_of_run(run_dir, plot_path=run_dir / "fidelity.png",
                               title=str(info.get("title", "")))
    if step == "fmvss":
        return fmvss_of_run(run_dir, info["amplitude_deg"], info["a_deg"])
    if step == "sis":
        return sis_of_run(run_dir)
    if step == "stability":  # the stability benchmark's verdicts (harness/paper/benchmark.py)
        return stability_of_run(run_dir, info, vehicle)
    raise ValueError(f"unknown post step {step!r}")


def worker_bench() -> Bench:
    """This worker's warm bench (started at its first run, stopped when the worker exits;
    its processes die with the worker in any case): one hub, plant and controller for every
    run the worker carries out, across campaigns when the worker outlives one (a cluster
    started by hand). Its own files are in a temporary directory of the worker; every run's
    logs are in the run's directory."""
    global _BENCH
    if _BENCH is None:
        _BENCH = Bench(warm=True)
        atexit.register(_BENCH.close)
    return _BENCH


_BENCH: Bench | None = None


def check_runs(runs: list[RunSpec], root: Path) -> None:
    """Every run of a campaign's matrix meets the checks of ``rhonn-harness run``
    (harness/run/validate.py) before the first starts; the first that does not is a
    CampaignError naming its group, scenario and controller."""
    seen: set[str] = set()
    for spec in runs:
        # the seed and the run's directory cannot make a run invalid: check the rest once
        ident = {k: v for k, v in spec.identity().items() if k != "seed"}
        key = json.dumps(ident, sort_keys=True, default=str)
        if key in seen:
            continue
        seen.add(key)
        try:
            check_run_config(replace(spec, out_dir=spec.run_dir(root)), bus=False)
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
        if run_dir.exists():  # a run cut short by a killed campaign: start it afresh
            shutil.rmtree(run_dir)
        result = run_and_report(replace(spec, out_dir=run_dir), bench=worker_bench())
        m = result.metrics
        row["reason"] = result.reason
        row["run_wall_s"] = _float(m.get("wall_time_s"))
        row["loop_wall_s"] = _float(m.get("loop_wall_s"))
        row["bench"] = json.dumps(m.get("bench") or {}, sort_keys=True)
        for k in KPI_FLOATS:
            row[k] = _float(m.get(k))
        for k in KPI_FLAGS:
            row[k] = None if m.get(k) is None else bool(m.get(k))
        err = m.get("analysis_error")
        post: dict[str, Any] = {}
        info = dict(spec.info)
        for step in spec.post:
            try:
                post[step] = _clean(_post(step, run_dir, info, dict(spec.vehicle)))
            except Exception as exc:  # keep the run; say which step failed
                post[step] = {"error": error_text(exc)}
                err = err or f"post {step}: {error_text(exc)}"
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
               started_at=None, task_wall_s=None, post="{}", bench="{}")
    return row
