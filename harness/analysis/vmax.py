"""Maximum DLC entry speed by bisection (paper Table 4; pass rule: harness/analysis/kpi.py).

A probe is one closed-loop run of ``dlc-paper`` at an entry speed; it passes when the run's
``passed_dlc`` KPI is true (no spin, max |β| ≤ 8° and max |lateral deviation| ≤ 1.0 m from
the start to 2 s after the course end, and the run covers that window).

:class:`Bisection` is a pure state machine (no I/O), so a scheduler can run the probes of
several controllers in parallel: ``pending()`` lists the speeds to run next, ``record()``
feeds a probe's metrics back. Sequence:

1. both bracket ends (the low end must pass, the high end must fail: the monotonicity
   check at the ends; otherwise the result is "below/above the bracket" and no bisection);
2. bisection on the ``resolution`` grid between the highest passing and the lowest failing
   speed until they are one grid step apart; v_max = the highest passing speed;
3. optional verification probes at v_max − offsets (a failure there means the pass/fail
   boundary is not monotone in speed; it is reported, v_max is not changed).

Every probed speed is kept with its pass flag, max |β| and max |deviation|. ``rule`` names
the metrics key that decides a probe (default ``passed_dlc``, the paper's rule; the
benchmark also bisects on the ``stable`` and ``course`` verdicts of
harness.analysis.verdicts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

PROBE_KEYS = ("passed_dlc", "max_abs_beta_deg", "max_abs_lateral_dev_m", "spun",
              "completed", "reason")


@dataclass
class Bisection:
    """Bisection for one controller. Speeds in km/h."""

    controller: str
    lo_kmh: float = 30.0
    hi_kmh: float = 90.0
    resolution_kmh: float = 0.5
    verify_offsets_kmh: tuple[float, ...] = (2.0, 5.0)
    probes: list[dict[str, Any]] = field(default_factory=list)
    rule: str = "passed_dlc"  # metrics key (bool) that decides a probe's pass
    _phase: str = "ends"
    _pass: float = math.nan  # highest passing speed of the bracket
    _fail: float = math.nan  # lowest failing speed of the bracket
    _waiting: set[float] = field(default_factory=set)
    status: str = "running"

    def _probed(self, v: float) -> dict[str, Any] | None:
        return next((p for p in self.probes if abs(p["speed_kmh"] - v) < 1e-9), None)

    def pending(self) -> list[float]:
        """Speeds (km/h) to run now; empty while probes are outstanding or when done."""
        if self._waiting or self.done:
            return []
        if self._phase == "ends":
            want = [self.lo_kmh, self.hi_kmh]
        elif self._phase == "bisect":
            steps = round((self._fail - self._pass) / self.resolution_kmh)
            want = [self._pass + self.resolution_kmh * max(1, steps // 2)]
        else:  # verify
            want = [v for v in (self._pass - o for o in self.verify_offsets_kmh)
                    if v > self.lo_kmh + 1e-9 and self._probed(v) is None]
        want = [round(v, 6) for v in want if self._probed(v) is None]
        self._waiting.update(want)
        if not want:
            self._advance()
            return self.pending() if not self.done else []
        return want

    def record(self, speed_kmh: float, metrics: dict[str, Any]) -> None:
        """Feed back the metrics of the run at ``speed_kmh``."""
        v = round(float(speed_kmh), 6)
        self._waiting.discard(v)
        probe = {"speed_kmh": v, "phase": self._phase}
        probe.update({k: metrics.get(k) for k in PROBE_KEYS})
        probe["passed"] = bool(metrics.get(self.rule))
        self.probes.append(probe)
        if not self._waiting:
            self._advance()

    def _advance(self) -> None:
        if self._phase == "ends":
            lo, hi = self._probed(self.lo_kmh), self._probed(self.hi_kmh)
            if lo is None or hi is None:
                return
            if not lo["passed"]:
                self.status, self._phase = "below_bracket", "done"
            elif hi["passed"]:
                self.status, self._phase = "above_bracket", "done"
            else:
                self._pass, self._fail, self._phase = self.lo_kmh, self.hi_kmh, "bisect"
        elif self._phase == "bisect":
            for p in self.probes:
                if p["phase"] != "bisect":
                    continue
                if p["passed"] and p["speed_kmh"] > self._pass and p["speed_kmh"] < self._fail:
                    self._pass = p["speed_kmh"]
                elif not p["passed"] and self._pass < p["speed_kmh"] < self._fail:
                    self._fail = p["speed_kmh"]
            if self._fail - self._pass <= self.resolution_kmh + 1e-9:
                self._phase = "verify" if self.verify_offsets_kmh else "done"
                if self._phase == "done":
                    self.status = "ok"
        elif self._phase == "verify":
            self._phase, self.status = "done", "ok"

    @property
    def done(self) -> bool:
        """No more probes will be requested."""
        return self._phase == "done"

    @property
    def vmax_kmh(self) -> float | None:
        """Highest passing speed on the grid (None unless the bisection completed)."""
        if self.status == "ok":
            return self._pass
        if self.status == "above_bracket":
            return self.hi_kmh
        return None

    def expected_remaining(self) -> int:
        """Rough number of probes still to come (for the progress line)."""
        if self.done:
            return 0
        span = (self.hi_kmh - self.lo_kmh) if self._phase == "ends" else (
            self._fail - self._pass if math.isfinite(self._fail) else 0.0)
        n = max(0, math.ceil(math.log2(max(span / self.resolution_kmh, 1.0))))
        extra = 2 if self._phase == "ends" else 0
        verify = len(self.verify_offsets_kmh) if self._phase != "verify" else 0
        return n + extra + verify

    def to_json(self) -> dict[str, Any]:
        """Result and every probe (sorted by speed)."""
        monotone = all(p["passed"] for p in self.probes
                       if self.vmax_kmh is not None and p["speed_kmh"] <= self.vmax_kmh)
        monotone = monotone and not any(
            p["passed"] for p in self.probes
            if self.vmax_kmh is not None and p["speed_kmh"] > self.vmax_kmh)
        return {"controller": self.controller, "vmax_kmh": self.vmax_kmh,
                "status": self.status, "bracket_kmh": [self.lo_kmh, self.hi_kmh],
                "resolution_kmh": self.resolution_kmh,
                "lowest_fail_kmh": None if math.isnan(self._fail) else self._fail,
                "ends_ok": self.status not in ("below_bracket", "above_bracket"),
                "monotone": monotone,
                "probes": sorted(self.probes, key=lambda p: p["speed_kmh"])}
