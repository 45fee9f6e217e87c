"""FMVSS 126 post-processing of one run directory (the paper study and the fmvss126 campaign).

``sis_of_run``: the steering amplitude A (deg) at which the slowly-increasing-steer run of the
passive car reaches 0.3 g; ``fmvss_of_run``: the sine-with-dwell verdict of one run
(:func:`harness.analysis.fmvss126.evaluate_sine_with_dwell`).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.errors import error_text
from harness.analysis.fmvss126 import G, evaluate_sine_with_dwell, find_a_deg
from harness.analysis.run_data import load_truth_csv


def sis_of_run(run_dir: Path) -> dict[str, Any]:
    """A (deg of steering-wheel angle) and the peak |a_y| (g) of a slowly-increasing-steer run."""
    tr = load_truth_csv(Path(run_dir) / "truth.csv")
    swa, ay = np.degrees(tr["swa_rad"]), tr["ay_mps2"]
    try:
        return {"a_deg": find_a_deg(swa, ay), "max_ay_g": float(np.max(np.abs(ay)) / G)}
    except ValueError as exc:
        return {"error": error_text(exc)}


def fmvss_of_run(run_dir: Path, amplitude_deg: float, a_deg: float) -> dict[str, Any]:
    """Sine-with-dwell verdict (yaw-rate ratios, lateral displacement) of one run; amplitude
    and A in deg of steering-wheel angle."""
    tr = load_truth_csv(Path(run_dir) / "truth.csv")
    try:
        r = evaluate_sine_with_dwell(
            tr["t_s"], np.degrees(tr["swa_rad"]), tr["yaw_rate_radps"], tr["x_m"], tr["y_m"],
            tr["yaw_rad"], amplitude_deg=amplitude_deg, a_deg=a_deg)
    except (KeyError, ValueError, IndexError) as exc:
        return {"error": error_text(exc), "passed": False}
    d = asdict(r)
    d["passed"] = r.passed
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in d.items()}
