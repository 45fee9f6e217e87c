"""`rhonn-bench deploy`: what a user deploying the controller alone meets (core-only install).

  rhonn-bench deploy [--venv DIR] [--keep] [--controller NAME] [--starts N] [--steps N]
                     [--no-cache] [--json FILE]

1. **Install**: a fresh venv (``python3 -m venv``) in a temp dir, ``pip install SRC`` of a
   clean copy of the source tree (tracked + untracked-not-ignored files: no ``build/``, no
   ``.venv``; core only, no extras, not editable). Reported: venv creation and pip wall
   time, the venv's size (``du``) and its site-packages, the 5 largest distributions (sum of
   their RECORD files), numba/llvmlite present (they must not be) and whether the C core
   (``controller.native._rhcore64``) imports. ``--venv DIR`` skips this and measures an
   existing venv (then "first start" is the first of this run, not the first after install).
   pip uses its cache unless ``--no-cache``.
2. **Start-up**: exec → the ``ready`` line of ``rhonn-controller`` of that venv on a local
   bus (``local:NAME``: Unix sockets only; its hub, ``python -m can_db.transport.hub`` of that
   venv, is
   started first and not timed): the first start, then ``--starts`` warm starts
   (median/min/max), and ``python -X importtime`` of ``controller.runtime.process``: top 5
   modules by cumulative time and top 5 top-level packages by self time.
3. **Memory**: RSS (psutil) of the controller after ``ready`` and after ``--steps`` MPC steps
   of the real process, driven in lockstep over the bus by the project's plant (run by
   this Python, so with the harness's own extras; constant-radius held at 50 km/h for
   steps × Ts simulated seconds); peak (sampled every 0.1 s and the controller's own
   samples) and final.

Exit codes: 0 measured, 1 the deployed controller failed (the reason in one line; what was
measured is still printed and written), 2 something the bench needs is missing. Timings are
this machine's at this moment; nothing here asserts a threshold.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import select
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from can_db.process.argcheck import OneLineParser, number
from controller.core.registry import CONTROLLER_NAMES, load_controller_config
from harness.bench.stats import write_json

REPO = Path(__file__).resolve().parents[2]
FORBIDDEN = ("numba", "llvmlite")
INSTALLER = ("pip", "setuptools", "wheel")  # what the venv brings itself (osqp needs setuptools)
PLANT_SCENARIO = "constant-radius"
PLANT_SPEED_KMH = 50.0  # ≈ 0.5 g on the 40 m circle: the stability function is active
READY_TIMEOUT_S = 60.0
NETWORK_WORDS = ("NewConnectionError", "DeployFailedError to establish a new connection",
                 "Temporary failure in name resolution", "Network is unreachable",
                 "No matching distribution found", "Could not find a version",
                 "ProxyError", "ConnectTimeoutError", "ReadTimeoutError")


class MissingError(Exception):
    """Something the bench needs is missing: one line, exit 2."""


class DeployFailedError(Exception):
    """The deployed controller failed: one line, exit 1."""


# ---------------------------------------------------------------- install and inspection

def source_files(src: Path) -> list[Path]:
    """Files of the source tree an install needs: git's tracked and untracked-not-ignored
    files that exist, else everything but build products and environments."""
    if (src / ".git").exists() and shutil.which("git"):
        out = subprocess.run(["git", "-C", str(src), "ls-files", "-z", "-co",
                              "--exclude-standard"], capture_output=True, check=False)
        if out.returncode == 0:
            return [Path(p.decode()) for p in out.stdout.split(b"\0")
                    if p and (src / p.decode()).is_file()]
    skip = {".git", ".venv", "build", "dist", "__pycache__", ".pytest_cache", ".ruff_cache",
            ".hypothesis", "runs", "out"}
    files = []
    for root, dirs, names in os.walk(src):
        dirs[:] = [d for d in dirs if d not in skip and not d.endswith(".egg-info")]
        files += [Path(root, n).relative_to(src) for n in names
                  if not n.endswith((".so", ".pyc", ".rrd"))]
    return files


def copy_source(src: Path, dest: Path) -> Path:
    """A clean copy of ``src`` (pip builds a local path in place: no stale ``build/``)."""
    for rel in source_files(src):
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / rel, dest / rel)
    return dest


def pip_failure_line(log: str) -> tuple[bool, str]:
    """(is it the package index being unreachable, the line to show) from pip's output."""
    lines = [ln.strip() for ln in log.splitlines() if ln.strip()]
    for word in NETWORK_WORDS:
        for ln in lines:
            if word in ln:
                return True, ("pip could not reach a package index (no network to PyPI or "
                              f"the configured index?): {ln[:200]}")
    errors = [ln for ln in lines if ln.startswith("ERROR") or "error:" in ln.lower()]
    return False, f"pip install failed: {(errors or lines or ['no output'])[-1][:200]}"


def make_venv(where: Path, src: Path, no_cache: bool) -> dict[str, Any]:
    """Create the venv and install ``src`` into it; the timings and pip's verdict."""
    venv = where / "venv"
    t0 = time.perf_counter()
    made = subprocess.run([sys.executable if not shutil.which("python3") else "python3",
                           "-m", "venv", str(venv)], capture_output=True, text=True)
    venv_s = time.perf_counter() - t0
    if made.returncode != 0 or not (venv / "bin" / "python").exists():
        raise MissingError("python3 -m venv failed (is python3-venv / ensurepip installed?): "
                      + ((made.stderr or made.stdout).strip().splitlines() or ["?"])[-1])
    copy = copy_source(src, where / "src")
    cmd = [str(venv / "bin" / "python"), "-m", "pip", "install", "--no-input",
           "--disable-pip-version-check", str(copy)] + (["--no-cache-dir"] if no_cache else [])
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    pip_s = time.perf_counter() - t0
    (where / "pip.log").write_text(res.stdout + res.stderr)
    if res.returncode != 0:
        network, line = pip_failure_line(res.stdout + res.stderr)
        raise MissingError(line) if network else DeployFailedError(line)
    return {"venv_create_s": round(venv_s, 2), "pip_install_s": round(pip_s, 2),
            "pip_cache": not no_cache, "pip_log": str(where / "pip.log"),
            "command": " ".join(cmd)}


def du_mb(path: Path) -> float:
    """Disk usage of a tree, MB (``du -sk``; st_blocks where there is no du)."""
    if shutil.which("du"):
        out = subprocess.run(["du", "-sk", str(path)], capture_output=True, text=True)
        if out.returncode == 0:
            return round(int(out.stdout.split()[0]) / 1024, 1)
    total = 0
    for root, _, names in os.walk(path):
        for n in names:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, n)).st_blocks * 512
    return round(total / 2**20, 1)


_INSPECT = r"""
import importlib, importlib.metadata as md, importlib.util, json, site, sys
from pathlib import Path
sizes = {}
for d in md.distributions():
    tot = 0
    for f in d.files or []:
        try:
            tot += Path(d.locate_file(f)).stat().st_size
        except OSError:
            pass
    sizes[d.metadata["Name"]] = tot
forbidden = {n: importlib.util.find_spec(n) is not None for n in sys.argv[1].split(",")}
core = {}
for mod in ("controller.native._rhcore64", "controller.native._rhcore32"):
    try:
        importlib.import_module(mod)
        core[mod] = "ok"
    except Exception as exc:
        core[mod] = f"{type(exc).__name__}: {exc}"
print(json.dumps({"sizes": sizes, "forbidden": forbidden, "core": core,
                  "site_packages": site.getsitepackages()}))
"""


def inspect_venv(venv: Path) -> dict[str, Any]:
    """Size, largest distributions, forbidden packages and the C core of ``venv``."""
    py = venv / "bin" / "python"
    out = subprocess.run([str(py), "-c", _INSPECT, ",".join(FORBIDDEN)],
                         capture_output=True, text=True, cwd=tempfile.gettempdir())
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["?"])[-1]
        raise DeployFailedError(f"cannot inspect {venv}: {last}")
    info = json.loads(out.stdout)
    site_dirs = [Path(p) for p in info["site_packages"] if Path(p).is_dir()]
    top = sorted(info["sizes"].items(), key=lambda kv: -kv[1])[:5]
    installer = sum(v for k, v in info["sizes"].items() if k.lower() in INSTALLER)
    return {"venv_mb": du_mb(venv),
            "site_packages_mb": round(sum(du_mb(p) for p in site_dirs), 1),
            "largest": [{"name": n, "mb": round(s / 1e6, 1)} for n, s in top],
            "distributions": len(info["sizes"]),
            "installer_mb": round(installer / 1e6, 1),
            "forbidden_present": info["forbidden"],
            "c_core": info["core"],
            "c_core_built": info["core"].get("controller.native._rhcore64") == "ok"}


# ---------------------------------------------------------------- the bus and the processes

def start_hub(python: Path, channel: str) -> subprocess.Popen[str]:
    """The local bus hub of ``channel`` with ``python`` (the project's own command), after
    its ready line."""
    proc = subprocess.Popen([str(python), "-m", "can_db.transport.hub", "--channel", channel],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tempfile.gettempdir())
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 20.0)
    line = proc.stdout.readline() if ready else ""
    if not line.startswith("ready"):
        err = stop(proc)
        raise MissingError(f"the local bus hub did not start ({python} -m can_db.transport.hub): "
                           f"{err or 'no ready line'}")
    return proc


def stop(proc: subprocess.Popen[str], timeout_s: float = 10.0) -> str:
    """SIGTERM (then SIGKILL) and reap; the last line of its stderr ("" if none)."""
    if proc.poll() is None:
        proc.terminate()
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    lines = (err or "").strip().splitlines()
    return lines[-1] if lines else ""


def start_controller(venv: Path, bus: str, controller: str,
                     extra: list[str] | None = None) -> tuple[subprocess.Popen[str], float]:
    """Exec ``rhonn-controller`` of ``venv`` and wait for its ready line: (process, s)."""
    exe = venv / "bin" / "rhonn-controller"
    t0 = time.perf_counter()
    proc = subprocess.Popen([str(exe), "--bus", bus, "--controller", controller,
                             *(extra or [])], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tempfile.gettempdir())
    assert proc.stdout is not None
    deadline = t0 + READY_TIMEOUT_S
    while True:
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.perf_counter()))
        line = proc.stdout.readline() if ready else ""
        if line.startswith("ready"):
            return proc, time.perf_counter() - t0
        if not ready or (line == "" and proc.poll() is not None):
            why = stop(proc) or f"no ready line within {READY_TIMEOUT_S:g} s"
            raise DeployFailedError(f"rhonn-controller of {venv} did not start: {why}")


def rss_mb(pid: int) -> float:
    return round(psutil.Process(pid).memory_info().rss / 2**20, 1)


def measure_starts(venv: Path, bus: str, controller: str, warm: int) -> dict[str, Any]:
    """The first start and ``warm`` more: exec → ready (s) and RSS after ready (MB)."""
    times, rss = [], []
    for _ in range(1 + warm):
        proc, t = start_controller(venv, bus, controller)
        rss.append(rss_mb(proc.pid))
        stop(proc)
        times.append(round(t, 3))
    out: dict[str, Any] = {"first_s": times[0], "first_rss_mb": rss[0], "warm_s": times[1:],
                           "rss_ready_mb": rss}
    if warm:
        out.update(warm_median_s=round(statistics.median(times[1:]), 3),
                   warm_min_s=min(times[1:]), warm_max_s=max(times[1:]))
    return out


def import_times(venv: Path, module: str = "controller.runtime.process") -> dict[str, Any]:
    """``python -X importtime -c 'import MODULE'`` in ``venv``: total, top 5 modules by
    cumulative time (the module itself excluded) and top 5 top-level packages by self time."""
    out = subprocess.run([str(venv / "bin" / "python"), "-X", "importtime", "-c",
                          f"import {module}"], capture_output=True, text=True,
                         cwd=tempfile.gettempdir())
    rows = []
    for ln in out.stderr.splitlines():
        if not ln.startswith("import time:") or "self [us]" in ln:
            continue
        self_us, cum_us, name = ln[len("import time:"):].split("|", 2)
        rows.append((name.strip(), int(self_us), int(cum_us)))
    if out.returncode != 0 or not rows:
        raise DeployFailedError(f"import {module} failed in {venv}: "
                     f"{(out.stderr.strip().splitlines() or ['?'])[-1]}")
    total = next((c for n, s, c in rows if n == module), max(c for _, _, c in rows))
    by_cum = sorted((r for r in rows if r[0] != module), key=lambda r: -r[2])[:5]
    pkgs: dict[str, int] = {}
    for name, self_us, _ in rows:
        pkgs[name.split(".")[0]] = pkgs.get(name.split(".")[0], 0) + self_us
    return {"total_ms": round(total / 1000, 1),
            "top_cumulative": [{"module": n, "cum_ms": round(c / 1000, 1)} for n, _, c in by_cum],
            "top_packages_self": [{"package": p, "self_ms": round(s / 1000, 1)} for p, s in
                                  sorted(pkgs.items(), key=lambda kv: -kv[1])[:5]],
            "modules": len(rows)}


def _ts_s() -> float:
    return float(load_controller_config(None).ts)


def measure_steps(venv: Path, bus: str, controller: str, steps: int,
                  work: Path) -> dict[str, Any]:
    """RSS of the deployed controller after ready and after ``steps`` MPC steps driven in
    lockstep by the plant (this Python's); the MPC steps are counted in its timing log."""
    duration = steps * _ts_s()
    timing, summary = work / "timing.csv", work / "summary.json"
    proc, _ = start_controller(venv, bus, controller,
                               ["--timing", str(timing), "--summary", str(summary)])
    ctl = psutil.Process(proc.pid)
    ready_mb, peak = rss_mb(proc.pid), ctl.memory_info().rss
    cmd = [sys.executable, "-m", "plant_sim.process", "--bus", bus, "--scenario", PLANT_SCENARIO,
           "--speed", f"{PLANT_SPEED_KMH:g}", "--param", "speed_ramp_kmhps=0",
           "--param", f"laps={max(2, int(duration * PLANT_SPEED_KMH / 3.6 / 250) + 2)}",
           "--param", f"duration_s={duration:g}", "--duration", f"{duration:g}",
           "--summary", str(work / "plant.json")]
    t0 = time.perf_counter()
    plant = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             cwd=tempfile.gettempdir())
    try:
        while plant.poll() is None:
            if proc.poll() is not None:
                raise DeployFailedError(f"rhonn-controller exited during the run: {stop(proc)}")
            peak = max(peak, ctl.memory_info().rss)
            time.sleep(0.1)
        wall = time.perf_counter() - t0
        final = ctl.memory_info().rss
        peak = max(peak, final)
    finally:
        plant_err = stop(plant)
        stop(proc)
    if plant.returncode != 0:
        raise DeployFailedError(f"the plant failed (exit {plant.returncode}): {plant_err}")
    with timing.open() as f:
        rows = list(csv.DictReader(f))
    mpc = sum(1 for r in rows if int(r["mpc_update"]) > 0)
    ctl_summary = json.loads(summary.read_text()) if summary.exists() else {}
    peak = max([peak, *(kb * 1024 for kb in ctl_summary.get("rss_samples_kb", []))])
    plant_summary = json.loads((work / "plant.json").read_text())
    return {"measured": "rhonn-controller process over the bus, lockstep with rhonn-plant",
            "scenario": f"{PLANT_SCENARIO} at {PLANT_SPEED_KMH:g} km/h held, "
                        f"{duration:g} s simulated",
            "backend": ctl_summary.get("backend"), "cycles": len(rows), "mpc_steps": mpc,
            "wall_s": round(wall, 1),
            "fallback_cycles": plant_summary.get("fallback_cycles"),
            "rss_ready_mb": ready_mb, "rss_final_mb": round(final / 2**20, 1),
            "rss_peak_mb": round(peak / 2**20, 1)}


# ---------------------------------------------------------------- report

def format_table(res: dict[str, Any]) -> str:
    """The compact table of a result (any part may be missing)."""
    lines = [f"rhonn-bench deploy: {res.get('controller', '?')} in {res.get('venv', '?')}"
             f"{' (fresh install)' if res.get('fresh') else ' (existing venv)'}"]
    def row(what: str, value: str) -> None:
        lines.append(f"  {what:<34}{value}")
    inst, size = res.get("install"), res.get("size")
    if inst:
        row("install wall (venv + pip)", f"{inst['venv_create_s']:.1f} s + "
            f"{inst['pip_install_s']:.1f} s (pip cache {'on' if inst['pip_cache'] else 'off'})")
    if size:
        row("venv size (du)", f"{size['venv_mb']:.1f} MB (site-packages "
            f"{size['site_packages_mb']:.1f} MB, {size['distributions']} distributions; "
            f"pip/setuptools/wheel {size['installer_mb']:.1f} MB of it)")
        row("largest distributions", ", ".join(f"{d['name']} {d['mb']:.1f}"
                                               for d in size["largest"]) + " MB")
        present = [n for n, p in size["forbidden_present"].items() if p]
        row("numba / llvmlite", "PRESENT: " + ", ".join(present) if present else "absent")
        row("C core (_rhcore64)", "built" if size["c_core_built"] else
            f"NOT built: {size['c_core'].get('controller.native._rhcore64')}")
    st = res.get("start")
    if st:
        row("first start → ready", f"{st['first_s']:.3f} s")
        if st.get("warm_s"):
            row(f"warm starts ({len(st['warm_s'])})", f"median {st['warm_median_s']:.3f} s, "
                f"min {st['warm_min_s']:.3f}, max {st['warm_max_s']:.3f}")
    imp = res.get("importtime")
    if imp:
        row("import controller.runtime.process", f"{imp['total_ms']:.0f} ms, "
            f"{imp['modules']} modules")
        row("  top by cumulative", ", ".join(f"{m['module']} {m['cum_ms']:.0f}"
                                             for m in imp["top_cumulative"]) + " ms")
        row("  top packages by self time", ", ".join(f"{p['package']} {p['self_ms']:.0f}"
                                                    for p in imp["top_packages_self"]) + " ms")
    mem = res.get("memory")
    if mem:
        row("RSS after ready", f"{mem['rss_ready_mb']:.1f} MB")
        row(f"RSS after {mem['mpc_steps']} MPC steps", f"final {mem['rss_final_mb']:.1f} MB, "
            f"peak {mem['rss_peak_mb']:.1f} MB ({mem['cycles']} cycles, "
            f"{mem['wall_s']:.0f} s wall, {mem['fallback_cycles']} fallback, "
            f"backend {mem['backend']})")
    if res.get("error"):
        row("FAILED", res["error"])
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench deploy", description=__doc__)
    parser.add_argument("--venv", default=None,
                        help="measure this existing venv (skip the install)")
    parser.add_argument("--keep", action="store_true", help="keep the temp venv")
    parser.add_argument("--source", default=str(REPO),
                        help="the source tree to install (default: this repository)")
    parser.add_argument("--controller", default="nmpc-rhonn", choices=CONTROLLER_NAMES,
                        metavar="NAME", help="controller to start: " + ", ".join(CONTROLLER_NAMES))
    parser.add_argument("--starts", type=number(int, lo=0), default=5,
                        help="warm starts after the first one")
    parser.add_argument("--steps", type=number(int, lo=1), default=10_000,
                        help="MPC steps before the last RSS reading")
    parser.add_argument("--no-cache", action="store_true", help="pip --no-cache-dir")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    args = parser.parse_args(argv)
    res: dict[str, Any] = {"controller": args.controller, "fresh": args.venv is None}
    tmp: Path | None = None
    hub: subprocess.Popen[str] | None = None
    code = 0
    try:
        if args.venv is None:
            src = Path(args.source)
            if not (src / "pyproject.toml").is_file():
                raise MissingError(f"--source {src}: no pyproject.toml there")
            tmp = Path(tempfile.mkdtemp(prefix="rhonn-deploy-"))
            venv = tmp / "venv"
            res["venv"] = str(venv)
            print(f"installing {src} (core only) into {venv} …", file=sys.stderr, flush=True)
            res["install"] = make_venv(tmp, src, args.no_cache)
        else:
            venv = Path(args.venv).resolve()
            res["venv"] = str(venv)
            if not (venv / "bin" / "python").exists():
                raise MissingError(f"--venv {venv}: not a venv (no bin/python)")
        if not (venv / "bin" / "rhonn-controller").exists():
            raise MissingError(f"{venv}: no bin/rhonn-controller (rhonn-tv is not installed there)")
        res["size"] = inspect_venv(venv)
        channel = f"rhonn-deploy-{os.getpid()}"
        hub = start_hub(venv / "bin" / "python", channel)
        bus = f"local:{channel}"
        res["bus"] = bus
        res["start"] = measure_starts(venv, bus, args.controller, args.starts)
        res["importtime"] = import_times(venv)
        with tempfile.TemporaryDirectory(prefix="rhonn-deploy-run-") as work:
            res["memory"] = measure_steps(venv, bus, args.controller, args.steps, Path(work))
    except MissingError as exc:
        print(f"rhonn-bench deploy: error: {exc}", file=sys.stderr)
        code = 2
    except DeployFailedError as exc:
        res["error"] = str(exc)
        code = 1
    finally:
        if hub is not None:
            stop(hub)
        if tmp is not None:
            if args.keep:
                res["kept"] = str(tmp)
                print(f"kept {tmp}", file=sys.stderr)
            else:
                shutil.rmtree(tmp, ignore_errors=True)
    if code != 2:
        print(format_table(res))
        write_json(args.json, res)
    return code
