"""Reference path: a dense polyline with arc length, heading and local projection.

Positions in m (global frame), arc length s in m, heading in rad. Lateral deviation is signed,
+ = the point lies to the LEFT of the path (ISO y direction of the path frame).
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from plant_sim.path_kernel import (
    as_arrays,
    compiled_projection_enabled,
    project_compiled,
    project_window,
)


class ReferencePath:
    """Polyline path with fast local projection (warm-started by the last segment index)."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if x.shape != y.shape or x.ndim != 1 or len(x) < 2:
            raise ValueError("path needs two 1-D arrays of equal length >= 2")
        seg = np.hypot(np.diff(x), np.diff(y))
        keep = np.concatenate([[True], seg > 1e-9])  # drop duplicate points
        x, y = x[keep], y[keep]
        self.x = x
        self.y = y
        self.s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
        self.heading = np.unwrap(np.arctan2(np.diff(y), np.diff(x)))
        # python lists: scalar access in the per-cycle projection is faster than numpy indexing
        self._x = x.tolist()
        self._y = y.tolist()
        self._s = self.s.tolist()
        self._hx = np.cos(self.heading).tolist()
        self._hy = np.sin(self.heading).tolist()
        self._hint = 0
        self._arrays = as_arrays(self._x, self._y, self._s, self._hx, self._hy)

    @property
    def length_m(self) -> float:
        """Total arc length, m."""
        return float(self.s[-1])

    def reset(self) -> None:
        """Forget the warm-start index (new run)."""
        self._hint = 0

    def project(self, px: float, py: float) -> tuple[float, float]:
        """(s, lateral deviation) of the point (px, py), m.

        Searches the segments near the last hit and widens the window while the best match
        sits on its forward edge, so paths that overlap themselves (several laps of a circle)
        stay unambiguous and a cycle costs a few dozen segment tests.
        """
        if compiled_projection_enabled():  # same arithmetic, compiled (path_kernel.py)
            s, lat, kb = project_compiled(px, py, *self._arrays, self._hint)
        else:
            s, lat, kb = project_window(px, py, self._x, self._y, self._s, self._hx, self._hy,
                                        self._hint)
        self._hint = kb
        return s, lat

    def point_at(self, s: float) -> tuple[float, float, float]:
        """(x, y, heading) at arc length s (m), linear interpolation; extrapolates straight."""
        ss = self._s
        k = bisect.bisect_right(ss, s) - 1
        k = min(max(k, 0), len(ss) - 2)
        t = s - ss[k]
        return self._x[k] + t * self._hx[k], self._y[k] + t * self._hy[k], float(
            self.heading[k])

    def offset_polyline(self, offset_m: float) -> np.ndarray:
        """The path shifted laterally by ``offset_m`` (+ left), as an (N, 2) array in m."""
        hx = np.concatenate([np.cos(self.heading), [math.cos(self.heading[-1])]])
        hy = np.concatenate([np.sin(self.heading), [math.sin(self.heading[-1])]])
        return np.column_stack([self.x - offset_m * hy, self.y + offset_m * hx])


# ---------------------------------------------------------------------- builders
def smoothstep5(u: np.ndarray) -> np.ndarray:
    """Quintic 0->1 transition with zero slope and curvature at both ends (u in [0, 1])."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)


def plateau_path(
    x_knots: list[float], y_levels: list[float], x_end: float, x_start: float, ds: float = 0.25
) -> ReferencePath:
    """y(x) path: ``y_levels[k]`` held on [x_knots[2k], x_knots[2k+1]] with quintic
    transitions in between (lane-change courses). Extends flat to x_start and x_end (m)."""
    xs = np.arange(x_start, x_end + ds, ds)
    ys = np.full_like(xs, y_levels[0])
    for k in range(1, len(y_levels)):
        xa, xb = x_knots[2 * k - 1], x_knots[2 * k]
        ys = ys + (y_levels[k] - y_levels[k - 1]) * smoothstep5((xs - xa) / (xb - xa))
    return ReferencePath(xs, ys)


def curvature_path(
    pieces: list[tuple[float, float, float]], ds: float = 0.25, x0: float = 0.0, y0: float = 0.0
) -> ReferencePath:
    """Path from curvature pieces (length m, curvature at start 1/m, curvature at end 1/m):
    linear curvature = clothoid, constant = arc or straight. Starts at (x0, y0) heading +x."""
    kappas: list[float] = []
    for length, k0, k1 in pieces:
        n = max(1, round(length / ds))
        kappas.extend((k0 + (k1 - k0) * (i + 0.5) / n) for i in range(n))
    k = np.asarray(kappas)
    heading = np.concatenate([[0.0], np.cumsum(k * ds)])
    hm = 0.5 * (heading[1:] + heading[:-1])
    x = x0 + np.concatenate([[0.0], np.cumsum(ds * np.cos(hm))])
    y = y0 + np.concatenate([[0.0], np.cumsum(ds * np.sin(hm))])
    return ReferencePath(x, y)
