"""Smoothness of the yaw moment and of the wheel torques: one definition for every run.

From the four commanded wheel torques T_FL, T_FR, T_RL, T_RR (N·m), one sample per
communication cycle dt (s), ΔM = T_FR + T_RR − T_FL − T_RL (N·m, eq. 16):

* ``dM_tv_per_s_Nm_per_s``: total variation of ΔM, Σ|ΔM(k) − ΔM(k−1)|, per second of run
  (the run's duration n·dt), N·m/s;
* ``dM_max_change_per_period_Nm``: the largest |ΔM(k) − ΔM(k−p)|, p = the MPC period in
  cycles (50 ms / 10 ms = 5), N·m: the largest yaw-moment step one controller decision made;
* ``wheel_torque_rate_max_Nm_per_s`` / ``wheel_torque_rate_p99_Nm_per_s``: over the four
  wheels and all cycles, |T(k) − T(k−1)| / dt, the largest and the 99th percentile, N·m/s
  (to hold against the motor torque-rate specification);
* ``dM_chatter_per_s``: sign reversals of the ΔM increment per second: the increments
  ΔM(k) − ΔM(k−1) larger than ``CHATTER_DEADBAND_NM`` in magnitude, consecutive pairs of
  opposite sign, per second of run, 1/s (a yaw moment that swings back and forth).

Non-finite samples are dropped (a wheel's sample row with any non-finite torque is dropped
whole); a value that cannot be computed is None.
"""

from __future__ import annotations

import math

import numpy as np

CHATTER_DEADBAND_NM = 5.0
"""|ΔM increment| at or below this (N·m) is not a move: 10 × the torque frame's 0.5 N·m
resolution, above sensor-noise-driven jitter of a held command."""
SMOOTHNESS_KEYS = ("dM_tv_per_s_Nm_per_s", "dM_max_change_per_period_Nm",
                   "wheel_torque_rate_max_Nm_per_s", "wheel_torque_rate_p99_Nm_per_s",
                   "dM_chatter_per_s")


def delta_m_of(torques: np.ndarray) -> np.ndarray:
    """ΔM (n,) N·m of wheel torques (n, 4) N·m in the order FL, FR, RL, RR."""
    t = np.asarray(torques, dtype=float)
    return t[:, 1] + t[:, 3] - t[:, 0] - t[:, 2]


def chatter_count(delta_m: np.ndarray, deadband_nm: float = CHATTER_DEADBAND_NM) -> int:
    """Sign reversals of the ΔM increments beyond ``deadband_nm`` (N·m)."""
    d = np.diff(np.asarray(delta_m, dtype=float))
    d = d[np.abs(d) > deadband_nm]
    return int(np.sum(np.sign(d[1:]) != np.sign(d[:-1]))) if d.size > 1 else 0


def smoothness(torques: np.ndarray, cycle_s: float = 0.01, period_s: float = 0.05
               ) -> dict[str, float | None]:
    """The smoothness KPIs (module docstring) of commanded wheel torques (n, 4) N·m sampled
    every ``cycle_s`` s, with the MPC period ``period_s`` s."""
    t = np.asarray(torques, dtype=float).reshape(-1, 4)
    t = t[np.all(np.isfinite(t), axis=1)]
    out: dict[str, float | None] = dict.fromkeys(SMOOTHNESS_KEYS)
    if t.shape[0] < 2 or not cycle_s > 0.0:
        return out
    duration = t.shape[0] * cycle_s
    dm = delta_m_of(t)
    out["dM_tv_per_s_Nm_per_s"] = float(np.sum(np.abs(np.diff(dm)))) / duration
    p = max(1, round(period_s / cycle_s))
    if dm.size > p:
        out["dM_max_change_per_period_Nm"] = float(np.max(np.abs(dm[p:] - dm[:-p])))
    rate = np.abs(np.diff(t, axis=0)).ravel() / cycle_s
    out["wheel_torque_rate_max_Nm_per_s"] = float(np.max(rate))
    out["wheel_torque_rate_p99_Nm_per_s"] = float(np.percentile(rate, 99))
    out["dM_chatter_per_s"] = chatter_count(dm) / duration
    return {k: (v if v is None or math.isfinite(v) else None) for k, v in out.items()}
