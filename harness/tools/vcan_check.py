"""The SocketCAN check: the loop, its logs and its tools on a Linux ``vcan0``, compared with
the local bus (docs/vcan.md).

Three steps, all under one work directory (default ``runs/vcan-check``):

1. **host**: the local-bus reference on this machine: the main job (``dlc-paper`` with
   ``nmpc-rhonn``), a warm-bench pair (``lmpc``, ``nmpc-rhonn``, 2 s each) and the plant's
   frames of the main job's first ``SLICE_CYCLES`` cycles as ``plant_slice.blf``;
2. **vcan**: ``harness/tools/vcan_vm.sh`` with SocketCAN, either in a VM (Debian's stock
   kernel under QEMU through virtme-ng: ``vng --run KERNEL --disable-kvm``) or, with
   ``--here``, on this machine when ``vcan0`` is up;
3. **compare**: truth bytes, the bus log cycle by cycle, replay BIT-IDENTICAL, zero
   fallbacks and lockstep time-outs, candump and ``rhonn-bus dump`` captured every frame,
   the can.logger/can.player round trip and the lone controller's answers.

Exit codes: 0 every check passed, 1 a check failed, 3 SocketCAN could not be had (no
kernel, no QEMU, no virtme-ng, not root: one line says which).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path

import can

from can_db.codec import Codec, Decoded
from can_db.secoc_keys import load_keys
from can_db.transport.hub import LocalHub
from can_db.transport.server import vcan_available
from harness.run.bus_logger import PERIOD_S, PLANT_BURST
from harness.run.replay import replay_log

REPO = Path(__file__).resolve().parents[2]
VM_SCRIPT = Path(__file__).with_name("vcan_vm.sh")
SCENARIO, CONTROLLER, PAIR = "dlc-paper", "nmpc-rhonn", ("lmpc", "nmpc-rhonn")
PAIR_DURATION_S = 2.0  # simulated s of each run of the warm-bench pair
SLICE_CYCLES = 200  # cycles of plant frames fed to the lone controller (2 s simulated)
VM_CPUS, VM_MEMORY = 2, "3G"
VM_TIMEOUT_S = 1800.0  # the whole VM, wall s: a hung guest ends the check, failed
SKIPPED = 3  # exit code: SocketCAN could not be had
DIAG_MIN_ID = 0x700  # diagnostic frames (UDS) are not part of a run's log
#: frames the player sends: the plant's burst and SYNC with its authenticator
SLICE_NAMES = (*PLANT_BURST, "SYNC", "SYNC_AUTH")
#: the controller's frames that are bit-exact functions of its input (CTRL_STATUS carries
#: the measured compute time, and its authenticator's MAC covers it)
EXACT_ANSWERS = ("WHEEL_TORQUE_CMD", "WHEEL_TORQUE_AUTH")
RUN_OPTS = ["--no-plots", "--no-rrd", "--lockstep-wait-ms", "2000", "--bus-start-timeout",
            "120", "--secoc-keys", "ci-test-key"]


@dataclass
class Check:
    """One comparison's verdict and a line on what it saw."""

    name: str
    ok: bool
    detail: str


# ----------------------------------------------------------------------------- logs
def read_frames(path: Path) -> list[can.Message]:
    """Every frame of a bus log (BLF, ASC or MF4 through python-can; candump -L text)."""
    if path.suffix == ".log":
        return list(_candump_frames(path))
    with can.LogReader(str(path)) as log:
        return [m for m in log if isinstance(m, can.Message) and not m.is_error_frame]


def _candump_frames(path: Path):
    pattern = re.compile(r"^\((\d+\.\d+)\)\s+\S+\s+([0-9A-Fa-f]+)#([0-9A-Fa-f]*)")
    for line in path.read_text(errors="replace").splitlines():
        match = pattern.match(line)
        if match:
            yield can.Message(timestamp=float(match[1]), arbitration_id=int(match[2], 16),
                              data=bytes.fromhex(match[3]), is_extended_id=len(match[2]) > 3)


#: signals that carry a measured wall-clock time, never the same in two runs on any bus:
#: the controller's compute time, the CRC over it, and the authenticator's MAC (and CRC)
#: over that frame; the rest of these frames (mode, faults, QP status, echo, freshness,
#: alive counter) must be equal
MEASURED = {"CTRL_STATUS": ("COMPUTE_TIME", "CRC8"), "CTRL_STATUS_AUTH": ("MAC", "CRC8")}


def comparable(msg: can.Message, codec: Codec) -> str:
    """A frame's data as compared between two runs: the bytes, or for a frame with measured
    signals its other signals, decoded."""
    for name, skip in MEASURED.items():
        if msg.arbitration_id == codec.messages[name].frame_id:
            dec = codec.decode_message(msg)
            if not isinstance(dec, Decoded):  # a frame that fails its E2E check: as it is
                break
            alive = msg.data[1] & 0x0F  # ALIVE: bits 8-11 of both frames (the DBC)
            return name + repr((alive, sorted((k, v) for k, v in dec.values.items()
                                              if k not in skip)))
    return bytes(msg.data).hex()


def by_cycle(frames: list[can.Message], codec: Codec | None = None
             ) -> dict[int, list[tuple[int, int, str]]]:
    """Frames grouped by their 10 ms cycle from the log's first frame: per cycle, each
    frame's offset in µs, id and :func:`comparable` data (lockstep logs are stamped in
    simulated time)."""
    codec = codec or Codec()
    cycles: dict[int, list[tuple[int, int, str]]] = defaultdict(list)
    if not frames:
        return cycles
    t0 = frames[0].timestamp
    for m in frames:
        k = math.floor((m.timestamp - t0) / PERIOD_S + 1e-6)  # (1 µs: float rounding)
        cycles[k].append((round((m.timestamp - t0 - k * PERIOD_S) * 1e6), m.arbitration_id,
                          comparable(m, codec)))
    return cycles


def compare_logs(name: str, vm_log: Path, host_log: Path) -> Check:
    """The two lockstep bus logs are equal cycle by cycle: the same frames at the same
    stamps with the same data, measured times aside (:data:`MEASURED`)."""
    if not vm_log.exists() or not host_log.exists():
        return Check(name, False, f"missing {vm_log if not vm_log.exists() else host_log}")
    a, b = by_cycle(read_frames(vm_log)), by_cycle(read_frames(host_log))
    differ = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    frames = sum(len(v) for v in a.values())
    if differ:
        return Check(name, False, f"{len(differ)} of {len(set(a) | set(b))} cycles differ, "
                                  f"first cycle {differ[0]}")
    return Check(name, True, f"{len(a)} cycles, {frames} frames, the same cycle by cycle")


def compare_bytes(name: str, vm_file: Path, host_file: Path) -> Check:
    if not vm_file.exists() or not host_file.exists():
        return Check(name, False, f"missing {vm_file if not vm_file.exists() else host_file}")
    same = vm_file.read_bytes() == host_file.read_bytes()
    return Check(name, same, f"{vm_file.stat().st_size} bytes, "
                             f"{'identical' if same else 'DIFFERENT'}")


def run_health(name: str, run_dir: Path, bus_kind: str) -> Check:
    """Zero fallbacks, zero lockstep time-outs and (SocketCAN) zero frames dropped by any
    node's socket, counted for every node, on the bus asked for."""
    try:
        metrics = json.loads((run_dir / "metrics.json").read_text())
        plant = json.loads((run_dir / "plant_summary.json").read_text())
    except (OSError, ValueError) as exc:
        return Check(name, False, f"no metrics: {exc}")
    fallbacks = metrics.get("fallback_events")
    timeouts = plant.get("lockstep_timeouts")
    bus = str(metrics.get("bus", ""))
    ok = fallbacks == 0 and timeouts == 0 and bus == bus_kind
    detail = f"bus {bus}, fallback_events {fallbacks}, lockstep_timeouts {timeouts}"
    if bus_kind == "socketcan":
        socket_drops = (metrics.get("rx_drops") or {}).get("socket") or {}
        ok = ok and len(socket_drops) == 3 and not any(socket_drops.values())
        counted = ", ".join(f"{node} {n}" for node, n in socket_drops.items())
        detail += f", socket drops: {counted or 'not counted'}"
    return Check(name, ok, detail)


def capture_complete(name: str, capture: list[can.Message], log: list[can.Message]) -> Check:
    """Every frame of the run's log (diagnostics aside) is in the capture."""
    want = Counter((m.arbitration_id, bytes(m.data)) for m in log
                   if m.arbitration_id < DIAG_MIN_ID)
    got = Counter((m.arbitration_id, bytes(m.data)) for m in capture
                  if m.arbitration_id < DIAG_MIN_ID)
    missing = want - got
    return Check(name, not missing and sum(want.values()) > 0,
                 f"{sum(got.values())} frames captured, {sum(want.values())} in the log, "
                 f"{sum(missing.values())} missing")


def dump_complete(dump_txt: Path, log: list[can.Message], codec: Codec) -> Check:
    """``rhonn-bus dump`` printed every SYNC of the run (its rejection summary is shown, not
    judged: its receive-time checks see the emulator's pace, not the loop's)."""
    name = "rhonn-bus dump saw the run"
    if not dump_txt.exists():
        return Check(name, False, "no dump output")
    text = dump_txt.read_text(errors="replace")
    sync_id = codec.messages["SYNC"].frame_id
    syncs = sum(m.arbitration_id == sync_id for m in log)
    printed = len(re.findall(rf"^\S+ 0x{sync_id:03X} ", text, re.MULTILINE))
    summary = re.search(r"^frames: (\d+)\s+rejections: (.*)$", text, re.MULTILINE)
    return Check(name, printed == syncs > 0,
                 f"{printed} SYNC printed of {syncs}; {summary[0] if summary else 'no summary'}")


def round_trip(roundtrip: Path, plant_slice: Path, host_log: Path, codec: Codec) -> list[Check]:
    """can.player sent the slice, can.logger recorded it, the lone controller answered each
    SYNC with the torque frames of the local-bus run, bit for bit."""
    if not roundtrip.exists():
        return [Check("can.logger/can.player round trip", False, "no can.logger file")]
    got = read_frames(roundtrip)
    sent = read_frames(plant_slice)
    slice_ids = {m.arbitration_id for m in sent}
    echoed = [(m.arbitration_id, bytes(m.data)) for m in got if m.arbitration_id in slice_ids]
    want = [(m.arbitration_id, bytes(m.data)) for m in sent]
    checks = [Check("can.logger/can.player round trip", echoed == want,
                    f"{len(want)} frames played, {len(echoed)} logged, "
                    f"{'in order, identical' if echoed == want else 'DIFFERENT'}")]
    host = read_frames(host_log)
    for name in EXACT_ANSWERS:
        fid = codec.messages[name].frame_id
        mine = [bytes(m.data) for m in got if m.arbitration_id == fid]
        ref = [bytes(m.data) for m in host if m.arbitration_id == fid][:SLICE_CYCLES]
        same = mine == ref and len(ref) == SLICE_CYCLES
        checks.append(Check(f"lone controller {name}", same,
                            f"{len(mine)} answers, {len(ref)} in the local-bus run, "
                            f"{'bit-identical' if same else 'DIFFERENT'}"))
    return checks


def drops_counted(drops_json: Path) -> Check:
    """The flood step: the kernel's drop count for the reader's socket is every frame it
    did not get, and there were some (the flood outran its receive buffer)."""
    name = "drops under a flood counted on vcan0"
    try:
        d = json.loads(drops_json.read_text())
    except (OSError, ValueError) as exc:
        return Check(name, False, f"no result: {exc}")
    lost = d["sent"] - d["received"]
    ok = lost > 0 and d["rx_dropped"] == lost
    return Check(name, ok, f"{d['sent']} sent, {d['received']} read, rx_dropped "
                           f"{d['rx_dropped']} (lost {lost}), receive buffer "
                           f"{d['rcvbuf_bytes']} bytes")


def compare(work: Path) -> list[Check]:
    """Every comparison of the vcan outputs with the local-bus reference."""
    codec, host, vm = Codec(), work / "host", work / "vm"
    checks = []
    for label, rc_file in (("main job", vm / "main.rc"), ("pair", vm / "pair.rc")):
        rc = rc_file.read_text().strip() if rc_file.exists() else "missing"
        checks.append(Check(f"{label} exit code on vcan0", rc == "0", rc))
    checks.append(compare_bytes("main job truth.csv", vm / "main/truth.csv",
                                host / "main/truth.csv"))
    checks.append(compare_logs("main job bus log", vm / "main/bus.blf", host / "main/bus.blf"))
    checks.append(run_health("main job on socketcan:vcan0", vm / "main", "socketcan"))
    if (vm / "main/bus.blf").exists():
        result = replay_log(vm / "main/bus.blf", keys=load_keys("ci-test-key"))
        checks.append(Check("replay of the vcan0 log", result.bit_identical,
                            f"{'BIT-IDENTICAL' if result.bit_identical else 'DIFFERENT'}, "
                            f"{result.identical}/{result.recorded} torque frames"))
        log = read_frames(vm / "main/bus.blf")
        checks.append(capture_complete("candump -L captured the run",
                                       read_frames(vm / "candump.log")
                                       if (vm / "candump.log").exists() else [], log))
        checks.append(dump_complete(vm / "dump.txt", log, codec))
    for name in PAIR:
        checks.append(compare_bytes(f"pair {name} truth.csv", vm / "pair" / name / "truth.csv",
                                    host / "pair" / name / "truth.csv"))
        checks.append(compare_logs(f"pair {name} bus log", vm / "pair" / name / "bus.blf",
                                   host / "pair" / name / "bus.blf"))
        checks.append(run_health(f"pair {name} over --bus auto", vm / "pair" / name,
                                 "socketcan"))
    checks += round_trip(vm / "roundtrip.blf", host / "plant_slice.blf", host / "main/bus.blf",
                         codec)
    checks.append(drops_counted(vm / "drops.json"))
    return checks


# ----------------------------------------------------------------------------- host
def _harness(*args: str) -> None:
    cmd = [sys.executable, "-m", "harness.cli", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:2])} on the local bus failed: "
                           f"{(proc.stderr.strip().splitlines() or ['?'])[-1]}")


def write_plant_slice(host_log: Path, out: Path, codec: Codec) -> int:
    """The plant's frames of the first SLICE_CYCLES cycles of ``host_log`` into ``out``
    (stamps kept), for can.player; returns the frame count."""
    ids = {codec.messages[n].frame_id for n in SLICE_NAMES}
    sync_id = codec.messages["SYNC"].frame_id
    frames, syncs = [], 0
    for m in read_frames(host_log):
        if m.arbitration_id not in ids:
            continue
        if m.arbitration_id == sync_id:
            if syncs == SLICE_CYCLES:
                break
            syncs += 1
        frames.append(m)
    while frames and frames[-1].arbitration_id not in (sync_id,
                                                       codec.messages["SYNC_AUTH"].frame_id):
        frames.pop()  # the next cycle's burst without its SYNC
    with can.BLFWriter(str(out)) as writer:
        for m in frames:
            writer.on_message_received(m)
    return len(frames)


def host_reference(work: Path) -> None:
    """The local-bus runs and the player's slice (step 1)."""
    host = work / "host"
    shutil.rmtree(host, ignore_errors=True)
    host.mkdir(parents=True)
    with LocalHub() as hub:  # the local bus even where vcan0 is up (auto would pick it)
        _harness("run", SCENARIO, "--controller", CONTROLLER, "--bus", hub.spec,
                 "--out", str(host / "main"), *RUN_OPTS)
        _harness("compare", SCENARIO, "--controllers", ",".join(PAIR), "--bus", hub.spec,
                 "--duration", str(PAIR_DURATION_S), "--out", str(host / "pair"), *RUN_OPTS)
    write_plant_slice(host / "main/bus.blf", host / "plant_slice.blf", Codec())
    # matplotlib's font cache, built here once: the guest sees the same fonts and would
    # otherwise build it in every process, slowly
    subprocess.run([sys.executable, "-c", "import matplotlib.font_manager"], check=False,
                   env={**os.environ, "MPLCONFIGDIR": str(work / "mplconfig")})


# ----------------------------------------------------------------------------- vcan
def pick_kernel(rt: bool = False) -> Path | None:
    """Debian's newest stock (or PREEMPT_RT) kernel image in /boot, by its file name (not
    the /vmlinuz link, which the last installed image moves)."""
    images = [Path(p) for p in glob.glob("/boot/vmlinuz-*-amd64")]
    images = [p for p in images if ("-rt-" in p.name) == rt]
    if not images:
        return None

    def version(p: Path) -> list[int]:
        return [int(x) for x in re.findall(r"\d+", p.name)]

    return max(images, key=version)


def vm_unavailable(kernel: Path | None) -> str | None:
    """Why the VM cannot be booted here, or None."""
    if os.geteuid() != 0:
        return "not root (the guest's modprobe and ip need it, and the host's /boot image)"
    if kernel is None or not kernel.exists():
        return "no kernel image (apt-get install linux-image-amd64)"
    for tool, package in (("vng", "pip install virtme-ng"),
                          ("qemu-system-x86_64", "apt-get install qemu-system-x86"),
                          ("busybox", "apt-get install busybox-static")):
        if shutil.which(tool, path=_path()) is None:
            return f"no {tool} ({package})"
    return None


def _path() -> str:
    """PATH with this interpreter's bin directory first (vng calls virtme-run from there)."""
    return f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"


def boot_vm(work: Path, kernel: Path, kvm: bool = False) -> int:
    """Run the SocketCAN set in a VM with ``kernel`` (``kvm``: with the host's KVM, else
    QEMU's software emulation); its exit code."""
    cmd = ["vng", "--run", str(kernel), *([] if kvm else ["--disable-kvm"]), "--cpus",
           str(VM_CPUS), "--memory", VM_MEMORY, "--rwdir", str(work), "--exec",
           f"{VM_SCRIPT} {work}"]
    with open(work / "vm.log", "w") as out:
        # its own session: on a time-out the whole group goes (vng, virtme-run and QEMU)
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                                env={**os.environ, "PATH": _path()}, start_new_session=True)
        try:
            return proc.wait(timeout=VM_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            print(f"vcan check: the VM did not finish within {VM_TIMEOUT_S:g} s",
                  file=sys.stderr)
            return 124


def run_here(work: Path) -> int:
    """Run the SocketCAN set on this machine (vcan0 up already)."""
    with open(work / "vm.log", "w") as out:
        return subprocess.run([str(VM_SCRIPT), str(work)], stdout=out,
                              stderr=subprocess.STDOUT, check=False, cwd=REPO,
                              env={**os.environ, "VCAN_SETUP": "0"}).returncode


def step_times(work: Path) -> list[str]:
    """The VM script's steps with their wall durations."""
    path = work / "vm/steps.log"
    if not path.exists():
        return []
    rows = [line.split(" ", 1) for line in path.read_text().splitlines() if " " in line]
    return [f"{rows[i][1]}: {int(rows[i + 1][0]) - int(rows[i][0])} s"
            for i in range(len(rows) - 1)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rhonn-bench vcan", description=__doc__.split("\n")[0])
    parser.add_argument("--work", default="runs/vcan-check", metavar="DIR",
                        help="work directory (host/, vm/, vm.log, result.json)")
    parser.add_argument("--here", action="store_true",
                        help="run on this machine's vcan0 (up already) instead of a VM")
    parser.add_argument("--kernel", default=None, metavar="FILE",
                        help="kernel image for the VM (default: the newest "
                             "/boot/vmlinuz-*-amd64 that is not -rt-)")
    parser.add_argument("--rt", action="store_true",
                        help="boot the PREEMPT_RT image (/boot/vmlinuz-*-rt-amd64)")
    parser.add_argument("--kvm", action="store_true",
                        help="use the host's KVM (default: QEMU's software emulation, which "
                             "boots a stock kernel anywhere)")
    parser.add_argument("--compare-only", action="store_true",
                        help="only compare the outputs already in the work directory")
    parser.add_argument("--json", default=None, metavar="FILE", help="write the checks here")
    args = parser.parse_args(argv)
    work = Path(args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    if not args.compare_only:
        if args.here:
            if not vcan_available("vcan0"):
                print("vcan check skipped: vcan0 is not up (docs/vcan.md)")
                return SKIPPED
        else:
            kernel = Path(args.kernel) if args.kernel else pick_kernel(args.rt)
            why = vm_unavailable(kernel)
            if why:
                print(f"vcan check skipped: no VM: {why}")
                return SKIPPED
        started = time.monotonic()
        try:
            host_reference(work)
        except RuntimeError as exc:
            print(f"vcan check: {exc}", file=sys.stderr)
            return 1
        timings["host_s"] = time.monotonic() - started
        started = time.monotonic()
        code = (run_here(work) if args.here
                else boot_vm(work, kernel, args.kvm))  # type: ignore[arg-type]
        timings["vcan_s"] = time.monotonic() - started
        if code == SKIPPED and not (work / "vm/main.rc").exists():
            err = work / "vm/setup.err"
            why = err.read_text().strip() if err.exists() else "see vm.log"
            print(f"vcan check skipped: SocketCAN not set up in the guest ({why})")
            return SKIPPED
    checks = compare(work)
    for c in checks:
        print(f"{'ok  ' if c.ok else 'FAIL'} {c.name}: {c.detail}")
    for line in step_times(work):
        print(f"     step {line}")
    if timings:
        print("     wall: " + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in timings.items()))
    failed = [c.name for c in checks if not c.ok]
    print(f"vcan check: {len(checks) - len(failed)}/{len(checks)} passed"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"checks": [c.__dict__ for c in checks], "timings_s": timings,
             "steps": step_times(work)}, indent=2))
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
