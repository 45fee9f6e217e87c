"""`rhonn-bench soak`: a long real-time 100 Hz closed loop under a bus flood and frame loss.

The plant runs in real time on a constant-radius circle (μ = 1, 50 km/h held, R = 100 m,
enough laps for the duration); the controller runs the 100 Hz configuration
(``controller/config/100hz.toml``: a full MPC step every 10 ms cycle), with the faults
``flood:5000`` (unknown-ID frames from a third process) and ``loss:5%`` on every frame.
Reports deadline misses (answer later than one period after the SYNC), period jitter p99,
max rx→tx turnaround and the controller's memory growth (resident set sampled every 1000
cycles; growth = last sample − the sample after warm-up).
"""

from __future__ import annotations

import math
import tempfile
from importlib import resources
from pathlib import Path

import numpy as np

from can_db.argcheck import OneLineParser, UsageError, check_out_dir, check_out_file, number
from controller.core.registry import CONTROLLER_NAMES
from harness.analysis.run_data import load_timing_csv
from harness.bench.stats import write_json
from harness.run.runner import RunConfig, run_closed_loop
from harness.tools.progress import Bar

SPEED_KMH = 50.0
RADIUS_M = 100.0


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench soak", description=__doc__)
    parser.add_argument("--minutes", type=number(lo=0.0, hi=24 * 60.0, lo_open=True,
                                                 unit="min"), default=10.0,
                        help="length of the real-time run, min (wall = simulated)")
    parser.add_argument("--controller", choices=CONTROLLER_NAMES, default="nmpc-rhonn",
                        help="controller under test (at 100 Hz, config 100hz.toml)")
    parser.add_argument("--flood", type=number(lo=0.0, hi=50_000.0, unit="frames/s"),
                        default=5000.0, help="flood of foreign frames, frames/s, 0 = off")
    parser.add_argument("--loss", type=number(lo=0.0, hi=100.0, unit="%"), default=5.0,
                        help="random frame loss, percent, 0 = off")
    parser.add_argument("--out", default=None,
                        help="keep the run directory here (default: a temporary one)")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    try:
        if args.out:
            check_out_dir(args.out)
        if args.json:
            check_out_file(args.json, "--json")
    except UsageError as exc:
        parser.error(str(exc))

    duration = args.minutes * 60.0
    laps = math.ceil(SPEED_KMH / 3.6 * duration / (2 * math.pi * RADIUS_M)) + 1
    config = str(resources.files("controller").joinpath("config/100hz.toml"))
    faults = []
    if args.flood > 0:
        faults.append(f"flood:{args.flood:g}")
    if args.loss > 0:
        faults.append(f"loss:{args.loss:g}%")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        bar = Bar("soak", total=round(duration), unit="sim s", line_every_s=30.0)
        res = run_closed_loop(RunConfig(
            scenario="constant-radius", controller=args.controller, out_dir=out,
            mode="realtime", controller_config=config, speed_kmh=SPEED_KMH,
            duration_s=duration, faults=faults, make_plots=False, make_rrd=False,
            wall_timeout_s=duration + 120.0,
            params={"radius_m": RADIUS_M, "laps": laps, "speed_ramp_kmhps": 0.0,
                    "duration_s": duration + 1.0}),
            progress=lambda t: bar.set(round(t)))
        bar.close()
        timing = load_timing_csv(out / "controller_timing.csv")
    m = res.metrics
    rss = m.get("controller_summary", {}).get("rss_samples_kb", [])
    growth_kb = (rss[-1] - rss[1]) if len(rss) >= 3 else None
    turnaround = timing.get("turnaround_us", np.zeros(0))
    result = {
        "minutes": args.minutes, "controller": args.controller, "faults": faults,
        "reason": res.reason, "cycles": int(turnaround.size),
        "deadline_misses": m.get("deadline_misses"),
        "period_jitter_p99_us": m.get("period_jitter_us_p99"),
        "turnaround_p50_us": m.get("turnaround_us_p50"),
        "turnaround_p99_us": m.get("turnaround_us_p99"),
        "turnaround_max_us": float(turnaround.max()) if turnaround.size else None,
        "step_p50_us": m.get("step_us_p50"), "step_p99_us": m.get("step_us_p99"),
        "fallback_events": m.get("fallback_events"),
        "plant_overruns": m.get("plant_summary", {}).get("overruns"),
        "rss_samples_kb": rss, "memory_growth_kb": growth_kb,
        "frames_rejected": m.get("frames_rejected"),
        "spun": m.get("spun"),
    }
    print(f"soak {args.minutes:g} min, {args.controller} @100 Hz, faults {faults}: "
          f"{result['cycles']} cycles, deadline misses {result['deadline_misses']}, "
          f"period jitter p99 {result['period_jitter_p99_us']} µs, turnaround p99 "
          f"{result['turnaround_p99_us']} µs / max {result['turnaround_max_us']} µs, "
          f"memory growth {growth_kb} kB (RSS samples {rss[:3]}…{rss[-2:]}), "
          f"fallback cycles {result['fallback_events']}, plant overruns "
          f"{result['plant_overruns']}, reason {res.reason}")
    write_json(args.json, result)
    return 0 if res.reason == "finished" else 1
