"""`rhonn-bench mpc-update`: the MPC update inside the controller process, per CPU layout
(a smoke test across processes: one short run per layout; nothing about speed is
asserted)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from can_db.process.cpu import allowed_cpus
from harness.bench.mpc_update import main


def test_one_run_per_layout_reads_the_controllers_own_timing(tmp_path: Path) -> None:
    layouts = "shared,own-cpu" if len(allowed_cpus()) >= 2 else "shared"
    out = tmp_path / "mpc_update.json"
    assert main(["--controllers", "lmpc", "--layouts", layouts, "--runs", "1",
                 "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert set(rows) == {f"lmpc {x}" for x in layouts.split(",")}
    for r in rows.values():
        # dlc-paper: 11.28 s at one MPC update per 50 ms, the first included
        assert r["updates"] >= 200 and r["runs"] == 1
        m = r["update_mean_us_per_run"][0]
        assert math.isfinite(m) and 0.0 < r["update_p50_us"] <= r["update_p99_us"]
        assert r["update_p99_us"] <= r["update_max_us"] and r["hold_p50_us"] > 0.0
        assert r["speed_x"][0] > 0.0


@pytest.mark.parametrize("argv, words", [
    (["--layouts", "fastest"], "unknown controller or layout ['fastest']"),
    (["--controllers", "passive"], "unknown controller or layout ['passive']"),
])
def test_bad_choices_are_one_line_errors(argv: list[str], words: str,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and words in capsys.readouterr().err
