"""Compiled (numba) projection of a point onto a reference path (``ReferencePath.project``).

The plant projects the car onto its reference path every cycle (driver, truth trace); in
Python that window search costs ≈ 25 µs a cycle, about half of the plant's model time. This
is the same loop, statement by statement and in the same order (IEEE double arithmetic, no
``fastmath``): the result is bit-identical to the Python loop (tests/test_plant_kernel.py
compares them). Without numba, or with ``RHONN_PLANT_KERNEL=python``, the Python loop runs.
"""

from __future__ import annotations

import math

import numpy as np

from plant_sim.kernel import enabled, numba


def project_window(px: float, py: float, xs, ys, ss, hx, hy, hint: int
                   ) -> tuple[float, float, int]:
    """(s, lateral deviation, best segment) of (px, py), m: the segments near ``hint``,
    widened while the best match sits on the window's forward edge; the end segments are
    extended straight. ``xs``..``hy``: the path's points, arc lengths and unit tangents."""
    nseg = len(xs) - 1
    lo = max(0, hint - 8)
    hi = min(nseg, hint + 40)
    best_d2 = math.inf
    s, lat, kb = 0.0, 0.0, lo
    k = lo
    while k < hi:
        dx, dy = px - xs[k], py - ys[k]
        seg_len = ss[k + 1] - ss[k]
        t = dx * hx[k] + dy * hy[k]
        t = 0.0 if t < 0.0 else (seg_len if t > seg_len else t)
        ex, ey = dx - t * hx[k], dy - t * hy[k]
        d2 = ex * ex + ey * ey
        if d2 < best_d2:
            best_d2 = d2
            s, lat, kb = ss[k] + t, hx[k] * dy - hy[k] * dx, k  # cross(tangent, offset)
        k += 1
        if k == hi and kb >= hi - 2 and hi < nseg:
            hi = min(nseg, hi + 40)
    # before the start / after the end: extend the end segments straight
    if kb == 0 or kb == nseg - 1:
        dx, dy = px - xs[kb], py - ys[kb]
        t = dx * hx[kb] + dy * hy[kb]
        if (kb == 0 and t < 0.0) or (kb == nseg - 1 and t > ss[kb + 1] - ss[kb]):
            s = ss[kb] + t
            lat = hx[kb] * dy - hy[kb] * dx
    return s, lat, kb


project_compiled = None
if numba is not None:
    project_compiled = numba.njit(cache=True, error_model="python")(project_window)


def compiled_projection_enabled() -> bool:
    """True when the compiled projection is used (numba present, not switched off)."""
    return project_compiled is not None and enabled()


def as_arrays(*columns: list[float]) -> tuple[np.ndarray, ...]:
    """Contiguous float64 arrays for the compiled projection."""
    return tuple(np.ascontiguousarray(c, dtype=np.float64) for c in columns)
