"""Checkpointed learning: bit-exact round trip, atomic writes, corrupted files → cold start,
and learned state surviving a controller process restart in a closed loop."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import can
import numpy as np
import pytest

from can_db.codec import Codec
from controller.core.interfaces import ControllerInputs
from controller.core.params import load_vehicle_params
from controller.registry import CONTROLLER_NAMES, make_controller
from controller.runtime.checkpoint import (
    FORMAT_VERSION,
    CheckpointManager,
    config_hash,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from harness.analysis.model_error import one_step_errors
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from tests.helpers_proc import live_children
from tests.test_controller_support import BicycleSim, dlc_swa, fill_inputs

P = load_vehicle_params()
HASH = config_hash("nmpc-rhonn")
PENDING = {"rhonn.has_record"}  # dropped on restore (a restart is a break in time)


def drive(ctrl, steps: int, seed: int = 0) -> None:
    """Closed loop against the support bicycle model so the controller learns something."""
    sim = BicycleSim(P, mu=0.7)
    sim.reset(18.0)
    rng = np.random.default_rng(seed)
    inp = ControllerInputs()
    for k in range(steps):
        fill_inputs(inp, sim, dlc_swa((k * ctrl.ts) % 8.0, 40.0), rng)
        out = ctrl.step(inp)
        sim.step(out.torques, inp.swa_rad / P.steering_ratio, ctrl.ts)


def states_equal(a: dict, b: dict, skip: set[str] = frozenset()) -> bool:
    if set(a) != set(b):
        return False
    return all(np.array_equal(np.asarray(a[k]), np.asarray(b[k]), equal_nan=True)
               for k in a if k not in skip)


@pytest.fixture(scope="module")
def learned() -> object:
    ctrl = make_controller("nmpc-rhonn")
    drive(ctrl, 120)
    return ctrl


# ------------------------------------------------------------------------ round trip
@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_round_trip_is_bit_exact(name: str, tmp_path: Path) -> None:
    a = make_controller(name)
    drive(a, 60)
    path = tmp_path / "c.npz"
    save_checkpoint(path, a, cfg_hash=config_hash(name), steps=60)
    header, data = read_checkpoint(path)
    assert header["version"] == FORMAT_VERSION and header["controller"] == name
    assert header["steps"] == 60 and header["config_hash"] == config_hash(name)
    assert states_equal(a.get_state(), data)       # the file holds the exact bits
    b = make_controller(name)
    result = load_checkpoint(path, b, cfg_hash=config_hash(name))
    assert result.restored and result.steps == 60, result.reason
    assert states_equal(a.get_state(), b.get_state(), skip=PENDING)
    for k, v in a.get_state().items():  # floats come back as floats
        assert isinstance(b.get_state()[k], float) == isinstance(v, float), k


def test_restored_controller_learns_on_identically(learned, tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned, cfg_hash=HASH, steps=120)
    a, b = make_controller("nmpc-rhonn"), make_controller("nmpc-rhonn")
    assert load_checkpoint(path, a, cfg_hash=HASH).restored
    assert load_checkpoint(path, b, cfg_hash=HASH).restored
    drive(a, 40, seed=5)
    drive(b, 40, seed=5)
    assert states_equal(a.get_state(), b.get_state())


def test_restore_drops_the_stopped_runs_pending_prediction(learned, tmp_path: Path) -> None:
    """The prediction recorded before the stop is for a state the new run never measures;
    learning from it once injected a large bogus error (found by the cross-process test)."""
    assert learned.get_state()["rhonn.has_record"] == 1.0
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned, cfg_hash=HASH, steps=120)
    ctrl = make_controller("nmpc-rhonn")
    assert load_checkpoint(path, ctrl, cfg_hash=HASH).restored
    w = ctrl.model.W.copy()
    inp = ControllerInputs(vx=25.0, vy=-1.0, yaw_rate=0.4, swa_rad=1.0)
    inp.wheel_speeds[:] = 25.0 / P.wheel_radius_m
    ctrl.step(inp)  # first step after the restart: nothing to learn from yet
    assert np.array_equal(ctrl.model.W, w)


# ------------------------------------------------------------------------- atomicity
def test_a_failure_between_write_and_replace_keeps_the_previous_checkpoint(
        learned, tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned, cfg_hash=HASH, steps=1)
    before = path.read_bytes()

    def crash(tmp: Path) -> None:
        assert tmp.parent == path.parent
        assert read_checkpoint(tmp)[0]["steps"] == 2  # complete and readable before the rename
        raise OSError("power lost")

    with pytest.raises(OSError, match="power lost"):
        save_checkpoint(path, learned, cfg_hash=HASH, steps=2, _before_replace=crash)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.npz"]  # temp file removed
    assert load_checkpoint(path, make_controller("nmpc-rhonn"), cfg_hash=HASH).steps == 1


def test_a_process_killed_mid_save_leaves_the_previous_checkpoint(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    script = textwrap.dedent(f"""
        import os
        from controller.runtime.checkpoint import save_checkpoint
        from controller.registry import make_controller
        c = make_controller("nmpc-rhonn")
        save_checkpoint({str(path)!r}, c, cfg_hash="h", steps=1)
        # the second save dies hard after writing the temp file, before the rename
        save_checkpoint({str(path)!r}, c, cfg_hash="h", steps=2,
                        _before_replace=lambda tmp: os._exit(9))
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parent.parent,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 9, proc.stderr
    stale = [p for p in tmp_path.iterdir() if p.name != "c.npz"]
    assert len(stale) == 1 and stale[0].name.startswith(".c.npz.")
    header, _ = read_checkpoint(path)
    assert header["steps"] == 1
    mgr = CheckpointManager(path, make_controller("nmpc-rhonn"), "h")
    assert mgr.restore().restored and mgr.steps == 1
    assert [p.name for p in tmp_path.iterdir()] == ["c.npz"]  # stale temp cleaned up


# ----------------------------------------------------------- corrupted / mismatched
def _corruptions(good: bytes, learned, tmp: Path) -> dict[str, tuple[bytes, str]]:
    """name → (file bytes, expected words in the reason)."""
    out = {
        "empty": (b"", "unreadable"),
        "truncated": (good[: len(good) // 2], "unreadable"),
        "garbage": (bytes(np.random.default_rng(1).integers(0, 256, 4000, np.uint8)),
                    "unreadable"),
    }
    flipped = bytearray(good)
    flipped[len(good) // 3] ^= 0xFF  # inside an array: the zip CRC catches it
    out["bit flip"] = (bytes(flipped), "unreadable")

    def variant(name: str, mutate, cfg_hash: str = HASH, steps: int = 5) -> None:
        class Wrapped:
            def __init__(self) -> None:
                self.name, self.ts = learned.name, learned.ts

            def get_state(self) -> dict:
                return mutate(dict(learned.get_state()))

        p = tmp / f"{name}.npz"
        save_checkpoint(p, Wrapped(), cfg_hash=cfg_hash, steps=steps)
        return p.read_bytes()

    out["other config"] = (variant("cfg", lambda d: d, cfg_hash="0" * 16), "config hash")
    out["missing key"] = (variant("miss", lambda d: {k: v for k, v in d.items()
                                                     if k != "rhonn.P"}), "missing")
    out["extra key"] = (variant("extra", lambda d: {**d, "x.y": 1.0}), "unexpected")
    out["wrong shape"] = (variant("shape", lambda d: {**d, "rhonn.W": np.zeros((3, 14))}),
                          "shape")
    out["NaN weights"] = (variant("nan", lambda d: {**d, "rhonn.W": np.full((3, 15),
                                                                            np.nan)}),
                          "NaN")
    out["inf"] = (variant("inf", lambda d: {**d, "qp.sol": np.full_like(d["qp.sol"],
                                                                         np.inf)}),
                  "infinite")
    # finite but not a state the controller reaches (the EKF's bounds, [rhonn.ekf])
    out["absurd weights"] = (variant("w", lambda d: {**d, "rhonn.W": np.full((3, 15), 1e30)}),
                             "w_max")
    out["weights just past w_max"] = (variant("w2", lambda d: {
        **d, "rhonn.W": np.where(np.arange(45).reshape(3, 15) == 7, 1000.5, d["rhonn.W"])}),
        "w_max")

    def negative_variance(d: dict) -> dict:
        p = np.array(d["rhonn.P"], dtype=float)
        p[1, 4, 4] = -1e-3
        return {**d, "rhonn.P": p}

    def asymmetric(d: dict) -> dict:
        p = np.array(d["rhonn.P"], dtype=float)
        p[0, 2, 3] += 1e-3 * np.abs(p).max()
        return {**d, "rhonn.P": p}

    out["negative covariance"] = (variant("negP", negative_variance), "diagonal entry <= 0")
    out["asymmetric covariance"] = (variant("asym", asymmetric), "not symmetric")
    out["trace above trace_max"] = (variant("trace", lambda d: {
        **d, "rhonn.P": np.asarray(d["rhonn.P"]) * (2e3 / np.trace(d["rhonn.P"][0]))}),
        "trace above")
    out["absurd duals"] = (variant("dual", lambda d: {**d, "qp.y": np.full_like(d["qp.y"],
                                                                            1e30)}),
                           "above 1e+12")
    return out


def test_corrupted_or_mismatched_checkpoints_give_a_cold_start_with_a_reason(
        learned, tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned, cfg_hash=HASH, steps=5)
    good = path.read_bytes()
    cold = make_controller("nmpc-rhonn").get_state()
    for name, (blob, words) in _corruptions(good, learned, tmp_path).items():
        path.write_bytes(blob)
        ctrl = make_controller("nmpc-rhonn")
        result = load_checkpoint(path, ctrl, cfg_hash=HASH)
        assert not result.restored, name
        assert words in result.reason and "cold start" in result.reason, (name, result)
        assert states_equal(ctrl.get_state(), cold), name
    # another controller's checkpoint, another format version
    path.write_bytes(good)
    result = load_checkpoint(path, make_controller("lmpc"), cfg_hash=config_hash("lmpc"))
    assert not result.restored and "controller 'nmpc-rhonn'" in result.reason
    assert not load_checkpoint(tmp_path / "absent.npz", make_controller("passive")).restored


def test_a_state_the_controller_rejects_is_undone(learned, tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned, cfg_hash=HASH, steps=5)
    ctrl = make_controller("nmpc-rhonn")
    cold = ctrl.get_state()

    def refuse(d: dict) -> None:
        ctrl.dm_held = 123.0  # a partial restore ...
        raise ValueError("no")  # ... then a failure

    ctrl.set_state = refuse  # type: ignore[method-assign]
    result = load_checkpoint(path, ctrl, cfg_hash=HASH)
    assert not result.restored and "rejected" in result.reason
    assert states_equal(ctrl.get_state(), cold)


def test_manager_saves_every_second_of_controller_time_and_survives_errors(
        learned, tmp_path: Path) -> None:
    msgs: list[str] = []
    mgr = CheckpointManager(tmp_path / "c.npz", learned, HASH, report=msgs.append)
    assert mgr.every_steps == 20  # 1 s at Ts = 50 ms
    saved = [mgr.after_cycle(k % 5 == 0) for k in range(500)]  # 100 MPC steps
    assert sum(saved) == 5 and mgr.saves == 5
    assert read_checkpoint(tmp_path / "c.npz")[0]["steps"] == 100
    bad = CheckpointManager(tmp_path / "no" / "such" / "dir.npz", learned, HASH,
                            every_steps=1, report=msgs.append)
    assert bad.after_cycle(True) is False and bad.save_failures == 1
    assert any("failed" in m for m in msgs)


# ------------------------------------------------------------------- across processes
def _torque_frames(log: Path) -> list[bytes]:
    tid = Codec().messages["WHEEL_TORQUE_CMD"].frame_id
    return [bytes(m.data) for m in can.LogReader(str(log)) if m.arbitration_id == tid]


def _normalised_rms(rms: np.ndarray) -> float:
    """One number: RMS errors scaled by the RHONN's state ranges [30 m/s, 3 m/s, 0.6 rad/s]."""
    return float(np.sqrt(np.sum((rms / np.array([30.0, 3.0, 0.6])) ** 2)))


def test_learned_state_survives_a_controller_process_restart(tmp_path: Path) -> None:
    """Run 1 (step steer, 6 s) learns and checkpoints; run 2 (a step steer 0.2 s after the
    start) restores it in a new controller process. Run 2's bus log is replayed offline
    through a restored and a cold controller: the restored replay reproduces run 2's torque
    frames bit for bit (so it IS the controller that ran), and its one-step model error in
    the first second is far below the cold controller's on the same inputs."""
    ckpt = tmp_path / "learned.npz"
    args = ["--checkpoint", str(ckpt)]
    first = run_and_report(RunSpec(
        scenario="step-steer", controller="nmpc-rhonn", out_dir=tmp_path / "run1",
        duration_s=6.0, controller_extra_args=args, make_plots=False, make_rrd=False))
    assert first.reason == "finished" and first.controller_code == 0
    summary1 = json.loads((tmp_path / "run1" / "controller_summary.json").read_text())
    assert summary1["checkpoint"]["restored"] is False
    assert summary1["checkpoint"]["saves"] >= 6 and summary1["checkpoint"]["save_failures"] == 0
    start = tmp_path / "start_of_run2.npz"
    shutil.copy(ckpt, start)
    assert read_checkpoint(start)[0]["steps"] >= 115

    second = run_and_report(RunSpec(
        scenario="step-steer", controller="nmpc-rhonn", out_dir=tmp_path / "run2",
        duration_s=1.5, params={"start_s": 0.2}, controller_extra_args=args,
        make_plots=False, make_rrd=False))
    assert second.reason == "finished"
    summary2 = json.loads((tmp_path / "run2" / "controller_summary.json").read_text())
    assert summary2["checkpoint"]["restored"] is True, summary2["checkpoint"]
    assert "restored" in (tmp_path / "run2" / "controller.log").read_text()

    log = tmp_path / "run2" / "bus.blf"
    warm = one_step_errors(log, "nmpc-rhonn", checkpoint=start)
    cold = one_step_errors(log, "nmpc-rhonn")
    recorded = _torque_frames(log)
    assert warm.restore is not None and warm.restore.restored
    assert warm.torque_frames == recorded and cold.torque_frames != recorded
    w, c = warm.rms(until_s=1.0), cold.rms(until_s=1.0)
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(c)) and len(warm.errors) >= 19
    ratio = _normalised_rms(w) / _normalised_rms(c)
    print(f"first-second RMS one-step error warm {w} cold {c} "
          f"(vx m/s, vy m/s, r rad/s); normalised ratio {ratio:.3f}")
    # Lockstep, so deterministic: measured 0.191 (docs: 0.19x) and 0.171x on the yaw rate
    # with the "demand" references (0.134 / 0.11x with Algorithm 1 references);
    # bounds = measured + ~15 %.
    assert ratio < 0.22
    assert w[2] < 0.20 * c[2]  # yaw rate, the controlled state
    assert np.all(w < c)
    assert not live_children()


def test_a_corrupted_checkpoint_does_not_stop_the_controller_process(tmp_path: Path) -> None:
    ckpt = tmp_path / "bad.npz"
    ckpt.write_bytes(b"not a checkpoint")
    result = run_and_report(RunSpec(
        scenario="step-steer", controller="nmpc-rhonn", out_dir=tmp_path / "run",
        duration_s=0.5, controller_extra_args=["--checkpoint", str(ckpt)],
        make_plots=False, make_rrd=False))
    assert result.reason == "finished" and result.controller_code == 0
    summary = json.loads((tmp_path / "run" / "controller_summary.json").read_text())
    assert summary["checkpoint"]["restored"] is False
    assert "unreadable" in summary["checkpoint"]["restore_reason"]
    assert summary["cycles_answered"] >= 49
    # the clean stop replaced the bad file with a valid checkpoint of this run
    assert read_checkpoint(ckpt)[0]["steps"] >= 9


def test_a_latched_core_fault_saves_no_checkpoint(tmp_path: Path) -> None:
    """A core that raised may have left its state half-updated: from the latch on the core
    makes no MPC steps (so no periodic save comes due) and the clean stop does not write it;
    the checkpoint on disk is the last one saved before the fault (1 s of controller time =
    20 MPC steps per save)."""
    ckpt = tmp_path / "c.npz"
    result = run_and_report(RunSpec(
        scenario="step-steer", controller="nmpc-rhonn", out_dir=tmp_path / "run",
        duration_s=3.0, faults=["core-exception@1.55"],
        controller_extra_args=["--checkpoint", str(ckpt)], make_plots=False, make_rrd=False))
    assert result.reason == "finished" and result.controller_code == 0
    summary = json.loads((tmp_path / "run" / "controller_summary.json").read_text())
    assert summary["core_exceptions"] == 1
    assert summary["checkpoint"]["saves"] == 1  # at 1 s; none after the fault at 1.55 s
    assert summary["checkpoint"]["blocked_saves"] == 1  # the clean stop
    assert summary["checkpoint"]["block_reason"] == "core fault latched"
    assert read_checkpoint(ckpt)[0]["steps"] == 20


def test_manager_does_not_save_while_blocked(learned, tmp_path: Path) -> None:
    msgs: list[str] = []
    mgr = CheckpointManager(tmp_path / "c.npz", learned, HASH, every_steps=1,
                            report=msgs.append)
    assert mgr.after_cycle(True) is True
    mgr.blocked_by = lambda: "core fault latched"
    assert [mgr.after_cycle(True), mgr.save()] == [False, False]
    assert mgr.saves == 1 and mgr.blocked_saves == 2 and mgr.save_failures == 0
    assert read_checkpoint(tmp_path / "c.npz")[0]["steps"] == 1
    assert sum("not saved" in m for m in msgs) == 1  # reported once, counted every time
    assert mgr.summary()["block_reason"] == "core fault latched"
