"""`rhonn-harness campaign CAMPAIGN.toml [--scheduler local|ADDRESS] [--jobs N] [--out DIR]
[--resume] [--retry-failed] [--duration S] [--seeds SPEC] [--dashboard PORT]
[--no-progress]`.

``--jobs N`` is the number of LocalCluster workers (= concurrent runs); the old spelling
``--workers N`` still works with a deprecation warning. ``--seeds SPEC`` replaces the file's
seeds: ``0,1,2,3,4``, ``0-4`` (can_db/process/argcheck.py, seed_spec)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from can_db.process.argcheck import add_jobs_option, error_line, number, seed_spec
from harness.campaign.engine import EngineConfig, EngineError, worker_count_hint
from harness.campaign.runner import CampaignRunner
from harness.campaign.spec import CampaignError, load_campaign
from harness.campaign.summary import format_summary
from harness.campaign.task import check_runs
from harness.run import signals
from harness.run.marker import clear_interrupted, mark_interrupted


def _value(x: object, unit: str) -> str:
    """A figure with its unit, or "—" where there is none (no seed gave one)."""
    return "—" if x is None else f"{x} {unit}"


def study_lines(studies: dict) -> list[str]:
    """One line per study and controller: v_max median [min–max] over the seeds, or the
    seeds passing every amplitude; "—" for a figure no seed gave."""
    out = []
    for name, study in studies.items():
        for c, s in study["controllers"].items():
            if study["kind"] == "vmax":
                v = s["vmax_kmh"]
                span = "" if v["min"] is None else f" [{v['min']}–{v['max']}]"
                out.append(f"{name}: {c}: v_max median {_value(v['median'], 'km/h')}{span} "
                           f"over {v['n']} seeds ({', '.join(s['statuses'])})")
            else:
                f = s["first_fail_amplitude_deg"]
                out.append(f"{name}: {c}: {s['seeds_passing_all']}/{s['n_seeds']} seeds pass "
                           f"every amplitude; first failing amplitude median "
                           f"{_value(f['median'], 'deg')}")
    return out

def add_engine_options(p: argparse.ArgumentParser) -> None:
    """--scheduler, --jobs (hidden old spelling --workers), --dashboard, --connect-timeout."""
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster on 127.0.0.1) | tcp://HOST:PORT | scheduler file")
    add_jobs_option(p, worker_count_hint(),
                    "LocalCluster worker processes = concurrent runs (default: %(default)s)",
                    deprecated=("--workers",))
    p.add_argument("--dashboard", type=number(int, lo=1, hi=65535), default=None,
                   metavar="PORT",
                   help="serve the dask dashboard on 127.0.0.1:PORT (default: off)")
    p.add_argument("--connect-timeout", type=number(lo=0.0, lo_open=True, unit="s"),
                   default=20.0, metavar="S",
                   help="seconds to wait for an external scheduler and its first worker")


def engine_config(args: argparse.Namespace) -> EngineConfig:
    """The engine settings of parsed options."""
    return EngineConfig(scheduler=args.scheduler, workers=args.jobs,
                        dashboard_port=args.dashboard, connect_timeout_s=args.connect_timeout)


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register the `campaign` subcommand."""
    p = sub.add_parser("campaign", help="a campaign of runs on dask (resumable, Parquet)")
    p.add_argument("file", help="campaign TOML (see harness/campaign/campaigns/)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output directory (default: runs/campaign-NAME)")
    p.add_argument("--resume", action="store_true", help="run only what DIR does not hold yet")
    p.add_argument("--retry-failed", action="store_true",
                   help="with --resume: also run again the runs recorded as failed")
    p.add_argument("--duration", type=number(lo=0.0, lo_open=True, unit="s"), default=None,
                   metavar="S", help="cap every run at this many simulated s (smoke campaigns)")
    p.add_argument("--seeds", type=seed_spec, default=None, metavar="SPEC",
                   help="seeds replacing the file's, e.g. 0-4 or 0,1,2,3,4")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_engine_options(p)
    p.set_defaults(func=cmd_campaign, error_parser=p)


def cmd_campaign(args: argparse.Namespace) -> int:
    """Run the campaign; 0 if every run finished, 1 if some failed, 2 on bad input."""

    out = Path(args.out or "runs/campaign")
    try:
        seeds = list(args.seeds) if args.seeds else None
        campaign = load_campaign(Path(args.file), duration_cap_s=args.duration, seeds=seeds)
        out = Path(args.out or f"runs/campaign-{campaign.name}")
        check_runs(campaign.runs, out)  # every run as `run` checks it, before any starts
        result = CampaignRunner(campaign, out, engine_config(args), resume=args.resume,
                                retry_failed=args.retry_failed,
                                progress=not args.no_progress).run()
    except (CampaignError, EngineError) as exc:
        return error_line("rhonn-harness campaign", str(exc))
    except KeyboardInterrupt:  # SIGINT or SIGTERM (harness/run/signals.py)
        note = (f"interrupted: the finished runs are kept in {out}/parts; finish with "
                f"--resume")
        if out.is_dir():
            mark_interrupted(out, signals.received(), note)
        print(f"\nrhonn-harness campaign: {note}", file=sys.stderr)
        return signals.exit_code()
    clear_interrupted(out)
    print(format_summary(result.summary))
    for line in study_lines(result.studies):
        print(line)
    print(f"\ncampaign {campaign.name}: {len(result.rows)} runs ({result.executed} run now, "
          f"{result.cached} resumed, {len(result.failed)} failed) in {result.wall_time_s:.0f} s "
          f"-> {result.out}/results.parquet, summary.csv, studies.json, runs/")
    for r in result.failed[:10]:
        print(f"failed: {r['group']}/{r['key']} {r['scenario']} {r['controller']} "
              f"seed {r['seed']}: {r['error'] or r['reason']}", file=sys.stderr)
    return 1 if result.failed else 0
