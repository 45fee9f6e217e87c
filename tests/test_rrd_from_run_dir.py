"""`rhonn-harness rrd RUN_DIR`: the rerun recording of a run directory that has none, written
by the installed command in its own process from a real run's files (a run with --no-rrd),
the same recording `run` writes; an interrupted run's recording carries its partial label."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from harness.viz.rerun_log import read_scalars

EXE = Path(sys.executable).with_name("rhonn-harness")
CMD = [str(EXE)] if EXE.exists() else [sys.executable, "-m", "harness.cli"]


def _harness(*args: str, timeout: float = 180.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CMD, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1 s lockstep run without its recording (and without plots)."""
    out = tmp_path_factory.mktemp("rrd") / "run"
    proc = _harness("run", "dlc-paper", "--controller", "passive", "--duration", "1",
                    "--no-plots", "--no-rrd", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert not (out / "run.rrd").exists()
    meta = json.loads((out / "metrics.json").read_text())  # what the recording is made from
    assert (meta["controller_config"], meta["controller_overrides"], meta["duration_s"]) == (
        None, {}, 1.0)
    return out


def _summary(path: Path) -> str:
    return "\n".join(t[0] for c in RrdReader(str(path)).stream() if c.entity_path == "/summary"
                     for t in c.to_record_batch().column("TextDocument:text").to_pylist())


def test_rrd_writes_the_recording_of_a_run_directory(run_dir: Path) -> None:
    proc = _harness("rrd", str(run_dir))
    assert proc.returncode == 0, proc.stderr
    path = run_dir / "run.rrd"
    assert proc.stdout.splitlines() == [
        f"recording of {run_dir}/ written: {path}",
        f"open the timeline: rerun analytics disable && rerun {path}"]
    reader = RrdReader(str(path))
    assert [r.recording_id for r in reader.recordings()] == ["dlc-paper-passive-mu0.35-v65-s0"]
    assert len(reader.blueprints()) == 1
    sc = read_scalars(path)
    truth = np.genfromtxt(run_dir / "truth.csv", delimiter=",", names=True)
    assert truth.size > 90  # 1 s: a row per 10 ms cycle
    assert sc["/plant/beta"]["cycle"].tolist() == truth["cycle"].astype(int).tolist()
    np.testing.assert_allclose(sc["/plant/beta"]["values"], np.degrees(truth["beta_rad"]))
    assert "PARTIAL" not in _summary(path)
    assert sorted(p.name for p in run_dir.iterdir() if p.name.endswith(".part")) == []


def test_rrd_to_another_file_and_of_an_interrupted_run(run_dir: Path, tmp_path: Path) -> None:
    """--out FILE; an interrupted run (its metrics.json says so) is labelled as partial in
    the recording and in the command's line."""
    cut = tmp_path / "cut"
    shutil.copytree(run_dir, cut, ignore=shutil.ignore_patterns("run.rrd"))
    meta = json.loads((cut / "metrics.json").read_text())
    meta.update(interrupted=True, reason="interrupted", sim_time_reached_s=0.5)
    lines = (cut / "truth.csv").read_text().splitlines(keepends=True)
    (cut / "truth.csv").write_text("".join(lines[:52]))  # the header and 0.00 .. 0.50 s
    (cut / "metrics.json").write_text(json.dumps(meta))
    target = tmp_path / "shots" / "cut.rrd"
    proc = _harness("rrd", str(cut), "--out", str(target))
    assert proc.returncode == 0, proc.stderr
    assert "(PARTIAL RUN — interrupted at 0.5 s of 1.0 s)" in proc.stdout.splitlines()[0]
    assert target.is_file() and not (cut / "run.rrd").exists()
    assert "PARTIAL RUN — interrupted at 0.5 s of 1.0 s" in _summary(target)
    assert json.loads((cut / "metrics.json").read_text()) == meta  # left as it was


def test_rrd_of_a_directory_without_a_run_is_one_line_exit_2(tmp_path: Path) -> None:
    """The installed command: a missing directory and one without truth.csv."""
    for arg, phrase in ((tmp_path / "missing", "no such directory"),
                        (tmp_path, "no truth.csv")):
        proc = _harness("rrd", str(arg), timeout=120.0)
        assert proc.returncode == 2, proc.stderr
        assert proc.stdout == ""
        lines = proc.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"rhonn-harness rrd: error: {arg}: "
                                                       f"{phrase}"), proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_spec_read_back_from_metrics(tmp_path: Path) -> None:
    """What the analysis of a run directory reads from its metrics.json: a scenario file by
    its absolute path (the run may have named it relative to another directory), the
    controller's configuration, the duration (older directories: the planned one)."""
    from harness.run.runner import spec_of_run

    meta = {"scenario": "mine.toml", "scenario_file": "/abs/mine.toml", "controller": "lmpc",
            "mode": "realtime", "mu": 0.5, "speed_kmh": None, "seed": 3,
            "params": {"amplitude_deg": 90}, "faults": ["loss:5%"],
            "controller_config": "/abs/c.toml", "controller_overrides": {"mpc.horizon": 6},
            "duration_s": 2.0, "duration_planned_s": 2.0, "bus_log": "bus.mf4"}
    spec = spec_of_run(tmp_path, meta)
    assert (spec.scenario, spec.controller, spec.mode, spec.mu, spec.speed_kmh, spec.seed) == (
        "/abs/mine.toml", "lmpc", "realtime", 0.5, None, 3)
    assert dict(spec.params) == {"amplitude_deg": 90} and spec.faults == ("loss:5%",)
    assert spec.controller_config == "/abs/c.toml"
    assert dict(spec.controller_overrides) == {"mpc.horizon": 6}
    assert (spec.duration_s, spec.log_format, spec.out_dir) == (2.0, "mf4", tmp_path)
    old = {k: v for k, v in meta.items()
           if k not in ("scenario_file", "controller_config", "controller_overrides",
                        "duration_s")}
    spec = spec_of_run(tmp_path, old)
    assert (spec.scenario, spec.controller_config, spec.duration_s) == ("mine.toml", None, 2.0)
