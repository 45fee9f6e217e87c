"""Structural coverage of the C core (statement, branch, MC/DC) from the back-to-back and module
tests, with clang's source-based coverage, and its gate.

Independent of how the binding is built: a copy of the repository's files is built through the
normal install step (``setup.py build_ext --inplace``) with ``CC`` set to a wrapper that adds
``-fprofile-instr-generate -fcoverage-mapping -fcoverage-mcdc``; the module tests compile
their own libraries with the same ``$CC``. The tests that exercise controller.native then run
in that copy, each process writing its raw profile; llvm-cov reports the files of
``controller/native/src`` only (OSQP's generated code and the binding aside).

    python controller/native/c_coverage.py                    # per-module table (markdown)
    python controller/native/c_coverage.py --gate             # fail below the recorded floor
    python controller/native/c_coverage.py --keep DIR --gaps  # keep the work; list the gaps
    python controller/native/c_coverage.py --from DIR --gaps  # the same from a kept DIR

``--gaps`` lists every line not run, branch direction not taken and MC/DC condition not shown
(``llvm-cov export``: lcov lines, JSON branches and MC/DC records; a branch inside a macro at
the macro's use), each with its reason from the table of docs/c_coverage.md (keyed by place,
what and not-shown; paste the generated table there and fill in new reasons), and exits 1 when
one has none.

Needs Debian's clang-19 and llvm-19 (apt-get install -y clang-19 llvm-19). Standalone (no
package import), like build_tools.py beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

NATIVE_DIR = Path(__file__).resolve().parent
REPO = NATIVE_DIR.parents[1]
TOOLS = {"cc": "clang-19", "profdata": "llvm-profdata-19", "cov": "llvm-cov-19"}
COV_FLAGS = ("-fprofile-instr-generate", "-fcoverage-mapping", "-fcoverage-mcdc")
TESTS: tuple[str, ...] = ("tests/test_native_core.py", "tests/test_native_refs.py",
                          "tests/test_native_handling.py", "tests/test_native_ekf_alloc.py",
                          "tests/test_native_baselines.py", "tests/test_native_fallback.py",
                          "tests/test_qp_recovery.py", "tests/test_native_dm_gain.py")
MCDC_BRANCH = 6  # llvm-cov's region kind of a condition of an MC/DC decision
# The gate: the level measured when it was set (docs/c_coverage.md), rounded down to 0.1, in
# percent of the core's lines, branches and MC/DC conditions; a drop below any fails.
FLOOR = {"lines": 99.8, "branches": 99.1, "mcdc": 96.4}


class NoClangError(RuntimeError):
    """clang-19 / llvm-19 missing (the message says how to install them)."""


def tools() -> dict[str, str]:
    """Paths of clang-19, llvm-profdata-19 and llvm-cov-19; NoClangError when one is absent."""
    found = {k: shutil.which(v) for k, v in TOOLS.items()}
    missing = [TOOLS[k] for k, v in found.items() if v is None]
    if missing:
        raise NoClangError(f"{', '.join(missing)} not found (apt-get install -y clang-19 llvm-19)")
    return {k: str(v) for k, v in found.items()}


def _copy_repo(dst: Path) -> None:
    """The repository's tracked and untracked-not-ignored files (no build output)."""
    names = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO,
                           check=True, capture_output=True).stdout.decode().split("\0")
    for name in filter(None, names):
        src = REPO / name
        if src.is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / name)


def measure(work: Path, tests: Sequence[str] = TESTS) -> dict[str, dict[str, list[int]]]:
    """{source file name: {"lines"|"branches"|"mcdc": [covered, count]}} plus "TOTAL"."""
    t = tools()
    repo = work / "repo"
    _copy_repo(repo)
    wrapper = work / "cc-cov"
    wrapper.write_text(f"#!/bin/sh\nexec {t['cc']} {' '.join(COV_FLAGS)} \"$@\"\n")
    wrapper.chmod(0o755)
    env = {**os.environ, "CC": str(wrapper), "PYTHONPATH": str(repo),
           "LLVM_PROFILE_FILE": str(work / "prof" / "%p-%m.profraw")}
    env.pop("RHONN_NO_CC", None)
    res = subprocess.run([sys.executable, "setup.py", "build_ext", "--inplace", "-q"], cwd=repo,
                         env=env, capture_output=True, text=True)
    exts = sorted((repo / "controller" / "native").glob("_rhcore*.so"))
    if res.returncode != 0 or len(exts) < 2:
        raise RuntimeError(f"instrumented build failed: {(res.stdout + res.stderr)[-800:]}")
    basetemp = work / "bt"
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                          f"--basetemp={basetemp}", *tests], cwd=repo, env=env,
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"tests failed under coverage: {res.stdout[-1500:]}")
    raws = sorted((work / "prof").glob("*.profraw"))
    merged = work / "merged.profdata"
    subprocess.run([t["profdata"], "merge", "-sparse", "-o", str(merged), *map(str, raws)],
                   check=True, capture_output=True)
    objs = [*exts, *sorted(basetemp.rglob("*.so"))]
    obj_args = [str(objs[0])] + [a for o in objs[1:] for a in ("-object", str(o))]
    (work / "obj_args.json").write_text(json.dumps([str(merged), obj_args]))
    return summary(work)


def _export(work: Path, *opts: str) -> str:
    """``llvm-cov export`` of the core's sources over the profile and objects kept in work."""
    merged, obj_args = json.loads((work / "obj_args.json").read_text())
    src = work / "repo" / "controller" / "native" / "src"
    return subprocess.run([tools()["cov"], "export", *opts, f"-instr-profile={merged}",
                           *obj_args, "--", *map(str, sorted(src.glob("*.c")))],
                          check=True, capture_output=True, text=True).stdout


def summary(work: Path) -> dict[str, dict[str, list[int]]]:
    """The per-file table of a measured work directory (see measure)."""
    data = json.loads(_export(work, "-summary-only"))["data"][0]
    table: dict[str, dict[str, list[int]]] = {}
    for f in data["files"]:
        s = f["summary"]
        table[Path(f["filename"]).name] = {k: [s[k]["covered"], s[k]["count"]]
                                           for k in ("lines", "branches", "mcdc")}
    tot = {k: [sum(v[k][0] for v in table.values()), sum(v[k][1] for v in table.values())]
           for k in ("lines", "branches", "mcdc")}
    table["TOTAL"] = tot
    return table


def _text(lines: list[str], l0: int, c0: int, l1: int, c1: int) -> str:
    """Source text of the region l0:c0 .. l1:c1 (1-based, end column exclusive) on one line; a
    region ending at a macro's name runs on to the macro's closing parenthesis."""
    rest = lines[l1 - 1][c1 - 1:]
    if rest.startswith("("):
        depth = 0
        for k, ch in enumerate(rest):
            depth += {"(": 1, ")": -1}.get(ch, 0)
            if depth == 0:
                c1 += k + 1
                break
    if l0 == l1:
        return lines[l0 - 1][c0 - 1:c1 - 1].strip()
    parts = [lines[l0 - 1][c0 - 1:], *lines[l0:l1 - 1], lines[l1 - 1][:c1 - 1]]
    return " ".join(p.strip() for p in parts)


def _side(true_n: int, false_n: int) -> str:
    return ("not evaluated" if not (true_n or false_n)
            else "never true" if not true_n else "never false")


def gaps(work: Path) -> list[tuple[str, str, str]]:
    """Every line and branch direction of the core the tests did not reach, and every condition
    of a multi-condition decision whose independent effect they did not show, in source order:
    (place, what, not shown); place ``file:line`` (a run of lines ``file:first-last``); a
    branch inside a macro is placed at the macro's use, with the macro's condition after it."""
    out: list[tuple[str, str, str]] = []
    missed: dict[str, list[int]] = {}
    name = ""
    for row in _export(work, "-format=lcov", "-skip-functions").splitlines():
        if row.startswith("SF:"):
            name = Path(row[3:]).name
        elif row.startswith("DA:") and row[3:].split(",")[1] == "0":
            missed.setdefault(name, []).append(int(row[3:].split(",")[0]))
    data = json.loads(_export(work, "-skip-functions"))["data"][0]
    for f in sorted(data["files"], key=lambda f: Path(f["filename"]).name):
        name = Path(f["filename"]).name
        lines = Path(f["filename"]).read_text().splitlines()
        items: set[tuple[int, int, str, str, str]] = set()
        for ln in sorted(missed.get(name, [])):
            items.add((ln, 0, f"{name}:{ln}", "line", "not run"))
        # conditions of MC/DC decisions by position: (l0, c0, l1, c1, text)
        conds: list[tuple[int, int, int, int, str]] = []
        for br in f["branches"]:
            l0, c0, l1, c1, true_n, false_n = br[:6]
            text = f"`{_text(lines, l0, c0, l1, c1)}`"
            if br[8] == MCDC_BRANCH:
                conds.append((l0, c0, l1, c1, text))
            if not (true_n and false_n):
                items.add((l0, c0, f"{name}:{l0}", text, _side(true_n, false_n)))
        for ex in f["expansions"]:
            l0, c0, l1, c1 = ex["source_region"][:4]
            if ex["filenames"][ex["source_region"][5]] != f["filename"]:
                continue  # a macro used inside another macro: placed at the outer one's use
            call = _text(lines, l0, c0, l1, c1)
            for br in ex["branches"]:
                mlines = Path(ex["filenames"][br[6]]).read_text().splitlines()
                text = f"`{call}` → `{_text(mlines, *br[:4])}`"
                if br[8] == MCDC_BRANCH:
                    conds.append((l0, c0, l1, c1, f"`{call}`"))
                if not (br[4] and br[5]):
                    items.add((l0, c0, f"{name}:{l0}", text, _side(br[4], br[5])))
        conds.sort()
        for l0, c0, l1, c1, *_, shown in f["mcdc_records"]:
            inside = [c[4] for c in conds if (l0, c0) <= c[:2] and c[2:4] <= (l1, c1)]
            decision = _text(lines, l0, c0, l1, c1)
            for i, ok in enumerate(shown):
                cond = inside[i] if len(inside) == len(shown) else f"condition {i + 1}"
                if not ok:
                    items.add((l0, c0, f"{name}:{l0}", f"{cond} in `{decision}`",
                               "MC/DC not shown"))
        # consecutive lines not run: one row
        rows: list[tuple[str, str, str]] = []
        first = last = 0
        for ln, _, place, what, side in sorted(items):
            if what == "line" and rows and rows[-1][1] == "line" and ln == last + 1:
                last = ln
                rows[-1] = (f"{name}:{first}-{last}", "line", side)
                continue
            if what == "line":
                first = last = ln
            rows.append((place, what, side))
        out.extend((p, "lines" if w == "line" else w, n) for p, w, n in rows)
    return out


def pct(cov: list[int]) -> float:
    """Percent covered (100 when there is nothing to cover)."""
    return 100.0 * cov[0] / cov[1] if cov[1] else 100.0


def markdown(table: dict[str, dict[str, list[int]]]) -> str:
    """The per-module table of docs/c_coverage.md."""
    rows = ["| module | statements (lines) | branches | MC/DC conditions |", "|---|---:|---:|---:|"]
    for name in [*sorted(k for k in table if k != "TOTAL"), "TOTAL"]:
        v = table[name]
        rows.append(f"| {'**total**' if name == 'TOTAL' else '`' + name + '`'} | "
                    + " | ".join(f"{pct(v[k]):.1f} % ({v[k][0]}/{v[k][1]})"
                                 for k in ("lines", "branches", "mcdc")) + " |")
    return "\n".join(rows)


GAPS_DOC = REPO / "docs" / "c_coverage.md"
GAPS_BEGIN, GAPS_END = "<!-- gaps: generated by c_coverage.py --gaps -->", "<!-- /gaps -->"


def _cells(row: str) -> list[str]:
    """The cells of a markdown table row (``\\|`` is a literal bar)."""
    return [c.strip().replace("\\|", "|")
            for c in re.split(r"(?<!\\)\|", row.strip())[1:-1]]


def documented_reasons(doc: Path = GAPS_DOC) -> dict[tuple[str, str, str], str]:
    """{(place, what, not shown): reason} from the gap table of docs/c_coverage.md."""
    text = doc.read_text() if doc.is_file() else ""
    if GAPS_BEGIN not in text:
        return {}
    block = text.split(GAPS_BEGIN, 1)[1].split(GAPS_END, 1)[0]
    rows = [_cells(r) for r in block.splitlines() if r.startswith("| `")]
    return {(c[0].strip("`"), c[1], c[2]): c[3] for c in rows if len(c) == 4}


def gaps_markdown(found: list[tuple[str, str, str]],
                  reasons: dict[tuple[str, str, str], str]) -> str:
    """The gap table, each row with its documented reason (or "reason to write")."""
    rows = ["| place | line, branch or condition | not shown | reason |", "|---|---|---|---|"]
    for g in found:
        cells = [f"`{g[0]}`", g[1], g[2], reasons.get(g, "*reason to write*")]
        rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join([GAPS_BEGIN, *rows, GAPS_END])


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gate", action="store_true", help="exit 1 below the recorded floor")
    ap.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (profiles, report)")
    ap.add_argument("--from", dest="reuse", metavar="DIR",
                    help="report on a measurement kept with --keep DIR (no build, no tests)")
    ap.add_argument("--gaps", action="store_true",
                    help="also list every uncovered line, branch direction and MC/DC condition "
                         "with its reason from docs/c_coverage.md; exit 1 if one has none")
    args = ap.parse_args(argv)
    try:
        tools()
    except NoClangError as exc:
        print(f"c_coverage: {exc}", file=sys.stderr)
        return 2
    if args.reuse:
        work = Path(args.reuse)
        table, found = summary(work), gaps(work) if args.gaps else []
    elif args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
        table = measure(work)
        found = gaps(work) if args.gaps else []
    else:
        with tempfile.TemporaryDirectory() as tmp:
            table = measure(Path(tmp))
            found = gaps(Path(tmp)) if args.gaps else []
    print(markdown(table))
    undocumented = 0
    if args.gaps:
        reasons = documented_reasons()
        undocumented = sum(g not in reasons for g in found)
        print()
        print(gaps_markdown(found, reasons))
        if undocumented:
            print(f"c_coverage: {undocumented} of {len(found)} gaps without a documented reason")
    tot = table["TOTAL"]
    low = {k: (round(pct(tot[k]), 2), f) for k, f in FLOOR.items() if pct(tot[k]) < f}
    if args.gate and low:
        print(f"c_coverage: below the floor {{measure: (percent, floor)}}: {low}")
        return 1
    return 1 if undocumented else 0


if __name__ == "__main__":
    sys.exit(main())
