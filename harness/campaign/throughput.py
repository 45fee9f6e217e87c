"""Campaign throughput over the bus, engine start included:

  python -m harness.campaign.throughput [--jobs 2] [--scheduler ADDRESS] [--repeats 3]
                                        [--campaign FILE] [--json FILE]

Runs the campaign (default: campaigns/throughput.toml, 24 dlc-paper runs) into a fresh
temporary directory ``--repeats`` times and reports per round: the wall time from before the
engine starts to the last row (s), runs per minute, and the per-run overhead on the warm
benches — run wall minus the plant's loop wall (s), median and p99 — with the benches'
counters (soft and hard resets, processes started, retries).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import add_jobs_option
from harness.campaign.engine import EngineConfig
from harness.campaign.runner import CampaignRunner
from harness.campaign.spec import load_campaign

BENCH_COUNTERS = ("soft_resets", "hard_resets", "controller_starts", "plant_starts",
                  "retries", "replaced")


def default_campaign() -> Path:
    """The packaged 24-run throughput campaign."""
    return Path(str(resources.files("harness.campaign").joinpath(
        "campaigns/throughput.toml")))


def measure(campaign_file: Path, engine: EngineConfig) -> dict[str, Any]:
    """One round: wall s, runs/min, overhead s (median, p99) and the benches' counters."""
    campaign = load_campaign(campaign_file)
    with tempfile.TemporaryDirectory(prefix="rhonn-throughput-") as tmp:
        t0 = time.monotonic()
        result = CampaignRunner(campaign, Path(tmp), engine, progress=False).run()
        wall_s = time.monotonic() - t0
    rows = list(result.rows.values())
    overhead = [r["run_wall_s"] - r["loop_wall_s"] for r in rows
                if r.get("run_wall_s") is not None and r.get("loop_wall_s") is not None]
    loops = [r["loop_wall_s"] for r in rows if r.get("loop_wall_s") is not None]
    counters = {k: 0 for k in BENCH_COUNTERS}
    for r in rows:
        bench = json.loads(r.get("bench") or "{}")
        for k in BENCH_COUNTERS:
            counters[k] += int(bench.get(k) or 0)
    return {"runs": len(rows), "failed": len(result.failed), "wall_s": round(wall_s, 2),
            "runs_per_min": round(60.0 * len(rows) / wall_s, 2),
            "overhead_s_median": round(float(np.median(overhead)), 3) if overhead else None,
            "overhead_s_p99": round(float(np.percentile(overhead, 99)), 3)
            if overhead else None,
            "loop_wall_s_median": round(float(np.median(loops)), 3) if loops else None,
            "bench": counters}


def main(argv: list[str] | None = None) -> int:
    """Print each round as JSON, then the medians over rounds."""
    p = argparse.ArgumentParser(prog="python -m harness.campaign.throughput",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_jobs_option(p, default=2, help="LocalCluster workers")
    p.add_argument("--scheduler", default="local",
                   help="local, or a running scheduler's address tcp://127.0.0.1:PORT")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--campaign", type=Path, default=None,
                   help="campaign file (default: the packaged throughput.toml)")
    p.add_argument("--json", type=Path, default=None, help="also write the rounds here")
    args = p.parse_args(argv)
    engine = EngineConfig(args.scheduler, args.jobs)
    rounds = []
    for _ in range(args.repeats):
        rounds.append(measure(args.campaign or default_campaign(), engine))
        print(json.dumps(rounds[-1]), flush=True)
    keys = ("wall_s", "runs_per_min", "overhead_s_median", "overhead_s_p99")
    med = {k: float(np.median([r[k] for r in rounds if r[k] is not None])) for k in keys}
    summary = {"median_over_rounds": med, "scheduler": args.scheduler, "workers": args.jobs,
               "repeats": args.repeats}
    print(json.dumps(summary))
    if args.json is not None:
        args.json.write_text(json.dumps({"rounds": rounds, **summary}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
