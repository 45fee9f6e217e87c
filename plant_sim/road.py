"""Road friction field over the ground plane: a base mu plus axis-aligned rectangular patches,
optionally changing in time.

Split-mu is a patch covering one side of a line (e.g. y < 0 for the right-hand wheels of a
car driving along +x on y = 0). Later patches override earlier ones. Positions in m
(global frame), mu dimensionless (it scales the tyre's LMUX/LMUY).

Time steps (``steps``: (t_s, mu) pairs) change the grip of the whole road at t_s s: from
then on the base friction is mu and every patch keeps its ratio to the base — rain or ice
reaching a car in a steady manoeuvre, whatever its course. Applied at the first plant cycle
at or after t_s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

_BIG = 1e9  # m, stands for an unbounded patch edge


@dataclass(frozen=True, slots=True)
class Patch:
    """Rectangle x0 <= x < x1, y0 <= y < y1 (m) with friction mu (-)."""

    x0: float
    x1: float
    y0: float
    y1: float
    mu: float

    def contains(self, x: float, y: float) -> bool:
        """True if the global point (x, y) in m lies in the patch."""
        return self.x0 <= x < self.x1 and self.y0 <= y < self.y1


@dataclass(frozen=True, slots=True)
class FrictionField:
    """Base friction ``mu`` (-) with overriding rectangular ``patches``."""

    mu: float
    patches: tuple[Patch, ...] = field(default_factory=tuple)
    steps: tuple[tuple[float, float], ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        for value in (self.mu, *(pt.mu for pt in self.patches), *(m for _, m in self.steps)):
            if not 0.0 < value <= 2.0:
                raise ValueError(f"road mu must be in (0, 2], got {value}")
        times = [t for t, _ in self.steps]
        if any(not t >= 0.0 for t in times) or times != sorted(times):
            raise ValueError(f"road steps need times t_s >= 0 in increasing order, got {times}")

    def base_mu_at_time(self, t_s: float) -> float:
        """Base friction (-) in force at time t_s s (the last step with t ≤ t_s)."""
        mu = self.mu
        for t, m in self.steps:
            if t <= t_s + 1e-9:
                mu = m
        return mu

    def at_time(self, t_s: float) -> FrictionField:
        """The static field in force at time t_s s (no steps; patches scaled with the base)."""
        base = FrictionField(self.mu, self.patches)
        mu = self.base_mu_at_time(t_s)
        return base if mu == self.mu else base.scaled(mu)

    @property
    def uniform(self) -> float | None:
        """The constant mu if there are no patches, else None."""
        return None if self.patches else self.mu

    def mu_at(self, x: float, y: float) -> float:
        """Friction at the global point (x, y) in m."""
        mu = self.mu
        for pt in self.patches:
            if pt.x0 <= x < pt.x1 and pt.y0 <= y < pt.y1:
                mu = pt.mu
        return mu

    def scaled(self, mu: float) -> FrictionField:
        """Override the base mu; patches keep their ratio to the base (mu override of a run).
        Time steps keep their absolute values: the override sets the grip before the first."""
        k = mu / self.mu
        return FrictionField(
            mu, tuple(Patch(p.x0, p.x1, p.y0, p.y1, min(2.0, p.mu * k)) for p in self.patches),
            self.steps,
        )

    def rectangles(self) -> list[tuple[float, float, float, float, float]]:
        """Patches as (x0, x1, y0, y1, mu) for plotting (unbounded edges clipped to +-1e9 m)."""
        return [(p.x0, p.x1, p.y0, p.y1, p.mu) for p in self.patches]


def friction_from_spec(spec: dict[str, Any]) -> FrictionField:
    """Build a field from a scenario's ``[road]`` table.

    Keys: ``mu`` (base), optional ``patches`` = list of {x0, x1, y0, y1, mu} (missing edges
    are unbounded), optional ``split`` = {y_line, mu_left, mu_right, x0, x1}: left (y >= y_line)
    and right halves get their own mu from x0 (default -inf) to x1 (default +inf), optional
    ``steps`` = list of [t_s, mu] pairs (or {t_s, mu} tables): the base friction from t_s s.
    """
    base = float(spec.get("mu", 1.0))
    patches: list[Patch] = []
    for p in spec.get("patches", []):
        patches.append(Patch(float(p.get("x0", -_BIG)), float(p.get("x1", _BIG)),
                             float(p.get("y0", -_BIG)), float(p.get("y1", _BIG)), float(p["mu"])))
    split = spec.get("split")
    if split:
        yl = float(split.get("y_line", 0.0))
        x0, x1 = float(split.get("x0", -_BIG)), float(split.get("x1", _BIG))
        patches.append(Patch(x0, x1, yl, _BIG, float(split["mu_left"])))
        patches.append(Patch(x0, x1, -_BIG, yl, float(split["mu_right"])))
    steps: list[tuple[float, float]] = []
    for st in spec.get("steps", []):
        t, m = (st["t_s"], st["mu"]) if isinstance(st, dict) else st
        steps.append((float(t), float(m)))
    return FrictionField(base, tuple(patches), tuple(steps))
