"""Pareto view (harness/paper/pareto.py): the front / dominance functions on hand-made point
sets, and the quick plan end to end (bus runs on the campaign engine, two workers)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest

from harness.campaign.engine import EngineConfig
from harness.paper.benchmark import run_benchmark
from harness.paper.pareto import (
    SECTION_TITLE,
    ParetoPlan,
    dominance,
    front_dominates,
    non_dominated,
    pareto_figure,
    pareto_markdown,
    pareto_section,
    pareto_specs,
    strictly_dominates,
    undominated_by,
    weakly_dominates,
)


# ------------------------------------------------------------------------ unit
def test_weak_and_strict_dominance() -> None:
    assert weakly_dominates((1.0, 2.0), (1.0, 2.0))          # a tie weakly dominates
    assert not strictly_dominates((1.0, 2.0), (1.0, 2.0))    # ... but not strictly
    assert strictly_dominates((1.0, 2.0), (1.0, 3.0))
    assert not weakly_dominates((0.5, 4.0), (1.0, 3.0))      # a trade-off: neither
    assert not weakly_dominates((1.0, 3.0), (0.5, 4.0))


def test_non_dominated_front_keeps_ties_and_orders_by_path() -> None:
    pts = [(3.0, 1.0), (1.0, 3.0), (2.0, 2.0), (2.0, 2.0), (2.5, 2.5), (1.0, 4.0), (4.0, 1.0)]
    # (2.5, 2.5) is dominated by (2, 2); (1, 4) by (1, 3); (4, 1) by (3, 1); the tie stays.
    assert non_dominated(pts) == [1, 2, 3, 0]
    assert non_dominated([]) == []
    assert non_dominated([(1.0, 1.0)]) == [0]


def test_front_dominates_with_ties_and_a_failing_case() -> None:
    front = [(1.0, 3.0), (2.0, 2.0), (3.0, 1.0)]
    assert front_dominates(front, [(1.0, 3.0), (2.5, 2.0), (3.0, 5.0)])   # incl. a tie
    others = [(2.0, 2.5), (0.5, 5.0), (3.5, 0.5)]     # beats the front's ends on one axis
    assert not front_dominates(front, others)
    assert undominated_by(front, others) == [1, 2]
    assert front_dominates(front, [])


def _pt(label: str, x: float, y: float, spun: int = 0) -> dict[str, Any]:
    return {"label": label, "x": x, "y": y, "spun": spun}


def test_dominance_verdict_ignores_spun_points() -> None:
    points = {"nmpc-rhonn": [_pt("a", 1.0, 2.0), _pt("b", 2.0, 1.0), _pt("c", 0.1, 0.1, 1)],
              "nmpc-mf": [_pt("p", 1.5, 2.0), _pt("q", 2.0, 1.0)],
              "lmpc": [_pt("r", 0.9, 3.0), _pt("s", 3.0, 3.0)]}
    d = dominance(points)
    assert d["nmpc-mf"] == {"dominates": True, "undominated": []}   # q ties with b
    assert d["lmpc"] == {"dominates": False, "undominated": ["r"]}  # the spun c does not count


def test_dominance_counts_seeds_on_their_own_points() -> None:
    def pt(label: str, *seeds: tuple[float, float]) -> dict[str, Any]:
        xs, ys = sorted(s[0] for s in seeds), sorted(s[1] for s in seeds)
        return {"label": label, "x": xs[len(xs) // 2], "y": ys[len(ys) // 2], "spun": 0,
                "per_seed": [[x, y, 0] for x, y in seeds]}

    # medians: a (1, 1) dominates p (1, 1) by a tie; seed 2 alone: a (2, 2) vs p (1.5, 1.5)
    points = {"nmpc-rhonn": [pt("a", (1.0, 1.0), (2.0, 2.0), (0.5, 0.5))],
              "nmpc-mf": [pt("p", (1.0, 1.0), (1.5, 1.5), (1.0, 1.0))]}
    d = dominance(points)["nmpc-mf"]
    assert d["dominates"] and (d["seeds_dominating"], d["n_seeds"]) == (2, 3)


# ------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[ParetoPlan, dict[str, Any], Path]:
    # one campaign of real bus runs on two workers (A: the slowly-increasing-steer run first)
    plan = ParetoPlan.quick()
    out = tmp_path_factory.mktemp("pareto")
    tables = run_benchmark(out, [pareto_section(plan)], EngineConfig("local", 2),
                           bar=False)["pareto"]
    png = pareto_figure(tables, out / "figure.png")
    assert (out / "pareto.png").is_file() and "pareto.png" in (out / "benchmark.md").read_text()
    return dataclasses.replace(plan, a_deg=tables["plan"]["a_deg"]), tables, png


def test_quick_plan_is_small() -> None:
    plan = dataclasses.replace(ParetoPlan.quick(), a_deg=40.0)
    assert len(plan.seeds) == 1
    assert all(2 <= len(k.settings) <= 3 for k in plan.knobs.values())
    assert len(pareto_specs(plan)) <= 40


def test_quick_tables_have_fronts_and_verdicts(quick: tuple[ParetoPlan, dict[str, Any], Path]
                                               ) -> None:
    plan, tables, _ = quick
    assert list(tables["planes"]) == [p.key for p in plan.planes()]
    for t in tables["planes"].values():
        assert set(t["fronts"]) == set(plan.knobs)
        for c, labels in t["fronts"].items():
            assert labels, c
            assert set(labels) <= {p["label"] for p in t["points"][c]}
        assert set(t["dominance"]) == {"nmpc-mf", "lmpc"}
        assert t["passive"] is not None
    curve = next(t for t in tables["planes"].values() if t["kind"] == "curve")
    assert curve["near_best_baseline"]["best"]["controller"] in ("nmpc-mf", "lmpc")
    json.dumps(tables)  # plain data


def test_quick_markdown_and_figure(quick: tuple[ParetoPlan, dict[str, Any], Path]) -> None:
    _, tables, png = quick
    md = pareto_markdown(tables)
    assert md.startswith(f"## {SECTION_TITLE}")
    assert md.count("nmpc-rhonn's front dominates") == 2 * len(tables["planes"])
    assert png.is_file() and png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
