"""Numbers of one finished run beyond its KPIs, read from its directory: the controller's
step-time statistics (µs, measured in the controller process) and the diagnostics the paper's
discussion quotes (reference roughness, ΔM saturation, where the largest deviation happened).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from harness.analysis.run_data import load_run, load_timing_csv


def timing_stats(run_dir: Path) -> dict[str, Any]:
    """Controller step time (µs, measured in the controller process) over all answered
    cycles, the MPC-update cycles (full step: learning, references, QP) and the others
    (re-allocation of the held ΔM)."""
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
