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

Needs Debian's clang-19 and llvm-19 (apt-get install -y clang-19 llvm-19). Standalone (no
package import), like build_tools.py beside it.
"""

from __future__ import annotations

import argparse
import json
import os
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
                          "tests/test_qp_recovery.py")
# The gate: the level measured when it was set (docs/c_coverage.md), in percent of the core's
# lines, branches and MC/DC conditions; a drop below any fails.
FLOOR = {"lines": 99.0, "branches": 95.0, "mcdc": 95.0}


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
    src = repo / "controller" / "native" / "src"
    out = subprocess.run([t["cov"], "export", "-summary-only", f"-instr-profile={merged}",
                          *obj_args, "--", *map(str, sorted(src.glob("*.c")))],
                         check=True, capture_output=True, text=True).stdout
    data = json.loads(out)["data"][0]
    table: dict[str, dict[str, list[int]]] = {}
    for f in data["files"]:
        s = f["summary"]
        table[Path(f["filename"]).name] = {k: [s[k]["covered"], s[k]["count"]]
                                           for k in ("lines", "branches", "mcdc")}
    tot = {k: [sum(v[k][0] for v in table.values()), sum(v[k][1] for v in table.values())]
           for k in ("lines", "branches", "mcdc")}
    table["TOTAL"] = tot
    (work / "obj_args.json").write_text(json.dumps([str(merged), obj_args]))
    return table


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


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gate", action="store_true", help="exit 1 below the recorded floor")
    ap.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (profiles, report)")
    args = ap.parse_args(argv)
    try:
        tools()
    except NoClangError as exc:
        print(f"c_coverage: {exc}", file=sys.stderr)
        return 2
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
        table = measure(work)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            table = measure(Path(tmp))
    print(markdown(table))
    tot = table["TOTAL"]
    low = {k: (round(pct(tot[k]), 2), f) for k, f in FLOOR.items() if pct(tot[k]) < f}
    if args.gate and low:
        print(f"c_coverage: below the floor {{measure: (percent, floor)}}: {low}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
