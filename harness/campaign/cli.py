"""`rhonn-harness campaign CAMPAIGN.toml [--scheduler local|ADDRESS] [--workers N] [--out DIR]
[--resume] [--retry-failed] [--duration S] [--seeds 0,1,...] [--dashboard PORT]
[--no-progress]`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from harness.campaign.engine import EngineConfig, EngineError, worker_count_hint
from harness.campaign.spec import CampaignError, load_campaign


def add_engine_options(p: argparse.ArgumentParser) -> None:
    """--scheduler, --workers, --dashboard (shared by `campaign` and `paper`)."""
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster on 127.0.0.1) | tcp://HOST:PORT | scheduler file")
    p.add_argument("--workers", type=int, default=worker_count_hint(),
                   help="LocalCluster worker processes = concurrent runs (default: %(default)s)")
    p.add_argument("--dashboard", type=int, default=None, metavar="PORT",
                   help="serve the dask dashboard on 127.0.0.1:PORT (default: off)")
    p.add_argument("--connect-timeout", type=float, default=20.0, metavar="S",
                   help="seconds to wait for an external scheduler and its first worker")


def engine_config(args: argparse.Namespace) -> EngineConfig:
    """The engine settings of parsed options."""
    return EngineConfig(scheduler=args.scheduler, workers=args.workers,
                        dashboard_port=args.dashboard, connect_timeout_s=args.connect_timeout)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register the `campaign` subcommand."""
    p = sub.add_parser("campaign", help="a campaign of runs on dask (resumable, Parquet)")
    p.add_argument("file", help="campaign TOML (see harness/campaign/campaigns/)")
    p.add_argument("--out", default=None, help="output directory (default: runs/campaign-NAME)")
    p.add_argument("--resume", action="store_true", help="run only what DIR does not hold yet")
    p.add_argument("--retry-failed", action="store_true",
                   help="with --resume: also run again the runs recorded as failed")
    p.add_argument("--duration", type=float, default=None,
                   help="cap every run at this many simulated s (smoke campaigns)")
    p.add_argument("--seeds", default=None,
                   help="comma-separated seeds replacing the file's (e.g. 0,1,2,3,4)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_engine_options(p)
    p.set_defaults(func=cmd_campaign)


def cmd_campaign(args: argparse.Namespace) -> int:
    """Run the campaign; 0 if every run finished, 1 if some failed, 2 on bad input."""
    from harness.campaign.runner import CampaignRunner
    from harness.campaign.summary import format_summary

    out = Path(args.out or "runs/campaign")
    try:
        seeds = None
        if args.seeds:
            try:
                seeds = [int(x) for x in args.seeds.split(",")]
            except ValueError as exc:
                raise CampaignError(f"--seeds {args.seeds!r}: comma-separated integers") \
                    from exc
        campaign = load_campaign(Path(args.file), duration_cap_s=args.duration, seeds=seeds)
        out = Path(args.out or f"runs/campaign-{campaign.name}")
        result = CampaignRunner(campaign, out, engine_config(args), resume=args.resume,
                                retry_failed=args.retry_failed,
                                progress=not args.no_progress).run()
    except (CampaignError, EngineError) as exc:
        print(f"rhonn-harness campaign: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nrhonn-harness campaign: interrupted; the finished runs are kept in {out}/parts, "
              "finish with --resume", file=sys.stderr)
        return 130
    print(format_summary(result.summary))
    for name, study in result.studies.items():
        for c, s in study["controllers"].items():
            if study["kind"] == "vmax":
                v = s["vmax_kmh"]
                print(f"{name}: {c}: v_max median {v['median']} km/h "
                      f"[{v['min']}–{v['max']}] over {v['n']} seeds ({', '.join(s['statuses'])})")
            else:
                f = s["first_fail_amplitude_deg"]
                print(f"{name}: {c}: {s['seeds_passing_all']}/{s['n_seeds']} seeds pass every "
                      f"amplitude; first failing amplitude median {f['median']} deg")
    print(f"\ncampaign {campaign.name}: {len(result.rows)} runs ({result.executed} run now, "
          f"{result.cached} resumed, {len(result.failed)} failed) in {result.wall_time_s:.0f} s "
          f"-> {result.out}/results.parquet, summary.csv, studies.json, runs/")
    for r in result.failed[:10]:
        print(f"failed: {r['group']}/{r['key']} {r['scenario']} {r['controller']} "
              f"seed {r['seed']}: {r['error'] or r['reason']}", file=sys.stderr)
    return 1 if result.failed else 0
