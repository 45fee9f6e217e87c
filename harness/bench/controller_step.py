"""`rhonn-bench controller`: step time of every registered controller (cf. paper Table 5).

Each controller runs closed loop against a small built-in single-track plant (nonlinear
lateral tyres, μ = 0.35, 65 km/h entry, pedals released, DLC-like steering: one full
steering-wheel sine of 25°, a 1 s pause, one opposite sine; repeated every 8 s; seeded
sensor noise). ``time.perf_counter_ns`` is taken around ``step()`` only; the first
``--warmup`` steps are excluded. Reported: p50 / p99 step time (µs) and the mean number of
OSQP iterations per step, plus the ratios nmpc-rhonn/lmpc and nmpc-mf/nmpc-rhonn.
Controllers whose model module is not present yet are skipped with a note.
``--profile`` prints a cProfile summary of nmpc-rhonn. Nothing is asserted.
"""

from __future__ import annotations

import cProfile
import gc
import io
import json
import math
import pstats
import time
from pathlib import Path
from typing import Any

import numpy as np

from can_db.argcheck import OneLineParser, number
from controller.core.interfaces import ControllerInputs
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.registry import CONTROLLER_NAMES, make_controller

G = 9.81


class _Plant:
    """Single-track plant with Magic-Formula-like lateral tyres (explicit Euler, 1 ms)."""

    def __init__(self, p: VehicleParams, mu: float, vx0: float) -> None:
        self.p, self.mu = p, mu
        L = p.wheelbase_m
        self.fz = (p.mass_kg * G * p.lr_m / L, p.mass_kg * G * p.lf_m / L)
        self.c = (abs(p.cf_axle_n_per_rad), abs(p.cr_axle_n_per_rad))
        self.vx, self.vy, self.r, self.ax, self.ay = vx0, 0.0, 0.0, 0.0, 0.0

    def _fy(self, alpha: float, axle: int) -> float:
        d = self.mu * self.fz[axle]
        return d * math.sin(1.3 * math.atan(self.c[axle] / (1.3 * d) * alpha))

    def step(self, torques: np.ndarray, delta: float, t: float) -> None:
        p = self.p
        fx = float(np.sum(torques)) / p.wheel_radius_m
        mz = float(torques[1] + torques[3] - torques[0] - torques[2]) * p.track_m / (
            2.0 * p.wheel_radius_m)
        n = max(1, round(t / 1e-3))
        h = t / n
        for _ in range(n):
            vx = max(self.vx, 1.0)
            fyf = self._fy(delta - math.atan2(self.vy + p.lf_m * self.r, vx), 0)
            fyr = self._fy(-math.atan2(self.vy - p.lr_m * self.r, vx), 1)
            drag = math.copysign(0.4 * self.vx * self.vx + 150.0, self.vx)
            self.ax = (fx - fyf * math.sin(delta) - drag) / p.mass_kg
            self.ay = (fyf * math.cos(delta) + fyr) / p.mass_kg
            dr = (p.lf_m * fyf * math.cos(delta) - p.lr_m * fyr + mz) / p.yaw_inertia_kgm2
            self.vx += h * (self.ax + self.vy * self.r)
            self.vy += h * (self.ay - self.vx * self.r)
            self.r += h * dr


def dlc_swa(t: float, amp_deg: float = 25.0) -> float:
    """DLC-like steering-wheel angle, rad, period 8 s."""
    tt = (t % 8.0) - 1.0
    a = math.radians(amp_deg)
    if 0.0 <= tt < 2.5:
        return a * math.sin(2 * math.pi * tt / 2.5)
    if 3.5 <= tt < 6.0:
        return -a * math.sin(2 * math.pi * (tt - 3.5) / 2.5)
    return 0.0


def run_one(name: str, steps: int, warmup: int, config: str | None,
            seed: int = 0, prof: cProfile.Profile | None = None) -> dict[str, Any]:
    """Closed-loop run of one controller; returns timing and iteration statistics.

    With ``prof``, the profiler is switched on around ``step()`` only (plant excluded)."""
    ctrl = make_controller(name, config)
    p = load_vehicle_params()
    vx_ref = 65.0 / 3.6
    plant = _Plant(p, mu=0.35, vx0=vx_ref)
    rng = np.random.default_rng(seed)
    inp = ControllerInputs()
    times = np.zeros(steps, dtype=np.int64)
    iters = np.zeros(steps)
    gc.collect()
    for k in range(steps + warmup):
        t = k * ctrl.ts
        swa = dlc_swa(t)
        inp.swa_rad = swa
        # The driver holds 65 km/h (P control on the pedals), so every step is timed at a
        # paper-like speed rather than on a long coast-down to standstill.
        pedal = 0.06 + 0.2 * (vx_ref - plant.vx)
        inp.accel_pedal, inp.brake_pedal = min(max(pedal, 0.0), 1.0), min(max(-pedal, 0.0), 1.0)
        inp.vx = plant.vx + rng.normal(0.0, 0.05)
        inp.vy = plant.vy + rng.normal(0.0, 0.03)
        inp.yaw_rate = plant.r + rng.normal(0.0, 0.003)
        inp.ax = plant.ax + rng.normal(0.0, 0.05)
        inp.ay = plant.ay + rng.normal(0.0, 0.05)
        inp.wheel_speeds[:] = plant.vx / p.wheel_radius_m
        if prof is not None:
            prof.enable()
        t0 = time.perf_counter_ns()
        out = ctrl.step(inp)
        t1 = time.perf_counter_ns()
        if prof is not None:
            prof.disable()
        if k >= warmup:
            times[k - warmup] = t1 - t0
            iters[k - warmup] = out.qp_iterations
        plant.step(out.torques, swa / p.steering_ratio, ctrl.ts)
    us = times / 1e3
    return {
        "name": name,
        "p50_us": float(np.percentile(us, 50)),
        "p99_us": float(np.percentile(us, 99)),
        "qp_iterations_mean": float(iters.mean()),
        "steps": steps,
    }


def profile_rhonn(steps: int, config: str | None, top: int = 18) -> str:
    """cProfile summary (tottime) of nmpc-rhonn's step() over a closed-loop run."""
    prof = cProfile.Profile()
    run_one("nmpc-rhonn", steps, 0, config, prof=prof)
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    return buf.getvalue()


def _ratio(rows: dict[str, dict[str, Any]], a: str, b: str) -> dict[str, Any]:
    if a in rows and b in rows:
        return {"name": f"{a}/{b}",
                "p50_ratio": rows[a]["p50_us"] / rows[b]["p50_us"],
                "p99_ratio": rows[a]["p99_us"] / rows[b]["p99_us"]}
    return {"name": f"{a}/{b}", "p50_ratio": None, "p99_ratio": None}


def main(argv: list[str]) -> int:
    """Entry point: ``rhonn-bench controller [--json FILE] [--steps N] [--profile]``."""
    ap = OneLineParser(prog="rhonn-bench controller", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the results as a JSON list")
    ap.add_argument("--steps", type=number(int, lo=1), default=4000,
                    help="timed steps per controller")
    ap.add_argument("--warmup", type=number(int, lo=0), default=20, help="untimed steps first")
    ap.add_argument("--config", default=None, help="controller TOML (default: paper 20 Hz)")
    ap.add_argument("--profile", action="store_true", help="cProfile nmpc-rhonn")
    args = ap.parse_args(argv)
    rows: dict[str, dict[str, Any]] = {}
    for name in CONTROLLER_NAMES:
        try:
            rows[name] = run_one(name, args.steps, args.warmup, args.config)
        except ModuleNotFoundError as exc:
            print(f"note: skipping {name}: {exc}")
    print(f"{'controller':<12} {'p50 µs':>9} {'p99 µs':>9} {'OSQP iter':>10}")
    for r in rows.values():
        print(f"{r['name']:<12} {r['p50_us']:9.1f} {r['p99_us']:9.1f} "
              f"{r['qp_iterations_mean']:10.2f}")
    ratios = [_ratio(rows, "nmpc-rhonn", "lmpc"), _ratio(rows, "nmpc-mf", "nmpc-rhonn")]
    for q in ratios:
        if q["p50_ratio"] is None:
            print(f"{q['name']:<22} n/a (a controller was skipped)")
        else:
            print(f"{q['name']:<22} p50 ×{q['p50_ratio']:.2f}  p99 ×{q['p99_ratio']:.2f}")
    if args.profile:
        print(profile_rhonn(min(args.steps, 2000), args.config))
    if args.json is not None:
        args.json.write_text(json.dumps([*rows.values(), *ratios], indent=2))
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
