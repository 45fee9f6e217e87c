"""KPIs of a run in which the road or the car changes: the response to a friction step and
the time the learned model needs to re-learn.

Definitions (truth = the plant's truth trace, one row per 10 ms cycle; t_step = the time of
the road's friction step, s):

* ``yaw_overshoot_degps``: how far the yaw rate rises above its steady value after the
  step, in the turning direction: s·max(r) over [t_step, t_step + window] − s·mean(r) over
  the ``pre_s`` before the step, s = the sign of that mean (deg/s; ≤ 0 when the yaw rate
  never rises, e.g. a car that only understeers). A corner held at constant speed and
  radius needs the same yaw rate before and after the step, so any rise is the car turning
  in harder than the road asks (oversteer), the quantity an ESC exists to stop.
* ``yaw_undershoot_degps``: the fall below the steady value (s·mean − s·min, deg/s).
* ``max_abs_beta_after_deg``, ``max_abs_dev_after_m``: over the same window.
* ``relearn_time_s``: the settling time of the learned model's filtered RMS one-step
  yaw-rate prediction error e(t) (rad/s, the confidence gate's signal): the steady band is
  ``band_factor`` × the median of e over the ``pre_s`` before the step (at least
  ``band_floor`` rad/s); the re-learning time is the time from the step to the last cycle
  at which e was above the band, within the window (0 when e never left the band; None
  when e is still above the band at the end of the window, or no model error is recorded).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

WINDOW_S = 5.0        # analysis window after the step, s
PRE_S = 1.0           # steady reference before the step, s
BAND_FACTOR = 1.5     # steady band of the model error = factor × its pre-step median, -
BAND_FLOOR = 0.002    # lowest steady band, rad/s (the converged error is 0.002–0.005)


def _window(t: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (t >= lo - 1e-9) & (t <= hi + 1e-9)


def step_response(truth: dict[str, np.ndarray], t_step_s: float, window_s: float = WINDOW_S,
                  pre_s: float = PRE_S) -> dict[str, float | None]:
    """Yaw overshoot / undershoot (deg/s), max |β| (deg) and max |lateral dev| (m) after a
    step at ``t_step_s`` s (see the module docstring)."""
    t = np.asarray(truth["t_s"], dtype=float)
    r = np.degrees(np.asarray(truth["yaw_rate_radps"], dtype=float))
    pre = _window(t, t_step_s - pre_s, t_step_s)
    post = _window(t, t_step_s, t_step_s + window_s)
    if not pre.any() or not post.any():
        return {"yaw_overshoot_degps": None, "yaw_undershoot_degps": None,
                "max_abs_beta_after_deg": None, "max_abs_dev_after_m": None}
    r_pre = float(np.mean(r[pre]))
    s = 1.0 if r_pre >= 0.0 else -1.0
    rp = s * r[post]
    return {
        "yaw_pre_degps": abs(r_pre),
        "yaw_overshoot_degps": float(np.max(rp) - abs(r_pre)),
        "yaw_undershoot_degps": float(abs(r_pre) - np.min(rp)),
        "max_abs_beta_after_deg": float(np.degrees(np.max(np.abs(truth["beta_rad"][post])))),
        "max_abs_dev_after_m": float(np.max(np.abs(truth["lateral_dev_m"][post]))),
    }


def relearn_time(t_s: np.ndarray, err_rms: np.ndarray, t_step_s: float,
                 window_s: float = WINDOW_S, pre_s: float = PRE_S,
                 band_factor: float = BAND_FACTOR, band_floor: float = BAND_FLOOR
                 ) -> dict[str, float | None]:
    """Re-learning time, s, of the model error ``err_rms`` (rad/s, sampled at ``t_s`` s)
    after a change at ``t_step_s`` (see the module docstring), with the band (rad/s) and the
    error's peak after the step (rad/s)."""
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(err_rms, dtype=float)
    pre = _window(t, t_step_s - pre_s, t_step_s) & np.isfinite(e)
    post = _window(t, t_step_s, t_step_s + window_s) & np.isfinite(e)
    if not pre.any() or not post.any():
        return {"relearn_time_s": None, "err_band_radps": None, "err_peak_radps": None}
    band = max(band_factor * float(np.median(e[pre])), band_floor)
    tp, ep = t[post], e[post]
    above = np.flatnonzero(ep > band)
    if above.size == 0:
        settle: float | None = 0.0
    elif above[-1] == ep.size - 1:
        settle = None                              # not back in the band within the window
    else:
        settle = float(tp[above[-1] + 1] - t_step_s)
    return {"relearn_time_s": settle, "err_band_radps": band,
            "err_peak_radps": float(np.max(ep))}


def adaptation_kpis(truth: dict[str, np.ndarray], t_step_s: float,
                    err_rms: np.ndarray | None = None) -> dict[str, Any]:
    """step_response() and, when the learned model's error trace (rad/s, one value per
    truth row; NaN where there is none) is given, relearn_time()."""
    out: dict[str, Any] = dict(step_response(truth, t_step_s))
    if err_rms is not None and np.isfinite(err_rms).any():
        out.update(relearn_time(truth["t_s"], err_rms, t_step_s))
    else:
        out.update({"relearn_time_s": None, "err_band_radps": None, "err_peak_radps": None})
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in out.items()}
