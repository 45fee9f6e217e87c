"""`rhonn-harness paper --quick` end to end (the campaign paper-quick.toml as real bus runs on
the warm benches of a 2-worker LocalCluster, then the table writer), and the bisection state
machine on synthetic pass/fail thresholds."""

from __future__ import annotations

import ctypes
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

import matplotlib.image as mpimg
import numpy as np
import pytest

from harness.analysis.vmax import Bisection
from harness.campaign.store import ResultStore
from harness.cli import main as harness_main
from tests.helpers_proc import live_children

# One-step (50 ms) RHONN Vx RMSE, km/h: measured 0.15–0.19 over the four quick fidelity runs
# (lockstep, seed 0); bound = the largest + 35 %.
RHONN_VX_RMSE_BOUND_KMH = 0.25
PR_SET_CHILD_SUBREAPER = 36


def _subreaper(on: bool) -> None:
    """Linux: orphaned descendants are re-parented to this process (so a process leaked by
    a pool worker or a run still shows up in live_children() instead of under init)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0)


def _ours(procs: list[Any]) -> list[Any]:
    """Without the stdlib's multiprocessing resource tracker: one helper per interpreter
    (started by the spawn-context pool) that lives until this interpreter exits."""
    out = []
    for p in procs:
        try:
            if "multiprocessing.resource_tracker" not in " ".join(p.cmdline()):
                out.append(p)
        except Exception:  # gone meanwhile
            pass
    return out


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("paper") / "quick"
    _subreaper(True)
    try:
        assert harness_main(["paper", "--out", str(out), "--jobs", "2", "--quick"]) == 0
        deadline = time.monotonic() + 10.0
        while _ours(live_children()) and time.monotonic() < deadline:
            time.sleep(0.1)
        leftovers = [(p.pid, p.cmdline()) for p in _ours(live_children())]
    finally:
        _subreaper(False)
    tables = json.loads((out / "tables.json").read_text())
    tables["_leftover_processes"] = leftovers
    return out, tables


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def _table_after(text: str, heading: str) -> list[list[str]]:
    """Cells of the first markdown table after the line starting with ``heading`` (header
    row included, separator row dropped)."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(heading))
    first = next(i for i in range(start, len(lines)) if lines[i].startswith("|"))
    rows = []
    for ln in lines[first:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
    return [r for r in rows if not set("".join(r)) <= set("-")]


def test_report_tables_show_the_json_numbers_and_its_figures_are_drawn(
        quick: tuple[Path, dict[str, Any]]) -> None:
    out, t = quick
    text = (out / "report.md").read_text()
    for heading in ("Claims, one by one", "Table 2", "Table 3", "Closed-loop DLC",
                    "Maximum DLC entry speed (Table 4)", "Slippery curve",
                    "Computation time (Table 5)", "FMVSS 126"):
        assert heading in text, heading
    # Table 2: the RHONN's min / max / RMSE cells are the tables.json values (2 decimals).
    rows = _table_after(text, "### Table 2")
    col = rows[0].index("rhonn ours")
    vx = next(r for r in rows if r[0] == "Vx [km/h]")
    e = t["fidelity"]["high_mu"]["paper"]["rhonn"]["vx_kmh"]
    assert vx[col] == f"{e['min']:.2f} / {e['max']:.2f} / {e['rmse']:.2f}"
    # Table 4: v_max, status and every probe with its verdict, as in tables.json.
    rows = _table_after(text, "## Maximum DLC entry speed (Table 4)")
    by_ctrl = {r[0]: dict(zip(rows[0], r, strict=True)) for r in rows[1:]}
    assert set(by_ctrl) == set(t["vmax"])
    for c, v in t["vmax"].items():
        row = by_ctrl[c]
        assert float(row["v_max ours [km/h]"]) == v["vmax_kmh"], c
        assert row["status"] == v["status"], c
        probes = sorted((float(p[:-1]), p[-1] == "✓")
                        for p in row["probes (✓ pass, ✗ fail)"].split(", "))
        assert probes == sorted((p["speed_kmh"], p["passed"]) for p in v["probes"]), c
    # Every linked figure is a drawn image: several colours, not a blank canvas.
    links = re.findall(r"\]\((figures/[^)]+\.png)\)", text)
    assert len(links) >= 10
    for link in links:
        img = mpimg.imread(out / link)[::2, ::2, :3]          # every 4th pixel is plenty
        inked = np.any(img < 0.9, axis=-1).mean()
        assert 0.01 < inked < 0.9, (link, inked)
        rgb = (img * 255).round().astype(np.int64)
        colours = np.unique(rgb[..., 0] << 16 | rgb[..., 1] << 8 | rgb[..., 2])
        assert colours.size > 10, link


def test_tables_json_fidelity(quick: tuple[Path, dict[str, Any]]) -> None:
    _, t = quick
    assert t["meta"]["quick"] is True and t["meta"]["runs"] >= 10
    for name in ("high_mu", "low_mu", "low_mu_closed_loop", "low_mu_spin"):
        fid = t["fidelity"][name]
        for which in ("paper", "one_step", "multi_step"):
            for model in ("rhonn", "7dof-li", "7dof-mf"):
                for state in ("vx_kmh", "vy_kmh", "yaw_rate_degps"):
                    e = fid[which][model][state]
                    assert all(_finite(e[k]) for k in ("min", "max", "rmse")), (name, which,
                                                                                model, state)
                    assert 0.0 <= e["min"] <= e["rmse"] <= e["max"]
        assert fid["paper"]["rhonn"]["vx_kmh"]["rmse"] < RHONN_VX_RMSE_BOUND_KMH
    assert t["fidelity"]["low_mu"]["speed_kmh"] == 50.0


def test_tables_json_closed_loop_and_vmax(quick: tuple[Path, dict[str, Any]]) -> None:
    out, t = quick
    assert set(t["dlc"]) == {"nmpc-rhonn", "passive"}
    for c, m in t["dlc"].items():
        assert m["reason"] == "finished", c
        assert _finite(m["max_abs_beta_deg"]) and _finite(m["phase_area"])
        assert isinstance(m["passed_dlc"], bool)
    assert _finite(t["curve"]["nmpc-rhonn"]["max_abs_lateral_dev_m"])
    upd = t["timing"]["dlc"]["nmpc-rhonn"]["mpc_update"]
    assert upd["n"] > 0 and _finite(upd["p50_us"]) and upd["p50_us"] > 0
    assert t["timing"]["dlc"]["nmpc-rhonn"]["hold"]["n"] > upd["n"]  # MPC every 5th cycle
    for c in ("nmpc-rhonn", "passive"):
        v = t["vmax"][c]
        speeds = [p["speed_kmh"] for p in v["probes"]]
        assert 2 <= len(speeds) <= 3 and 40.0 in speeds and 80.0 in speeds
        for p in v["probes"]:
            assert isinstance(p["passed"], bool) and "max_abs_beta_deg" in p
        # every probed speed was a real run, and every run is recorded
        rows = [r for r in ResultStore(out / "campaign").rows().values()
                if r["group"] == "vmax" and r["controller"] == c]
        assert sorted(r["speed_kmh"] for r in rows) == sorted(speeds)
        assert all((Path(r["run_dir"]) / "truth.csv").is_file() for r in rows)
        if v["status"] == "ok":
            assert v["vmax_kmh"] in speeds


def test_tables_json_fmvss(quick: tuple[Path, dict[str, Any]]) -> None:
    _, t = quick
    fm = t["fmvss"]
    # the same A as the plant's own FMVSS test measures (19.07 deg)
    assert fm["a_deg"] == pytest.approx(19.07, abs=0.2)
    assert len(fm["runs"]) == 1
    run = fm["runs"][0]
    assert run["amplitude_deg"] == pytest.approx(1.5 * fm["a_deg"], abs=1e-3)  # 3 decimals
    for k in ("pass_yrr_1s", "pass_yrr_175s", "pass_lateral", "passed"):
        assert isinstance(run[k], bool), k
    assert fm["summary"]["nmpc-rhonn"]["runs"] == 1


def test_table5_runs_ran_last_and_alone(quick: tuple[Path, dict[str, Any]]) -> None:
    # the exclusive matrices (dlc*, curve): after every other run, one at a time
    out, t = quick
    rows = list(ResultStore(out / "campaign").rows().values())
    alone = sorted((r for r in rows if r["group"].startswith(("dlc", "curve"))),
                   key=lambda r: r["started_at"])
    others = [r for r in rows if r not in alone]
    assert [r["group"] for r in alone] == ["dlc-nmpc-rhonn", "dlc-passive", "curve"]
    assert len(others) >= 8 and len(rows) == t["meta"]["runs"]
    last_other_end = max(r["started_at"] + r["task_wall_s"] for r in others)
    ends = [r["started_at"] + r["task_wall_s"] for r in alone]
    assert alone[0]["started_at"] >= last_other_end - 0.01
    for prev_end, nxt in zip(ends, alone[1:], strict=False):
        assert nxt["started_at"] >= prev_end - 0.01


def test_no_orphan_processes(quick: tuple[Path, dict[str, Any]]) -> None:
    # checked right after the run, with this process as child subreaper (see the fixture)
    assert quick[1]["_leftover_processes"] == []


@pytest.mark.parametrize("threshold", [29.0, 30.0, 52.3, 63.2, 89.6, 95.0])
def test_bisection_finds_the_threshold_on_the_grid(threshold: float) -> None:
    b = Bisection("x", 30.0, 90.0, 0.5, (2.0, 5.0))
    runs = 0
    while not b.done:
        speeds = b.pending()
        assert speeds or b.done
        for v in speeds:
            runs += 1
            b.record(v, {"passed_dlc": v <= threshold, "max_abs_beta_deg": 1.0})
    r = b.to_json()
    assert len(r["probes"]) == runs and runs <= 11
    if threshold < 30.0:
        assert r["status"] == "below_bracket" and r["vmax_kmh"] is None
    elif threshold >= 90.0:
        assert r["status"] == "above_bracket" and r["vmax_kmh"] == 90.0
    else:
        assert r["status"] == "ok" and r["monotone"]
        assert r["vmax_kmh"] == math.floor(threshold * 2) / 2


def test_bisection_reports_non_monotone_boundary() -> None:
    b = Bisection("x", 30.0, 90.0, 0.5, (2.0, 5.0))
    while not b.done:
        for v in b.pending():  # passes up to 60 except a hole at 55–56
            b.record(v, {"passed_dlc": v <= 60.0 and not 55.0 <= v <= 56.0})
    r = b.to_json()
    assert r["vmax_kmh"] == 60.0 and r["monotone"] is False
