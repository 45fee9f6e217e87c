"""Processor in the loop: the whole controller node as Cortex-M4F firmware on QEMU
(controller/native/mcu/pil/pil_node.c, harness/bench/mcu/pil_node.py), on the bus.

* closed loop across processes: ``rhonn-harness run``'s path with ``target="m4f"`` (plant
  process, local bus hub, the firmware's process: QEMU + SLCAN bridge), a short DLC that
  finishes with every SYNC answered by a torque frame echoing it, KPIs and the firmware's
  figures (instructions per cycle, stack, flash/RAM) written;
* the same run with the host's float32 C core in the Python controller process: the same
  torque commands and the same vehicle motion;
* open loop: the plant's frames of that run replayed into a fresh firmware and a fresh
  Python node (float32 C core): the same answer frames, byte for byte; a corrupted SYNC and a
  diagnostic request are not answered, and the node answers the next good SYNC;
* bad input: the run options the firmware cannot honour are refused before anything starts.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from can_db.codec import Codec
from can_db.secoc import ControllerSecOc
from can_db.secoc_keys import (
    ENV_CTRL_TO_PLANT,
    ENV_PLANT_TO_CTRL,
    TEST_KEY_SOURCE,
    ci_test_keys,
)
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode
from harness.analysis.run_data import load_run
from harness.bench import mcu
from harness.bench.mcu.pil_node import CACHE_ENV, SECOC_VERDICTS, build_pil_node
from harness.cli import firmware_line
from harness.report.run_report import run_and_report
from harness.run.hil_bench import check_target
from harness.run.pil_link import PilLink
from harness.run.replay import replay_log
from harness.run.spec import RunSpec
from harness.run.validate import UsageError, check_run_config

MISSING = mcu.missing_tools()
needs_toolchain = pytest.mark.skipif(MISSING is not None, reason=f"MCU toolchain: {MISSING}")

DURATION_S = 2.0  # simulated s of the DLC (200 cycles, 40 full controller steps)
CODEC = Codec()
ID = {name: CODEC.messages[name].frame_id for name in CODEC.messages}
PLANT_DATA = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")
PLANT_IDS = {ID[n] for n in PLANT_DATA}
PLANT_SECOC_IDS = PLANT_IDS | {ID[f"{n}_AUTH"] for n in PLANT_DATA}
ANSWER = ("WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS")
ANSWER_SECOC = (
    "WHEEL_TORQUE_CMD",
    "WHEEL_TORQUE_AUTH",
    "CTRL_STATUS",
    "CTRL_STATUS_AUTH",
    "CTRL_REFS",
)


def _spec(out: Path, **kw: Any) -> RunSpec:
    return RunSpec(
        scenario="dlc-paper",
        controller="nmpc-rhonn",
        out_dir=out,
        duration_s=DURATION_S,
        make_plots=False,
        make_rrd=False,
        **{"secoc": False, **kw},
    )


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("pil-cache")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cache: Path) -> dict[str, Any]:
    """The DLC on the firmware, then on the host's float32 C core with the firmware's
    controller file (the firmware's build writes it beside the ELF)."""
    mp = pytest.MonkeyPatch()
    mp.setenv(CACHE_ENV, str(cache))  # the firmware's process inherits it
    try:
        root = tmp_path_factory.mktemp("pil-runs")
        fw = build_pil_node("nmpc-rhonn")
        fw_secoc = build_pil_node("nmpc-rhonn", secoc=True)
        m4f = run_and_report(_spec(root / "m4f", target="m4f"))
        host = run_and_report(
            _spec(root / "host", controller_config=str(fw.out / "pil_controller.toml"))
        )
        secoc = run_and_report(
            _spec(root / "m4f-secoc", target="m4f", secoc=True, secoc_keys=TEST_KEY_SOURCE)
        )
    finally:
        mp.undo()
    return {"m4f": m4f, "host": host, "fw": fw, "m4f-secoc": secoc, "fw-secoc": fw_secoc}


def _frames(run_dir: Path) -> list[can.Message]:
    with can.BLFReader(str(run_dir / "bus.blf")) as reader:
        return list(reader)


@needs_toolchain
def test_closed_loop_on_the_firmware_answers_every_cycle(runs) -> None:
    res = runs["m4f"]
    out, metrics = res.out_dir, res.metrics
    assert res.reason == "finished", metrics
    assert metrics["target"] == "m4f"
    assert metrics["sim_time_reached_s"] == pytest.approx(DURATION_S)
    plant = json.loads((out / "plant_summary.json").read_text())
    assert plant["lockstep_timeouts"] == 0 and metrics["command_held_cycles"] == 0
    # every SYNC of the plant is answered by exactly one torque frame that echoes it
    frames = _frames(out)
    cycles = [
        CODEC.decode_message(m).values["CYCLE"] for m in frames if m.arbitration_id == ID["SYNC"]
    ]
    echoes = [
        CODEC.decode_message(m).values["ECHO_CYCLE"]
        for m in frames
        if m.arbitration_id == ID["WHEEL_TORQUE_CMD"]
    ]
    assert len(cycles) == round(DURATION_S / 0.01)
    assert echoes == [c % 256 for c in cycles]
    status = [
        CODEC.decode_message(m).values for m in frames if m.arbitration_id == ID["CTRL_STATUS"]
    ]
    assert {s["CONTROLLER_ID"] for s in status} == {1}  # nmpc-rhonn
    assert sum(1 for s in status if s["MODE"] == 1) >= len(status) - 1  # ACTIVE (INIT first)
    # KPIs written as for any run
    assert np.isfinite(metrics["max_abs_beta_deg"]) and metrics["max_abs_beta_deg"] > 0.5
    assert np.isfinite(metrics["max_abs_lateral_dev_m"])
    # the firmware's own figures
    summ = metrics["controller_summary"]
    assert summ["guest_ready"] == "PIL node ready 0 0"  # core and node initialised
    assert summ["cycles_answered"] == len(cycles)
    ins = summ["instructions_per_cycle"]
    assert ins["cycles"] == len(cycles)
    full, alloc = ins["full_step"], ins["allocate_only"]
    assert full["cycles"] == len(cycles) // 5 and alloc["cycles"] == len(cycles) - full["cycles"]
    assert 1e5 < full["insns_p50"] <= full["insns_p99"] <= full["insns_max"] < 5e7
    assert 1e3 < alloc["insns_p50"] < full["insns_min"]
    assert full["us_at_clock_p50"] == pytest.approx(full["insns_p50"] / 168.0)
    assert 256 < summ["stack_high_water_bytes"] < 64 * 1024
    line = firmware_line(summ)  # what rhonn-harness run prints for the target
    assert f"{full['insns_max']:,}" in line and f"stack {summ['stack_high_water_bytes']} B" in line
    fwm = summ["firmware"]
    assert fwm["flash_bytes"] > 50_000 and 16_000 < fwm["ram_static_bytes"] < 4 << 20


@needs_toolchain
def test_closed_loop_with_secoc_every_answer_authenticated(runs) -> None:
    """SecOC on both ends (the public CI test key compiled into the firmware): the plant
    accepts every torque and status frame of the firmware, the firmware every frame of the
    plant's bursts, and the loop holds."""
    res = runs["m4f-secoc"]
    assert res.reason == "finished", res.metrics
    n = round(DURATION_S / 0.01)
    plant = json.loads((res.out_dir / "plant_summary.json").read_text())
    assert plant["lockstep_timeouts"] == 0 and res.metrics["command_held_cycles"] == 0
    sec = plant["secoc"]
    assert sec["enabled"] and sec["rejected"] == {}
    assert sec["accepted"]["WHEEL_TORQUE_CMD"] == n
    assert sec["accepted"]["CTRL_STATUS"] >= n - 1  # the last may come after the plant's end
    ctrl = res.metrics["controller_summary"]["secoc"]
    assert ctrl["enabled"] and ctrl["rejected"] == {}
    assert ctrl["accepted"] == {"all secured frames": 5 * n}  # SYNC and 4 data frames a cycle
    ins = res.metrics["controller_summary"]["instructions_per_cycle"]
    assert ins["cycles"] == n  # one marker pair per SYNC_AUTH
    assert res.metrics["max_abs_beta_deg"] == pytest.approx(
        runs["m4f"].metrics["max_abs_beta_deg"], rel=1e-9
    )  # SecOC changes no value
    # the whole firmware (node + core + OSQP float + SecOC) within the ECU budget: 96 kB
    # flash, 24 kB static RAM (controller/native/mcu/README.md)
    fwm = res.metrics["controller_summary"]["firmware"]
    assert fwm["flash_bytes"] <= 96 * 1024 and fwm["ram_static_bytes"] <= 24 * 1024, fwm


@needs_toolchain
def test_firmware_and_host_float32_core_drive_alike(runs) -> None:
    a, b = runs["m4f"], runs["host"]
    assert b.reason == "finished"
    assert "float32" in (b.out_dir / "controller.log").read_text()  # the host ran float32

    def torques(run_dir: Path) -> np.ndarray:
        return np.array(
            [
                [CODEC.decode_message(m).values[f"TQ_{w}"] for w in ("FL", "FR", "RL", "RR")]
                for m in _frames(run_dir)
                if m.arbitration_id == ID["WHEEL_TORQUE_CMD"]
            ]
        )

    ta, tb = torques(a.out_dir), torques(b.out_dir)
    assert ta.shape == tb.shape
    # same sources, both float32: only libm differs (newlib vs glibc, a few ulp); one DBC
    # step (0.5 N m) of the commanded torques bounds what that can move
    step = CODEC.messages["WHEEL_TORQUE_CMD"].signals[0].scale
    assert np.abs(ta - tb).max() <= step
    ra, rb = load_run(a.out_dir), load_run(b.out_dir)
    for col in ("beta_rad", "yaw_rate_radps", "vy_mps"):
        x, y = ra.truth_col(col), rb.truth_col(col)
        assert np.abs(x - y).max() <= 1e-4 * np.abs(y).max(), col
    for key in ("max_abs_beta_deg", "max_abs_lateral_dev_m"):
        assert a.metrics[key] == pytest.approx(b.metrics[key], rel=1e-4), key


@needs_toolchain
@pytest.mark.parametrize("secoc", [False, True], ids=["plain", "secoc"])
def test_recorded_frames_are_answered_as_the_python_node_does(runs, tmp_path, secoc) -> None:
    """Open loop: the plant's frames of the closed-loop run, burst by burst, into a fresh
    firmware and a fresh Python node on the float32 C core (compute time 0 on both; with
    SecOC both verify the recorded trip's frames and sign their answers with it)."""
    fw = runs["fw-secoc" if secoc else "fw"]
    node = ControllerNode(
        make_controller("nmpc-rhonn", fw.out / "pil_controller.toml"),
        load_vehicle_params(),
        codec=Codec(),
        secoc=ControllerSecOc(Codec(), ci_test_keys()) if secoc else None,
    )
    assert node.controller.backend == "native"
    ids = PLANT_SECOC_IDS if secoc else PLANT_IDS
    plant = [
        m for m in _frames(runs["m4f-secoc" if secoc else "m4f"].out_dir) if m.arbitration_id in ids
    ]
    per_cycle = len(ids)
    with PilLink(fw.elf, tmp_path) as link:
        answered = 0
        for msg in plant[: per_cycle * 100]:  # the first 100 cycles
            want = node.on_frame_lockstep(msg)
            link.send(msg)
            if want is None:
                continue
            got = [link.recv(30.0) for _ in want]
            assert [g.arbitration_id for g in got] == [
                ID[n] for n in (ANSWER_SECOC if secoc else ANSWER)
            ]
            assert [bytes(g.data) for g in got] == [bytes(w.data) for w in want]
            answered += 1
        assert answered == 100
        # the next cycle's SYNC (and authenticator): corrupted copies are not answered (the
        # plant's timeout handles it), a diagnostic request neither (no UDS server)
        nxt = plant[per_cycle * 100 : per_cycle * 101]
        good = [m for m in nxt if m.arbitration_id in (ID["SYNC"], ID["SYNC_AUTH"])]
        assert len(good) == (2 if secoc else 1)
        for k in (0, 1, 7):
            forged = [
                can.Message(
                    arbitration_id=m.arbitration_id,
                    is_extended_id=False,
                    data=bytes(b ^ (0xFF if i == k else 0) for i, b in enumerate(m.data)),
                )
                for m in good
            ]
            for msg in forged:
                assert node.on_frame_lockstep(msg) is None
                link.send(msg)
        link.send(
            can.Message(
                arbitration_id=CODEC.diagnostic["DIAG_REQ_CTRL"],
                is_extended_id=False,
                data=bytes([2, 0x10, 3, 0, 0, 0, 0, 0]),
            )
        )
        assert link.recv(3.0) is None
        # the genuine SYNC is answered alike (its burst's data frames were not sent)
        for msg in good:
            want = node.on_frame_lockstep(msg)
            link.send(msg)
        got = [link.recv(30.0) for _ in want]
        assert [bytes(g.data) for g in got] == [bytes(w.data) for w in want]
        cycle = int(CODEC.decode_message(good[0]).values["CYCLE"])
        assert CODEC.decode_message(got[0]).values["ECHO_CYCLE"] == cycle % 256


# the firmware's SecOC hold per deferred stream (pil_node.c PIL_NODE_SEC_HELD: data frames
# and authenticators of RH_NODE_BURST_MAX = 6 cycles) and the accepted FVs it remembers per
# stream (pil_node.py SECOC_HISTORY)
FW_SEC_HELD = 12
FW_HISTORY = 16
RX_OVERLOAD = 1 << 7  # CTRL_STATUS.FAULT_BITS


def _verdicts(guest: str) -> dict[str, int]:
    last = [ln.split()[1:] for ln in guest.splitlines() if ln.startswith("R ")][-1]
    return dict(zip(SECOC_VERDICTS, map(int, last), strict=True))


@needs_toolchain
def test_floods_on_one_secured_stream_are_rejected_and_counted(runs, tmp_path) -> None:
    """SecOC, the DRIVER_INPUTS stream flooded with 40 frames that pass E2E before a cycle's
    burst; every answer equals the Python node's (ControllerSecOc, 4 096 FVs remembered, a
    hold of 32 frames a stream) and every flood frame is counted once, none reaches the node.

    * cycle 20: the 20 earlier cycles' genuine pairs replayed (data frame, authenticator):
      each judged on arrival (early verification), "replay" for the last 16 accepted FVs the
      firmware remembers, "stale_freshness" for older ones; nothing is pushed out.
    * cycle 21: the same data frames, each followed by a forged authenticator (MAC changed):
      nothing verifies, so they are held; the firmware's hold (12 frames a stream) pushes
      the oldest out (unauthenticated / unchecked_auth: RX_OVERLOAD in the answer, as the
      Python node's larger hold also overflows), the rest are judged at the SYNC (bad_mac,
      orphan_auth, the data unauthenticated); the genuine pair behind the flood is accepted.
    """
    fw = runs["fw-secoc"]
    node = ControllerNode(
        make_controller("nmpc-rhonn", fw.out / "pil_controller.toml"),
        load_vehicle_params(),
        codec=Codec(),
        secoc=ControllerSecOc(Codec(), ci_test_keys()),
    )
    plant = [m for m in _frames(runs["m4f-secoc"].out_dir) if m.arbitration_id in PLANT_SECOC_IDS]
    per_cycle, n_before = len(PLANT_SECOC_IDS), 20
    pairs = [
        m
        for m in plant[: per_cycle * n_before]
        if m.arbitration_id in (ID["DRIVER_INPUTS"], ID["DRIVER_INPUTS_AUTH"])
    ]
    forged = []
    for m in pairs:
        if m.arbitration_id == ID["DRIVER_INPUTS_AUTH"]:
            auth = CODEC.decode_message(m)
            values = {**auth.values, "MAC": int(auth.values["MAC"]) ^ 1}
            m = CODEC.message("DRIVER_INPUTS_AUTH", values, auth.counter)
        forged.append(m)
    assert len(pairs) == len(forged) == 2 * n_before

    def burst(k: int) -> list[can.Message]:
        return plant[per_cycle * k : per_cycle * (k + 1)]

    counts = []
    status = []
    with PilLink(fw.elf, tmp_path) as link:
        for frames in (
            plant[: per_cycle * n_before],
            [*pairs, *burst(n_before)],
            [*forged, *burst(n_before + 1)],
        ):
            for msg in frames:
                want = node.on_frame_lockstep(msg)
                link.send(msg)
                if want is None:
                    continue
                got = [link.recv(30.0) for _ in want]
                assert [bytes(g.data) for g in got] == [bytes(w.data) for w in want]
            status.append(int(CODEC.decode_message(got[2]).values["FAULT_BITS"]))
            counts.append(_verdicts(link.guest_log.read_text()))
    genuine = {"accepted": 5 * n_before}  # SYNC and four data frames a cycle
    assert counts[0] == {**dict.fromkeys(SECOC_VERDICTS, 0), **genuine}
    replays = {k: counts[1][k] - counts[0][k] for k in SECOC_VERDICTS}
    assert replays == {
        **dict.fromkeys(SECOC_VERDICTS, 0),
        "accepted": 5,
        "replay": FW_HISTORY,
        "stale_freshness": n_before - FW_HISTORY,
    }
    assert not status[1] & RX_OVERLOAD
    flood = {k: counts[2][k] - counts[1][k] for k in SECOC_VERDICTS}
    assert flood.pop("accepted") == 5 and flood["replay"] == flood["stale_freshness"] == 0
    assert sum(flood.values()) == 2 * n_before  # each forged pair counted once, nothing more
    # pushed out of the hold: all but its last 12 frames, of which the genuine pair
    assert flood["unchecked_auth"] + flood["unauthenticated"] > 2 * n_before - FW_SEC_HELD
    assert flood["bad_mac"] > 0 and status[2] & RX_OVERLOAD


def test_targets_the_firmware_cannot_run_are_refused(tmp_path, monkeypatch) -> None:
    for var in (ENV_CTRL_TO_PLANT, ENV_PLANT_TO_CTRL):  # keys of one's own, loadable
        monkeypatch.setenv(var, "5a" * 16)
    with pytest.raises(ValueError, match="target must be one of"):
        check_target(_spec(tmp_path, target="stm32"))
    for kw, why in (
        (dict(secoc=True, secoc_keys="env"), "CI test key only"),
        (dict(controller_mode="freerun"), "SYNC frames only"),
        (dict(controller="passive"), "not passive"),
        (dict(faults=("core-exception:0.1@0.5",)), "injects no faults"),
    ):
        spec = dataclasses.replace(_spec(tmp_path, target="m4f"), **kw)
        with pytest.raises(ValueError, match=why):
            check_target(spec)
        with pytest.raises(UsageError, match=why):
            check_run_config(spec, bus=False)
    check_target(_spec(tmp_path, target="m4f"))  # the supported set passes
    check_target(_spec(tmp_path, target="m4f", secoc=True, secoc_keys=TEST_KEY_SOURCE))
    assert "target" not in _spec(tmp_path).identity()
    assert _spec(tmp_path, target="m4f").key() != _spec(tmp_path).key()


@needs_toolchain
@pytest.mark.parametrize("kind", ["m4f", "m4f-secoc"])
def test_the_firmware_runs_bus_log_replays_bit_identical_through_the_python_runtime(
    runs, kind: str
) -> None:
    """The run directory keeps the firmware's configuration; with it the Python controller
    node (host float32 C core) reproduces every recorded torque frame (and its MAC)."""
    out = runs[kind].out_dir
    config = out / "pil" / "pil_controller.toml"
    assert config.is_file()
    keys = ci_test_keys() if kind == "m4f-secoc" else None
    res = replay_log(out / "bus.blf", "nmpc-rhonn", str(config), keys)
    assert res.recorded == round(DURATION_S / 0.01)
    assert res.bit_identical and len(res.segments) == 1
