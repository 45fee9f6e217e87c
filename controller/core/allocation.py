"""Torque allocation: (Tt, ΔM) → wheel torques T1..T4 (1 FL, 2 FR, 3 RL, 4 RR), N·m.

Eq. 16:  Tt = T1 + T2 + T3 + T4,  ΔM = T2 + T4 − T1 − T3   (+ΔM turns the car left).

Per-motor limit |Ti| ≤ Tlim_i = min(T_peak, P_peak / |ωi|) (ωi wheel speed rad/s; a
non-finite ωi falls back to T_peak — the motor inverter enforces its own speed-dependent
limit, and a broken speed signal must not zero the driver's torque). Side capacities
C_L = Tlim_1 + Tlim_3, C_R = Tlim_2 + Tlim_4.

Priority when (Tt, ΔM) is infeasible — ΔM is kept, Tt yields:
  1. ΔM ← clip(ΔM, ±(C_L + C_R)) (the largest ΔM any Tt can realise);
  2. Tt ← clip(Tt, [max(−2C_R − ΔM, ΔM − 2C_L), min(2C_R − ΔM, ΔM + 2C_L)]).
  Why: ΔM is the stabilising command of a safety function; cutting drive/brake torque
  during an intervention is what an ESC does anyway, and less longitudinal force leaves the
  tyres more lateral grip. The MPC's ΔM box (``delta_m_capacity``) is the capacity at zero
  pedal torque, ±2·min(C_L, C_R), so with pedals released ΔM never forces a net torque.
  Whenever (Tt, ΔM) is feasible both pass unchanged, i.e. eq. 16 holds exactly.

Motor torque rate (``VehicleParams.torque_rate_nm_per_s`` > 0): every wheel torque moves at
most rate·``cycle_s`` per call from the torque of the previous call (the allocation runs once
per communication cycle, ``cycle_s``; the motor limit |T_i| ≤ Tlim_i has priority: a limit
that fell cuts at once); the realised (Tt, ΔM) are then those of the slewed torques, and
``rate_limited_calls`` counts the calls in which a wheel was held back.

Front/rear split on each side: proportional to the estimated normal loads (static load
plus longitudinal transfer m·ax·h/L and lateral transfer m·ay·h/wB, the latter shared
between the axles like the static loads). T_i ∝ Fz_i minimises Σ T_i² / Fz_i, the sum of
squared longitudinal tyre utilisations. A wheel over its limit is saturated and the rest
moves to the other wheel of that side (always possible since |T_side| ≤ C_side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.core.config_schema import ConfigError, build_section, require_positive
from controller.core.params import VehicleParams

G = 9.81


@dataclass(slots=True)
class AllocationConfig:
    """split: "normal_load" or "equal". fz_floor_frac: floor of a wheel's load estimate as
    a fraction of its static load, -. acc_clip: |ax|, |ay| used for the load estimate are
    clipped to this, m/s². cycle_s: time between two allocations (the node's communication
    cycle), s: the motor torque-rate limit allows rate × cycle_s per call."""

    split: str = "normal_load"
    fz_floor_frac: float = 0.05
    acc_clip: float = 12.0
    cycle_s: float = 0.01

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AllocationConfig:
        """Build from the [allocation] table; unknown keys and wrong types raise ConfigError."""
        cfg = build_section(cls, d, "allocation")
        if cfg.split not in ("normal_load", "equal"):
            raise ConfigError("allocation", "split", "must be 'normal_load' or 'equal'")
        require_positive(cfg, "allocation", ("cycle_s",))
        return cfg


def _finite_or(v: float, default: float) -> float:
    return v if math.isfinite(v) else default


class TorqueAllocator:
    """Pure allocation with a preallocated output; see the module docstring."""

    def __init__(self, params: VehicleParams, cfg: AllocationConfig | None = None,
                 dtype: type = np.float64) -> None:
        """dtype: precision of the limits and the torques."""
        self.p = params
        self.cfg = cfg or AllocationConfig()
        self.dtype = dtype
        L = params.wheelbase_m
        self._fzf_static = params.mass_kg * G * params.lr_m / L  # front axle, N
        self._fzr_static = params.mass_kg * G * params.lf_m / L
        self.limits = np.full(4, params.peak_torque_nm, dtype)  # N·m, last computed
        self.out = np.zeros(4, dtype)
        self.tt_applied = 0.0
        self.dm_applied = 0.0
        self.rate_step = params.torque_rate_nm_per_s * self.cfg.cycle_s   # N·m per call
        self.prev = np.zeros(4, dtype)   # torques of the previous call, N·m
        self.rate_limited_calls = 0

    def reset(self) -> None:
        """Forget the previous torques (the motors start from zero) and the counter."""
        self.prev[:] = 0.0
        self.out[:] = 0.0
        self.rate_limited_calls = 0

    def motor_limits(self, wheel_speeds: np.ndarray) -> np.ndarray:
        """Per-motor torque limits (4,) N·m at the wheel speeds (4,) rad/s (in self.limits)."""
        tp, pp = self.p.peak_torque_nm, self.p.peak_power_w
        lim = self.limits
        for i in range(4):
            w = abs(float(wheel_speeds[i]))
            lim[i] = min(tp, pp / w) if (math.isfinite(w) and w > 0.0) else tp
        return lim

    def delta_m_capacity(self, wheel_speeds: np.ndarray) -> float:
        """|ΔM| available at zero pedal torque, N·m: 2·min(C_L, C_R)."""
        lim = self.motor_limits(wheel_speeds)
        return 2.0 * min(lim[0] + lim[2], lim[1] + lim[3])

    def front_share(self, ax: float, ay: float) -> tuple[float, float]:
        """Front share of the left and right side torque, from normal-load estimates."""
        if self.cfg.split == "equal":
            return 0.5, 0.5
        p, c = self.p, self.cfg
        ax = min(max(_finite_or(ax, 0.0), -c.acc_clip), c.acc_clip)
        ay = min(max(_finite_or(ay, 0.0), -c.acc_clip), c.acc_clip)
        L = p.wheelbase_m
        dlong = p.mass_kg * ax * p.cg_height_m / L            # N, rear gains under +ax
        fzf = self._fzf_static - dlong
        fzr = self._fzr_static + dlong
        dlat = p.mass_kg * ay * p.cg_height_m / p.track_m     # N, right gains under +ay
        dlf = dlat * p.lr_m / L
        dlr = dlat * p.lf_m / L
        ff, fr = c.fz_floor_frac * self._fzf_static / 2, c.fz_floor_frac * self._fzr_static / 2
        fz1 = max(fzf / 2 - dlf / 2, ff)
        fz2 = max(fzf / 2 + dlf / 2, ff)
        fz3 = max(fzr / 2 - dlr / 2, fr)
        fz4 = max(fzr / 2 + dlr / 2, fr)
        return fz1 / (fz1 + fz3), fz2 / (fz2 + fz4)

    def allocate(self, total_torque: float, delta_m: float, ax: float, ay: float,
                 wheel_speeds: np.ndarray, limits_current: bool = False) -> np.ndarray:
        """Wheel torques (4,) N·m for Tt N·m and ΔM N·m (view of self.out, reused).

        limits_current: self.limits were just computed for these wheel speeds (skip it).
        Sets self.tt_applied / self.dm_applied to the realised (Tt, ΔM)."""
        lim = self.limits if limits_current else self.motor_limits(wheel_speeds)
        cl = lim[0] + lim[2]
        cr = lim[1] + lim[3]
        dm = _finite_or(float(delta_m), 0.0)
        tt = _finite_or(float(total_torque), 0.0)
        dm = min(max(dm, -(cl + cr)), cl + cr)
        tt_lo = max(-2.0 * cr - dm, dm - 2.0 * cl)
        tt_hi = min(2.0 * cr - dm, dm + 2.0 * cl)
        tt = min(max(tt, tt_lo), tt_hi)
        t_left = 0.5 * (tt - dm)
        t_right = 0.5 * (tt + dm)
        # Rounding can put a side a hair over capacity at the corners; clamp it.
        t_left = min(max(t_left, -cl), cl)
        t_right = min(max(t_right, -cr), cr)
        sl, sr = self.front_share(ax, ay)
        out = self.out
        out[0], out[2] = self._split(t_left, sl, lim[0], lim[2])
        out[1], out[3] = self._split(t_right, sr, lim[1], lim[3])
        step = self.rate_step
        if step > 0.0:
            prev = self.prev
            held = False
            for i in range(4):
                # the motor limit first: a wheel over a limit that fell (power limit at a
                # higher wheel speed) is cut at once, whatever the rate
                lo = min(max(prev[i] - step, -lim[i]), lim[i])
                hi = max(min(prev[i] + step, lim[i]), -lim[i])
                v = out[i]
                if v > hi:
                    out[i], held = hi, True
                elif v < lo:
                    out[i], held = lo, True
                prev[i] = out[i]
            if held:
                self.rate_limited_calls += 1
                t_left = float(out[0]) + float(out[2])
                t_right = float(out[1]) + float(out[3])
        self.tt_applied = t_left + t_right
        self.dm_applied = t_right - t_left
        return out

    @staticmethod
    def _split(t_side: float, front: float, lim_f: float, lim_r: float) -> tuple[float, float]:
        """Split a side torque front/rear by share, saturating one wheel into the other."""
        tf = t_side * front
        if tf > lim_f:
            tf = lim_f
        elif tf < -lim_f:
            tf = -lim_f
        tr = t_side - tf
        if tr > lim_r:
            tr = lim_r
            tf = t_side - tr
        elif tr < -lim_r:
            tr = -lim_r
            tf = t_side - tr
        # Final clamp only matters at the rounding level (|t_side| ≤ lim_f + lim_r).
        tf = min(max(tf, -lim_f), lim_f)
        return tf, tr
