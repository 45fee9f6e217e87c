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
    """One safety module and the fast unit tests that exercise it (pytest arguments)."""

    path: str
    tests: tuple[str, ...]


# The fast, single-process tests of each module (no closed loops, no bus processes).
TARGETS: dict[str, Target] = {
    "crc": Target("can_db/crc.py", ("tests/test_safety_coverage_crc.py",)),
    "codec": Target("can_db/codec.py", ("tests/test_can_codec.py",
                                        "tests/test_safety_coverage_codec.py")),
    "monitor": Target("can_db/monitor.py", ("tests/test_can_monitor.py",)),
    "secoc": Target("can_db/secoc.py", ("tests/test_secoc_unit.py",)),
    "secoc_keys": Target("can_db/secoc_keys.py", ("tests/test_safety_coverage_secoc_keys.py",
                                                  "tests/test_secoc_unit.py")),
    "durable": Target("can_db/process/durable.py", ("tests/test_safety_coverage_durable.py",)),
    "envelope": Target("controller/runtime/envelope.py",
                       ("tests/test_safety_coverage_envelope.py", "tests/test_envelope.py")),
    "checkpoint": Target("controller/runtime/checkpoint.py",
                         ("tests/test_safety_coverage_checkpoint.py",)),
    "plausibility": Target("controller/runtime/plausibility.py",
                           ("tests/test_safety_coverage_plausibility.py",)),
    "node": Target("controller/runtime/node.py", ("tests/test_controller_node.py",
                                                  "tests/test_faults_unit.py")),
    "hub": Target("can_db/transport/hub.py", ("tests/test_localbus.py",
                                              "tests/test_safety_coverage_hub.py")),
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
    result = ModuleResult(name, target.path, list(target.tests), operators)
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
        with use_db(str(work_db), WorkDB.Mode.open) as db:
            for item in list(db.pending_work_items):
                m = item.mutations[0]
                why = None
                if _inside(m.start_pos, spans):
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
        skipped_ann = skipped_op = 0
        for job_id, r in done.items():
            m = items[job_id].mutations[0]
            if r.worker_outcome == WorkerOutcome.SKIPPED:
                if str(r.output).startswith("annotation"):
                    skipped_ann += 1
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


def _table(results: dict[str, dict[str, object]]) -> str:
    rows = ["| module | mutants | not run (annotation / operator) | run | killed (timeout) "
            "| equivalent | survived | pending | score | tests | per-mutant timeout |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results.values():
        denom = int(r["run"]) - len(r["equivalent"])   # type: ignore[arg-type]
        score = 100.0 * int(r["killed"]) / denom if denom > 0 else 100.0  # type: ignore[call-overload]
        tests = ", ".join(f"`{Path(t).name}`" for t in r["tests"])  # type: ignore[attr-defined]
        rows.append(
            f"| `{r['path']}` | {r['mutants']} | {r['skipped_annotation']} / "
            f"{r['skipped_operator']} | {r['run']} | {r['killed']} ({r['timeouts']}) | "
            f"{len(r['equivalent'])} | {len(r['survivors'])} | {r['pending']} | "  # type: ignore[arg-type]
            f"**{score:.1f} %** | {tests} | {float(r['timeout_s']):.0f} s |")  # type: ignore[arg-type]
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
