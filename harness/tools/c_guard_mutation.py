"""Hand-picked mutants of the C core's guards, each rebuilt and run against the back-to-back
tests (the C core against the numpy reference).

    python -m harness.tools.c_guard_mutation --scratch /tmp/c-scratch [--out runs/c_guards.json]

``--scratch`` is a separate checkout of this project (``git worktree add --detach DIR``),
never this one: each mutant is written into its C source there, the core is rebuilt in place
(``setup.py -q build_ext --inplace``), the tests run from there, and the source is restored
from git before the next mutant. A mutant whose build produces no extension is "not built"
(a compile error: no verdict); a test run that skips any test does not count as a survivor
(the tests skip when the core is missing). Killed: a test fails or the run times out.

The guards (docs/safety/mutation.md, "C core"): the input finiteness check of
``controller.c`` (wheel speeds included), the QP data's finiteness and magnitude check in
``mpc_qp.c``, the solution's finiteness check, the clamp of the QP solution into the ΔM box,
the clamp of the fallback command and the rate window's non-finite previous ΔM.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TESTS = ("tests/test_native_core.py", "tests/test_qp_recovery.py")
SRC = "controller/native/src/"


@dataclass(frozen=True)
class CMutant:
    """One source edit: ``old`` (exactly once in ``path``) → ``new``."""

    name: str
    path: str
    old: str
    new: str
    what: str


MUTANTS = (
    CMutant("inputs-no-wheel-speeds", SRC + "controller.c",
            "  s = s + (in->wheel_speeds[0] + in->wheel_speeds[1] + in->wheel_speeds[2] +\n"
            "           in->wheel_speeds[3]);\n", "",
            "the input check ignores the wheel speeds (NaN wheel speeds pass)"),
    CMutant("inputs-wheel-usable-ignored", SRC + "controller.c",
            "  if (!in->wheel_speeds_usable) return 0;\n", "",
            "the input check ignores the wheel speeds' usable flag"),
    CMutant("step-valid-without-finite", SRC + "controller.c",
            "valid = in->sensors_valid && finite;", "valid = in->sensors_valid && (finite || 1);",
            "a step with non-finite inputs counts as valid"),
    CMutant("qp-P-check-removed", SRC + "mpc_qp.c",
            "      qp->Px[k++] = v;\n      if (!(RH_FABS(v) < lim)) ok = 0;\n",
            "      qp->Px[k++] = v;\n",
            "the QP's P entries are not checked (finite, below the magnitude limit)"),
    CMutant("qp-q-check-removed", SRC + "mpc_qp.c",
            "    if (!(RH_FABS(qp->q[a]) < lim)) ok = 0;\n", "",
            "the QP's q entries are not checked"),
    CMutant("qp-data-check-always-true", SRC + "mpc_qp.c",
            "if (!condense_build(qp)) {", "if (!condense_build(qp) && 0) {",
            "the QP data's finiteness check always passes"),
    CMutant("qp-solution-finite-always", SRC + "mpc_qp.c",
            "ok = RH_FINITE(sum);", "ok = RH_FINITE(sum) || 1;",
            "a non-finite QP solution is accepted"),
    CMutant("dm-box-clamp-removed", SRC + "mpc_qp.c",
            "      v = v > qp->lb[i] ? v : qp->lb[i];\n"
            "      qp->z[i] = v < qp->ub[i] ? v : qp->ub[i];\n",
            "      qp->z[i] = v;\n",
            "the QP solution is not clamped into the ΔM box"),
    CMutant("fallback-clamp-removed", SRC + "mpc_qp.c",
            "    d = d > dm_min ? d : dm_min;\n    d = d < dm_max ? d : dm_max;\n",
            "    (void)dm_min; (void)dm_max;\n",
            "the fallback's decayed command is not clamped into the ΔM box"),
    CMutant("rate-window-nonfinite-prev", SRC + "mpc_qp.c",
            "OSQPFloat p = RH_FINITE(dm_prev) ? (OSQPFloat)dm_prev / us : (OSQPFloat)0.0;",
            "OSQPFloat p = (OSQPFloat)dm_prev / us;",
            "a non-finite previous ΔM enters the rate window"),
)


@dataclass
class Outcome:
    """One mutant's verdict."""

    name: str
    what: str
    verdict: str          # killed, survived, not built, skipped tests, timeout
    build_s: float
    test_s: float
    first_failure: str


def _run(cmd: list[str], cwd: Path, timeout: float | None = None
         ) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONPATH": str(cwd),
                               "PYTHONDONTWRITEBYTECODE": "1"})


def run_mutant(m: CMutant, scratch: Path, test_timeout: float) -> Outcome:
    """Apply ``m`` in ``scratch``, rebuild, run the tests, restore the source."""
    src = scratch / m.path
    text = src.read_text()
    if text.count(m.old) != 1:
        raise SystemExit(f"{m.name}: the original text occurs {text.count(m.old)} times in "
                         f"{m.path}")
    sos = list((scratch / "controller" / "native").glob("_rhcore*.so"))
    for so in sos:
        so.unlink()
    src.write_text(text.replace(m.old, m.new))
    try:
        t0 = time.monotonic()
        _run([sys.executable, "setup.py", "-q", "build_ext", "--inplace"], scratch)
        build_s = time.monotonic() - t0
        built = sorted(p.name for p in (scratch / "controller" / "native").glob("_rhcore*.so"))
        if len(built) != 2:
            return Outcome(m.name, m.what, "not built", build_s, 0.0, "")
        t0 = time.monotonic()
        try:
            res = _run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                        "-o", "addopts=", "-rfs", *TESTS], scratch, timeout=test_timeout)
        except subprocess.TimeoutExpired:
            return Outcome(m.name, m.what, "killed (timeout)", build_s,
                           time.monotonic() - t0, "")
        test_s = time.monotonic() - t0
        failed = re.findall(r"^FAILED (\S+)", res.stdout, re.M)
        if res.returncode != 0:
            return Outcome(m.name, m.what, "killed", build_s, test_s,
                           failed[0] if failed else res.stdout.strip().splitlines()[-1])
        if re.search(r"\d+ skipped", res.stdout):
            return Outcome(m.name, m.what, "skipped tests", build_s, test_s, "")
        return Outcome(m.name, m.what, "survived", build_s, test_s, "")
    finally:
        src.write_text(text)


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog="python -m harness.tools.c_guard_mutation",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scratch", type=Path, required=True,
                    help="a separate checkout (git worktree) where the mutants are built")
    ap.add_argument("--out", type=Path, default=None, help="results as JSON")
    ap.add_argument("--only", nargs="+", choices=[m.name for m in MUTANTS], default=None)
    ap.add_argument("--test-timeout", type=float, default=900.0, help="s per mutant")
    args = ap.parse_args(argv)
    scratch = args.scratch.resolve()
    if scratch == ROOT or not (scratch / "setup.py").is_file():
        print("--scratch: a separate checkout of the project, not this one", file=sys.stderr)
        return 2
    dirty = _run(["git", "status", "--porcelain", "--", SRC], scratch).stdout.strip()
    if dirty:
        print(f"--scratch: its C sources are modified:\n{dirty}", file=sys.stderr)
        return 2
    results = []
    for m in MUTANTS:
        if args.only and m.name not in args.only:
            continue
        o = run_mutant(m, scratch, args.test_timeout)
        results.append(o)
        print(f"{o.name}: {o.verdict} (build {o.build_s:.0f} s, tests {o.test_s:.0f} s) "
              f"{o.first_failure}", flush=True)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps([asdict(r) for r in results], indent=1) + "\n")
    killed = sum(o.verdict.startswith("killed") for o in results)
    judged = sum(o.verdict in ("survived",) or o.verdict.startswith("killed") for o in results)
    print(f"{killed}/{judged} killed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
