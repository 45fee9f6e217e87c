"""The paper study's campaign files (paper.toml, paper-quick.toml: the runs of
`rhonn-harness paper`), the ``exclusive`` matrix key, and the campaign runner's order for it: on a
real 2-worker LocalCluster with a stand-in task (no bus), exclusive runs start only after every
other run (study runs included) has ended, one at a time, in file order."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from harness.campaign import runner as campaign_runner
from harness.campaign.engine import EngineConfig
from harness.campaign.runner import CampaignRunner
from harness.campaign.spec import CampaignError, RunSpec, load_campaign, parse_campaign
from harness.campaign.task import base_row
from harness.paper.study import campaign_file

ALL = ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive")
# group → (controllers, scenario, speed km/h, duration s, post steps, rrd) of the full study
FULL = {
    "fidelity-high-mu": (("passive",), "dlc-paper-high-mu", 65.0, None, ("fidelity",), False),
    "fidelity-low-mu": (("passive",), "dlc-paper", 50.0, None, ("fidelity",), False),
    "dlc-nmpc-rhonn": (("nmpc-rhonn",), "dlc-paper", 65.0, None,
                       ("timing", "diag", "fidelity"), True),
    "dlc": (("nmpc-mf", "lmpc"), "dlc-paper", 65.0, None, ("timing", "diag"), True),
    "dlc-passive": (("passive",), "dlc-paper", 65.0, None, ("timing", "diag", "fidelity"), True),
    "curve": (ALL, "slippery-curve", 85.0, None, ("timing", "diag"), True),
}
QUICK = {
    "fidelity-high-mu": (("passive",), "dlc-paper-high-mu", 65.0, 6.0, ("fidelity",), False),
    "fidelity-low-mu": (("passive",), "dlc-paper", 50.0, 6.0, ("fidelity",), False),
    "dlc-nmpc-rhonn": (("nmpc-rhonn",), "dlc-paper", 65.0, None,
                       ("timing", "diag", "fidelity"), False),
    "dlc-passive": (("passive",), "dlc-paper", 65.0, None, ("timing", "diag", "fidelity"),
                    False),
    "curve": (("nmpc-rhonn",), "slippery-curve", 85.0, 8.0, ("timing", "diag"), False),
}
TABLE5 = ("dlc-nmpc-rhonn", "dlc", "dlc-passive", "curve")


@pytest.mark.parametrize(("quick", "expected"), [(False, FULL), (True, QUICK)])
def test_paper_files_hold_the_paper_runs(quick: bool,
                                         expected: dict[str, tuple[Any, ...]]) -> None:
    c = load_campaign(campaign_file(quick))
    got: dict[str, list[RunSpec]] = {}
    for r in c.runs:
        got.setdefault(r.group, []).append(r)
    assert list(got) == list(expected)  # file order = the order the Table 5 runs go in
    for group, (ctrls, scen, v, dur, post, rrd) in expected.items():
        runs = got[group]
        assert tuple(r.controller for r in runs) == ctrls, group
        for r in runs:
            assert (r.scenario, r.speed_kmh, r.duration_s, r.post, r.mu, r.seed) == (
                scen, v, dur, post, None, 0), group
            assert r.make_plots and r.make_rrd is rrd, group
            assert (r.key() in c.exclusive) is (group in TABLE5), group
    assert len(c.exclusive) == sum(len(got[g]) for g in TABLE5 if g in got)
    # the fidelity post step's figure title names the run
    titles = {r.group: dict(r.info).get("title", "") for r in c.runs if "fidelity" in r.post}
    assert "passive car on dlc-paper-high-mu (μ 0.7, 65 km/h)" in titles["fidelity-high-mu"]
    assert "nmpc-rhonn on dlc-paper μ 0.35 65 km/h" in titles["dlc-nmpc-rhonn"]
    studies = {d.name: d for d in c.studies}
    assert set(studies) == {"vmax", "fmvss"}
    vm, fm = studies["vmax"], studies["fmvss"]
    assert vm.kind == "vmax" and fm.kind == "fmvss126"
    if quick:
        assert vm.controllers == ("nmpc-rhonn", "passive") and fm.controllers == ("nmpc-rhonn",)
        assert (vm.options["bracket_kmh"], vm.options["resolution_kmh"],
                vm.options["verify_offsets_kmh"]) == ([40.0, 80.0], 20.0, [])
        assert fm.options == {"directions": ["left"], "amplitude_factors": [1.5],
                              "sis_duration_s": 5.0}
    else:
        assert vm.controllers == ALL and fm.controllers == ALL
        assert (vm.options["bracket_kmh"], vm.options["resolution_kmh"],
                vm.options["verify_offsets_kmh"]) == ([30.0, 90.0], 0.5, [2.0, 5.0])
        assert fm.options == {"directions": ["left", "right"]}  # 1.5A … 6.5A, full length


def test_exclusive_follows_seeds_and_must_be_a_bool() -> None:
    c = load_campaign(campaign_file(False), seeds=[0, 1, 2])
    assert len(c.runs) == 30 and len(c.exclusive) == 24
    assert {r.seed for r in c.runs if r.key() in c.exclusive} == {0, 1, 2}
    with pytest.raises(CampaignError, match="exclusive: expected true or false"):
        parse_campaign('[[matrix]]\nscenarios = ["dlc-paper"]\ncontrollers = ["passive"]\n'
                       'exclusive = "yes"\n')


# ---------------------------------------------------------------- the runner's order
ORDER = """
[campaign]
name = "order"

[[matrix]]
name = "alone-a"
scenarios = ["dlc-paper"]
controllers = ["passive", "lmpc"]
exclusive = true

[[matrix]]
name = "free"
scenarios = ["dlc-paper"]
controllers = ["passive", "lmpc", "nmpc-mf", "nmpc-rhonn"]
speeds_kmh = [50.0]

[[matrix]]
name = "alone-b"
scenarios = ["slippery-curve"]
controllers = ["passive"]
exclusive = true

[[study]]
kind = "vmax"
controllers = ["passive"]
bracket_kmh = [40.0, 80.0]
resolution_kmh = 20.0
verify_offsets_kmh = []
"""


def stand_in_run(spec_json: dict[str, Any], root: str) -> dict[str, Any]:
    """In place of a bus run (in the worker): 0.3 s of wall time, v_max threshold 55 km/h."""
    spec = RunSpec.from_json(spec_json)
    row = base_row(spec, Path(root))
    started = time.time()
    time.sleep(0.3)
    v = spec.speed_kmh or 0.0
    row.update(status="ok", reason="finished", error="", started_at=started,
               task_wall_s=time.time() - started, passed_dlc=v <= 55.0,
               max_abs_beta_deg=1.0, post="{}", bench="{}")
    return row


def test_exclusive_runs_go_last_one_at_a_time(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(campaign_runner, "execute_run", stand_in_run)
    c = parse_campaign(ORDER)
    result = CampaignRunner(c, tmp_path / "c", EngineConfig("local", 2), progress=False).run()
    rows = sorted(result.rows.values(), key=lambda r: r["started_at"])
    assert len(rows) == 2 + 4 + 1 + 3  # the bisection: 40, 80, then 60
    alone = [r for r in rows if r["key"] in c.exclusive]
    others = [r for r in rows if r["key"] not in c.exclusive]
    assert [(r["group"], r["controller"]) for r in alone] == [
        ("alone-a", "passive"), ("alone-a", "lmpc"), ("alone-b", "passive")]
    assert sorted(r["speed_kmh"] for r in others if r["group"] == "vmax") == [40.0, 60.0, 80.0]
    end = max(r["started_at"] + r["task_wall_s"] for r in others)
    for r in alone:
        assert r["started_at"] >= end - 0.005
        end = r["started_at"] + r["task_wall_s"]
