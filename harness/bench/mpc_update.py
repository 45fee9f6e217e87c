"""`rhonn-bench mpc-update`: the MPC update inside the controller process, per CPU layout.

Runs a scenario (default ``dlc-paper``, lockstep, plant and controller as OS processes on
the bus) ``--runs`` times per controller and layout, alternating the layouts run by run so
both see the same machine noise, and reads the controller's own timing log: ``step_us`` of
the cycles that ran an MPC update (``mpc_update``) and of the hold cycles in between
(allocation only). Layouts:

* ``shared``: every process may run on every CPU (the harness default);
* ``own-cpu``: the HIL layout of ``rhonn-harness run --controller-cpu auto``: the controller
  alone on the highest CPU, kept from idling (can_db/process/cpu.py), the rest on the others.

Per controller and layout: the mean of the MPC update of every run (the issue's figure),
p50 / p99 / max over all updates of all runs, the hold cycles' p50 and the loop's speed
(simulated s / wall s). The first MPC update of a run (it touches everything for the first
time) is included. Nothing here asserts a threshold.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import OneLineParser, number
from can_db.process.cpu import CpuChoiceError, choose_cpu
from harness.analysis.run_data import load_timing_csv
from harness.bench.stats import write_json
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from plant_sim.scenario import list_scenarios

MPC_CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc")
LAYOUTS = {"shared": None, "own-cpu": "auto"}  # RunSpec.controller_cpu


def one_run(scenario: str, controller: str, layout: str, bus: str) -> dict[str, Any]:
    """One closed-loop run; the MPC update and hold step times (µs) and the loop speed."""
    with tempfile.TemporaryDirectory() as tmp:
        res = run_and_report(RunSpec(scenario=scenario, controller=controller,
                                        out_dir=Path(tmp), bus=bus, make_plots=False,
                                        make_rrd=False, controller_cpu=LAYOUTS[layout]))
        summary = res.metrics.get("plant_summary", {})
        if res.reason != "finished" or not summary.get("loop_wall_s"):
            raise SystemExit(f"{controller} ({layout}) failed: {res.reason}")
        timing = load_timing_csv(Path(tmp) / "controller_timing.csv")
    update = timing["mpc_update"] > 0
    return {"update_us": timing["step_us"][update], "hold_us": timing["step_us"][~update],
            "speed": summary["sim_time_s"] / summary["loop_wall_s"]}


def _row(runs: list[dict[str, Any]]) -> dict[str, Any]:
    allup = np.concatenate([r["update_us"] for r in runs])
    means = [float(r["update_us"].mean()) for r in runs]
    return {"runs": len(runs), "update_mean_us_per_run": means,
            "update_mean_us_median": float(np.median(means)),
            "update_p50_us": float(np.percentile(allup, 50)),
            "update_p99_us": float(np.percentile(allup, 99)),
            "update_max_us": float(allup.max()), "updates": int(allup.size),
            "hold_p50_us": float(np.percentile(np.concatenate([r["hold_us"] for r in runs]),
                                               50)),
            "speed_x": [round(r["speed"], 1) for r in runs]}


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench mpc-update", description=__doc__)
    parser.add_argument("--controllers", default=",".join(MPC_CONTROLLERS),
                        help="comma-separated MPC controllers (default: all three)")
    parser.add_argument("--layouts", default="shared,own-cpu",
                        help="comma-separated: shared, own-cpu (default: both, alternated)")
    parser.add_argument("--runs", type=number(int, lo=1), default=3,
                        help="runs per controller and layout")
    parser.add_argument("--scenario", choices=list_scenarios(), default="dlc-paper",
                        metavar="NAME", help="scenario: " + ", ".join(list_scenarios()))
    parser.add_argument("--bus", default="auto", help="bus spec (default: auto)")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    controllers = [c.strip() for c in args.controllers.split(",") if c.strip()]
    layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
    bad = [c for c in controllers if c not in MPC_CONTROLLERS] + \
        [x for x in layouts if x not in LAYOUTS]
    if bad or not controllers or not layouts:
        parser.error(f"unknown controller or layout {bad}; controllers: "
                     f"{', '.join(MPC_CONTROLLERS)}; layouts: {', '.join(LAYOUTS)}")
    if "own-cpu" in layouts:
        try:
            choose_cpu("auto")
        except CpuChoiceError as exc:
            parser.error(f"layout own-cpu: {exc}")
    runs: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for k in range(args.runs):
        for controller in controllers:
            for layout in (layouts if k % 2 == 0 else layouts[::-1]):  # alternate the order
                runs.setdefault((controller, layout), []).append(
                    one_run(args.scenario, controller, layout, args.bus))
    rows = {f"{c} {x}": _row(runs[(c, x)]) for c in controllers for x in layouts}
    print(f"MPC update in the controller process, {args.scenario}, {args.runs} runs each "
          f"(µs; mean per run, then p50/p99/max over all updates)")
    print(f"{'controller layout':<22}{'mean per run':>26}{'p50':>8}{'p99':>8}{'max':>8}"
          f"{'hold p50':>10}  speed ×")
    for name, r in rows.items():
        means = ", ".join(f"{m:.1f}" for m in r["update_mean_us_per_run"])
        print(f"{name:<22}{means:>26}{r['update_p50_us']:>8.1f}{r['update_p99_us']:>8.1f}"
              f"{r['update_max_us']:>8.1f}{r['hold_p50_us']:>10.1f}  "
              f"{', '.join(str(s) for s in r['speed_x'])}")
    write_json(args.json, {"scenario": args.scenario, "rows": rows})
    return 0
