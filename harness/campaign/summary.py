"""Grouped summaries: every configuration except the seed → median and min–max over seeds.

Only runs with status ``ok`` enter the statistics; ``n_runs``/``n_ok``/``n_failed`` say how
many there were. Output: ``DIR/summary.parquet`` and ``DIR/summary.csv`` (same columns:
``<kpi>_median``, ``<kpi>_min``, ``<kpi>_max`` with the KPI's unit in its name).
"""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from harness.campaign.task import KPI_FLAGS, KPI_FLOATS

GROUP_BY = ("group", "scenario", "controller", "mu", "speed_kmh", "duration_s", "params",
            "faults", "controller_config", "mode")
SHOWN = (("max_abs_beta_deg", "max |β| deg", "{:.2f}"),
         ("max_abs_lateral_dev_m", "max |dev| m", "{:.3f}"),
         ("max_abs_dM_Nm", "max |ΔM| N·m", "{:.0f}"),
         ("dM_tv_per_s_Nm_per_s", "ΔM TV/s N·m/s", "{:.0f}"),
         ("wheel_torque_rate_max_Nm_per_s", "max dT/dt N·m/s", "{:.0f}"))


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One summary row per configuration (seeds pooled)."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(k) for k in GROUP_BY), []).append(r)
    out = []
    for gkey, members in sorted(groups.items(), key=lambda kv: tuple(str(x) for x in kv[0])):
        ok = [m for m in members if m.get("status") == "ok"]
        s: dict[str, Any] = dict(zip(GROUP_BY, gkey, strict=True))
        s.update(n_runs=len(members), n_ok=len(ok), n_failed=len(members) - len(ok),
                 seeds=",".join(str(m["seed"]) for m in sorted(members,
                                                               key=lambda m: m["seed"])))
        for k in KPI_FLOATS:
            v = [float(m[k]) for m in ok if m.get(k) is not None]
            s[f"{k}_median"] = statistics.median(v) if v else None
            s[f"{k}_min"] = min(v) if v else None
            s[f"{k}_max"] = max(v) if v else None
        for k in KPI_FLAGS:
            v = [bool(m[k]) for m in ok if m.get(k) is not None]
            s[f"{k}_share"] = sum(v) / len(v) if v else None
        out.append(s)
    return out


def write_summary(root: Path, summary: list[dict[str, Any]]) -> tuple[Path, Path]:
    """summary.parquet and summary.csv in ``root``."""
    root = Path(root)
    cols = list(summary[0]) if summary else list(GROUP_BY)
    table = pa.Table.from_pylist(summary) if summary else pa.table({c: [] for c in cols})
    pq.write_table(table, root / "summary.parquet")
    with open(root / "summary.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(summary)
    return root / "summary.parquet", root / "summary.csv"


def format_summary(summary: list[dict[str, Any]], limit: int = 40) -> str:
    """A console table: median [min–max] over seeds of a few KPIs per configuration."""
    def cell(s: dict[str, Any], k: str, fmt: str) -> str:
        if s.get(f"{k}_median") is None:
            return "-"
        return (f"{fmt.format(s[f'{k}_median'])} [{fmt.format(s[f'{k}_min'])}–"
                f"{fmt.format(s[f'{k}_max'])}]")

    def variant(s: dict[str, Any]) -> str:
        parts = [f"{k}={v}" for k, v in json.loads(s["params"] or "{}").items()]
        parts += json.loads(s["faults"] or "[]")
        return (",".join(parts) or "-")[:19]

    head = (f"{'group':<12}{'scenario':<18}{'controller':<12}{'μ':>5}{'km/h':>7}  "
            f"{'params/faults':<20}{'ok/n':>5}  "
            + "  ".join(f"{label:<22}" for _, label, _ in SHOWN))
    lines = [head]
    for s in summary[:limit]:
        mu = "-" if s["mu"] is None else f"{s['mu']:.2f}"
        v = "-" if s["speed_kmh"] is None else f"{s['speed_kmh']:.1f}"
        lines.append(f"{str(s['group'])[:11]:<12}{str(s['scenario'])[:17]:<18}"
                     f"{s['controller']:<12}{mu:>5}{v:>7}  {variant(s):<20}"
                     f"{s['n_ok']:>2}/{s['n_runs']:<2}  "
                     + "  ".join(f"{cell(s, k, fmt):<22}" for k, _, fmt in SHOWN))
    if len(summary) > limit:
        lines.append(f"... {len(summary) - limit} more configurations in summary.csv")
    return "\n".join(lines)
