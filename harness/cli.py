"""`rhonn-harness`: closed-loop runs over the bus, controller comparisons, offline replay.

  rhonn-harness run SCENARIO --controller NAME [--bus auto|SPEC] [--mode lockstep|realtime]
                    [--out DIR] [--mu X] [--speed KMH] [--seed N] [--duration S]
                    [--no-secoc] [--secoc-keys env|ci-test-key|KEYFILE]
  rhonn-harness compare SCENARIO [--controllers a,b,...] [--out DIR] [...]
  rhonn-harness replay LOG [--controller NAME] [--secoc-keys SRC]
  rhonn-harness rrd RUN_DIR [--out FILE]
  rhonn-harness paper --out DIR [--jobs N] [--quick] [--resume] [--scheduler local|ADDRESS]
  rhonn-harness benchmark --out DIR [--seeds SPEC] [--jobs N] [--quick] [--sections LIST]
                          [--scheduler local|ADDRESS]
  rhonn-harness campaign CAMPAIGN.toml [--scheduler local|ADDRESS] [--jobs N] [--out DIR]
                         [--resume] [--seeds SPEC] [--duration S]

Every command takes -v/--verbose (DEBUG diagnostics) and -q/--quiet (warnings only);
--seeds SPEC is a seed list such as 0,3,7 or 1-5 (docs/cli.md).
SCENARIO is a packaged name or a scenario TOML file, PATH.toml (docs/scenarios.md).
SecOC (authenticated SYNC, torque and status frames, can_db/secoc.py) is on by default.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from can_db.process.argcheck import (
    OneLineParser,
    UsageError,
    add_jobs_option,
    check_extra,
    check_out_dir,
    choice_list,
    error_line,
    number,
    seed_spec,
)
from can_db.process.errors import error_text
from can_db.process.logsetup import add_logging_options, logging_args, setup_logging
from can_db.secoc_keys import SecOcKeyError, load_keys, resolve_key_source
from controller.core.registry import CONTROLLER_NAMES
from harness.analysis.course import course_geometry, scenario_for
from harness.analysis.loop_health import DEGRADED, loop_cell
from harness.analysis.run_data import load_run
from harness.analysis.run_status import partial_note
from harness.analysis.verdicts import VERDICT_LABELS, verdict_word
from harness.campaign import cli as campaign_cli
from harness.campaign.engine import EngineConfig, EngineError
from harness.campaign.spec import CampaignError
from harness.paper.adaptation import AdaptationPlan, adaptation_section
from harness.paper.benchmark import BenchmarkPlan, core_section, run_benchmark
from harness.paper.handling import HandlingPlan, handling_section
from harness.paper.pareto import ParetoPlan, pareto_section
from harness.paper.study import run_paper
from harness.report.run_report import run_and_report, write_run_rrd
from harness.run import marker, signals
from harness.run.bus_logger import LOG_FORMATS
from harness.run.hil_bench import Bench
from harness.run.marker import report_stale
from harness.run.replay import log_is_secured, replay_log
from harness.run.spec import RunSpec
from harness.run.validate import check_controller_config, check_run_config
from harness.viz.plots import write_overlay_plots
from harness.viz.rerun_live import keep_viewer_open
from plant_sim.overrides import parse_key_values
from plant_sim.run_options import DURATION_MAX_S, MU_MAX, SPEED_MAX_KMH, parse_params, scenario_arg
from plant_sim.scenario import list_scenarios, scenario_label

log = logging.getLogger("rhonn-harness")
EXIT_DEGRADED = 4  # the run reached its end, but the loop did not hold (loop_health.py)
HARNESS_MODULES = ("matplotlib", "rerun", "tqdm", "asammdf")
RUN_HELP = ("Units: speed km/h, durations s (simulated), friction dimensionless.\n"
            "Every argument is checked before any process starts; a bad one is one line on\n"
            "stderr and exit code 2.")

def _verdict_cell(name: str) -> Any:
    """Cell of one verdict of the metrics' ``verdicts`` block: pass / FAIL / – (no such
    rule or not judged), the course rule with its struck-cone count."""
    def cell(metrics: dict[str, Any]) -> str:
        entry = (metrics.get("verdicts") or {}).get(name) or {}
        text = verdict_word(entry.get("passed"))
        if name == "course_rule" and entry.get("cones_struck") is not None:
            text += f" ({entry['cones_struck']} struck)"
        return text
    return cell


def _jitter_cell(metrics: dict[str, Any]) -> str:
    """Period jitter exists only on a real-time schedule (in lockstep the period is
    simulated; kpi.py)."""
    if metrics.get("mode") == "lockstep":
        return "n/a lockstep"
    value = metrics.get("period_jitter_us_p99")
    return "-" if value is None else f"{value:.0f}"


def _step_cell(metrics: dict[str, Any]) -> str:
    """The controller's step time from CTRL_STATUS.COMPUTE_TIME; firmware on QEMU has no
    clock to fill it (its instructions per step are on the firmware line)."""
    if metrics.get("target") is not None:
        return "n/a (firmware)"
    p50, p99 = metrics.get("step_us_p50"), metrics.get("step_us_p99")
    return "-" if p50 is None or p99 is None else f"{p50:.0f} / {p99:.0f}"


def _kilo_cell(keys: tuple[str, ...], fmt: str = "{:.1f}") -> Callable[[dict[str, Any]], str]:
    """A cell of metrics ``keys`` divided by 1000 (N·m/s → kN·m/s), " / " between them."""
    def cell(metrics: dict[str, Any]) -> str:
        values = [metrics.get(k) for k in keys]
        if any(not isinstance(v, int | float) for v in values):
            return "-"
        return " / ".join(fmt.format(v / 1000.0) for v in values)
    return cell


#: KPI table rows: (label, metrics key | keys | cell function, format). Timing figures are
#: wall-clock compute times in both modes; see :func:`print_table` for the lockstep labels.
SUMMARY_KEYS: tuple[tuple[str, Any, str], ...] = (
    (VERDICT_LABELS["paper_rule"], _verdict_cell("paper_rule"), ""),
    (VERDICT_LABELS["course_rule"], _verdict_cell("course_rule"), ""),
    (VERDICT_LABELS["stable"], _verdict_cell("stable"), ""),
    ("loop (SecOC, fallback, timing)", loop_cell, ""),
    ("completed", "completed", "{}"), ("spun", "spun", "{}"),
    ("max |beta| deg", "max_abs_beta_deg", "{:.2f}"),
    ("max |lat dev| m", "max_abs_lateral_dev_m", "{:.3f}"),
    ("rms lat dev m", "rms_lateral_dev_m", "{:.3f}"),
    ("phase area rad²/s", "phase_area", "{:.4f}"),
    ("max |swa| deg", "max_abs_swa_deg", "{:.1f}"),
    ("max |dM| Nm", "max_abs_dM_Nm", "{:.0f}"),
    ("dM total variation/s Nm/s", "dM_tv_per_s_Nm_per_s", "{:.0f}"),
    ("max dM change/MPC period Nm", "dM_max_change_per_period_Nm", "{:.0f}"),
    ("wheel torque rate max/p99 kNm/s", _kilo_cell(("wheel_torque_rate_max_Nm_per_s",
                                                    "wheel_torque_rate_p99_Nm_per_s")), ""),
    ("dM chatter 1/s", "dM_chatter_per_s", "{:.1f}"),
    ("step compute p50/p99 µs (wall)", _step_cell, ""),
    ("turnaround p50/p99 µs (wall)", ("turnaround_us_p50", "turnaround_us_p99"),
     "{:.0f} / {:.0f}"),
    ("period jitter p99 µs", _jitter_cell, ""),
    ("deadline misses", "deadline_misses", "{}"),
    ("fallback events", "fallback_events", "{}"),
    ("commands held (lost answers)", "command_held_cycles", "{}"),
    ("bus log frames lost", "bus_log_frames_lost", "{}"),
    ("frames rejected", "frames_rejected", "{}"),
    ("SecOC rejected", "secoc_rejected", "{}"),
)
#: Labels in a table of lockstep runs only: the plant waits for every answer, so a
#: turnaround over the period is compute over the 10 ms budget, not a missed deadline.
LOCKSTEP_LABELS = {"deadline misses": "turnaround > 10 ms (wall)"}


def _fmt(metrics: dict[str, Any], key: Any, fmt: str) -> str:
    if callable(key):
        return str(key(metrics))
    keys = key if isinstance(key, tuple) else (key,)
    values = [metrics.get(k) for k in keys]
    if any(v is None for v in values):
        return "-"
    if len(values) == 1 and isinstance(values[0], dict):  # counts by reason, not a repr
        return ", ".join(f"{k} {v}" for k, v in sorted(values[0].items())) or "0"
    try:
        return fmt.format(*values)
    except (TypeError, ValueError):
        return str(values[0] if len(values) == 1 else values)


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    """KPI table: one column per run; a run stopped by a signal is named above it. The
    three verdict rows read the metrics' ``verdicts`` block (harness/analysis/verdicts.py);
    in a table of lockstep runs the deadline row is labelled as the compute figure it is."""
    names = list(rows)
    for n in names:
        note = partial_note(rows[n])
        if note is not None:
            print(f"{n}: {note}" if len(names) > 1 else note)
    lockstep = all(rows[n].get("mode") == "lockstep" for n in names)
    width = max(16, *(len(n) for n in names))
    print(f"{'KPI':<32}" + "".join(f"{n:>{width + 2}}" for n in names))
    for label, key, fmt in SUMMARY_KEYS:
        label = LOCKSTEP_LABELS.get(label, label) if lockstep else label
        print(f"{label:<32}" + "".join(f"{_fmt(rows[n], key, fmt):>{width + 2}}"
                                        for n in names))


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bus", default="auto",
                   help="auto (vcan0 if up, else a local bus with a hub of its own) | "
                        "local:NAME | socketcan:IFACE | remote:ws://127.0.0.1:PORT/")
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
                   help="inject a fault, repeatable (docs/faults-and-security.md)")
    p.add_argument("--log-format", choices=LOG_FORMATS, default="blf",
                   help="bus log format: Vector BLF, Vector ASCII or ASAM MDF4 "
                        "(docs/logs.md; print one with `rhonn-bus decode LOG`)")
    p.add_argument("--rerun-live", action="store_true",
                   help="stream plant, controller and timing live to a rerun web viewer on "
                        "127.0.0.1 while the run goes")
    p.add_argument("--rerun-port", type=number(int, lo=1024, hi=64749), default=None,
                   metavar="PORT",
                   help="--rerun-live: web viewer port on 127.0.0.1 (the data port is "
                        f"this + 786; default {RunSpec.rerun_port})")
    p.add_argument("--rerun-hold", type=number(lo=0.0, hi=86_400.0, unit="s"), default=None,
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
                        "RHONN_SECOC_KEY_* variables are set, else the public test key: "
                        "simulation only)")
    p.add_argument("--lockstep-wait-ms", type=number(lo=0.0, hi=60_000.0, lo_open=True,
                                                      unit="ms"),
                   default=None, metavar="MS",
                   help="lockstep: the plant's wall-clock wait for each cycle's answer, ms "
                        "(default 200; raise it on slow machines and emulators)")
    p.add_argument("--command-hold-ms", type=number(lo=0.0, hi=1000.0, unit="ms"),
                   default=None, metavar="MS",
                   help="the plant holds the last torque command this long when a cycle has "
                        "no fresh one, then falls back to the driver's torques, ms (lockstep "
                        "and real time alike; default 30, 0 = no hold)")
    p.add_argument("--bus-start-timeout", type=number(lo=0.0, hi=600.0, lo_open=True, unit="s"),
                   default=RunSpec.bus_start_timeout_s, metavar="S",
                   help="wall time a started local hub or bus server may take to come up, s "
                        f"(default {RunSpec.bus_start_timeout_s:g})")
    p.add_argument("--target", choices=("host", "m4f"), default="host",
                   help="where the controller runs: host (the Python controller process) or "
                        "m4f (processor in the loop: the whole node as Cortex-M4F firmware on "
                        "QEMU mps2-an386, built for the controller's configuration in float32 "
                        "on first use and cached, bridged to the bus over SLCAN; lockstep; "
                        "SecOC only with the public test key compiled into the firmware "
                        "(--secoc-keys ci-test-key, or --no-secoc); needs the ARM toolchain "
                        "and qemu-system-arm; the plant waits up to 5 s for each answer unless "
                        "--lockstep-wait-ms says otherwise; instructions per cycle, stack and "
                        "flash/RAM in metrics.json's controller_summary)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-rrd", action="store_true", help="skip the rerun recording file")


def _config(args: argparse.Namespace, controller: str, out: Path) -> RunSpec:
    return RunSpec(scenario=args.scenario, controller=controller, out_dir=out, bus=args.bus,
                     mode=args.mode, controller_mode=args.controller_mode,
                     controller_config=args.config, mu=args.mu, speed_kmh=args.speed,
                     seed=args.seed, duration_s=args.duration,
                     params=parse_params(args.param),
                     vehicle=parse_key_values(args.vehicle), faults=list(args.fault),
                     log_format=args.log_format, rerun_live=args.rerun_live,
                     rerun_port=(RunSpec.rerun_port if args.rerun_port is None
                                 else args.rerun_port),
                     secoc=not args.no_secoc, secoc_keys=args.secoc_keys,
                     controller_cpu=args.controller_cpu,
                     lockstep_wait_ms=args.lockstep_wait_ms,
                     command_hold_ms=args.command_hold_ms,
                     target=args.target,
                     bus_start_timeout_s=args.bus_start_timeout,
                     make_plots=not args.no_plots, make_rrd=not args.no_rrd)


def _check_live_options(args: argparse.Namespace) -> None:
    """The live viewer's options mean nothing without the live viewer: refused, not ignored."""
    given = [o for o, v in (("--rerun-port", args.rerun_port), ("--rerun-hold", args.rerun_hold))
             if v is not None]
    if given and not args.rerun_live:
        verb = "needs" if len(given) == 1 else "need"
        raise UsageError(f"{' and '.join(given)} {verb} --rerun-live")


def firmware_line(summary: dict[str, Any]) -> str:
    """The PIL firmware's figures of a ``--target m4f`` run in one line (its controller
    summary, harness/bench/mcu/pil_node.py): instructions per full step and per
    allocate-only cycle (p50 / p99 / max), the full step's time at the part's clock if every
    instruction took one cycle, the stack's high-water mark, flash and static RAM."""
    ins = summary.get("instructions_per_cycle") or {}
    full, alloc = ins.get("full_step") or {}, ins.get("allocate_only") or {}
    fw = summary.get("firmware") or {}
    if not full.get("cycles"):
        return f"firmware (Cortex-M4F on QEMU): no instruction counts ({ins.get('error', 'none')})"
    mhz = full["clock_hz"] / 1e6
    return (f"firmware (Cortex-M4F on QEMU): instructions per full step p50/p99/max "
            f"{full['insns_p50']:,.0f} / {full['insns_p99']:,.0f} / {full['insns_max']:,} "
            f"({full['us_at_clock_p50'] / 1e3:.2f} / {full['us_at_clock_p99'] / 1e3:.2f} / "
            f"{full['us_at_clock_max'] / 1e3:.2f} ms at {mhz:g} MHz, 1 instruction a cycle), "
            f"per allocate-only cycle {alloc.get('insns_p50', 0):,.0f} / "
            f"{alloc.get('insns_p99', 0):,.0f} / {alloc.get('insns_max', 0):,}; stack "
            f"{summary.get('stack_high_water_bytes')} B; flash {fw.get('flash_bytes')} B, "
            f"static RAM {fw.get('ram_static_bytes')} B")


def cmd_run(args: argparse.Namespace) -> int:
    _check_live_options(args)
    out = Path(args.out or f"runs/{scenario_label(args.scenario)}-{args.controller}")
    cfg = _config(args, args.controller, out)
    check_run_config(cfg)
    result = run_and_report(cfg)
    print_table({args.controller: result.metrics})
    if result.metrics.get("target") == "m4f":
        print(firmware_line(result.metrics.get("controller_summary") or {}))
    print(f"\nrun: {result.reason}")
    for why in result.metrics.get("degraded_because", []):
        print(f"degraded: {why}", file=sys.stderr)
    written = [f for f in ("metrics.json", "truth.csv", f"bus.{cfg.log_format}",
                           "controller_timing.csv", "run.rrd") if (out / f).is_file()]
    plots = [p for p in result.metrics.get("plots", []) if (out / p).is_file()]
    print(f"results in {out}/: {', '.join(written)}"
          + (f", {len(plots)} PNG plots" if plots else ""))
    if "analysis_error" in result.metrics:
        print(f"analysis error: {result.metrics['analysis_error']}", file=sys.stderr)
    if "analysis_cut" in result.metrics:
        print(f"partial results: {result.metrics['analysis_cut']}", file=sys.stderr)
    if "rrd" in result.metrics:
        print(f"open the timeline: rerun analytics disable && rerun {out}/run.rrd")
    if result.live is not None:

        try:
            if result.metrics.get("interrupted"):
                pass  # a stop signal ends the command, the viewer with it
            elif sys.stdin.isatty():
                print(f"live view stays open at {result.live.url} — Ctrl-C closes it",
                      flush=True)
                keep_viewer_open(result.live)
            elif args.rerun_hold:
                print(f"live view stays open {args.rerun_hold:g} s at {result.live.url}",
                      flush=True)
                keep_viewer_open(result.live, args.rerun_hold)
        finally:
            result.live.close()
    if result.metrics.get("interrupted"):
        return signals.exit_code()
    if result.reason == DEGRADED:
        return EXIT_DEGRADED
    return 0 if result.reason == "finished" else 1


def cmd_compare(args: argparse.Namespace) -> int:
    _check_live_options(args)
    names = args.controllers
    base = Path(args.out or f"runs/compare-{scenario_label(args.scenario)}")
    for name in names:
        check_run_config(_config(args, name, base / name), bus=name == names[0])
    rows: dict[str, dict[str, Any]] = {}
    first = _config(args, names[0], base / names[0])
    # one warm bench: the controller is reset over UDS between the runs (harness/run/hil_bench.py)
    bench = Bench(base / ".bench", bus=first.bus, rt=first.rt,
                  controller_cpu=first.controller_cpu,
                  bus_start_timeout_s=first.bus_start_timeout_s)
    with bench:
        for name in names:
            log.info("running %s with %s ...", scenario_label(args.scenario), name)
            rows[name] = run_and_report(_config(args, name, base / name), bench=bench).metrics
            if rows[name].get("interrupted"):  # the remaining controllers do not start
                break
    if rows[names[len(rows) - 1]].get("interrupted"):
        print_table(rows)
        print(f"compare: interrupted during {names[len(rows) - 1]}; not run: "
              f"{', '.join(names[len(rows):]) or '-'}", file=sys.stderr)
        return signals.exit_code()
    print_table(rows)
    try:

        cfg = _config(args, names[0], base)
        geo = course_geometry(scenario_for(cfg.scenario, cfg.mu, cfg.speed_kmh,
                                           dict(cfg.params)))
        runs = {n: load_run(base / n) for n in names}
        plots = write_overlay_plots(runs, geo.boundaries, geo.ref_path, base, cones=geo.cones,
                                    lanes=geo.lanes,
                                    course_end_arc_m=geo.course_end_arc_m or None)
        print(f"overlay plots: {', '.join(str(p) for p in plots)}")
    except Exception as exc:
        print(f"overlay plots failed: {error_text(exc)}", file=sys.stderr)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:

    check_controller_config(args.config)
    report_stale(Path(args.log).parent)  # the log of a killed harness: say so, then replay it
    keys = load_keys(resolve_key_source(args.secoc_keys)) if log_is_secured(args.log) else None
    if not log.isEnabledFor(logging.DEBUG):
        # the log's SecOC rejections were the run's (its metrics count them); every node and
        # observer the replay builds would warn of them once again (-v shows them)
        logging.getLogger("can_db.secoc").setLevel(logging.ERROR)
    result = replay_log(args.log, args.controller, args.config, keys=keys)
    lost = (f" ({result.lost_in_log} not in the log: lost on the bus)"
            if result.lost_in_log else "")
    verdict = ("BIT-IDENTICAL" if result.bit_identical
               else f"PARTIAL ({result.uncompared} torque frames of the log not compared)"
               if result.uncompared else "DIFFERENT") \
        + (" (SecOC: torque frames and their MACs)" if result.secured else "")
    source = "given" if args.controller else "from CTRL_STATUS.CONTROLLER_ID"
    print(f"replay of {args.log} with {result.controller} ({source}): {verdict} — recorded "
          f"{result.recorded} torque frames, replayed {result.replayed}{lost}, identical "
          f"{result.identical}, first mismatch "
          f"{'none' if result.first_mismatch is None else result.first_mismatch}")
    if len(result.segments) > 1:
        for i, seg in enumerate(result.segments):
            print(f"  controller process {i + 1} (from frame {seg.first_frame}, "
                  f"{seg.controller}): {'BIT-IDENTICAL' if seg.bit_identical else 'DIFFERENT'}"
                  f" — {seg.identical}/{seg.recorded} identical, replayed {seg.replayed}")
    return 0 if result.bit_identical else 1


def cmd_rrd(args: argparse.Namespace) -> int:
    """The rerun recording of an existing run directory (the same file ``run`` writes)."""
    run_dir = Path(args.run_dir)
    path, metrics = write_run_rrd(run_dir, Path(args.out) if args.out else None)
    note = partial_note(metrics)
    print(f"recording of {run_dir}/ written: {path}" + (f" ({note})" if note else ""))
    print(f"open the timeline: rerun analytics disable && rerun {path}")
    return 0


def _shows_progress() -> bool:
    """Progress of a campaign on stderr (a bar on a terminal, else a plain line at most every
    10 s: harness/campaign/runner.py) unless -q asked for warnings only."""
    return log.isEnabledFor(logging.INFO)


def cmd_paper(args: argparse.Namespace) -> int:

    out = Path(args.out)
    try:
        tables = run_paper(out, jobs=args.jobs, quick=args.quick, resume=args.resume,
                           engine=EngineConfig(args.scheduler, max(1, args.jobs),
                                               args.dashboard), progress=_shows_progress())
    except (EngineError, CampaignError) as exc:
        return error_line("rhonn-harness paper", str(exc))
    except KeyboardInterrupt:  # SIGINT/SIGTERM: the engine is stopped (Engine.abort)
        return _study_interrupted("paper", out, f"interrupted: the runs finished so far are in "
                                  f"{out}/campaign (finish with --resume); report.md and "
                                  "tables.json are not written")
    marker.clear_interrupted(out)
    meta = tables.get("meta", {})
    print(f"paper reproduction: {meta.get('runs')} runs in {meta.get('wall_time_s', 0):.0f} s "
          f"-> {out}/report.md, {out}/tables.json, {out}/figures/")
    failed = meta.get("failed_runs", [])
    if failed:
        print(f"{len(failed)} runs did not finish normally: {', '.join(failed)}",
              file=sys.stderr)
    return 1 if failed else 0


def _study_interrupted(command: str, out: Path, note: str) -> int:
    """A study stopped by a signal: ``out/INTERRUPTED`` says what is there; 130 or 143."""
    if out.is_dir():
        marker.mark_interrupted(out, signals.received(), note)
    print(f"\nrhonn-harness {command}: {note}", file=sys.stderr)
    return signals.exit_code()


# Commands whose runs go to worker pools (dask, process pools): after a stop signal they end
# with os._exit, as the pools' exit hooks would wait for the workers already stopped.
POOL_COMMANDS = ("paper", "benchmark", "campaign")
BENCHMARK_SECTIONS = ("core", "adaptation", "pareto", "handling")


def cmd_benchmark(args: argparse.Namespace) -> int:

    seeds = tuple(args.seeds)
    if len(seeds) < 5 and not args.quick:  # median and min–max over seeds
        log.warning("benchmark over %d seed(s) %s; the report's statistics want >= 5 "
                    "(e.g. --seeds 1-5)", len(seeds), ",".join(map(str, seeds)))
    out = Path(args.out)
    q = args.quick
    makers = {"core": core_section(BenchmarkPlan.smoke() if q else BenchmarkPlan(
                  seeds=seeds, sine_seeds=seeds)),
              "adaptation": adaptation_section(AdaptationPlan.quick() if q
                                               else AdaptationPlan(seeds=seeds)),
              "pareto": pareto_section(ParetoPlan.quick() if q else ParetoPlan.full(seeds)),
              "handling": handling_section(HandlingPlan.quick() if q
                                           else HandlingPlan(seeds=seeds))}
    try:  # every section's runs in one campaign over the bus (harness/paper/benchmark.py)
        run_benchmark(out, [makers[s] for s in BENCHMARK_SECTIONS if s in args.sections],
                      EngineConfig(args.scheduler, max(1, args.jobs)), progress=log.info,
                      bar=_shows_progress())
    except EngineError as exc:
        return error_line("rhonn-harness benchmark", str(exc))
    marker.clear_interrupted(out)
    print(f"tables: {out / 'benchmark.md'}, {out}/*.json; runs: {out / 'campaign'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="rhonn-harness", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    scenarios = list_scenarios()
    scen_help = ("a packaged scenario (" + ", ".join(scenarios) + ") or a scenario TOML "
                 "file, PATH.toml (docs/scenarios.md)")
    p = sub.add_parser("run", help="one closed-loop run over the bus", description=RUN_HELP)
    p.add_argument("scenario", type=scenario_arg, metavar="SCENARIO", help=scen_help)
    p.add_argument("--controller", required=True, choices=CONTROLLER_NAMES,
                   help="which controller runs")
    p.add_argument("--out", default=None,
                   help="output directory (default: runs/SCENARIO-CONTROLLER)")
    _add_run_options(p)
    p.set_defaults(func=cmd_run, error_parser=p)
    p = sub.add_parser("compare", help="run several controllers on one scenario",
                       description=RUN_HELP)
    p.add_argument("scenario", type=scenario_arg, metavar="SCENARIO", help=scen_help)
    p.add_argument("--controllers", type=choice_list(CONTROLLER_NAMES, "controller"),
                   default=",".join(CONTROLLER_NAMES),  # argparse parses a string default
                   help="comma-separated, from: " + ", ".join(CONTROLLER_NAMES))
    p.add_argument("--out", default=None,
                   help="output directory (default: runs/compare-SCENARIO)")
    _add_run_options(p)
    p.set_defaults(func=cmd_compare, error_parser=p)
    p = sub.add_parser("replay", help="replay a bus log through a controller offline")
    p.add_argument("log", help="bus log recorded by run (.blf, .asc or .mf4)")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, default=None,
                   help="controller to replay with (default: from the log's "
                        "CTRL_STATUS.CONTROLLER_ID, per controller process)")
    p.add_argument("--config", default=None, help="controller TOML the run used")
    p.add_argument("--secoc-keys", default=None,
                   help="keys of a SecOC log: env | ci-test-key | KEYFILE (default as for run)")
    p.set_defaults(func=cmd_replay, error_parser=p)
    p = sub.add_parser("rrd", help="write the rerun recording of an existing run directory",
                       description="Write the rerun recording (the run.rrd that `run` writes) "
                                   "from a run directory's files: a run with --no-rrd, an "
                                   "interrupted run, a campaign run. A directory without "
                                   "truth.csv or metrics.json is one line on stderr and exit "
                                   "code 2.")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run's output directory (run --out)")
    p.add_argument("--out", default=None, metavar="FILE",
                   help="the recording to write (default: RUN_DIR/run.rrd)")
    p.set_defaults(func=cmd_rrd, error_parser=p)
    p = sub.add_parser("paper", help="the paper's experiments + FMVSS 126, report and tables")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    add_jobs_option(p, 2, "parallel runs (each a full bus run: 2 processes)")
    p.add_argument("--quick", action="store_true", help="reduced smoke set (≈ 1 min)")
    p.add_argument("--resume", action="store_true",
                   help="finish DIR/campaign: run only the runs it does not hold yet")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster of --jobs workers) | tcp://HOST:PORT")
    p.add_argument("--dashboard", type=number(int, lo=1, hi=65535), default=None,
                   metavar="PORT", help="dask dashboard on 127.0.0.1:PORT (default: off)")
    p.set_defaults(func=cmd_paper, error_parser=p)
    p = sub.add_parser("benchmark", help="stability vs lane keeping benchmark: v_max per "
                                         "rule over seeds, margins, ablation, adaptation, "
                                         "Pareto fronts")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    add_jobs_option(p, 2, "parallel runs: LocalCluster workers, each a warm bus bench")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster of --jobs workers) | tcp://HOST:PORT")
    p.add_argument("--seeds", type=seed_spec, default=seed_spec("1-5"), metavar="SPEC",
                   help="seeds, e.g. 1-5 or 0,3,7 (>= 5 for the report; default: 1-5)")
    p.add_argument("--quick", action="store_true", help="smoke size (1 seed, coarse)")
    p.add_argument("--sections", type=choice_list(BENCHMARK_SECTIONS, "section"),
                   default=",".join(BENCHMARK_SECTIONS),  # (shown as typed)
                   help="comma-separated, from: " + ", ".join(BENCHMARK_SECTIONS)
                        + " (core: v_max, margins, sine with dwell, curves, ablation; "
                          "adaptation: friction steps, perturbed cars, friction estimates; "
                          "pareto: max |β| against path deviation per controller; "
                          "handling: smoothness, friction steps and stability near the "
                          "limit against the paper's and grip-bounded baselines, ablation)")
    p.set_defaults(func=cmd_benchmark, error_parser=p)
    campaign_cli.add_parser(sub)
    add_logging_options(parser)
    for command in sub.choices.values():
        add_logging_options(command, top=False)
    args = parser.parse_args(argv)
    setup_logging("rhonn-harness", *logging_args(args))
    signals.install()  # SIGINT and SIGTERM stop every command the same way
    try:
        check_extra(HARNESS_MODULES)
        if getattr(args, "out", None) == "":  # "--out=" would silently mean the default
            raise UsageError("--out: empty path (give a directory)")
        if getattr(args, "out", None) and args.command in ("paper", "benchmark"):
            check_out_dir(args.out)
        code = int(args.func(args))
    except KeyboardInterrupt as exc:  # a signal outside a run's own handling
        if args.command == "benchmark":
            code = _study_interrupted("benchmark", Path(args.out), "interrupted: the runs "
                                      f"finished so far are in {args.out}/campaign; the same "
                                      "command again reuses them")
        else:
            print(f"rhonn-harness {args.command}: interrupted by {exc or 'SIGINT'}",
                  file=sys.stderr)
            code = signals.exit_code()
    except (UsageError, ValueError, SecOcKeyError) as exc:
        # "rhonn-harness run: error: ...": the subcommand whose input it was
        getattr(args, "error_parser", parser).error(str(exc))
    if signals.received() is not None and args.command in POOL_COMMANDS:
        signals.leave(code)  # the workers are stopped; skip the pools' waits at exit
    return code

if __name__ == "__main__":
    raise SystemExit(main())
