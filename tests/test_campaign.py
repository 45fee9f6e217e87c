"""Campaigns: the file → run matrix and its keys, the Parquet store, the statistics, and real
campaigns (cross-process closed loops on their own buses) on a dask LocalCluster, on a
`dask scheduler` + two `dask worker` processes on 127.0.0.1, and killed with SIGKILL then
resumed."""

from __future__ import annotations

import contextlib
import ctypes
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil
import pyarrow.parquet as pq
import pytest

from can_db.process.parent import die_with_parent
from harness.campaign.cli import study_lines
from harness.campaign.spec import CampaignError, RunSpec, parse_campaign
from harness.campaign.store import ResultStore
from harness.campaign.summary import summarise
from harness.cli import main as harness_main
from harness.run.marker import INTERRUPTED
from tests.helpers_proc import live_children

PR_SET_CHILD_SUBREAPER = 36
BIN = Path(sys.executable).parent

TINY = """
[campaign]
name = "tiny"
seeds = [0, 1]

[[matrix]]
name = "dlc"
scenarios = ["dlc-paper"]
controllers = ["passive"]
speeds_kmh = [50.0]
duration_s = 1.0
"""

WITH_FAILURE_AND_STUDY = TINY + """
[[matrix]]
name = "crash"
scenarios = ["dlc-paper"]
controllers = ["passive"]
duration_s = 2.0
seeds = [0]
faults = [["kill-plant@0.3s"]]

[[study]]
kind = "vmax"
controllers = ["passive"]
seeds = [0]
bracket_kmh = [40.0, 80.0]
resolution_kmh = 20.0
verify_offsets_kmh = []
"""


def _subreaper(on: bool) -> None:
    """Orphaned descendants are re-parented to this process (so a leak stays visible)."""
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0)


def _ours(procs: list[psutil.Process]) -> list[psutil.Process]:
    """Without the interpreter-lifetime multiprocessing resource tracker, without zombies
    (a process that has exited but whose parent has not reaped it yet: it runs nothing and
    holds nothing but its pid) and without processes in the middle of exiting (their address
    space, and with it the command line, is already gone: seen in full-suite runs as an
    entry with no command)."""
    out = []
    for p in procs:
        try:
            if p.status() == psutil.STATUS_ZOMBIE:
                continue
            cmd = p.cmdline()
            if not cmd:
                continue
            if "multiprocessing.resource_tracker" not in " ".join(cmd):
                out.append(p)
        except psutil.Error:
            pass
    return out


def _settle(deadline_s: float = 15.0) -> list[tuple[int, list[str]]]:
    """Descendants still alive after waiting up to ``deadline_s`` for them to end."""
    end = time.monotonic() + deadline_s
    while _ours(live_children()) and time.monotonic() < end:
        time.sleep(0.2)
    left = []
    for p in _ours(live_children()):
        with contextlib.suppress(psutil.Error):
            left.append((p.pid, p.cmdline()))
    return left


def _listen_addresses(pids: list[int]) -> set[str]:
    """IP addresses on which these processes listen (TCP)."""
    ips = set()
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except psutil.Error:
            continue
        ips |= {c.laddr.ip for c in conns if c.status == psutil.CONN_LISTEN}
    return ips


# ------------------------------------------------------------------------- the file
def test_matrix_expands_and_keys_follow_the_configuration() -> None:
    c = parse_campaign("""
[campaign]
seeds = [0, 1, 2]
[[matrix]]
name = "m"
scenarios = ["dlc-paper", "slippery-curve"]
controllers = ["passive", "lmpc"]
mu = [0.35, 0.5]
params = [{}, { stab_enable_after_s = "1.0" }]
faults = [[], ["loss:10%"]]
[[matrix]]
name = "again"
scenarios = ["dlc-paper"]
controllers = ["passive"]
mu = [0.35]
seeds = [0]
""")
    assert len(c.runs) == 2 * 2 * 2 * 2 * 2 * 3  # the second matrix repeats a run: once
    keys = {r.key() for r in c.runs}
    assert len(keys) == len(c.runs)
    r = c.runs[0]
    assert RunSpec.from_json(r.to_json()) == r and RunSpec.from_json(r.to_json()).key() == r.key()
    from dataclasses import replace

    assert replace(r, seed=9).key() != r.key()
    assert replace(r, params=(("stab_enable_after_s", "2.0"),)).key() != r.key()
    # how a run is carried out and recorded has no effect on its result
    assert replace(r, make_plots=True, group="other", bus="local:x",
                   out_dir=Path("/tmp")).key() == r.key()
    assert replace(r, vehicle=(("mass_scale", 1.15),)).key() != r.key()


def test_vehicle_override_sets_expand_and_are_checked() -> None:
    c = parse_campaign("""
[[matrix]]
scenarios = ["step-steer"]
controllers = ["passive"]
vehicle = [{}, { mass_scale = 1.15, yaw_inertia_scale = 1.2 }]
""")
    assert [r.vehicle for r in c.runs] == [(), (("mass_scale", 1.15),
                                                 ("yaw_inertia_scale", 1.2))]
    r = c.runs[1]
    assert RunSpec.from_json(r.to_json()) == r
    for bad, msg in (("{ warp = 2 }", "unknown vehicle override 'warp'"),
                     ("{ mass_scale = -1 }", "mass_scale"), ("{ mass_scale = 'x' }", "vehicle")):
        with pytest.raises(CampaignError) as exc:
            parse_campaign("[[matrix]]\nscenarios=['step-steer']\ncontrollers=['passive']\n"
                           f"vehicle=[{bad}]")
        assert msg in str(exc.value) and "\n" not in str(exc.value)


def test_vehicle_overrides_reach_the_plant_process(tmp_path: Path) -> None:
    # Across processes: the same step steer with the yaw inertia doubled turns in later.
    f = tmp_path / "v.toml"
    f.write_text("""
[campaign]
name = "veh"
[[matrix]]
name = "iz"
scenarios = ["step-steer"]
controllers = ["passive"]
duration_s = 1.6
vehicle = [{}, { yaw_inertia_scale = 2.0 }]
""")
    out = tmp_path / "out"
    proc = _cli("campaign", str(f), "--out", str(out), "--jobs", "1", "--no-progress")
    assert proc.wait(timeout=300) == 0
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert len(rows) == 2 and all(r["status"] == "ok" for r in rows)
    from harness.analysis.run_data import load_truth_csv

    peak = {}
    for r in rows:
        cfg = json.loads(r["config"])
        tr = load_truth_csv(Path(r["run_dir"]) / "truth.csv")
        peak[bool(cfg.get("vehicle"))] = float(tr["yaw_rate_radps"][tr["t_s"] <= 1.3].max())
    assert peak[True] < 0.9 * peak[False]


@pytest.mark.parametrize(("text", "message"), [
    ("[[matrix]]\nscenarios=['dlc-paper']\ncontrollers=['nope']", "unknown controller 'nope'"),
    ("[[matrix]]\nscenarios=['moon']\ncontrollers=['passive']", "unknown scenario 'moon'"),
    ("[[matrix]]\nscenarios=['dlc-paper']\ncontrollers=['passive']\nspeed=[1]",
     "unknown key(s) speed"),
    ("[[matrix]]\nscenarios=['dlc-paper']\ncontrollers=['passive']\nfaults=[['warp:9']]",
     "faults"),
    ("[[matrix]]\nscenarios='dlc-paper'\ncontrollers=['passive']", "expected a non-empty list"),
    ("[[study]]\nkind='vmax'\ncontrollers=['passive']\nbracket_kmh=[90,30]", "bracket_kmh"),
    ("[campaign]\nname='x'", "nothing to run"),
    ("[[matrix]\n", "not valid TOML"),
])
def test_bad_campaign_files_are_one_line_errors(text: str, message: str) -> None:
    with pytest.raises(CampaignError) as exc:
        parse_campaign(text)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_cli_rejects_a_bad_file_with_exit_2(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("[[matrix]]\nscenarios=['dlc-paper']\ncontrollers=['nope']\n")
    assert harness_main(["campaign", str(f), "--out", str(tmp_path / "o")]) == 2
    assert "unknown controller" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------- store, statistics
def _row(key: str, seed: int, beta: float | None, status: str = "ok") -> dict[str, Any]:
    return {"key": key, "group": "g", "scenario": "dlc-paper", "controller": "passive",
            "seed": seed, "mu": 0.35, "speed_kmh": 65.0, "duration_s": None, "params": "{}",
            "faults": "[]", "controller_config": "", "mode": "lockstep", "status": status,
            "max_abs_beta_deg": beta, "passed_dlc": beta is not None and beta < 8.0}


def test_store_keeps_every_row_and_summary_pools_seeds(tmp_path: Path) -> None:
    store = ResultStore(tmp_path)
    rows = [_row("a", 0, 2.0), _row("b", 1, 10.0), _row("c", 2, 4.0),
            _row("d", 3, None, "failed")]
    for r in rows:
        store.write(r)
    (store.parts / ".junk.tmp").write_text("half a file")  # what a SIGKILL can leave
    got = store.rows()
    assert set(got) == {"a", "b", "c", "d"} and got["d"]["status"] == "failed"
    table = pq.read_table(store.consolidate())
    assert table.num_rows == 4 and "max_abs_beta_deg" in table.column_names
    (s,) = summarise(list(got.values()))
    assert (s["n_runs"], s["n_ok"], s["n_failed"]) == (4, 3, 1)
    assert (s["max_abs_beta_deg_median"], s["max_abs_beta_deg_min"],
            s["max_abs_beta_deg_max"]) == (4.0, 2.0, 10.0)
    assert s["passed_dlc_share"] == pytest.approx(2 / 3)


# ------------------------------------------------------------------------- real campaigns
def _cli(*args: str, stderr: Any = subprocess.DEVNULL) -> subprocess.Popen[bytes]:
    """`rhonn-harness ARGS` as a child process (a LocalCluster in the pytest process would
    leave the interpreter-lifetime multiprocessing resource tracker behind for the tests
    that check for leftover processes)."""
    return subprocess.Popen([str(BIN / "rhonn-harness"), *args], stdout=subprocess.DEVNULL,
                            stderr=stderr, preexec_fn=die_with_parent)


def test_campaign_on_a_local_cluster(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text(WITH_FAILURE_AND_STUDY)
    out = tmp_path / "out"
    _subreaper(True)
    try:
        err_file = (tmp_path / "stderr.txt").open("w")  # not a terminal: plain progress lines
        proc = _cli("campaign", str(f), "--out", str(out), "--jobs", "2", stderr=err_file)
        ips: set[str] = set()
        while proc.poll() is None:  # every socket the campaign's processes listen on
            tree = [proc.pid]
            with contextlib.suppress(psutil.Error):
                tree += [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
            ips |= _listen_addresses(tree)
            time.sleep(0.5)
        code = proc.wait()
        leftovers = _settle()
    finally:
        _subreaper(False)
    err_file.close()
    err = (tmp_path / "stderr.txt").read_text()
    assert ips and ips <= {"127.0.0.1"}, ips
    assert code == 1  # the crashed run is a failed row, not a lost campaign
    # off a terminal: one plain progress line at a time, the last one complete; dask's own
    # INFO lines stay out (other libraries log warnings only)
    progress = re.findall(r"^campaign: (\d+)/(\d+) runs", err, re.MULTILINE)
    assert progress and progress[-1][0] == progress[-1][1], err
    assert "\r" not in err and "INFO distributed" not in err, err
    assert leftovers == []
    rows = {r["key"]: r for r in pq.read_table(out / "results.parquet").to_pylist()}
    by_group: dict[str, list[dict[str, Any]]] = {}
    for r in rows.values():
        by_group.setdefault(r["group"], []).append(r)
    assert sorted(r["seed"] for r in by_group["dlc"]) == [0, 1]
    for r in by_group["dlc"]:
        assert r["status"] == "ok" and r["reason"] == "finished"
        assert (Path(r["run_dir"]) / "metrics.json").is_file()
        assert Path(r["run_dir"]).name == r["key"]
        assert json.loads(r["config"])["seed"] == r["seed"]
    (crash,) = by_group["crash"]
    assert crash["status"] == "failed" and "plant exited" in crash["reason"]
    # the v_max study: both bracket ends, then at most one bisection step (20 km/h grid)
    vmax = json.loads((out / "studies.json").read_text())["studies"]["vmax"]
    probes = vmax["controllers"]["passive"]["seeds"]["0"]["probes"]
    speeds = sorted(p["speed_kmh"] for p in probes)
    assert speeds in ([40.0, 80.0], [40.0, 60.0, 80.0])
    assert sorted(r["speed_kmh"] for r in by_group["vmax"]) == speeds  # one run per probe
    summary = {(s["group"]): s for s in pq.read_table(out / "summary.parquet").to_pylist()}
    assert summary["dlc"]["n_ok"] == 2 and summary["dlc"]["seeds"] == "0,1"
    lo, med, hi = (summary["dlc"][f"max_abs_beta_deg_{k}"] for k in ("min", "median", "max"))
    assert lo <= med <= hi


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Any:
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1. Their HTTP servers
    (served even with --no-dashboard) bind 0.0.0.0:8787 unless --dashboard-address says
    otherwise: the test below checks every listening socket."""
    sched_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")  # noqa: SIM115
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--no-dashboard", "--dashboard-address",
                               "127.0.0.1:0", "--scheduler-file",
                               str(sched_file)], stdout=log, stderr=log,
                              preexec_fn=die_with_parent)]
    try:
        end = time.monotonic() + 30
        while not sched_file.is_file() and time.monotonic() < end:
            time.sleep(0.1)
        assert sched_file.is_file(), (tmp_path / "dask.log").read_text()
        for i in range(2):
            procs.append(subprocess.Popen(
                [str(BIN / "dask"), "worker", "--scheduler-file", str(sched_file), "--host",
                 "127.0.0.1", "--nthreads", "1", "--no-dashboard", "--dashboard-address",
                 "127.0.0.1:0", "--name", f"w{i}"],
                stdout=log, stderr=log, preexec_fn=die_with_parent))
        from distributed import Client

        with Client(scheduler_file=str(sched_file), timeout=30) as c:
            c.wait_for_workers(2, timeout=60)
        yield sched_file, procs
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        log.close()


def test_campaign_on_a_scheduler_and_two_worker_processes(tmp_path: Path,
                                                          dask_cluster: Any) -> None:
    sched_file, procs = dask_cluster
    address = json.loads(sched_file.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    pids = [p.pid for p in procs]
    pids += [c.pid for p in procs for c in psutil.Process(p.pid).children(recursive=True)]
    ips = _listen_addresses(pids)
    assert ips and ips <= {"127.0.0.1"}, ips
    f = tmp_path / "c.toml"
    f.write_text(TINY)
    out = tmp_path / "out"
    assert harness_main(["campaign", str(f), "--out", str(out), "--scheduler", address,
                         "--no-progress"]) == 0
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert sorted(r["seed"] for r in rows) == [0, 1]
    assert all(r["status"] == "ok" for r in rows)
    # each run ran in one of the two dask worker processes, and both took one
    workers = {c.pid for p in procs[1:] for c in psutil.Process(p.pid).children()
               if "multiprocessing.spawn" in " ".join(c.cmdline())}
    assert {r["worker_pid"] for r in rows} == workers and len(workers) == 2


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_a_killed_or_stopped_campaign_resumes_without_losing_or_repeating_runs(
        tmp_path: Path, sig: signal.Signals) -> None:
    """SIGKILL: the campaign and its cluster die at once. SIGTERM: the engine stops its
    workers and their runs, exits 143 and leaves an INTERRUPTED note. Either way the finished
    runs stay, ``--resume`` runs only the rest, and the note goes with the complete campaign."""
    f = tmp_path / "c.toml"
    f.write_text(TINY.replace("seeds = [0, 1]", "seeds = [0, 1, 2, 3]"))
    out = tmp_path / "out"
    _subreaper(True)
    try:
        err_file = (tmp_path / "stderr.txt").open("w")  # not a terminal: plain progress lines
        proc = _cli("campaign", str(f), "--out", str(out), "--jobs", "2", stderr=err_file)
        parts = out / "parts"
        end = time.monotonic() + 60
        while time.monotonic() < end and not list(parts.glob("*.parquet")):
            time.sleep(0.05)
        assert proc.poll() is None, "the campaign ended before the signal"
        proc.send_signal(sig)
        code = proc.wait(timeout=30)
        assert _settle() == []  # the cluster and every run's processes are gone
        if sig == signal.SIGTERM:
            assert code == 143
            assert json.loads((out / INTERRUPTED).read_text())["signal"] == "SIGTERM"
        before = {p.name: p.stat().st_mtime_ns for p in parts.glob("*.parquet")}
        assert 1 <= len(before) < 4
        assert harness_main(["campaign", str(f), "--out", str(out)]) == 2  # needs --resume
        assert _cli("campaign", str(f), "--out", str(out), "--resume",
                    "--no-progress").wait() == 0
        assert _settle() == []
    finally:
        _subreaper(False)
    after = {p.name: p.stat().st_mtime_ns for p in parts.glob("*.parquet")}
    assert len(after) == 4
    assert {k: after[k] for k in before} == before  # nothing finished was run again
    meta = json.loads((out / "studies.json").read_text())["meta"]
    assert (meta["executed"], meta["resumed"]) == (4 - len(before), len(before))
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert sorted(r["seed"] for r in rows) == [0, 1, 2, 3]
    assert all(r["status"] == "ok" for r in rows)
    assert not (out / INTERRUPTED).exists()


def test_packaged_campaigns_parse_and_paper_holds_the_paper_matrix() -> None:
    from harness.campaign.spec import load_campaign

    root = Path(__file__).resolve().parents[1] / "harness" / "campaign" / "campaigns"
    paper = load_campaign(root / "paper.toml")
    groups = sorted({r.group for r in paper.runs})
    assert groups == ["curve", "dlc", "dlc-nmpc-rhonn", "dlc-passive", "fidelity-high-mu",
                      "fidelity-low-mu"]  # tests/test_paper_campaign.py: run by run
    assert len(paper.runs) == 10 and {r.seed for r in paper.runs} == {0}
    assert sorted(d.kind for d in paper.studies) == ["fmvss126", "vmax"]
    seeded = load_campaign(root / "paper.toml", seeds=[0, 1, 2])
    assert len(seeded.runs) == 30 and all(d.seeds == (0, 1, 2) for d in seeded.studies)
    assert load_campaign(root / "smoke.toml").runs


def test_an_unreachable_scheduler_is_a_one_line_error(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    import socket

    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    f = tmp_path / "c.toml"
    f.write_text(TINY)
    code = harness_main(["campaign", str(f), "--out", str(tmp_path / "o"), "--scheduler",
                         f"tcp://127.0.0.1:{port}", "--connect-timeout", "2",
                         "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "cannot reach the dask scheduler" in err
    assert not (tmp_path / "o" / "parts").exists()


def test_study_lines_say_a_missing_figure_in_words() -> None:
    """A study with no figure for a controller (no seed found a v_max, none failed) prints
    "—", never Python's ``None``."""
    studies = {
        "vmax": {"kind": "vmax", "controllers": {
            "lmpc": {"vmax_kmh": {"median": None, "min": None, "max": None, "n": 2},
                     "statuses": ["failed", "failed"]},
            "passive": {"vmax_kmh": {"median": 80.0, "min": 78.0, "max": 82.0, "n": 2},
                        "statuses": ["found", "found"]}}},
        "sine": {"kind": "sine", "controllers": {
            "lmpc": {"first_fail_amplitude_deg": {"median": None}, "seeds_passing_all": 2,
                     "n_seeds": 2}}},
    }
    lines = study_lines(studies)
    assert lines == [
        "vmax: lmpc: v_max median — over 2 seeds (failed, failed)",
        "vmax: passive: v_max median 80.0 km/h [78.0–82.0] over 2 seeds (found, found)",
        "sine: lmpc: 2/2 seeds pass every amplitude; first failing amplitude median —",
    ]
    assert not any("None" in line for line in lines)
