"""MISRA C:2012 check of the C core with cppcheck's MISRA add-on, against a recorded baseline.

cppcheck (Debian's ``cppcheck``) ships the add-on but not the rule texts, so the report names
rules by number only. The core (``src/``) is checked against ``misra_baseline.txt``: one line
``rule file count`` per (rule, file) pair the deviation list in docs/misra.md accepts. A
violation count above its baseline (or a pair not in it) is a new violation and fails the
check; a count below it is reported so that the baseline can be tightened with ``--update``.
OSQP's generated code is third-party: ``--osqp`` reports its counts per rule, kept apart and
never gated.

Standalone (no package import), like build_tools.py beside it:

    python controller/native/misra_check.py            # the gate (exit 1 on a new violation)
    python controller/native/misra_check.py --update   # rewrite the baseline from this run
    python controller/native/misra_check.py --osqp     # the generated OSQP code, per rule
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

NATIVE_DIR = Path(__file__).resolve().parent
SRC_DIR = NATIVE_DIR / "src"
BASELINE = NATIVE_DIR / "misra_baseline.txt"
_LINE = re.compile(r"^(?P<file>[^:]+):(?P<line>\d+):(?P<id>misra-c2012-[\d.]+)$")

Key = tuple[str, str]  # (rule "12.1", file name "mpc_qp.c")


class NoCppcheckError(RuntimeError):
    """cppcheck is not installed (the message says how to install it)."""


def cppcheck() -> str:
    """Path of cppcheck; NoCppcheckError when absent."""
    path = shutil.which("cppcheck")
    if path is None:
        raise NoCppcheckError("cppcheck not found (apt-get install -y cppcheck)")
    return path


def run_misra(sources: Sequence[Path], include_dirs: Sequence[Path],
              defines: Sequence[str] = ()) -> list[tuple[str, int, str]]:
    """[(file name, line, rule)] of every MISRA C:2012 violation cppcheck reports in
    ``sources`` (and the headers they include from ``include_dirs``)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [cppcheck(), "--quiet", "--std=c99", "--addon=misra", "--enable=style",
               f"--cppcheck-build-dir={tmp}", "--suppress=missingIncludeSystem",
               "--template={file}:{line}:{id}",
               *(f"-I{d}" for d in include_dirs), *(f"-D{d}" for d in defines),
               *map(str, sources)]
        res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"cppcheck failed ({res.returncode}): {res.stderr.strip()[-500:]}")
    out = []
    for line in res.stderr.splitlines():
        m = _LINE.match(line.strip())
        if m:
            out.append((Path(m["file"]).name, int(m["line"]), m["id"].rsplit("-", 1)[1]))
    return sorted(set(out))


def core_violations(src_dir: Path = SRC_DIR) -> list[tuple[str, int, str]]:
    """The core's violations (every ``*.c`` of ``src_dir``, double build)."""
    return run_misra(sorted(src_dir.glob("*.c")), [src_dir, src_dir.parent / "include"])


def count(violations: Sequence[tuple[str, int, str]]) -> Counter[Key]:
    """Violations per (rule, file)."""
    return Counter((rule, name) for name, _line, rule in violations)


def read_baseline(path: Path = BASELINE) -> Counter[Key]:
    """The accepted counts (``rule file count`` lines; ``#`` comments)."""
    base: Counter[Key] = Counter()
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            rule, name, n = line.split()
            base[(rule, name)] = int(n)
    return base


def write_baseline(counts: Counter[Key], path: Path = BASELINE) -> None:
    """Rewrite the baseline from ``counts``, sorted by rule then file."""
    def rule_key(k: Key) -> tuple[tuple[int, ...], str]:
        return tuple(int(p) for p in k[0].split(".")), k[1]
    lines = ["# MISRA C:2012 violations accepted in controller/native/src (rule file count);",
             "# the reasons per rule are in docs/misra.md. Regenerate with",
             "# python controller/native/misra_check.py --update"]
    lines += [f"{r} {f} {counts[(r, f)]}" for r, f in sorted(counts, key=rule_key)]
    path.write_text("\n".join(lines) + "\n")


def new_violations(counts: Counter[Key], base: Counter[Key]) -> dict[Key, tuple[int, int]]:
    """{(rule, file): (found, accepted)} wherever more were found than accepted."""
    return {k: (n, base.get(k, 0)) for k, n in sorted(counts.items()) if n > base.get(k, 0)}


def osqp_violations() -> Counter[str]:
    """Violations per rule in OSQP's generated code (every shape the install builds)."""
    sys.path.append(str(NATIVE_DIR))
    import osqp_gen
    with tempfile.TemporaryDirectory() as tmp:
        osqp_gen.generate(tmp)
        found = run_misra(osqp_gen.osqp_sources(tmp), osqp_gen.osqp_include_dirs(tmp))
    return Counter(rule for _name, _line, rule in found)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--update", action="store_true", help="rewrite the baseline from this run")
    ap.add_argument("--osqp", action="store_true",
                    help="report OSQP's generated code per rule (never gated)")
    args = ap.parse_args(argv)
    try:
        if args.osqp:
            per_rule = osqp_violations()
            for rule, n in sorted(per_rule.items(),
                                  key=lambda kv: tuple(int(p) for p in kv[0].split("."))):
                print(f"{rule} {n}")
            print(f"total {sum(per_rule.values())}")
            return 0
        found = core_violations()
    except NoCppcheckError as exc:
        print(f"misra_check: {exc}", file=sys.stderr)
        return 2
    counts = count(found)
    if args.update:
        write_baseline(counts)
        print(f"misra_check: baseline written: {sum(counts.values())} violations, "
              f"{len(counts)} (rule, file) pairs")
        return 0
    base = read_baseline()
    new = new_violations(counts, base)
    for (rule, name), (n, ok) in new.items():
        lines = [str(ln) for f, ln, r in found if (r, f) == (rule, name)]
        print(f"new MISRA C:2012 violation: rule {rule} in {name}: {n} found, {ok} accepted "
              f"(lines {', '.join(lines)})")
    fewer = [k for k in base if counts.get(k, 0) < base[k]]
    if fewer:
        print(f"misra_check: {len(fewer)} (rule, file) pairs below the baseline; "
              f"tighten it with --update")
    print(f"misra_check: {sum(counts.values())} violations, {len(new)} new")
    return 1 if new else 0


if __name__ == "__main__":
    sys.exit(main())
