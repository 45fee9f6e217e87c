"""User scenario files: one typed schema for packaged and user files, its documentation, and
a file run end to end over the bus (rhonn-harness, plant and controller processes)."""

from __future__ import annotations

import csv
import inspect
import json
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from harness.analysis.course import course_geometry, scenario_for
from plant_sim import course as course_builders
from plant_sim.driver import DriverSpec
from plant_sim.scenario import (
    ScenarioError,
    is_scenario_file,
    list_scenarios,
    load_scenario,
    read_spec,
    scenario_label,
)
from plant_sim.scenario_schema import (
    COURSE_TYPES,
    DRIVER,
    REQUIRED,
    SpecError,
    check_spec,
    markdown_tables,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "brake-in-turn.toml"


@pytest.mark.parametrize("name", list_scenarios())
def test_every_packaged_scenario_meets_the_schema(name: str) -> None:
    check_spec(read_spec(name))


def test_driver_schema_is_the_driver_spec() -> None:
    """Every DriverSpec field is in the schema with the same default (and nothing else)."""
    spec_fields = {f.name: f.default for f in fields(DriverSpec)}
    assert [k.name for k in DRIVER] == list(spec_fields)
    for key in DRIVER:
        if key.default is not REQUIRED:
            assert key.default == spec_fields[key.name], key.name


@pytest.mark.parametrize("kind", list(COURSE_TYPES))
def test_course_schema_is_the_builder_signature(kind: str) -> None:
    """The keys of each course type are its builder's arguments, with its defaults."""
    builder = getattr(course_builders, kind)
    params = {n: p.default for n, p in inspect.signature(builder).parameters.items()
              if n != "vehicle_width_m"}
    keys = {k.name: k.default for k in COURSE_TYPES[kind]}
    assert set(keys) == set(params)
    for name, default in keys.items():
        expected = REQUIRED if params[name] is inspect.Parameter.empty else params[name]
        assert default == expected or (default is REQUIRED and expected is REQUIRED), name


def test_docs_hold_the_schema_tables() -> None:
    """docs/scenarios.md shows the tables generated from the schema, word for word."""
    assert markdown_tables() in (ROOT / "docs" / "scenarios.md").read_text()


def test_a_file_is_the_same_scenario_as_its_packaged_twin(tmp_path: Path) -> None:
    text = (ROOT / "plant_sim" / "scenarios" / "dlc-paper.toml").read_text()
    (tmp_path / "my-dlc.toml").write_text(text)
    ref = str(tmp_path / "my-dlc.toml")
    assert is_scenario_file(ref) and is_scenario_file("my-dlc.toml")
    assert not is_scenario_file("dlc-paper")
    assert scenario_label(ref) == "my-dlc"
    mine, packaged = load_scenario(ref, mu=0.5), load_scenario("dlc-paper", mu=0.5)
    assert mine.name == "my-dlc" and mine.mu == packaged.mu == 0.5
    np.testing.assert_array_equal(mine.reference_path_xy, packaged.reference_path_xy)
    np.testing.assert_array_equal(mine.cones, packaged.cones)
    # the analysis loads it as the plant does (KPIs, plots, rerun)
    geo = course_geometry(scenario_for(ref, None, 50.0, {"run_out_m": "40"}))
    assert len(geo.cones) == len(packaged.cones) and geo.duration_s == packaged.duration_s


def test_parameters_of_a_file_go_where_the_schema_has_them(tmp_path: Path) -> None:
    f = tmp_path / "turn.toml"
    f.write_text(EXAMPLE.read_text())
    sc = load_scenario(str(f), brake_pedal="0.5", radius_m=80.0, steps=[(4.0, 0.3)],
                       target_speed_kmh=60)
    assert sc.driver.brake_pedal == 0.5 and sc.driver.target_speed_kmh == 60.0
    assert sc.spec["course"]["radius_m"] == 80.0
    assert sc.friction.base_mu_at_time(5.0) == pytest.approx(0.3)
    with pytest.raises(KeyError, match="no parameter 'arc_deg'"):  # not a circle's key
        load_scenario(str(f), arc_deg=90.0)
    # as text, the way a command line or a campaign file gives them (the plant reads the same)
    text = load_scenario(str(f), brake_pedal="0.5", steps="[[4.0, 0.3]]")
    assert text.driver.brake_pedal == 0.5 and text.friction.steps == ((4.0, 0.3),)


@pytest.mark.parametrize(("text", "message"), [
    ("duration_s = 0.0", "duration_s: must be > 0 and <= 3600, got 0"),
    ("duration_s = true", "duration_s: must be a number (s), got True"),
    ("duration_s = nan", "duration_s: must be a finite number"),
    ("[road]\nmu = 0.5\n[road.split]\nmu_left = 1.0", "missing key 'road.split.mu_right'"),
    ("[road]\nmu = 0.5\npatches = [{ x0 = 1.0 }]", "missing key 'road.patches[0].mu'"),
    ("[course]\ntype = 'oval'", "course.type: must be one of iso3888_1, iso3888_2"),
    ("[course]\ntype = 'straight'", "missing key 'course.length_m'"),
])
def test_schema_errors_name_the_key(text: str, message: str) -> None:
    base = {"duration_s": 5.0, "speed_kmh": 50.0, "course": {"type": "iso3888_1"},
            "road": {"mu": 0.5}, "driver": {"steer": "path", "speed": "coast"}}
    import tomllib

    spec = {**base, **tomllib.loads(text)}
    with pytest.raises(SpecError) as exc:
        check_spec(spec)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_file_errors_name_the_file(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(EXAMPLE.read_text().replace("mu = 0.6", "mu = 0.0"))
    with pytest.raises(ScenarioError, match=r"bad\.toml: road\.mu: must be > 0 and <= 1\.5"):
        load_scenario(str(f))


def test_a_scenario_file_runs_across_processes(tmp_path: Path) -> None:
    """`rhonn-harness run PATH.toml`: the plant process drives the file's manoeuvre (its μ and
    its speed in the truth trace) and the run directory is named after the file."""
    exe = Path(sys.executable).with_name("rhonn-harness")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "harness.cli"]
    proc = subprocess.run([*cmd, "run", str(EXAMPLE), "--controller", "passive",
                           "--duration", "2", "--no-plots", "--no-rrd", "--bus", "auto"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = tmp_path / "runs" / "brake-in-turn-passive"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["reason"] == "finished" and metrics["completed"] is True
    assert metrics["scenario_name"] == "brake-in-turn"
    with (out / "truth.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    first, last = rows[0], rows[-1]
    assert float(last["t_s"]) == pytest.approx(2.0, abs=0.011)
    for wheel in ("fl", "fr", "rl", "rr"):  # the file's road: mu = 0.6 under every wheel
        assert float(first[f"mu_{wheel}"]) == pytest.approx(0.6)
        assert float(last[f"mu_{wheel}"]) == pytest.approx(0.6)
    assert float(first["vx_mps"]) == pytest.approx(80.0 / 3.6, rel=1e-6)  # the file's speed
    assert float(last["brake_pedal"]) == 0.0  # the brake comes at 3.5 s, after this run


def test_a_campaign_runs_scenario_files(tmp_path: Path) -> None:
    """A campaign matrix names a file relative to the campaign file; the run key follows the
    file's content (a resumed campaign runs an edited manoeuvre again)."""
    from harness.campaign.spec import parse_campaign
    from harness.campaign.task import check_runs

    (tmp_path / "manoeuvres").mkdir()
    turn = tmp_path / "manoeuvres" / "turn.toml"
    turn.write_text(EXAMPLE.read_text())
    text = ('[[matrix]]\nname = "m"\nscenarios = ["manoeuvres/turn.toml", "step-steer"]\n'
            'controllers = ["passive"]\n')
    runs = parse_campaign(text, tmp_path).runs
    assert [r.scenario for r in runs] == [str(turn.resolve()), "step-steer"]
    check_runs(runs, tmp_path / "out")  # both meet the checks of `rhonn-harness run`
    assert not (tmp_path / "out").exists()
    key = runs[0].key()
    turn.write_text(EXAMPLE.read_text().replace("mu = 0.6", "mu = 0.5"))
    assert parse_campaign(text, tmp_path).runs[0].key() != key
    assert parse_campaign(text, tmp_path).runs[1].key() == runs[1].key()
