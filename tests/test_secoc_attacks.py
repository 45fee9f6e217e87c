"""Attacks on the secured torque path, across real OS processes on the loopback bus.

Each test runs a short lockstep dlc-paper (LMPC; the SecOC handling is the node's and the
plant's, the same for every controller) with a rogue node process (harness/run/rogue.py) or a
bit-flip fault, and checks from the plant's truth trace and the summaries that every forged
frame was rejected and counted, none was applied, and the legitimate controller kept control.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from can_db.secoc_keys import ci_test_keys
from harness.analysis.run_data import RunData, load_run
from harness.report.run_report import run_and_report
from harness.run.replay import replay_log
from harness.run.rogue import ROGUE_TORQUES_NM
from harness.run.runner import RunResult
from harness.run.spec import RunSpec
from tests.helpers_proc import live_children


def run(tmp_path: Path, *faults: str, duration: float = 3.0, secoc: bool = True
        ) -> tuple[RunResult, RunData]:
    result = run_and_report(RunSpec(scenario="dlc-paper", controller="lmpc",
                                       out_dir=tmp_path, duration_s=duration,
                                       faults=list(faults), secoc=secoc,
                                       secoc_keys="ci-test-key", make_plots=False,
                                       make_rrd=False))
    assert result.reason == "finished", result.metrics
    assert not our_children()
    return result, load_run(tmp_path)


def our_children() -> list[str]:
    """Command lines of the live descendants (the test process's own resource tracker aside:
    tests/helpers_proc.py)."""
    out = []
    for proc in live_children():
        try:
            out.append(" ".join(proc.cmdline()))
        except Exception:  # gone meanwhile
            continue
    return out


def rogue_cycles(data: RunData) -> int:
    """Cycles in which the plant applied the rogue's command."""
    cmd = np.column_stack([data.truth_col(f"tcmd_{w}") for w in ("fl", "fr", "rl", "rr")])
    return int(np.sum(np.all(np.abs(cmd - np.asarray(ROGUE_TORQUES_NM)) < 0.25, axis=1)))


def summaries(tmp_path: Path) -> tuple[dict, dict, dict]:
    plant = json.loads((tmp_path / "plant_summary.json").read_text())
    ctrl = json.loads((tmp_path / "controller_summary.json").read_text())
    rogue_file = tmp_path / "rogue0_summary.json"
    rogue = json.loads(rogue_file.read_text()) if rogue_file.exists() else {}
    return plant, ctrl, rogue


def fallbacks_beyond_stalls(plant: dict) -> int:
    """Fallback cycles not explained by a lockstep wall-clock timeout (a > 200 ms stall of
    the shared machine, which costs a cycle with or without SecOC)."""
    return plant["fallback_cycles"] - plant["lockstep_timeouts"]


def assert_no_forgery_accepted(plant: dict, ctrl: dict, data: RunData) -> None:
    accepted = plant["secoc"]["accepted"]["WHEEL_TORQUE_CMD"]
    # every applied command was authentic (a late authentic one is accepted but not applied
    # in lockstep: its cycle is gone), and no more were accepted than the controller sent
    assert plant["commanded_cycles"] <= accepted <= ctrl["cycles_answered"]
    assert rogue_cycles(data) == 0


def test_without_secoc_the_rogue_node_moves_the_wheels(tmp_path: Path) -> None:
    """The attack is real: with SecOC off the plant obeys the rogue's well-formed frames."""
    _, data = run(tmp_path, "rogue-inject", secoc=False)
    assert rogue_cycles(data) > 30


def test_rogue_node_injection_is_rejected_and_the_controller_keeps_control(
        tmp_path: Path) -> None:
    result, data = run(tmp_path, "rogue-inject")
    plant, ctrl, rogue = summaries(tmp_path)
    assert rogue["frames_sent"] > 100
    sec = plant["secoc"]
    rejected = sec["rejected"]
    # Every torque frame and authenticator the plant received is accounted for exactly:
    # the genuine ones accepted, every forged frame dropped unauthenticated (or still
    # pending at the stop), every forged authenticator failing its MAC or finding no frame.
    # (A rogue lagging behind a loaded machine sends its last pairs after the plant stopped
    # reading: those were never received.)
    cmd = "WHEEL_TORQUE_CMD"
    forged = sec["received"][cmd] - sec["accepted"][cmd]
    forged_auth = sec["authenticators_received"][cmd] - sec["accepted"][cmd]
    assert 100 < forged <= rogue["frames_sent"] // 2
    assert rejected.get("unauthenticated", 0) + sec["pending"][cmd] == forged
    assert rejected.get("bad_mac", 0) + rejected.get("orphan_auth", 0) == forged_auth
    assert result.metrics["secoc_rejected"] == dict(sorted(rejected.items()))  # KPI table
    assert_no_forgery_accepted(plant, ctrl, data)
    assert fallbacks_beyond_stalls(plant) <= 0 and result.metrics["spun"] is False


def test_replay_of_a_recorded_valid_sequence_is_rejected(tmp_path: Path) -> None:
    result, data = run(tmp_path, "rogue-replay:0.3s")
    plant, ctrl, rogue = summaries(tmp_path)
    assert rogue["frames_sent"] > 100
    assert plant["secoc"]["rejected"].get("replay", 0) > 50
    assert_no_forgery_accepted(plant, ctrl, data)
    assert fallbacks_beyond_stalls(plant) <= 0 and result.metrics["spun"] is False
    # the secured log replays bit-identically (MACs included), rogue frames left out
    replay = replay_log(tmp_path / "bus.blf", "lmpc", keys=ci_test_keys())
    assert replay.secured and replay.bit_identical, replay


def test_flood_of_forged_frames_is_rejected(tmp_path: Path) -> None:
    # 1000 forged pairs/s = 2000 frames/s, about half of what a 500 kbit/s bus can carry
    result, data = run(tmp_path, "rogue-flood:1000")
    plant, ctrl, rogue = summaries(tmp_path)
    assert rogue["frames_sent"] > 1000
    assert plant["secoc"]["rejected"].get("bad_mac", 0) > 100
    assert_no_forgery_accepted(plant, ctrl, data)
    # a forged frame can only evict a genuine one that waits for its authenticator behind
    # 16 forged ones: allow 1 % of the cycles
    assert fallbacks_beyond_stalls(plant) <= 0.01 * plant["cycles"]
    assert result.metrics["spun"] is False


@pytest.mark.parametrize("fault", ["payload-flip:20%,WHEEL_TORQUE_CMD@1s",
                                   "mac-flip:20%,WHEEL_TORQUE_AUTH@1s"])
def test_bit_flips_are_rejected_and_cost_exactly_their_cycles(tmp_path: Path,
                                                              fault: str) -> None:
    result, data = run(tmp_path, fault)
    plant, ctrl, _ = summaries(tmp_path)
    flips = sum(ctrl["injected"].values())
    assert flips > 20
    assert plant["secoc"]["rejected"]["bad_mac"] == flips
    # a rejected command is handled exactly as a missing one: that cycle holds the last
    # command, or falls back after 30 ms without one (plus, on a loaded machine, any cycle
    # whose answer took > 200 ms)
    assert result.metrics["fallback_events"] == plant["fallback_cycles"]
    without_fresh = plant["held_cycles"] + plant["fallback_cycles"]
    assert flips <= without_fresh <= flips + plant["lockstep_timeouts"]
    assert plant["fallback_cycles"] <= plant["held_cycles"] / 5  # 4 flips in a row: rare
    assert_no_forgery_accepted(plant, ctrl, data)
    assert result.metrics["spun"] is False


def test_restarted_plant_resynchronises_through_the_authenticated_sync(tmp_path: Path
                                                                       ) -> None:
    _, data = run(tmp_path, "restart-plant@1.5s", duration=2.5)
    plant, ctrl, _ = summaries(tmp_path)
    # the killed plant (trip 1, SIGKILL: no summary) left its trip counter in the file
    assert plant["secoc"]["trip"] == 2 and (tmp_path / "secoc_trip").read_text().strip() == "2"
    assert ctrl["secoc"]["resyncs"] == 1 and ctrl["secoc"]["rejected"] == {}
    assert plant["secoc"]["rejected"] == {}
    assert np.all(data.truth_col("cmd_valid")[1:] == 1)  # the new plant obeys from cycle 1


# ------------------------------------------------------ forged driver and sensor frames
def spoofed_cycles(data: RunData) -> int:
    """Cycles in which the plant got a total torque command above 1500 N·m: the rogue's
    full accelerator (4 × 450 N·m); the dlc-paper driver coasts at a few N·m."""
    cmd = np.column_stack([data.truth_col(f"tcmd_{w}") for w in ("fl", "fr", "rl", "rr")])
    return int(np.sum(cmd.sum(axis=1) > 1500.0))


def test_without_secoc_spoofed_driver_and_sensor_frames_are_acted_on(tmp_path: Path) -> None:
    """The attack is real: with SecOC off the controller takes the rogue's well-formed
    DRIVER_INPUTS (full accelerator) for the plant's and commands full torque."""
    _, data = run(tmp_path, "rogue-spoof", secoc=False)
    _, ctrl, _ = summaries(tmp_path)
    # how many cycles the rogue wins is a race with the loop's next burst: 2 of 300 in a
    # full-suite run with the loop's process modules traced by coverage, 12 in a loaded one
    # without, more alone; with SecOC on the same attack wins none (below)
    assert spoofed_cycles(data) >= 1
    # the genuine frames then look repeated (the forged ones took their counters)
    assert ctrl["rejections"].get("counter_frozen", 0) > 100


def test_spoofed_driver_and_sensor_frames_are_rejected_and_counted(tmp_path: Path) -> None:
    result, data = run(tmp_path, "rogue-spoof")
    plant, ctrl, rogue = summaries(tmp_path)
    forged = rogue["frames_sent"] // 4  # per frame: a data frame and its authenticator
    assert forged > 100
    sec = ctrl["secoc"]
    by_frame = sec["rejected_by_frame"]
    # a rogue that lagged behind the lockstep loop sends its backlog at once: more than the
    # 32 frames held per ID, the oldest are pushed out unverified (counted, never used)
    evicted = sec["evicted_unverified"]
    for name in ("DRIVER_INPUTS", "MOTION_SENSORS"):
        counts = by_frame[name]
        # what the controller read of the rogue's: all it received beyond the genuine frames
        # it accepted. The rogue's last frames may still be in flight when the run ends
        # (a loaded CI machine: 3 of 300), hence "nearly all" of the sent ones.
        forged_data = sec["received"][name] - sec["accepted"][name]
        forged_auth = sec["authenticators_received"][name] - sec["accepted"][name]
        assert forged_data >= forged - 10 and forged_auth >= forged - 10, name
        # every forged authenticator read failed its MAC (or found no frame held); every
        # forged data frame read was dropped unauthenticated at its burst's SYNC, or still
        # waits for one when the run ends (pending: data and authenticators): none was used
        assert counts.get("bad_mac", 0) + counts.get("orphan_auth", 0) + evicted \
            + sec["pending"][name] + sec["pending_authenticators"][name] >= forged_auth, name
        assert counts.get("unauthenticated", 0) + sec["pending"][name] >= forged_data, name
    assert set(by_frame) == {"DRIVER_INPUTS", "MOTION_SENSORS"}  # nothing else disturbed
    assert spoofed_cycles(data) == 0
    # no forged frame reached the E2E monitor: the genuine counters never looked repeated
    assert ctrl["rejections"].get("counter_frozen", 0) == 0
    assert ctrl["secoc"]["accepted"]["MOTION_SENSORS"] >= ctrl["cycles_answered"] - 2
    assert fallbacks_beyond_stalls(plant) <= 0 and result.metrics["spun"] is False


def test_replayed_driver_and_sensor_frames_are_rejected(tmp_path: Path) -> None:
    result, data = run(tmp_path, "rogue-sensor-replay:0.3s")
    plant, ctrl, rogue = summaries(tmp_path)
    assert rogue["frames_sent"] > 400
    by_frame = ctrl["secoc"]["rejected_by_frame"]
    for name in ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST"):
        assert by_frame[name].get("replay", 0) + by_frame[name].get("stale_freshness", 0) \
            > 100, name
    assert ctrl["rejections"].get("counter_frozen", 0) == 0
    assert ctrl["rejections"].get("wrong_sequence", 0) == 0
    assert ctrl["secoc"]["accepted"]["MOTION_SENSORS"] >= ctrl["cycles_answered"] - 2
    assert spoofed_cycles(data) == 0
    assert fallbacks_beyond_stalls(plant) <= 0 and result.metrics["spun"] is False
    # the secured log replays bit-identically (MACs included), rogue frames rejected again
    replay = replay_log(tmp_path / "bus.blf", "lmpc", keys=ci_test_keys())
    assert replay.secured and replay.bit_identical, replay
