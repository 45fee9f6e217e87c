"""Smoothness of the yaw moment ΔM and of the wheel torques: one definition for every run.

The inputs are samples on the communication-cycle grid: one sample per cycle of ``cycle_s``
seconds (10 ms), NaN where a cycle has none. ΔM(k) is the yaw-moment command in N·m and
T_w(k) the commanded torque of wheel w in N·m. A run's KPIs (harness/analysis/kpi.py) take ΔM
from the CTRL_REFS.DELTA_M frames and the torques from the WHEEL_TORQUE_CMD frames (TQ_FL,
TQ_FR, TQ_RL, TQ_RR: the controller's commands as sent on the bus, not the torques the
plant's truth trace records), each frame placed at its cycle by :func:`on_cycle_grid`.

With D = (the cycles from the first to the last finite ΔM sample) × ``cycle_s``, the run's
duration in s, and p = round(MPC period / ``cycle_s``) cycles (50 ms / 10 ms = 5):

* ``dM_tv_per_s_Nm_per_s``: the total variation Σ|ΔM(k) − ΔM(k')| over consecutive finite
  samples k' < k (a cycle without a sample is bridged, as ``dM_total_variation_Nm`` does),
  divided by D; N·m/s.
* ``dM_max_change_per_period_Nm``: the largest |ΔM(k) − ΔM(k − p)| over the cycles where both
  samples are finite; N·m: the largest yaw-moment step over one controller decision.
* ``wheel_torque_rate_max_Nm_per_s`` / ``wheel_torque_rate_p99_Nm_per_s``: over the four
  wheels and every cycle k where T_w(k) and T_w(k − 1) are finite, |T_w(k) − T_w(k − 1)| /
  ``cycle_s``: the largest and the 99th percentile (linear interpolation); N·m/s, to hold
  against the motor torque-rate specification.
* ``dM_chatter_per_s``: sign reversals of the ΔM increment per second: the increments
  d = ΔM(k) − ΔM(k') of consecutive finite samples, those with |d| ≤
  :data:`CHATTER_DEADBAND_NM` dropped, then the number of consecutive remaining increments
  with opposite signs, divided by D; 1/s (a yaw moment that swings back and forth).

A value that cannot be computed (too few finite samples, no pair p cycles apart) is None.
"""

from __future__ import annotations

import math

import numpy as np

CHATTER_DEADBAND_NM = 5.0
"""ΔM increments of at most this magnitude (N·m) are resolution noise, not moves: DELTA_M and
every TQ_* are sent in steps of 0.5 N·m (can_db/rhonn_tv.dbc), and a nearly held command under
sensor noise toggles by one or a few such steps; 5 N·m is 10 steps."""
DEFAULT_CYCLE_S = 0.01
"""The DBC's communication cycle, s."""
DEFAULT_MPC_PERIOD_S = 0.05
"""The controller's MPC period Ts of the packaged configuration, s."""
SMOOTHNESS_KEYS = ("dM_tv_per_s_Nm_per_s", "dM_max_change_per_period_Nm",
                   "wheel_torque_rate_max_Nm_per_s", "wheel_torque_rate_p99_Nm_per_s",
                   "dM_chatter_per_s")


def delta_m_of(torques: np.ndarray) -> np.ndarray:
    """ΔM (n,) N·m of wheel torques (n, 4) N·m in the order FL, FR, RL, RR (the DBC's lever
    dM = TQ_FR + TQ_RR − TQ_FL − TQ_RL, as the controller sends it in CTRL_REFS.DELTA_M)."""
    t = np.asarray(torques, dtype=float).reshape(-1, 4)
    return t[:, 1] + t[:, 3] - t[:, 0] - t[:, 2]


def on_cycle_grid(cycles: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Frame values (n,) or (n, k) placed on the grid of cycles from the first to the last
    valid cycle (≥ 0), NaN where a cycle has no frame; a cycle with several frames keeps the
    last one in bus order. Units are those of ``values``."""
    c = np.asarray(cycles, dtype=float)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(c) & (c >= 0)
    c, v = c[ok].astype(np.int64), v[ok]
    if c.size == 0:
        return np.full((0, *v.shape[1:]), math.nan)
    first = int(c.min())
    grid = np.full((int(c.max()) - first + 1, *v.shape[1:]), math.nan)
    _, last_rev = np.unique(c[::-1], return_index=True)  # last frame of every cycle
    last = c.size - 1 - last_rev
    grid[c[last] - first] = v[last]
    return grid


def step_rates(samples: np.ndarray, cycle_s: float = DEFAULT_CYCLE_S) -> np.ndarray:
    """|x(k) − x(k − 1)| / ``cycle_s`` of per-cycle samples (n,) or (n, k), units of x per
    second; row 0 and rows next to a missing (NaN) sample are NaN."""
    x = np.asarray(samples, dtype=float)
    out = np.full(x.shape, math.nan)
    if x.shape[0] > 1:
        out[1:] = np.abs(np.diff(x, axis=0)) / cycle_s
    return out


def frame_rates(cycles: np.ndarray, values: np.ndarray,
                cycle_s: float = DEFAULT_CYCLE_S) -> np.ndarray:
    """:func:`step_rates` of frame values (n,) at their cycles, one per frame (units of the
    values per second; NaN for a frame whose previous cycle has no frame or whose cycle is
    unknown)."""
    c = np.asarray(cycles, dtype=float)
    out = np.full(c.shape, math.nan)
    grid = step_rates(on_cycle_grid(c, values), cycle_s)
    ok = np.isfinite(c) & (c >= 0)
    if ok.any():
        out[ok] = grid[c[ok].astype(np.int64) - int(c[ok].min())]
    return out


def _finite(x: np.ndarray) -> np.ndarray:
    a = np.asarray(x, dtype=float).ravel()
    return a[np.isfinite(a)]


def duration_s(delta_m: np.ndarray, cycle_s: float = DEFAULT_CYCLE_S) -> float:
    """Cycles from the first to the last finite sample × ``cycle_s``, s (0 if none)."""
    idx = np.flatnonzero(np.isfinite(np.asarray(delta_m, dtype=float)))
    return float(idx[-1] - idx[0] + 1) * cycle_s if idx.size else 0.0


def max_change_over(delta_m: np.ndarray, lag: int) -> float | None:
    """max |ΔM(k) − ΔM(k − lag)| over finite pairs (N·m), None if there is no such pair."""
    dm = np.asarray(delta_m, dtype=float)
    if lag < 1 or dm.size <= lag:
        return None
    change = _finite(dm[lag:] - dm[:-lag])
    return float(np.max(np.abs(change))) if change.size else None


def chatter_count(delta_m: np.ndarray, deadband_nm: float = CHATTER_DEADBAND_NM) -> int:
    """Sign reversals of the increments of the finite ΔM samples whose magnitude exceeds
    ``deadband_nm`` (N·m), counted over consecutive remaining increments."""
    d = np.diff(_finite(delta_m))
    d = d[np.abs(d) > deadband_nm]
    return int(np.count_nonzero(np.sign(d[1:]) != np.sign(d[:-1]))) if d.size > 1 else 0


def smoothness(delta_m: np.ndarray, torques: np.ndarray, cycle_s: float = DEFAULT_CYCLE_S,
               period_s: float = DEFAULT_MPC_PERIOD_S) -> dict[str, float | None]:
    """The smoothness KPIs (module docstring) of ΔM (n,) N·m and the wheel torques (m, 4)
    N·m, both one sample per cycle of ``cycle_s`` s (NaN: no sample), with the MPC period
    ``period_s`` s."""
    out: dict[str, float | None] = dict.fromkeys(SMOOTHNESS_KEYS)
    if not (math.isfinite(cycle_s) and cycle_s > 0.0):
        return out
    dm = np.asarray(delta_m, dtype=float).ravel()
    rates = _finite(step_rates(np.asarray(torques, dtype=float).reshape(-1, 4), cycle_s))
    if rates.size:
        out["wheel_torque_rate_max_Nm_per_s"] = float(np.max(rates))
        out["wheel_torque_rate_p99_Nm_per_s"] = float(np.percentile(rates, 99))
    period = period_s if math.isfinite(period_s) and period_s > 0.0 else DEFAULT_MPC_PERIOD_S
    out["dM_max_change_per_period_Nm"] = max_change_over(dm, max(1, round(period / cycle_s)))
    samples = _finite(dm)
    if samples.size > 1:
        span = duration_s(dm, cycle_s)
        out["dM_tv_per_s_Nm_per_s"] = float(np.sum(np.abs(np.diff(samples)))) / span
        out["dM_chatter_per_s"] = chatter_count(samples) / span
    return out
