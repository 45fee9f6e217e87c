"""`rhonn-harness`: closed-loop runs over the bus, controller comparisons, offline replay.

  rhonn-harness run SCENARIO --controller NAME [--bus auto|SPEC] [--mode lockstep|realtime]
                    [--out DIR] [--mu X] [--speed KMH] [--seed N] [--duration S]
                    [--no-secoc] [--secoc-keys env|ci-test-key|KEYFILE]
  rhonn-harness compare SCENARIO [--controllers a,b,...] [--out DIR] [...]
  rhonn-harness replay LOG [--controller NAME] [--secoc-keys SRC]
  rhonn-harness paper --out DIR [--jobs N] [--quick] [--scheduler local|ADDRESS]
  rhonn-harness campaign CAMPAIGN.toml [--scheduler local|ADDRESS] [--workers N] [--out DIR]
                         [--resume]

SecOC (authenticated SYNC, torque and status frames, can_db/secoc.py) is on by default.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from can_db.process.argcheck import (
    OneLineParser,
    UsageError,
    check_extra,
    check_out_dir,
    choice_list,
    number,
)
from can_db.secoc_keys import SecOcKeyError
from controller.core.registry import CONTROLLER_NAMES
from harness.campaign import cli as campaign_cli
from harness.run.bus_logger import LOG_FORMATS
from harness.run.runner import RunConfig, run_closed_loop
from harness.run.validate import check_run_config
from plant_sim.overrides import parse_key_values
from plant_sim.process import DURATION_MAX_S, MU_MAX, SPEED_MAX_KMH, parse_params
from plant_sim.scenario import list_scenarios

HARNESS_MODULES = ("matplotlib", "rerun", "tqdm", "asammdf")
RUN_HELP = ("Units: speed km/h, durations s (simulated), friction dimensionless.\n"
            "Every argument is checked before any process starts; a bad one is one line on\n"
            "stderr and exit code 2.")

SUMMARY_KEYS = (
    ("completed", "completed", "{}"), ("spun", "spun", "{}"),
    ("max |beta| deg", "max_abs_beta_deg", "{:.2f}"),
    ("max |lat dev| m", "max_abs_lateral_dev_m", "{:.3f}"),
    ("rms lat dev m", "rms_lateral_dev_m", "{:.3f}"),
    ("phase area rad²/s", "phase_area", "{:.4f}"),
    ("max |swa| deg", "max_abs_swa_deg", "{:.1f}"),
    ("max |dM| Nm", "max_abs_dM_Nm", "{:.0f}"),
    ("step p50/p99 us", ("step_us_p50", "step_us_p99"), "{:.0f} / {:.0f}"),
    ("turnaround p50/p99 us", ("turnaround_us_p50", "turnaround_us_p99"), "{:.0f} / {:.0f}"),
    ("deadline misses", "deadline_misses", "{}"),
    ("fallback events", "fallback_events", "{}"),
    ("frames rejected", "frames_rejected", "{}"),
    ("SecOC rejected", "secoc_rejected", "{}"),
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
    p.add_argument("--bus", default="auto",
                   help="auto (vcan0 if up, else a loopback bus server) | socketcan:IFACE | "
                        "remote:ws://127.0.0.1:PORT/")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="lockstep: deterministic, faster than real time; realtime: HIL-like "
                        "on the monotonic clock")
    p.add_argument("--controller-mode", choices=("lockstep", "freerun"), default="lockstep",
                   help="controller answers SYNC frames (lockstep) or runs its own schedule")
    p.add_argument("--config", default=None,
                   help="controller TOML file or packaged name (default: default.toml)")
    p.add_argument("--mu", type=number(lo=0.0, hi=MU_MAX, lo_open=True), default=None,
                   metavar="MU",
                   help=f"road friction coefficient, 0 < mu <= {MU_MAX:g} "
                        "(default: the scenario's)")
    p.add_argument("--speed", type=number(lo=0.0, hi=SPEED_MAX_KMH, unit="km/h"),
                   default=None, metavar="KMH", help=f"initial speed, km/h, 0 .. {SPEED_MAX_KMH:g} "
                                      "(default: the scenario's)")
    p.add_argument("--seed", type=number(int, lo=0), default=0, metavar="N",
                   help="sensor-noise seed, >= 0")
    p.add_argument("--duration", type=number(lo=0.0, hi=DURATION_MAX_S, lo_open=True,
                                              unit="s"),
                   default=None, metavar="S",
                   help="simulated time, s (default: the scenario's)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="scenario parameter override, repeatable (e.g. amplitude_deg=120)")
    p.add_argument("--vehicle", action="append", default=[], metavar="KEY=VALUE",
                   help="plant override, repeatable, e.g. mass_scale=1.15 "
                        "(plant_sim/overrides.py)")
    p.add_argument("--fault", action="append", default=[], metavar="KIND[:ARG][@T]",
                   help="inject a fault, repeatable (see README, Faults)")
    p.add_argument("--log-format", choices=LOG_FORMATS, default="blf",
                   help="bus log format: Vector BLF, Vector ASCII or ASAM MDF4")
    p.add_argument("--rerun-live", action="store_true",
                   help="stream plant, controller and timing live to a rerun web viewer on "
                        "127.0.0.1 while the run goes")
    p.add_argument("--rerun-port", type=number(int, lo=1024, hi=64749), default=9090,
                   metavar="PORT",
                   help="--rerun-live: web viewer port on 127.0.0.1 (the data port is "
                        "this + 786)")
    p.add_argument("--rerun-hold", type=number(lo=0.0, hi=86_400.0, unit="s"), default=0.0,
                   metavar="S", help="--rerun-live: keep the viewer up S s after the run when "
                                     "not on a terminal (on a terminal: until Ctrl-C)")
    p.add_argument("--controller-cpu", default=None, metavar="CPU|auto",
                   help="HIL layout: the controller alone on this CPU (auto: the highest), "
                        "kept from idling; everything else on the other CPUs (default: all "
                        "share)")
    p.add_argument("--no-secoc", action="store_true",
                   help="turn SecOC (authenticated SYNC/torque/status frames) off")
    p.add_argument("--secoc-keys", default=None,
                   help="SecOC keys: env | ci-test-key | KEYFILE (default: env when the "
                        "RHONN_SECOC_KEY_* variables are set, else the public CI test key)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-rrd", action="store_true", help="skip the rerun recording file")


def _config(args: argparse.Namespace, controller: str, out: Path) -> RunConfig:
    return RunConfig(scenario=args.scenario, controller=controller, out_dir=out, bus=args.bus,
                     mode=args.mode, controller_mode=args.controller_mode,
                     controller_config=args.config, mu=args.mu, speed_kmh=args.speed,
                     seed=args.seed, duration_s=args.duration,
                     params=parse_params(args.param),
                     vehicle=parse_key_values(args.vehicle), faults=list(args.fault),
                     log_format=args.log_format, rerun_live=args.rerun_live,
                     rerun_port=args.rerun_port,
                     secoc=not args.no_secoc, secoc_keys=args.secoc_keys,
                     controller_cpu=args.controller_cpu,
                     make_plots=not args.no_plots, make_rrd=not args.no_rrd)


def cmd_run(args: argparse.Namespace) -> int:
    out = Path(args.out or f"runs/{args.scenario}-{args.controller}")
    cfg = _config(args, args.controller, out)
    check_run_config(cfg)
    result = run_closed_loop(cfg)
    print_table({args.controller: result.metrics})
    print(f"\nrun: {result.reason}")
    written = [f for f in ("metrics.json", "truth.csv", f"bus.{cfg.log_format}",
                           "controller_timing.csv", "run.rrd") if (out / f).is_file()]
    plots = [p for p in result.metrics.get("plots", []) if (out / p).is_file()]
    print(f"results in {out}/: {', '.join(written)}"
          + (f", {len(plots)} PNG plots" if plots else ""))
    if "analysis_error" in result.metrics:
        print(f"analysis error: {result.metrics['analysis_error']}", file=sys.stderr)
    if "rrd" in result.metrics:
        print(f"open the timeline: rerun analytics disable && rerun {out}/run.rrd")
    if result.live is not None:
        from harness.viz.rerun_live import keep_viewer_open

        try:
            if sys.stdin.isatty():
                print(f"live view stays open at {result.live.url} — Ctrl-C closes it",
                      flush=True)
                keep_viewer_open(result.live)
            elif args.rerun_hold > 0:
                print(f"live view stays open {args.rerun_hold:g} s at {result.live.url}",
                      flush=True)
                keep_viewer_open(result.live, args.rerun_hold)
        finally:
            result.live.close()
    return 0 if result.reason == "finished" else 1


def cmd_compare(args: argparse.Namespace) -> int:
    names = args.controllers
    base = Path(args.out or f"runs/compare-{args.scenario}")
    for name in names:
        check_run_config(_config(args, name, base / name), bus=name == names[0])
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
    from can_db.secoc_keys import load_keys, resolve_key_source
    from harness.run.replay import log_is_secured, replay_log
    from harness.run.validate import check_controller_config

    check_controller_config(args.config)
    keys = load_keys(resolve_key_source(args.secoc_keys)) if log_is_secured(args.log) else None
    result = replay_log(args.log, args.controller, args.config, keys=keys)
    verdict = ("BIT-IDENTICAL" if result.bit_identical else "DIFFERENT") \
        + (" (SecOC: torque frames and their MACs)" if result.secured else "")
    source = "given" if args.controller else "from CTRL_STATUS.CONTROLLER_ID"
    print(f"replay of {args.log} with {result.controller} ({source}): {verdict} — recorded "
          f"{result.recorded} torque frames, replayed {result.replayed}, identical "
          f"{result.identical}, first mismatch {result.first_mismatch}")
    if len(result.segments) > 1:
        for i, seg in enumerate(result.segments):
            print(f"  controller process {i + 1} (from frame {seg.first_frame}, "
                  f"{seg.controller}): {'BIT-IDENTICAL' if seg.bit_identical else 'DIFFERENT'}"
                  f" — {seg.identical}/{seg.recorded} identical, replayed {seg.replayed}")
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


BENCHMARK_SECTIONS = ("core", "adaptation", "pareto")


def cmd_benchmark(args: argparse.Namespace) -> int:
    import json

    from harness.paper.benchmark import BenchmarkPlan, run_benchmark, run_specs

    if args.jobs < 1 or args.seeds < 1:
        print("rhonn-harness: --jobs and --seeds must be >= 1", file=sys.stderr)
        return 2
    seeds = tuple(range(1, args.seeds + 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    say = lambda s: print(s, flush=True)  # noqa: E731
    md = out / "benchmark.md"
    if "core" in args.sections:
        plan = BenchmarkPlan.smoke() if args.quick else BenchmarkPlan(seeds=seeds,
                                                                      sine_seeds=seeds)
        tables = run_benchmark(out, plan, args.jobs, progress=say)
        if args.confirm_bus:
            from harness.paper.benchmark import bus_confirmation, bus_markdown

            rows = bus_confirmation(tables, out)
            (out / "bus_confirmation.json").write_text(json.dumps(rows, indent=1))
            with md.open("a") as f:
                f.write(bus_markdown(rows))
    else:
        md.write_text("")

    def runner(specs: list) -> list:
        return run_specs(specs, args.jobs)

    if "adaptation" in args.sections:
        from harness.paper.adaptation import AdaptationPlan, adaptation_markdown, adaptation_tables

        aplan = AdaptationPlan.quick() if args.quick else AdaptationPlan(seeds=seeds)
        at = adaptation_tables(aplan, runner, progress=say)
        (out / "adaptation.json").write_text(json.dumps(at, indent=1, default=str))
        with md.open("a") as f:
            f.write("\n" + adaptation_markdown(at))
    if "pareto" in args.sections:
        from harness.paper.pareto import ParetoPlan, pareto_figure, pareto_markdown, pareto_tables

        pplan = ParetoPlan.quick() if args.quick else ParetoPlan.full(seeds=seeds)
        say("pareto sweep")
        pt = pareto_tables(pplan, runner)
        (out / "pareto.json").write_text(json.dumps(pt, indent=1, default=str))
        pareto_figure(pt, out / "pareto.png")
        with md.open("a") as f:
            f.write("\n" + pareto_markdown(pt) + "\n![Pareto fronts](pareto.png)\n")
    print(f"tables: {md}, {out}/*.json")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="rhonn-harness", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    scenarios = list_scenarios()
    scen_help = "scenario: " + ", ".join(scenarios)
    p = sub.add_parser("run", help="one closed-loop run over the bus", description=RUN_HELP)
    p.add_argument("scenario", choices=scenarios, metavar="SCENARIO", help=scen_help)
    p.add_argument("--controller", required=True, choices=CONTROLLER_NAMES,
                   help="which controller runs")
    p.add_argument("--out", default=None,
                   help="output directory (default: runs/SCENARIO-CONTROLLER)")
    _add_run_options(p)
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("compare", help="run several controllers on one scenario",
                       description=RUN_HELP)
    p.add_argument("scenario", choices=scenarios, metavar="SCENARIO", help=scen_help)
    p.add_argument("--controllers", type=choice_list(CONTROLLER_NAMES, "controller"),
                   default=list(CONTROLLER_NAMES),
                   help="comma-separated, from: " + ", ".join(CONTROLLER_NAMES))
    p.add_argument("--out", default=None,
                   help="output directory (default: runs/compare-SCENARIO)")
    _add_run_options(p)
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser("replay", help="replay a bus log through a controller offline")
    p.add_argument("log", help="bus log recorded by run (.blf, .asc or .mf4)")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, default=None,
                   help="controller to replay with (default: from the log's "
                        "CTRL_STATUS.CONTROLLER_ID, per controller process)")
    p.add_argument("--config", default=None, help="controller TOML the run used")
    p.add_argument("--secoc-keys", default=None,
                   help="keys of a SecOC log: env | ci-test-key | KEYFILE (default as for run)")
    p.set_defaults(func=cmd_replay)
    p = sub.add_parser("paper", help="the paper's experiments + FMVSS 126, report and tables")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--jobs", type=number(int, lo=1, hi=64), default=2,
                   help="parallel runs (each a full bus run: 2 processes)")
    p.add_argument("--quick", action="store_true", help="reduced smoke set (≈ 1 min)")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster of --jobs workers) | tcp://HOST:PORT")
    p.add_argument("--dashboard", type=int, default=None, metavar="PORT",
                   help="dask dashboard on 127.0.0.1:PORT (default: off)")
    p.set_defaults(func=cmd_paper)
    p = sub.add_parser("benchmark", help="stability vs lane keeping benchmark: v_max per "
                                         "rule over seeds, margins, ablation, adaptation, "
                                         "Pareto fronts")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--jobs", type=int, default=2, help="parallel in-process runs")
    p.add_argument("--seeds", type=int, default=5, help="seeds 1..N (≥ 5 for the report)")
    p.add_argument("--quick", action="store_true", help="smoke size (1 seed, coarse)")
    p.add_argument("--confirm-bus", action="store_true",
                   help="afterwards repeat the v_max boundary probes as real bus runs")
    p.add_argument("--sections", type=choice_list(BENCHMARK_SECTIONS, "section"),
                   default=list(BENCHMARK_SECTIONS),
                   help="comma-separated, from: " + ", ".join(BENCHMARK_SECTIONS)
                        + " (core: v_max, margins, sine with dwell, curves, ablation; "
                          "adaptation: friction steps, perturbed cars, friction estimates; "
                          "pareto: max |β| against path deviation per controller)")
    p.set_defaults(func=cmd_benchmark)
    campaign_cli.add_parser(sub)
    args = parser.parse_args(argv)
    try:
        check_extra(HARNESS_MODULES)
        if getattr(args, "out", None) and args.command == "paper":
            check_out_dir(args.out)
        return int(args.func(args))
    except UsageError as exc:
        parser.error(str(exc))
    except (ValueError, SecOcKeyError) as exc:
        parser.error(str(exc))

if __name__ == "__main__":
    raise SystemExit(main())
