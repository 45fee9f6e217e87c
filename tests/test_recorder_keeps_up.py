"""The bus recorder keeps every frame of a real-time-scheduled lockstep run (cross-process).

With ``rt`` the loop's processes run SCHED_FIFO pinned to one CPU. A recorder blocking on
the bus there, below their priority, starved: the hub's queue to it (4 MiB) overflowed and
82 % of a 300 s run's frames were dropped. It now polls from the other CPU(s), and in
lockstep it is a lossless node: with every CPU busy (the test suite's other worker) and
coverage tracing it read a third as fast as the loop sent, and the hub now waits for it
instead of dropping. The test gives the recorder a 256 KiB queue (≈ 150 cycles of frames)
so a 12 s run shows either.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec


def test_rt_lockstep_run_records_every_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                             ) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    monkeypatch.setenv("RHONN_RT_CPUS", str(cpus[-1]))  # as `rhonn-bench loop --rt` does
    monkeypatch.setenv("RHONN_HUB_QUEUE_KIB", "256")
    res = run_and_report(RunSpec(scenario="dlc-paper", controller="nmpc-rhonn",
                                    out_dir=tmp_path, make_plots=False, make_rrd=False,
                                    rt=True))
    assert res.reason == "finished"
    hub = res.metrics["bus_hub"]
    recorder = [n for n in hub["nodes"] if n["name"] == "bus-recorder"]
    assert len(recorder) == 1 and recorder[0]["frames_in"] == 0
    assert hub["frames"] > 10_000  # 1128 cycles of 10 frames
    assert recorder[0]["lossless"] is True  # lockstep: the hub waits for it
    assert hub["dropped"] == 0 and recorder[0]["dropped"] == 0
    assert res.metrics["bus_frames_recorded"] == hub["frames"]
    assert res.metrics["bus_log_frames_lost"] == 0


def test_frames_the_recorder_lost_are_the_hubs_drops_for_its_node() -> None:
    from harness.analysis.run_metrics import bus_log_frames_lost

    hub = {"nodes": [{"name": "process.py:1", "dropped": 7},
                     {"name": "bus-recorder", "dropped": 229_740}]}
    assert bus_log_frames_lost(hub) == 229_740  # not the other node's drops
    assert bus_log_frames_lost({"nodes": [{"name": "bus-recorder", "dropped": 0}]}) == 0
    assert bus_log_frames_lost(None) is None  # the websocket server keeps no such count
    assert bus_log_frames_lost(None, 12) == 12  # SocketCAN: the kernel's for its socket
