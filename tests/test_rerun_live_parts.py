"""The live rerun view's inputs: a growing CSV read row by row, bus frames placed at the cycle
they answer (harness/viz/rerun_live.py; the viewer itself is looked at with
harness/tools/rerun_screenshots.py, not in CI)."""

from __future__ import annotations

from pathlib import Path

from can_db.codec import Codec, Transmitter
from harness.viz.rerun_live import CsvTail, FrameBatcher, web_viewer_url


def test_csv_tail_returns_only_whole_new_rows_and_follows_a_replaced_file(tmp_path: Path
                                                                         ) -> None:
    path = tmp_path / "truth.csv"
    tail = CsvTail(path)
    assert tail.rows() == {}  # not there yet
    path.write_text("t_s,cycle\n0,0\n0.01,1\n0.0")  # last row still being written
    rows = tail.rows()
    assert rows["cycle"].tolist() == [0.0, 1.0]
    with path.open("a") as fh:
        fh.write("2,2\n")
    assert tail.rows()["t_s"].tolist() == [0.02]
    assert tail.rows() == {}
    path.rename(tmp_path / "truth.run1.csv")  # a restarted plant writes a new file
    path.write_text("t_s,cycle\n0,0\n")
    assert tail.rows()["cycle"].tolist() == [0.0]
    tail.close()


def test_frames_go_to_the_cycle_their_echo_names() -> None:
    codec = Codec()
    tx = Transmitter(codec)
    frames = [tx.message("SYNC", {"CYCLE": 300, "SIM_TIME": 3.0}),
              tx.message("CTRL_REFS", {"DELTA_M": 10.0, "YAW_RATE_REF": 1.0, "BETA_REF": 0.1,
                                       "ECHO_CYCLE": 299 % 256}),
              tx.message("CTRL_REFS", {"DELTA_M": 20.0, "YAW_RATE_REF": 1.0, "BETA_REF": 0.1,
                                       "ECHO_CYCLE": 300 % 256})]
    cols = FrameBatcher(codec).columns(frames)
    assert cols["CTRL_REFS"]["cycle"].tolist() == [299.0, 300.0]
    assert cols["CTRL_REFS"]["sim_time_s"].tolist() == [2.99, 3.0]
    assert cols["CTRL_REFS"]["DELTA_M"].tolist() == [10.0, 20.0]
    assert cols["SYNC"]["cycle"].tolist() == [300.0]


def test_viewer_url_is_loopback() -> None:
    assert web_viewer_url(9090, 9876).startswith("http://127.0.0.1:9090/?url=rerun%2Bhttp"
                                                 "://127.0.0.1:9876/")


def test_dump_shows_value_names_and_units() -> None:
    from can_db.cli import format_frame, signal_formats

    codec = Codec()
    msg = Transmitter(codec).message("CTRL_STATUS", {
        "MODE": 1, "FAULT_BITS": 0, "QP_STATUS": 0, "QP_ITER": 7, "COMPUTE_TIME": 124,
        "ECHO_CYCLE": 3, "CONTROLLER_ID": 1})
    line = format_frame(codec.decode_message(msg), signal_formats(codec))
    assert "MODE=ACTIVE" in line and "QP_STATUS=SOLVED" in line
    assert "COMPUTE_TIME=124 us" in line and "QP_ITER=7," in line


def test_live_layout_has_automatic_axes_and_no_never_fed_view() -> None:
    """A live view's data is still to come: automatic value axes, every view that the live
    stream feeds, and no rejected-frames view (rejections are known after the run only)."""
    from harness.viz.rerun_log import TAB_NAMES, build_blueprint

    bp = build_blueprint((0.0, 100.0, -8.0, 8.0))
    tabs = bp.root_container.contents[1].contents[1]
    assert [t.name for t in tabs.contents] == list(TAB_NAMES)
    views = [v for t in tabs.contents for v in t.contents]
    names = [v.name for v in views]
    assert not any("Rejected" in n for n in names)
    assert any("frame age" in n for n in names)
    assert not any("ScalarAxis" in v.properties for v in views
                   if type(v).__name__ == "TimeSeriesView")


def test_screenshot_tool_serves_files_on_loopback_with_cors(tmp_path: Path) -> None:
    import urllib.request

    from harness.tools.rerun_screenshots import file_server

    (tmp_path / "run.rrd").write_bytes(b"RRF2-test")
    with file_server(tmp_path) as base:
        assert base.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(f"{base}/run.rrd", timeout=10) as reply:
            assert reply.read() == b"RRF2-test"
            assert reply.headers["Access-Control-Allow-Origin"] == "*"


def test_screenshot_tool_rejects_a_bad_tab_list(capsys: object) -> None:
    import pytest

    from harness.tools.rerun_screenshots import main

    with pytest.raises(SystemExit) as exc:
        main(["/nonexistent", "--tabs", "0,9"])
    assert exc.value.code == 2
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert err.count("\n") == 1 and "--tabs" in err and "0..3" in err


def test_every_wheel_view_shows_its_colour_key_and_the_views_of_a_tab_differ() -> None:
    """A grid cell shows only the first ~25 characters of a title: the per-wheel views name
    their colours within them, so FL/FR and RL/RR can be told apart without hovering, and no
    two views of one tab look the same there (the Plant tab's motor torques, bus commands and
    their rates were six titles of two kinds, "FL blue, FR orange — Fro…")."""
    from harness.viz.rerun_log import TITLE_SHOWN, build_blueprint

    bp = build_blueprint((0.0, 100.0, -8.0, 8.0))
    tabs = bp.root_container.contents[1].contents[1]
    wheel_views = 0
    for tab in tabs.contents:
        shown = [str(v.name)[:TITLE_SHOWN] for v in getattr(tab, "contents", [])]
        assert len(set(shown)) == len(shown), shown
        for n in shown:
            if "FL" in n or "RL" in n:
                wheel_views += 1
                assert "FL blue, FR orange" in n or "RL green, RR red" in n, n
    assert wheel_views >= 8  # applied, motor, command, rate: front and rear
