"""Recurrent high-order neural network (RHONN) model of the planar vehicle (paper eq. 5–17).

States χ = [Vx m/s, Vy m/s, ωr rad/s]; inputs u = [Tt N·m, ΔM N·m, δw rad].
Steering input: δw is the *road-wheel* angle, rad = steering-wheel angle / steering ratio.
(The paper calls δw the "steering wheel angle", but eq. 15 uses the front-wheel angle δf;
the two differ only by the constant ratio, which the learned weights would absorb anyway.
We use the road-wheel angle so the scaling below has a physical meaning.)

Neurons (appendix): ξ = [S(Vx), S(Vy), S(ωr), S(δw)], S_j(x) = μ_j tanh(β_j x), and
φ = the 15 products of distinct non-empty subsets of ξ, in the paper's order
(4 singles, 6 pairs, 4 triples, 1 quadruple).

Scaling (default, ``[rhonn]`` in default.toml): μ_j = 1 and β_j = 1 / x_ref,j with
x_ref = [30 m/s, 3 m/s, 0.6 rad/s, 0.15 rad]. So |ξ_j| < 1 always (|φ_k| < 1, which keeps
the EKF well conditioned and the weights in state units), the tanh is nearly linear over
normal driving (Vx ≤ 30 m/s → tanh(1) = 0.76), and it bends where the tyres saturate
(|Vy| of a few m/s, |δw| ≳ 0.1 rad), giving the polynomial a saturating shape to work with.

Known parts (eq. 8/17): Ts·Tt/(m r) on Vx and Ts·wB/(2 Iz r)·ΔM on ωr. Eq. 17 omits Ts,
but those are accelerations (m/s², rad/s²), so the discrete map multiplies them by Ts.

Forms (``form``):
* ``"literal"`` — eq. 17 verbatim: χ_{k+1} = known + W φ(χ_k, u_k).
* ``"increment"`` (default) — χ_{k+1} = χ_k + known + W φ(χ_k, u_k): the network learns the
  per-step change (Ts·f) instead of the whole next state. Chosen by measurement on
  nonlinear single-track data (simplified MF tyres, 65 km/h, DLC-like steering, sensor
  noise, 40 s at 20 Hz): one-step RMSE vy 0.030 vs 0.039 m/s and ωr 0.0058 vs 0.0072 rad/s
  at μ = 0.7 (0.026/0.027 m/s and 0.0040/0.0041 rad/s at μ = 0.35), 3-step parallel RMSE vy
  0.051 vs 0.081 m/s; when the car slid (vy up to 11 m/s) the literal form's vy one-step
  error was 0.82 m/s vs 0.047 m/s. The literal form has to rebuild the identity map
  through saturated tanh features (e.g. Vx ≈ w·tanh(Vx/30)), which the EKF only tracks
  locally, and its cold start predicts χ = 0. The increment form starts at
  "χ_{k+1} = χ_k"; S(Vx) acts as the bias term of the increment.

Identification is series-parallel (φ on the measured state, e = x − χ, eq. 10);
prediction inside the horizon is parallel (φ on the model's own prediction, eq. 21).

Deviations for the closed loop on our plant (default.toml, each measured there):
* Actuator dead time T_d (``dm_dead_time_s``): the known ΔM part is
  k·[(Ts − T_d)·ΔM_k + T_d·ΔM_{k−1}], k = wB/(2 Iz r), instead of Ts·k·ΔM_k. The plant's
  ωr responds to a 50 ms ΔM pulse with only 0.61 of Ts·k·ΔM inside the period (motor lag
  15 ms + one bus cycle); the rest arrives in the next period. ΔM is not an argument of φ,
  so the EKF cannot learn this: with T_d = 0 every ΔM change left a ±0.03 rad/s one-step
  error that the EKF fitted into the state weights, which drove the ΔM bang-bang. With
  T_d = 20 ms the closed-loop one-step ωr RMS error is 0.002–0.007 rad/s. The MPC reads
  ∂χ_{k+1}/∂ΔM_{k−1} from ``b_prev`` (nmpc.LinearizedMpc); the previously applied ΔM comes
  in ``PredictionContext.delta_m_prev``. T_d = 0 is eq. 17 exactly.
* Learned ΔM effectiveness (``dm_gain_p0`` > 0; off by default): the known ΔM part is
  θ·k·[…], with θ estimated jointly with the yaw row's weights (learning/input_gain.py);
  the yaw row is then learned by that filter, and b, b_prev follow θ.
* Model-confidence gate (``gate_*``, ``confidence()``): the MPC's ΔM box is scaled by a
  confidence that is 0 for the first ``gate_warmup_s`` of learning, then ramps with the
  filtered one-step ωr error and latches open once converged. The paper shows the RHONN
  converging in < 1 s from a cold start but does not say what the controller does
  meanwhile; cold weights (W = 0) gave ±1800 N·m on the straight lead-in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controller.core.config_schema import ConfigError, build_section
from controller.core.interfaces import ControllerInputs, PredictionContext
from controller.core.learning.ekf import BatchedEkf, EkfConfig
from controller.core.learning.input_gain import YawGainFilter
from controller.core.learning.ud_ekf import UdEkf
from controller.core.params import VehicleParams

N_PHI = 15
N_XI = 4

# Paper order of the 15 products (indices into ξ = [Vx, Vy, ωr, δw]).
PHI_SUBSETS: tuple[tuple[int, ...], ...] = (
    (0,), (1,), (2,), (3,),
    (0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3),
    (0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3),
    (0, 1, 2, 3),
)


def _build_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index tables for derivatives and the (Vy, ωr) bilinear collapse.

    deriv[j, k]: index into φ_ext = [1, φ_1..φ_15, 0] of ∂φ_k/∂ξ_j (16 → zero).
    mono[k] ∈ {0: 1, 1: ξ2, 2: ξ3, 3: ξ2ξ3}; tfac[k] ∈ {0: 1, 1: ξ1, 2: ξ4, 3: ξ1ξ4}.
    """
    pos = {s: i + 1 for i, s in enumerate(PHI_SUBSETS)}
    pos[()] = 0
    deriv = np.full((N_XI, N_PHI), N_PHI + 1, dtype=np.intp)
    mono = np.zeros(N_PHI, dtype=np.intp)
    tfac = np.zeros(N_PHI, dtype=np.intp)
    for k, s in enumerate(PHI_SUBSETS):
        for j in s:
            deriv[j, k] = pos[tuple(i for i in s if i != j)]
        mono[k] = (1 if 1 in s else 0) + (2 if 2 in s else 0)
        tfac[k] = (1 if 0 in s else 0) + (2 if 3 in s else 0)
    return deriv, mono, tfac


DERIV_INDEX, MONO_INDEX, TFAC_INDEX = _build_tables()


def phi_batch(xi: np.ndarray) -> np.ndarray:
    """φ for any batch of ξ (..., 4) → (..., 15), paper order (reference implementation)."""
    xi = np.asarray(xi, dtype=float)
    out = np.empty((*xi.shape[:-1], N_PHI))
    for k, s in enumerate(PHI_SUBSETS):
        p = xi[..., s[0]].copy()
        for j in s[1:]:
            p = p * xi[..., j]
        out[..., k] = p
    return out


@dataclass(slots=True)
class RhonnConfig:
    """RHONN structure. mu (4,): output scale of S, -. beta (4,): input gains of S in
    1/(m/s), 1/(m/s), 1/(rad/s), 1/rad for [Vx, Vy, ωr, δw]. form: "increment" | "literal".
    dm_dead_time_s: effective actuator dead time T_d of the known ΔM part, s (0 = eq. 17;
    clamped to [0, Ts]). Model-confidence gate (see ``confidence``): gate_warmup_s,
    learning time before any ΔM, s; gate_tau_s: time constant of the filtered one-step ωr
    error, s; gate_err_lo / gate_err_hi: filtered RMS ωr error, rad/s, at which the
    confidence is 1 / 0 (gate_err_hi = 0 disables the gate: confidence 1 always).
    ekf: learning tuning (see ekf.EkfConfig). init_seed: 0 = cold start at W0 = 0 (paper);
    any other value draws W0 ~ N(0, init_w_std²) element-wise from that seed (state units),
    so multi-seed studies vary the RHONN's initial state deterministically.
    dm_gain_p0: prior variance of the learned ΔM effectiveness θ, -² (0 = off: θ = 1, the
    nominal gain; learning/input_gain.py); dm_gain_min / dm_gain_max: its bounds, -."""

    form: str = "increment"
    dm_dead_time_s: float = 0.0
    gate_warmup_s: float = 0.0
    gate_tau_s: float = 0.5
    gate_err_lo: float = 0.0
    gate_err_hi: float = 0.0
    mu: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    beta: tuple[float, ...] = (1.0 / 30.0, 1.0 / 3.0, 1.0 / 0.6, 1.0 / 0.15)
    ekf: EkfConfig = field(default_factory=EkfConfig)
    init_seed: int = 0
    init_w_std: float = 1e-3
    dm_gain_p0: float = 0.0
    dm_gain_min: float = 0.4
    dm_gain_max: float = 2.5

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RhonnConfig:
        """Build from the [rhonn] table (with an optional [rhonn.ekf] sub-table)."""
        cfg = build_section(cls, {k: v for k, v in d.items() if k != "ekf"}, "rhonn")
        if "ekf" in d:
            cfg.ekf = EkfConfig.from_dict(d["ekf"])
        if cfg.form not in ("increment", "literal"):
            raise ConfigError("rhonn", "form",
                              f"must be 'increment' or 'literal', not {cfg.form!r}")
        if not 0.0 <= float(cfg.dm_dead_time_s) < 1.0:
            raise ConfigError("rhonn", "dm_dead_time_s", "must be in [0, 1) s")
        if cfg.gate_err_hi > 0.0 and not 0.0 <= cfg.gate_err_lo < cfg.gate_err_hi:
            raise ConfigError("rhonn", "gate_err_lo", "must be in [0, gate_err_hi)")
        if cfg.dm_gain_p0 < 0.0:
            raise ConfigError("rhonn", "dm_gain_p0", "must be >= 0 (0 = off)")
        if not 0.0 < cfg.dm_gain_min <= 1.0 <= cfg.dm_gain_max:
            raise ConfigError("rhonn", "dm_gain_min",
                              "needs 0 < dm_gain_min <= 1 <= dm_gain_max")
        if len(cfg.mu) != N_XI or len(cfg.beta) != N_XI:
            raise ConfigError("rhonn", "mu" if len(cfg.mu) != N_XI else "beta",
                              "needs 4 entries [vx, vy, r, delta_w]")
        return cfg


class RhonnModel:
    """RHONN prediction model with online EKF learning; implements PredictionModel (nx = 3).

    Learning protocol (series-parallel, called once per controller step by MpcController
    or RhonnEstimator):
      1. ``observe(x_meas, learn)`` — e = x_k − χ_k with χ_k the prediction recorded at
         the previous step, EKF update with H = φ(x_{k−1}, u_{k−1}).
      2. ``record(x_meas, delta_m, ctx, out)`` — χ_{k+1} = f(x_k, u_k) with the applied
         inputs; remembered (with its φ) for the next ``observe``.
    """

    nx = 3

    def __init__(self, params: VehicleParams, cfg: RhonnConfig | None = None,
                 ts: float = 0.05, dtype: type = np.float64) -> None:
        """dtype: working precision of W, P, φ, states and Jacobians (np.float64 or
        np.float32; Python scalar temporaries stay float64)."""
        self.params = params
        self.cfg = cfg or RhonnConfig()
        self.dtype = dtype
        self.ts = float(ts)
        self.increment = self.cfg.form == "increment"
        self._mu = tuple(float(v) for v in self.cfg.mu)
        self._beta = tuple(float(v) for v in self.cfg.beta)
        self.k_tt = 1.0 / (params.mass_kg * params.wheel_radius_m)  # (m/s²)/(N·m)
        self.k_dm = params.track_m / (2.0 * params.yaw_inertia_kgm2 * params.wheel_radius_m)
        # Known ΔM part split by the actuator dead time T_d (see the module docstring):
        # (Ts − T_d)·k_dm on ΔM_k and T_d·k_dm on ΔM_{k−1} (ctx.delta_m_prev).
        self.b_prev = np.zeros(3)       # ∂χ_{k+1}/∂ΔM_{k−1}, read by nmpc.LinearizedMpc
        self._set_split()
        # Model-confidence gate: filtered mean square of the one-step ωr error, (rad/s)².
        c = self.cfg
        self._gate_on = c.gate_err_hi > 0.0
        self._gate_a = math.exp(-self.ts / c.gate_tau_s) if c.gate_tau_s > 0.0 else 0.0
        self._gate_n = max(0, round(c.gate_warmup_s / self.ts))
        self.err_ms = c.gate_err_hi ** 2
        self.learn_steps = 0
        self._gate_open = False
        if self.cfg.ekf.form == "ud":
            if self.cfg.ekf.q_nis > 0.0:
                raise ValueError("rhonn.ekf.q_nis needs form = 'standard'")
            self.ekf = UdEkf(3, N_PHI, self.cfg.ekf, dtype=dtype)
        elif self.cfg.ekf.form == "standard":
            self.ekf = BatchedEkf(3, N_PHI, self.cfg.ekf, dtype=dtype)
        else:
            raise ValueError(f"rhonn.ekf.form must be 'standard' or 'ud', not "
                             f"{self.cfg.ekf.form!r}")
        if int(c.init_seed) != 0:
            rng = np.random.default_rng(int(c.init_seed))
            self.ekf.w0[:] = rng.normal(0.0, float(c.init_w_std), self.ekf.w0.shape)
            self.ekf.reset()
        self.W = self.ekf.W  # alias: the EKF updates in place
        # Learned ΔM effectiveness θ (off: None, θ = 1): its filter owns the yaw row.
        self.dm_gain: YawGainFilter | None = None
        if c.dm_gain_p0 > 0.0:
            self.dm_gain = YawGainFilter(N_PHI, c.ekf, self.ekf.w0[2], c.dm_gain_p0,
                                         c.dm_gain_min, c.dm_gain_max, dtype=dtype)
        self.theta = 1.0
        self._rec_u = 0.0
        # Scratch (hot path, no allocation of lasting size).
        self._phi = np.zeros(N_PHI, dtype)
        self._phi_ext = np.zeros(N_PHI + 2, dtype)
        self._phi_ext[0] = 1.0
        self._jt = np.zeros((3, N_PHI), dtype)
        self._wx = np.zeros(3, dtype)
        self._dxi = np.zeros((3, 1), dtype)
        self._rec_phi = np.zeros(N_PHI, dtype)
        self._rec_chi = np.full(3, np.nan, dtype)
        self._e = np.zeros(3, dtype)
        self._has_record = False
        # (Vy, ωr) bilinear collapse table: W4[i, mono, tfac].
        self._w4 = np.zeros((3, 4, 4))
        self._t4 = np.zeros(4)
        self._coef = np.zeros((3, 4))
        self._eye3 = np.eye(3, dtype=dtype)
        self._d3 = DERIV_INDEX[:3]

    def _set_split(self) -> None:
        """Effective gains of ΔM_k and ΔM_{k−1} on ωr_{k+1} for the current self.ts."""
        td = min(max(float(self.cfg.dm_dead_time_s), 0.0), self.ts)
        self._ts_seen = self.ts
        self.kd0_now = (self.ts - td) * self.k_dm     # at θ = 1, (rad/s)/(N·m)
        self.kd0_prev = td * self.k_dm
        self._scale_gain(getattr(self, "theta", 1.0))

    def _scale_gain(self, theta: float) -> None:
        """The known ΔM part's gains at the effectiveness θ (-)."""
        self.theta = theta
        self.kd_now = theta * self.kd0_now            # (rad/s)/(N·m)
        self.kd_prev = theta * self.kd0_prev
        self.b_prev[2] = self.kd_prev

    # ----------------------------------------------------------------- structure
    def xi(self, j: int, x: float) -> float:
        """ξ_j = μ_j tanh(β_j x) (dimensionless)."""
        return self._mu[j] * math.tanh(self._beta[j] * x)

    def dxi(self, j: int, x: float) -> float:
        """dξ_j/dx = μ_j β_j (1 − tanh²(β_j x)), per unit of x."""
        t = math.tanh(self._beta[j] * x)
        return self._mu[j] * self._beta[j] * (1.0 - t * t)

    def _fill_phi(self, vx: float, vy: float, r: float, dw: float) -> None:
        """φ (paper order) into self._phi and φ_ext = [1, φ, 0]."""
        mu, be = self._mu, self._beta
        a = mu[0] * math.tanh(be[0] * vx)
        b = mu[1] * math.tanh(be[1] * vy)
        c = mu[2] * math.tanh(be[2] * r)
        d = mu[3] * math.tanh(be[3] * dw)
        ab, ac, ad, bc, bd, cd = a * b, a * c, a * d, b * c, b * d, c * d
        abc = ab * c
        vals = (a, b, c, d, ab, ac, ad, bc, bd, cd, abc, ab * d, ac * d, bc * d, abc * d)
        self._phi[:] = vals
        self._phi_ext[1:16] = self._phi

    def phi(self, x: np.ndarray, delta_w: float) -> np.ndarray:
        """φ(x, δw) (15,) for x = [vx m/s, vy m/s, r rad/s] (a view, overwritten next call)."""
        self._fill_phi(float(x[0]), float(x[1]), float(x[2]), float(delta_w))
        return self._phi

    # ----------------------------------------------------------------- PredictionModel
    def initial_state(self, inputs: ControllerInputs, out: np.ndarray) -> None:
        """out = [vx m/s, vy m/s, yaw_rate rad/s] from the (estimated/measured) inputs."""
        out[0] = inputs.vx
        out[1] = inputs.vy
        out[2] = inputs.yaw_rate

    def predict(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                out: np.ndarray) -> None:
        """out = χ_{k+1} for state x, ΔM N·m, δw = ctx.delta_w rad, Tt = ctx.total_torque N·m.

        Uses self.ts (the period the weights were learned at) for the known parts.
        """
        x0, x1, x2 = float(x[0]), float(x[1]), float(x[2])
        ts = self.ts
        self._fill_phi(x0, x1, x2, ctx.delta_w)
        np.matmul(self.W, self._phi, out=self._wx)
        wx = self._wx
        if ts != self._ts_seen:
            self._set_split()
        kdm = self.kd_now * delta_m + self.kd_prev * ctx.delta_m_prev
        if self.increment:
            out[0] = x0 + ts * self.k_tt * ctx.total_torque + wx[0]
            out[1] = x1 + wx[1]
            out[2] = x2 + kdm + wx[2]
        else:
            out[0] = ts * self.k_tt * ctx.total_torque + wx[0]
            out[1] = wx[1]
            out[2] = kdm + wx[2]

    def linearize(self, x: np.ndarray, delta_m: float, ctx: PredictionContext,
                  a_out: np.ndarray, b_out: np.ndarray) -> None:
        """Analytic Jacobians: a_out (3,3) = W ∂φ/∂x (+ I for the increment form);
        b_out (3,) = [0, 0, (Ts − T_d) wB/(2 Iz r)] in (rad/s)/(N·m) (∂/∂ΔM_{k−1}: b_prev)."""
        x0, x1, x2 = float(x[0]), float(x[1]), float(x[2])
        self._fill_phi(x0, x1, x2, ctx.delta_w)
        jt = self._jt
        self._phi_ext.take(self._d3, out=jt)                 # ∂φ/∂ξ_j, (3, 15)
        d = self._dxi
        d[0, 0] = self.dxi(0, x0)
        d[1, 0] = self.dxi(1, x1)
        d[2, 0] = self.dxi(2, x2)
        jt *= d                                              # ∂φ/∂x_j
        np.matmul(self.W, jt.T, out=a_out)
        if self.increment:
            a_out[0, 0] += 1.0
            a_out[1, 1] += 1.0
            a_out[2, 2] += 1.0
        if self.ts != self._ts_seen:
            self._set_split()
        b_out[0] = 0.0
        b_out[1] = 0.0
        b_out[2] = self.kd_now

    # ----------------------------------------------------------------- learning
    def observe(self, x_meas: np.ndarray, learn: bool) -> bool:
        """EKF update with e = x_meas − χ (the prediction recorded last step).

        Returns True if the weights changed. Frozen (and counted) when learn is False.
        """
        if not learn:
            self.ekf.counters.frozen += 1
            return False
        if not self._has_record:
            return False
        np.subtract(x_meas, self._rec_chi, out=self._e)
        ok = self.ekf.update(self._rec_phi, self._e, True)
        g = self.dm_gain
        # the joint filter owns the yaw row: its weights replace the EKF's row
        if ok and g is not None and g.update(self._rec_phi, self._rec_u, float(self._e[2])):
            self.W[2] = g.w_row
            self._scale_gain(g.theta)
        if ok:
            er = float(self._e[2])
            a = self._gate_a
            self.err_ms = a * self.err_ms + (1.0 - a) * er * er
            self.learn_steps += 1
        return ok

    def confidence(self) -> float:
        """Model confidence in [0, 1] for the ΔM box (mpc_controller): 0 during the
        learning warm-up (gate_warmup_s of accepted EKF updates), then a linear ramp from 1
        at a filtered RMS one-step ωr error ≤ gate_err_lo to 0 at ≥ gate_err_hi rad/s;
        latched at 1 the first time it reaches 1 (until reset). 1 when disabled."""
        c = self.cfg
        if not self._gate_on:
            return 1.0
        if self._gate_open:
            return 1.0
        if self.learn_steps < self._gate_n:
            return 0.0
        rms = math.sqrt(self.err_ms)
        conf = min(max((c.gate_err_hi - rms) / (c.gate_err_hi - c.gate_err_lo), 0.0), 1.0)
        if conf >= 1.0:
            # Latched: once converged the gate stays open. A gate that closed again on
            # large errors would switch ΔM off exactly in the nonlinear transients it is
            # for (measured: sine-with-dwell 250° spun with a non-latching gate).
            self._gate_open = True
        return conf

    def record(self, x_meas: np.ndarray, delta_m: float, ctx: PredictionContext,
               out: np.ndarray) -> None:
        """One-step prediction χ_{k+1} = f(x_k, u_k) → out (3,), kept for the next observe.

        Non-finite states or inputs invalidate the record (the next observe is skipped).
        """
        self.predict(x_meas, delta_m, ctx, out)
        if math.isfinite(sum(out.tolist())):   # ≈ 1 µs less than np.isfinite(out.sum())
            self._rec_u = self.kd0_now * delta_m + self.kd0_prev * ctx.delta_m_prev
            self._rec_phi[:] = self._phi
            self._rec_chi[:] = out
            self._has_record = True
        else:
            self._has_record = False

    def forget_record(self) -> None:
        """Drop the pending prediction (e.g. the state estimate was invalid this step)."""
        self._has_record = False

    # ----------------------------------------------------------------- references helper
    def bilinear_coefficients(self, vx: float, delta_w: float) -> np.ndarray:
        """Coefficients C (3, 4) such that, at fixed Vx and δw,
        W φ = C[:, 0] + C[:, 1] ξ2 + C[:, 2] ξ3 + C[:, 3] ξ2 ξ3 with ξ2 = S(Vy), ξ3 = S(ωr).
        (A view, overwritten next call.)"""
        a = self.xi(0, vx)
        d = self.xi(3, delta_w)
        w4 = self._w4
        w4[:, MONO_INDEX, TFAC_INDEX] = self.W
        t = self._t4
        t[0] = 1.0
        t[1] = a
        t[2] = d
        t[3] = a * d
        np.matmul(w4, t, out=self._coef)
        return self._coef

    # ----------------------------------------------------------------- state
    def reset(self) -> None:
        """Cold start: weights W0, covariance P0, no pending record."""
        self.ekf.reset()
        if self.dm_gain is not None:
            self.dm_gain.reset()
        self._scale_gain(1.0)
        self._has_record = False
        self._rec_chi[:] = np.nan
        self.err_ms = self.cfg.gate_err_hi ** 2
        self.learn_steps = 0
        self._gate_open = False

    def get_state(self) -> dict[str, np.ndarray | float]:
        """Learned state: weights (3, 15), covariances (3, 15, 15), pending record."""
        s = self.ekf.get_state()
        out: dict[str, np.ndarray | float] = {
            "rhonn.W": s["W"], "rhonn.P": s["P"],
            "rhonn.rec_phi": self._rec_phi.copy(), "rhonn.rec_chi": self._rec_chi.copy(),
            "rhonn.has_record": float(self._has_record),
            "rhonn.err_ms": float(self.err_ms), "rhonn.learn_steps": float(self.learn_steps),
            "rhonn.gate_open": float(self._gate_open),
        }
        if self.dm_gain is not None:   # the learned ΔM effectiveness and its covariance
            g = self.dm_gain.get_state()
            out.update({"rhonn.dm_gain.W": g["W"], "rhonn.dm_gain.P": g["P"],
                        "rhonn.rec_u": float(self._rec_u)})
        return out

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore what get_state returned."""
        self.ekf.set_state({"W": np.asarray(d["rhonn.W"]), "P": np.asarray(d["rhonn.P"])})
        self._rec_phi[:] = np.asarray(d["rhonn.rec_phi"])
        self._rec_chi[:] = np.asarray(d["rhonn.rec_chi"])
        self._has_record = bool(d["rhonn.has_record"])
        self.err_ms = float(d.get("rhonn.err_ms", self.cfg.gate_err_hi ** 2))
        self.learn_steps = int(d.get("rhonn.learn_steps", 0))
        self._gate_open = bool(d.get("rhonn.gate_open", 0.0))
        if self.dm_gain is not None and "rhonn.dm_gain.W" in d:
            self.dm_gain.set_state({"W": np.asarray(d["rhonn.dm_gain.W"]),
                                    "P": np.asarray(d["rhonn.dm_gain.P"])})
            self._rec_u = float(d.get("rhonn.rec_u", 0.0))
            self._scale_gain(self.dm_gain.theta)


class RhonnEstimator:
    """StateEstimator for the fidelity study: online EKF from cold start, series-parallel.

    step() learns from the current measurement and returns the one-step-ahead estimate
    [vx m/s, vy m/s, r rad/s] for the next sample (dt s later), using the applied torques.
    """

    def __init__(self, params: VehicleParams, cfg: RhonnConfig | None = None,
                 ts: float = 0.05) -> None:
        self.params = params
        self.model = RhonnModel(params, cfg, ts)
        self._x = np.zeros(3)
        self._out = np.full(3, np.nan)
        self._ctx = PredictionContext(ts=ts)

    def reset(self) -> None:
        """Cold start (weights and covariances back to their initial values)."""
        self.model.reset()
        self._out[:] = np.nan
        self._ctx.delta_m_prev = 0.0

    def step(self, inputs: ControllerInputs, torques: np.ndarray, dt: float) -> np.ndarray:
        """Learn from inputs (vx, vy, yaw_rate), then predict dt s ahead with torques (4,) N·m."""
        m = self.model
        x = self._x
        m.initial_state(inputs, x)
        valid = bool(inputs.sensors_valid) and bool(np.isfinite(x.sum()))
        if valid:
            m.observe(x, learn=True)
        else:
            m.ekf.counters.frozen += 1
        t1, t2, t3, t4 = (float(v) for v in torques)
        ctx = self._ctx
        ctx.ts = dt
        ctx.total_torque = t1 + t2 + t3 + t4
        ctx.delta_w = float(inputs.swa_rad) / self.params.steering_ratio
        if dt > 0.0 and math.isfinite(dt):
            m.ts = dt
        dm = t2 + t4 - t1 - t3
        if valid and math.isfinite(ctx.total_torque + ctx.delta_w):
            m.record(x, dm, ctx, self._out)
            ctx.delta_m_prev = dm
        else:
            m.forget_record()
            self._out[:] = np.nan
        return self._out

    def get_state(self) -> dict[str, np.ndarray | float]:
        """Learned state (see RhonnModel.get_state)."""
        return self.model.get_state()

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore learned state."""
        self.model.set_state(d)
