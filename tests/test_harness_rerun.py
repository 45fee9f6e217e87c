"""The rerun recording is written to a file and read back with rerun 0.41's RrdReader."""

from __future__ import annotations

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
