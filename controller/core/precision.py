"""Working precision of the numpy reference: ``[mpc] precision`` → numpy dtype."""

from __future__ import annotations

from typing import Any

import numpy as np

PRECISIONS = ("float64", "float32")


def dtype_of(precision: str) -> Any:
    """numpy dtype for config value ``precision`` ("float64" | "float32")."""
    if precision not in PRECISIONS:
        raise ValueError(f"mpc.precision must be one of {PRECISIONS}, not {precision!r}")
    return np.float32 if precision == "float32" else np.float64
