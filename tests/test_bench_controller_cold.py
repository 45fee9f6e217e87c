"""`rhonn-bench controller --gap-ms --evict-mb`: cold steps run and are recorded as such
(a smoke test: nothing about speed is asserted)."""

from __future__ import annotations

import json
from pathlib import Path

from harness.bench.controller_step import main


def test_cold_options_run_every_controller_and_record_the_settings(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    assert main(["--steps", "20", "--warmup", "2", "--precision", "float64", "--gap-ms", "1",
                 "--evict-mb", "1", "--json", str(out)]) == 0
    rows = [r for r in json.loads(out.read_text()) if "p50_us" in r]
    assert {r["name"] for r in rows} >= {"nmpc-rhonn", "nmpc-mf", "lmpc", "passive"}
    for r in rows:
        assert r["gap_ms"] == 1.0 and r["evict_mb"] == 1 and r["steps"] == 20
        assert 0.0 < r["p50_us"] <= r["p99_us"] <= r["max_us"]
    rhonn = next(r for r in rows if r["name"] == "nmpc-rhonn")
    assert rhonn["backend"] in ("native", "numpy")
    if rhonn["backend"] == "numpy":
        assert rhonn["parts"]  # the per-part run ran with the same settings


def test_the_numpy_reference_is_timed_per_part(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    assert main(["--steps", "20", "--warmup", "2", "--precision", "float64",
                 "--backend", "numpy", "--json", str(out)]) == 0
    rows = [r for r in json.loads(out.read_text()) if "p50_us" in r]
    assert {r["backend"] for r in rows} == {"numpy"}
    rhonn = next(r for r in rows if r["name"] == "nmpc-rhonn")
    assert set(rhonn["parts"]) == {"references", "ekf", "linearise", "qp", "allocation",
                                   "other"}
