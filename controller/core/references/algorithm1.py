"""RHONN steady-state references (paper eq. 18–20, Algorithm 1 "neighbors-searching").

The references are the fixed point (Vyd, ωrd) of the learned lateral map at the current
Vx and δw, with ΔM = 0 (the vehicle's own steady state for the driver's steering):

    Vyd = F_vy(Vx, Vyd, ωrd, δw),   ωrd = F_r(Vx, Vyd, ωrd, δw)            (eq. 18–19)

cost(Vy, ωr) = |F_vy − Vy| + η |F_r − ωr|   (m/s; η in (m/s)/(rad/s))

Search (deterministic, bounded):
1. Centre C0 = the latest measured (Vy, ωr) — the "previous state" that Algorithm 1
   searches around; initial radius r_s0 = (rs0_vy m/s, rs0_r rad/s).
2. Evaluate the cost on an n×n grid over the neighbourhood ∩ physical limits (vectorised;
   at fixed Vx, δw the map is bilinear in S(Vy), S(ωr), see RhonnModel.bilinear_coefficients).
   The best node minimises cost + ε_t·d² (d: distance to C0 in radii), so equal costs go to
   the node nearest the previous state. (A bare argmin picked the box corner on a flat map:
   the cold-start RHONN, W = 0, where every point is a fixed point.)
3. Polish the best grid point with ≤ newton_iters damped Newton steps on the 2×2 fixed-point
   equations (accepted only if the cost decreases and the point stays in the searched
   area) — a cheap replacement for an ever finer grid.
4. Cost ≤ ε_t → done. Else grow the radius by Δr_s and repeat, at most max_rounds times;
   then the best point found is used and ``not_converged`` is counted.

Physical limits (no road μ; the controller never gets it):
  |ωr| ≤ a_max / Vx, a_max = clip(ay_margin · envelope(|ay| measured), ay_floor, ay_ceiling)
  (envelope: peak hold with exponential decay, time constant ay_decay_s);
  |Vy| ≤ tan(beta_max) · Vx;
  ωr between min(0, k_kin ρ) − r_band and max(0, k_kin ρ) + r_band with ρ = Vx δw / L the
  neutral-steer yaw rate: the steady state turns the way the wheels point, at most k_kin
  times faster than kinematically (k_kin = 1.5 covers this slightly oversteering car).
  If the whole feasible box was searched without reaching ε_t, the search stops early.
Low speed (Vx < v_min): kinematic references ωrd = Vx δw / L, Vyd = lr ωrd, βd = Vyd/v_min.
βd = Vyd / max(Vx, v_min) (eq. 20, guarded).

Measured on our plant: where |ωr| > 5°/s the fixed point sits at ≈ 0.96–0.97 × the
measured yaw rate on dlc-paper (the map has just fitted the transient, so its equilibrium
lies just behind the state) and the NMPC mostly damps yaw, which costs lane keeping
(v_max 70.5–71 vs 76.5 km/h for nmpc-mf, 3 seeds). In a quasi-steady corner it matches the
car (constant-radius, μ 0.35/0.7/1.0: 0.994–1.008 × the measured yaw rate). It is therefore
used where it helps — as the sideslip grows — by the default ``demand`` references
(references/intent.py, chosen by references/factory.py); ``kind = "algorithm1"`` keeps it
alone. ``slow_tau_s`` > 0 runs it on a slowly updated weight copy (slow_weights.py).

No reference smoothing. Tried (in-process loop): a first-order low-pass on ωrd and Vyd
(τ = 0.025–0.3 s), on Vyd only (τ = 0.02–0.3 s) and rate limits (ωrd 1–2 rad/s², Vyd
0.25–2 m/s²). Each cut the ΔM total variation on dlc-paper but none helped everywhere:
filtering ωrd adds lag (dlc-paper 65 km/h, τ = 0.05 s: max|β| 2.58 → 2.92°, phase area
0.0125 → 0.0137; τ ≥ 0.2 s: max|dev| > 1 m), Vyd-only τ = 0.1 s moves slippery-curve max|dev|
1.40 → 1.97 m, a Vyd rate limit of 2 m/s² raises dlc-paper 70 km/h max|β| 3.00 → 3.19°.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.core.config_schema import build_section
from controller.core.model.rhonn import RhonnModel
from controller.core.params import VehicleParams
from controller.core.references.slow_weights import SlowWeights


@dataclass(slots=True)
class RhonnRefConfig:
    """Reference search tuning.

    eta: weight of the ωr residual, (m/s)/(rad/s). eps_t: threshold on the cost, m/s.
    rs0_vy m/s, rs0_r rad/s: initial search radius; drs_vy m/s, drs_r rad/s: growth per
    round. grid_n: points per axis. max_rounds: radius rounds. newton_iters: polish steps.
    beta_max: sideslip limit, rad. ay_floor, ay_ceiling: bounds on a_max, m/s².
    ay_margin: factor on the |ay| envelope, -. ay_decay_s: envelope decay time constant, s.
    v_min: below this speed, m/s, references are kinematic. r_kin_factor: bound on ωrd
    relative to the neutral-steer yaw rate Vx δw / L, -. r_band: sign tolerance, rad/s.
    ts: call period, s.
    kind: which reference design the nmpc-rhonn controller uses ("algorithm1" = this
    module; "intent" = references/intent.py; see references/factory.py).
    slow_tau_s: time constant of the weight copy the references read, s (0 = the live EKF
    weights; see references/slow_weights.py).
    intent_lead_s: driver-intent references only: lead time on the steering rate, s
    (0 = steady state only). intent_ay_margin: driver-intent references only: |ωrd| ≤
    a_max/Vx with a_max = clip(intent_ay_margin × envelope(|ay|), ay_floor, ay_ceiling)
    (0 = no friction limit).
    blend_beta_lo, blend_beta_hi: "blend" references: measured |β|, rad, at which the
    Algorithm-1 share starts / is complete (see references/intent.BlendedReferences).
    guard_beta_rad: |β| threshold of the sideslip guard, rad; guard_gain_per_s: its
    demanded decay rate of the excess, 1/s (0 = no guard; references/sideslip_guard.py).
    guard_lead_s: the guard acts on β + T·β̇ (β̇ = ay/Vx − ωr), T in s (0 = on β alone).
    grip_beta_per_g, grip_beta_max: grip-scaled sideslip thresholds: θ = clip(grip_beta_per_g
    × envelope(|ay|)/g, guard_beta_rad, grip_beta_max) (rad per g, rad; 0 = off) replaces
    guard_beta_rad, and blend_beta_lo/hi are scaled by θ/guard_beta_rad.
    """

    eta: float = 5.0
    eps_t: float = 1e-4
    rs0_vy: float = 0.3
    rs0_r: float = 0.05
    drs_vy: float = 1.0
    drs_r: float = 0.15
    grid_n: int = 9
    max_rounds: int = 3
    newton_iters: int = 3
    beta_max: float = 0.12
    ay_floor: float = 4.0
    ay_ceiling: float = 9.5
    ay_margin: float = 1.15
    ay_decay_s: float = 3.0
    v_min: float = 3.0
    r_kin_factor: float = 1.5
    r_band: float = 0.02
    ts: float = 0.05
    kind: str = "algorithm1"
    slow_tau_s: float = 0.0
    intent_lead_s: float = 0.0
    intent_ay_margin: float = 0.0
    blend_beta_lo: float = 0.035
    blend_beta_hi: float = 0.07
    guard_beta_rad: float = 0.035
    guard_gain_per_s: float = 0.0
    guard_lead_s: float = 0.0
    grip_beta_per_g: float = 0.0
    grip_beta_max: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RhonnRefConfig:
        """Build from the [references] table; unknown keys and wrong types raise ConfigError."""
        return build_section(cls, d, "references")


class RhonnReferences:
    """ReferenceGenerator using the learned RHONN map (shares the model's weights)."""

    def __init__(self, model: RhonnModel, params: VehicleParams,
                 cfg: RhonnRefConfig | None = None) -> None:
        self.model = model
        self.params = params
        self.cfg = cfg or RhonnRefConfig()
        n = int(self.cfg.grid_n)
        if n < 3 or n % 2 == 0:
            raise ValueError("references.grid_n must be odd and >= 3 (the centre is a node)")
        self._unit = np.linspace(-1.0, 1.0, n)[None, :]
        self._half = np.zeros((2, 1))
        self._mid = np.zeros((2, 1))
        self._nodes = np.zeros((2, n))
        self._xi = np.zeros((2, n))
        self._sbeta = np.array([[model._beta[1]], [model._beta[2]]])
        self._smu = np.array([[model._mu[1]], [model._mu[2]]])
        self._t1 = np.zeros((2, n, 1))
        self._t2 = np.zeros((2, n, 1))
        self._g = np.zeros((2, n, n))
        self._cost = np.zeros((n, n))
        self._sel = np.zeros((n, n))
        self._dv = np.zeros(n)
        self._dr = np.zeros(n)
        self._decay = math.exp(-self.cfg.ts / self.cfg.ay_decay_s)
        self.weights = SlowWeights(model, self.cfg.slow_tau_s, self.cfg.ts)
        self.ay_envelope = 0.0
        self.not_converged = 0
        self.rounds_last = 0
        self.cost_last = 0.0

    def reset(self) -> None:
        """Forget the |ay| envelope, the counters and the slow weight copy."""
        self.weights.reset()
        self.ay_envelope = 0.0
        self.not_converged = 0
        self.rounds_last = 0
        self.cost_last = 0.0

    # ------------------------------------------------------------------ helpers
    def a_max(self) -> float:
        """Current lateral-acceleration bound used for the yaw-rate limit, m/s²."""
        c = self.cfg
        return min(max(c.ay_margin * self.ay_envelope, c.ay_floor), c.ay_ceiling)

    def _residual(self, coef: np.ndarray, vy: float, r: float) -> tuple[float, float]:
        """Fixed-point residuals (F_vy − Vy m/s, F_r − ωr rad/s) at one point."""
        m = self.model
        a = m.xi(1, vy)
        b = m.xi(2, r)
        gv = coef[1, 0] + coef[1, 1] * a + coef[1, 2] * b + coef[1, 3] * a * b
        gr = coef[2, 0] + coef[2, 1] * a + coef[2, 2] * b + coef[2, 3] * a * b
        if not m.increment:
            gv -= vy
            gr -= r
        return gv, gr

    def _grid(self, coef: np.ndarray, lo_v: float, hi_v: float, lo_r: float,
              hi_r: float, cv: float, cr: float, rv: float,
              rr: float) -> tuple[float, float, float]:
        """Vectorised cost over the n×n grid; returns (best vy, best r, best cost).

        Ties are broken towards the centre (cv m/s, cr rad/s): the selection minimises
        cost + ε_t·d², d = distance to the centre normalised by the radius (rv, rr), so
        among points within ε_t of the best cost the one nearest the previous state wins
        (Algorithm 1: "the nearby equilibrium"). The returned cost is the raw cost."""
        m = self.model
        nodes, xi, g, cost = self._nodes, self._xi, self._g, self._cost
        # Row 0: Vy nodes, row 1: ωr nodes, spanning the neighbourhood ∩ limits.
        hv, hr = 0.5 * (hi_v - lo_v), 0.5 * (hi_r - lo_r)
        self._half[0, 0], self._half[1, 0] = hv, hr
        self._mid[0, 0], self._mid[1, 0] = lo_v + hv, lo_r + hr
        np.multiply(self._unit, self._half, out=nodes)
        nodes += self._mid
        np.multiply(nodes, self._sbeta, out=xi)
        np.tanh(xi, out=xi)
        xi *= self._smu                       # xi[0] = S(Vy) nodes, xi[1] = S(ωr) nodes
        # g_k(a, b) = (c0 + c1 a) + (c2 + c3 a) b for k ∈ {Vy, ωr}, both at once: (2, n, n)
        c = coef[1:3]
        a = xi[0][None, :, None]
        np.multiply(c[:, 3, None, None], a, out=self._t2)
        self._t2 += c[:, 2, None, None]
        np.multiply(self._t2, xi[1][None, None, :], out=g)
        np.multiply(c[:, 1, None, None], a, out=self._t1)
        self._t1 += c[:, 0, None, None]
        g += self._t1
        if not m.increment:
            g[0] -= nodes[0][:, None]
            g[1] -= nodes[1][None, :]
        np.abs(g, out=g)
        g[1] *= self.cfg.eta
        np.add(g[0], g[1], out=cost)
        # Tie-break towards the centre. Without it a flat map — the cold-start RHONN
        # (W = 0: every point is a fixed point of the increment form) — returned the
        # first grid node, i.e. the CORNER of the search box: Vyd = Vy − 0.3 m/s and
        # ωrd at the band edge while driving straight (measured on dlc-paper, t = 0).
        dv, dr = self._dv, self._dr
        np.subtract(nodes[0], cv, out=dv)
        dv *= 1.0 / rv
        np.square(dv, out=dv)
        np.subtract(nodes[1], cr, out=dr)
        dr *= 1.0 / rr
        np.square(dr, out=dr)
        sel = self._sel
        np.add(dv[:, None], dr[None, :], out=sel)
        sel *= self.cfg.eps_t
        sel += cost
        k = int(np.argmin(sel))
        i, j = divmod(k, cost.shape[1])
        return float(nodes[0, i]), float(nodes[1, j]), float(cost[i, j])

    def _newton(self, coef: np.ndarray, vy: float, r: float, cost: float,
                lo_v: float, hi_v: float, lo_r: float, hi_r: float) -> tuple[float, float, float]:
        """Bounded Newton polish of the fixed-point equations inside the box."""
        m, eta = self.model, self.cfg.eta
        for _ in range(self.cfg.newton_iters):
            gv, gr = self._residual(coef, vy, r)
            a = m.xi(1, vy)
            b = m.xi(2, r)
            da = m.dxi(1, vy)
            db = m.dxi(2, r)
            j11 = (coef[1, 1] + coef[1, 3] * b) * da
            j12 = (coef[1, 2] + coef[1, 3] * a) * db
            j21 = (coef[2, 1] + coef[2, 3] * b) * da
            j22 = (coef[2, 2] + coef[2, 3] * a) * db
            if not m.increment:
                j11 -= 1.0
                j22 -= 1.0
            det = j11 * j22 - j12 * j21
            if not math.isfinite(det) or abs(det) < 1e-12:
                break
            nv = min(max(vy - (j22 * gv - j12 * gr) / det, lo_v), hi_v)
            nr = min(max(r - (j11 * gr - j21 * gv) / det, lo_r), hi_r)
            ngv, ngr = self._residual(coef, nv, nr)
            ncost = abs(ngv) + eta * abs(ngr)
            if not ncost < cost:
                break
            vy, r, cost = nv, nr, ncost
            if cost <= self.cfg.eps_t:
                break
        return vy, r, cost

    # ------------------------------------------------------------------ API
    def compute(self, vx: float, vy: float, yaw_rate: float, delta_w: float,
                total_torque: float, ay_meas: float) -> tuple[float, float, float]:
        """(ωrd rad/s, Vyd m/s, βd rad) for Vx m/s, measured Vy m/s and ωr rad/s,
        road-wheel angle δw rad, Tt N·m (unused: ΔM = 0 steady state, Vx held),
        measured ay m/s² (envelope for the yaw-rate limit)."""
        c = self.cfg
        p = self.params
        if math.isfinite(ay_meas):
            self.ay_envelope = max(abs(ay_meas), self.ay_envelope * self._decay)
        self.weights.update()
        if not (math.isfinite(vx) and math.isfinite(delta_w)):
            return 0.0, 0.0, 0.0
        if not math.isfinite(vy):
            vy = 0.0
        if not math.isfinite(yaw_rate):
            yaw_rate = 0.0
        if vx < c.v_min:
            v = max(vx, 0.0)
            r_d = v * delta_w / p.wheelbase_m
            vy_d = p.lr_m * r_d
            return r_d, vy_d, vy_d / c.v_min
        r_lim = self.a_max() / vx
        v_lim = math.tan(c.beta_max) * vx
        # Yaw-rate band: |ωr| ≤ a_max/Vx, and between 0 and k_kin × the neutral-steer
        # (kinematic) value Vx δw / L, widened by r_band: the steady state of a stable car
        # turns the way the wheels point and not much faster than kinematically.
        r_kin = c.r_kin_factor * vx * delta_w / p.wheelbase_m
        r_lo = max(min(r_kin, 0.0) - c.r_band, -r_lim)
        r_hi = min(max(r_kin, 0.0) + c.r_band, r_lim)
        if self.weights.tau_s > 0.0:
            coef = self.weights.coefficients(vx, delta_w)
        else:
            coef = self.model.bilinear_coefficients(vx, delta_w)
        cv = min(max(vy, -v_lim), v_lim)
        cr = min(max(yaw_rate, r_lo), r_hi)
        best = (cv, cr, math.inf)
        rounds = 0
        for k in range(c.max_rounds):
            rounds = k + 1
            rv = c.rs0_vy + k * c.drs_vy
            rr = c.rs0_r + k * c.drs_r
            lo_v, hi_v = max(cv - rv, -v_lim), min(cv + rv, v_lim)
            lo_r, hi_r = max(cr - rr, r_lo), min(cr + rr, r_hi)
            gvy, gr, gcost = self._grid(coef, lo_v, hi_v, lo_r, hi_r, cv, cr, rv, rr)
            gvy, gr, gcost = self._newton(coef, gvy, gr, gcost, lo_v, hi_v, lo_r, hi_r)
            if gcost < best[2]:
                best = (gvy, gr, gcost)
            if best[2] <= c.eps_t:
                break
            if lo_v <= -v_lim and hi_v >= v_lim and lo_r <= r_lo and hi_r >= r_hi:
                # The whole feasible box is searched: the fixed point lies outside the
                # limits, growing the radius cannot help. Use the best feasible point.
                self.not_converged += 1
                break
        else:
            self.not_converged += 1
        self.rounds_last = rounds
        vy_d, r_d, self.cost_last = best
        if not (math.isfinite(vy_d) and math.isfinite(r_d)):
            vy_d, r_d = cv, cr
        return r_d, vy_d, vy_d / vx

    def get_state(self) -> dict[str, np.ndarray | float]:
        """Persistent state: the |ay| envelope, m/s², and the slow weight copy."""
        d: dict[str, np.ndarray | float] = {"ref.ay_envelope": float(self.ay_envelope)}
        d.update(self.weights.get_state())
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore get_state()."""
        self.ay_envelope = float(d["ref.ay_envelope"])
        self.weights.set_state(d)
