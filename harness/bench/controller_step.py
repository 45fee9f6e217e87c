"""`rhonn-bench controller`: step time of every registered controller (cf. paper Table 5).

Each controller runs closed loop against a small built-in single-track plant (nonlinear
lateral tyres, μ = 0.35, 65 km/h entry, driver holding 65 km/h on the pedals, DLC-like
steering: one full steering-wheel sine of 25°, a 1 s pause, one opposite sine; repeated
every 8 s; seeded sensor noise). ``time.perf_counter_ns`` is taken around ``step()`` only;
the first ``--warmup`` steps are excluded.

Each controller is built as ``controller.registry.make_controller`` builds it: the C core
(controller/native) when it is built and runs the configuration, else the numpy reference
(controller/core); ``--backend`` overrides the choice (auto | native | numpy) and every
row records the backend that ran.

Reported per controller and precision (float64, and float32 with the UD EKF): p50 / p99 /
max step time (µs), OSQP iterations (mean and worst), bounded-iteration hits (OSQP
max_iter, QP fallbacks, Algorithm 1 rounds not converged). For the numpy reference also
per part, from a second, instrumented run (each part timed by a wrapper, whose own cost
is in the part's time): references, EKF, linearise = model rollout + Jacobians, QP =
condensing + QP data + OSQP, allocation, other = the rest of step(); the C core's step is
one call, with no parts. And the ratios nmpc-mf / nmpc-rhonn and nmpc-rhonn / lmpc of the same run.
``--profile`` prints a cProfile summary of nmpc-rhonn. Nothing is asserted.

Cold steps: ``--gap-ms G --evict-mb M`` sleep G ms and then add 1 to every element of an M MB
buffer before each step (both outside the timed section). That is what the controller
process sees in the closed loop — it sleeps on the bus while the plant, the hub and the
recorder run, so every MPC update starts on cold caches (in the process the MPC update
takes ≈ 3–4× its back-to-back time). E.g. ``--gap-ms 5 --evict-mb 8 --steps 400``.
"""

from __future__ import annotations

import cProfile
import gc
import io
import json
import math
import os
import pstats
import tempfile
import time
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from can_db.process.argcheck import OneLineParser, number
from controller.core.interfaces import ControllerInputs
from controller.core.params import VehicleParams, load_vehicle_params
from controller.core.registry import load_controller_config
from controller.registry import CONTROLLER_NAMES, make_controller
from harness.bench.stats import summarize_us

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


def bench_inputs(inp: ControllerInputs, plant: _Plant, t: float, rng: np.random.Generator,
                 vx_ref: float = 65.0 / 3.6) -> float:
    """Fill ``inp`` with the bench's inputs at time ``t`` s: DLC-like steering, a driver
    holding ``vx_ref`` m/s on the pedals (P control, so every step is timed at a paper-like
    speed rather than on a long coast-down), the plant's states with seeded sensor noise
    (drawn in the order vx, vy, r, ax, ay). Returns the steering-wheel angle, rad."""
    swa = dlc_swa(t)
    inp.swa_rad = swa
    pedal = 0.06 + 0.2 * (vx_ref - plant.vx)
    inp.accel_pedal, inp.brake_pedal = min(max(pedal, 0.0), 1.0), min(max(-pedal, 0.0), 1.0)
    inp.vx = plant.vx + rng.normal(0.0, 0.05)
    inp.vy = plant.vy + rng.normal(0.0, 0.03)
    inp.yaw_rate = plant.r + rng.normal(0.0, 0.003)
    inp.ax = plant.ax + rng.normal(0.0, 0.05)
    inp.ay = plant.ay + rng.normal(0.0, 0.05)
    inp.wheel_speeds[:] = plant.vx / plant.p.wheel_radius_m
    return swa


def dlc_swa(t: float, amp_deg: float = 25.0) -> float:
    """DLC-like steering-wheel angle, rad, period 8 s."""
    tt = (t % 8.0) - 1.0
    a = math.radians(amp_deg)
    if 0.0 <= tt < 2.5:
        return a * math.sin(2 * math.pi * tt / 2.5)
    if 3.5 <= tt < 6.0:
        return -a * math.sin(2 * math.pi * (tt - 3.5) / 2.5)
    return 0.0


def recorded_inputs(name: str, tmp: Path | None = None, steps: int = 300,
                    config: str | Path | None = None) -> list[ControllerInputs]:
    """Inputs of a closed-loop run of controller ``name``'s numpy reference (``config``: a
    TOML path, None → the packaged default.toml) on the bench plant (μ 0.35, 65 km/h,
    DLC-like steering, seeded sensor noise, seed 11): the recorded sequence the other
    variants (C core, microcontroller build, copies and restores) are replayed on. ``tmp``
    is not used (the packaged configuration is read in place); it is accepted so callers
    may pass their temporary folder."""
    del tmp
    c = make_controller(name, config, backend="numpy")
    p = load_vehicle_params()
    plant = _Plant(p, 0.35, 65 / 3.6)
    rng = np.random.default_rng(11)
    rec = []
    for k in range(steps):
        inp = ControllerInputs()
        swa = bench_inputs(inp, plant, k * c.ts, rng)
        rec.append(inp)
        o = c.step(inp)
        plant.step(o.torques, swa / p.steering_ratio, c.ts)
    return rec


def config_with(config: str | None, mpc_lines: str = "", ekf_lines: str = "") -> str:
    """Path of a temporary copy of a controller TOML (None → packaged default) with extra
    lines at the top of [mpc] and [rhonn.ekf] (e.g. ``precision = "float32"``)."""
    if config is None:
        text = resources.files("controller").joinpath("config/default.toml").read_text()
    else:
        text = Path(config).read_text()
    for table, lines in (("[mpc]", mpc_lines), ("[rhonn.ekf]", ekf_lines)):
        if lines:
            text = set_toml_keys(text, table, lines)
    fd, path = tempfile.mkstemp(prefix="rhonn-bench-", suffix=".toml")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    return path


def set_toml_keys(text: str, table: str, lines: str) -> str:
    """``text`` with the ``key = value`` lines set in ``table`` (existing keys replaced)."""
    new = [ln.strip() for ln in lines.splitlines() if ln.strip()]
    keys = {ln.split("=", 1)[0].strip() for ln in new}
    out: list[str] = []
    inside = False
    found = False
    for ln in text.splitlines():
        st = ln.strip()
        if st.startswith("["):
            inside = st.split("#", 1)[0].strip() == table
            if inside:
                found = True
                out.append(ln)
                out += new
                continue
        if inside and "=" in st and st.split("=", 1)[0].strip() in keys:
            continue
        out.append(ln)
    if not found:
        out += ["", table, *new]
    return "\n".join(out) + "\n"


PARTS = ("references", "ekf", "linearise", "qp", "allocation", "other")


class _PartTimer:
    """Wraps the parts of one numpy-reference MpcController (instance attributes) with
    perf_counter_ns (PARTS)."""

    def __init__(self, ctrl: Any) -> None:
        self.ns = dict.fromkeys(PARTS, 0)
        self._wrap(ctrl.references, "compute", "references")
        if hasattr(ctrl.model, "observe"):
            self._wrap(ctrl.model, "observe", "ekf")
        self._wrap(ctrl.qp, "_model_rollout", "linearise")
        self._wrap(ctrl.qp, "solve", "qp")
        self._wrap(ctrl.allocator, "allocate", "allocation")
        self._wrap(ctrl.allocator, "delta_m_capacity", "allocation")

    def _wrap(self, obj: Any, attr: str, part: str) -> None:
        fn = getattr(obj, attr)
        ns = self.ns
        clock = time.perf_counter_ns

        def timed(*a: Any, **k: Any) -> Any:
            t0 = clock()
            r = fn(*a, **k)
            ns[part] += clock() - t0
            return r

        setattr(obj, attr, timed)

    def take(self) -> dict[str, int]:
        """Per-part ns since the last take (QP excludes the model rollout it calls)."""
        out = dict(self.ns)
        out["qp"] -= out["linearise"]
        for k in self.ns:
            self.ns[k] = 0
        return out


def has_parts(ctrl: Any) -> bool:
    """True for a numpy-reference MPC controller (the parts _PartTimer wraps)."""
    return getattr(ctrl, "backend", "numpy") == "numpy" and hasattr(ctrl, "qp")


def run_one(name: str, steps: int, warmup: int, config: str | None,
            seed: int = 0, prof: cProfile.Profile | None = None,
            parts: bool = False, gap_s: float = 0.0, evict_mb: int = 0,
            backend: str | None = None) -> dict[str, Any]:
    """Closed-loop run of one controller; returns timing and iteration statistics.

    With ``prof``, the profiler is switched on around ``step()`` only (plant excluded).
    With ``parts`` (numpy reference only), every part is timed (per-part p50/p99/max in
    the result). ``gap_s`` s of sleep and a sweep over ``evict_mb`` MB before every step
    (untimed): cold steps, see the module docstring. ``backend``: as make_controller's."""
    ctrl = make_controller(name, config, backend=backend)
    timer = _PartTimer(ctrl) if parts and has_parts(ctrl) else None
    p = load_vehicle_params()
    vx_ref = 65.0 / 3.6
    plant = _Plant(p, mu=0.35, vx0=vx_ref)
    rng = np.random.default_rng(seed)
    inp = ControllerInputs()
    times = np.zeros(steps, dtype=np.int64)
    names = tuple(timer.ns) if timer is not None else PARTS
    part_ns = {k: np.zeros(steps, dtype=np.int64) for k in names}
    iters = np.zeros(steps)
    evict = np.zeros(evict_mb * (1 << 17)) if evict_mb > 0 else None  # float64: 8 B each
    gc.collect()
    for k in range(steps + warmup):
        swa = bench_inputs(inp, plant, k * ctrl.ts, rng, vx_ref)
        if gap_s > 0.0:
            time.sleep(gap_s)
        if evict is not None:
            evict += 1.0  # reads and writes every cache line of the buffer
        if prof is not None:
            prof.enable()
        t0 = time.perf_counter_ns()
        out = ctrl.step(inp)
        t1 = time.perf_counter_ns()
        if prof is not None:
            prof.disable()
        if timer is not None:
            got = timer.take()
            got["other"] = (t1 - t0) - sum(v for p_, v in got.items() if p_ != "other")
            if k >= warmup:
                for part, v in got.items():
                    part_ns[part][k - warmup] = v
        if k >= warmup:
            times[k - warmup] = t1 - t0
            iters[k - warmup] = out.qp_iterations
        plant.step(out.torques, swa / p.steering_ratio, ctrl.ts)
    us = times / 1e3
    qp = getattr(ctrl, "qp", None)
    refs = getattr(ctrl, "references", None)
    max_iter = load_controller_config(config).mpc.osqp.get("max_iter", 0)
    row: dict[str, Any] = {
        "name": name,
        "p50_us": float(np.percentile(us, 50)),
        "p99_us": float(np.percentile(us, 99)),
        "max_us": float(us.max()),
        "qp_iterations_mean": float(iters.mean()),
        "qp_iterations_max": int(iters.max()),
        "osqp_max_iter": int(max_iter) if qp is not None else 0,
        "max_iter_hits": int(getattr(qp, "max_iter_hits", 0)),
        "qp_fallbacks": int(getattr(qp, "fallbacks", 0)),
        "ref_not_converged": int(getattr(refs, "not_converged", 0)),
        "steps": steps,
        "gap_ms": gap_s * 1e3,
        "evict_mb": evict_mb,
        "backend": getattr(ctrl, "backend", "numpy"),
    }
    if timer is not None:
        row["parts"] = {k: summarize_us(v) for k, v in part_ns.items()}
    return row


def profile_rhonn(steps: int, config: str | None, top: int = 18,
                  backend: str | None = None) -> str:
    """cProfile summary (tottime) of nmpc-rhonn's step() over a closed-loop run."""
    prof = cProfile.Profile()
    run_one("nmpc-rhonn", steps, 0, config, prof=prof, backend=backend)
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    return buf.getvalue()


def _ratio(rows: dict[str, dict[str, Any]], a: str, b: str) -> dict[str, Any]:
    if a in rows and b in rows:
        return {"name": f"{a}/{b}",
                "p50_ratio": rows[a]["p50_us"] / rows[b]["p50_us"],
                "p99_ratio": rows[a]["p99_us"] / rows[b]["p99_us"]}
    return {"name": f"{a}/{b}", "p50_ratio": None, "p99_ratio": None}


PRECISION_LINES = {
    "float64": ("", ""),
    # float32 needs the UD EKF (the standard P update drifts in float32, see docs/controller.md)
    "float32": ('precision = "float32"', 'form = "ud"'),
}


def main(argv: list[str]) -> int:
    """Entry point: ``rhonn-bench controller [--json FILE] [--steps N] [--precision P]
    [--backend B] [--no-parts] [--profile] [--gap-ms G] [--evict-mb M]``."""
    ap = OneLineParser(prog="rhonn-bench controller", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the results as a JSON list")
    ap.add_argument("--steps", type=number(int, lo=1), default=4000,
                    help="timed steps per controller")
    ap.add_argument("--warmup", type=number(int, lo=0), default=20, help="untimed steps first")
    ap.add_argument("--config", default=None, help="controller TOML (default: paper 20 Hz)")
    ap.add_argument("--precision", choices=("float64", "float32", "both"), default="both")
    ap.add_argument("--backend", choices=("auto", "native", "numpy"), default=None,
                    help="override the controller backend (default: the config's "
                         "[controller] backend, or RHONN_BACKEND)")
    ap.add_argument("--ekf-form", choices=("standard", "ud"), default=None,
                    help="override [rhonn.ekf] form in float64 (float32 always uses ud)")
    ap.add_argument("--no-parts", action="store_true", help="skip the per-part run")
    ap.add_argument("--profile", action="store_true", help="cProfile nmpc-rhonn")
    ap.add_argument("--gap-ms", type=number(float, lo=0.0, hi=1000.0), default=0.0,
                    help="sleep this long before every step (untimed), ms")
    ap.add_argument("--evict-mb", type=number(int, lo=0, hi=4096), default=0,
                    help="sweep a buffer of this size before every step (untimed), MB")
    args = ap.parse_args(argv)
    precisions = ("float64", "float32") if args.precision == "both" else (args.precision,)
    results: list[dict[str, Any]] = []
    for prec in precisions:
        mpc_lines, ekf_lines = PRECISION_LINES[prec]
        if args.ekf_form is not None and prec == "float64":
            ekf_lines = f'form = "{args.ekf_form}"'
        cfg_path = config_with(args.config, mpc_lines.strip(), ekf_lines)
        rows: dict[str, dict[str, Any]] = {}
        try:
            for name in CONTROLLER_NAMES:
                try:
                    cold = {"gap_s": args.gap_ms / 1e3, "evict_mb": args.evict_mb,
                            "backend": args.backend}
                    rows[name] = run_one(name, args.steps, args.warmup, cfg_path, **cold)
                    if (not args.no_parts and name != "passive"
                            and rows[name]["backend"] == "numpy"):
                        rows[name]["parts"] = run_one(name, args.steps, args.warmup,
                                                      cfg_path, parts=True, **cold)["parts"]
                    rows[name]["precision"] = prec
                except ModuleNotFoundError as exc:
                    print(f"note: skipping {name}: {exc}")
            _print(prec, rows)
            ratios = [_ratio(rows, "nmpc-mf", "nmpc-rhonn"), _ratio(rows, "nmpc-rhonn", "lmpc")]
            for q in ratios:
                q["precision"] = prec
                if q["p50_ratio"] is None:
                    print(f"{q['name']:<22} n/a (a controller was skipped)")
                else:
                    print(f"{q['name']:<22} p50 ×{q['p50_ratio']:.2f}  "
                          f"p99 ×{q['p99_ratio']:.2f}")
            results += [*rows.values(), *ratios]
            if args.profile and prec == precisions[0]:
                print(profile_rhonn(min(args.steps, 2000), cfg_path, backend=args.backend))
        finally:
            os.unlink(cfg_path)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


def _print(prec: str, rows: dict[str, dict[str, Any]]) -> None:
    backends = sorted({r.get("backend", "") for r in rows.values()} - {""})
    first = next(iter(rows.values()), {})
    cold = (f", cold: {first['gap_ms']:g} ms gap + {first['evict_mb']} MB swept before each step"
            if first.get("gap_ms") or first.get("evict_mb") else "")
    print(f"== {prec} == (backend: {', '.join(backends) or 'n/a'}{cold})")
    print(f"{'controller':<12} {'p50 µs':>8} {'p99 µs':>8} {'max µs':>8} {'iter':>6} "
          f"{'iter max':>8} {'max_iter hits':>13} {'fallbacks':>9} {'refs n.c.':>9}")
    for r in rows.values():
        print(f"{r['name']:<12} {r['p50_us']:8.1f} {r['p99_us']:8.1f} {r['max_us']:8.1f} "
              f"{r['qp_iterations_mean']:6.2f} {r['qp_iterations_max']:8d} "
              f"{r['max_iter_hits']:>9d}/{r['osqp_max_iter']:<3d} {r['qp_fallbacks']:9d} "
              f"{r['ref_not_converged']:9d}")
    for r in rows.values():
        if "parts" not in r:
            continue
        cells = "  ".join(f"{k} {v['p50_us']:.1f}/{v['p99_us']:.1f}/{v['max_us']:.0f}"
                          for k, v in r["parts"].items())
        print(f"  {r['name']:<11} parts p50/p99/max µs: {cells}")


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
