"""FMVSS 126 / UN R140 electronic-stability-control test evaluation (pure, from trace arrays).

* :func:`find_a_deg` — A, the steering-wheel angle (deg) that produces 0.3 g in the slowly
  increasing steer (SIS) test: linear regression of |SWA| on |ay| over 0.1 g .. 0.375 g
  (the standard fits the data around 0.3 g; 49 CFR 571.126 S7.6), evaluated at 0.3 g.
* :func:`amplitude_schedule_deg` — sine-with-dwell amplitudes 1.5A, 2.0A, ... 6.5A, each
  capped at 270 deg (the project's rule). ``standard_rule=True`` gives the regulation's final
  amplitude instead: the greater of 6.5A and 270 deg, but at most 300 deg.
* :func:`evaluate_sine_with_dwell` — beginning of steer (BOS, |SWA| first reaches 5 deg in the
  initial direction), completion of steer (COS, SWA returns to zero after the dwell), the first
  yaw-rate peak after the first steering reversal, yaw-rate ratios at COS + 1.00 s (pass
  <= 35 %) and COS + 1.75 s (pass <= 20 %), and the lateral displacement of the CG from its
  initial straight path at BOS + 1.07 s (pass >= 1.83 m for GVWR <= 3 500 kg; only required for
  amplitudes >= 5A).

Units: time s, angles deg (SWA) or rad (yaw), yaw rate rad/s or any consistent unit (only
ratios are used), positions m, accelerations m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

G = 9.80665  # m/s^2, standard gravity (the regulation's g)
YRR_1S_LIMIT = 0.35
YRR_175S_LIMIT = 0.20
LATERAL_DISPLACEMENT_LIMIT_M = 1.83  # GVWR <= 3 500 kg
BOS_THRESHOLD_DEG = 5.0


@dataclass(frozen=True, slots=True)
class SineWithDwellResult:
    """Outcome of one sine-with-dwell run.

    t_bos_s, t_cos_s: beginning / completion of steer, s. peak_yaw_rate: first peak after
    the first reversal (same unit as the input, signed). yrr_1s, yrr_175s: yaw-rate ratios
    (fractions, not %). lateral_displacement_m: at BOS + 1.07 s, positive in the direction of
    the first steering lobe, m. The ratios are signed (a yaw rate that has already reversed
    gives a negative ratio, which passes, as in the regulation). lateral_required: the
    displacement criterion applies (amplitude >= 5A, or A unknown). pass_*: the individual
    criteria; passed: all that apply.
    """

    t_bos_s: float
    t_cos_s: float
    peak_yaw_rate: float
    yrr_1s: float
    yrr_175s: float
    lateral_displacement_m: float
    lateral_required: bool
    pass_yrr_1s: bool
    pass_yrr_175s: bool
    pass_lateral: bool

    @property
    def passed(self) -> bool:
        """All applicable criteria met."""
        return self.pass_yrr_1s and self.pass_yrr_175s and (
            self.pass_lateral or not self.lateral_required)


def find_a_deg(swa_deg: np.ndarray, ay_mps2: np.ndarray, lo_g: float = 0.1,
               hi_g: float = 0.375, at_g: float = 0.3) -> float:
    """A (deg): SWA at ``at_g`` from a linear fit |SWA| = c0 + c1 |ay| over lo_g..hi_g.

    Only the monotone rising part of the SIS run is used (samples up to the first time |ay|
    exceeds ``hi_g``). Raises ValueError if the run never reaches ``hi_g``.
    """
    swa = np.abs(np.asarray(swa_deg, dtype=float))
    ay = np.abs(np.asarray(ay_mps2, dtype=float)) / G
    over = np.nonzero(ay > hi_g)[0]
    if len(over) == 0:
        raise ValueError(f"SIS run never reaches {hi_g} g (max {ay.max():.3f} g)")
    end = over[0]
    sel = (ay[:end] >= lo_g) & (ay[:end] <= hi_g)
    if sel.sum() < 3:
        raise ValueError("too few SIS samples between the regression limits")
    c1, c0 = np.polyfit(ay[:end][sel], swa[:end][sel], 1)
    return float(c0 + c1 * at_g)


def amplitude_schedule_deg(a_deg: float, cap_deg: float = 270.0,
                           standard_rule: bool = False) -> list[float]:
    """Sine-with-dwell amplitudes (deg): 1.5A ... 6.5A in 0.5A steps (see module docstring)."""
    if a_deg <= 0:
        raise ValueError("A must be positive")
    steps = [a_deg * (1.5 + 0.5 * k) for k in range(11)]  # 1.5A .. 6.5A
    if not standard_rule:
        out: list[float] = []
        for amp in steps:
            amp = min(amp, cap_deg)
            if not out or amp > out[-1] + 1e-9:
                out.append(amp)
        return out
    final = min(max(6.5 * a_deg, 270.0), 300.0)
    out = [amp for amp in steps if amp < final - 1e-9]
    return [*out, final]


def _interp_at(t: np.ndarray, v: np.ndarray, t_query: float) -> float:
    if t_query > t[-1] or t_query < t[0]:
        return math.nan
    return float(np.interp(t_query, t, v))


def evaluate_sine_with_dwell(
    t_s: np.ndarray, swa_deg: np.ndarray, yaw_rate: np.ndarray, x_m: np.ndarray,
    y_m: np.ndarray, yaw_rad: np.ndarray, amplitude_deg: float | None = None,
    a_deg: float | None = None,
) -> SineWithDwellResult:
    """Evaluate a sine-with-dwell trace (arrays sampled on a common time base ``t_s``)."""
    t = np.asarray(t_s, dtype=float)
    swa = np.asarray(swa_deg, dtype=float)
    r = np.asarray(yaw_rate, dtype=float)
    # initial direction = sign of the first sample beyond the BOS threshold
    beyond = np.nonzero(np.abs(swa) >= BOS_THRESHOLD_DEG)[0]
    if len(beyond) == 0:
        raise ValueError("steering never exceeds the 5 deg BOS threshold")
    i_bos = int(beyond[0])
    s1 = 1.0 if swa[i_bos] > 0 else -1.0
    # BOS by interpolation of the threshold crossing
    if i_bos > 0:
        a0, a1 = s1 * swa[i_bos - 1], s1 * swa[i_bos]
        f = (BOS_THRESHOLD_DEG - a0) / (a1 - a0) if a1 != a0 else 0.0
        t_bos = float(t[i_bos - 1] + f * (t[i_bos] - t[i_bos - 1]))
    else:
        t_bos = float(t[0])
    # first reversal: SWA crosses zero into the second lobe
    after = np.nonzero((s1 * swa[i_bos:]) < 0.0)[0]
    if len(after) == 0:
        raise ValueError("no steering reversal found")
    i_rev = i_bos + int(after[0])
    # second lobe peak (dwell) and completion of steer: back to zero after it
    i_pk2 = i_rev + int(np.argmin(s1 * swa[i_rev:]))
    tail = np.nonzero((s1 * swa[i_pk2:]) >= 0.0)[0]
    if len(tail) == 0:
        raise ValueError("steering does not return to zero (no completion of steer)")
    i_cos = i_pk2 + int(tail[0])
    a0, a1 = s1 * swa[i_cos - 1], s1 * swa[i_cos]
    f = (0.0 - a0) / (a1 - a0) if a1 != a0 else 0.0
    t_cos = float(t[i_cos - 1] + f * (t[i_cos] - t[i_cos - 1]))
    # first local peak of the yaw rate in the second-lobe direction after the reversal
    seg = -s1 * r[i_rev:]
    i_peak = None
    for k in range(1, len(seg) - 1):
        if seg[k] > 0.0 and seg[k] >= seg[k - 1] and seg[k] > seg[k + 1]:
            i_peak = i_rev + k
            break
    if i_peak is None:
        i_peak = i_rev + int(np.argmax(seg))
    peak = float(r[i_peak])
    r1 = _interp_at(t, r, t_cos + 1.0)
    r175 = _interp_at(t, r, t_cos + 1.75)
    yrr1 = r1 / peak if peak != 0.0 else math.inf
    yrr175 = r175 / peak if peak != 0.0 else math.inf
    # lateral displacement from the straight path held at BOS (heading at BOS)
    x0 = _interp_at(t, np.asarray(x_m, float), t_bos)
    y0 = _interp_at(t, np.asarray(y_m, float), t_bos)
    psi0 = _interp_at(t, np.asarray(yaw_rad, float), t_bos)
    x1 = _interp_at(t, np.asarray(x_m, float), t_bos + 1.07)
    y1 = _interp_at(t, np.asarray(y_m, float), t_bos + 1.07)
    lat = s1 * (-(x1 - x0) * math.sin(psi0) + (y1 - y0) * math.cos(psi0))
    lateral_required = True
    if amplitude_deg is not None and a_deg is not None:
        lateral_required = amplitude_deg >= 5.0 * a_deg - 1e-9
    return SineWithDwellResult(
        t_bos_s=t_bos, t_cos_s=t_cos, peak_yaw_rate=peak, yrr_1s=yrr1, yrr_175s=yrr175,
        lateral_displacement_m=lat, lateral_required=lateral_required,
        pass_yrr_1s=bool(yrr1 <= YRR_1S_LIMIT) if math.isfinite(yrr1) else False,
        pass_yrr_175s=bool(yrr175 <= YRR_175S_LIMIT) if math.isfinite(yrr175) else False,
        pass_lateral=bool(lat >= LATERAL_DISPLACEMENT_LIMIT_M) if math.isfinite(lat) else False,
    )
