"""`rhonn-bench ranges`: value ranges and fixed-point (Q-format) needs of the controller
core over a scenario campaign, and the float32 vs float64 closed-loop equivalence.

Campaign: every scenario in ``CAMPAIGN`` runs closed loop in this process (plant and
controller nodes exchanging the real frames, as ``harness.run.inprocess_loop``) with
nmpc-rhonn in three variants: float64 with the standard EKF (the default), float64 with
the UD EKF, and float32 with the UD EKF. After every controller step the instrument
reads the core's internal arrays (states, φ, weights, EKF P / U / D and gain K, the
innovation, references, linearisation, sensitivities, QP data, ΔM, torques) and keeps,
per signal, min, max and the smallest non-zero magnitude over all runs.

Q-format of a signal: signed, m integer bits (the smallest m ≥ 0 with max|v| < 2^m) and n
fraction bits for the resolution stated in ``RESOLUTION`` (n = ⌈−log2 resolution⌉);
word = 1 + m + n bits; words over 32 bits are flagged. ``range bits`` = log2(max|v| /
min non-zero |v|), the dynamic range actually used (not meaningful for signals that pass
through zero). ``U·√D`` is the square-root factor S of P (P = S Sᵀ) that a square-root
filter would store; its resolution is the one that resolves P to p_floor (see RESOLUTION).

Equivalence: per scenario the verdict (course rule of the DLC: no spin, max|β| ≤ 8°,
max|lateral deviation| ≤ 1 m up to 2 s after the course end; sine with dwell: FMVSS 126
criteria) of float32 (UD) against float64 (default), max|ΔM32 − ΔM64| over the run, and,
unless ``--no-vmax``, the DLC v_max of both by bisection (harness.analysis.vmax, 0.5 km/h).
Nothing is asserted.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import OneLineParser  # one-line errors, exit 2
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode
from harness.analysis.fmvss126 import evaluate_sine_with_dwell
from harness.analysis.kpi import compute_kpis, course_end_time_s
from harness.analysis.run_data import RunData
from harness.analysis.vmax import Bisection
from harness.bench.controller_step import set_toml_keys
from harness.bench.stats import write_json
from harness.run.inprocess_loop import exchange_cycle
from plant_sim.node import PlantNode
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation

# (label, scenario, overrides). μ and speeds as the paper study uses them.
CAMPAIGN: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("dlc-paper 50 km/h", "dlc-paper", {"speed_kmh": 50.0}),
    ("dlc-paper 65 km/h", "dlc-paper", {"speed_kmh": 65.0}),
    ("dlc-paper 75 km/h", "dlc-paper", {"speed_kmh": 75.0}),
    ("dlc-paper-high-mu", "dlc-paper-high-mu", {}),
    ("slippery-curve", "slippery-curve", {}),
    ("sine-with-dwell 180°", "sine-with-dwell", {"amplitude_deg": 180.0}),
    ("sine-with-dwell 270°", "sine-with-dwell", {"amplitude_deg": 270.0}),
    ("step-steer", "step-steer", {}),
    ("split-mu-braking", "split-mu-braking", {}),
)

VARIANTS: dict[str, tuple[str, str]] = {   # name: ([mpc] lines, [rhonn.ekf] lines)
    "float64": ("", ""),
    "float64-ud": ("", 'form = "ud"'),
    "float32-ud": ('precision = "float32"', 'form = "ud"'),
}

# Stated resolution per signal (unit of the signal). Sources: torque frame 0.5 N·m (DBC);
# P, D floor = [rhonn.ekf] p_floor 1e-9; the others chosen at ~1e-4 of their use.
RESOLUTION: dict[str, float] = {
    "x.vx m/s": 1e-4, "x.vy m/s": 1e-4, "x.r rad/s": 1e-5,
    "xbar.vx m/s": 1e-4, "xbar.vy m/s": 1e-4, "xbar.r rad/s": 1e-5,
    "phi": 2.0 ** -16, "W.vx m/s": 1e-6, "W.vy m/s": 1e-6, "W.r rad/s": 1e-6,
    "e.vx m/s": 1e-5, "e.vy m/s": 1e-5, "e.r rad/s": 1e-6,
    "EKF P u²": 1e-9, "EKF diag P u²": 1e-9, "EKF K u": 1e-6, "EKF D u²": 1e-9, "EKF U": 2.0 ** -20,
    # S = U√D resolved so that P = S Sᵀ is resolved to p_floor = 1e-9 at the smallest
    # diagonal seen (D ≈ 2e-5, √D ≈ 4.6e-3): δS = 1e-9 / (2·4.6e-3) ≈ 1e-7.
    "EKF U√D u": 1e-7,
    "ref r_d rad/s": 1e-5, "ref vy_d m/s": 1e-4, "ref beta_d rad": 1e-5,
    "A": 1e-6, "B (rad/s)/(N·m)": 1e-9, "S": 1e-9, "G": 1e-6, "ybar": 1e-5,
    "QP P": 1e-6, "QP q": 1e-6, "dM N·m": 0.1, "torques N·m": 0.5,
}


class RangeRecorder:
    """min / max / smallest non-zero |v| per signal, updated from numpy arrays."""

    def __init__(self) -> None:
        self.stats: dict[str, list[float]] = {}
        self.maxima: dict[str, float] = {}

    def add(self, name: str, v: Any) -> None:
        a = np.asarray(v, dtype=np.float64).ravel()
        a = a[np.isfinite(a)]
        if a.size == 0:
            return
        nz = np.abs(a[a != 0.0])
        s = self.stats.setdefault(name, [math.inf, -math.inf, math.inf])
        s[0] = min(s[0], float(a.min()))
        s[1] = max(s[1], float(a.max()))
        if nz.size:
            s[2] = min(s[2], float(nz.min()))

    def count_max(self, name: str, v: float) -> None:
        self.maxima[name] = max(self.maxima.get(name, -math.inf), float(v))

    def sample(self, ctrl: Any) -> None:
        """Read the controller's internal arrays after one step (nmpc-rhonn layout)."""
        m, qp, o = ctrl.model, ctrl.qp, ctrl.out
        for i, s in enumerate(("vx m/s", "vy m/s", "r rad/s")):
            self.add(f"x.{s}", ctrl._x[i])
            self.add(f"xbar.{s}", qp.xbar[:, i])
            self.add(f"W.{s}", m.W[i])
            self.add(f"e.{s}", m._e[i])
        self.add("phi", m._rec_phi)
        ekf = m.ekf
        P = ekf.P
        self.add("EKF P u²", P)
        self.add("EKF diag P u²", np.diagonal(P, axis1=1, axis2=2))
        if hasattr(ekf, "D"):
            self.add("EKF D u²", ekf.D)
            self.add("EKF U", ekf.U)
            self.add("EKF U√D u", ekf.U * np.sqrt(np.maximum(ekf.D, 0.0))[:, None, :])
        h = np.asarray(m._rec_phi, dtype=np.float64)
        ph = np.asarray(P, dtype=np.float64) @ h
        s = np.asarray(ekf.cfg.r, dtype=np.float64) + ph @ h
        self.add("EKF K u", ph / s[:, None])
        self.add("ref r_d rad/s", o.yaw_rate_ref)
        self.add("ref vy_d m/s", o.vy_ref)
        self.add("ref beta_d rad", o.beta_ref)
        if o.qp_status != 4:   # NOT_RUN: the QP arrays are stale
            self.add("A", qp.A)
            self.add("B (rad/s)/(N·m)", qp.B)
            self.add("S", qp._Sall)
            self.add("G", qp.G)
            self.add("ybar", qp.ybar)
            self.add("QP P", qp.Pd)
            self.add("QP q", qp.q)
        self.add("dM N·m", o.delta_m)
        self.add("torques N·m", o.torques)
        self.count_max("OSQP iterations per step", o.qp_iterations)
        self.count_max("Algorithm 1 rounds per step", ctrl.references.rounds_last)

    def table(self) -> list[dict[str, Any]]:
        """One row per signal: range, Q-format for its stated resolution, flag > 32 bits."""
        rows = []
        for name, (lo, hi, nz) in self.stats.items():
            amax = max(abs(lo), abs(hi))
            res = RESOLUTION.get(name, 1e-6)
            m_bits = max(0, math.floor(math.log2(amax)) + 1) if amax > 0 else 0
            n_bits = max(0, math.ceil(-math.log2(res)))
            word = 1 + m_bits + n_bits
            rows.append({
                "signal": name, "min": lo, "max": hi,
                "min_nonzero_abs": nz if math.isfinite(nz) else None,
                "range_bits": (math.log2(amax / nz) if amax > 0 and math.isfinite(nz)
                               else 0.0),
                "resolution": res, "int_bits": m_bits, "frac_bits": n_bits,
                "word_bits": word, "over_32": word > 32,
            })
        return rows


def _config(variant: str) -> str:
    """Path of a temporary controller TOML for ``variant`` (caller deletes it)."""
    mpc_lines, ekf_lines = VARIANTS[variant]
    text = resources.files("controller").joinpath("config/default.toml").read_text()
    text = set_toml_keys(text, "[mpc]", mpc_lines)
    text = set_toml_keys(text, "[rhonn.ekf]", ekf_lines)
    fd, path = tempfile.mkstemp(prefix="rhonn-ranges-", suffix=".toml")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    return path


def run_scenario(scenario: str, config: str, recorder: RangeRecorder | None,
                 seed: int = 0, **overrides: Any) -> dict[str, Any]:
    """One closed-loop run of nmpc-rhonn (same loop as harness.run.inprocess_loop, with
    the controller instrumented); returns truth arrays, per-cycle ΔM and the verdicts."""
    mu = overrides.pop("mu", None)
    speed = overrides.pop("speed_kmh", None)
    scn = load_scenario(scenario, mu=mu, speed_kmh=speed, **overrides)
    sim = Simulation(scn, seed=seed)
    plant = PlantNode(sim)
    # the internal signals are read from the numpy reference's arrays (the C core computes
    # the same quantities; tests/test_native_core.py holds the two equal)
    ctrl = make_controller("nmpc-rhonn", config,
                           backend="numpy" if recorder is not None else None)
    if recorder is not None:
        step = ctrl.step

        def instrumented(inputs: Any) -> Any:
            out = step(inputs)
            recorder.sample(ctrl)
            return out

        ctrl.step = instrumented
    node = ControllerNode(ctrl, load_vehicle_params())
    rows = [sim.truth_row()]
    dms = []
    while not sim.finished:
        command = exchange_cycle(plant, node)
        dms.append(float(node.torques[1] + node.torques[3] - node.torques[0]
                         - node.torques[2]))
        plant.advance(command)
        rows.append(sim.truth_row())
    truth = {k: np.array([r[k] for r in rows]) for k in sim.trace_columns}
    res = {"delta_m": np.array(dms), "spun": bool(sim.spun),
           "qp_max_iter_hits": ctrl.qp.max_iter_hits, "qp_fallbacks": ctrl.qp.fallbacks,
           "qp_worst_iterations": ctrl.qp.worst_iterations,
           "ref_not_converged": ctrl.references.not_converged,
           # the node passes the driver through on an exception in the step (or in the
           # instrument): a non-zero count means the ranges above are not the controller's
           "controller_exceptions": node.controller_exceptions}
    res.update(_verdict(scenario, scn, truth, overrides))
    return res


def _verdict(scenario: str, scn: Any, truth: dict[str, np.ndarray],
             overrides: dict[str, Any]) -> dict[str, Any]:
    """Pass/fail of one run: FMVSS 126 for sine with dwell, else the DLC course rule."""
    if scenario == "sine-with-dwell":
        r = evaluate_sine_with_dwell(truth["t_s"], np.degrees(truth["swa_rad"]),
                                     truth["yaw_rate_radps"], truth["x_m"], truth["y_m"],
                                     truth["yaw_rad"],
                                     amplitude_deg=overrides.get("amplitude_deg"))
        return {"passed": bool(r.passed), "rule": "FMVSS 126",
                "max_abs_beta_deg": float(np.degrees(np.max(np.abs(truth["beta_rad"])))),
                "max_abs_lateral_dev_m": None}

    run = RunData(truth=truth, meta={"scenario_end_s": float(scn.duration_s),
                                     "comm_period_s": 0.01})
    end = None
    if float(scn.course_end_s) > 0:
        end = course_end_time_s(run, float(scn.course_end_s))
        end = math.inf if end is None else end
    k = compute_kpis(run, course_end_s=end)
    rule = "DLC course" if float(scn.course_end_s) > 0 else "whole run (no course end)"
    return {"passed": bool(k["passed_dlc"]), "rule": rule,
            "max_abs_beta_deg": k["max_abs_beta_deg"],
            "max_abs_lateral_dev_m": k["max_abs_lateral_dev_m"]}


def dlc_duration_s(speed_kmh: float, path_m: float = 191.0) -> float:
    """Run length for a DLC probe, s: coast the ≈ 191 m path at 1.5× its time plus 3 s,
    ≥ 18 s (the rule of harness.campaign.studies.coast_duration_s, so the pass window course
    end + 2 s fits)."""
    return max(18.0, 1.5 * path_m / (speed_kmh / 3.6) + 3.0)


def vmax(config: str, lo: float = 30.0, hi: float = 90.0) -> dict[str, Any]:
    """DLC (dlc-paper) v_max, km/h, by bisection on a 0.5 km/h grid."""
    b = Bisection("nmpc-rhonn", lo_kmh=lo, hi_kmh=hi, verify_offsets_kmh=())
    while not b.done:
        for v in b.pending():
            r = run_scenario("dlc-paper", config, None, speed_kmh=v,
                             duration_s=dlc_duration_s(v))
            b.record(v, {"passed_dlc": r["passed"], "max_abs_beta_deg": r["max_abs_beta_deg"],
                         "max_abs_lateral_dev_m": r["max_abs_lateral_dev_m"],
                         "spun": r["spun"], "completed": True, "reason": None})
    return {"status": b.status, "v_max_kmh": b.vmax_kmh,
            "probes": len(b.probes)}


def markdown(ranges: list[dict[str, Any]], ranges_ud: list[dict[str, Any]],
             equiv: list[dict[str, Any]], vm: dict[str, Any] | None) -> str:
    """Markdown tables for docs/controller.md."""
    L = ["| signal | min | max | range bits | resolution | Q (int.frac) | word | > 32 bit |",
         "|---|---|---|---|---|---|---|---|"]
    ud_only = ("EKF D u²", "EKF U", "EKF U√D u")
    for r in ranges + [r for r in ranges_ud if r["signal"] in ud_only]:
        L.append(f"| {r['signal']} | {r['min']:.4g} | {r['max']:.4g} | {r['range_bits']:.1f} | "
                 f"{r['resolution']:.3g} | Q{r['int_bits']}.{r['frac_bits']} | "
                 f"{r['word_bits']} | {'**yes**' if r['over_32'] else 'no'} |")
    L += ["", "| scenario | rule | verdict float64 | verdict float32 (UD) | "
          "max\\|β\\| 64 / 32 ° | max\\|ΔM32 − ΔM64\\| N·m | max\\|ΔM(64 UD) − ΔM64\\| N·m | "
          "max\\|ΔM64\\| N·m |", "|---|---|---|---|---|---|---|---|"]
    for e in equiv:
        L.append(f"| {e['scenario']} | {e['rule']} | {e['passed_64']} | {e['passed_32']} | "
                 f"{e['beta_64']:.2f} / {e['beta_32']:.2f} | {e['max_abs_ddm_nm']:.3g} | "
                 f"{e['max_abs_ddm_ud64_nm']:.3g} | {e['max_abs_dm64_nm']:.0f} |")
    if vm is not None:
        L += ["", f"DLC v_max: float64 {vm['float64']} km/h, float32 (UD) {vm['float32-ud']} "
              "km/h."]
    return "\n".join(L) + "\n"


def main(argv: list[str]) -> int:
    """Entry point: ``rhonn-bench ranges [--json FILE] [--md FILE] [--no-vmax]``."""
    ap = OneLineParser(prog="rhonn-bench ranges", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, help="write ranges + equivalence as JSON")
    ap.add_argument("--md", type=Path, help="write the markdown tables")
    ap.add_argument("--no-vmax", action="store_true", help="skip the v_max bisections")
    ap.add_argument("--quick", action="store_true", help="first two scenarios only")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    campaign = CAMPAIGN[:2] if args.quick else CAMPAIGN
    paths = {v: _config(v) for v in VARIANTS}
    try:
        rec = {v: RangeRecorder() for v in VARIANTS}
        equiv = []
        counts: dict[str, dict[str, int]] = {v: {} for v in VARIANTS}
        for label, scenario, ov in campaign:
            got = {}
            for v in VARIANTS:
                got[v] = run_scenario(scenario, paths[v], rec[v], **dict(ov))
                c = counts[v]
                for key in ("qp_max_iter_hits", "qp_fallbacks", "ref_not_converged",
                            "controller_exceptions"):
                    c[key] = c.get(key, 0) + int(got[v][key])
                c["qp_worst_iterations"] = max(c.get("qp_worst_iterations", 0),
                                               int(got[v]["qp_worst_iterations"]))
            a, b = got["float64"], got["float32-ud"]
            n = min(a["delta_m"].size, b["delta_m"].size)
            u = got["float64-ud"]
            e = {"scenario": label, "rule": a["rule"], "passed_64": a["passed"],
                 "max_abs_ddm_ud64_nm": float(np.max(np.abs(
                     a["delta_m"][:n] - u["delta_m"][:n]))),
                 "passed_32": b["passed"], "passed_64_ud": got["float64-ud"]["passed"],
                 "beta_64": a["max_abs_beta_deg"], "beta_32": b["max_abs_beta_deg"],
                 "dev_64": a["max_abs_lateral_dev_m"], "dev_32": b["max_abs_lateral_dev_m"],
                 "max_abs_ddm_nm": float(np.max(np.abs(a["delta_m"][:n] - b["delta_m"][:n]))),
                 "max_abs_dm64_nm": float(np.max(np.abs(a["delta_m"]))),
                 "spun_64": a["spun"], "spun_32": b["spun"]}
            equiv.append(e)
            print(f"{label:<22} pass64 {e['passed_64']!s:<5} pass32 {e['passed_32']!s:<5} "
                  f"max|ΔM32−ΔM64| {e['max_abs_ddm_nm']:8.3g} N·m "
                  f"(max|ΔM| {e['max_abs_dm64_nm']:.0f})", flush=True)
        vm = None
        if not args.no_vmax:
            vm = {}
            for v in ("float64", "float32-ud"):
                r = vmax(paths[v])
                vm[v] = r.get("v_max_kmh")
                print(f"v_max {v}: {vm[v]} km/h", flush=True)
        ranges = rec["float64"].table()
        ranges_ud = rec["float64-ud"].table()
        md = markdown(ranges, ranges_ud, equiv, vm)
        print(md)
        print("bounded iterations over the campaign (OSQP max_iter hits, QP fallbacks, "
              "worst OSQP iterations per step, Algorithm 1 not converged):")
        for v, c in counts.items():
            print(f"  {v}: {c}  (max per step: {rec[v].maxima})")
        print(f"campaign wall time {time.monotonic() - t0:.0f} s")
        if args.md is not None:
            args.md.write_text(md)
        write_json(args.json, {"ranges_float64": ranges, "ranges_float64_ud": ranges_ud,
                               "equivalence": equiv, "vmax_kmh": vm, "counts": counts,
                               "per_step_maxima": {v: r.maxima for v, r in rec.items()}})
    finally:
        for p in paths.values():
            os.unlink(p)
    failed = {v: c["controller_exceptions"] for v, c in counts.items()
              if c.get("controller_exceptions")}
    if failed:   # the node passed the driver through: the ranges are not the controller's
        print(f"rhonn-bench ranges: the controller step raised in {failed} steps; "
              "the ranges above are incomplete", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
