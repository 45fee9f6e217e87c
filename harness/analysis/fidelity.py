"""Model fidelity offline from a recorded run (paper Tables 2–3, Figs 5–6).

Inputs come from a bus run directory: the decoded plant frames of every 10 ms cycle
(DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST — exactly what the controller saw)
and the truth trace (true Vx, Vy, ωr; the applied wheel torques ``tcmd_*``). Truth row k+1
holds the command that acted over [t_k, t_{k+1}], so the torque of step k is row k+1's.

Two comparisons, both honest about what they measure:

* ``paper`` (the paper's set-up): the RHONN as a *one-step* series-parallel estimator from
  cold start with online EKF learning (at every step it sees the measured state, learns,
  and predicts Ts ahead), against the two 7-DoF models integrated *open loop* over the whole
  run from the true initial state (they never see a measurement). Evaluated on the
  controller grid (every Ts, default 50 ms) at the predicted instants.
* ``prediction``: every model restarted at every grid point from the *measured* state (the
  bus's VX_EST, VY_EST and YAW_RATE, as the MPC would) and run with the recorded inputs for
  1 and ``horizon`` steps of Ts (default 3 × 50 ms = 150 ms). The RHONN uses the weights it
  has learned up to that instant and predicts in parallel mode (its own outputs fed back).

Errors: min / max / RMSE of |estimate − truth| in km/h (Vx, Vy) and deg/s (ωr)
(:func:`harness.analysis.kpi.model_fidelity`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controller.core.interfaces import ControllerInputs, PredictionContext
from controller.core.registry import load_controller_config, make_estimator
from harness.analysis.kpi import model_fidelity
from harness.analysis.run_data import RunData, load_run

MODELS = ("rhonn", "7dof-li", "7dof-mf")
COMM_PERIOD_S = 0.01
WHEELS = ("fl", "fr", "rl", "rr")


@dataclass
class FidelityInputs:
    """Per-cycle arrays (N rows at 10 ms) of one run.

    t_s: s. truth: (N, 3) true [Vx m/s, Vy m/s, ωr rad/s]. swa_rad: rad. accel, brake: 0..1.
    yaw_rate: rad/s (sensor). ax, ay: m/s². vx_est, vy_est: m/s (bus estimate).
    wheel_speeds: (N, 4) rad/s. torques: (N, 4) N·m acting over [t_k, t_{k+1}].
    """

    t_s: np.ndarray
    truth: np.ndarray
    swa_rad: np.ndarray
    accel: np.ndarray
    brake: np.ndarray
    yaw_rate: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    vx_est: np.ndarray
    vy_est: np.ndarray
    wheel_speeds: np.ndarray
    torques: np.ndarray

    @property
    def n(self) -> int:
        """Number of cycles."""
        return int(self.t_s.size)


def _per_cycle(run: RunData, message: str, signal: str, cycles: np.ndarray,
               scale: float = 1.0) -> np.ndarray:
    """Value of a plant signal at every truth cycle (last frame of that cycle; gaps are
    filled with the previous value, a missing start with the first value)."""
    vals = run.bus_sig(message, signal).astype(float)
    cyc = run.bus_sig(message, "cycle")
    out = np.full(cycles.size, math.nan)
    if vals.size == 0:
        return out
    row = {int(c): i for i, c in enumerate(cycles.tolist())}
    for c, v in zip(cyc.tolist(), vals.tolist(), strict=True):
        i = row.get(int(c))
        if i is not None:
            out[i] = v * scale
    ok = np.isfinite(out)
    if not ok.any():
        return out
    idx = np.where(ok, np.arange(out.size), 0)
    np.maximum.accumulate(idx, out=idx)
    out = out[idx]
    first = int(np.flatnonzero(ok)[0])
    out[:first] = out[first]
    return out


def load_fidelity_inputs(run_dir: str | Path) -> FidelityInputs:
    """Decode a run directory into :class:`FidelityInputs` (raises ValueError if empty)."""
    run = load_run(run_dir)
    cycles = run.truth_col("cycle")
    if cycles.size < 2:
        raise ValueError(f"{run_dir}: truth trace too short for a fidelity evaluation")
    deg = math.pi / 180.0
    truth = np.column_stack([run.truth_col("vx_mps"), run.truth_col("vy_mps"),
                             run.truth_col("yaw_rate_radps")])
    tcmd = np.column_stack([run.truth_col(f"tcmd_{w}") for w in WHEELS])
    torques = np.vstack([tcmd[1:], tcmd[-1:]])  # row k+1 acted over [t_k, t_{k+1}]
    ws = np.column_stack([_per_cycle(run, "WHEEL_SPEEDS", f"WS_{w.upper()}", cycles)
                          for w in WHEELS])
    return FidelityInputs(
        t_s=run.truth_col("t_s"), truth=truth,
        swa_rad=_per_cycle(run, "DRIVER_INPUTS", "SWA", cycles, deg),
        accel=_per_cycle(run, "DRIVER_INPUTS", "ACCEL_PEDAL", cycles, 0.01),
        brake=_per_cycle(run, "DRIVER_INPUTS", "BRAKE_PEDAL", cycles, 0.01),
        yaw_rate=_per_cycle(run, "MOTION_SENSORS", "YAW_RATE", cycles, deg),
        ax=_per_cycle(run, "MOTION_SENSORS", "AX", cycles),
        ay=_per_cycle(run, "MOTION_SENSORS", "AY", cycles),
        vx_est=_per_cycle(run, "VEHICLE_EST", "VX_EST", cycles),
        vy_est=_per_cycle(run, "VEHICLE_EST", "VY_EST", cycles),
        wheel_speeds=ws, torques=torques)


def _fill(inp: Any, d: FidelityInputs, k: int) -> Any:
    """Write cycle k's bus values into a ControllerInputs."""
    inp.swa_rad = float(d.swa_rad[k])
    inp.accel_pedal = float(d.accel[k])
    inp.brake_pedal = float(d.brake[k])
    inp.yaw_rate = float(d.yaw_rate[k])
    inp.ax, inp.ay = float(d.ax[k]), float(d.ay[k])
    inp.wheel_speeds[:] = d.wheel_speeds[k]
    inp.vx, inp.vy = float(d.vx_est[k]), float(d.vy_est[k])
    inp.stab_enable, inp.sensors_valid = True, True
    return inp


@dataclass
class FidelityResult:
    """Errors per comparison and model, plus the time series for the figures.

    ``paper[model]``, ``one_step[model]``, ``multi_step[model]``: model_fidelity dicts.
    ``series[model]``: (M, 3) estimates at ``t_grid`` (NaN where none) of the ``paper``
    comparison; ``truth_grid`` (M, 3) the truth there. ``reference``: the floor and the
    naive baseline of any predictor fed with the bus measurement — ``sensor`` = |measured −
    true| at the same instant, ``hold_1``/``hold_h`` = the measurement held for 1 / horizon
    steps (x̂_{k+n} = x_meas,k).
    """

    ts_s: float
    horizon: int
    paper: dict[str, dict[str, dict[str, float | None]]] = field(default_factory=dict)
    one_step: dict[str, dict[str, dict[str, float | None]]] = field(default_factory=dict)
    multi_step: dict[str, dict[str, dict[str, float | None]]] = field(default_factory=dict)
    reference: dict[str, dict[str, dict[str, float | None]]] = field(default_factory=dict)
    t_grid: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_grid: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    series: dict[str, np.ndarray] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The numbers (no time series)."""
        return {"ts_s": self.ts_s, "horizon_steps": self.horizon,
                "horizon_s": self.ts_s * self.horizon, "paper": self.paper,
                "one_step": self.one_step, "multi_step": self.multi_step,
                "reference": self.reference}


def _rhonn_parallel(model: Any, d: FidelityInputs, k: int, m: int, horizon: int,
                    ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """RHONN parallel prediction from the measured state at k: states after 1 and
    ``horizon`` steps of m cycles (NaN if the model has no ``predict``)."""
    if not hasattr(model, "predict"):
        return np.full(3, math.nan), np.full(3, math.nan)
    x = np.array([d.vx_est[k], d.vy_est[k], d.yaw_rate[k]], dtype=float)
    out = np.zeros(3)
    ctx = PredictionContext(ts=m * COMM_PERIOD_S)
    first = np.full(3, math.nan)
    for j in range(horizon):
        i = k + j * m
        tq = d.torques[i:i + m].mean(axis=0)
        ctx.delta_w = float(d.swa_rad[i]) / ratio
        ctx.total_torque = float(tq.sum())
        ctx.wheel_speeds = d.wheel_speeds[i]
        model.predict(x, float(tq[1] + tq[3] - tq[0] - tq[2]), ctx, out)
        x = out.copy()
        if j == 0:
            first = x.copy()
    return first, x


def evaluate_fidelity(d: FidelityInputs, ts_s: float = 0.05, horizon: int = 3,
                      config: str | None = None) -> FidelityResult:
    """Run the three estimators over the recorded inputs (see the module docstring).

    ts_s: model/controller period, s (a multiple of the 10 ms cycle). horizon: steps of
    ts_s for the multi-step prediction. config: controller TOML for the RHONN (None =
    packaged default).
    """
    m = max(1, round(ts_s / COMM_PERIOD_S))
    ts = m * COMM_PERIOD_S
    ratio = load_controller_config(config).params.steering_ratio
    grid = np.arange(0, d.n, m)
    res = FidelityResult(ts_s=ts, horizon=horizon, t_grid=d.t_s[grid],
                         truth_grid=d.truth[grid])
    inp = ControllerInputs()

    # --- the paper's comparison -------------------------------------------------------
    # RHONN: series-parallel one-step from cold start; estimate for grid point g+1.
    rh = make_estimator("rhonn", config)
    rh.reset()
    est = np.full((grid.size, 3), math.nan)
    one = {name: np.full((grid.size, 3), math.nan) for name in MODELS}
    multi = {name: np.full((grid.size, 3), math.nan) for name in MODELS}
    rh_model = getattr(rh, "model", None)
    for g, k in enumerate(grid):
        if k + m >= d.n:
            break
        tq = d.torques[k:k + m].mean(axis=0)  # the torque that acted over the step
        est[g + 1] = rh.step(_fill(inp, d, int(k)), tq, ts)
        if rh_model is not None and k + horizon * m < d.n:
            o1, oh = _rhonn_parallel(rh_model, d, int(k), m, horizon, ratio)
            one["rhonn"][g + 1], multi["rhonn"][g + horizon] = o1, oh
    res.series["rhonn"] = est

    # 7-DoF: open loop over the whole run from the true initial state (paper set-up).
    for name in ("7dof-li", "7dof-mf"):
        e = make_estimator(name, config)
        e.initialise(*(float(v) for v in d.truth[0]))  # type: ignore[attr-defined]
        s = np.full((grid.size, 3), math.nan)
        s[0] = d.truth[0]
        for k in range(d.n - 1):
            x = e.step(_fill(inp, d, k), d.torques[k], COMM_PERIOD_S)
            if (k + 1) % m == 0:
                s[(k + 1) // m] = x
        res.series[name] = s
        # restarted from the measured state at every grid point
        p = make_estimator(name, config)
        for g, k in enumerate(grid):
            if k + horizon * m >= d.n:
                break
            p.initialise(float(d.vx_est[k]), float(d.vy_est[k]),  # type: ignore[attr-defined]
                         float(d.yaw_rate[k]))
            for j in range(horizon * m):
                x = p.step(_fill(inp, d, int(k) + j), d.torques[k + j], COMM_PERIOD_S)
                if j + 1 == m:
                    one[name][g + 1] = x
            multi[name][g + horizon] = x

    meas = np.column_stack([d.vx_est[grid], d.vy_est[grid], d.yaw_rate[grid]])
    hold_1, hold_h = np.full_like(meas, math.nan), np.full_like(meas, math.nan)
    hold_1[1:], hold_h[horizon:] = meas[:-1], meas[:-horizon]
    res.reference = {"sensor": model_fidelity(res.truth_grid, meas),
                     "hold_1": model_fidelity(res.truth_grid, hold_1),
                     "hold_h": model_fidelity(res.truth_grid, hold_h)}
    for name in MODELS:
        res.paper[name] = model_fidelity(res.truth_grid, res.series[name])
        res.one_step[name] = model_fidelity(res.truth_grid, one[name])
        res.multi_step[name] = model_fidelity(res.truth_grid, multi[name])
    return res


def evaluate_run(run_dir: str | Path, ts_s: float = 0.05,
                 horizon: int = 3) -> tuple[FidelityResult, dict[str, Any]]:
    """Load and evaluate a run (ts_s: model period, s; horizon: steps): the result, whose time
    series a figure draws (harness/viz/fidelity_plot.py), and its numbers
    (:meth:`FidelityResult.to_json` plus the run's duration s, peak |Vy| km/h and peak |ωr|
    deg/s)."""
    d = load_fidelity_inputs(run_dir)
    res = evaluate_fidelity(d, ts_s, horizon)
    out = res.to_json()
    out["duration_s"] = float(d.t_s[-1]) if d.n else 0.0
    out["max_abs_vy_kmh"] = float(np.nanmax(np.abs(d.truth[:, 1]))) * 3.6
    out["max_abs_yaw_rate_degps"] = float(np.degrees(np.nanmax(np.abs(d.truth[:, 2]))))
    return res, out
