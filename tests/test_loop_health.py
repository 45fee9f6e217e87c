"""Security on by default and loud when it fails; a run's end says how well the loop held.

Cross-process: the controller and plant programs authenticate by default and say so in their
ready lines; a run whose controller has the wrong SecOC key, or whose processes disagree on
SecOC, ends ``degraded`` with the reason, the first rejection of a kind is logged with its
reason, and the KPI table's loop row says so. Unit: the limits of harness/analysis/
loop_health.py per mode, and the exit code of ``rhonn-harness run`` for a degraded run.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from can_db.transport.hub import LocalHub
from controller.runtime.process import stopped_line
from harness import cli
from harness.analysis.loop_health import (
    FALLBACK_SHARE_MAX,
    JITTER_P99_MAX_US,
    apply_loop_verdict,
    loop_cell,
)
from harness.report.run_report import run_and_report
from harness.run.runner import RunResult
from harness.run.spec import RunSpec
from tests.helpers_proc import interrupt_and_wait, spawn
from tests.test_secoc_unit import assert_frames_add_up

WRONG_KEYS = ('ctrl_to_plant = "00112233445566778899aabbccddeeff"\n'
              'plant_to_ctrl = "ffeeddccbbaa99887766554433221100"\n')


def _run(out: Path, **kw: Any) -> RunResult:
    return run_and_report(RunSpec(scenario="dlc-paper", controller="passive", out_dir=out,
                                  duration_s=1.0, secoc_keys="ci-test-key", make_plots=False,
                                  make_rrd=False, **kw))


def _start(err: Path, *args: str) -> subprocess.Popen[str]:
    with open(err, "w") as f:
        return spawn(*args, stdout=subprocess.PIPE, stderr=f,
                     env={k: v for k, v in os.environ.items()
                          if not k.startswith("RHONN_SECOC_KEY")})


def _ready_line(proc: subprocess.Popen[str], timeout_s: float = 90.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("ready"):
            return line.strip()
        if not line and proc.poll() is not None:
            raise AssertionError(f"exited with {proc.returncode}")
    raise AssertionError("not ready")


def test_controller_and_plant_authenticate_by_default_and_say_so(tmp_path: Path) -> None:
    """No SecOC option at all: both programs run SecOC with the public test key (no key
    variables set), say so in their ready lines, and every cycle is commanded."""
    summary = tmp_path / "plant.json"
    with LocalHub() as hub:
        ctrl = _start(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                      hub.spec, "--controller", "passive")
        plant = None
        try:
            ctrl_ready = _ready_line(ctrl)
            plant = _start(tmp_path / "plant.err", "-m", "plant_sim.process", "--bus",
                           hub.spec, "--scenario", "dlc-paper", "--duration", "0.5",
                           "--summary", str(summary), "--secoc-state", str(tmp_path / "trip"))
            plant_ready = _ready_line(plant)
            assert plant.wait(120) == 0
            assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
        finally:
            for proc in (plant, ctrl):
                if proc is not None and proc.poll() is None:
                    proc.kill()
    assert ctrl_ready.endswith("SecOC on (key: public test key); "
                               "diagnostics: public test secret)"), ctrl_ready
    assert plant_ready.endswith("SecOC on (key: public test key))"), plant_ready
    stats = json.loads(summary.read_text())
    assert stats["secoc"]["enabled"] and stats["fallback_cycles"] == 0, stats
    assert stats["secoc"]["accepted"]["WHEEL_TORQUE_CMD"] >= stats["cycles"] - 1


def test_no_secoc_says_so_and_refuses_keys(tmp_path: Path) -> None:
    """--no-secoc is stated in the ready line; keys given with it are a usage error."""
    with LocalHub() as hub:
        ctrl = _start(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                      hub.spec, "--controller", "passive", "--no-secoc")
        try:
            assert "SecOC off; diagnostics: " in _ready_line(ctrl)
            assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
        finally:
            if ctrl.poll() is None:
                ctrl.kill()
    for module, what in (("controller.runtime.process", "--controller=passive"),
                         ("plant_sim.process", "--scenario=dlc-paper")):
        proc = spawn("-m", module, "--bus", "local:x", what, "--no-secoc", "--secoc-keys",
                     "ci-test-key", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, err
        assert "--secoc-keys is given with --no-secoc" in err


def test_wrong_controller_key_ends_degraded_with_the_reason(tmp_path: Path) -> None:
    """A well-formed wrong key on the controller: every SYNC fails its MAC. The first
    rejection is logged with its reason, the run ends degraded (not finished), and the
    table's loop row says so."""
    keys = tmp_path / "keys.toml"
    keys.write_text(WRONG_KEYS)
    keys.chmod(0o600)
    result = _run(tmp_path / "run", controller_extra_args=("--secoc-keys", str(keys)))
    assert result.reason == "degraded", result.metrics.get("loop")
    because = " | ".join(result.metrics["degraded_because"])
    assert "controller rejected 100% of the authenticated frames (bad_mac" in because
    assert "the plant fell back in 100% of its cycles" in because
    log = (tmp_path / "run" / "controller.log").read_text()
    assert "SecOC on (key: file)" in log
    assert log.count("first rejected SYNC frame (bad_mac): the MAC does not verify") == 1
    assert loop_cell(result.metrics) == "DEGRADED"
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["reason"] == "degraded" and saved["loop"]["held"] is False


def test_secoc_on_one_side_only_ends_degraded(tmp_path: Path) -> None:
    """The plant authenticates, the controller does not: the plant rejects every command
    as unauthenticated and falls back every cycle; the run says both."""
    result = _run(tmp_path / "run", secoc=False, plant_extra_args=("--secoc",))
    assert result.reason == "degraded"
    because = " | ".join(result.metrics["degraded_because"])
    assert "SecOC is on in one process only" in because
    assert "plant rejected 100% of the authenticated frames (unauthenticated" in because
    assert "first rejected WHEEL_TORQUE_CMD frame (unauthenticated)" in \
        (tmp_path / "run" / "plant.log").read_text()
    # the controller without SecOC says so too: it sees the plant's authenticators
    log = (tmp_path / "run" / "controller.log").read_text()
    assert log.count("SecOC is off here (--no-secoc) but the plant authenticates its "
                     "frames") == 1, log
    ctrl = result.metrics["controller_summary"]
    cycles = result.metrics["plant_summary"]["cycles"]
    # five authenticators a cycle (SYNC and the four driver and sensor frames)
    assert ctrl["secoc"]["authenticators_ignored"] >= 5 * (cycles - 1), ctrl["secoc"]
    assert "SecOC off, but " in stopped_line(ctrl, None)


def test_stopped_line_names_ignored_authenticators_only_when_there_were_some() -> None:
    base = {"controller": "passive", "backend": "native", "cycles_answered": 3,
            "rejections": {}, "core_exceptions": 0}
    quiet = stopped_line({**base, "secoc": {"enabled": False, "authenticators_ignored": 0}},
                         None)
    assert "SecOC off;" in quiet and "authenticators" not in quiet
    loud = stopped_line({**base, "secoc": {"enabled": False, "authenticators_ignored": 15}},
                        "s.json")
    assert ("SecOC off, but 15 authenticators of a plant with SecOC seen (it rejects these "
            "answers); whole summary in s.json") in loud


def _metrics(mode: str, **kw: Any) -> dict[str, Any]:
    on = {"enabled": True, "accepted": {"SYNC": 1000}, "rejected": {}}
    m: dict[str, Any] = {"reason": "finished", "mode": mode,
                         "plant_summary": {"cycles": 1000, "fallback_cycles": 0, "secoc": on},
                         "controller_summary": {"secoc": on},
                         "deadline_misses": 0, "period_jitter_us_p99": 100.0}
    m.update(kw)
    return m


def test_realtime_limits_degrade_a_realtime_run_only() -> None:
    m = _metrics("realtime", period_jitter_us_p99=JITTER_P99_MAX_US + 1, deadline_misses=120)
    apply_loop_verdict(m, faults_injected=False)
    assert m["reason"] == "degraded"
    assert any("period jitter" in p for p in m["degraded_because"])
    assert any("120 deadline misses" in p for p in m["degraded_because"])
    lock = _metrics("lockstep", period_jitter_us_p99=None, deadline_misses=120)
    apply_loop_verdict(lock, faults_injected=False)
    assert lock["reason"] == "finished" and lock["loop"]["held"]


def test_fallback_share_limit_and_injected_faults() -> None:
    cycles = 1000
    at_limit = _metrics("lockstep")
    at_limit["plant_summary"]["fallback_cycles"] = int(FALLBACK_SHARE_MAX * cycles)
    apply_loop_verdict(at_limit, faults_injected=False)
    assert at_limit["reason"] == "finished"
    over = _metrics("lockstep")
    over["plant_summary"]["fallback_cycles"] = int(FALLBACK_SHARE_MAX * cycles) + 1
    faulted = json.loads(json.dumps(over))
    apply_loop_verdict(over, faults_injected=False)
    assert over["reason"] == "degraded"
    apply_loop_verdict(faulted, faults_injected=True)  # a fault campaign: expected
    assert faulted["reason"] == "finished" and loop_cell(faulted) == "faulted (expected)"


def test_a_degraded_run_exits_4(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    metrics = _metrics("realtime", reason="degraded", degraded_because=["period jitter x"])

    def fake(spec: RunSpec, *a: Any, **k: Any) -> RunResult:
        return RunResult(tmp_path, metrics, "degraded", 0, 0)

    monkeypatch.setattr(cli, "run_and_report", fake)
    code = cli.main(["run", "dlc-paper", "--controller", "passive", "--out",
                     str(tmp_path / "o"), "--mode", "realtime"])
    assert code == cli.EXIT_DEGRADED == 4
    err = capsys.readouterr().err
    assert "degraded: period jitter x" in err


def test_plant_alone_without_an_authenticating_controller_says_degraded(
        tmp_path: Path) -> None:
    """A one-shot plant whose controller uses other SecOC keys: no command is ever accepted.
    The plant warns once when its fallback share passes the harness's limit, and ends with
    the reason and exit code 4 instead of ``finished``, exit 0; the controller logs its first
    rejected SYNC."""
    keys = tmp_path / "keys.toml"
    keys.write_text(WRONG_KEYS)
    keys.chmod(0o600)
    with LocalHub() as hub:
        ctrl = _start(tmp_path / "ctrl.err", "-m", "controller.runtime.process", "--bus",
                      hub.spec, "--controller", "passive", "--secoc-keys", str(keys),
                      "--summary", str(tmp_path / "ctrl.json"))
        plant = None
        try:
            _ready_line(ctrl)
            plant = _start(tmp_path / "plant.err", "-m", "plant_sim.process", "--bus",
                           hub.spec, "--scenario", "dlc-paper", "--duration", "1",
                           "--wait-ms", "20", "--secoc-state", str(tmp_path / "trip"))
            out, _ = plant.communicate(timeout=120)
            assert interrupt_and_wait(ctrl, 30, tmp_path / "ctrl.err") == 0
            ctrl_out = ctrl.stdout.read()
        finally:
            for proc in (plant, ctrl):
                if proc is not None and proc.poll() is None:
                    proc.kill()
    assert plant.returncode == 4, out
    # the controller's last line is one a person reads: what it ran, what it rejected and
    # where the whole summary is (no JSON dump on stdout)
    last = ctrl_out.strip().splitlines()[-1]
    assert last.startswith("stopped: passive (") and "{" not in last, last
    # every SYNC fails its MAC; how many are checked before a loaded controller pushes held
    # authenticators out unchecked depends on the load, so the count is not fixed here
    assert re.search(r"SecOC on, rejected bad_mac [1-9]\d*", last), last
    summary = json.loads((tmp_path / "ctrl.json").read_text())
    assert summary["cycles_answered"] == 0 and not summary["secoc"]["accepted"].get("SYNC")
    assert last.endswith(f"whole summary in {tmp_path / 'ctrl.json'}"), last
    assert "stopped: finished after 100 cycles, 100 fallback cycles" in out
    err = (tmp_path / "plant.err").read_text()
    assert err.count("WARNING rhonn-plant: the plant fell back in 100% of its cycles "
                     "(50 of 50; limit 2%) so far") == 1, err
    assert err.rstrip().endswith(
        "rhonn-plant: degraded: the plant fell back in 100% of its cycles (100 of 100; "
        f"limit {FALLBACK_SHARE_MAX:.0%}): no torque command accepted: no controller answers "
        "on this bus, or it uses other SecOC keys (its log then says 'first rejected SYNC "
        "frame (bad_mac)'), or SecOC is on in one process only"), err
    assert "first rejected SYNC frame (bad_mac)" in (tmp_path / "ctrl.err").read_text()
    # the controller's SecOC counters add up: each SYNC it read is one bad_mac authenticator
    # and one data frame (unauthenticated or still pending), nothing counted twice. How many of
    # the plant's 100 it read before the interrupt depends on the load (the plant, waiting
    # 20 ms for answers that never come, can finish ahead of a loaded controller: 86 once)
    sec = json.loads((tmp_path / "ctrl.json").read_text())["secoc"]
    received = sec["received"]["SYNC"]
    assert 0 < received <= 100
    assert received == sec["rejected_by_frame"]["SYNC"]["bad_mac"]
    assert_frames_add_up(sec)


def test_half_set_key_variables_are_refused_naming_the_missing_one() -> None:
    """One RHONN_SECOC_KEY_* variable without the other is a mistake: each program refuses
    to start (one line, exit 2) instead of using the public test key."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RHONN_SECOC_KEY")}
    env["RHONN_SECOC_KEY_CTRL_TO_PLANT"] = "00112233445566778899aabbccddeeff"
    for module, what in (("controller.runtime.process", "--controller=passive"),
                         ("plant_sim.process", "--scenario=dlc-paper")):
        proc = spawn("-m", module, "--bus", "local:half_set_keys", what,
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, (out, err)
        assert "SecOC key variable(s) not set: RHONN_SECOC_KEY_PLANT_TO_CTRL (set both" in err
        assert err.count("error") == 1 and "ready" not in out, err
