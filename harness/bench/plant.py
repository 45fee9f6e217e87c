"""`rhonn-bench plant`: standalone plant model speed (simulated seconds per wall second).

Runs a representative scenario (default ``slippery-curve``: path-following driver, speed
holder, full vehicle model at 1 kHz) the way the process wrapper drives it: every 10 ms cycle
``step_comm()`` + ``sensors()`` + ``truth_row()``. Each repetition builds a fresh simulation
and runs ``--seconds`` of simulated time; we report the median and p10/p90 of the real-time
factor over ``--repeats`` repetitions, plus a breakdown: the vehicle model alone
(``VehicleModel.advance``, tyres + wheels + body + motors) versus the per-cycle overhead
(driver, path projection, sensors, trace row). Nothing here asserts a threshold.

Usage: ``rhonn-bench plant [--json FILE] [--seconds S] [--repeats N] [--scenario NAME]``.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import OneLineParser, number
from plant_sim import kernel
from plant_sim.params import load_vehicle_params
from plant_sim.scenario import list_scenarios, load_scenario
from plant_sim.simulation import Simulation


def _run_full(scenario_name: str, sim_seconds: float) -> tuple[float, float, float]:
    """(simulated s, wall s, model share) of one repetition.

    Pass 1 times the uninstrumented loop; pass 2 (a fresh, identical run) wraps
    ``VehicleModel.advance`` with a timer to get the share of time spent in the model.
    """
    scenario = load_scenario(scenario_name, duration_s=max(sim_seconds, 1.0) + 1.0)
    sim = Simulation(scenario, seed=0)
    n_cycles = round(sim_seconds / sim.comm_period_s)
    t0 = time.perf_counter()
    for _ in range(n_cycles):
        sim.step_comm(None)
        sim.sensors()
        sim.truth_row()
    wall = time.perf_counter() - t0
    simulated = sim.time_s

    sim = Simulation(scenario, seed=0)
    inner = sim.vehicle.advance
    t_model = 0.0

    def timed_advance(*args: Any, **kwargs: Any) -> None:
        nonlocal t_model
        t_start = time.perf_counter()
        inner(*args, **kwargs)
        t_model += time.perf_counter() - t_start

    sim.vehicle.advance = timed_advance  # type: ignore[method-assign]
    t1 = time.perf_counter()
    for _ in range(n_cycles):
        sim.step_comm(None)
        sim.sensors()
        sim.truth_row()
    wall2 = time.perf_counter() - t1
    return simulated, wall, (t_model / wall2 if wall2 > 0 else 0.0)


def main(argv: list[str]) -> int:
    """Entry point for ``rhonn-bench plant``; returns the process exit code."""
    ap = OneLineParser(prog="rhonn-bench plant", description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="write the results to this JSON file")
    ap.add_argument("--seconds", type=number(lo=0.0, lo_open=True, unit="s"), default=20.0,
                    help="simulated s per repetition")
    ap.add_argument("--repeats", type=number(int, lo=1), default=7,
                    help="repetitions (median/p10/p90)")
    ap.add_argument("--scenario", choices=list_scenarios(), default="slippery-curve",
                    metavar="NAME", help="scenario: " + ", ".join(list_scenarios()))
    args = ap.parse_args(argv)
    if args.seconds <= 0 or args.repeats < 1:
        ap.error("--seconds must be > 0 and --repeats >= 1")

    params = load_vehicle_params()
    _run_full(args.scenario, min(1.0, args.seconds))  # warm-up (imports, caches)
    factors, model_shares = [], []
    for _ in range(args.repeats):
        simulated, wall, share = _run_full(args.scenario, args.seconds)
        factors.append(simulated / wall)
        model_shares.append(share)
    steps_per_s = 1.0 / params.step_s
    med = statistics.median(factors)
    # one combined-slip MF evaluation as the vehicle calls it (four per integration step);
    # best of 5 batches, the machine may be shared
    tyre_eval = params.tyres()[0].forces_with_slope
    n_calls = 20000
    batches = []
    for _ in range(5):
        t0 = time.perf_counter()
        for k in range(n_calls):
            tyre_eval(0.01 + 1e-7 * k, 0.03, 5000.0, 0.9, 0.9)
        batches.append((time.perf_counter() - t0) / n_calls)
    us_tyre = 1e6 * min(batches)
    result = {
        "benchmark": "plant",
        "scenario": args.scenario,
        "integration_rate_hz": steps_per_s,
        "comm_period_s": params.comm_period_s,
        "simulated_seconds_per_repeat": args.seconds,
        "repeats": args.repeats,
        "realtime_factor": med,
        "realtime_factor_p10": float(np.percentile(factors, 10)),
        "realtime_factor_p90": float(np.percentile(factors, 90)),
        "us_per_integration_step": 1e6 / (med * steps_per_s),
        "vehicle_model_share": statistics.median(model_shares),
        "us_per_tyre_call": us_tyre,
        "kernel": "numba" if kernel.enabled() else "python",
        "tyre_share": 4.0 * us_tyre / (1e6 / (med * steps_per_s)),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    print(f"plant model, scenario {args.scenario}, {steps_per_s:.0f} Hz fixed step, "
          f"{args.repeats} x {args.seconds:g} s simulated")
    print(f"  real-time factor: median {med:.1f}x  (p10 {result['realtime_factor_p10']:.1f}x, "
          f"p90 {result['realtime_factor_p90']:.1f}x)")
    print(f"  {result['us_per_integration_step']:.1f} µs per 1 ms integration step (all in);"
          f" vehicle model (4 MF tyres, wheels, body, motors) "
          f"{100 * result['vehicle_model_share']:.0f} % of the time, the rest is the per-cycle"
          " driver, path projection, sensors and trace row")
    if kernel.enabled():
        print("  vehicle model: compiled kernel (plant_sim/kernel.py, bit-identical to the "
              "Python model; RHONN_PLANT_KERNEL=python for the interpreted one)")
    else:
        print(f"  one combined-slip MF call {us_tyre:.2f} µs (interpreted) -> the 4 tyres are ~"
              f"{100 * result['tyre_share']:.0f} % of the total")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
