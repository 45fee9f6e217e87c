"""The rerun recording is written to a file and read back with rerun 0.41's RrdReader."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from harness.analysis.run_data import load_run
from harness.viz.rerun_log import APPLICATION_ID, HOW_TO_OPEN, read_scalars, write_rrd
from tests.test_harness_kpi import DM_A, FALLBACK_CYCLES, MISS_ROWS, make_run_dir

N = 400
COURSE = [np.column_stack([np.linspace(0, 60, 13), np.full(13, 1.5)]),
          np.column_stack([np.linspace(0, 60, 13), np.full(13, -1.5)])]
REF = np.column_stack([np.linspace(0, 80, 9), np.zeros(9)])
CONES = np.vstack([c[::4] for c in COURSE])


@pytest.fixture(scope="module")
def rrd(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    root = tmp_path_factory.mktemp("rr")
    run = load_run(make_run_dir(root / "run", N, bad_frames_at=(20,)))
    path = write_rrd(run, COURSE, REF, root / "run.rrd", recording_name="synthetic-nmpc",
                     cones=CONES)
    return path, run


def test_scalars_round_trip(rrd: tuple[Path, object]) -> None:
    path, run = rrd
    sc = read_scalars(path)
    dm = sc["/controller/delta_m"]
    assert np.max(dm["values"]) == np.max(run.bus["CTRL_REFS"]["DELTA_M"]) == DM_A
    # One row per cycle on the cycle timeline, aligned with sim time.
    for ent in ("/plant/velocity/vx", "/plant/beta", "/controller/yaw_rate/actual",
                "/controller/yaw_rate/ref", "/controller/beta/ref", "/bus/timing/step_us"):
        assert sc[ent]["cycle"].tolist() == list(range(N)), ent
        np.testing.assert_allclose(sc[ent]["sim_time"], np.arange(N) * 0.01, atol=1e-9)
    np.testing.assert_allclose(sc["/plant/beta"]["values"],
                               np.degrees(run.truth["beta_rad"]), rtol=1e-12)
    np.testing.assert_allclose(sc["/controller/yaw_rate/ref"]["values"],
                               run.bus["CTRL_REFS"]["YAW_RATE_REF"])
    assert sc["/controller/status/qp_status"]["values"].max() == 5
    assert np.count_nonzero(sc["/controller/status/qp_status"]["values"] == 5) == len(
        FALLBACK_CYCLES)
    assert sc["/bus/deadline_misses"]["values"][-1] == len(MISS_ROWS)
    assert sc["/bus/rejections/bad_crc"]["values"].tolist() == [1.0]
    assert sc["/bus/rejections/bad_crc"]["cycle"].tolist() == [20]
    assert len(sc["/bus/timing/jitter_us"]["values"]) == N - 1  # first period undefined
    assert np.all(sc["/bus/frame_age_ms"]["values"] > 0)
    # |dT/dt| of the commanded torque: every frame after the first, per 10 ms cycle
    rate = sc["/controller/torque_rate/fl"]
    assert rate["cycle"].tolist() == list(range(1, N))
    np.testing.assert_allclose(rate["values"],
                               np.abs(np.diff(run.bus["WHEEL_TORQUE_CMD"]["TQ_FL"])) / 0.01)


def test_stores_entities_and_blueprint(rrd: tuple[Path, object]) -> None:
    path, _ = rrd
    reader = RrdReader(path)
    recs, bps = reader.recordings(), reader.blueprints()
    assert len(recs) == 1 and len(bps) == 1
    assert recs[0].application_id == APPLICATION_ID == bps[0].application_id
    assert recs[0].recording_id == "synthetic-nmpc"
    chunks = list(reader.stream())
    paths = {c.entity_path for c in chunks}
    for ent in ("/plant/trajectory/course/cones", "/plant/trajectory/course/lines",
                "/plant/trajectory/ref_path", "/plant/trajectory/driven_path",
                "/plant/trajectory/vehicle", "/log", "/summary"):
        assert ent in paths, ent
    vehicle = [c for c in chunks if c.entity_path == "/plant/trajectory/vehicle"
               and not c.is_static]
    assert sum(c.num_rows for c in vehicle) == N
    log = [c for c in chunks if c.entity_path == "/log"]
    texts = [t[0] for c in log for t in c.to_record_batch().column("TextLog:text").to_pylist()]
    assert "controller mode ACTIVE" in texts
    assert any("rejected: bad_crc" in t for t in texts)
    assert any("no valid command" in t for t in texts)
    assert sum("deadline miss" in t for t in texts) == len(MISS_ROWS)
    bp_names = {c.entity_path for c in reader.stream(store=bps[0])}
    assert any("view" in p for p in bp_names)  # views and containers were saved


def test_empty_run_still_writes(tmp_path: Path) -> None:
    path = write_rrd(load_run(tmp_path), [], None, tmp_path / "empty.rrd",
                     recording_name="empty")
    assert path.stat().st_size > 0
    assert read_scalars(path) == {}
    assert len(RrdReader(path).blueprints()) == 1


def test_how_to_open_text() -> None:
    assert "rerun analytics disable" in HOW_TO_OPEN
    assert "127.0.0.1" in HOW_TO_OPEN and "never bind to all interfaces" in HOW_TO_OPEN


# --- the saved layout (blueprint) ------------------------------------------------------------

def _views(node: object) -> list[object]:
    """Every view of a blueprint container tree, depth first."""
    if type(node).__name__.endswith("View"):
        return [node]
    return [v for k in node.contents for v in _views(k)]  # type: ignore[attr-defined]


def _contents(view: object) -> list[str]:
    c = view.contents  # type: ignore[attr-defined]
    return [c] if isinstance(c, str) else list(c)


def _prop(view: object, name: str, field: str) -> object:
    arr = getattr(view.properties[name], field)  # type: ignore[attr-defined]
    return arr.as_arrow_array().to_pylist()[0]


@pytest.fixture(scope="module")
def lockstep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, object]:
    """A lockstep run (bus log in simulated time) written with an interrupt and verdicts."""
    from harness.viz.rerun_log import blueprint_for

    root = tmp_path_factory.mktemp("rr_lockstep")
    run = load_run(make_run_dir(root / "run", N), meta={"log_time": "sim", "mode": "lockstep"})
    metrics = {"interrupted": True, "sim_time_reached_s": 2.5, "duration_planned_s": 8.0,
               "verdicts": {"paper_rule": {"passed": True, "rule": "max |β| ≤ 8°"},
                            "course_rule": {"passed": False, "cones_struck": 2,
                                            "gate_exits": 3, "rule": "ISO 3888"},
                            "stable": {"passed": None, "rule": "no rule"}}}
    path = write_rrd(run, COURSE, REF, root / "run.rrd", recording_name="lockstep-nmpc",
                     cones=CONES, metrics=metrics)
    return path, blueprint_for(run, COURSE, REF, CONES, metrics), run


def test_lockstep_layout_has_no_view_without_data(lockstep: tuple[Path, object, object]
                                                  ) -> None:
    path, bp, _ = lockstep
    names = [v.name for v in _views(bp.root_container)]
    assert not any("frame age" in n or "Rejected" in n or "Sync period" in n
                   or "Period −" in n for n in names), names
    sc = read_scalars(path)
    for ent in ("/bus/frame_age_ms", "/bus/timing/period_us", "/bus/timing/jitter_us"):
        assert ent not in sc, ent  # wall-clock figures of a simulated schedule: not written
    assert not any(e.startswith("/bus/rejections") for e in sc)
    # Every time-series view has data, and its value axis holds all of it (no clipped peak).
    for view in _views(bp.root_container):
        if type(view).__name__ != "TimeSeriesView":
            continue
        wanted = [c.removeprefix("+ ").removesuffix("/**") for c in _contents(view)]
        ents = [e for e in sc if any(e == w or e.startswith(w + "/") for w in wanted)]
        assert ents, view.name
        lo, hi = _prop(view, "ScalarAxis", "range")
        for e in ents:
            assert lo < sc[e]["values"].min() and sc[e]["values"].max() < hi, (view.name, e)
    compute = next(n for n in names if n.startswith("Compute"))
    assert "wall]" in compute


def test_wheel_torques_per_axle_and_step_time_apart_from_turnaround(
        lockstep: tuple[Path, object, object]) -> None:
    """Left front and left rear torques are often equal: one view per axle, so none hides
    under another; the µs step time gets its own axis, not the ms turnaround's."""
    _, bp, _ = lockstep
    views = {v.name: _contents(v) for v in _views(bp.root_container)
             if type(v).__name__ == "TimeSeriesView"}
    for root in ("/plant/torque", "/plant/torque_actual", "/controller/torque_cmd",
                 "/controller/torque_rate"):
        axle_views = [c for c in views.values() if any(x.startswith(f"+ {root}/") for x in c)]
        assert sorted(sorted(x.split("/")[-2] for x in c) for c in axle_views) == \
            [["fl", "fr"], ["rl", "rr"]], (root, axle_views)
    compute = next(c for n, c in views.items() if n.startswith("Compute"))
    turnaround = next(c for n, c in views.items() if n.startswith("Turnaround"))
    assert not any("turnaround" in x for x in compute)
    assert turnaround == ["+ /bus/timing/turnaround_us/**"]
    assert all(len(n) <= 55 for n in views), [n for n in views if len(n) > 55]


def test_realtime_layout_keeps_bus_timing_views(rrd: tuple[Path, object]) -> None:
    from harness.viz.rerun_log import blueprint_for

    _, run = rrd
    names = [v.name for v in _views(blueprint_for(run, COURSE, REF, CONES).root_container)]
    for part in ("Sync period", "Period −", "frame age", "Rejected frames"):
        assert any(part in n for n in names), part


def test_discrete_states_have_their_own_view(lockstep: tuple[Path, object, object]) -> None:
    path, bp, _ = lockstep
    views = _views(bp.root_container)
    states = [v for v in views if type(v).__name__ == "StateTimelineView"]
    assert len(states) == 1
    shown = " ".join(_contents(states[0]))
    for ent in ("/controller/state/mode", "/controller/state/qp_status",
                "/controller/state/faults", "/plant/state/command"):
        assert ent in shown
    qp = [v for v in views if "QP iterations" in (v.name or "")]
    assert len(qp) == 1 and not any("state" in c for c in _contents(qp[0]))
    for v in views:  # no plot mixes a discrete state with a continuous value
        if type(v).__name__ == "TimeSeriesView":
            assert not any(k in c for c in _contents(v)
                           for k in ("/status/mode", "qp_status", "fault_bits")), v.name
    # The states are named (DBC value tables), written where they change.
    chunks = [c for c in RrdReader(path).stream() if c.entity_path == "/controller/state/mode"]
    modes = [s[0] for c in chunks if "StateChange:state" in c.to_record_batch().schema.names
             for s in c.to_record_batch().column("StateChange:state").to_pylist()]
    assert modes == ["ACTIVE"]


def test_top_view_bounds_hold_course_and_car(lockstep: tuple[Path, object, object]) -> None:
    _, bp, run = lockstep
    top = next(v for v in _views(bp.root_container) if type(v).__name__ == "Spatial2DView")
    b = _prop(top, "VisualBounds2D", "range")
    (x0, x1), (y0, y1) = b["x_range"], b["y_range"]
    pts = np.vstack([CONES * [1, -1],
                     np.column_stack([run.truth["x_m"], -run.truth["y_m"]])])
    # The box is the course and the driven path with one margin in metres on both axes:
    # the 2-D view letterboxes it at one scale for x and y (true aspect, not stretched).
    np.testing.assert_allclose([x0, x1, y0, y1],
                               [pts[:, 0].min() - 3, pts[:, 0].max() + 3,
                                pts[:, 1].min() - 3, pts[:, 1].max() + 3])


def test_side_panels_make_room_for_the_views(lockstep: tuple[Path, object, object]) -> None:
    _, bp, _ = lockstep
    assert str(bp.blueprint_panel.state).lower() == "hidden"
    assert str(bp.selection_panel.state).lower() == "hidden"
    assert str(bp.time_panel.state).lower() == "collapsed"


def test_summary_rounds_kpis_and_shows_verdicts(lockstep: tuple[Path, object, object]
                                                ) -> None:
    from harness.viz.rerun_log import summary_text

    _, _, run = lockstep
    text = summary_text(run, "lockstep-nmpc", {
        "verdicts": {"paper_rule": {"passed": True, "rule": "r1"},
                     "course_rule": {"passed": False, "cones_struck": 2, "gate_exits": 3,
                                     "rule": "r2"},
                     "stable": {"passed": None, "rule": "r3"}}})
    kpi_rows = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert kpi_rows and not any(re.search(r"\d\.\d{5,}", ln) for ln in kpi_rows), kpi_rows
    assert "| max \\|β\\| [deg] |" in text
    assert "[µs] (wall-clock compute)" in text and "period jitter" not in text
    assert "* **paper rule: PASS** — r1" in text
    assert "* **course rule (cones): FAIL** (2 cones struck, 3 gate exits) — r2" in text
    assert "* **stable: not judged** — r3" in text
    assert "verdicts: not in this run's metrics" in summary_text(run, "x", {})


def test_partial_run_is_labelled_in_the_recording(lockstep: tuple[Path, object, object]
                                                  ) -> None:
    path, bp, _ = lockstep
    label = "PARTIAL RUN — interrupted at 2.5 s of 8.0 s"
    chunks = list(RrdReader(path).stream())
    summary = [t for c in chunks if c.entity_path == "/summary"
               for t in c.to_record_batch().column("TextDocument:text").to_pylist()]
    assert label in summary[0][0]
    log = [t[0] for c in chunks if c.entity_path == "/log"
           for t in c.to_record_batch().column("TextLog:text").to_pylist()]
    assert log[-1] == label
    assert any(label in (v.name or "") for v in _views(bp.root_container))


def test_a_complete_run_has_no_partial_label() -> None:
    from harness.viz.rerun_log import partial_label

    assert partial_label({"interrupted": False, "sim_time_reached_s": 3.0}) is None
    assert partial_label({}) is None
    assert partial_label({"interrupted": True, "sim_time_reached_s": 1.234}) == (
        "PARTIAL RUN — interrupted at 1.2 s")


def test_layout_read_back_from_the_file_matches(lockstep: tuple[Path, object, object]
                                                ) -> None:
    """The screenshot tool rebuilds the layout from the .rrd: same data ranges, states."""
    from harness.viz.rerun_log import _Writer, log_time_series, recording_layout

    path, _, run = lockstep
    dry = _Writer(None)
    log_time_series(dry, run)
    layout = recording_layout(path)
    assert layout["ranges"] == dry.ranges
    assert layout["states"] == sorted(dry.states)
    assert layout["driven"].shape == (N, 2)
