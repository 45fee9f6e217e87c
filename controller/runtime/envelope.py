"""Output safety envelope: the last guard on every wheel-torque answer (panda-style).

Independent of the optimiser and the allocator: it sees only the four commanded wheel
torques (N·m, FL FR RL RR), the measured wheel speeds (rad/s), one flag and its own
previous output, and for ANY floats (NaN, ±inf, huge, negative) returns torques that hold
the limits below. Limits in priority order (a higher one wins if two cannot both hold; such
a conflict is counted, and with the default parameters it cannot happen — see below):

1. finite: a non-finite command reads as 0 N·m (and is then rate-limited like any other);
2. motor limit: |T_i| ≤ L_i = min(T_peak, P_peak / |ω_i|), floored to the torque frame's
   resolution (0.5 N·m) so the encoded value holds it too. A non-finite ω_i gives T_peak,
   like the allocator: cutting one wheel on a broken speed signal would itself create a yaw
   moment, and the inverter enforces its own speed limit;
3. zero yaw moment when ``zero_dm`` (sensors invalid or stability function disabled):
   left = right on each axle (T1 = T2, T3 = T4, hence ΔM = 0 exactly), axle torques kept;
4. per-wheel rate: |T_i − T_prev,i| ≤ R·dt;
5. ΔM rate: |ΔM − ΔM_prev| ≤ D·dt on the lever ΔM = T2 + T4 − T1 − T3, with Tt kept;
6. total torque Tt = ΣT_i kept as far as 2–5 allow, then each wheel kept as close to its
   command as its side total allows.

Feasibility: the previous output always holds |T_prev,i| ≤ T_peak, so with R·dt ≥ T_peak the
rate window of every wheel contains 0, and with D·dt ≥ 4·T_peak (the largest possible |ΔM|)
the ΔM window contains 0; T = 0 then satisfies 2–5 at once, so they are never in conflict.
The defaults (envelope.toml, dt = 10 ms) are R = 60 kN·m/s (600 N·m per cycle) and D =
180 kN·m/s (1800 N·m per cycle).

A command already inside every limit passes bit-for-bit unchanged (the fast path), so the
envelope never perturbs normal control. ``apply`` writes into a caller array; the only
state is the counters (and a few preallocated scalars), so it is pure in its outputs.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from controller.core.config_schema import ConfigError, build_section


@dataclass(slots=True)
class EnvelopeConfig:
    """[envelope] table.

    torque_rate_nm_per_s: per-wheel |dT/dt| bound, N·m/s.
    delta_m_rate_nm_per_s: |dΔM/dt| bound on the yaw-moment lever, N·m/s.
    torque_quantum_nm: torque frame resolution the power limit is floored to, N·m (0 = off).
    clip_tol_nm: a change smaller than this is not counted as a clip, N·m.
    """

    torque_rate_nm_per_s: float = 60000.0
    delta_m_rate_nm_per_s: float = 180000.0
    torque_quantum_nm: float = 0.5
    clip_tol_nm: float = 1e-6

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EnvelopeConfig:
        """Build from the [envelope] table; unknown keys, wrong types and non-positive rates
        raise ConfigError."""
        cfg = build_section(cls, d, "envelope")
        for k in ("torque_rate_nm_per_s", "delta_m_rate_nm_per_s"):
            v = getattr(cfg, k)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError("envelope", k, f"must be finite and > 0, got {v}")
        for k in ("torque_quantum_nm", "clip_tol_nm"):
            v = getattr(cfg, k)
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError("envelope", k, f"must be finite and >= 0, got {v}")
        return cfg


def load_envelope_config(path: str | Path | None = None) -> EnvelopeConfig:
    """Read [envelope] from a TOML file (None → the packaged config/envelope.toml)."""
    if path is None:
        text = resources.files("controller").joinpath("config/envelope.toml").read_text()
    else:
        text = Path(path).read_text()
    return EnvelopeConfig.from_dict(tomllib.loads(text).get("envelope", {}))


@dataclass(slots=True)
class EnvelopeCounters:
    """How often each limit acted (wheel counts per wheel, step counts per call)."""

    steps: int = 0
    limited_steps: int = 0     # steps where 1, 2, 4 or 5 changed the command (FAULT bit 6)
    nonfinite_cmd: int = 0     # wheels: non-finite command → 0
    torque_limit: int = 0      # wheels: |T| > T_peak
    power_limit: int = 0       # wheels: T_peak ≥ |T| > P_peak/|ω|
    rate_limit: int = 0        # wheels: outside the per-wheel rate window
    dm_rate_limit: int = 0     # steps: commanded ΔM outside the ΔM rate window
    dm_zeroed: int = 0         # steps: zero_dm and the command was not axle-symmetric
    tt_reduced: int = 0        # steps: Tt could not be kept
    invalid_speed: int = 0     # wheels: non-finite ω → T_peak
    bad_prev: int = 0          # wheels: previous output non-finite or beyond T_peak
    conflicts: int = 0         # a lower-priority limit had to give way (never by default)


def _clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else (hi if v > hi else v)


class SafetyEnvelope:
    """Applies the envelope of the module docstring; one instance per node."""

    def __init__(self, cfg: EnvelopeConfig, peak_torque_nm: float, peak_power_w: float,
                 dt_s: float) -> None:
        if not (peak_torque_nm > 0.0 and peak_power_w > 0.0 and dt_s > 0.0):
            raise ValueError("envelope needs peak torque, peak power and dt > 0")
        self.cfg = cfg
        self.t_peak = float(peak_torque_nm)
        self.p_peak = float(peak_power_w)
        self.dt = float(dt_s)
        self.d_wheel = cfg.torque_rate_nm_per_s * self.dt   # N·m per call
        self.d_dm = cfg.delta_m_rate_nm_per_s * self.dt     # N·m per call
        self.counters = EnvelopeCounters()
        self.limits = np.full(4, self.t_peak)               # N·m, last computed L_i
        self.last_zeroed = False
        # Scratch lists (FL FR RL RR), reused: command, previous output, window bounds.
        self._cm = [0.0] * 4
        self._pv = [0.0] * 4
        self._lo = [0.0] * 4
        self._hi = [0.0] * 4

    @property
    def conflict_free(self) -> bool:
        """True when the parameters guarantee that limits 2–5 never conflict."""
        return self.d_wheel >= self.t_peak and self.d_dm >= 4.0 * self.t_peak

    def wheel_limit(self, omega: float) -> float:
        """min(T_peak, P_peak/|ω|) N·m, floored to the quantum; non-finite ω → T_peak."""
        tp = self.t_peak
        if not math.isfinite(omega):
            return tp
        w = abs(omega)
        if w * tp <= self.p_peak:   # multiplication: no overflow error for tiny ω
            return tp
        lim = self.p_peak / w
        q = self.cfg.torque_quantum_nm
        return math.floor(lim / q) * q if q > 0.0 else lim

    def apply(self, cmd: np.ndarray, wheel_speeds: np.ndarray, zero_dm: bool,
              prev: np.ndarray, out: np.ndarray) -> bool:
        """Envelope ``cmd`` (4,) N·m given ω (4,) rad/s and the previous output (4,) N·m.

        Writes (4,) N·m into ``out`` (may be ``cmd`` itself, not ``prev``). Returns True when
        a limit other than the zero-ΔM equalisation changed the command (FAULT_BITS bit 6).
        """
        c, tp = self.counters, self.t_peak
        c.steps += 1
        d, lim_arr = self.d_wheel, self.limits
        cm, pv, lo, hi = self._cm, self._pv, self._lo, self._hi
        acted = False   # a limit (not the zero-ΔM equalisation) changed something
        fast = True     # the command already holds every limit: pass it unchanged
        for i in range(4):
            w = float(wheel_speeds[i])
            if not math.isfinite(w):
                c.invalid_speed += 1
            L = self.wheel_limit(w)
            lim_arr[i] = L
            p = float(prev[i])
            if not math.isfinite(p):
                c.bad_prev += 1
                p = 0.0
            elif abs(p) > tp:
                c.bad_prev += 1
                p = math.copysign(tp, p)
            pv[i] = p
            t = float(cmd[i])
            if not math.isfinite(t):
                c.nonfinite_cmd += 1
                t, acted = 0.0, True
            elif abs(t) > tp:
                c.torque_limit += 1
                t, acted = math.copysign(tp, t), True
            elif abs(t) > L:
                c.power_limit += 1
                acted = True
            cm[i] = t
            a, b = max(-L, p - d), min(L, p + d)
            if a > b:  # rate window outside the motor limit: the motor limit wins
                c.conflicts += 1
                a = b = (L if p - d > L else -L)
            lo[i], hi[i] = a, b
            if t < a or t > b:
                fast = False
                if -L <= t <= L:
                    c.rate_limit += 1
                    acted = True
        dm_prev = (pv[1] - pv[0]) + (pv[3] - pv[2])  # per axle: exactly 0 when symmetric
        dm_c = (cm[1] - cm[0]) + (cm[3] - cm[2])
        tt_c = cm[0] + cm[1] + cm[2] + cm[3]
        self.last_zeroed = False
        dm_lo, dm_hi = dm_prev - self.d_dm, dm_prev + self.d_dm
        if zero_dm:
            if cm[0] != cm[1] or cm[2] != cm[3]:
                fast = False
                c.dm_zeroed += 1
                self.last_zeroed = True
            if abs(dm_prev) > self.d_dm:
                c.conflicts += 1  # ΔM = 0 wins over the ΔM rate
        elif dm_c < dm_lo or dm_c > dm_hi:
            fast = False
            c.dm_rate_limit += 1
            acted = True
        if fast:
            for i in range(4):
                out[i] = cm[i]
        elif zero_dm:
            self._symmetric(cm, lo, hi, tt_c, out)
        else:
            self._lever(cm, lo, hi, tt_c, _clip(dm_c, dm_lo, dm_hi), dm_lo, dm_hi, out)
        if abs(float(out[0] + out[1] + out[2] + out[3]) - tt_c) > self.cfg.clip_tol_nm:
            c.tt_reduced += 1
            acted = True
        if acted:
            c.limited_steps += 1
        return acted

    def _symmetric(self, cm: list[float], lo: list[float], hi: list[float], tt: float,
                   out: np.ndarray) -> None:
        """Zero ΔM: one torque per axle inside both wheels' windows, Tt kept if possible."""
        f_lo, f_hi = self._pair_window(0, 1, lo, hi)
        r_lo, r_hi = self._pair_window(2, 3, lo, hi)
        f = _clip(0.5 * (cm[0] + cm[1]), f_lo, f_hi)
        r = _clip(0.5 * tt - f, r_lo, r_hi)
        f = _clip(0.5 * tt - r, f_lo, f_hi)  # the front takes what the rear could not
        out[0] = out[1] = f
        out[2] = out[3] = r

    def _pair_window(self, a: int, b: int, lo: list[float], hi: list[float]
                     ) -> tuple[float, float]:
        """Common window of wheels a and b; if their rate windows do not overlap the
        symmetric point nearest both (within the motor limits) wins: a counted conflict."""
        w_lo, w_hi = max(lo[a], lo[b]), min(hi[a], hi[b])
        if w_lo <= w_hi:
            return w_lo, w_hi
        self.counters.conflicts += 1
        lim = min(float(self.limits[a]), float(self.limits[b]))
        x = _clip(0.5 * (w_lo + w_hi), -lim, lim)
        lo[a] = lo[b] = hi[a] = hi[b] = x
        return x, x

    def _lever(self, cm: list[float], lo: list[float], hi: list[float], tt: float,
               dm_t: float, dm_lo: float, dm_hi: float, out: np.ndarray) -> None:
        """ΔM as close to dm_t as the windows allow, then Tt, then each wheel."""
        lo_l, hi_l = lo[0] + lo[2], hi[0] + hi[2]
        lo_r, hi_r = lo[1] + lo[3], hi[1] + hi[3]
        dm_min, dm_max = lo_r - hi_l, hi_r - lo_l
        if dm_t < dm_min or dm_t > dm_max:
            dm_t = _clip(dm_t, dm_min, dm_max)
            if dm_t < dm_lo or dm_t > dm_hi:
                self.counters.conflicts += 1  # the wheel windows win over the ΔM rate
        s_lo, s_hi = max(lo_l, lo_r - dm_t), min(hi_l, hi_r - dm_t)
        if s_lo > s_hi:  # only by rounding at a corner
            s_lo = s_hi = 0.5 * (s_lo + s_hi)
        s_left = _clip(0.5 * (tt - dm_t), s_lo, s_hi)
        s_right = s_left + dm_t
        self._side(s_left, cm, lo, hi, 0, 2, out)
        self._side(s_right, cm, lo, hi, 1, 3, out)

    @staticmethod
    def _side(s: float, cm: list[float], lo: list[float], hi: list[float], a: int, b: int,
              out: np.ndarray) -> None:
        """Wheels a, b summing to s within their windows, nearest to their commands in the
        least-squares sense (an equal shift of both, then the window of each)."""
        xa = _clip(cm[a] + 0.5 * (s - cm[a] - cm[b]), lo[a], hi[a])
        xb = _clip(s - xa, lo[b], hi[b])
        xa = _clip(s - xb, lo[a], hi[a])
        out[a], out[b] = xa, xb
