"""Time limits that follow the machine: the plant's lockstep wait and the start limits of
the local hub and the websocket bus server are options, and each reaches what it limits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from can_db.transport.bus import resolve_bus
from can_db.transport.hub import LocalHub, LocalHubError
from can_db.transport.server import BusServer, BusServerError
from harness.cli import main as harness_main
from harness.run.hil_bench import plant_run_args
from harness.run.spec import RunSpec

TOO_SHORT_S = 1e-4  # no Python child process is up within 0.1 ms


def test_hub_start_limit_is_its_option_and_a_miss_says_so() -> None:
    with pytest.raises(LocalHubError, match=r"no ready line within 0\.0001 s"):
        LocalHub(start_timeout_s=TOO_SHORT_S).start()
    hub = LocalHub(start_timeout_s=120.0).start()  # the same hub with time to come up
    try:
        assert hub.alive()
        hub.restart()  # a restart keeps the hub's limit
        assert hub.alive() and hub.start_timeout_s == 120.0
    finally:
        hub.stop()


def test_bus_server_start_limit_is_its_option() -> None:
    with pytest.raises(BusServerError, match=r"within 0\.0001 s"):
        BusServer(start_timeout_s=TOO_SHORT_S).start()


def test_resolve_bus_passes_the_start_limit_to_the_hub_it_starts() -> None:
    with pytest.raises((LocalHubError, BusServerError)):
        resolve_bus("auto", start_timeout_s=TOO_SHORT_S)
    spec, hub = resolve_bus("auto", start_timeout_s=120.0)
    try:
        assert hub is None or hub.start_timeout_s == 120.0
        assert spec.startswith(("local:", "socketcan:", "remote:"))
    finally:
        if hub is not None:
            hub.stop()


def test_lockstep_wait_reaches_the_plant_command_line(tmp_path: Path) -> None:
    spec = RunSpec("dlc-paper", "passive", out_dir=tmp_path, lockstep_wait_ms=1500.0)
    args = plant_run_args(spec, tmp_path, [])
    assert args[args.index("--wait-ms") + 1] == "1500.0"
    assert "--wait-ms" not in plant_run_args(RunSpec("dlc-paper", "passive"), tmp_path, [])


@pytest.mark.parametrize("option,value", [("--lockstep-wait-ms", "0"),
                                          ("--lockstep-wait-ms", "-5"),
                                          ("--bus-start-timeout", "0")])
def test_bad_limits_are_refused_in_one_line(option: str, value: str, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        harness_main(["run", "dlc-paper", "--controller", "passive", option, value,
                      "--out", str(tmp_path / "o")])
    code = exit_.value.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and option in err
    assert not (tmp_path / "o").exists()


def test_a_run_with_a_tiny_lockstep_wait_times_out_in_the_plant(tmp_path: Path) -> None:
    """Across processes: the harness's option is the wait the plant process uses. With a
    wait far below any controller's turnaround the plant times out and falls back, and the
    run ends degraded; with the default it does not (a fallback-free run is what the longer
    wait buys a slow machine)."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "run", "dlc-paper", "--controller", "passive",
         "--duration", "0.3", "--no-plots", "--no-rrd", "--lockstep-wait-ms", "0.001",
         "--bus-start-timeout", "120", "--out", str(out)],
        capture_output=True, text=True, timeout=600)
    # a plant that falls back in every cycle: the run ends degraded (exit 4) and says why
    assert proc.returncode == 4, proc.stderr[-2000:]
    assert "degraded: the plant fell back in" in proc.stderr
    summary = json.loads((out / "plant_summary.json").read_text())
    assert summary["lockstep_timeouts"] > 0
