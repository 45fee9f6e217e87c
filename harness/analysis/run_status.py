"""Whether a run is complete, in the words every display uses (KPI table, plots, rerun).

A run stopped by SIGINT/SIGTERM has ``"interrupted": true`` in metrics.json, with
``sim_time_reached_s`` (simulated s the plant reached) and ``duration_planned_s`` (the
simulated s it was meant to run). :func:`partial_note` turns those into the one label all
displays show, ``PARTIAL RUN — interrupted at 3.2 s of 20.0 s``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

PARTIAL = "PARTIAL RUN"


def _seconds(value: Any) -> str:
    try:
        return f"{float(value):.1f} s"
    except (TypeError, ValueError):
        return "? s"


def partial_note(metrics: Mapping[str, Any] | None) -> str | None:
    """``"PARTIAL RUN — interrupted at X.X s of Y.Y s"`` for an interrupted run, else None.

    ``metrics``: a run's metrics.json content (or a run's ``meta``), any mapping with the
    keys above; a missing planned duration reads ``of ? s``."""
    if not metrics or not metrics.get("interrupted"):
        return None
    return (f"{PARTIAL} — interrupted at {_seconds(metrics.get('sim_time_reached_s'))} of "
            f"{_seconds(metrics.get('duration_planned_s'))}")


def with_partial_note(title: str, metrics: Mapping[str, Any] | None) -> str:
    """``title`` with the partial-run note on a line of its own (unchanged for a full run)."""
    note = partial_note(metrics)
    return title if note is None else f"{title}\n{note}"
