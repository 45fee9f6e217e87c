"""Mutation testing of the safety modules with cosmic-ray, one module at a time.

    python -m harness.tools.mutation --modules envelope checkpoint --out docs/safety/mutation.md

For each module: copy the source tree into a scratch directory (the mutants are written
there, never into the working tree, so tests running from the checkout never import a
mutant), create a cosmic-ray work database (``runs/mutation/<name>.sqlite``), mark the mutants that
are not run (see below) as skipped, time the module's fast unit tests on the unmutated code,
then let cosmic-ray's ``local`` distributor (one worker: one test process at a time) run
every remaining mutant against those tests with a per-mutant timeout of
``max(--min-timeout, --timeout-factor × baseline)``; a timed-out mutant counts as killed.

Not run:

* mutants inside annotations: every safety module has ``from __future__ import
  annotations``, so an annotation is never evaluated and its mutants are equivalent;
* with ``--operators focused`` (the default), the replacements of a binary or comparison
  operator outside its "natural" set (``+`` → ``-``/``*`` but not ``+`` → ``<<``/``**``;
  ``>`` → ``>=``/``<``/``<=`` but not ``>`` → ``is``; the choice of PIT's and mutmut's default
  operators). All other operators (numbers, ``not``, booleans, ``and``/``or``, unary
  operators, exceptions, loops, decorators) always run. ``--operators all`` runs everything.

Survivors listed in ``docs/safety/mutation-equivalent.toml`` (module, operator, the stripped
source line, the column and a reason) count as equivalent: they leave the score's denominator
and are listed with their reason. The score is killed / (run − equivalent).

Results accumulate in ``<out>.json`` (one entry per module, replaced when the module is run
again); the part of ``--out`` between the two ``mutation-results`` markers is regenerated
from it, the rest of the file (the hand-written dispositions) is kept.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import json
import os
import re
import shlex
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BEGIN = "<!-- mutation-results:begin -->"
END = "<!-- mutation-results:end -->"
EQUIVALENT_FILE = ROOT / "docs" / "safety" / "mutation-equivalent.toml"
WORK_DIR = ROOT / "runs" / "mutation"


@dataclass(frozen=True)
class Target:
    """One safety module and the fast unit tests that exercise it (pytest arguments: a file,
    or ``file::test`` for the single-process tests of a file that also starts processes).
    ``functions``: when given, only the mutants inside these functions (qualified names,
    ``Class.method``) or module-level constants run (the decision-carrying part of a large
    module), the rest are not run."""

    path: str
    tests: tuple[str, ...]
    functions: tuple[str, ...] = ()


_BENCH = "tests/test_safety_coverage_bench.py::"
# the bench's single-process tests (its two cross-process runs take 8 s of the file's 10 s)
BENCH_TESTS = tuple(_BENCH + t for t in (
    "test_every_run_option_reaches_the_plant_as_its_parser_reads_it",
    "test_the_controller_and_plant_command_lines",
    "test_process_faults_and_core_faults_are_routed",
    "test_a_bench_without_a_work_dir_removes_its_own",
    "test_a_dead_hub_takes_its_processes_with_it",
    "test_a_failed_start_is_not_awaited_again",
    "test_a_dirty_or_reconfigured_controller_is_replaced",
    "test_an_unanswered_soft_reset_marks_the_controller_for_replacement",
    "test_a_failed_recoding_is_a_start_failure",
    "test_the_reason_of_a_run_from_the_plants_end",
    "test_a_run_the_plant_does_not_load_is_a_start_failure",
    "test_an_unanswered_reset_after_a_run_replaces_the_controller_and_keeps_the_log_whole",
    "test_a_reset_response_the_recorder_misses_costs_an_idle_wait",
    "test_what_is_retried_and_how_it_is_named",
    "test_a_retry_replaces_an_older_first_attempt",
    "test_a_bus_restart_without_a_bus_server_is_skipped_and_said",
    "test_frame_faults_go_to_the_sender_of_the_message_or_signal_they_name",
    "test_a_process_fault_is_due_at_its_time_and_only_once",
    "test_a_live_controller_with_the_same_coding_is_kept_and_a_dead_one_replaced",
    "test_a_recoding_counts_its_reset_once",
    "test_the_controller_setup_names_the_keys_only_when_secoc_is_on",
    "test_in_lockstep_delays_act_on_the_plants_frames_only",
    "test_a_fault_due_within_the_rounding_tolerance_is_taken_once",
    "test_the_benchs_coding_has_the_controllers_default_fault_seed",
    "test_another_coding_is_applied_in_place_or_by_a_restart",
))

# The fast, single-process tests of each module (no closed loops, no bus processes).
TARGETS: dict[str, Target] = {
    "crc": Target("can_db/crc.py", ("tests/test_safety_coverage_crc.py",)),
    "codec": Target("can_db/codec.py", ("tests/test_can_codec.py",
                                        "tests/test_safety_coverage_codec.py")),
    "monitor": Target("can_db/monitor.py", ("tests/test_can_monitor.py",
                                            "tests/test_safety_coverage_monitor.py")),
    "secoc": Target("can_db/secoc.py", ("tests/test_secoc_unit.py",
                                        "tests/test_safety_coverage_secoc.py")),
    "secoc_keys": Target("can_db/secoc_keys.py", ("tests/test_safety_coverage_secoc_keys.py",
                                                  "tests/test_secoc_unit.py")),
    "durable": Target("can_db/process/durable.py", ("tests/test_safety_coverage_durable.py",)),
    "envelope": Target("controller/runtime/envelope.py",
                       ("tests/test_safety_coverage_envelope.py", "tests/test_envelope.py")),
    "checkpoint": Target("controller/runtime/checkpoint.py",
                         ("tests/test_safety_coverage_checkpoint.py",)),
    "plausibility": Target("controller/runtime/plausibility.py",
                           ("tests/test_safety_coverage_plausibility.py",)),
    # the node's safety decisions: the per-cycle validation and its fault bits and mode
    # (`_answer`), the core's fault reaction and latch with its safe output, the ramp-down of
    # a lost driver, the output envelope's application, the rx-overload bit and the hand-off
    # of accepted sensor frames to the frozen-signal check (the frame plumbing, the SecOC
    # hooks and the frame encoding are exercised by the cross-process tests)
    "node": Target("controller/runtime/node.py", ("tests/test_safety_coverage_node.py",
                                                  "tests/test_controller_node.py",
                                                  "tests/test_faults_unit.py"),
                   functions=("ControllerNode._answer", "ControllerNode._run_controller",
                              "ControllerNode._fault_outputs", "ControllerNode._ramp_down",
                              "ControllerNode._apply_envelope", "ControllerNode._accept",
                              "ControllerNode._rx_overloaded")),
    # who may reset the controller or write its coding: sessions, S3, SecurityAccess with its
    # attempt counting and lock-out, the protected services, the production allow-list and
    # the moving refusal (reads, TesterPresent, the secret's file parsing and the coding's
    # type check are not mutated: 467 mutants at ~6 s each do not fit the run's time box)
    "uds": Target("controller/runtime/uds.py", ("tests/test_uds_server.py",),
                  functions=("UdsServer.__init__", "UdsServer.handle", "UdsServer.expire",
                             "UdsServer._enter", "UdsServer._protected",
                             "UdsServer.soft_reset_done", "UdsServer._security_access",
                             "UdsServer._ecu_reset", "UdsServer._write", "security_key",
                             "production_problem", "SEED_BYTES", "S3_S", "MAX_ATTEMPTS",
                             "LOCKOUT_S", "PRODUCTION_KEYS")),
    # the diagnostic channel of the controller process: the "moving" decision that guards
    # resets and coding writes, the request path, and the coding a reset applies
    "diag_link": Target("controller/runtime/process.py",
                        ("tests/test_uds_server.py",
                         "tests/test_safety_coverage_controller_process.py"),
                        functions=("DiagLink.moving", "DiagLink.on_frame",
                                   "DiagLink._log_refusal", "DiagLink.respond_pending",
                                   "_coding_problem", "apply_coding", "coding_of",
                                   "_boot_count")),
    # the warm bench's decisions between and after runs: which controller is replaced or
    # reset (a dirty or reconfigured one, a failed reset), the coding it gets, the faults
    # routed to each process, the plant's per-run SecOC arguments, what counts as an
    # unexpected death and the retry's reason and kept files (the process plumbing is
    # exercised by the cross-process tests, too slow to run per mutant)
    "bench": Target("harness/run/hil_bench.py", BENCH_TESTS,
                    functions=("route_frame_faults", "run_faults", "plant_run_args",
                               "controller_coding", "controller_setup",
                               "Bench._prepare_controller", "Bench._recode",
                               "Bench._soft_reset", "Bench._reset_failed",
                               "Bench._died_unexpectedly", "Bench._due",
                               "_failure_of", "_keep_attempt_files")),
    # the hub's own unit tests first: with -x a mutant they kill costs ~3 s, not the ~20 s of
    # the cross-process bus tests
    "hub": Target("can_db/transport/hub.py", ("tests/test_safety_coverage_hub.py",
                                              "tests/test_localbus.py")),
}

# Natural replacements kept by ``--operators focused`` (source operator → targets).
_BINARY_KEEP = {
    "Add": {"Sub", "Mul"}, "Sub": {"Add"}, "Mul": {"Div", "Add"}, "Div": {"Mul", "FloorDiv"},
    "FloorDiv": {"Div", "Mul"}, "Mod": {"FloorDiv", "Add"}, "Pow": {"Mul"},
    "LShift": {"RShift"}, "RShift": {"LShift"}, "BitAnd": {"BitOr", "BitXor"},
    "BitOr": {"BitAnd", "BitXor"}, "BitXor": {"BitOr", "BitAnd"},
}
_COMPARISON_KEEP = {
    "Lt": {"LtE", "Gt", "GtE"}, "LtE": {"Lt", "Gt", "GtE"}, "Gt": {"GtE", "Lt", "LtE"},
    "GtE": {"Gt", "Lt", "LtE"}, "Eq": {"NotEq"}, "NotEq": {"Eq"}, "Is": {"IsNot"},
    "IsNot": {"Is"}, "In": {"NotIn"}, "NotIn": {"In"},
}
_REPLACE = re.compile(r"core/Replace(BinaryOperator|ComparisonOperator)_(\w+?)_(\w+)$")


def operator_kept(name: str) -> bool:
    """Whether ``--operators focused`` runs the cosmic-ray operator ``name``."""
    m = _REPLACE.match(name)
    if m is None:
        return True
    kind, src, dst = m.groups()
    keep = _BINARY_KEEP if kind == "BinaryOperator" else _COMPARISON_KEEP
    return dst in keep.get(src, set())


def annotation_spans(source: str) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) (line, column) spans of every annotation in ``source``."""
    spans = []
    for node in ast.walk(ast.parse(source)):
        anns: list[ast.expr | None] = []
        if isinstance(node, ast.arg):
            anns.append(node.annotation)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            anns.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            anns.append(node.annotation)
        for a in anns:
            if a is not None and a.end_lineno is not None and a.end_col_offset is not None:
                spans.append(((a.lineno, a.col_offset), (a.end_lineno, a.end_col_offset)))
    return spans


def function_spans(source: str, names: Iterable[str]
                   ) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) (line, column) spans of the functions ``names`` (qualified:
    ``Class.method``; or a module-level constant, ``NAME = ...``) in ``source``, decorators
    included; ValueError names one not found."""
    wanted, spans = set(names), []
    found: set[str] = set()

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                qual = prefix + child.name
                if qual in wanted and not isinstance(child, ast.ClassDef):
                    found.add(qual)
                    first = min([child.lineno, *(d.lineno for d in child.decorator_list)])
                    assert child.end_lineno is not None and child.end_col_offset is not None
                    spans.append(((first, 0), (child.end_lineno, child.end_col_offset)))
                visit(child, qual + ".")
            elif (not prefix and isinstance(child, ast.Assign | ast.AnnAssign)
                  and (targets := child.targets if isinstance(child, ast.Assign)
                       else [child.target])
                  and any(isinstance(t, ast.Name) and t.id in wanted for t in targets)):
                found.update(t.id for t in targets if isinstance(t, ast.Name))
                assert child.end_lineno is not None and child.end_col_offset is not None
                spans.append(((child.lineno, 0), (child.end_lineno, child.end_col_offset)))

    visit(ast.parse(source), "")
    if wanted - found:
        raise ValueError(f"function(s) not found: {', '.join(sorted(wanted - found))}")
    return spans


def _inside(pos: Sequence[int], spans: Iterable[tuple[tuple[int, int], tuple[int, int]]]
            ) -> bool:
    p = (int(pos[0]), int(pos[1]))
    return any(s <= p < e for s, e in spans)


@dataclass
class Survivor:
    """A mutant the tests did not kill."""

    line: int
    col: int
    operator: str
    code: str
    diff: str
    reason: str = ""      # set when listed as equivalent


@dataclass
class ModuleResult:
    """Outcome of one module's run."""

    name: str
    path: str
    tests: list[str]
    operators: str
    mutants: int = 0
    skipped_annotation: int = 0
    skipped_operator: int = 0
    skipped_scope: int = 0          # outside the target's functions
    functions: list[str] = field(default_factory=list)
    run: int = 0
    killed: int = 0
    timeouts: int = 0
    incompetent: int = 0
    pending: int = 0
    baseline_s: float = 0.0
    timeout_s: float = 0.0
    wall_s: float = 0.0
    survivors: list[Survivor] = field(default_factory=list)
    equivalent: list[Survivor] = field(default_factory=list)

    @property
    def score(self) -> float:
        """Killed / (run − equivalent), percent (100 when nothing is left to kill)."""
        denom = self.run - len(self.equivalent)
        return 100.0 * self.killed / denom if denom > 0 else 100.0


def load_equivalents(path: Path = EQUIVALENT_FILE) -> list[dict[str, object]]:
    """The reviewed equivalent mutants (empty when the file does not exist)."""
    if not path.exists():
        return []
    return list(tomllib.loads(path.read_text()).get("equivalent", []))


def _match_equivalent(module: str, s: Survivor, equivalents: list[dict[str, object]]
                      ) -> str | None:
    for e in equivalents:
        if (e.get("module") == module and e.get("operator") == s.operator
                and str(e.get("code", "")).strip() == s.code
                and int(e.get("col", s.col)) == s.col):   # type: ignore[call-overload]
            return str(e.get("reason", ""))
    return None


def copy_tree(dest: Path) -> None:
    """The checkout's sources (no VCS, venv, outputs or caches) into ``dest``."""
    ignore = shutil.ignore_patterns(".git", ".venv", "runs", "out", "build", "__pycache__",
                                    ".hypothesis", ".pytest_cache", ".ruff_cache",
                                    ".coverage*", "*.egg-info")
    shutil.copytree(ROOT, dest, ignore=ignore, symlinks=True)


def test_command(target: Target) -> list[str]:
    """The per-mutant test command (stops at the first failure, measures no coverage)."""
    cov = ["--no-cov"] if _has_pytest_cov() else []
    return [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *cov,
            "-o", "addopts=", *target.tests]


def _has_pytest_cov() -> bool:
    try:
        import pytest_cov  # noqa: F401
    except ImportError:
        return False
    return True


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    for var in ("COVERAGE_PROCESS_CONFIG", "COVERAGE_PROCESS_START"):
        env.pop(var, None)
    return env


def reopen_survivors(work_db: Path) -> int:
    """Forget the outcome of the surviving mutants so the next exec runs them again (once
    tests were added); returns how many."""
    with contextlib.closing(sqlite3.connect(work_db)) as db, db:
        n = db.execute("DELETE FROM work_results WHERE test_outcome = 'SURVIVED'").rowcount
    return n


def run_module(name: str, target: Target, tree: Path, *, operators: str, min_timeout: float,
               timeout_factor: float, resume: bool, log: Path,
               rerun_survivors: bool = False) -> ModuleResult:
    """Mutate ``target`` in ``tree`` and run its tests against every kept mutant."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    WORK_DIR.mkdir(parents=True, exist_ok=True)
    work_db = WORK_DIR / f"{name}.sqlite"
    config = WORK_DIR / f"{name}.toml"
    env = _env(tree)
    cmd = test_command(target)
    result = ModuleResult(name, target.path, list(target.tests), operators,
                          functions=list(target.functions))
    t0 = time.monotonic()
    base = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    result.baseline_s = time.monotonic() - t0
    if base.returncode != 0:
        raise SystemExit(f"{name}: the tests fail on the unmutated code:\n{base.stdout[-3000:]}")
    result.timeout_s = max(min_timeout, timeout_factor * result.baseline_s)
    config.write_text(
        "[cosmic-ray]\n"
        f'module-path = "{target.path}"\n'
        f"timeout = {result.timeout_s:.1f}\n"
        "excluded-modules = []\n"
        f"test-command = {json.dumps(shlex.join(cmd))}\n\n"
        "[cosmic-ray.distributor]\n"
        'name = "local"\n')
    source = WORK_DIR / f"{name}.source.py"
    if rerun_survivors:
        if not (work_db.exists() and source.exists()
                and source.read_text() == (tree / target.path).read_text()):
            raise SystemExit(f"{name}: --rerun-survivors needs the work database of the unchanged "
                             "module; run it in full")
        print(f"{name}: {reopen_survivors(work_db)} survivors to run again", flush=True)
    elif not (resume and work_db.exists()):
        work_db.unlink(missing_ok=True)
        # the text the mutants were made from: a later report reads lines from it
        shutil.copyfile(tree / target.path, source)
        subprocess.run([sys.executable, "-m", "cosmic_ray.cli", "init", str(config),
                        str(work_db)], cwd=tree, env=env, check=True, capture_output=True)
        spans = annotation_spans((tree / target.path).read_text())
        scope = (function_spans((tree / target.path).read_text(), target.functions)
                 if target.functions else None)
        with use_db(str(work_db), WorkDB.Mode.open) as db:
            for item in list(db.pending_work_items):
                m = item.mutations[0]
                why = None
                if scope is not None and not _inside(m.start_pos, scope):
                    why = "outside the selected functions"
                    result.skipped_scope += 1
                elif _inside(m.start_pos, spans):
                    why = "annotation (never evaluated)"
                    result.skipped_annotation += 1
                elif operators == "focused" and not operator_kept(m.operator_name):
                    why = "operator outside the focused set"
                    result.skipped_operator += 1
                if why:
                    db.set_result(item.job_id, WorkResult(worker_outcome=WorkerOutcome.SKIPPED,
                                                          output=why))
    with log.open("a") as fh:
        subprocess.run([sys.executable, "-m", "cosmic_ray.cli", "exec", str(config),
                        str(work_db)], cwd=tree, env=env, stdout=fh, stderr=fh, check=False)
    collect(result, work_db, (tree / target.path).read_text())
    result.wall_s = time.monotonic() - t0
    return result


def collect(result: ModuleResult, work_db: Path, source: str) -> None:
    """Fill ``result`` from a cosmic-ray work database of the module whose text is ``source``."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    lines = source.splitlines()
    equivalents = load_equivalents()
    with use_db(str(work_db), WorkDB.Mode.open) as db:
        items = {w.job_id: w for w in db.work_items}
        result.mutants = len(items)
        done = dict(db.results)
        result.pending = len(items) - len(done)
        skipped_ann = skipped_op = skipped_scope = 0
        for job_id, r in done.items():
            m = items[job_id].mutations[0]
            if r.worker_outcome == WorkerOutcome.SKIPPED:
                if str(r.output).startswith("annotation"):
                    skipped_ann += 1
                elif str(r.output).startswith("outside"):
                    skipped_scope += 1
                else:
                    skipped_op += 1
                continue
            result.run += 1
            if r.test_outcome == TestOutcome.INCOMPETENT:
                result.incompetent += 1
            if r.test_outcome != TestOutcome.SURVIVED:
                result.killed += 1
                result.timeouts += r.output == "timeout"
                continue
            line, col = int(m.start_pos[0]), int(m.start_pos[1])
            s = Survivor(line, col, m.operator_name, lines[line - 1].strip(),
                         "\n".join(d[0] + " " + d[1:].strip() for d in (r.diff or "").splitlines()
                                   if d[:1] in ("+", "-") and d[:3] not in ("+++", "---")))
            reason = _match_equivalent(result.path, s, equivalents)
            if reason is None:
                result.survivors.append(s)
            else:
                s.reason = reason
                result.equivalent.append(s)
        result.skipped_annotation, result.skipped_operator = skipped_ann, skipped_op
        result.skipped_scope = skipped_scope


def _table(results: dict[str, dict[str, object]]) -> str:
    rows = ["| module | mutants | not run (annotation / operator / outside the functions) | run "
            "| killed (timeout / incompetent) | equivalent | survived | pending | score | tests "
            "| per-mutant timeout | wall time |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results.values():
        denom = int(r["run"]) - len(r["equivalent"])   # type: ignore[arg-type]
        score = 100.0 * int(r["killed"]) / denom if denom > 0 else 100.0  # type: ignore[call-overload]
        files: dict[str, str] = {}   # file name → "" or " (some tests)"
        for t in r["tests"]:  # type: ignore[attr-defined]
            name = Path(t.split("::")[0]).name
            files[name] = " (its single-process tests)" if "::" in t else ""
        tests = ", ".join(f"`{name}`{note}" for name, note in files.items())
        path = f"`{r['path']}`" + (f" (restricted: {len(r['functions'])} names)"  # type: ignore[arg-type]
                                   if r.get("functions") else "")
        rows.append(
            f"| {path} | {r['mutants']} | {r['skipped_annotation']} / "
            f"{r['skipped_operator']} / {r.get('skipped_scope', 0)} | {r['run']} | "
            f"{r['killed']} ({r['timeouts']} / {r.get('incompetent', 0)}) | "
            f"{len(r['equivalent'])} | {len(r['survivors'])} | {r['pending']} | "  # type: ignore[arg-type]
            f"**{score:.1f} %** | {tests} | {float(r['timeout_s']):.0f} s | "  # type: ignore[arg-type]
            f"{float(r.get('wall_s', 0.0)):.0f} s |")  # type: ignore[arg-type]
    scoped = [f"- `{r['path']}`: " + ", ".join(f"`{f}`" for f in r["functions"])  # type: ignore[attr-defined]
              for r in results.values() if r.get("functions")]
    if scoped:
        rows += ["", "Functions and constants mutated where a module is restricted (its other "
                 "mutants are not run):", "", *scoped]
    return "\n".join(rows)


def _survivor_lines(results: dict[str, dict[str, object]]) -> str:
    out: list[str] = []
    for r in results.values():
        for kind, key in (("survived", "survivors"), ("equivalent", "equivalent")):
            for s in r[key]:  # type: ignore[attr-defined]
                diff = s["diff"].replace("\n", " ⟶ ")
                line = (f"- `{r['path']}:{s['line']}` {kind}: "
                        f"`{s['operator'].removeprefix('core/')}` `{diff}`")
                if s.get("reason"):
                    line += f" — {s['reason']}"
                out.append(line)
    return "\n".join(out) if out else "(none)"


def render(results: dict[str, dict[str, object]]) -> str:
    """The generated part of the markdown (between the markers)."""
    return (f"{BEGIN}\n\n{_table(results)}\n\nSurviving and equivalent mutants:\n\n"
            f"{_survivor_lines(results)}\n\n{END}")


def write_outputs(out: Path, new: list[ModuleResult]) -> dict[str, dict[str, object]]:
    """Merge ``new`` into ``<out>.json`` and regenerate the marked part of ``out``."""
    store = out.with_suffix(".json")
    results: dict[str, dict[str, object]] = (json.loads(store.read_text())
                                             if store.exists() else {})
    for r in new:
        d = asdict(r)
        d["score"] = r.score
        results[r.name] = d
    order = list(TARGETS)
    results = {k: results[k] for k in sorted(results, key=order.index)}
    out.parent.mkdir(parents=True, exist_ok=True)
    store.write_text(json.dumps(results, indent=1) + "\n")
    text = out.read_text() if out.exists() else f"# Mutation testing\n\n{BEGIN}\n{END}\n"
    if BEGIN not in text or END not in text:
        text += f"\n{BEGIN}\n{END}\n"
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    out.write_text(head + render(results) + tail)
    return results


def report_only(modules: Sequence[str], out: Path) -> int:
    """Re-read the work databases of ``modules`` and rewrite the report (timings kept)."""
    store = out.with_suffix(".json")
    old = json.loads(store.read_text()) if store.exists() else {}
    results = []
    for name in modules:
        work_db = WORK_DIR / f"{name}.sqlite"
        if not work_db.exists():
            continue
        target = TARGETS[name]
        prev = old.get(name, {})
        r = ModuleResult(name, target.path, list(prev.get("tests", target.tests)),
                         prev.get("operators", "focused"),
                         functions=list(prev.get("functions", target.functions)),
                         baseline_s=prev.get("baseline_s", 0.0),
                         timeout_s=prev.get("timeout_s", 0.0), wall_s=prev.get("wall_s", 0.0))
        source = WORK_DIR / f"{name}.source.py"
        collect(r, work_db, (source if source.exists() else ROOT / target.path).read_text())
        results.append(r)
        print(f"{name}: {r.score:.1f} %, {len(r.survivors)} survived, "
              f"{len(r.equivalent)} equivalent")
    write_outputs(out, results)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog="python -m harness.tools.mutation",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--modules", nargs="+", default=["envelope", "checkpoint", "plausibility",
                                                     "secoc_keys", "crc"],
                    choices=list(TARGETS), help="modules to mutate, one after the other")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "safety" / "mutation.md")
    ap.add_argument("--operators", choices=["focused", "all"], default="focused")
    ap.add_argument("--min-timeout", type=float, default=10.0,
                    help="smallest per-mutant timeout, s")
    ap.add_argument("--timeout-factor", type=float, default=4.0,
                    help="per-mutant timeout as a multiple of the baseline test time")
    ap.add_argument("--resume", action="store_true",
                    help="continue the modules' existing work databases instead of starting anew")
    ap.add_argument("--fail-under", type=float, default=None,
                    help="exit 1 when a module's score is below this percentage")
    ap.add_argument("--rerun-survivors", action="store_true",
                    help="run only the survivors of the existing work databases again (once tests "
                         "were added; the module must be unchanged)")
    ap.add_argument("--report-only", action="store_true",
                    help="rebuild the report from the existing work databases (equivalents "
                         "re-applied), run nothing")
    args = ap.parse_args(argv)
    done: list[ModuleResult] = []
    if args.report_only:
        return report_only(args.modules, args.out)
    with tempfile.TemporaryDirectory(prefix="rhonn-mutation-") as tmp:
        tree = Path(tmp) / "tree"
        copy_tree(tree)
        log = WORK_DIR / "cosmic-ray.log"
        WORK_DIR.mkdir(parents=True, exist_ok=True)
        for name in args.modules:
            target = TARGETS[name]
            missing = [t for t in target.tests if not (tree / t.split("::")[0]).exists()]
            if missing:  # a wrong listing would measure the module against fewer tests
                print(f"{name}: test file(s) not found: {', '.join(missing)}", file=sys.stderr)
                return 2
            r = run_module(name, target, tree, operators=args.operators,
                           min_timeout=args.min_timeout, timeout_factor=args.timeout_factor,
                           resume=args.resume, log=log,
                           rerun_survivors=args.rerun_survivors)
            done.append(r)
            write_outputs(args.out, [r])
            print(f"{name}: {r.killed}/{r.run - len(r.equivalent)} killed ({r.score:.1f} %), "
                  f"{len(r.survivors)} survived, {len(r.equivalent)} equivalent, "
                  f"{r.pending} pending, {r.wall_s:.0f} s", flush=True)
    if args.fail_under is not None and any(r.score < args.fail_under for r in done):
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
