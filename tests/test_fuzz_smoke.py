"""CI budget of ``rhonn-bench fuzz`` (the full run is ≥ 1e6 cases): zero findings on every
target, and planted bugs are caught (the fuzzer is not vacuous): a controller bug, a decoder
crash, and each planted missing check of the codec and rx monitor (harness/fuzz/planted.py)
against the independent oracles (harness/fuzz/oracle.py, docs/safety/fuzz.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from can_db.codec import Codec
from controller.core.interfaces import ControllerOutputs
from harness.fuzz.cli import SHARES, main, run_fuzz
from harness.fuzz.planted import PLANTED, detect
from harness.fuzz.targets import (
    ControllerTarget,
    DecoderTarget,
    Findings,
    MonitorTarget,
    default_params,
)


def test_smoke_budget_finds_nothing_on_any_target() -> None:
    report = run_fuzz(cases=40_000, hypothesis_examples=80, seed=0)
    details = "\n".join(f"{f.target} {f.kind} {f.message} {f.case}\n{f.traceback}"
                        for f in report.findings)
    assert report.total_findings == 0, details
    numpy_targets = {s.target for s in report.stats if s.engine == "numpy"}
    assert numpy_targets == set(SHARES)
    assert all(s.cases > 0 for s in report.stats)
    assert report.cases >= 40_000
    json.dumps(report.to_json())


# (bug, target, cases, mismatch kinds that must appear): each planted missing check is
# reported by the oracle-checked target meant for it, within a small budget
PLANTED_CASES = [
    ("no_crc", "decoder", 2_000, {"missed:bad_crc"}),
    ("no_crc", "monitor", 2_000, {"missed:bad_crc"}),
    ("no_crc", "hypothesis:decoder", 100, {"missed:bad_crc"}),
    ("no_range", "decoder", 2_000, {"missed:out_of_range"}),
    ("no_range", "monitor", 2_000, {"missed:out_of_range"}),
    ("no_range", "hypothesis:decoder", 150, {"missed:out_of_range"}),
    ("timeout_5_cycles", "monitor", 2_000, {"missed:timeout"}),
    ("timeout_5_cycles", "hypothesis:monitor", 100, {"missed:timeout"}),
    ("no_counter", "monitor", 2_000, {"missed:counter_frozen", "missed:wrong_sequence",
                                      "uncounted:counter_jump"}),
    ("no_window", "monitor", 2_000, {"missed:wrong_sequence"}),
    ("no_window", "hypothesis:monitor", 150, {"missed:wrong_sequence"}),
]


@pytest.mark.parametrize(("bug", "target", "cases", "kinds"), PLANTED_CASES,
                         ids=[f"{b}-{t}" for b, t, _, _ in PLANTED_CASES])
def test_a_planted_missing_check_is_caught(bug: str, target: str, cases: int,
                                           kinds: set[str]) -> None:
    found = detect(bug, target, cases, seed=0)
    assert kinds <= set(found.by_kind), found.by_kind
    assert found.first_at is not None and found.first_at <= cases


def test_every_planted_bug_is_in_the_table_and_the_code_as_it_is_passes() -> None:
    assert {b for b, *_ in PLANTED_CASES} == set(PLANTED)
    for target, cases in (("decoder", 5_000), ("monitor", 5_000),
                          ("hypothesis:monitor", 60)):
        found = detect(None, target, cases, seed=1)
        assert found.cases == cases and found.mismatches == 0, found.by_kind


def test_a_mutant_is_gone_once_its_context_closes() -> None:
    with PLANTED["no_crc"]():
        assert detect(None, "decoder", 500).mismatches > 0  # the codec built inside
    assert detect(None, "decoder", 500).mismatches == 0


def test_the_oracle_targets_never_use_the_codec_to_make_frames(
        monkeypatch: pytest.MonkeyPatch) -> None:
    codec = Codec()

    def no(*args: object, **kwargs: object) -> None:
        raise AssertionError("the codec under test made a frame")

    for name in ("encode", "message"):
        monkeypatch.setattr(codec, name, no)
    for name in ("seal", "e2e_crc"):  # the E2E helpers, where the codec has them
        monkeypatch.setattr(codec, name, no, raising=False)
    findings = Findings()
    DecoderTarget(codec).run(np.random.default_rng(3), 1_000, findings)
    MonitorTarget(codec).run(np.random.default_rng(3), 1_000, findings)
    assert findings.counts == {}, findings.items[:3]
    assert findings.cases == {"decoder": 1_000, "monitor": 1_000}


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
    DecoderTarget(codec).run(np.random.default_rng(2), 5_000, findings)
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
    assert all(t["by_kind"] == {} for t in data["targets"])


def test_command_line_planted_matrix(tmp_path: Path) -> None:
    out = tmp_path / "planted.json"
    assert main(["--planted", "--cases", "1500", "--hypothesis-examples", "0",
                 "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["not_caught"] == []
    caught = {d["bug"] for d in data["detections"] if d["mismatches"] > 0}
    assert caught == set(PLANTED)
    assert {d["target"] for d in data["detections"]} == {"decoder", "monitor"}
