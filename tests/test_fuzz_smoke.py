"""CI budget of ``rhonn-bench fuzz`` (the full run is ≥ 1e6 cases): zero findings on every
target, and planted bugs are caught (the fuzzer is not vacuous)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from can_db.codec import Codec
from controller.core.interfaces import ControllerOutputs
from harness.fuzz.cli import SHARES, main, run_fuzz
from harness.fuzz.targets import ControllerTarget, DecoderTarget, Findings, default_params


def test_smoke_budget_finds_nothing_on_any_target() -> None:
    report = run_fuzz(cases=120_000, hypothesis_examples=150, seed=0)
    details = "\n".join(f"{f.target} {f.kind} {f.message} {f.case}\n{f.traceback}"
                        for f in report.findings)
    assert report.total_findings == 0, details
    numpy_targets = {s.target for s in report.stats if s.engine == "numpy"}
    assert numpy_targets == set(SHARES)
    assert all(s.cases > 0 for s in report.stats)
    assert report.cases >= 120_000
    json.dumps(report.to_json())


class _Buggy:
    """A controller with two classic bugs: raises on NaN steering, ignores the power limit."""

    name, ts = "buggy", 0.05

    def __init__(self) -> None:
        self.out = ControllerOutputs()

    def reset(self) -> None: ...

    def step(self, inputs) -> ControllerOutputs:
        if inputs.swa_rad != inputs.swa_rad:
            raise ZeroDivisionError("NaN steering")
        self.out.torques[:] = 450.0 * min(max(inputs.accel_pedal, 0.0), 1.0)
        self.out.delta_m = 0.0
        return self.out

    allocate_only = step


def test_planted_controller_bugs_are_found() -> None:
    target = ControllerTarget("passive", default_params())
    target.ctrl = _Buggy()
    findings = Findings()
    target.run(np.random.default_rng(1), 3000, findings)
    kinds = {f.kind for f in findings.items}
    assert kinds == {"exception", "invariant"}, kinds
    assert any("ZeroDivisionError" in f.traceback for f in findings.items)
    assert any("motor limit" in f.message for f in findings.items)


def test_a_planted_decoder_bug_is_found(monkeypatch: pytest.MonkeyPatch) -> None:
    codec = Codec()
    real = codec.decode

    def broken(fid: int, data: bytes, **kw):
        if len(data) == 3:
            raise IndexError("short frame")
        return real(fid, data, **kw)

    monkeypatch.setattr(codec, "decode", broken)
    findings = Findings()
    DecoderTarget(codec).run(np.random.default_rng(2), 20_000, findings)
    assert findings.counts.get("decoder", 0) > 0
    assert "IndexError" in findings.items[0].message


def test_command_line_writes_a_json_report(tmp_path: Path) -> None:
    out = tmp_path / "fuzz.json"
    assert main(["--cases", "3000", "--hypothesis-examples", "0", "--only",
                 "decoder,monitor,controller:passive", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["findings"] == 0 and data["cases"] >= 3000
    assert {t["target"] for t in data["targets"]} == {"decoder", "monitor",
                                                      "controller:passive"}
