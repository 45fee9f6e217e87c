"""Small helpers shared by the benchmarks: percentiles and JSON output."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def summarize_us(samples_ns: Sequence[int] | np.ndarray) -> dict[str, float]:
    """Median, p90, p99 and max of durations given in ns, returned in µs."""
    arr = np.asarray(samples_ns, dtype=float) / 1000.0
    return {"p50_us": float(np.percentile(arr, 50)), "p90_us": float(np.percentile(arr, 90)),
            "p99_us": float(np.percentile(arr, 99)), "max_us": float(arr.max()),
            "samples": int(arr.size)}


def write_json(path: str | Path | None, payload: Any) -> None:
    """Write ``payload`` as indented JSON when a path is given."""
    if path:
        Path(path).write_text(json.dumps(payload, indent=2) + "\n")
