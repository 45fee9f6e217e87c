"""Where no C compiler exists: the install succeeds without the core and says so in one line,
and the controller process runs the numpy reference, saying so in one line at start."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec
from tests.helpers_proc import live_children

ROOT = Path(__file__).resolve().parents[1]


def test_build_without_a_compiler_skips_the_core_and_says_so(tmp_path: Path) -> None:
    """setup.py's build step with the compiler hidden: exit 0, one line naming the cause,
    no extension module written."""
    env = {**os.environ, "CC": str(tmp_path / "no-such-cc")}
    res = subprocess.run(
        [sys.executable, "setup.py", "build_ext", "--build-lib", str(tmp_path / "lib"),
         "--build-temp", str(tmp_path / "tmp")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("rhonn-tv:")]
    assert len(lines) == 1 and "C core not built" in lines[0]
    assert "numpy reference runs" in lines[0]
    assert not list((tmp_path / "lib").rglob("_rhcore*"))


@pytest.mark.parametrize("hidden", [False, True])
def test_controller_process_says_which_backend_runs(tmp_path: Path, hidden: bool,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A closed loop over the bus with the built core, and with the core made unimportable
    in every process (as on a machine without a compiler): the controller's first log line
    says why the numpy reference runs, its ready line names the backend, the run finishes."""
    if hidden:
        site = tmp_path / "site"
        site.mkdir()
        (site / "sitecustomize.py").write_text(
            "import sys\n"
            "sys.modules['controller.native._rhcore64'] = None\n"
            "sys.modules['controller.native._rhcore32'] = None\n")
        monkeypatch.setenv("PYTHONPATH", str(site))
    out = tmp_path / "run"
    result = run_and_report(RunSpec(scenario="dlc-paper", controller="nmpc-rhonn",
                                       out_dir=out, duration_s=1.0, make_plots=False,
                                       make_rrd=False))
    assert result.reason == "finished", result.metrics
    assert not live_children()
    log = (out / "controller.log").read_text().splitlines()
    summary = json.loads((out / "controller_summary.json").read_text())
    ready = next(ln for ln in log if ln.startswith("ready "))
    before_ready = log[:log.index(ready)]  # the start-up diagnostics (logging, stderr)
    if hidden:
        assert ("WARNING controller.native.backend: controller backend: numpy reference "
                "(the C core is not built") in log[0]
        assert "(lockstep, numpy reference float64, SecOC on (key: " in ready, ready
        assert ready.endswith("; diagnostics: public test secret)"), ready
        assert summary["backend"] == "numpy"
    else:
        assert not any(" WARNING " in ln for ln in before_ready), before_ready
        assert "INFO rhonn-controller: starting controller nmpc-rhonn (C core float64)" \
            in before_ready[0]
        assert "(lockstep, C core float64, SecOC on (key: " in ready, ready
        assert ready.endswith("; diagnostics: public test secret)"), ready
        assert summary["backend"] == "native"
