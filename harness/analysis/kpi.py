"""KPIs of one run (one definition, used everywhere).

All results are JSON-serialisable plain ``float``/``int``/``bool``/``dict``; a value that
cannot be computed (missing data, NaN) is ``None``.

Definitions (truth = the plant's truth trace, one row per 10 ms cycle):

* ``completed``: the truth trace is non-empty, the vehicle did not spin, and, when
  ``meta["scenario_end_s"]`` is known, the trace reaches it (within 1.5 cycles).
* ``phase_area``: area (rad·rad/s) of the convex hull of the (β, β̇) trajectory. β̇ is a
  Savitzky–Golay derivative (quadratic fit over 5 samples = ±20 ms at 10 ms): a central finite
  difference with light smoothing of sample noise, exact for polynomials up to degree 2,
  attenuating a sinusoid's β̇ by 0.2 % at 1 Hz, 2 % at 3 Hz (lateral manoeuvres are ≲ 1 Hz).
  Runs shorter than 5 samples use ``np.gradient``.
* ``steering_effort_deg``: ∫|dδsw/dt| dt = Σ|Δδsw| (total variation of the sampled angle).
* ``max_abs_dM_Nm`` / ``dM_total_variation_Nm``: CTRL_REFS.DELTA_M over the run (bus order).
* smoothness (harness/analysis/smoothness.py, one definition, see there):
  ``dM_tv_per_s_Nm_per_s`` (Σ|ΔM(k) − ΔM(k−1)| / run duration, N·m/s),
  ``dM_max_change_per_period_Nm`` (max |ΔM(k) − ΔM(k−p)|, p = MPC period in cycles, N·m),
  ``dM_chatter_per_s`` (sign reversals of the ΔM increments beyond 5 N·m per second, 1/s) of
  CTRL_REFS.DELTA_M, and ``wheel_torque_rate_max_Nm_per_s`` / ``wheel_torque_rate_p99_Nm_per_s``
  (|T(k) − T(k−1)| / cycle over the four wheels, N·m/s) of the commanded torques of the
  WHEEL_TORQUE_CMD frames (the bus, not the truth's torques); every frame at its cycle, cycle
  ``meta["comm_period_s"]`` (default 10 ms), MPC period ``meta["ctrl_period_s"]`` (default
  50 ms).
* ``yaw_rate_rmse_degps`` / ``beta_rmse_deg``: CTRL_REFS reference of cycle k vs truth at
  cycle k, over cycles where CTRL_STATUS reports MODE = ACTIVE (all matched cycles if no
  CTRL_STATUS was logged).
* timing: ``controller_timing.csv`` (``step_us`` falls back to CTRL_STATUS.COMPUTE_TIME).
  ``step_us_*`` (controller step) and ``turnaround_us_*`` (SYNC received → last answer
  sent) are wall-clock compute times in every mode; ``deadline_misses`` counts turnarounds
  longer than the period (in lockstep: compute over the 10 ms budget, the plant waits).
  ``period_jitter_us_p99`` = p99 of |period − nominal| with nominal
  ``meta["comm_period_s"]`` (default 10 ms), the first row (no previous sync) and rows after
  a missing cycle (a lost SYNC: loss, not jitter) excluded; None when ``meta["mode"]`` is
  ``"lockstep"``: there the SYNC period is simulated (exactly 10 ms) and its wall-clock
  spacing is only the loop's compute speed, not jitter.
* ``frames_rejected``: by reason, bus-log decode + ``meta["rejections"]`` (a flat
  ``{reason: n}`` or per process ``{process: {reason: n}}``), summed.
* ``fallback_events``: truth cycles after the first with ``cmd_valid == 0`` + CTRL_STATUS
  frames with QP_STATUS = 5 (FALLBACK).
* ``passed_dlc``: the paper rule as the paper study's v_max bisection reads it (a window the
  trace does not cover counts as a fail; users see the three-valued ``verdicts`` block of
  harness/analysis/verdicts.py instead): no spin, max|β| ≤ ``pass_beta_deg`` and
  max|lateral dev| ≤ ``pass_dev_m``
  for t ≤ ``course_end_s`` + 2 s, and the trace covers that window (whole run and
  ``completed`` if ``course_end_s`` is None). ``course_end_s`` is a sim *time*; convert an
  arc length with :func:`course_end_time_s`; if that returns None (course end never
  reached), pass ``math.inf``: the window is then not covered and the DLC fails.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy.signal import savgol_filter
from scipy.spatial import ConvexHull, QhullError

from harness.analysis.run_data import RunData
from harness.analysis.smoothness import (
    DEFAULT_MPC_PERIOD_S,
    SMOOTHNESS_KEYS,
    on_cycle_grid,
    smoothness,
)

MODE_ACTIVE = 1
QP_STATUS_FALLBACK = 5
DEFAULT_PERIOD_S = 0.01
DLC_AFTER_COURSE_S = 2.0
SAVGOL_WINDOW = 5
SAVGOL_ORDER = 2
WHEEL_NAMES = ("FL", "FR", "RL", "RR")  # WHEEL_TORQUE_CMD.TQ_<wheel>

KPI_KEYS = (
    "completed", "spun", "max_abs_beta_deg", "max_abs_lateral_dev_m", "rms_lateral_dev_m",
    "phase_area", "max_abs_swa_deg", "steering_effort_deg", "max_abs_dM_Nm",
    "dM_total_variation_Nm", *SMOOTHNESS_KEYS, "yaw_rate_rmse_degps", "beta_rmse_deg",
    "step_us_p50", "step_us_p99", "turnaround_us_p50", "turnaround_us_p99", "period_jitter_us_p99",
    "deadline_misses", "frames_rejected", "fallback_events", "passed_dlc",
)


def _f(x: float | None) -> float | None:
    """Plain float, NaN/inf -> None."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _finite(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return a[np.isfinite(a)]


def _max_abs(a: np.ndarray) -> float | None:
    a = _finite(a)
    return float(np.max(np.abs(a))) if a.size else None


def _rms(a: np.ndarray) -> float | None:
    a = _finite(a)
    return float(np.sqrt(np.mean(a * a))) if a.size else None


def _pct(a: np.ndarray, q: float) -> float | None:
    a = _finite(a)
    return float(np.percentile(a, q)) if a.size else None


def _total_variation(a: np.ndarray) -> float | None:
    a = _finite(a)
    return float(np.sum(np.abs(np.diff(a)))) if a.size else None


def beta_rate(beta_rad: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """β̇ (rad/s): Savitzky–Golay derivative (5 samples, quadratic) at the median step."""
    beta = np.asarray(beta_rad, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if beta.size < 2:
        return np.zeros_like(beta)
    dt = float(np.median(np.diff(t))) if t.size == beta.size else DEFAULT_PERIOD_S
    if not (math.isfinite(dt) and dt > 0):
        dt = DEFAULT_PERIOD_S
    if beta.size < SAVGOL_WINDOW:
        return np.gradient(beta, dt)

    return savgol_filter(beta, SAVGOL_WINDOW, SAVGOL_ORDER, deriv=1, delta=dt, mode="interp")


def phase_area(beta_rad: np.ndarray, t_s: np.ndarray) -> float:
    """Convex-hull area of the (β, β̇) trajectory in rad·rad/s (0 if degenerate)."""
    beta = np.asarray(beta_rad, dtype=float)
    t = np.asarray(t_s, dtype=float)
    ok = np.isfinite(beta) & np.isfinite(t)
    beta, t = beta[ok], t[ok]
    if beta.size < 3:
        return 0.0
    pts = np.column_stack([beta, beta_rate(beta, t)])

    try:
        return float(ConvexHull(pts).volume)  # in 2-D "volume" is the area
    except (QhullError, ValueError):
        return 0.0


def model_fidelity(truth_xyz: np.ndarray, est_xyz: np.ndarray
                   ) -> dict[str, dict[str, float | None]]:
    """Min / max / RMSE of |estimate − truth| (paper Tables 2–3).

    Both arrays are (N, 3) with columns Vx (m/s), Vy (m/s), ωr (rad/s); rows with a non-finite
    value are ignored. Returns ``{"vx_kmh": {"min", "max", "rmse"}, "vy_kmh": …,
    "yaw_rate_degps": …}`` in km/h, km/h and deg/s.
    """
    truth = np.asarray(truth_xyz, dtype=float).reshape(-1, 3)
    est = np.asarray(est_xyz, dtype=float).reshape(-1, 3)
    n = min(len(truth), len(est))
    err = np.abs(est[:n] - truth[:n]) * np.array([3.6, 3.6, 180.0 / math.pi])
    err = err[np.all(np.isfinite(err), axis=1)]
    out: dict[str, dict[str, float | None]] = {}
    for i, key in enumerate(("vx_kmh", "vy_kmh", "yaw_rate_degps")):
        e = err[:, i]
        out[key] = {"min": _f(e.min()) if e.size else None,
                    "max": _f(e.max()) if e.size else None,
                    "rmse": _rms(e)}
    return out


def _merge_counts(total: dict[str, int], counts: Any) -> None:
    """Add ``{reason: n}`` or ``{process: {reason: n}}`` into ``total``."""
    if not isinstance(counts, Mapping):
        return
    for key, val in counts.items():
        if isinstance(val, Mapping):
            _merge_counts(total, val)
        elif isinstance(val, numbers.Real) and math.isfinite(float(val)):
            total[str(key)] = total.get(str(key), 0) + int(val)


def _tracking_rmse(run: RunData, ref_sig: str, truth_col: str, scale: float) -> float | None:
    """RMSE (reference units) of CTRL_REFS.<ref_sig> vs truth[truth_col]·scale, per cycle."""
    ref = run.bus_sig("CTRL_REFS", ref_sig).astype(float)
    ref_cyc = run.bus_sig("CTRL_REFS", "cycle")
    t_cyc, actual = run.truth_col("cycle"), run.truth_col(truth_col)
    if ref.size == 0 or t_cyc.size == 0 or actual.size != t_cyc.size:
        return None
    active_cycles = None
    st_cyc = run.bus_sig("CTRL_STATUS", "cycle")
    if st_cyc.size:
        mode = run.bus_sig("CTRL_STATUS", "MODE")
        active_cycles = set(st_cyc[mode == MODE_ACTIVE].tolist())
    row_of = {int(c): i for i, c in enumerate(t_cyc.tolist()) if math.isfinite(c)}
    err = []
    for c, r in zip(ref_cyc.tolist(), ref.tolist(), strict=True):
        i = row_of.get(int(c))
        if i is None or (active_cycles is not None and c not in active_cycles):
            continue
        err.append(r - actual[i] * scale)
    return _rms(np.asarray(err))


def _smoothness(run: RunData, cycle_s: float) -> dict[str, float | None]:
    """Smoothness KPIs of CTRL_REFS.DELTA_M (N·m) and the WHEEL_TORQUE_CMD torques (N·m) of the
    bus log, each frame at its cycle of ``cycle_s`` s; MPC period ``meta["ctrl_period_s"]`` s."""
    dm = on_cycle_grid(run.bus_sig("CTRL_REFS", "cycle"), run.bus_sig("CTRL_REFS", "DELTA_M"))
    sig = [run.bus_sig("WHEEL_TORQUE_CMD", f"TQ_{w}").astype(float) for w in WHEEL_NAMES]
    cyc = run.bus_sig("WHEEL_TORQUE_CMD", "cycle")
    if not all(s.size == cyc.size for s in sig):
        sig = [np.empty(0)] * len(WHEEL_NAMES)
        cyc = np.empty(0)
    torques = on_cycle_grid(cyc, np.stack(sig, axis=1).reshape(-1, len(WHEEL_NAMES)))
    period = _f(run.meta.get("ctrl_period_s")) or DEFAULT_MPC_PERIOD_S
    return smoothness(dm, torques, cycle_s=cycle_s, period_s=period)


def course_end_time_s(run: RunData, course_end_arc_m: float) -> float | None:
    """Sim time (s) at which the truth's ``path_s_m`` first reaches ``course_end_arc_m`` (m).

    Converts a course end given as arc length (e.g. ``plant_sim.course.Course.course_end_s``)
    into the time ``compute_kpis(course_end_s=…)`` expects; None if it is never reached.
    """
    t, s = run.truth_col("t_s"), run.truth_col("path_s_m")
    if t.size == 0 or s.size != t.size:
        return None
    hit = np.flatnonzero(s >= course_end_arc_m)
    return float(t[hit[0]]) if hit.size else None


def compute_kpis(run: RunData, *, pass_beta_deg: float = 8.0, pass_dev_m: float = 1.0,
                 course_end_s: float | None = None) -> dict[str, Any]:
    """The KPI dict of one run (keys :data:`KPI_KEYS`, see the module docstring)."""
    deg = 180.0 / math.pi
    t = run.truth_col("t_s")
    beta = run.truth_col("beta_rad")
    dev = run.truth_col("lateral_dev_m")
    spun_col = run.truth_col("spun")
    has_truth = t.size > 0
    spun: bool | None = bool(np.any(spun_col > 0.5)) if spun_col.size else (
        False if has_truth else None)

    completed = bool(has_truth and not spun)
    end = run.meta.get("scenario_end_s")
    dt = float(run.meta.get("comm_period_s", DEFAULT_PERIOD_S))
    t_last = float(np.max(_finite(t))) if _finite(t).size else -math.inf
    if completed and end is not None:
        completed = bool(t_last >= float(end) - 1.5 * dt)

    swa = run.truth_col("swa_rad") * deg
    if swa.size == 0:
        swa = run.bus_sig("DRIVER_INPUTS", "SWA").astype(float)
    dM = run.bus_sig("CTRL_REFS", "DELTA_M").astype(float)

    step = run.timing_col("step_us")
    if step.size == 0:
        step = run.bus_sig("CTRL_STATUS", "COMPUTE_TIME").astype(float)
    # Jitter of the SYNC period over consecutive cycles only: a lost SYNC (loss faults) makes
    # one 2-period gap, which is loss, not jitter (counted by fallback_events instead).
    period = run.timing_col("period_us")[1:]
    cycles = run.timing_col("cycle")
    if cycles.size == period.size + 1:
        period = period[np.diff(cycles) == 1]
    period = period[np.isfinite(period) & (period > 0)]
    miss = run.timing_col("deadline_miss")

    rejected: dict[str, int] = {}
    _merge_counts(rejected, run.rejections)
    _merge_counts(rejected, run.meta.get("rejections"))

    cmd_valid = run.truth_col("cmd_valid")
    fallbacks = int(np.sum(cmd_valid[1:] < 0.5)) if cmd_valid.size > 1 else 0
    fallbacks += int(np.sum(run.bus_sig("CTRL_STATUS", "QP_STATUS") == QP_STATUS_FALLBACK))

    # DLC pass window: from the start to course end + 2 s.
    if course_end_s is None:
        window = np.ones(t.size, dtype=bool)
        covered = completed
    else:
        t_end = float(course_end_s) + DLC_AFTER_COURSE_S
        window = t <= t_end + 1e-9
        covered = bool(t_last >= t_end - 1.5 * dt)
    w_beta = _max_abs(beta[window]) if beta.size == t.size else None
    w_dev = _max_abs(dev[window]) if dev.size == t.size else None
    w_spun = bool(np.any(spun_col[window] > 0.5)) if spun_col.size == t.size else False
    passed = bool(covered and not w_spun and w_beta is not None and w_dev is not None
                  and w_beta * deg <= pass_beta_deg and w_dev <= pass_dev_m)

    max_beta = _max_abs(beta)
    kpis: dict[str, Any] = {
        "completed": completed,
        "spun": spun,
        "max_abs_beta_deg": None if max_beta is None else max_beta * deg,
        "max_abs_lateral_dev_m": _max_abs(dev),
        "rms_lateral_dev_m": _rms(dev),
        "phase_area": phase_area(beta, t) if beta.size == t.size and has_truth else None,
        "max_abs_swa_deg": _max_abs(swa),
        "steering_effort_deg": _total_variation(swa),
        "max_abs_dM_Nm": _max_abs(dM),
        "dM_total_variation_Nm": _total_variation(dM),
        **_smoothness(run, dt),
        "yaw_rate_rmse_degps": _tracking_rmse(run, "YAW_RATE_REF", "yaw_rate_radps", deg),
        "beta_rmse_deg": _tracking_rmse(run, "BETA_REF", "beta_rad", deg),
        "step_us_p50": _pct(step, 50),
        "step_us_p99": _pct(step, 99),
        "turnaround_us_p50": _pct(run.timing_col("turnaround_us"), 50),
        "turnaround_us_p99": _pct(run.timing_col("turnaround_us"), 99),
        "period_jitter_us_p99": (None if run.meta.get("mode") == "lockstep"
                                 else _pct(np.abs(period - dt * 1e6), 99)),
        "deadline_misses": int(np.nansum(miss > 0.5)) if miss.size else None,
        "frames_rejected": dict(sorted(rejected.items())),
        "fallback_events": fallbacks,
        "passed_dlc": passed,
    }
    return {k: _f(v) if isinstance(v, float) else v for k, v in kpis.items()}
