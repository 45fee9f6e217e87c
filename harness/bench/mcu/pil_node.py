"""The controller node as Cortex-M4F firmware on QEMU, on the run's bus (processor in the loop).

``python -m harness.bench.mcu.pil_node --bus SPEC --controller NAME [--config TOML]`` is what
``rhonn-harness run ... --target m4f`` starts in place of the Python controller process
(harness/run/hil_bench.py starts it by module name): it builds the firmware for the
controller's configuration (:func:`build_pil_node`, cached by the hash of everything that
goes into it), boots it on QEMU's MPS2 AN386 with the instruction-count plugin
(harness/run/pil_link.py ``PilLink``), bridges it to the bus (``PilBridge``), prints its
``ready`` line and runs until SIGTERM/SIGINT. Then it stops QEMU and writes the summary JSON
(``--summary``): instructions per answered cycle from the plugin's log (p50 / p99 / max, and
the time they take at 168 MHz if every instruction took one cycle), the stack's high-water
mark, flash and RAM from the link map, the bridge's frame counts.

Firmware: controller/native/mcu/pil/pil_node.c (the frame layer and node logic of
controller/native/node/, the core of controller/native/src/ in float, OSQP generated for the
configuration's one QP shape). The controller runs as configured with ``[mpc] precision =
"float32"`` and ``[rhonn.ekf] form = "ud"`` (what the float build needs; the same file runs
the host's float32 C core, :func:`float32_config`). Lockstep only; no UDS. SecOC
(``--secoc``) with the public CI test keys compiled in, or off (the plant with --no-secoc).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from can_db.codec import Codec
from can_db.process.stopflag import StopFlag
from can_db.secoc_keys import TEST_KEY_SOURCE, ci_test_keys
from controller.core.registry import load_controller_config
from controller.native import osqp_gen
from controller.native.build_tools import NATIVE_DIR, SRC_DIR
from controller.native.config import ctrl_config
from controller.native.node import dbc_gen
from controller.runtime.node import CONTROLLER_IDS
from harness.bench.mcu.build import (
    CORE_FLAGS,
    HARNESS_FLAGS,
    LIB_FLAGS,
    linked_sizes,
)
from harness.bench.mcu.case import MCU_DIR, McuError, c_initializer
from harness.bench.mcu.cases import qp_shape
from harness.bench.mcu.pil import PIL_DIR, PIL_SOURCES, boot_with_plugin, build_pil_firmware
from harness.bench.mcu.toolchain import ARCH_FLAGS, missing_tools, tool_versions
from harness.run.pil_link import PilBridge, PilLink, PilLinkError

NODE_DIR = NATIVE_DIR / "node"
NODE_MAIN = PIL_DIR / "pil_node.c"
# object folders of a build (build_pil_firmware's groups): the PIL link, the core, OSQP,
# the node logic, the frame layer, the firmware main with start-up and semihosting
FIRMWARE_GROUPS = ("pil", "core", "lib", "node_logic", "frame_layer", "harness")
LOGIC_MODULES = ("node_monitor", "node_plaus", "node_envelope", "node_fault", "node_logic")
COMM_PERIOD_S = 0.01  # the bus's communication cycle, s (rh_node_logic_default_config)
CLOCK_HZ = 168e6  # the target part's core clock, Hz (an STM32F4-class Cortex-M4F)
N_BASELINE = 4  # empty marker pairs at the firmware's start (pil_node.c)
START_TIMEOUT_S = 60.0  # wall s for QEMU to boot the firmware and answer V
CACHE_ENV = "RHONN_PIL_CACHE"  # where built firmware is kept (default ~/.cache/rhonn-tv/pil)
OSQP_PRECISIONS = ("double", "float")
# SecOC receiver memory of the firmware (node_secoc.h), sized for the lockstep bus schedule:
# accepted freshness values remembered per stream: the plant sends each secured message once
# per 10 ms cycle, so 16 (more than the forward window, RH_NODE_SECOC_MAX_AGE_CYCLES + 1 = 11
# cycles) names every replay from inside the window "replay"; an older one is
# "stale_freshness" (rejected either way, FV not above the last accepted)
SECOC_HISTORY = 16
# unverified data frames pending per stream: every data frame one held stream can carry
# (pil_node.c PIL_NODE_SEC_HELD, checked there at compile time), so the hold alone bounds
# what a burst keeps, as HELD does in can_db/secoc.py
SECOC_PENDING = 12


def cache_root() -> Path:
    """``$RHONN_PIL_CACHE``, else ``$XDG_CACHE_HOME/rhonn-tv/pil`` (``~/.cache`` without)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rhonn-tv" / "pil"


def float32_config(config: str | Path | None, out: Path) -> Path:
    """A controller TOML in ``out`` that extends ``config`` (None: the packaged default) with
    ``[mpc] precision = "float32"`` and ``[rhonn.ekf] form = "ud"``: what the firmware runs,
    and the file to run the host's float32 C core with for a comparison."""
    out.mkdir(parents=True, exist_ok=True)
    base = "default" if config is None else str(config)
    if Path(base).is_file():
        base = str(Path(base).absolute())
    path = out / "pil_controller.toml"
    path.write_text(
        f'extends = {json.dumps(base)}\n\n[mpc]\nprecision = "float32"\n\n'
        '[rhonn.ekf]\nform = "ud"\n'
    )
    return path


@dataclass
class PilNodeFirmware:
    """A built firmware: the ELF, its link map, the build folder, the key it is cached by."""

    elf: Path
    map_file: Path
    out: Path
    key: str
    controller: str
    mpc_every: int
    osqp: str
    defines: tuple[str, ...]
    secoc: bool = False


def _c_bytes(key: bytes) -> str:
    return "{" + ", ".join(f"0x{b:02X}u" for b in key) + "}"


def _config_header(
    name: str, config_file: Path, secoc: bool
) -> tuple[str, int, list[str], tuple[int, int]]:
    """(pil_node_config.h text, mpc_every, defines, QP shape) of controller ``name``; with
    ``secoc`` the public CI test keys (the only ones this build writes into an image)."""
    cfg = load_controller_config(config_file)
    mpc_every = max(1, round(cfg.ts / COMM_PERIOD_S))
    n, shape = qp_shape(cfg, name)
    diag = Codec().diagnostic["DIAG_REQ_CTRL"]
    text = (
        "/* generated by harness/bench/mcu/pil_node.py */\n"
        "#ifndef PIL_NODE_CONFIG_H\n#define PIL_NODE_CONFIG_H\n"
        '#include "rhonn_core.h"\n'
        f"static const rh_ctrl_config_t MCU_CONFIG = {c_initializer(ctrl_config(name, cfg))};\n"
        f"#define PIL_NODE_MPC_EVERY {mpc_every}\n"
        f"#define PIL_NODE_CONTROLLER_ID {CONTROLLER_IDS.get(name, 15)}\n"
        f"#define PIL_NODE_DIAG_REQ_ID 0x{diag:03X}u\n"
    )
    # state sized for this configuration: its horizon, and no ΔM-effectiveness filter when
    # it is off (rhonn_model.h RH_DM_GAIN)
    defines = [f"RH_N_MAX={n}"]
    if name != "nmpc-rhonn" or cfg.rhonn.dm_gain_p0 == 0.0:
        defines.append("RH_DM_GAIN=0")
    if secoc:
        keys = ci_test_keys()
        text += (
            f"#define PIL_NODE_KEY_PLANT_TO_CTRL {_c_bytes(keys.plant_to_ctrl)}\n"
            f"#define PIL_NODE_KEY_CTRL_TO_PLANT {_c_bytes(keys.ctrl_to_plant)}\n"
        )
        defines += [
            "PIL_NODE_SECOC",
            f"RH_NODE_SECOC_HISTORY={SECOC_HISTORY}u",
            f"RH_NODE_SECOC_PENDING={SECOC_PENDING}u",
        ]
    return text + "#endif\n", mpc_every, defines, (n, shape)


def build_pil_node(
    name: str = "nmpc-rhonn",
    config: str | Path | None = None,
    osqp: str = "float",
    opt: str = "Os",
    cache: Path | None = None,
    secoc: bool = False,
) -> PilNodeFirmware:
    """The PIL node firmware for controller ``name`` with ``config`` (run in float32 with the
    UD EKF, :func:`float32_config`), OSQP in ``osqp`` precision ("float": the FPU's, the
    default; "double": software floating point, the precision the host's cores solve in),
    built at -<opt>.
    Cached in ``cache`` (default :func:`cache_root`) under the SHA-256 of every source,
    generated file, flag and tool version that goes into it: a second call with the same
    inputs only checks. ``secoc``: the node verifies the plant's frames and authenticates
    its own with the public CI test keys (can_db/secoc_keys.py; a key of one's own would be
    written into the image and the cache: not done). Raises McuError (no toolchain, a
    failed build)."""
    why = missing_tools()
    if why is not None:
        raise McuError(why)
    if osqp not in OSQP_PRECISIONS:
        raise McuError(f"osqp must be one of {', '.join(OSQP_PRECISIONS)}, not {osqp!r}")
    if name not in CONTROLLER_IDS or name == "passive":
        mpc = ", ".join(sorted(set(CONTROLLER_IDS) - {"passive"}))
        raise McuError(f"the PIL node runs an MPC controller ({mpc}), not {name!r}")
    root = cache or cache_root()
    stage = root / f"stage-{os.getpid()}"
    cfg_file = float32_config(config, stage)
    header, mpc_every, defines, shape = _config_header(name, cfg_file, secoc)
    if osqp == "float":
        defines.append("OSQP_USE_FLOAT")
    gen = osqp_gen.generate(stage / "osqp", [shape])
    frame_layer = dbc_gen.frame_layer_sources(stage / "dbc")
    (stage / "pil_node_config.h").write_text(header)
    core = sorted(SRC_DIR.glob("*.c"))
    logic = [NODE_DIR / f"{m}.c" for m in LOGIC_MODULES]
    lib = osqp_gen.osqp_sources(gen)
    lib_flags = ["-fsingle-precision-constant"] if osqp == "float" else []
    hashed = sorted(
        {
            *core,
            *SRC_DIR.glob("*.h"),
            *(NATIVE_DIR / "include").glob("*.h"),
            *NODE_DIR.glob("*.[ch]"),
            *(stage / "dbc").glob("*.[ch]"),
            *(PIL_DIR / s for s in PIL_SOURCES),
            *PIL_DIR.glob("*.h"),
            NODE_MAIN,
            *(MCU_DIR / f for f in ("startup.c", "semihost.c", "semihost.h", "mps2_an386.ld")),
            *lib,
            *gen.glob("*.h"),
            *gen.glob("inc/*/*.h"),
            stage / "pil_node_config.h",
        }
    )
    h = hashlib.sha256()
    for path in hashed:
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    h.update(
        json.dumps(
            [
                CORE_FLAGS,
                HARNESS_FLAGS,
                LIB_FLAGS,
                ARCH_FLAGS,
                opt,
                defines,
                lib_flags,
                FIRMWARE_GROUPS,
                tool_versions(),
            ]
        ).encode()
    )
    key = h.hexdigest()[:16]
    out = root / key
    fw = PilNodeFirmware(
        out / "pil.elf", out / "pil.map", out, key, name, mpc_every, osqp, tuple(defines), secoc
    )
    if (out / "done").is_file() and fw.elf.is_file():
        _remove_tree(stage)
        return fw
    build_dir = root / f"build-{key}-{os.getpid()}"
    build_pil_firmware(
        build_dir,
        main=NODE_MAIN,
        opt=opt,
        insn_marks=False,
        source_groups={"core": core, "node_logic": logic, "frame_layer": frame_layer},
        include_dirs=[SRC_DIR, NATIVE_DIR / "include", NODE_DIR, stage / "dbc", stage],
        system_include_dirs=osqp_gen.osqp_include_dirs(gen),
        defines=defines,
        lib_sources=lib,
        lib_flags=lib_flags,
    )
    (build_dir / "pil_controller.toml").write_text(cfg_file.read_text())
    (build_dir / "done").write_text(f"{key}\n{build_dir}\n")
    if out.exists():  # a build another process finished meanwhile: keep that one
        _remove_tree(build_dir)
    else:
        build_dir.rename(out)
    _remove_tree(stage)
    return fw


def _remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def cycle_instructions(marks: list[int], n_baseline: int = N_BASELINE) -> list[int]:
    """Instructions per SYNC handled, from the plugin's marker counts: the firmware's
    ``n_baseline`` empty pairs first (the marker's own cost), then one pair per SYNC; a pair
    cut by the stop (an odd count) is left out."""
    if len(marks) < 2 * n_baseline:
        raise McuError(f"{len(marks)} marker counts: the firmware's baseline is missing")
    base = {marks[2 * i + 1] - marks[2 * i] for i in range(n_baseline)}
    if len(base) != 1:
        raise McuError(f"marker baseline not constant: {sorted(base)}")
    b = base.pop()
    return [marks[i + 1] - marks[i] - b for i in range(2 * n_baseline, len(marks) - 1, 2)]


def percentile(values: list[int], q: float) -> float:
    """The ``q`` quantile (0..1) of ``values``, linear between order statistics (numpy's
    default)."""
    s = sorted(values)
    pos = q * (len(s) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


def instruction_stats(per_cycle: list[int]) -> dict[str, Any]:
    """p50 / p99 / max instructions per cycle and their time at CLOCK_HZ, one instruction a
    cycle (QEMU counts instructions, not cycles: a lower-bound estimate of the time)."""
    if not per_cycle:
        return {"cycles": 0}
    p50, p99, mx = (statistics.median(per_cycle), percentile(per_cycle, 0.99), max(per_cycle))
    us = 1e6 / CLOCK_HZ
    return {
        "cycles": len(per_cycle),
        "insns_p50": p50,
        "insns_p99": p99,
        "insns_max": mx,
        "insns_min": min(per_cycle),
        "clock_hz": CLOCK_HZ,
        "us_at_clock_p50": p50 * us,
        "us_at_clock_p99": p99 * us,
        "us_at_clock_max": mx * us,
    }


def memory_figures(fw: PilNodeFirmware) -> dict[str, int]:
    """Flash (text + rodata + .data's load image) and static RAM (data + bss) of the whole
    firmware, from the link map (the stack, 64 KB reserved, apart), and flash per group
    (FIRMWARE_GROUPS, "lib" = OSQP, and newlib / libgcc)."""
    built = Path((fw.out / "done").read_text().split()[1])  # the objects' folder at the link
    groups = linked_sizes(fw.map_file, {g: built / g for g in FIRMWARE_GROUPS})
    flash = sum(g["text"] + g["rodata"] + g["data"] for g in groups.values())
    ram = sum(g["data"] + g["bss"] for g in groups.values())
    return {
        "flash_bytes": flash,
        "ram_static_bytes": ram,
        **{f"flash_{k}_bytes": g["text"] + g["rodata"] + g["data"] for k, g in groups.items()},
    }


def stack_high_water(guest_text: str) -> int | None:
    """The largest stack high-water mark the firmware reported (``H <bytes>`` lines), bytes."""
    marks = [int(ln.split()[1]) for ln in guest_text.splitlines() if ln.startswith("H ")]
    return max(marks) if marks else None


def boot(
    fw: PilNodeFirmware, work_dir: Path, start_timeout_s: float = START_TIMEOUT_S
) -> tuple[PilLink, Path]:
    """QEMU running ``fw`` with the instruction-count plugin, the link started; (link, the
    plugin's log). Tries the plugin API versions 1..5 as the QEMU at hand wants."""
    link, log, _api = boot_with_plugin(fw.elf, fw.out, work_dir, start_timeout_s)
    return link, log


SECOC_VERDICTS = (
    "accepted",
    "bad_mac",
    "stale_freshness",
    "replay",
    "unauthenticated",
    "orphan_auth",
    "unchecked_auth",
)  # the order of rh_node_secoc_verdict_t (node_secoc.h): the firmware's "R" lines


def secoc_summary(guest_text: str, enabled: bool) -> dict[str, Any]:
    """The firmware's SecOC counts (its last ``R`` line), as the controller's summary has
    them: accepted frames and the rejections by reason (non-zero only)."""
    if not enabled:
        return {"enabled": False}
    last = [ln.split()[1:] for ln in guest_text.splitlines() if ln.startswith("R ")]
    counts = dict(zip(SECOC_VERDICTS, map(int, last[-1]), strict=True)) if last else {}
    return {
        "enabled": True,
        "keys": TEST_KEY_SOURCE,
        "accepted": {"all secured frames": counts.get("accepted", 0)},
        "rejected": {k: v for k, v in counts.items() if k != "accepted" and v},
    }


def cycle_kinds(guest_text: str) -> list[tuple[bool, bool]]:
    """(answered, full controller step) per SYNC the firmware handled, in order (its ``C``
    lines)."""
    return [
        (p[1] == "1", p[2] == "1")
        for p in (ln.split() for ln in guest_text.splitlines() if ln.startswith("C "))
    ]


def summary(
    fw: PilNodeFirmware, link: PilLink, bridge: PilBridge | None, log: Path, stop_reason: str
) -> dict[str, Any]:
    """The run's figures of the firmware (after QEMU stopped): see the module docstring.
    Instructions per answered cycle, all of them and split into the cycles that ran the
    full controller step and those that re-allocated the held yaw moment."""
    guest = link.guest_log.read_text(errors="replace") if link.guest_log.exists() else ""
    marks = (
        [int(ln.split()[1]) for ln in log.read_text().splitlines() if ln.startswith("M ")]
        if log.exists()
        else []
    )
    kinds = cycle_kinds(guest)
    insns: dict[str, Any]
    try:
        per = cycle_instructions(marks)
        n = min(len(per), len(kinds))  # a SYNC cut by the stop has one and not the other
        answered = [(i, full) for i, (ok, full) in zip(per[:n], kinds[:n], strict=True) if ok]
        insns = {
            **instruction_stats([i for i, _ in answered]),
            "full_step": instruction_stats([i for i, f in answered if f]),
            "allocate_only": instruction_stats([i for i, f in answered if not f]),
        }
    except McuError as exc:
        insns = {"error": str(exc)}
    return {
        "controller": fw.controller,
        "backend": "m4f",
        "target": "m4f",
        "firmware": {
            "elf": str(fw.elf),
            "key": fw.key,
            "osqp": fw.osqp,
            "defines": list(fw.defines),
            "mpc_every": fw.mpc_every,
            **memory_figures(fw),
        },
        "instructions_per_cycle": insns,
        "stack_high_water_bytes": stack_high_water(guest),
        "guest_ready": next(
            (ln for ln in guest.splitlines() if ln.startswith("PIL node ready")), None
        ),
        "syncs_handled": len(kinds),
        "cycles_answered": sum(1 for ok, _ in kinds if ok),
        "frames_to_firmware": bridge.to_firmware if bridge else 0,
        "frames_from_firmware": bridge.from_firmware if bridge else 0,
        "stop": stop_reason,
        "secoc": secoc_summary(guest, fw.secoc),
        "core_exceptions": 0,
    }


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m harness.bench.mcu.pil_node", description=__doc__.splitlines()[0]
    )
    p.add_argument("--bus", required=True, help="the run's bus (can_db.transport.bus spec)")
    p.add_argument("--controller", default="nmpc-rhonn", help="which controller runs")
    p.add_argument("--config", default=None, help="controller TOML or packaged name")
    p.add_argument("--summary", default=None, help="write the figures as JSON here at exit")
    p.add_argument(
        "--work-dir", default=None, help="QEMU's logs and the plugin's (default: beside --summary)"
    )
    p.add_argument(
        "--osqp",
        choices=OSQP_PRECISIONS,
        default="float",
        help="OSQP's precision in the firmware (default float: the FPU's)",
    )
    p.add_argument("--opt", default="Os", help="optimisation level (default Os)")
    p.add_argument(
        "--secoc",
        action="store_true",
        help="verify the plant's frames and authenticate the answers (SecOC) with the public "
        "CI test keys, compiled into the firmware (default: off, the plant with --no-secoc)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    stop = StopFlag()
    work = Path(args.work_dir or (Path(args.summary).parent if args.summary else "."))
    work = work / "pil"
    work.mkdir(parents=True, exist_ok=True)
    try:
        fw = build_pil_node(args.controller, args.config, args.osqp, args.opt, secoc=args.secoc)
        # the configuration the firmware was built from, for `rhonn-harness replay --config`
        shutil.copyfile(fw.out / "pil_controller.toml", work / "pil_controller.toml")
        link, log = boot(fw, work)
    except (McuError, PilLinkError) as exc:
        print(f"pil-node: error: {exc}", file=sys.stderr, flush=True)
        return 2
    bridge = PilBridge(link, args.bus)
    reason = "stopped by signal"
    code = 0
    try:
        bridge.start()
        print(
            f"ready {args.controller} on {args.bus} (lockstep, Cortex-M4F firmware on QEMU "
            f"{fw.key}, OSQP {fw.osqp}, SecOC {'on, CI test key' if fw.secoc else 'off'})",
            flush=True,
        )
        while not stop():
            time.sleep(0.1)
            if bridge.error is not None:
                reason = f"link lost: {bridge.error}"
                code = 3
                break
    finally:
        try:
            bridge.stop()
        except Exception as exc:  # the link's error is reported, the files still written
            if code == 0:
                reason, code = f"link lost: {exc}", 3
        try:
            link.close()
        except PilLinkError as exc:
            reason, code = f"QEMU failed: {exc}", 3
    result = summary(fw, link, bridge, log, reason)
    if args.summary:
        Path(args.summary).write_text(json.dumps(result, indent=2) + "\n")
    full = result["instructions_per_cycle"].get("full_step", {})
    print(
        f"stopped: {args.controller} on the Cortex-M4F ({reason}), "
        f"{result['cycles_answered']} cycles answered; instructions per full step p50 "
        f"{full.get('insns_p50')}, p99 {full.get('insns_p99')}, max "
        f"{full.get('insns_max')}; stack {result['stack_high_water_bytes']} B",
        flush=True,
    )
    return code


if __name__ == "__main__":
    raise SystemExit(main())
