"""`rhonn-bench soak`: a long real-time 100 Hz closed loop under a bus flood and frame loss.

The plant runs in real time on a constant-radius circle (μ = 1, 50 km/h held, R = 100 m,
enough laps for the duration); the controller runs the 100 Hz configuration
(``controller/config/100hz.toml``: a full MPC step every 10 ms cycle), with the faults
``flood:5000`` (unknown-ID frames from a third process) and ``loss:5%`` on every frame.
Plant and controller ask for SCHED_FIFO (``--no-rt``: normal scheduling).

Targets (exit code 1 when one is missed, each named): 0 deadline misses (an answer later than
one period after the SYNC), period jitter p99 ≤ 1 ms, no gen-2 collection in the controller
longer than 1 ms, controller RSS flat over the last half of the run (growth ≤ 128 kB between
the resident-set samples, taken every 1000 cycles). Progress is printed every 30 s.
"""

from __future__ import annotations

import math
import tempfile
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import OneLineParser, UsageError, check_out_dir, check_out_file, number
from can_db.process.rowlog import RowTail, rows_path
from controller.core.registry import CONTROLLER_NAMES
from harness.analysis.run_data import load_timing_csv
from harness.analysis.run_status import partial_note
from harness.bench.stats import write_json
from harness.report.run_report import run_and_report
from harness.run import signals
from harness.run.marker import mark_interrupted
from harness.run.spec import RunSpec

SPEED_KMH = 50.0
RADIUS_M = 100.0
JITTER_P99_TARGET_US = 1000.0
GC2_PAUSE_TARGET_MS = 1.0
RSS_GROWTH_TARGET_KB = 128
PROGRESS_EVERY_S = 30.0


def _progress(timing_csv: Path, minutes: float, stop: threading.Event) -> None:
    """Print cycles, misses and the worst turnaround so far, every PROGRESS_EVERY_S (read
    from the controller's timing row file while it runs, can_db/process/rowlog.py)."""
    start = time.monotonic()
    tail = RowTail(rows_path(timing_csv))
    cycles = misses = 0
    worst_us = 0.0
    while not stop.wait(PROGRESS_EVERY_S):
        new = tail.rows()
        if new:
            cycles += len(new["cycle"])
            misses += int(np.count_nonzero(new["deadline_miss"]))
            worst_us = max(worst_us, float(np.max(new["turnaround_us"])))
        elapsed = (time.monotonic() - start) / 60.0
        print(f"soak: {elapsed:4.1f}/{minutes:g} min, {cycles} cycles, deadline misses "
              f"{misses}, turnaround max {worst_us / 1000.0:.2f} ms", flush=True)
    tail.close()


def _targets(result: dict[str, Any]) -> list[str]:
    """The targets missed, as short sentences (empty: all met)."""
    missed = []
    if result["reason"] != "finished":
        missed.append(f"run did not finish: {result['reason']}")
    if result["deadline_misses"] != 0:
        missed.append(f"{result['deadline_misses']} deadline misses (target 0)")
    jitter = result["period_jitter_p99_us"]
    if jitter is None or not jitter <= JITTER_P99_TARGET_US:
        missed.append(f"period jitter p99 {jitter} µs (target ≤ {JITTER_P99_TARGET_US:.0f})")
    gc2 = result["gc2_max_pause_ms"]
    if gc2 is None or gc2 > GC2_PAUSE_TARGET_MS:
        missed.append(f"longest gen-2 collection {gc2} ms (target ≤ {GC2_PAUSE_TARGET_MS})")
    growth = result["rss_growth_last_half_kb"]
    if growth is None or growth > RSS_GROWTH_TARGET_KB:
        missed.append(f"controller RSS grew {growth} kB over the last half "
                      f"(target ≤ {RSS_GROWTH_TARGET_KB})")
    return missed


def _r(value: Any, digits: int = 0) -> Any:
    """Round a figure for printing and JSON (None stays None)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return value
    return round(float(value), digits) if digits else round(float(value))


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
    parser.add_argument("--bus", default="auto",
                        help="bus spec: auto (default), local:NAME, remote:new, socketcan:IFACE")
    parser.add_argument("--no-rt", action="store_true",
                        help="normal scheduling only (default: SCHED_FIFO where permitted)")
    parser.add_argument("--out", default=None,
                        help="keep the run directory here (default: a temporary one)")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    signals.install()  # SIGINT/SIGTERM: the run stops, the partial figures are reported
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
        out.mkdir(parents=True, exist_ok=True)
        print(f"soak: {args.minutes:g} min real time, {args.controller} @100 Hz, faults "
              f"{faults}, bus {args.bus}, {'normal scheduling' if args.no_rt else 'SCHED_FIFO'}"
              f" (run dir {out})", flush=True)
        stop = threading.Event()
        ticker = threading.Thread(target=_progress, daemon=True,
                                  args=(out / "controller_timing.csv", args.minutes, stop))
        ticker.start()
        try:
            res = run_and_report(RunSpec(
                scenario="constant-radius", controller=args.controller, out_dir=out,
                bus=args.bus, mode="realtime", controller_config=config,
                speed_kmh=SPEED_KMH, duration_s=duration, faults=faults, make_plots=False,
                make_rrd=False, wall_timeout_s=duration + 120.0, rt=not args.no_rt,
                params={"radius_m": RADIUS_M, "laps": laps, "speed_ramp_kmhps": 0.0,
                        "duration_s": duration + 1.0}))
        finally:
            stop.set()
        timing = load_timing_csv(out / "controller_timing.csv")
    m = res.metrics
    summary = m.get("controller_summary", {})
    rss = summary.get("rss_samples_kb", [])
    half = len(rss) // 2
    growth_kb = (rss[-1] - rss[half]) if len(rss) >= 4 else None
    gc_info = summary.get("gc", {})
    gc2 = gc_info.get("max_pause_ms", [None, None, None])[2]
    turnaround = timing.get("turnaround_us", np.zeros(0))
    result = {
        "minutes": args.minutes, "controller": args.controller, "faults": faults,
        "rt": not args.no_rt, "reason": res.reason, "cycles": int(turnaround.size),
        "deadline_misses": m.get("deadline_misses"),
        "period_jitter_p99_us": _r(m.get("period_jitter_us_p99")),
        "turnaround_p50_us": _r(m.get("turnaround_us_p50")),
        "turnaround_p99_us": _r(m.get("turnaround_us_p99")),
        "turnaround_max_us": _r(turnaround.max()) if turnaround.size else None,
        "step_p50_us": _r(m.get("step_us_p50")), "step_p99_us": _r(m.get("step_us_p99")),
        "fallback_events": m.get("fallback_events"),
        "plant_overruns": m.get("plant_summary", {}).get("overruns"),
        "gc_collections": gc_info.get("collections"), "gc2_max_pause_ms": gc2,
        "rss_samples_kb": rss, "rss_growth_last_half_kb": growth_kb,
        "frames_rejected": m.get("frames_rejected"),
        "bus_dropped_by_node": {n["name"]: n["dropped"]
                                for n in (m.get("bus_hub") or {}).get("nodes", [])
                                if n.get("dropped")},
        "spun": m.get("spun"),
        # cycles > 5 ms, with what the process was doing (can_db/process/stall.py)
        "controller_stalls": summary.get("stalls"),
        "plant_stalls": m.get("plant_summary", {}).get("stalls"),
    }
    result["targets_missed"] = _targets(result)
    if m.get("interrupted"):  # a signal: report what ran, no verdict on the targets
        result.update(interrupted=True, sim_time_reached_s=m.get("sim_time_reached_s"))
        note = partial_note(m)
        write_json(args.json, result)
        if args.out:
            mark_interrupted(Path(args.out), signals.received(), f"{note}; soak figures of "
                             "the part that ran are in metrics.json")
        print(f"soak: {note} — {result['cycles']} cycles, deadline misses "
              f"{result['deadline_misses']}; targets not judged", flush=True)
        return signals.exit_code()
    print(f"soak {args.minutes:g} min, {args.controller} @100 Hz, faults {faults}: "
          f"{result['cycles']} cycles, deadline misses {result['deadline_misses']}, "
          f"period jitter p99 {result['period_jitter_p99_us']} µs, turnaround p50 "
          f"{result['turnaround_p50_us']} / p99 {result['turnaround_p99_us']} / max "
          f"{result['turnaround_max_us']} µs, gen-2 collections "
          f"{(gc_info.get('collections') or [None] * 3)[2]} (longest {gc2} ms), controller "
          f"RSS {rss[half] if rss else None} → {rss[-1] if rss else None} kB over the last "
          f"half ({growth_kb} kB), fallback cycles {result['fallback_events']}, plant "
          f"overruns {result['plant_overruns']}, frames dropped by full node queues "
          f"{result['bus_dropped_by_node']}, reason {res.reason}")
    for who in ("controller", "plant"):
        stalls = result[f"{who}_stalls"] or {}
        if stalls.get("stalls"):
            print(f"soak: {who} stalls > {stalls['threshold_ms']:g} ms: {stalls['stalls']} "
                  f"(longest {stalls['worst_ms']} ms); newest: {stalls['recent'][-1]}",
                  flush=True)
    write_json(args.json, result)
    if result["targets_missed"]:
        print("soak: targets missed: " + "; ".join(result["targets_missed"]), flush=True)
        return 1
    print("soak: every target met", flush=True)
    return 0
