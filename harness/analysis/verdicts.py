"""Two verdicts per lane-change run (issue 12, DESIGN §9): *stable* and *course*.

A DLC probe used to pass on one rule only (the paper's: CG within 1.0 m of the lane centre
and |β| ≤ 8°), which measures lane-centre tracking at the grip limit, not stability. The
verdicts here separate the two, over the window [0, course end + 2 s]:

* **stable**: no spin, max |β| ≤ ``beta_limit_deg`` (8°), and the yaw rate settles *to the
  path*: over the last ``SETTLE_WINDOW_S`` of the window, the mean |ωr − ay/Vx| (= |β̇| by
  the planar identity V̇y = ay − ωr·Vx: the rotation the car's path does not explain) is
  ≤ ``settle_ratio`` × the window's peak |ωr| (35 %, the FMVSS 126 lateral-stability
  ratio). A car still steering back to its lane turns with its path and passes; a car
  rotating away from its path (a beginning spin) fails. The former rule compared |ωr| itself
  with its peak and failed stable cars whose driver was still steering back after a wide exit
  (measured: nmpc-rhonn dlc-paper 88 km/h, |β| 4.1°, ratio 0.39); it is still reported as
  ``yaw_settle_ratio``.
* **course** (ISO 3888 style): the vehicle's *footprint* — a rectangle of the body width b
  and the overall length (lf + lr + overhangs, :data:`FRONT_OVERHANG_M`,
  :data:`REAR_OVERHANG_M`) around the CG, aligned with the yaw angle — must not touch a cone
  (cones as points at their layout positions; ``cones_hit`` counts the distinct cones the
  footprint ever covered) and its four corners must stay inside every gated lane section
  while they are in its x range (``gate_exits``: samples with a corner outside). course
  passes when both are 0 and the car did not spin.
* **paper** (Table 4 reproduction): ``passed_dlc`` of harness.analysis.kpi (1.0 m, 8°).

Inputs are the plant truth arrays (10 ms rows): t s, x m, y m, yaw rad, β rad, ωr rad/s,
lateral deviation m, spun flag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

FRONT_OVERHANG_M = 0.95   # chosen: bumper ahead of the front axle, mid-size SUV, m
REAR_OVERHANG_M = 1.05    # chosen: bumper behind the rear axle, m
AFTER_COURSE_S = 2.0
BETA_LIMIT_DEG = 8.0
SETTLE_RATIO = 0.35
SETTLE_WINDOW_S = 0.5   # s, averaging window of the sideslip-rate settle test
PAPER_DEV_M = 1.0


@dataclass(frozen=True)
class Footprint:
    """Body rectangle about the CG, m: ahead (front), behind (rear), half width."""

    front_m: float
    rear_m: float
    half_width_m: float

    @classmethod
    def for_vehicle(cls, lf_m: float, lr_m: float, width_m: float) -> Footprint:
        """Footprint from the axle distances and body width, m (overhangs added)."""
        return cls(lf_m + FRONT_OVERHANG_M, lr_m + REAR_OVERHANG_M, 0.5 * width_m)

    def corners(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """(T, 4, 2) world corner positions, m."""
        c, s = np.cos(yaw), np.sin(yaw)
        local = np.array([[self.front_m, self.half_width_m], [self.front_m, -self.half_width_m],
                          [-self.rear_m, -self.half_width_m], [-self.rear_m, self.half_width_m]])
        cx = x[:, None] + c[:, None] * local[None, :, 0] - s[:, None] * local[None, :, 1]
        cy = y[:, None] + s[:, None] * local[None, :, 0] + c[:, None] * local[None, :, 1]
        return np.stack([cx, cy], axis=-1)


def cones_hit(fp: Footprint, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
              cones: np.ndarray) -> int:
    """Number of distinct cones (N, 2) m ever inside the footprint."""
    if cones.size == 0 or x.size == 0:
        return 0
    dx = cones[None, :, 0] - x[:, None]
    dy = cones[None, :, 1] - y[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    inside = (lx <= fp.front_m) & (lx >= -fp.rear_m) & (np.abs(ly) <= fp.half_width_m)
    return int(np.count_nonzero(inside.any(axis=0)))


def gate_exits(fp: Footprint, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
               lanes: list[Any]) -> int:
    """Samples where a footprint corner is inside a gated section's x range but outside its
    y range (lanes: objects with x0, x1, y_right, y_left in m)."""
    if not lanes or x.size == 0:
        return 0
    corners = fp.corners(x, y, yaw)
    cx, cy = corners[..., 0], corners[..., 1]
    bad = np.zeros(x.size, dtype=bool)
    for ln in lanes:
        in_x = (cx >= ln.x0) & (cx <= ln.x1)
        out_y = (cy < ln.y_right) | (cy > ln.y_left)
        bad |= np.any(in_x & out_y, axis=1)
    return int(np.count_nonzero(bad))


def window_mask(t: np.ndarray, path_s: np.ndarray, course_end_arc_m: float | None
                ) -> tuple[np.ndarray, bool]:
    """Rows of the verdict window [0, course end + 2 s] and whether the trace covers it."""
    if course_end_arc_m is None or path_s.size != t.size:
        return np.ones(t.size, dtype=bool), True
    hit = np.flatnonzero(path_s >= course_end_arc_m)
    if hit.size == 0:
        return np.ones(t.size, dtype=bool), False
    t_end = float(t[hit[0]]) + AFTER_COURSE_S
    return t <= t_end + 1e-9, bool(t[-1] >= t_end - 0.015)


def _sideslip_rate_ratio(truth: dict[str, np.ndarray], w: np.ndarray, t: np.ndarray,
                         peak_r: float) -> float:
    """Mean |ωr − ay/Vx| (rad/s) over the last SETTLE_WINDOW_S of the window ``w``, divided
    by the window's peak |ωr| rad/s (0 when the car never turned)."""
    if peak_r <= 1e-6 or not np.any(w):
        return 0.0
    tw = t[w]
    last = tw >= tw[-1] - SETTLE_WINDOW_S - 1e-9
    r = np.asarray(truth["yaw_rate_radps"], dtype=float)[w][last]
    ay = np.asarray(truth["ay_mps2"], dtype=float)[w][last]
    vx = np.maximum(np.asarray(truth["vx_mps"], dtype=float)[w][last], 1.0)
    return float(np.mean(np.abs(r - ay / vx)) / peak_r)


def dlc_verdicts(truth: dict[str, np.ndarray], *, cones: np.ndarray, lanes: list[Any],
                 course_end_arc_m: float | None, footprint: Footprint) -> dict[str, Any]:
    """Verdicts and their numbers for one run (see the module docstring).

    Keys: stable, course, paper (bools); max_abs_beta_deg, max_abs_dev_m, cones_hit,
    gate_exits, yaw_settle_ratio, sideslip_rate_ratio, spun, covered."""
    t = np.asarray(truth["t_s"], dtype=float)
    w, covered = window_mask(t, np.asarray(truth.get("path_s_m", np.zeros(0))),
                             course_end_arc_m)
    x, y, yaw = (np.asarray(truth[k], dtype=float)[w] for k in ("x_m", "y_m", "yaw_rad"))
    beta = np.asarray(truth["beta_rad"], dtype=float)[w]
    r = np.asarray(truth["yaw_rate_radps"], dtype=float)[w]
    dev = np.asarray(truth["lateral_dev_m"], dtype=float)[w]
    spun = bool(np.any(np.asarray(truth["spun"])[w] > 0.5))
    max_beta = float(np.degrees(np.max(np.abs(beta)))) if beta.size else math.inf
    max_dev = float(np.max(np.abs(dev))) if dev.size else math.inf
    peak_r = float(np.max(np.abs(r))) if r.size else 0.0
    settle = float(abs(r[-1]) / peak_r) if r.size and peak_r > 1e-6 else 0.0
    slip_rate = _sideslip_rate_ratio(truth, w, t, peak_r)
    n_cones = cones_hit(footprint, x, y, yaw, np.asarray(cones, dtype=float).reshape(-1, 2))
    n_exits = gate_exits(footprint, x, y, yaw, lanes)
    stable = (covered and not spun and max_beta <= BETA_LIMIT_DEG
              and slip_rate <= SETTLE_RATIO)
    return {
        "stable": bool(stable),
        "course": bool(covered and not spun and n_cones == 0 and n_exits == 0),
        "paper": bool(covered and not spun and max_beta <= BETA_LIMIT_DEG
                      and max_dev <= PAPER_DEV_M),
        "max_abs_beta_deg": max_beta, "max_abs_dev_m": max_dev, "cones_hit": n_cones,
        "gate_exits": n_exits, "yaw_settle_ratio": settle,
        "sideslip_rate_ratio": slip_rate, "spun": spun,
        "covered": covered,
    }
