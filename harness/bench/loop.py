"""`rhonn-bench loop`: closed-loop lockstep speed and rx→tx turnaround over the real bus.

Runs ``dlc-paper`` (plant and controller as separate processes over the bus ``auto`` picks:
vcan0, else the local Unix-socket bus; the harness records every frame) ``--repeat`` times.
Speed = simulated seconds / wall seconds of the plant's loop
(process start-up excluded); turnaround = SYNC received → last answer frame sent, measured in
the controller process. Reports medians over repetitions and p50/p99 over all cycles.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from can_db.process.argcheck import OneLineParser, number
from controller.core.registry import CONTROLLER_NAMES
from harness.analysis.run_data import load_timing_csv
from harness.bench.stats import write_json
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from plant_sim.scenario import list_scenarios


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench loop", description=__doc__)
    parser.add_argument("--controller", choices=CONTROLLER_NAMES, default="nmpc-rhonn",
                        help="controller in the loop")
    parser.add_argument("--scenario", choices=list_scenarios(), default="dlc-paper",
                        metavar="NAME", help="scenario: " + ", ".join(list_scenarios()))
    parser.add_argument("--repeat", type=number(int, lo=1), default=3,
                        help="closed-loop runs (median over them)")
    parser.add_argument("--bus", default="auto",
                        help="bus spec: auto (default), local:NAME, remote:new, socketcan:IFACE")
    parser.add_argument("--rt", action="store_true",
                        help="plant, controller and bus hub ask for SCHED_FIFO (where "
                             "permitted), all on the last CPU unless $RHONN_RT_CPUS says")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    if args.rt and "RHONN_RT_CPUS" not in os.environ:
        # lockstep hand-offs between plant, hub and controller are cheapest on one CPU
        # (27× vs 18× on the 2-core VM, see can_db/process/rt.py); the children inherit this
        os.environ["RHONN_RT_CPUS"] = str(max(os.sched_getaffinity(0)))

    factors, turnarounds, steps = [], [], []
    for k in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            res = run_and_report(RunSpec(scenario=args.scenario, controller=args.controller,
                                            out_dir=Path(tmp), bus=args.bus, make_plots=False,
                                            make_rrd=False, rt=args.rt))
            summary = res.metrics.get("plant_summary", {})
            if res.reason != "finished" or not summary.get("loop_wall_s"):
                raise SystemExit(f"run {k} failed: {res.reason}")
            factors.append(summary["sim_time_s"] / summary["loop_wall_s"])
            timing = load_timing_csv(Path(tmp) / "controller_timing.csv")
            turnarounds.append(timing["turnaround_us"][1:])
            steps.append(timing["step_us"][1:])
    ta, st = np.concatenate(turnarounds), np.concatenate(steps)
    result = {
        "controller": args.controller, "scenario": args.scenario, "repeat": args.repeat,
        "bus": args.bus, "rt": args.rt, "factors": [round(f, 2) for f in factors],
        "realtime_factor": float(np.median(factors)),
        "realtime_factor_min": float(np.min(factors)),
        "turnaround_p50_us": float(np.percentile(ta, 50)),
        "turnaround_p99_us": float(np.percentile(ta, 99)),
        "step_p50_us": float(np.percentile(st, 50)), "step_p99_us": float(np.percentile(st, 99)),
        "cycles": int(ta.size),
    }
    print(f"loop ({args.controller}, {args.scenario}, lockstep, bus {args.bus}"
          f"{', rt' if args.rt else ''}, {args.repeat} runs): "
          f"{result['realtime_factor']:.1f}x real time (min {result['realtime_factor_min']:.1f}x); "
          f"turnaround p50 {result['turnaround_p50_us']:.0f} µs, "
          f"p99 {result['turnaround_p99_us']:.0f} µs over {result['cycles']} cycles")
    write_json(args.json, result)
    return 0
