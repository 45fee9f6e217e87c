"""Measure how long each process of a run takes to start, and where the time goes.

  python -m harness.tools.startup_profile [--repeat N] [--json FILE] [--only NAME ...]
                                          [--variant LABEL=DIR[,-MODULE...] ...]

For each process a run starts — the local bus hub, the controller (each controller, with
SecOC and the public CI test key), the plant (dlc-paper, SecOC) and the harness itself
(``rhonn-harness --help`` to exit, ``rhonn-harness run`` up to the moment it starts the bus)
— it starts the process ``N`` times (default 5) and reports the median and the maximum of:

* ``total``: wall time from ``Popen`` to the ``ready`` line on stdout (for the harness: to
  its exit, or to its ``starting the bus`` log line), s;
* ``imports``: the sum of the top-level import times that ``python -X importtime`` reports
  before that line, s (taken on a second start of the same process with ``-X importtime``:
  the tracing itself costs a few percent);
* ``setup``: ``total`` − ``imports``: interpreter start, argument checks, configuration,
  bus connection, key set-up, caches, s;
* ``self``: the process's own ``ready in X s`` log line (its age when it printed ready), s.

and the ten largest cumulative import costs (median over the starts) of each process.
Every process runs on a hub this tool starts on a fresh local channel (Unix sockets on this
machine only); controller and plant are stopped with SIGTERM right after their ready line.
Timings are wall clock and depend on the load of the machine: the table's header gives the
load average before and after. To compare two project trees (e.g. a cut against the commit
before it) under the same load, give each as a ``--variant``: their starts alternate.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can_db.transport.hub import LocalHub

CONTROLLERS = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
SECOC = ["--secoc", "--secoc-keys", "ci-test-key"]
# how long one start may take before it counts as failed, wall s (a first start after an
# install compiles the plant's kernel: minutes)
START_TIMEOUT_S = 300.0
# one -X importtime line: "import time:   self |   cumulative | <indent>name" (µs)
_IMPORTTIME = re.compile(r"^import time:\s+(\d+) \|\s+(\d+) \|( *)(\S.*)$")
_SELF_READY = re.compile(r"ready in ([0-9.]+) s")
# the console script (a Python file), run by this interpreter so -X importtime reaches it
_HARNESS = [sys.executable, str(Path(sys.executable).parent / "rhonn-harness")]


@dataclass
class Target:
    """One process to start: its command (after the interpreter) and when it counts as up."""

    name: str
    argv: Callable[[str, Path], list[str]]  # (bus spec, scratch dir) -> full command
    ready: str  # a stdout/stderr line containing this ends the measurement
    until_exit: bool = False  # the measurement ends when the process exits
    logs_ready_in: bool = False  # logs its own "ready in X s" after its ready line


@dataclass
class Sample:
    """One start: wall times in s, import costs in s per module."""

    total_s: float
    self_s: float | None = None
    imports_s: float | None = None
    modules: dict[str, float] = field(default_factory=dict)


def _python(*args: str) -> Callable[[str, Path], list[str]]:
    return lambda spec, tmp: [sys.executable, *(a.format(spec=spec, tmp=tmp) for a in args)]


def _hub_argv(spec: str, tmp: Path) -> list[str]:
    """A hub on a channel of its own (the tool's hub keeps serving the others)."""
    return [sys.executable, "-m", "can_db.transport.hub", "--channel",
            f"prof-{os.getpid()}-{time.monotonic_ns()}"]


def targets() -> list[Target]:
    """The processes of one run, in the order a run starts them."""
    out = [Target("hub", _hub_argv, "ready")]
    for name in CONTROLLERS:
        out.append(Target(f"controller {name}", _python(
            "-m", "controller.runtime.process", "--bus", "{spec}", "--controller", name,
            "--timing", "{tmp}/timing.csv", "--summary", "{tmp}/controller_summary.json",
            *SECOC), "ready", logs_ready_in=True))
    out.append(Target("plant dlc-paper", _python(
        "-m", "plant_sim.process", "--bus", "{spec}", "--scenario", "dlc-paper",
        "--trace", "{tmp}/truth.csv", "--summary", "{tmp}/plant_summary.json",
        "--secoc-state", "{tmp}/secoc_trip", *SECOC), "ready", logs_ready_in=True))
    out.append(Target("harness --help", lambda spec, tmp: [*_HARNESS, "--help"], "",
                      until_exit=True))
    out.append(Target("harness run (to bus start)", lambda spec, tmp: [
        *_HARNESS, "run", "dlc-paper", "--controller", "passive", "--bus", spec,
        "--out", str(tmp / "run"), "--no-plots", "--no-rrd"], "starting the bus"))
    return out


def _with_importtime(cmd: list[str]) -> list[str]:
    return [cmd[0], "-X", "importtime", *cmd[1:]]


def _blocking(cmd: list[str], blocked: list[str]) -> list[str]:
    """``cmd`` with ``blocked`` modules marked absent before anything is imported: what a
    process that does not import them at all would cost (``python -m M ARGS`` and
    ``python SCRIPT ARGS`` only)."""
    if not blocked:
        return cmd
    prelude = f"import runpy, sys; sys.modules.update(dict.fromkeys({blocked!r})); "
    if cmd[1] == "-m":
        run = f"runpy.run_module({cmd[2]!r}, run_name='__main__', alter_sys=True)"
        return [cmd[0], "-c", prelude + run, *cmd[3:]]
    run = f"runpy.run_path({cmd[1]!r}, run_name='__main__')"
    return [cmd[0], "-c", prelude + run, *cmd[2:]]


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5.0)
    if proc.stdout is not None:
        proc.stdout.close()


@dataclass(frozen=True)
class Variant:
    """What the processes run: the project tree first on ``PYTHONPATH`` (None: as
    installed) and modules marked absent (see :func:`_blocking`)."""

    label: str = ""
    pythonpath: str | None = None
    blocked: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Variant:
        """``LABEL=DIR[,-MODULE...]`` (DIR may be empty: the installed tree)."""
        label, sep, rest = text.partition("=")
        if not sep or not label:
            raise ValueError(f"bad variant {text!r}: use LABEL=DIR[,-MODULE...]")
        path, *mods = rest.split(",")
        if any(not m.startswith("-") or len(m) < 2 for m in mods):
            raise ValueError(f"bad variant {text!r}: modules are given as -MODULE")
        return cls(label, path or None, tuple(m[1:] for m in mods))


def start_once(target: Target, spec: str, tmp: Path, importtime: bool,
               variant: Variant = Variant()) -> Sample:
    """Start ``target`` once and measure it; raises RuntimeError if it never gets ready."""
    cmd = _blocking(target.argv(spec, tmp), list(variant.blocked))
    if importtime:
        cmd = _with_importtime(cmd)
    env = {**os.environ, "RHONN_LOG_LEVEL": "INFO", "PYTHONUNBUFFERED": "1"}
    if variant.pythonpath is not None:
        env["PYTHONPATH"] = variant.pythonpath
    # stderr into stdout: import-time lines, log lines and the ready line in their order;
    # unbuffered bytes split here (a buffered reader would hide lines from select)
    started = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, bufsize=0,
                            env=env, cwd=tmp)
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    lines: list[str] = []
    total: float | None = None
    pending = b""
    try:
        deadline = started + START_TIMEOUT_S
        after_ready: float | None = None  # until when to wait for the "ready in X s" line
        while time.monotonic() < min(deadline, after_ready or deadline):
            ready, _, _ = select.select([fd], [], [], 0.2)
            if not ready:
                continue
            chunk = os.read(fd, 65536)
            if not chunk:  # exited
                if target.until_exit:
                    proc.wait()
                    total = time.monotonic() - started
                break
            now = time.monotonic()
            *complete, pending = (pending + chunk).split(b"\n")
            for raw in complete:
                line = raw.decode(errors="replace")
                lines.append(line)
                if not target.until_exit and total is None and target.ready in line:
                    total = now - started
                    # a process's own "ready in X s" log line follows its ready line
                    after_ready = now + 2.0 if target.logs_ready_in else now
            if after_ready is not None and any(_SELF_READY.search(x) for x in lines[-3:]):
                break
    finally:
        _stop(proc)
    if total is None:
        tail = "\n".join(lines[-15:])
        raise RuntimeError(f"{target.name} did not get ready:\n{tail}")
    sample = Sample(total)
    for line in lines:
        match = _SELF_READY.search(line)
        if match and not line.startswith("import time:"):
            sample.self_s = float(match.group(1))
    if importtime:
        top = 0
        for line in lines:
            match = _IMPORTTIME.match(line)
            if match is None:
                continue
            cumulative_us, indent, name = int(match.group(2)), len(match.group(3)), match.group(4)
            if indent == 1:  # a top-level import of the process (one space after the bar)
                top += cumulative_us
            # the largest cumulative time a module shows in this start
            sample.modules[name] = max(sample.modules.get(name, 0.0), cumulative_us / 1e6)
        sample.imports_s = top / 1e6
    return sample


def profile(target: Target, spec: str, repeat: int, tmp_root: Path,
            variants: list[Variant]) -> list[dict[str, Any]]:
    """``repeat`` plain starts and ``repeat`` starts with ``-X importtime`` of each variant,
    taken in turn (start by start, so a change of the machine's load reaches every variant
    alike); one summary row per variant."""
    plain: dict[Variant, list[Sample]] = {v: [] for v in variants}
    traced: dict[Variant, list[Sample]] = {v: [] for v in variants}
    failures: dict[Variant, list[str]] = {v: [] for v in variants}
    for n in range(repeat):
        for variant in variants:
            for importtime, bucket in ((False, plain), (True, traced)):
                tmp = Path(tempfile.mkdtemp(prefix=f"start{n}-", dir=tmp_root))
                try:
                    bucket[variant].append(start_once(target, spec, tmp, importtime, variant))
                except RuntimeError as exc:  # counted and shown; the other processes go on
                    failures[variant].append(str(exc).splitlines()[-1])
    name = target.name
    return [_summary(f"{name} [{v.label}]" if v.label else name, plain[v], traced[v],
                     failures[v]) for v in variants]


def _summary(name: str, plain: list[Sample], traced: list[Sample],
             failures: list[str]) -> dict[str, Any]:
    """One row: median and max of each measure (s), the ten largest imports."""
    row: dict[str, Any] = {"process": name, "n": len(plain), "failed": len(failures),
                           "error": failures[-1] if failures else ""}
    if not plain or not traced:
        return {**row, "total_s": None, "imports_s": None, "setup_s": None,
                "self_ready_s": None, "top_imports_s": []}
    totals = [s.total_s for s in plain]
    imports = [s.imports_s or 0.0 for s in traced]
    # pairs of one plain and one traced start: the tracing's own cost is in neither column
    setups = [t - i for t, i in zip(totals, imports, strict=False)]
    selfs = [s.self_s for s in plain if s.self_s is not None]
    names = {module for s in traced for module in s.modules}
    costs = {module: statistics.median(s.modules.get(module, 0.0) for s in traced)
             for module in names}
    top = sorted(costs.items(), key=lambda kv: -kv[1])[:10]

    def stat(values: list[float]) -> dict[str, float] | None:
        return ({"median": statistics.median(values), "max": max(values)} if values else None)

    return {**row, "total_s": stat(totals), "imports_s": stat(imports),
            "setup_s": stat(setups), "self_ready_s": stat(selfs),
            "top_imports_s": [[module, round(cost, 4)] for module, cost in top]}


def _cell(stat: dict[str, float] | None) -> str:
    return "-" if stat is None else f"{stat['median']:6.3f} {stat['max']:6.3f}"


def table(rows: list[dict[str, Any]], load: tuple[str, str]) -> str:
    """The plain-text table: median and max per column, then the top imports per process."""
    head = (f"start-up profile (wall s; median max over N starts; load average "
            f"{load[0]} before, {load[1]} after)\n"
            f"{'process':44} {'N':>2}  {'total':>13}  {'imports':>13}  {'setup':>13}  "
            f"{'self ready':>13}")
    body = [f"{r['process']:44} {r['n']:>2}  {_cell(r['total_s']):>13}  "
            f"{_cell(r['imports_s']):>13}  {_cell(r['setup_s']):>13}  "
            f"{_cell(r['self_ready_s']):>13}" for r in rows]
    body += [f"{r['process']}: {r['failed']} start(s) failed: {r['error']}"
             for r in rows if r["failed"]]
    tops = []
    for r in rows:
        tops.append(f"\n{r['process']}: largest cumulative imports (median s)")
        tops += [f"  {cost:6.3f}  {name}" for name, cost in r["top_imports_s"]]
    return "\n".join([head, *body, *tops])


def _loadavg() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.tools.startup_profile",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5, help="starts per process (default 5)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--only", action="append", default=[],
                        help="profile only processes whose name contains this (repeatable)")
    parser.add_argument("--variant", action="append", default=[],
                        metavar="LABEL=DIR[,-MODULE...]",
                        help="profile the project tree DIR (first on PYTHONPATH; empty: as "
                        "installed), optionally with MODULE marked absent (what not importing "
                        "it would save); repeatable, the variants' starts taken in turn")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    try:
        variants = [Variant.parse(text) for text in args.variant] or [Variant()]
    except ValueError as exc:
        parser.error(str(exc))
    if len({v.label for v in variants}) != len(variants):
        parser.error("every --variant needs a label of its own")
    chosen = [t for t in targets() if not args.only or any(o in t.name for o in args.only)]
    load_before = _loadavg()
    rows = []
    with LocalHub() as hub, tempfile.TemporaryDirectory(prefix="startup-profile-") as root:
        for target in chosen:
            print(f"... {target.name}", file=sys.stderr, flush=True)
            rows += profile(target, hub.spec, args.repeat, Path(root), variants)
    load = (load_before, _loadavg())
    for v in variants:
        if v.label:
            absent = f", {', '.join(v.blocked)} marked absent" if v.blocked else ""
            print(f"[{v.label}]: {v.pythonpath or 'the installed tree'}{absent}")
    print(table(rows, load))
    if args.json is not None:
        args.json.write_text(json.dumps({"load_average": {"before": load[0], "after": load[1]},
                                         "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
