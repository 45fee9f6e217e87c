"""`rhonn-bench fuzz`: adversarial fuzzing of the bus input path and every controller.

  rhonn-bench fuzz [--cases N] [--hypothesis-examples M] [--seed S] [--only T,...]
                   [--json FILE]
  rhonn-bench fuzz --planted [--cases N] [--hypothesis-examples M] [--seed S] [--json FILE]

Two engines, both deterministic:

* **numpy** (the bulk, ``--cases``, default 1 000 000): seeded adversarial generators
  (harness/fuzz/targets.py). The budget is split over the targets by ``SHARES``; each target
  runs in chunks of ``CHUNK`` cases and chunk j of target i draws from
  ``numpy.random.default_rng([seed, i, j])``, so any finding is reproduced by re-running
  its chunk. Mostly plausible values, some 100× out of range, some special floats.
* **hypothesis** (``--hypothesis-examples`` per target, default 500): structured search
  with boundary values and shrinking to a minimal failing example (harness/
  property_pass.py), ``derandomize=True`` and no example database.

Targets and invariants (details in the target docstrings; oracles in harness/fuzz/
oracle.py and docs/safety/fuzz.md):
  decoder      Codec.decode on frames made by the oracle (cantools + crcmod), correct and
               damaged: never raises; verdict, reason and values equal the oracle's
               (cantools decode, crcmod CRC, DBC min/max).
  monitor      RxMonitor on a simulated bus (counter repeats/jumps, damage, silence gaps,
               odd times): every verdict and every ``valid`` equal the oracle's (documented
               counter rules per E2E profile, timeout = 3 × the DBC cycle time).
  node:NAME    the whole ControllerNode on adversarial bursts → 3 valid frames per SYNC,
               wire torques inside the envelope, no core exception.
  controller:NAME  step()/allocate_only() of every registry controller on any floats →
               never raises, finite, within motor limits, ΔM = 0 when invalid/disabled,
               and the output envelope holds on the sequence.

Prints one table (cases, findings, seconds, cases/s per target), the findings by kind
(``missed:R``: the code accepted what the oracle rejects for R; ``false_reject:R``,
``reason:R->S``, ``value:SIG``...) and the first findings with their tracebacks; exit code 0
when there are none, 1 otherwise. Timing is reported, never asserted.

``--planted`` instead runs the oracle-checked targets against each planted missing check
(harness/fuzz/planted.py: CRC check removed, range check removed, timeout at 5 cycles,
counter check removed, CRC16 counter window not applied) and prints, per bug and target, the
mismatches and the case at which the first came; exit code 0 when every bug is caught by at
least one target, 1 otherwise. ``--cases`` is then per numpy target (default 20 000) and
``--hypothesis-examples`` per hypothesis target (default 200).
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from can_db.codec import Codec
from can_db.process.argcheck import OneLineParser, UsageError, check_out_file, choice_list, number
from controller.core.registry import CONTROLLER_NAMES
from harness.fuzz import planted, property_pass
from harness.fuzz.planted import PLANTED
from harness.fuzz.targets import (
    ControllerTarget,
    DecoderTarget,
    Finding,
    Findings,
    MonitorTarget,
    NodeTarget,
    default_params,
)
from harness.viz.progress import Bar

DEFAULT_CASES = 1_000_000
PLANTED_CASES = 20_000     # --planted: numpy cases per target and bug
PLANTED_EXAMPLES = 200     # --planted: hypothesis examples per target and bug
CHUNK = 2_000
SHARES: dict[str, float] = {
    "decoder": 0.25, "monitor": 0.25, "node:nmpc-rhonn": 0.06, "node:passive": 0.04,
    **{f"controller:{n}": 0.10 for n in CONTROLLER_NAMES},
}


@dataclass
class TargetStats:
    """One target's numbers (seconds of wall time, measured only for the report)."""

    target: str
    engine: str
    cases: int
    findings: int
    seconds: float
    numeric_warnings: list[str] = field(default_factory=list)  # handled, for the record
    by_kind: dict[str, int] = field(default_factory=dict)      # findings by kind

    @property
    def cases_per_s(self) -> float:
        return self.cases / self.seconds if self.seconds > 0 else float("nan")


@dataclass
class FuzzReport:
    """Everything a fuzz run found."""

    seed: int
    stats: list[TargetStats] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)

    @property
    def cases(self) -> int:
        return sum(s.cases for s in self.stats)

    @property
    def total_findings(self) -> int:
        return sum(s.findings for s in self.stats)

    @property
    def seconds(self) -> float:
        return sum(s.seconds for s in self.stats)

    def to_json(self) -> dict[str, Any]:
        return {"seed": self.seed, "cases": self.cases, "findings": self.total_findings,
                "seconds": self.seconds,
                "cases_per_s": self.cases / self.seconds if self.seconds else None,
                "targets": [{**asdict(s), "cases_per_s": s.cases_per_s} for s in self.stats],
                "details": [asdict(f) for f in self.findings]}


def _make_target(name: str, codec: Codec) -> Any:
    params = default_params()
    if name == "decoder":
        return DecoderTarget(codec)
    if name == "monitor":
        return MonitorTarget(codec)
    kind, _, ctrl = name.partition(":")
    if kind == "node":
        return NodeTarget(ctrl, params, codec)
    if kind == "controller":
        return ControllerTarget(ctrl, params)
    raise ValueError(f"unknown fuzz target {name!r}")


def run_fuzz(cases: int = DEFAULT_CASES, hypothesis_examples: int = 500, seed: int = 0,
             only: list[str] | None = None,
             progress: Callable[[str], None] | None = None) -> FuzzReport:
    """Run both engines; ``cases`` numpy cases in total, split by SHARES."""
    codec = Codec()
    findings = Findings()
    report = FuzzReport(seed)
    names = [n for n in SHARES if only is None or n in only]
    share_sum = sum(SHARES[n] for n in names) or 1.0
    clock = time.perf_counter  # reporting only
    for index, name in enumerate(SHARES):
        if name not in names:
            continue
        budget = round(cases * SHARES[name] / share_sum)
        target = _make_target(name, codec)
        start, done, chunk = clock(), 0, 0
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")  # each location once: overflow etc. is
            while done < budget:               # allowed if the invariants still hold
                n = min(CHUNK, budget - done)
                target.run(np.random.default_rng([seed, index, chunk]), n, findings)
                done += n
                chunk += 1
        report.stats.append(TargetStats(name, "numpy", done, findings.counts.get(name, 0),
                                        clock() - start, _warning_sites(caught),
                                        dict(findings.by_kind.get(name, {}))))
        if progress:
            progress(_row(report.stats[-1]))
    if hypothesis_examples > 0:
        params = default_params()
        jobs: list[tuple[str, Callable[[], int]]] = []
        if only is None or "decoder" in only:
            jobs.append(("hypothesis:decoder", lambda: property_pass.decoder(
                hypothesis_examples, findings, codec)))
        if only is None or "monitor" in only:
            jobs.append(("hypothesis:monitor", lambda: property_pass.monitor(
                hypothesis_examples, findings, codec)))
        for ctrl in CONTROLLER_NAMES:
            if only is None or f"controller:{ctrl}" in only:
                jobs.append((f"hypothesis:controller:{ctrl}",
                             lambda c=ctrl: property_pass.controller(
                                 c, hypothesis_examples, findings, params)))
        for name, job in jobs:
            start = clock()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("default")
                n = job()
            report.stats.append(TargetStats(name, "hypothesis", n,
                                            findings.counts.get(name, 0), clock() - start,
                                            _warning_sites(caught),
                                            dict(findings.by_kind.get(name, {}))))
            if progress:
                progress(_row(report.stats[-1]))
    report.findings = findings.items
    return report


def _warning_sites(caught: list[warnings.WarningMessage]) -> list[str]:
    """Distinct 'file:line: message' of the warnings seen (sorted)."""
    return sorted({f"{w.filename.rsplit('/', 1)[-1]}:{w.lineno}: {w.message}" for w in caught})


def _row(s: TargetStats) -> str:
    return (f"  {s.target:<34} {s.engine:<10} {s.cases:>9} {s.findings:>8} "
            f"{s.seconds:>8.1f} {s.cases_per_s:>10.0f}")


def _target_count(only: list[str] | None, hypothesis_examples: int) -> int:
    """How many rows ``run_fuzz`` reports (numpy targets + hypothesis jobs)."""
    numpy_targets = [n for n in SHARES if only is None or n in only]
    hyp = ["decoder", "monitor", *(f"controller:{c}" for c in CONTROLLER_NAMES)]
    hyp_jobs = [] if hypothesis_examples <= 0 else [j for j in hyp if only is None or j in only]
    return len(numpy_targets) + len(hyp_jobs)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="rhonn-bench fuzz", description=__doc__)
    parser.add_argument("--cases", type=number(int, lo=0), default=None,
                        help="numpy-engine cases in total (split over the targets; default "
                             f"{DEFAULT_CASES}); with --planted per target (default "
                             f"{PLANTED_CASES})")
    parser.add_argument("--hypothesis-examples", type=number(int, lo=0), default=None,
                        help="hypothesis examples per hypothesis target (0 = skip; default "
                             f"500, with --planted {PLANTED_EXAMPLES})")
    parser.add_argument("--planted", action="store_true",
                        help="run the oracle-checked targets against each planted missing "
                             "check instead (harness/fuzz/planted.py)")
    parser.add_argument("--seed", type=number(int, lo=0), default=0,
                        help="seed of every random case (same seed, same cases)")
    parser.add_argument("--only", type=choice_list(tuple(SHARES), "target"), default=None,
                        help="comma-separated targets, from: " + ", ".join(SHARES)
                             + " (default: all)")
    parser.add_argument("--json", default=None, help="write the report as JSON here")
    args = parser.parse_args(argv)
    if args.json:
        try:
            check_out_file(args.json, "--json")
        except UsageError as exc:
            parser.error(str(exc))
    if args.planted:
        return _main_planted(args)
    args.cases = DEFAULT_CASES if args.cases is None else args.cases
    if args.hypothesis_examples is None:
        args.hypothesis_examples = 500
    only = args.only
    print(f"fuzz: {args.cases} numpy cases, {args.hypothesis_examples} hypothesis examples "
          f"per target, seed {args.seed}")
    print(f"  {'target':<34} {'engine':<10} {'cases':>9} {'findings':>8} {'s':>8} "
          f"{'cases/s':>10}", flush=True)
    bar = Bar("fuzz", total=_target_count(only, args.hypothesis_examples), unit="target")

    def show(line: str) -> None:
        bar.write(line)
        bar.set(bar.n + 1)

    report = run_fuzz(args.cases, args.hypothesis_examples, args.seed, only, progress=show)
    bar.close()
    print(f"  {'total':<34} {'':<10} {report.cases:>9} {report.total_findings:>8} "
          f"{report.seconds:>8.1f} {report.cases / max(report.seconds, 1e-9):>10.0f}")
    for s in report.stats:
        for kind, count in sorted(s.by_kind.items()):
            print(f"  findings [{s.target}] {kind}: {count}")
    for s in report.stats:
        for w in s.numeric_warnings:
            print(f"  note [{s.target}] numeric warning (handled): {w}")
    for f in report.findings:
        print(f"\n[{f.target}] {f.kind}: {f.message}\n  case: {f.case}\n{f.traceback}",
              file=sys.stderr)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report.to_json(), fh, indent=2)
            fh.write("\n")
    return 0 if report.total_findings == 0 else 1


def _main_planted(args: Any) -> int:
    """``--planted``: the planted-bug matrix (see the module docstring)."""
    cases = PLANTED_CASES if args.cases is None else args.cases
    examples = PLANTED_EXAMPLES if args.hypothesis_examples is None \
        else args.hypothesis_examples
    print(f"fuzz --planted: {cases} numpy cases, {examples} hypothesis examples per target, "
          f"seed {args.seed}")
    print(f"  {'bug':<18} {'target':<20} {'cases':>7} {'mismatches':>10} {'first at':>8}  "
          "kinds")
    rows = []
    for bug in PLANTED:
        for d in planted.matrix(cases, examples, args.seed, (bug,)):
            rows.append(d)
            kinds = ", ".join(f"{k} {v}" for k, v in sorted(d.by_kind.items(),
                                                              key=lambda kv: -kv[1]))
            first = "-" if d.first_at is None else str(d.first_at)
            print(f"  {d.bug:<18} {d.target:<20} {d.cases:>7} {d.mismatches:>10} "
                  f"{first:>8}  {kinds}", flush=True)
    missed = [b for b in PLANTED if not any(d.mismatches for d in rows if d.bug == b)]
    print("every planted bug caught" if not missed else f"NOT caught: {', '.join(missed)}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"seed": args.seed, "cases": cases, "hypothesis_examples": examples,
                       "detections": [asdict(d) for d in rows], "not_caught": missed},
                      fh, indent=2)
            fh.write("\n")
    return 0 if not missed else 1


if __name__ == "__main__":
    raise SystemExit(main())
