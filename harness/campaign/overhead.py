"""The engine's own cost per run, without any closed loop:

  python -m harness.campaign.overhead [--jobs 2] [--tasks 200] [--repeats 3]

* start: LocalCluster start + client connect, and close (s);
* latency: one no-op task at a time, submit → result (ms): median and p99;
* throughput: ``--tasks`` no-op tasks submitted at once, wall time per task (ms).

A campaign run costs its closed loop plus about one ``latency`` (the worker's wait for the
next task and the row's way back); ``start`` is paid once per campaign.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from can_db.process.argcheck import add_jobs_option
from harness.campaign.engine import Engine, EngineConfig


def _noop(i: int) -> int:
    return i


def measure(workers: int, tasks: int) -> dict[str, float]:
    """One round of the three measurements (s for start/close, ms per task otherwise)."""
    t0 = time.perf_counter()
    eng = Engine(EngineConfig("local", workers)).start()
    eng.client.wait_for_workers(workers)
    start_s = time.perf_counter() - t0
    try:
        lat = []
        for i in range(50):
            t = time.perf_counter()
            eng.submit(_noop, i).result()
            lat.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        futs = [eng.submit(_noop, i) for i in range(tasks)]
        eng.client.gather(futs)
        per_task_ms = (time.perf_counter() - t) * 1e3 / tasks
    finally:
        t = time.perf_counter()
        eng.close()
        close_s = time.perf_counter() - t
    return {"start_s": start_s, "close_s": close_s,
            "latency_ms_p50": float(np.percentile(lat, 50)),
            "latency_ms_p99": float(np.percentile(lat, 99)),
            "throughput_ms_per_task": per_task_ms}


def main(argv: list[str] | None = None) -> int:
    """Print each round and the median over rounds as JSON."""
    p = argparse.ArgumentParser(prog="python -m harness.campaign.overhead",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_jobs_option(p, default=2, help="LocalCluster workers")
    p.add_argument("--tasks", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    rounds = [measure(args.jobs, args.tasks) for _ in range(args.repeats)]
    for r in rounds:
        print(json.dumps({k: round(v, 3) for k, v in r.items()}))
    med = {k: round(float(np.median([r[k] for r in rounds])), 3) for k in rounds[0]}
    print(json.dumps({"median_over_rounds": med, "workers": args.jobs,
                      "tasks": args.tasks, "repeats": args.repeats}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
