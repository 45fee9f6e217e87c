"""`rhonn-harness`: closed-loop runs over the bus, controller comparisons, offline replay.

  rhonn-harness run SCENARIO --controller NAME [--bus auto|SPEC] [--mode lockstep|realtime]
                    [--out DIR] [--mu X] [--speed KMH] [--seed N] [--duration S]
  rhonn-harness compare SCENARIO [--controllers a,b,...] [--out DIR] [...]
  rhonn-harness replay LOG.blf --controller NAME
  rhonn-harness paper --out DIR [--jobs N] [--quick] [--scheduler local|ADDRESS]
  rhonn-harness campaign CAMPAIGN.toml [--scheduler local|ADDRESS] [--workers N] [--out DIR]
                         [--resume]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from can_db.faults import FaultSpecError
from harness.campaign import cli as campaign_cli
from harness.run.runner import RunConfig, run_closed_loop

SUMMARY_KEYS = (
    ("completed", "completed", "{}"), ("spun", "spun", "{}"),
    ("max |beta| deg", "max_abs_beta_deg", "{:.2f}"),
    ("max |lat dev| m", "max_abs_lateral_dev_m", "{:.3f}"),
    ("rms lat dev m", "rms_lateral_dev_m", "{:.3f}"),
    ("phase area", "phase_area", "{:.4f}"),
    ("max |swa| deg", "max_abs_swa_deg", "{:.1f}"),
    ("max |dM| Nm", "max_abs_dM_Nm", "{:.0f}"),
    ("step p50/p99 us", ("step_us_p50", "step_us_p99"), "{:.0f} / {:.0f}"),
    ("turnaround p50/p99 us", ("turnaround_us_p50", "turnaround_us_p99"), "{:.0f} / {:.0f}"),
    ("deadline misses", "deadline_misses", "{}"),
    ("fallback events", "fallback_events", "{}"),
    ("frames rejected", "frames_rejected", "{}"),
)


def _fmt(metrics: dict[str, Any], key: Any, fmt: str) -> str:
    keys = key if isinstance(key, tuple) else (key,)
    values = [metrics.get(k) for k in keys]
    if any(v is None for v in values):
        return "-"
    try:
        return fmt.format(*values)
    except (TypeError, ValueError):
        return str(values[0] if len(values) == 1 else values)


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    """KPI table: one column per run."""
    names = list(rows)
    width = max(12, *(len(n) for n in names))
    print(f"{'KPI':<24}" + "".join(f"{n:>{width + 2}}" for n in names))
    for label, key, fmt in SUMMARY_KEYS:
        print(f"{label:<24}" + "".join(f"{_fmt(rows[n], key, fmt):>{width + 2}}"
                                        for n in names))


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bus", default="auto", help="auto | socketcan:IFACE | remote:URL")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    p.add_argument("--controller-mode", choices=("lockstep", "freerun"), default="lockstep",
                   help="controller answers SYNC frames (lockstep) or runs its own schedule")
    p.add_argument("--config", default=None, help="controller TOML")
    p.add_argument("--mu", type=float, default=None)
    p.add_argument("--speed", type=float, default=None, help="km/h")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=None, help="sim seconds")
    p.add_argument("--param", action="append", default=[], help="scenario KEY=VALUE")
    p.add_argument("--fault", action="append", default=[],
                   help="inject a fault: KIND[:ARG][@T], repeatable (see README, Faults)")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--no-rrd", action="store_true")


def _config(args: argparse.Namespace, controller: str, out: Path) -> RunConfig:
    params = dict(item.split("=", 1) for item in args.param)
    return RunConfig(scenario=args.scenario, controller=controller, out_dir=out, bus=args.bus,
                     mode=args.mode, controller_mode=args.controller_mode,
                     controller_config=args.config, mu=args.mu, speed_kmh=args.speed,
                     seed=args.seed, duration_s=args.duration, params=params,
                     faults=list(args.fault),
                     make_plots=not args.no_plots, make_rrd=not args.no_rrd)


def cmd_run(args: argparse.Namespace) -> int:
    out = Path(args.out or f"runs/{args.scenario}-{args.controller}")
    result = run_closed_loop(_config(args, args.controller, out))
    print_table({args.controller: result.metrics})
    print(f"\nrun: {result.reason}")
    print(f"results in {out}/: metrics.json, truth.csv, bus.blf, controller_timing.csv"
          + (", run.rrd" if "rrd" in result.metrics else "")
          + (f", {len(result.metrics.get('plots', []))} PNG plots"
             if result.metrics.get("plots") else ""))
    if "analysis_error" in result.metrics:
        print(f"analysis error: {result.metrics['analysis_error']}", file=sys.stderr)
    if "rrd" in result.metrics:
        print(f"open the timeline: rerun analytics disable && rerun {out}/run.rrd")
    return 0 if result.reason == "finished" else 1


def cmd_compare(args: argparse.Namespace) -> int:
    from controller.core.registry import CONTROLLER_NAMES

    names = args.controllers.split(",") if args.controllers else list(CONTROLLER_NAMES)
    base = Path(args.out or f"runs/compare-{args.scenario}")
    rows: dict[str, dict[str, Any]] = {}
    for name in names:
        print(f"running {args.scenario} with {name} ...", flush=True)
        rows[name] = run_closed_loop(_config(args, name, base / name)).metrics
    print_table(rows)
    try:
        from harness.analysis.course import course_geometry, scenario_for
        from harness.analysis.run_data import load_run
        from harness.viz.plots import write_overlay_plots

        cfg = _config(args, names[0], base)
        geo = course_geometry(scenario_for(cfg.scenario, cfg.mu, cfg.speed_kmh, cfg.params))
        runs = {n: load_run(base / n) for n in names}
        plots = write_overlay_plots(runs, geo.boundaries, geo.ref_path, base, cones=geo.cones)
        print(f"overlay plots: {', '.join(str(p) for p in plots)}")
    except Exception as exc:
        print(f"overlay plots failed: {exc!r}", file=sys.stderr)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from harness.run.replay import replay_log

    result = replay_log(args.log, args.controller, args.config)
    verdict = "BIT-IDENTICAL" if result.bit_identical else "DIFFERENT"
    print(f"replay of {args.log} with {args.controller}: {verdict} — recorded "
          f"{result.recorded} torque frames, replayed {result.replayed}, identical "
          f"{result.identical}, first mismatch {result.first_mismatch}")
    return 0 if result.bit_identical else 1


def cmd_paper(args: argparse.Namespace) -> int:
    from harness.campaign.engine import EngineConfig, EngineError, session
    from harness.paper.study import run_paper

    out = Path(args.out)
    try:
        with session(EngineConfig(args.scheduler, max(1, args.jobs), args.dashboard)):
            tables = run_paper(out, jobs=args.jobs, quick=args.quick)  # its pools: this engine
    except EngineError as exc:
        print(f"rhonn-harness paper: {exc}", file=sys.stderr)
        return 2
    meta = tables.get("meta", {})
    print(f"paper reproduction: {meta.get('runs')} runs in {meta.get('wall_time_s', 0):.0f} s "
          f"-> {out}/report.md, {out}/tables.json, {out}/figures/")
    failed = meta.get("failed_runs", [])
    if failed:
        print(f"{len(failed)} runs did not finish normally: {', '.join(failed)}",
              file=sys.stderr)
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rhonn-harness", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="one closed-loop run over the bus")
    p.add_argument("scenario")
    p.add_argument("--controller", required=True)
    p.add_argument("--out", default=None, help="output directory")
    _add_run_options(p)
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("compare", help="run every controller on one scenario")
    p.add_argument("scenario")
    p.add_argument("--controllers", default=None, help="comma-separated (default: all)")
    p.add_argument("--out", default=None)
    _add_run_options(p)
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser("replay", help="replay a bus log through a controller offline")
    p.add_argument("log")
    p.add_argument("--controller", required=True)
    p.add_argument("--config", default=None)
    p.set_defaults(func=cmd_replay)
    p = sub.add_parser("paper", help="the paper's experiments + FMVSS 126, report and tables")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--jobs", type=int, default=2, help="parallel runs (each a full bus run)")
    p.add_argument("--quick", action="store_true", help="reduced smoke set (≈ 1 min)")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster of --jobs workers) | tcp://HOST:PORT")
    p.add_argument("--dashboard", type=int, default=None, metavar="PORT",
                   help="dask dashboard on 127.0.0.1:PORT (default: off)")
    p.set_defaults(func=cmd_paper)
    campaign_cli.add_parser(sub)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except FaultSpecError as exc:
        print(f"rhonn-harness: bad --fault: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
