"""The in-process handling screen (harness/tools/handling_screen.py): its variant syntax, and
one screen run as a user runs it, whose table must agree with its own per-run KPIs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from harness.tools.handling_screen import parse_variant

ROOT = Path(__file__).resolve().parents[1]


def test_variant_text_becomes_typed_overrides() -> None:
    name, ov = parse_variant("smooth:handling.jerk_weight=3,kind=demand,handling.envelope=false")
    assert name == "smooth"
    assert ov == {"handling.jerk_weight": 3, "kind": "demand", "handling.envelope": False}


@pytest.mark.parametrize("text", ["noname", ":a=1", "x:", "x:a", "x:=1"])
def test_malformed_variant_is_refused(text: str) -> None:
    with pytest.raises(ValueError):
        parse_variant(text)


def _screen(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "harness.tools.handling_screen", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_screen_table_agrees_with_its_runs_and_sees_the_jerk_weight(tmp_path: Path) -> None:
    out = tmp_path / "runs.json"
    proc = _screen(tmp_path, "--variant", "no-jerk:handling.jerk_weight=0", "--seeds", "1",
                   "--cases", "main job", "--a-deg", "19.1", "--json", str(out), "--jobs", "2")
    assert proc.returncode == 0, proc.stderr
    runs = json.loads(out.read_text())["runs"]
    assert sorted(r["who"] for r in runs) == ["lmpc", "nmpc-mf", "nmpc-rhonn", "no-jerk"]
    kpi = {r["who"]: r for r in runs}
    tv = {w: r["dM_tv_per_s_Nm_per_s"] for w, r in kpi.items()}
    smaller = min(tv["nmpc-mf"], tv["lmpc"])
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| DLC")]
    assert len(rows) == 4
    for line in rows:
        cells = [c.strip() for c in line.strip("|").split("|")]
        who = cells[1]
        assert float(cells[2]) == pytest.approx(tv[who] / 1e3, abs=0.005)
        assert float(cells[3]) == pytest.approx(tv[who] / smaller, abs=0.005)
    # the jerk weight is what keeps the packaged design's ΔM from reversing every period
    assert kpi["nmpc-rhonn"]["dM_chatter_per_s"] < 0.6 * kpi["no-jerk"]["dM_chatter_per_s"]
    assert np.isfinite([r["max_abs_beta_deg"] for r in runs]).all()


def test_bad_arguments_are_one_line_and_exit_2(tmp_path: Path) -> None:
    proc = _screen(tmp_path, "--variant", "broken", "--a-deg", "19.1")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "handling_screen: variant 'broken': expected NAME:KEY=VALUE[,KEY=VALUE...]"]
    proc = _screen(tmp_path, "--cases", "no such case", "--a-deg", "19.1")
    assert proc.returncode == 2 and "no case matches" in proc.stderr
