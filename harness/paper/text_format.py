"""Number formatting and table look-ups shared by the report and the claims text."""

from __future__ import annotations

import math
from typing import Any


def f(x: Any, fmt: str = "{:.2f}") -> str:
    """Format a number or '–' for None/NaN."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    try:
        out = fmt.format(x)
    except (TypeError, ValueError):
        return str(x)
    # "-0" / "-0.00" after rounding reads as a sign that is not there
    return out[1:] if out.startswith("-") and out.strip("-0.") == "" else out


def rmse(fid: dict[str, Any], model: str, key: str, which: str = "paper") -> float:
    """RMSE of one model/state (NaN if missing)."""
    v = fid.get(which, {}).get(model, {}).get(key, {}).get("rmse")
    return float(v) if v is not None else math.nan
