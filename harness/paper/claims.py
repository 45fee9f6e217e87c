"""The paper's claims checked against tables.json, and the discussion of the differences.

Each claim's verdict is computed from the numbers (True / False / None = not measured in
this run, e.g. --quick). The discussion quotes the measured diagnostics.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from harness.paper.reference_data import PAPER_TABLE3, PAPER_TABLE4_KMH, PAPER_TABLE5_MS
from harness.paper.text_format import f, rmse


def _get(d: dict[str, Any], *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)  # type: ignore[assignment]
    return d


def _cmp(a: Any, b: Any, more: str, less: str) -> str:
    """``more`` when a > b, ``less`` when a < b, "comparable" otherwise (equal or missing)."""
    x, y = _num(a), _num(b)
    if math.isnan(x) or math.isnan(y) or x == y:
        return "comparable"
    return more if x > y else less


def _num(x: Any) -> float:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else math.nan


def _lt(*xs: float) -> bool | None:
    """Strictly increasing (None if any is NaN)."""
    if any(math.isnan(x) for x in xs):
        return None
    return all(a < b for a, b in itertools.pairwise(xs))


def claims(t: dict[str, Any]) -> list[dict[str, Any]]:
    """Paper claims with our numbers and a computed verdict."""
    out: list[dict[str, Any]] = []
    fid = t.get("fidelity", {})

    def add(claim: str, paper: str, ours: str, holds: bool | None) -> None:
        out.append({"claim": claim, "paper": paper, "ours": ours, "holds": holds})

    for name, label in (("low_mu", "passive 50 km/h"),
                        ("low_mu_closed_loop", "nmpc-rhonn 65 km/h")):
        fd = fid.get(name)
        if not fd:
            continue
        for key, unit, paper in (("vx_kmh", "km/h", "0.12 < 0.86 < 3.05"),
                                 ("vy_kmh", "km/h", "0.65 < 4.14 ≈ 3.97"),
                                 ("yaw_rate_degps", "deg/s", "2.29 < 6.67 < 10.22")):
            r, mf, li = (rmse(fd, m, key) for m in ("rhonn", "7dof-mf", "7dof-li"))
            ok = None if math.isnan(r + mf + li) else (r < mf and r < li)
            add(f"Low μ ({label}): RHONN more accurate than both 7-DoF models, "
                f"RMSE {key.split('_')[0]}", f"{paper} {unit}",
                f"RHONN {f(r)}, MF {f(mf)}, LI {f(li)}", ok)
        r3, mf3, li3 = (rmse(fd, m, "yaw_rate_degps", "multi_step")
                        for m in ("rhonn", "7dof-mf", "7dof-li"))
        add(f"Low μ ({label}), 150 ms prediction from the measured state (not in the paper): "
            "RHONN ωr RMSE below both 7-DoF", "–",
            f"RHONN {f(r3)}, MF {f(mf3)}, LI {f(li3)} deg/s",
            None if math.isnan(r3 + mf3 + li3) else (r3 < mf3 and r3 < li3))
        mf_li = _lt(rmse(fd, "7dof-mf", "yaw_rate_degps"), rmse(fd, "7dof-li", "yaw_rate_degps"))
        add(f"Low μ ({label}): 7-DoF-MF better than 7-DoF-LI (ωr RMSE)", "6.67 < 10.22 deg/s",
            f"MF {f(rmse(fd, '7dof-mf', 'yaw_rate_degps'))}, LI "
            f"{f(rmse(fd, '7dof-li', 'yaw_rate_degps'))}", mf_li)
    fd = fid.get("high_mu")
    if fd:
        r, mf, li = (rmse(fd, m, "vx_kmh") for m in ("rhonn", "7dof-mf", "7dof-li"))
        add("High μ: RHONN Vx RMSE ~90 % below both 7-DoF models", "0.06 vs 0.78 / 0.64 km/h",
            f"RHONN {f(r)}, MF {f(mf)}, LI {f(li)}",
            None if math.isnan(r + mf + li) else r <= 0.2 * min(mf, li))
        rs = [rmse(fd, m, "yaw_rate_degps") for m in ("rhonn", "7dof-mf", "7dof-li")]
        add("High μ: ωr of the RHONN similar to, slightly worse than, the 7-DoF models "
            "(RMSE RHONN / MF / LI)", "1.96 / 1.53 / 1.98 deg/s",
            " / ".join(f(x) for x in rs),
            None if any(math.isnan(x) for x in rs) else rs[0] >= 0.8 * min(rs[1:]))

    dlc = t.get("dlc", {})
    if dlc:
        done = [c for c in ("nmpc-rhonn", "nmpc-mf") if c in dlc]
        add("DLC 65 km/h: NMPC-RHONN and NMPC-MF complete the lane change",
            "both complete", ", ".join(f"{c}: {f(dlc[c].get('passed_dlc'))}" for c in done),
            all(bool(dlc[c].get("passed_dlc")) for c in done) if done else None)
        if "lmpc" in dlc:
            add("DLC 65 km/h: LMPC shows unstable behaviour (does not pass cleanly)",
                "unstable, large δsw", f"passed {f(dlc['lmpc'].get('passed_dlc'))}, max |β| "
                f"{f(dlc['lmpc'].get('max_abs_beta_deg'))}°",
                not bool(dlc["lmpc"].get("passed_dlc")))
        pa = [_num(dlc.get(c, {}).get("phase_area")) for c in ("nmpc-rhonn", "nmpc-mf", "lmpc")]
        add("DLC: phase area NMPC-RHONN < NMPC-MF < LMPC", "RHONN < MF < LMPC",
            " / ".join(f(x, "{:.4f}") for x in pa), _lt(*pa))
    vm = t.get("vmax", {})
    if vm:
        v = [_num(vm.get(c, {}).get("vmax_kmh")) for c in ("nmpc-rhonn", "nmpc-mf", "lmpc")]
        holds = None if any(math.isnan(x) for x in v) else (v[0] >= v[1] > v[2])
        add("v_max: NMPC-RHONN ≥ NMPC-MF > LMPC", "{} ≥ {} > {} km/h".format(
            *(PAPER_TABLE4_KMH[c] for c in ("nmpc-rhonn", "nmpc-mf", "lmpc"))),
            " / ".join(f(x, "{:.1f}") for x in v) + " km/h", holds)
        pv = _num(vm.get("passive", {}).get("vmax_kmh"))
        if not math.isnan(pv) and not math.isnan(v[0]):
            add("Stabilisation raises v_max above the passive car (implicit)", "–",
                f"passive {f(pv, '{:.1f}')} vs nmpc-rhonn {f(v[0], '{:.1f}')} km/h", v[0] > pv)
    cv = t.get("curve", {})
    if cv:
        dev = {c: _num(cv.get(c, {}).get("max_abs_lateral_dev_m")) for c in cv}
        if "lmpc" in dev:
            nm = [dev[c] for c in ("nmpc-rhonn", "nmpc-mf") if c in dev]
            add("Curve: LMPC's path deviation large, both NMPCs' negligible",
                "LMPC 2.68 m, NMPCs ≈ 0", ", ".join(f"{c} {f(x)} m" for c, x in dev.items()),
                None if not nm else (dev["lmpc"] > 1.0 and max(nm) < 0.5 * dev["lmpc"]))
        pa = [_num(cv.get(c, {}).get("phase_area")) for c in ("nmpc-rhonn", "nmpc-mf", "lmpc")]
        add("Curve: phase area NMPC-RHONN < NMPC-MF < LMPC", "RHONN < MF < LMPC",
            " / ".join(f(x, "{:.4f}") for x in pa), _lt(*pa))
        sw = [_num(cv.get(c, {}).get("steering_effort_deg")) for c in
              ("nmpc-rhonn", "nmpc-mf", "lmpc")]
        add("Curve: NMPC-RHONN needs the fewest steering adjustments (steering effort)",
            "RHONN fewest", " / ".join(f(x, "{:.0f}") for x in sw) + " deg",
            None if any(math.isnan(x) for x in sw) else sw[0] <= min(sw[1:]))
    tm = t.get("timing", {})
    for exp in ("dlc", "curve"):
        m = {c: _num(_get(tm, exp, c, "mpc_update", "mean_us")) for c in
             ("nmpc-rhonn", "nmpc-mf", "lmpc")}
        if all(math.isnan(x) for x in m.values()):
            continue
        add(f"Computation ({exp}): NMPC-MF slowest; all far below the 50 ms period",
            "MF 0.019 ms > RHONN ≈ LMPC 0.017 ms",
            ", ".join(f"{c} {f(x / 1000, '{:.3f}')} ms" for c, x in m.items()),
            None if any(math.isnan(x) for x in m.values()) else
            (m["nmpc-mf"] > max(m["nmpc-rhonn"], m["lmpc"])
             and max(m.values()) < 50_000))
    return out


def _fid_line(fd: dict[str, Any], which: str, key: str) -> str:
    return ", ".join(f"{m} {f(rmse(fd, m, key, which))}" for m in ("rhonn", "7dof-mf", "7dof-li"))


def _ref(fd: dict[str, Any], which: str, key: str) -> float:
    v = _get(fd, "reference", which, key, "rmse")
    return _num(v)


def _ratio_range(fd: dict[str, Any]) -> str:
    """'a–b×': paper 7-DoF RMSE (Table 3) over ours, across models and states."""

    r = [PAPER_TABLE3[m][k][2] / v for m in ("7dof-mf", "7dof-li")
         for k in ("vx_kmh", "vy_kmh", "yaw_rate_degps")
         if (v := rmse(fd, m, k)) > 0]
    return f"{min(r):.0f}–{max(r):.0f}×" if r else "–"


def _discuss_fidelity(t: dict[str, Any]) -> list[str]:
    fid = t.get("fidelity", {})
    L: list[str] = []
    hi, lo, spin = fid.get("high_mu"), fid.get("low_mu"), fid.get("low_mu_spin")
    if hi:
        beat = rmse(hi, "rhonn", "vx_kmh") <= 0.2 * min(rmse(hi, "7dof-mf", "vx_kmh"),
                                                         rmse(hi, "7dof-li", "vx_kmh"))
        L += [
            "**Fidelity, high μ (Table 2).** All three models are good, as in the paper; our "
            "RHONN " + ("does" if beat else "does not") + " beat the 7-DoF models on Vx by "
            f"~90 % (RMSE Vx: {_fid_line(hi, 'paper', 'vx_kmh')} km/h). What sets the "
            "numbers, visible in the tables: (1) our 7-DoF models use the Magic-Formula fit "
            "and driving resistances "
            "of *this* plant (`controller/config/mf_tyre_fit.toml`), so in the linear region "
            "they are nearly exact; the paper's 7-DoF Vx error never drops below 0.26–0.60 "
            "km/h (its *min* column), i.e. its physics models carried a constant offset "
            "against CarSim that ours do not have against our plant. (2) The series-parallel "
            "RHONN restarts every prediction from the bus measurement, so its error cannot "
            "go below the measurement's own error (VX_EST vs truth: RMSE "
            f"{f(_ref(hi, 'sensor', 'vx_kmh'))} km/h), whereas the open-loop models never "
            "see the noisy measurement. The paper's RHONN max ωr error (8.07 deg/s, "
            "attributed to a delay) does not appear: ours predicts Ts = 50 ms ahead from the "
            f"latest measurement (max {f(_get(hi, 'paper', 'rhonn', 'yaw_rate_degps', 'max'))}"
            " deg/s).", ""]
    if lo:
        order = _lt(*(rmse(lo, m, "yaw_rate_degps") for m in ("rhonn", "7dof-mf", "7dof-li")))
        L += [
            "**Fidelity, low μ (Table 3).** The paper's ordering (RHONN most accurate, then "
            "7-DoF-MF, then 7-DoF-LI) " + ("holds" if order else "does not hold")
            + " in the paper's set-up for the passive car at "
            f"{f(lo.get('speed_kmh'), '{:.0f}')} km/h (ωr RMSE "
            f"{_fid_line(lo, 'paper', 'yaw_rate_degps')} deg/s), but the 7-DoF errors are "
            f"{_ratio_range(lo)} smaller than the paper's, because our passive "
            f"car at that speed stays nearly linear (max |Vy| {f(lo.get('max_abs_vy_kmh'))} km/h; "
            "the paper's 7-DoF errors of ~18 km/h in Vy mean its car was sliding). At 65 km/h "
            "our passive car spins (the paper's did not), so we use 50 km/h for Table 3 and "
            "add the spinning car as Table 3c: there the open-loop 7-DoF models diverge as in "
            f"the paper (ωr RMSE {_fid_line(spin, 'paper', 'yaw_rate_degps') if spin else '–'} "
            "deg/s). The cause is structural: the 7-DoF models assume μ = 1 (the controller "
            "does not know μ), so once the tyres saturate on μ = 0.35 they over-predict the "
            "lateral forces and, open loop, never recover.", ""]
        L += ["The paper's comparison is, however, not like for like: a one-step predictor "
              "fed with the measurement every 50 ms against simulators that never see a "
              "measurement. Restarting every model from the measured state (prediction "
              "tables) separates model quality from measurement feedback:", ""]
        for fd, label in ((lo, f"passive {f(lo.get('speed_kmh'), '{:.0f}')} km/h"),
                          (spin, "passive 65 km/h, spinning")):
            if not fd:
                continue
            r1, m1 = (rmse(fd, m, "yaw_rate_degps", "one_step") for m in ("rhonn", "7dof-mf"))
            r3, m3 = (rmse(fd, m, "yaw_rate_degps", "multi_step") for m in ("rhonn", "7dof-mf"))
            mp = rmse(fd, "7dof-mf", "yaw_rate_degps")
            rv3, hv3 = rmse(fd, "rhonn", "vx_kmh", "multi_step"), _ref(fd, "hold_h", "vx_kmh")
            L += [f"* {label}: 7-DoF-MF ωr RMSE {f(mp)} deg/s open loop → {f(m1)} (50 ms) / "
                  f"{f(m3)} (150 ms) restarted; RHONN {f(r1)} / {f(r3)}; holding the last "
                  f"measurement {f(_ref(fd, 'hold_1', 'yaw_rate_degps'))} / "
                  f"{f(_ref(fd, 'hold_h', 'yaw_rate_degps'))}. Over 150 ms the RHONN is "
                  + ("better than" if r3 < m3 else "worse than") + " the 7-DoF-MF"
                  + (f"; its Vx prediction is worse than holding ({f(rv3)} vs {f(hv3)} km/h: "
                     "the increment model compounds its Vx bias in parallel mode)"
                     if rv3 > hv3 else "") + "."]
        spin_worse = bool(spin) and rmse(spin, "rhonn", "yaw_rate_degps", "multi_step") > \
            rmse(spin, "7dof-mf", "yaw_rate_degps", "multi_step")
        L += ["", "So most of the 7-DoF models' error in the paper's set-up is open-loop "
              "drift; with the same measurement feedback the gap to the RHONN shrinks"
              + ("; on the spinning car, far outside anything it has learned, the RHONN's "
                 "150 ms prediction is the weaker one." if spin_worse else "."), ""]
    return L


def _discuss_closed_loop(t: dict[str, Any]) -> list[str]:
    L: list[str] = []
    dlc, vm, cv = t.get("dlc", {}), t.get("vmax", {}), t.get("curve", {})
    mf, lm, rh = dlc.get("nmpc-mf", {}), dlc.get("lmpc", {}), dlc.get("nmpc-rhonn", {})
    if mf and lm:
        same = abs(_num(mf.get("phase_area")) - _num(lm.get("phase_area"))) <= 0.1 * _num(
            lm.get("phase_area"))
        L += [
            "**NMPC-MF and LMPC behave "
            + ("almost identically" if same else "differently")
            + f"** on the DLC (phase area {f(mf.get('phase_area'), '{:.4f}')} vs "
            f"{f(lm.get('phase_area'), '{:.4f}')}, max |ΔM| {f(mf.get('max_abs_dM_Nm'), '{:.0f}')}"
            f" vs {f(lm.get('max_abs_dM_Nm'), '{:.0f}')} N·m"
            + (f", v_max {f(_get(vm, 'nmpc-mf', 'vmax_kmh'), '{:.1f}')} vs "
               f"{f(_get(vm, 'lmpc', 'vmax_kmh'), '{:.1f}')} km/h" if vm else "")
            + "). They share the linear references (no μ), the QP weights and horizon; they "
            "differ only in the prediction model, and the 7-DoF-MF model assumes μ = 1, so at "
            "the slip angles of these manoeuvres (|β| ≤ 3–6°) its tyres stay in their near-linear "
            "range and its linearisation is practically the bicycle's. The paper's gap "
            "between them (72.4 vs 62.8 km/h) needs an MF model that knows the road's μ.", ""]
    if rh:
        d_rh, d_mf = rh.get("diag", {}) or {}, mf.get("diag", {}) or {}
        L += [
            "**NMPC-RHONN on the DLC**: "
            + ("it passes at 65 km/h, " if rh.get("passed_dlc") else "it fails at 65 km/h, ")
            + f"with a {_cmp(rh.get('phase_area'), mf.get('phase_area'), 'larger', 'smaller')}"
            f" β–β̇ phase area ({f(rh.get('phase_area'), '{:.4f}')} vs "
            f"NMPC-MF {f(mf.get('phase_area'), '{:.4f}')}) and a "
            + _cmp(rh.get('dM_total_variation_Nm'), mf.get('dM_total_variation_Nm'),
                   'rougher', 'smoother')
            + " yaw moment (ΔM total "
            f"variation {f(rh.get('dM_total_variation_Nm'), '{:.0f}')} vs "
            f"{f(mf.get('dM_total_variation_Nm'), '{:.0f}')} N·m, max |ΔM| "
            f"{f(rh.get('max_abs_dM_Nm'), '{:.0f}')} N·m). Its references (dlc_tracking.png) are "
            "the bicycle demand limited by the grip estimate, with Algorithm 1's learned "
            "steady state blended in as |β| grows (docs/handling.md): total variation of the "
            "yaw-rate reference "
            f"{f(d_rh.get('yaw_ref_total_variation'), '{:.0f}')}"
            f" vs {f(d_mf.get('yaw_ref_total_variation'), '{:.0f}')} deg/s for the linear "
            f"references; of the β reference {f(d_rh.get('beta_ref_total_variation'), '{:.0f}')}"
            f" vs {f(d_mf.get('beta_ref_total_variation'), '{:.0f}')} deg. What each piece of "
            "the design costs and buys is measured in the ablation of `rhonn-harness "
            "benchmark` (docs/benchmark.md), not in this single-seed study.", ""]
    if vm:
        fails = [p for c in ("nmpc-rhonn", "nmpc-mf", "lmpc") for p in vm.get(c, {}).get(
            "probes", []) if not p["passed"]]
        max_b = max((_num(p.get("max_abs_beta_deg")) for p in fails), default=math.nan)
        spun = any(p.get("spun") for p in fails)
        L += [
            "**Maximum entry speed (Table 4).** Ours: "
            + ", ".join(f"{c} {f(_get(vm, c, 'vmax_kmh'), '{:.1f}')}" for c in vm)
            + " km/h (paper: NMPC-RHONN 74.4, NMPC-MF 72.4, LMPC 62.8). With every MPC the "
            "failing probes fail on the 1.0 m deviation limit, not on stability: the "
            f"largest max |β| of any failing MPC probe is {f(max_b, '{:.1f}')}° (limit 8°), "
            + ("and none spun" if not spun else "and some spun")
            + ". v_max here measures how well the car follows the lane centre, which on "
            "μ = 0.35 is bounded by the tyres (the plant notes: exact ISO 3888-1 tracking is "
            "limited to ~52 km/h without yaw moment; the passive car manages "
            f"{f(_get(vm, 'passive', 'vmax_kmh'), '{:.1f}')} km/h) and by how much ΔM helps "
            "the driver turn. "
            + ("The RHONN controller's lower v_max follows from its larger deviation at "
               "the failing speeds (see vmax_probes.png). A single-seed v_max tie or gap "
               "below ~1 km/h is within the seed spread; `rhonn-harness benchmark` gives the "
               "5-seed figures with their min–max and the ablation of the design's pieces."
               if _num(_get(vm, "nmpc-rhonn", "vmax_kmh"))
               < _num(_get(vm, "nmpc-mf", "vmax_kmh")) else
               "The RHONN controller reaches the highest v_max, as in the paper."), ""]
    if cv:
        pas, lmc = cv.get("passive", {}), cv.get("lmpc", {})
        L += [
            "**Slippery curve.** The paper gives no geometry; ours (R = 175 m, 90°, at ~94 % "
            "of the lateral grip at 85 km/h, see plant_sim/scenarios/slippery-curve.toml) "
            + ("turns out not to be critical enough to separate the controllers: even the "
               if not pas.get("spun") and _num(pas.get("max_abs_lateral_dev_m")) < 2.0
               else "is critical: the ")
            + f"passive car gets through (max |dev| {f(pas.get('max_abs_lateral_dev_m'))} m, "
            f"max |β| {f(pas.get('max_abs_beta_deg'))}°, spun: {f(pas.get('spun'))}). LMPC "
            f"deviates {f(lmc.get('max_abs_lateral_dev_m'))} m (paper 2.68 m) with max |δsw| "
            f"{f(lmc.get('max_abs_swa_deg'), '{:.0f}')}° (paper 394°). In the traces "
            "(curve_tracking.png) the car understeers below the linear yaw-rate reference "
            "while β is larger than the linear β reference; the two tracking terms ask for "
            "opposite yaw moments, so the linear-reference controllers apply almost none "
            f"(max |ΔM| LMPC {f(lmc.get('max_abs_dM_Nm'), '{:.0f}')} N·m) instead of the "
            "paper's saturated ΔM from 6.7 s that made its LMPC slide. The RHONN controller "
            "tracks its own references; its ΔM total variation is "
            f"{f(_get(cv, 'nmpc-rhonn', 'dM_total_variation_Nm'), '{:.0f}')} vs "
            f"{f(lmc.get('dM_total_variation_Nm'), '{:.0f}')} N·m (LMPC; curve_delta_m.png). "
            "A tighter curve "
            "(or a higher speed) would be needed to reproduce the paper's LMPC failure; we "
            "keep the scenario as documented rather than tune it to the wanted result.", ""]
    return L


def _timing_ratio(tm: dict[str, Any]) -> str:
    """'a–b×': our mean MPC-update time over the paper's Table 5 (DLC row)."""

    r = [_num(_get(tm, c, "mpc_update", "mean_us")) / 1000.0 / ms
         for c, ms in PAPER_TABLE5_MS["dlc"].items()]
    r = [x for x in r if not math.isnan(x)]
    return f"{min(r):.0f}–{max(r):.0f}×" if r else "–"


def _discuss_rest(t: dict[str, Any]) -> list[str]:
    L: list[str] = []
    tm = t.get("timing", {}).get("dlc", {})
    if tm:
        L += [
            "**Computation time (Table 5).** Our MPC update takes "
            + ", ".join(f"{c} {f((_num(_get(tm, c, 'mpc_update', 'mean_us'))) / 1000, '{:.2f}')}"
                        for c in ("nmpc-rhonn", "nmpc-mf", "lmpc") if c in tm)
            + " ms on average (DLC), "
            + _timing_ratio(tm)
            + " the paper's 0.017–0.019 ms: Python + OSQP measured around the whole step in "
            "the controller process, against a MATLAB figure for which the paper does not "
            "say what was timed. "
            + ("Our NMPC-RHONN is the slowest (EKF learning of 3 × 15 weights plus the "
               "Algorithm 1 grid/Newton equilibrium search every step), unlike the paper's "
               "NMPC-MF. " if _num(_get(tm, "nmpc-rhonn", "mpc_update", "mean_us"))
               > _num(_get(tm, "nmpc-mf", "mpc_update", "mean_us")) else "")
            + "Every p99 stays far below the 50 ms MPC "
            "period and the 10 ms bus cycle.", ""]
    fm = t.get("fmvss", {})
    if fm.get("summary"):
        a = _num(fm.get("a_deg"))
        parts = []
        for c, s in fm["summary"].items():
            amp = s.get("first_fail_amplitude_deg")
            parts.append(f"{c}: " + ("passes every run" if s.get("passed_all") else
                                     f"fails {s['failed']}/{s['runs']} runs from "
                                     f"{f(amp, '{:.1f}')}° = {f(_num(amp) / a, '{:.1f}')}A "
                                     f"({', '.join(s.get('fail_criteria', []))})"))
        L += [
            f"**FMVSS 126** (not in the paper; A = {f(a)}°): " + "; ".join(parts) + ". The "
            "criteria bound the yaw-rate decay and the lateral displacement, not β: at the "
            "largest amplitudes the controllers pass with max |β| up to "
            + f(max((_num(r.get("max_abs_beta_deg")) for r in fm.get("runs", [])
                     if r.get("controller") != "passive" and r.get("passed")),
                    default=math.nan), "{:.0f}")
            + "° (see the run table).", ""]
    return L


def discussion(t: dict[str, Any]) -> list[str]:
    """Paragraphs on where and why we agree or differ, quoting the measured diagnostics."""
    out = _discuss_fidelity(t) + _discuss_closed_loop(t) + _discuss_rest(t)
    return out or ["(nothing measured)"]
