"""`rhonn-bench deploy`: the parts that need no fresh install (a smoke test against the
running venv with few starts and steps; nothing about time, size or memory is asserted)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from harness.bench.deploy import format_table, main, pip_failure_line

VENV = Path(sys.prefix)


@pytest.mark.skipif(not (VENV / "bin" / "rhonn-controller").exists(),
                    reason="rhonn-controller is not installed in this venv")
def test_existing_venv_start_and_rss_after_steps(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "deploy.json"
    assert main(["--venv", str(VENV), "--controller", "lmpc", "--starts", "1", "--steps", "40",
                 "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert not res["fresh"] and "install" not in res
    assert res["size"]["venv_mb"] > 0 and len(res["size"]["largest"]) == 5
    assert set(res["size"]["forbidden_present"]) == {"numba", "llvmlite"}
    start = res["start"]
    assert start["first_s"] > 0 and len(start["warm_s"]) == 1 and len(start["rss_ready_mb"]) == 2
    imp = res["importtime"]
    assert imp["total_ms"] > 0 and len(imp["top_cumulative"]) == 5
    assert all(m["module"] != "controller.runtime.process" for m in imp["top_cumulative"])
    mem = res["memory"]
    assert mem["mpc_steps"] >= 40 and mem["fallback_cycles"] == 0
    assert 0 < mem["rss_ready_mb"] <= mem["rss_peak_mb"]
    assert mem["rss_final_mb"] <= mem["rss_peak_mb"]
    text = capsys.readouterr().out
    assert "first start → ready" in text and "RSS after 40 MPC steps" in text
    assert text == format_table(res) + "\n"


def test_table_of_a_failed_fresh_install() -> None:
    res = {"controller": "nmpc-rhonn", "venv": "/tmp/x/venv", "fresh": True,
           "install": {"venv_create_s": 3.0, "pip_install_s": 40.0, "pip_cache": False},
           "size": {"venv_mb": 270.0, "site_packages_mb": 269.9, "distributions": 24,
                    "installer_mb": 22.3, "largest": [{"name": "scipy", "mb": 143.0}],
                    "forbidden_present": {"numba": False, "llvmlite": True},
                    "c_core": {"controller.native._rhcore64": "ModuleNotFoundError: x"},
                    "c_core_built": False},
           "error": "rhonn-controller of /tmp/x/venv did not start: boom"}
    text = format_table(res)
    assert "(fresh install)" in text and "pip cache off" in text
    assert "PRESENT: llvmlite" in text and "NOT built: ModuleNotFoundError: x" in text
    assert text.splitlines()[-1].split() == ["FAILED", "rhonn-controller", "of",
                                             "/tmp/x/venv", "did", "not", "start:", "boom"]


def test_a_controller_that_does_not_start_is_exit_1_with_its_reason(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    scripts = {"python": f'#!/bin/sh\nexec "{sys.executable}" "$@"\n',  # the hub runs
               "rhonn-controller": "#!/bin/sh\necho 'rhonn-controller: boom' >&2\nexit 3\n"}
    for name, text in scripts.items():
        (venv / "bin" / name).write_text(text)
        os.chmod(venv / "bin" / name, 0o755)
    assert main(["--venv", str(venv), "--starts", "0"]) == 1
    out = capsys.readouterr().out
    assert out.splitlines()[-1].endswith("did not start: rhonn-controller: boom")


@pytest.mark.parametrize("argv, words", [
    (["--venv", "{tmp}"], "not a venv (no bin/python)"),
    (["--source", "{tmp}"], "no pyproject.toml there"),
])
def test_missing_things_are_one_line_exit_2(argv: list[str], words: str, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err and err.startswith("rhonn-bench deploy:")


def test_pip_without_an_index_is_named_as_such() -> None:
    log = ("Processing /tmp/src\n  WARNING: Retrying (Retry(total=4)) after connection broken "
           "by 'NewConnectionError(...: Failed to establish a new connection: [Errno 101] "
           "Network is unreachable')': /simple/setuptools/\nERROR: Could not find a version "
           "that satisfies the requirement setuptools>=77\n")
    network, line = pip_failure_line(log)
    assert network and line.startswith("pip could not reach a package index")
    network, line = pip_failure_line("ERROR: Failed building wheel for rhonn-tv\n")
    assert not network and line == "pip install failed: ERROR: Failed building wheel for rhonn-tv"
