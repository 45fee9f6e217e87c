"""The verdicts of a run: *paper rule*, *course rule (cones)* and *stable*.

These three names are the only verdict words of metrics.json (``verdicts`` block, see
:func:`verdict_block`), the KPI table, the plots and the rerun view. The paper's rule (CG
within 1.0 m of the lane centre and |β| ≤ 8°) measures lane-centre tracking at the grip
limit, not stability, so the stable and course verdicts judge those separately, over the
window [0, course end + 2 s]:

* **stable**: no spin, max |β| ≤ ``beta_limit_deg`` (8°), and the yaw rate settles *to the
  path*: over the last ``SETTLE_WINDOW_S`` of the window, the mean |ωr − ay/Vx| (= |β̇| by
  the planar identity V̇y = ay − ωr·Vx: the rotation the car's path does not explain) is
  ≤ ``settle_ratio`` × the window's peak |ωr| (35 %, the FMVSS 126 lateral-stability
  ratio). A car still steering back to its lane turns with its path and passes; a car
  rotating away from its path (a beginning spin) fails. Comparing |ωr| itself with its peak
  would fail stable cars whose driver is still steering back after a wide exit (measured:
  nmpc-rhonn dlc-paper 88 km/h, |β| 4.1°, ratio 0.39); that ratio is reported as
  ``yaw_settle_ratio``.
* **course** (ISO 3888 style): the vehicle's *footprint* (harness/analysis/footprint.py: a
  rectangle of the body width b and the overall length lf + lr + overhangs around the CG,
  aligned with the yaw angle; the same one the plots draw) must not touch a cone
  (cones as points at their layout positions; ``cones_hit`` counts the distinct cones the
  footprint ever covered) and its four corners must stay inside every gated lane section
  while they are in its x range (``gate_exits``: samples with a corner outside). course
  passes when both are 0 and the car did not spin.
* **paper** (Table 4 reproduction): ``passed_dlc`` of harness.analysis.kpi (1.0 m, 8°).

A scenario without cones has no paper or course rule (``passed`` null); its stable window is
the whole run. A trace that ends before its window closes (an interrupted or shortened run)
gives null unless a failure is already seen (a spin, |β| > 8°, a struck cone).

Inputs are the plant truth arrays (10 ms rows): t s, x m, y m, yaw rad, β rad, ωr rad/s,
lateral deviation m, spun flag.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from harness.analysis.footprint import Footprint, packaged_footprint, struck_cones

AFTER_COURSE_S = 2.0
BETA_LIMIT_DEG = 8.0
SETTLE_RATIO = 0.35
SETTLE_WINDOW_S = 0.5   # s, averaging window of the sideslip-rate settle test
PAPER_DEV_M = 1.0


def cones_hit(fp: Footprint, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
              cones: np.ndarray) -> int:
    """Number of distinct cones (N, 2) m ever inside the footprint."""
    return int(np.count_nonzero(struck_cones(x, y, yaw, cones, fp)))


def gate_exits(fp: Footprint, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
               lanes: list[Any]) -> int:
    """Samples where a footprint corner is inside a gated section's x range but outside its
    y range (lanes: objects with x0, x1, y_right, y_left in m)."""
    if not lanes or x.size == 0:
        return 0
    corners = fp.corners_over_time(x, y, yaw)
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


# --------------------------------------------------------------- the verdict block of a run
#: The three verdict names used by metrics.json, the KPI table, the plots and the rerun view.
VERDICT_NAMES = ("paper_rule", "course_rule", "stable")
#: How each verdict is shown to a user (KPI table rows, plot titles).
VERDICT_LABELS = {"paper_rule": "paper rule", "course_rule": "course rule (cones)",
                  "stable": "stable"}
PAPER_RULE = (f"no spin, max |β| ≤ {BETA_LIMIT_DEG:g}° and max |lateral deviation| ≤ "
              f"{PAPER_DEV_M:g} m from the start to {AFTER_COURSE_S:g} s after the course end "
              "(paper Table 4)")
COURSE_RULE = ("ISO 3888: the body footprint strikes no cone and its corners stay inside every "
               f"gated lane section, no spin, to {AFTER_COURSE_S:g} s after the course end")
STABLE_RULE = (f"no spin, max |β| ≤ {BETA_LIMIT_DEG:g}°, and over the last "
               f"{SETTLE_WINDOW_S:g} s mean |ωr − ay/Vx| ≤ {SETTLE_RATIO:.0%} of the peak "
               f"|ωr|; window: to {AFTER_COURSE_S:g} s after the course end (whole run "
               "without a course)")
NOT_COVERED = "not judged: the run ended before the verdict window closed; rule: "
#: Truth columns the verdicts read.
TRUTH_KEYS = ("t_s", "x_m", "y_m", "yaw_rad", "beta_rad", "yaw_rate_radps", "lateral_dev_m",
              "spun", "path_s_m", "ay_mps2", "vx_mps")


def has_course(cones: np.ndarray | None, lanes: list[Any] | None) -> bool:
    """The scenario is a lane-change course (cones and gated lanes): paper and course rules
    apply."""
    return bool(lanes) and cones is not None and np.asarray(cones).size > 0


def _judged(passed: bool, failed_on_seen: bool, covered: bool) -> bool | None:
    """Three-valued verdict: a failure seen in the part of the window the trace has is final;
    a pass needs the whole window; otherwise not judged (None)."""
    if passed:
        return True
    return False if failed_on_seen or covered else None


def _rule(text: str, judged: bool | None, covered: bool) -> str:
    return text if judged is not None or covered else NOT_COVERED + text


def window_struck(truth: Any, cones: np.ndarray | None, course_end_arc_m: float | None,
                  footprint: Footprint | None = None) -> np.ndarray | None:
    """Mask over ``cones`` (M, 2) m of the cones the footprint covered inside the verdict
    window (the count of the ``course_rule`` block and the red crosses of the trajectory
    plot). ``truth``: RunData or a column dict; None without cones or a trace."""
    col = truth.truth_col if hasattr(truth, "truth_col") else (
        lambda k: np.asarray(truth.get(k, np.zeros(0)), dtype=float))
    t, x, y, yaw = (col(k) for k in ("t_s", "x_m", "y_m", "yaw_rad"))
    pts = np.asarray(cones if cones is not None else np.zeros((0, 2)), dtype=float)
    if pts.size == 0 or t.size == 0 or not t.size == x.size == y.size == yaw.size:
        return None
    w, _ = window_mask(t, col("path_s_m"), course_end_arc_m)
    return struck_cones(x[w], y[w], yaw[w], pts.reshape(-1, 2),
                        footprint if footprint is not None else packaged_footprint())


def verdict_block(truth: Any, *, cones: np.ndarray | None, lanes: list[Any] | None,
                  course_end_arc_m: float | None, planned_end_s: float | None = None,
                  footprint: Footprint | None = None, dt_s: float = 0.01) -> dict[str, Any]:
    """The ``verdicts`` block of metrics.json for one run.

    ``{"paper_rule": {"passed", "rule"}, "course_rule": {"passed", "cones_struck",
    "gate_exits", "rule"}, "stable": {"passed", "rule"}}``; ``passed`` is True, False or None
    (no such rule in the scenario, no truth data, or the trace ends before the verdict
    window closes with no failure seen so far). ``truth``: RunData or a column dict (the
    plant truth, 10 ms rows). ``planned_end_s``: where a complete run ends, s (judges the
    coverage of a scenario without a course; None: the trace is taken as complete).
    Same computation as :func:`dlc_verdicts`, whose ``paper`` equals the ``passed_dlc`` KPI.
    """
    col = truth.truth_col if hasattr(truth, "truth_col") else (
        lambda k: np.asarray(truth.get(k, np.zeros(0)), dtype=float))
    cols = {k: col(k) for k in TRUTH_KEYS}
    course = has_course(cones, lanes)
    fp = footprint if footprint is not None else packaged_footprint()
    n = cols["t_s"].size
    none_course = {"passed": None, "cones_struck": None, "gate_exits": None,
                   "rule": "no cone course in this scenario"}
    block: dict[str, Any] = {
        "paper_rule": {"passed": None, "rule": "no lane-change course in this scenario"},
        "course_rule": none_course,
        "stable": {"passed": None, "rule": STABLE_RULE},
    }
    if n == 0 or any(cols[k].size != n for k in TRUTH_KEYS if k != "path_s_m"):
        block["stable"]["rule"] = "not judged: no truth data; rule: " + STABLE_RULE
        if course:
            block["paper_rule"]["rule"] = "not judged: no truth data; rule: " + PAPER_RULE
            block["course_rule"] = {**none_course,
                                    "rule": "not judged: no truth data; rule: " + COURSE_RULE}
        return block
    v = dlc_verdicts(cols, cones=np.asarray(cones if course else np.zeros((0, 2)), dtype=float),
                     lanes=list(lanes or []) if course else [],
                     course_end_arc_m=course_end_arc_m if course else None, footprint=fp)
    covered = bool(v["covered"])
    if not course and planned_end_s is not None:
        covered = bool(cols["t_s"][-1] >= float(planned_end_s) - 1.5 * dt_s)
    beta_seen = v["spun"] or v["max_abs_beta_deg"] > BETA_LIMIT_DEG
    stable = _judged(v["stable"] and covered, beta_seen, covered)
    block["stable"] = {"passed": stable, "rule": _rule(STABLE_RULE, stable, covered)}
    if course:
        paper = _judged(v["paper"], beta_seen or v["max_abs_dev_m"] > PAPER_DEV_M, covered)
        block["paper_rule"] = {"passed": paper, "rule": _rule(PAPER_RULE, paper, covered)}
        hit = v["cones_hit"] > 0 or v["gate_exits"] > 0
        crs = _judged(v["course"], v["spun"] or hit, covered)
        block["course_rule"] = {"passed": crs, "cones_struck": int(v["cones_hit"]),
                                "gate_exits": int(v["gate_exits"]),
                                "rule": _rule(COURSE_RULE, crs, covered)}
    return block


def verdict_word(passed: bool | None) -> str:
    """pass / FAIL / – (not judged or no such rule)."""
    return "–" if passed is None else ("pass" if passed else "FAIL")


def verdict_summary(block: dict[str, Any]) -> str:
    """One line of the three verdicts, e.g. ``paper rule: pass · course rule (cones): FAIL
    (2 cones struck) · stable: pass`` (plot titles, reports)."""
    parts = []
    for key in VERDICT_NAMES:
        entry = block.get(key) or {}
        text = f"{VERDICT_LABELS[key]}: {verdict_word(entry.get('passed'))}"
        if key == "course_rule" and entry.get("cones_struck") is not None:
            n = int(entry["cones_struck"])
            text += f" ({n} cone{'s' if n != 1 else ''} struck)"
        parts.append(text)
    return " · ".join(parts)

