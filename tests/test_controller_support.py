"""Test support for the controller tests: a small single-track vehicle simulator.

It is independent of the controller code (own equations, own tyre model) so it can serve
as the reference plant. Nonlinear by default (simplified Magic Formula lateral tyre with
friction coefficient mu), or linear (Fy = C·α, Table 1 stiffness) with ``linear=True``.
Sign convention ISO 8855 (+ left). The self-tests at the bottom check it against the
closed-form steady-state yaw gain of the linear bicycle.
"""

from __future__ import annotations

import math

import numpy as np

from controller.core.interfaces import ControllerInputs
from controller.core.params import VehicleParams, load_vehicle_params

G = 9.81


class BicycleSim:
    """Planar single-track model: states vx m/s, vy m/s, r rad/s; explicit Euler at 1 ms.

    Inputs: wheel torques (4,) N·m (1 FL, 2 FR, 3 RL, 4 RR), road-wheel angle rad.
    Longitudinal force = ΣT / r (no wheel slip); yaw moment from torques = ΔM·wB/(2r).
    """

    def __init__(self, params: VehicleParams | None = None, mu: float = 1.0,
                 linear: bool = False, dt: float = 1e-3) -> None:
        self.p = params or load_vehicle_params()
        self.mu = mu
        self.linear = linear
        self.dt = dt
        p = self.p
        L = p.lf_m + p.lr_m
        self.fzf = p.mass_kg * G * p.lr_m / L
        self.fzr = p.mass_kg * G * p.lf_m / L
        self.cf = abs(p.cf_axle_n_per_rad)
        self.cr = abs(p.cr_axle_n_per_rad)
        self.vx = self.vy = self.r = 0.0
        self.ax = self.ay = 0.0

    def reset(self, vx: float) -> None:
        """Straight-line start at vx m/s."""
        self.vx, self.vy, self.r = vx, 0.0, 0.0
        self.ax = self.ay = 0.0

    def _fy(self, alpha: float, c_alpha: float, fz: float) -> float:
        if self.linear:
            return c_alpha * alpha
        d = self.mu * fz
        c = 1.3
        b = c_alpha / (c * d)
        return d * math.sin(c * math.atan(b * alpha))

    def step(self, torques: np.ndarray, delta_w: float, t_step: float) -> None:
        """Advance t_step s with constant inputs."""
        p = self.p
        m, iz = p.mass_kg, p.yaw_inertia_kgm2
        fx = float(np.sum(torques)) / p.wheel_radius_m
        dm = float(torques[1] + torques[3] - torques[0] - torques[2])
        mz_t = dm * p.track_m / (2.0 * p.wheel_radius_m)
        n = max(1, round(t_step / self.dt))
        h = t_step / n
        for _ in range(n):
            vx = max(self.vx, 1.0)
            af = delta_w - math.atan2(self.vy + p.lf_m * self.r, vx)
            ar = -math.atan2(self.vy - p.lr_m * self.r, vx)
            fyf = self._fy(af, self.cf, self.fzf)
            fyr = self._fy(ar, self.cr, self.fzr)
            drag = 0.4 * self.vx * abs(self.vx) + 150.0
            ax = (fx - fyf * math.sin(delta_w) - drag) / m
            ay = (fyf * math.cos(delta_w) + fyr) / m
            dvx = ax + self.vy * self.r
            dvy = ay - self.vx * self.r
            dr = (p.lf_m * fyf * math.cos(delta_w) - p.lr_m * fyr + mz_t) / iz
            self.vx += h * dvx
            self.vy += h * dvy
            self.r += h * dr
            self.ax, self.ay = ax, ay


def dlc_swa(t: float, amp_deg: float = 90.0, t0: float = 1.0, period: float = 2.5) -> float:
    """DLC-like steering-wheel angle, rad: one full sine, a pause, one opposite sine."""
    tt = t - t0
    a = math.radians(amp_deg)
    if 0.0 <= tt < period:
        return a * math.sin(2 * math.pi * tt / period)
    if period + 1.0 <= tt < 2 * period + 1.0:
        return -a * math.sin(2 * math.pi * (tt - period - 1.0) / period)
    return 0.0


def fill_inputs(inp: ControllerInputs, sim: BicycleSim, swa: float,
                rng: np.random.Generator | None = None, noise: float = 1.0) -> None:
    """Copy the simulator's state into the controller inputs (optionally with sensor noise:
    σ = 0.05 m/s vx, 0.03 m/s vy, 0.003 rad/s r, 0.05 m/s² ax/ay, times noise)."""
    def nz(s: float) -> float:
        return float(rng.normal(0.0, s * noise)) if rng is not None else 0.0
    inp.swa_rad = swa
    inp.vx = sim.vx + nz(0.05)
    inp.vy = sim.vy + nz(0.03)
    inp.yaw_rate = sim.r + nz(0.003)
    inp.ax = sim.ax + nz(0.05)
    inp.ay = sim.ay + nz(0.05)
    inp.wheel_speeds[:] = sim.vx / sim.p.wheel_radius_m


def test_linear_sim_matches_closed_form_yaw_gain() -> None:
    """Independent check of the reference plant: steady-state r/δ of the linear bicycle."""
    p = load_vehicle_params()
    sim = BicycleSim(p, linear=True)
    vx, delta = 20.0, 0.02
    sim.reset(vx)
    hold = np.full(4, (0.4 * vx * vx + 150.0) * p.wheel_radius_m / 4)  # cancel drag
    for _ in range(100):
        sim.step(hold, delta, 0.05)
    L = p.lf_m + p.lr_m
    cf, cr = abs(p.cf_axle_n_per_rad), abs(p.cr_axle_n_per_rad)
    k_us = p.mass_kg / L * (p.lr_m / cf - p.lf_m / cr)
    r_ss = sim.vx * delta / (L + k_us * sim.vx**2)
    assert sim.r == pytest_approx(r_ss, rel=2e-2)


def test_nonlinear_sim_saturates_at_mu_g() -> None:
    """At a large steering angle the lateral acceleration stays below μ g (+ tolerance)."""
    sim = BicycleSim(mu=0.35)
    sim.reset(18.0)
    peak = 0.0
    for _ in range(60):
        sim.step(np.zeros(4), 0.15, 0.05)
        peak = max(peak, abs(sim.ay))
    assert 0.25 * G < peak < 0.37 * G


def pytest_approx(v: float, rel: float) -> object:
    """Late import keeps this module importable without pytest in a plain script."""
    import pytest

    return pytest.approx(v, rel=rel)


def node_period(ctrl: object, inp: object, sim: BicycleSim, delta_w: float,
                cycles: int = 5) -> object:
    """One MPC period as the node runs it: ``step()`` then ``cycles − 1`` × ``allocate_only()``
    with the same inputs, the simulator advanced one communication cycle (ts / cycles, s)
    with each answer's torques (the allocation slews the motors per cycle). Returns the
    ``step()`` outputs' copy of the torques and ΔM as the period's first answer."""
    dt = ctrl.ts / cycles  # type: ignore[attr-defined]
    o = ctrl.step(inp)  # type: ignore[attr-defined]
    first = (o.torques.copy(), float(o.delta_m))
    sim.step(o.torques.copy(), delta_w, dt)
    for _ in range(cycles - 1):
        o = ctrl.allocate_only(inp)  # type: ignore[attr-defined]
        sim.step(o.torques.copy(), delta_w, dt)
    return first
