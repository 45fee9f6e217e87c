"""Linearised-per-step NMPC (paper eq. 21–24) as a condensed QP solved with OSQP 1.x.

Decision: z = ΔM over the horizon (N,), scaled to kN·m (z = ΔM / u_scale) so the Hessian
entries are O(0.1–1). Cost (eq. 22) with held references (ωrd, βd):

    J = Σ_i q_i (ωrd − ωr,i)² + r_i (βd − β_i)² + λ Σ_i z_i²

β_i = Vy_i / Vx_i is linearised around the nominal trajectory. λ (``input_reg``, per
(kN·m)²) is a small regularisation: the paper has none, but it keeps P strictly positive
definite when the model says ΔM has (almost) no effect — e.g. at very low speed or a cold
model — and picks the smallest ΔM among equal-cost solutions. Default 1e-3, i.e. about 1 %
of the yaw-tracking curvature q·(∂ωr/∂z)² ≈ 100·0.033² ≈ 0.1.

Per step (RTI-style; ``sqp_iterations`` repeats 1–4):
  1. nominal input ū = previous solution shifted by one stage (last one repeated);
  2. rollout x̄_{i+1} = f(x̄_i, ū_i) with the PredictionModel (parallel prediction);
  3. A_i, B_i = ∂f/∂x, ∂f/∂ΔM at (x̄_i, ū_i); sensitivities S_{i+1} = A_i S_i + B_i e_iᵀ
     (+ b_prev e_{i−1}ᵀ for a model with an actuator dead time, see rhonn.py);
     outputs y = [ωr, β] ≈ ȳ + G (z − z̄);
  4. P = 2(Gᵀ W G + λ I), q = −2 Gᵀ W (y_d − ȳ + G z̄);
  5. the unconstrained minimiser if it satisfies every row (below), else OSQP
     ``update(q, Px, l, u)`` with a fixed sparsity pattern (full upper triangle) set up
     once and a warm-started solve.
Constraints: box ΔM_min ≤ ΔM_i ≤ ΔM_max (eq. 23) and, if enabled, a rate limit on
ΔM_0 − ΔM_prev and ΔM_i − ΔM_{i−1} (linear rows of A).

Smoothness: ``delta_rate_weight`` λ_Δ adds λ_Δ Σ_i (z_i − z_{i−1})² with z_{−1} = the applied
ΔM (per (kN·m)² of increment), the move-suppression term of MPC practice.
``delta_accel_weight`` λ₂ adds λ₂ Σ_i (z_i − 2z_{i−1} + z_{i−2})² with z_{−2} = the ΔM applied
at the solve before: a ramp costs nothing, an alternation does.

Stable-handling envelope (``envelope`` given, controller/core/mpc/envelope.py): two more
decisions, the slacks s_r, s_α ≥ 0 (fractions of their bounds), and per stage i the rows

    −1 − s_r ≤ ωr_i / r_max ≤ 1 + s_r,      −1 − s_α ≤ α_i / α_max ≤ 1 + s_α,

with ωr_i, α_i = β_i − (lr/Vx̄_i + T)·ωr_i + T·ay/Vx linearised like the cost outputs (their
rows of A change every step), priced by slack_linear·s + slack_quad·s² (exact penalty). The
rate rows are always part of this shape (±∞ when no rate limit is set), so the QP has
n = N + 2 decisions and m = 6N + 2 rows.

Unconstrained first (``unconstrained_first``, on by default): the QP is strictly convex
(λ > 0), so when the minimiser of the cost alone — ΔM from the Cholesky factor of P's ΔM block,
the slacks at 0 — satisfies every row of A, it is the QP's solution (KKT with zero multipliers
on every ΔM row; a slack at its bound 0 with multiplier slack_linear ≥ 0). OSQP then is not
updated or run (its scaling, factorisation and iterations are most of a step; most steps of
a manoeuvre have no active row) and is warm-started from that solution for the next solve
that needs it. With the envelope, a box collapsed to one value (ΔM_min = ΔM_max, e.g. 0 N·m
while the model is not yet confident) fixes every ΔM stage; the slacks are then the smallest
that satisfy their rows (the cost is increasing in a slack ≥ 0): the QP's unique solution,
also without OSQP. Otherwise OSQP solves the QP as below.

Status mapping: OSQP solved → SOLVED; solved inaccurate → SOLVED_INACCURATE; max iter /
time limit → MAX_ITER (the iterate is clipped to the box and used); anything else, or a
non-finite problem/solution → fallback: ΔM = fallback_decay · previous ΔM, status FALLBACK.

Polishing is off by default: OSQP 1.1 prints "Polishing not needed…" to stdout on every
solve without an active set even with verbose=False (osqp/osqp#785) — I/O in the hot path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from controller.core.config_schema import (
    ConfigError,
    build_section,
    require_nonnegative,
    require_positive,
)
from controller.core.interfaces import PredictionContext, PredictionModel, QpStatus
from controller.core.mpc.envelope import HandlingEnvelope
from controller.core.precision import dtype_of

OSQP_INF = 1e30


@dataclass(slots=True)
class QpConfig:
    """MPC/QP tuning.

    horizon: N, stages. q_yaw: q_i per stage on (rad/s)². r_beta: r_i per stage on rad².
    input_reg: λ per (kN·m)². rate_limit_nm_per_s: |dΔM/dt| bound, N·m/s (0 = off).
    sqp_iterations: linearise+solve rounds per step. fallback_decay: factor on the previous
    ΔM when the solver fails, -. u_scale: N·m per decision unit. v_min: speed floor for the
    β linearisation, m/s. delta_m_max_nm: optional cap on |ΔM|, N·m (0 = motor capacity).
    delta_rate_weight: λ_Δ per (kN·m)² of ΔM increment between stages (0 = off).
    delta_accel_weight: λ₂ per (kN·m)² of ΔM second difference between stages (0 = off).
    unconstrained_first: take the cost's minimiser without OSQP when it satisfies every
    row (see the module docstring). osqp: OSQP settings passed to setup(). precision:
    "float64" or "float32": dtype of everything the controller computes (model, EKF,
    linearisation, QP data); the QP data are handed to OSQP (a float64 build) converted to
    float64.
    """

    horizon: int = 3
    q_yaw: float | tuple[float, ...] = (100.0, 100.0, 100.0)
    r_beta: float | tuple[float, ...] = (1000.0, 1000.0, 1000.0)
    input_reg: float = 1e-3
    rate_limit_nm_per_s: float = 0.0
    sqp_iterations: int = 1
    fallback_decay: float = 0.5
    u_scale: float = 1000.0
    v_min: float = 3.0
    delta_m_max_nm: float = 0.0
    delta_rate_weight: float = 0.0
    delta_accel_weight: float = 0.0
    unconstrained_first: bool = True
    osqp: dict[str, Any] = field(default_factory=lambda: {
        "warm_starting": True, "polishing": False, "verbose": False, "max_iter": 200,
        "eps_abs": 1e-4, "eps_rel": 1e-4, "check_termination": 5, "adaptive_rho": 1,
        "adaptive_rho_interval": 25, "scaling": 4,
    })
    precision: str = "float64"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> QpConfig:
        """Build from the [mpc] table (+ optional [mpc.osqp]); per-stage weights may be a
        scalar (same for every stage) or a list of length N."""
        cfg = build_section(cls, {k: v for k, v in d.items() if k != "osqp"}, "mpc")
        osqp_over = d.get("osqp", {})
        if not isinstance(osqp_over, dict):
            raise ConfigError("mpc", "osqp", "expected a table [mpc.osqp]")
        cfg.osqp = {**cls().osqp, **osqp_over}
        n = cfg.horizon
        if not 1 <= n <= HORIZON_MAX:
            raise ConfigError("mpc", "horizon", f"must be in 1..{HORIZON_MAX}")
        for name in ("q_yaw", "r_beta"):
            v = getattr(cfg, name)
            v = (v,) * n if isinstance(v, float) else v
            if len(v) != n:
                raise ConfigError("mpc", name, f"needs 1 or {n} (horizon) entries, got {len(v)}")
            setattr(cfg, name, v)
        if not 1 <= cfg.sqp_iterations <= 10:
            raise ConfigError("mpc", "sqp_iterations", "must be in 1..10")
        require_nonnegative(cfg, "mpc", ("q_yaw", "r_beta", "input_reg", "rate_limit_nm_per_s",
                                         "delta_m_max_nm", "delta_rate_weight",
                                         "delta_accel_weight"))
        if not any(q > 0.0 for q in (*cfg.q_yaw, *cfg.r_beta)):
            raise ConfigError("mpc", "q_yaw", "q_yaw and r_beta are all 0: nothing to track")
        require_positive(cfg, "mpc", ("u_scale", "v_min"))
        if not 0.0 <= cfg.fallback_decay <= 1.0:
            raise ConfigError("mpc", "fallback_decay", "must be in [0, 1]")
        return cfg


QP_MAGNITUDE_LIMIT = 1e12  # |P|, |q| entries beyond this are numerically meaningless
HORIZON_MAX = 20   # stages (1 s at 50 ms); the C core runs 1..10 (its N_MAX), numpy beyond
_STATUS_MAP = {1: QpStatus.SOLVED, 2: QpStatus.SOLVED_INACCURATE, 7: QpStatus.MAX_ITER,
               8: QpStatus.MAX_ITER}


class LinearizedMpc:
    """Condensed linearised MPC over a generic PredictionModel (OSQP set up once)."""

    def __init__(self, model: PredictionModel, cfg: QpConfig, ts: float,
                 envelope: HandlingEnvelope | None = None) -> None:
        self.model = model
        self.cfg = cfg
        self.ts = float(ts)
        N = cfg.horizon
        nx = int(model.nx)
        self.N, self.nx = N, nx
        self.envelope = envelope
        self.env = envelope is not None
        self.rate = cfg.rate_limit_nm_per_s > 0.0 or self.env
        self.nv = N + 2 if self.env else N      # decisions: ΔM stages (+ the two slacks)
        self.m = (6 * N + 2) if self.env else (2 * N if self.rate else N)
        dt = self.dtype = dtype_of(cfg.precision)
        # Scratch (working dtype): nominal trajectory x̄ (N+1, nx) and inputs ū (N,) N·m,
        # Jacobians A (N, nx, nx), B (N, nx), sensitivities S (N, nx, N); G (2N, N) = ∂y/∂z
        # with rows ordered [ωr_1, β_1, ωr_2, β_2, …], ȳ, y_d and the output weights (2N,);
        # Pd (N, N) the dense Hessian (diagnostics/tests), Px its upper triangle in CSC
        # order, q (N,); sol (N,) the last accepted solution, N·m; lb, ub the box and z
        # the clipped iterate (decision units).
        self.xbar = np.zeros((N + 1, nx), dt)
        self.ubar = np.zeros(N, dt)
        self.A = np.zeros((N, nx, nx), dt)
        self.B = np.zeros((N, nx), dt)
        self._Sall = np.zeros((N, nx, N), dt)
        self.G = np.zeros((2 * N, N), dt)
        self.ybar = np.zeros(2 * N, dt)
        self.yd = np.zeros(2 * N, dt)
        self.wdiag = np.zeros(2 * N, dt)
        self.Pd = np.zeros((N, N), dt)
        iu = np.triu_indices(N)
        nt = len(iu[0])
        self.Px = np.zeros(nt, dt)
        self.q = np.zeros(N, dt)
        self.sol = np.zeros(N, dt)
        self.lb = np.zeros(N, dt)
        self.ub = np.zeros(N, dt)
        self.z = np.zeros(N, dt)
        self._dm_prev_z = 0.0      # applied ΔM of the current solve, decision units
        self._dm_prev2_z = 0.0     # and of the solve before it
        self.slack = np.zeros(2)   # last (s_r, s_α), fractions of the envelope bounds
        # OSQP's data, float64 in both precisions: Px (upper triangle, CSC order), q, l, u
        # (with the envelope: Px also holds the two slack diagonals, q their prices)
        self._px64 = np.zeros(nt + 2 if self.env else nt)
        self._q64 = np.zeros(self.nv)
        self.l = np.zeros(self.m)
        self.u = np.zeros(self.m)
        self._e0 = np.zeros(N, dt)
        self._e0[0] = 1.0
        self._vx = np.zeros(N, dt)
        self._beta_bar = np.zeros(N, dt)
        self._tmpn = np.zeros(N, dt)
        self._tmpnn = np.zeros((N, N), dt)
        self._G3 = self.G.reshape(N, 2, N)
        self._yb3 = self.ybar.reshape(N, 2)
        # The physics baselines predict and linearise a stage in one pass; otherwise (the
        # RHONN) predict along the horizon, then linearise at every stage.
        self._one_pass = hasattr(model, "predict_linearize")
        # Models with an actuator dead time also depend on the previous stage's ΔM:
        # x_{i+1} = f(x_i, ΔM_i, ΔM_{i−1}); ∂/∂ΔM_{i−1} = model.b_prev (nx,), constant.
        # (ΔM_{−1} = the applied ΔM is data, in ctx.delta_m_prev.)
        self._b_prev = getattr(model, "b_prev", None)
        self.wdiag[0::2] = cfg.q_yaw
        self.wdiag[1::2] = cfg.r_beta
        self._WG = np.zeros((2 * N, N), dt)
        self._rhs = np.zeros(2 * N, dt)
        self._zbar = np.zeros(N, dt)
        reg = 2.0 * cfg.input_reg * np.eye(N)
        if cfg.delta_rate_weight > 0.0:   # λ_Δ Σ (z_i − z_{i−1})², z_{−1} data: 2λ_Δ DᵀD
            D = np.eye(N) - np.eye(N, k=-1)
            reg += 2.0 * cfg.delta_rate_weight * (D.T @ D)
        if cfg.delta_accel_weight > 0.0:   # λ_2 Σ (z_i − 2z_{i−1} + z_{i−2})²: 2λ_2 D2ᵀD2
            D2 = np.eye(N) - 2.0 * np.eye(N, k=-1) + np.eye(N, k=-2)
            reg += 2.0 * cfg.delta_accel_weight * (D2.T @ D2)
        self._reg = reg.astype(dt)
        if self.env:
            # A of the envelope shape, dense (envelope_a_dense; only the envelope rows' ΔM
            # block changes), its structural values in CSC order, and per-stage scratch
            self._Adense = envelope_a_dense(N, np.zeros((4 * N, N)))
            self._env_flat = np.flatnonzero(_env_mask(N))[_csc_order(N)]
            self._ax_env = np.zeros(len(self._env_flat))
            self._c_env = np.zeros(N)
            self._ga = np.zeros((N, N))
            self._ya = np.zeros(N)
            self._hr = np.zeros(N)
            self._ha = np.zeros(N)
            # the slacks' prices, constant: their diagonals follow the upper triangle of the
            # ΔM block in CSC order, their linear prices follow q
            h = envelope.cfg
            self._px64[nt:] = 2.0 * h.slack_quad + 1e-6
            self._q64[N:] = h.slack_linear
        # CSC order of the upper triangle: column by column, rows ascending.
        order = np.lexsort((iu[0], iu[1]))
        self._tri_r = iu[0][order]
        self._tri_c = iu[1][order]
        self._tri_flat = self._tri_r * N + self._tri_c
        # Bounded iterations: OSQP max_iter (settings) and how often it was hit.
        self.max_iter_hits = 0
        self.fallbacks = 0
        self.unconstrained_solves = 0   # QPs solved without OSQP (unconstrained_first)
        self._az = np.zeros(self.m)     # A·x of the unconstrained minimiser
        self.worst_iterations = 0
        self.last_iterations = 0
        self.last_status = QpStatus.NOT_RUN
        self._y_last: np.ndarray | None = None
        self._setup()

    def _setup(self) -> None:
        self.l[:] = -1.0
        self.u[:] = 1.0
        self._bounds_dirty = True
        self._lo_last = self._hi_last = math.nan
        self.solver = self._new_solver()

    def _new_solver(self) -> osqp.OSQP:
        """OSQP set up on the fixed sparsity pattern with the current bounds l, u."""
        if self.env:
            P, A = envelope_pattern(self.N)
        else:
            P, A = qp_pattern(self.N, self.rate)
        solver = osqp.OSQP()
        solver.setup(P, np.zeros(self.nv), A, self.l.copy(), self.u.copy(), **self.cfg.osqp)
        return solver

    # copy.deepcopy and pickle: the OSQP object cannot be copied, so a copy sets up its own
    # solver and warm-starts it from the last solution and dual iterate, as set_state does
    # (OSQP's adaptive ρ and scaled iterates are not exported: the copy continues equal at
    # the solver tolerance, not bit for bit).
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        del state["solver"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        N = self.N
        self._G3 = self.G.reshape(N, 2, N)          # views of this copy's G and ȳ again
        self._yb3 = self.ybar.reshape(N, 2)
        self.solver = self._new_solver()
        self._bounds_dirty = True
        if self._y_last is not None:
            self.solver.warm_start(x=self._warm_x(), y=self._y_last)

    def reset(self) -> None:
        """Forget warm starts and the previous solution."""
        self.sol[:] = 0.0
        self.ubar[:] = 0.0
        self.slack[:] = 0.0
        self._dm_prev_z = self._dm_prev2_z = 0.0
        self.last_iterations = 0
        self.last_status = QpStatus.NOT_RUN
        self._setup()

    # ------------------------------------------------------------------ building blocks
    def _linearise(self, x0: np.ndarray, ctx: PredictionContext) -> None:
        """Rollout + Jacobians + output sensitivities G (decision units) and ȳ."""
        self._model_rollout(x0, ctx)
        self._condense()

    def _model_rollout(self, x0: np.ndarray, ctx: PredictionContext) -> None:
        """Nominal rollout x̄ and the model Jacobians A, B along ū."""
        model, N = self.model, self.N
        xbar, ubar, A, B = self.xbar, self.ubar, self.A, self.B
        if self._one_pass:
            xbar[0] = x0
            for i in range(N):
                model.predict_linearize(xbar[i], float(ubar[i]), ctx, xbar[i + 1], A[i], B[i])
        else:
            xbar[0] = x0
            u_applied = ctx.delta_m_prev
            for i in range(N):   # a dead-time model sees the previous STAGE's ΔM
                model.predict(xbar[i], float(ubar[i]), ctx, xbar[i + 1])
                ctx.delta_m_prev = float(ubar[i])
            ctx.delta_m_prev = u_applied
            for i in range(N):
                model.linearize(xbar[i], float(ubar[i]), ctx, A[i], B[i])

    def _condense(self) -> None:
        """Output sensitivities G (decision units) and ȳ from x̄, A, B (reference path)."""
        N, xbar, A, B = self.N, self.xbar, self.A, self.B
        # Sensitivities S_{i+1} = A_i S_i + B_i e_iᵀ, stacked in Sall (N, nx, N).
        Sall = self._Sall
        np.multiply(B[0][:, None], self._e0, out=Sall[0])
        bp = self._b_prev
        for i in range(1, N):
            np.matmul(A[i], Sall[i - 1], out=Sall[i])
            Sall[i, :, i] += B[i]
            if bp is not None:
                Sall[i, :, i - 1] += bp
        # Outputs y_i = [ωr, β = Vy/Vx] at stages 1..N; dβ = dVy/Vx − Vy dVx/Vx².
        vx = self._vx
        np.fmax(xbar[1:, 0], self.cfg.v_min, out=vx)   # fmax: a NaN speed → v_min
        vy = xbar[1:, 1]
        G3 = self._G3                                    # (N, 2, N) view of G
        us = self.cfg.u_scale
        np.multiply(Sall[:, 2, :], us, out=G3[:, 0, :])
        np.divide(vy, vx, out=self._beta_bar)
        np.divide(self._beta_bar, vx, out=self._tmpn)    # Vy/Vx²
        np.multiply(Sall[:, 0, :], self._tmpn[:, None], out=self._tmpnn)
        np.divide(Sall[:, 1, :], vx[:, None], out=G3[:, 1, :])
        G3[:, 1, :] -= self._tmpnn
        G3[:, 1, :] *= us
        yb = self._yb3
        yb[:, 0] = xbar[1:, 2]
        yb[:, 1] = self._beta_bar

    def set_bounds(self, dm_min: float, dm_max: float, dm_prev: float) -> None:
        """Box (N·m) and rate-limit rows around the previously applied ΔM dm_prev (N·m)."""
        us = self.cfg.u_scale
        lo, hi = dm_min / us, dm_max / us
        if not self.rate and lo == self._lo_last and hi == self._hi_last:
            return
        self._lo_last, self._hi_last = lo, hi
        self._bounds_dirty = True
        self.lb[:] = lo
        self.ub[:] = hi
        N = self.N
        self.l[:N] = lo
        self.u[:N] = hi
        if self.rate:
            d = self.cfg.rate_limit_nm_per_s * self.ts / us
            if not d > 0.0:
                d = OSQP_INF
            p = dm_prev / us if math.isfinite(dm_prev) else 0.0
            if self.env:   # keep the rows consistent with a box that shrank below ΔM_prev
                p = min(max(p, lo), hi)
            self.l[N] = p - d
            self.u[N] = p + d
            self.l[N + 1:2 * N] = -d
            self.u[N + 1:2 * N] = d

    # ------------------------------------------------------------------ solve
    def solve(self, x0: np.ndarray, ctx: PredictionContext, yaw_ref: float, beta_ref: float,
              dm_min: float, dm_max: float, dm_prev: float,
              env: tuple[float, float, float] | None = None
              ) -> tuple[float, QpStatus, int, bool]:
        """One MPC step from state x0 (nx,), references ωrd rad/s and βd rad, box in N·m.
        env: (r_max rad/s, α_max rad, ay m/s²) of the stable-handling envelope (None: its
        rows are inactive this step; ignored without the envelope shape).

        Returns (ΔM_0 N·m, status, OSQP iterations summed over SQP rounds, fallback flag).
        """
        self.set_bounds(dm_min, dm_max, dm_prev)
        self._dm_prev2_z = self._dm_prev_z
        self._dm_prev_z = (dm_prev / self.cfg.u_scale if math.isfinite(dm_prev) else 0.0)
        self._env_now = env if self.env else None
        ubar = self.ubar
        ubar[:-1] = self.sol[1:]
        ubar[-1] = self.sol[-1]
        np.maximum(ubar, dm_min, out=ubar)
        np.minimum(ubar, dm_max, out=ubar)
        self.yd[0::2] = yaw_ref
        self.yd[1::2] = beta_ref
        iters = 0
        status = QpStatus.FAILED
        us = self.cfg.u_scale
        ok = False
        for _ in range(self.cfg.sqp_iterations):
            self._linearise(x0, ctx)
            self._build()
            # finite but absurd (e.g. from |vx| ~ 1e300) is rejected too: OSQP would report
            # "not quasidefinite" on stdout and fail anyway
            if not (np.isfinite(self.Px.sum()) and np.isfinite(self.q.sum())
                    and np.abs(self.Px).max() < QP_MAGNITUDE_LIMIT
                    and np.abs(self.q).max() < QP_MAGNITUDE_LIMIT):
                status, ok = QpStatus.FAILED, False
                break
            self._px64[:len(self.Px)] = self.Px   # OSQP is a float64 build (also in float32)
            self._q64[:self.N] = self.q           # (the slack entries after them: set at init)
            if self.env and not self._envelope_rows(x0):   # absurd envelope data
                status, ok = QpStatus.FAILED, False
                break
            x = self._closed_form_solution() if self.cfg.unconstrained_first else None
            if x is not None:
                status, ok = QpStatus.SOLVED, True
                self.unconstrained_solves += 1
                self._y_last = np.zeros(self.m)
                self.solver.warm_start(x=x, y=self._y_last)
            else:
                self._osqp_update()
                res = self.solver.solve(raise_error=False)
                iters += int(res.info.iter)
                status = _STATUS_MAP.get(int(res.info.status_val), QpStatus.FAILED)
                x = res.x
                ok = (status != QpStatus.FAILED and x is not None
                      and bool(np.isfinite(x.sum())))
                if not ok:
                    status = QpStatus.FAILED
                    self._cold_start()
                    break
                self._y_last = res.y
            if self.env:
                self.slack[:] = x[self.N:]
                x = x[:self.N]
            np.maximum(x, self.lb, out=self.z)   # ufuncs: np.clip's wrapper costs µs
            np.minimum(self.z, self.ub, out=self.z)
            np.multiply(self.z, us, out=ubar)
        return self._finish(ok, status, iters, dm_min, dm_max, dm_prev)

    def _finish(self, ok: bool, status: QpStatus, iters: int, dm_min: float, dm_max: float,
                dm_prev: float) -> tuple[float, QpStatus, int, bool]:
        """Accept ū (N·m) or apply the defined fallback; count the bounded-iteration hits."""
        ubar = self.ubar
        self.last_iterations = iters
        if iters > self.worst_iterations:
            self.worst_iterations = iters
        if status == QpStatus.MAX_ITER:
            self.max_iter_hits += 1
        if ok:
            self.sol[:] = ubar
            self.last_status = status
            return float(ubar[0]), status, iters, False
        # Fallback: decay the previous command, keep it inside the box.
        self.fallbacks += 1
        dm = self.cfg.fallback_decay * (dm_prev if math.isfinite(dm_prev) else 0.0)
        dm = min(max(dm, dm_min), dm_max)
        self.sol[:] = dm
        self.last_status = QpStatus.FALLBACK
        return dm, QpStatus.FALLBACK, iters, True

    def _build(self) -> None:
        """P (dense + CSC upper-triangle values) and q from G, ȳ, y_d, z̄."""
        G, WG, Pd = self.G, self._WG, self.Pd
        np.multiply(G, self.wdiag[:, None], out=WG)
        np.matmul(G.T, WG, out=Pd)
        Pd *= 2.0
        Pd += self._reg
        Pd.take(self._tri_flat, out=self.Px)
        # q = −2 Gᵀ W (y_d − ȳ + G z̄)
        np.divide(self.ubar, self.cfg.u_scale, out=self._zbar)
        rhs = self._rhs
        np.matmul(G, self._zbar, out=rhs)
        rhs += self.yd
        rhs -= self.ybar
        np.matmul(WG.T, rhs, out=self.q)
        self.q *= -2.0
        if self.cfg.delta_rate_weight > 0.0:   # −2λ_Δ z_{−1} on the first stage
            self.q[0] -= 2.0 * self.cfg.delta_rate_weight * self._dm_prev_z
        w2 = self.cfg.delta_accel_weight
        if w2 > 0.0:   # data terms c = (z_{−2} − 2z_{−1}, z_{−1}) of rows 0, 1: q += 2λ_2 D2ᵀc
            c0 = self._dm_prev2_z - 2.0 * self._dm_prev_z
            c1 = self._dm_prev_z
            self.q[0] += 2.0 * w2 * (c0 + (-2.0 * c1 if self.N > 1 else 0.0))
            if self.N > 1:
                self.q[1] += 2.0 * w2 * c1

    def _cold_start(self) -> None:
        """Forget OSQP's iterate after a failed solve: a NaN iterate would otherwise be
        warm-started into every later solve."""
        self.solver.warm_start(x=np.zeros(self.nv), y=np.zeros(self.m))

    def _envelope_rows(self, x0: np.ndarray) -> bool:
        """The envelope shape's rows of A (dense; OSQP gets their CSC values) and their
        bounds (see the module docstring). Works in place on preallocated buffers (no
        allocation per step). False, with the envelope rows left inactive, when a row's
        values or offset are non-finite or beyond QP_MAGNITUDE_LIMIT (e.g. from a finite but
        absurd Vx): OSQP would reject l > u or a KKT matrix that is not quasidefinite."""
        N = self.N
        h = self.envelope.cfg if self.envelope is not None else None
        Ad = self._Adense
        env = self._env_now
        lo, hi = self.l, self.u
        r0 = 2 * N
        valid = True
        if env is not None and h is not None:
            r_max, a_max, ay = env
            vx0 = max(float(x0[0]), h.v_min_mps)
            G3 = self._G3
            c, ga, ya, hr, ha = self._c_env, self._ga, self._ya, self._hr, self._ha
            np.divide(self.envelope.lr, self._vx, out=c)
            c += h.lead_s
            gr = G3[:, 0, :]
            yr = self._yb3[:, 0]
            # α rows: G_β − c·G_r and ȳ_β − c·ȳ_r + T·ay/Vx
            np.multiply(gr, c[:, None], out=ga)
            np.subtract(G3[:, 1, :], ga, out=ga)
            np.multiply(yr, c, out=ya)
            np.subtract(self._yb3[:, 1], ya, out=ya)
            ya += h.lead_s * ay / vx0
            # h = (ȳ − G z̄)/bound
            # scaled by the bounds' reciprocals (the C core's order of operations)
            inv_r, inv_a = 1.0 / r_max, 1.0 / a_max
            np.matmul(gr, self._zbar, out=hr)
            np.subtract(yr, hr, out=hr)
            hr *= inv_r
            np.matmul(ga, self._zbar, out=ha)
            np.subtract(ya, ha, out=ha)
            ha *= inv_a
            np.multiply(gr, inv_r, out=Ad[r0:r0 + N, :N])
            Ad[r0 + N:r0 + 2 * N, :N] = Ad[r0:r0 + N, :N]
            np.multiply(ga, inv_a, out=Ad[r0 + 2 * N:r0 + 3 * N, :N])
            Ad[r0 + 3 * N:r0 + 4 * N, :N] = Ad[r0 + 2 * N:r0 + 3 * N, :N]
            lo[r0:r0 + N] = -OSQP_INF
            np.subtract(1.0, hr, out=hi[r0:r0 + N])
            np.subtract(-1.0, hr, out=lo[r0 + N:r0 + 2 * N])
            hi[r0 + N:r0 + 2 * N] = OSQP_INF
            lo[r0 + 2 * N:r0 + 3 * N] = -OSQP_INF
            np.subtract(1.0, ha, out=hi[r0 + 2 * N:r0 + 3 * N])
            np.subtract(-1.0, ha, out=lo[r0 + 3 * N:r0 + 4 * N])
            hi[r0 + 3 * N:r0 + 4 * N] = OSQP_INF
            # max() of an array holding NaN is NaN, and NaN < limit is False
            valid = bool(max(np.abs(hr).max(), np.abs(ha).max(),
                             np.abs(Ad[r0:r0 + 4 * N, :N]).max()) < QP_MAGNITUDE_LIMIT)
        if env is None or h is None or not valid:
            Ad[r0:r0 + 4 * N, :N] = 0.0
            lo[r0:r0 + 4 * N] = -OSQP_INF
            hi[r0:r0 + 4 * N] = OSQP_INF
        lo[6 * N:] = 0.0
        hi[6 * N:] = OSQP_INF
        return valid

    def _osqp_update(self) -> None:
        """Hand this round's P, q (and the envelope shape's A, l, u; else l, u when they
        changed) to OSQP."""
        if self.env:   # A's values in CSC order: only OSQP needs them
            self._Adense.ravel().take(self._env_flat, out=self._ax_env)
            self.solver.update(q=self._q64, Px=self._px64, Ax=self._ax_env, l=self.l,
                               u=self.u)
            self._bounds_dirty = False
        elif self._bounds_dirty:
            self.solver.update(q=self._q64, Px=self._px64, l=self.l, u=self.u)
            self._bounds_dirty = False
        else:   # l, u unchanged: skip their copy/clip in the wrapper
            self.solver.update(q=self._q64, Px=self._px64)

    def _closed_form_solution(self) -> np.ndarray | None:
        """The QP's solution (nv,) without OSQP when it has a closed form: the box collapsed
        to one value (ΔM fixed, e.g. a model not yet confident), else the cost's minimiser
        when it satisfies every row; None when OSQP solves."""
        fixed = self._fixed_box_solution()
        return fixed if fixed is not None else self._unconstrained_minimiser()

    def _fixed_box_solution(self) -> np.ndarray | None:
        """The envelope shape when the box holds every ΔM stage at one value c (l = u on the
        box rows): z = c and each slack the smallest that satisfies its rows — the cost is
        increasing in a slack ≥ 0 (price slack_linear ≥ 0, curvature > 0), so that is the
        QP's unique solution. The rate rows hold there: the first is anchored to the applied
        ΔM clipped into the box (set_bounds), i.e. to c, the others see equal stages; the
        envelope rows' data are finite (_envelope_rows refused others). None when this does
        not apply. float64, in decision units."""
        N = self.N
        lo, hi = self.l[:N], self.u[:N]
        if not self.env or not np.all(lo == hi):   # NaN fails too
            return None
        x = np.zeros(self.nv)
        x[:N] = lo
        env = self._Adense[2 * N:6 * N, :N] @ x[:N]
        for k, r0 in enumerate((2 * N, 4 * N)):   # s_r: yaw rows, s_α: slip rows
            up = env[r0 - 2 * N:r0 - N] - self.u[r0:r0 + N]
            down = self.l[r0 + N:r0 + 2 * N] - env[r0 - N:r0]
            x[N + k] = max(0.0, float(up.max()), float(down.max()))
        return x

    def _unconstrained_minimiser(self) -> np.ndarray | None:
        """The cost's minimiser (nv,) in decision units — ΔM = −P_zz⁻¹ q_z by Cholesky, the
        slacks 0 — when it satisfies every row l ≤ A x ≤ u; else None (OSQP solves). float64,
        from the data OSQP would get."""
        N = self.N
        P = np.zeros((N, N))
        P[self._tri_r, self._tri_c] = self._px64[:len(self._tri_r)]
        try:
            L = np.linalg.cholesky(P.T + np.triu(P, 1))   # the symmetric ΔM block
        except np.linalg.LinAlgError:
            return None
        z = -np.linalg.solve(L.T, np.linalg.solve(L, self._q64[:N]))
        x = np.zeros(self.nv)
        x[:N] = z
        az = self._az
        az[:N] = z
        if self.rate:
            az[N] = z[0]
            np.subtract(z[1:], z[:-1], out=az[N + 1:2 * N])
        if self.env:
            np.matmul(self._Adense[2 * N:6 * N, :N], z, out=az[2 * N:6 * N])
            az[6 * N:] = 0.0
        if not (np.all(az >= self.l) and np.all(az <= self.u)):   # NaN fails both
            return None
        return x

    def get_state(self) -> dict[str, np.ndarray | float]:
        """Warm-start state: last solution (N,) N·m, OSQP's last dual iterate (m,) and the
        ΔM applied at the last solve (decision units: the jerk weight's z_{−2} at the next).

        OSQP's internal adaptive ρ and scaled iterates are not exported, so a restored
        controller warm-starts from the same (x, y) but may differ from an uninterrupted
        run at the solver tolerance (eps_abs/eps_rel)."""
        y = self._y_last if self._y_last is not None else np.zeros(self.m)
        d = {"qp.sol": self.sol.copy(), "qp.y": np.array(y, dtype=float),
             "qp.zprev": float(self._dm_prev_z)}
        if self.env:
            d["qp.slack"] = self.slack.copy()
        return d

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        """Restore the last solution and warm-start OSQP from (x, y)."""
        self.sol[:] = np.asarray(d["qp.sol"], dtype=float)
        self._dm_prev_z = float(d.get("qp.zprev", 0.0))
        if self.env:
            self.slack[:] = np.asarray(d.get("qp.slack", np.zeros(2)), dtype=float)
        y = np.asarray(d.get("qp.y", np.zeros(self.m)), dtype=float)
        self.solver.warm_start(x=self._warm_x(), y=y)
        self._y_last = y.copy()   # get_state() after a restore returns what was restored

    def _warm_x(self) -> np.ndarray:
        """The primal warm start: the last solution in decision units (+ the slacks)."""
        x = self.sol / self.cfg.u_scale
        return np.concatenate([x, self.slack]) if self.env else x


# ---------------------------------------------------------------------- sparsity patterns
def qp_pattern(n: int, rate: bool) -> tuple[sp.csc_matrix, sp.csc_matrix]:
    """(P, A) patterns of the plain shape: P the full upper triangle (ones), A = I or
    [I; I − shift] (the rate rows)."""
    iu = np.triu_indices(n)
    order = np.lexsort((iu[0], iu[1]))
    P = sp.csc_matrix((np.ones(len(iu[0])), (iu[0][order], iu[1][order])), shape=(n, n))
    rows = [sp.eye(n, format="csc")]
    if rate:
        rows.append((sp.eye(n) - sp.eye(n, k=-1)).tocsc())
    return P, sp.vstack(rows, format="csc")


def envelope_a_dense(n: int, a_env: np.ndarray) -> np.ndarray:
    """Dense A (6n + 2, n + 2) of the envelope shape with the envelope rows ``a_env`` (4n, n):
    box I, rate [I − shift], envelope rows with −1 / +1 on their slack (s_r for the 2n yaw
    rows, s_α for the 2n slip rows: upper rows −1, lower rows +1), slack rows I."""
    A = np.zeros((6 * n + 2, n + 2))
    A[:n, :n] = np.eye(n)
    A[n:2 * n, :n] = np.eye(n) - np.eye(n, k=-1)
    A[2 * n:6 * n, :n] = a_env
    A[2 * n:3 * n, n] = -1.0
    A[3 * n:4 * n, n] = 1.0
    A[4 * n:5 * n, n + 1] = -1.0
    A[5 * n:6 * n, n + 1] = 1.0
    A[6 * n, n] = 1.0
    A[6 * n + 1, n + 1] = 1.0
    return A


def _env_mask(n: int) -> np.ndarray:
    """Structural non-zeros of the envelope shape's A (every envelope row is dense in z)."""
    return envelope_a_dense(n, np.ones((4 * n, n))) != 0.0


def envelope_pattern(n: int) -> tuple[sp.csc_matrix, sp.csc_matrix]:
    """(P, A) patterns of the envelope shape: P = the full upper triangle of the n ΔM
    decisions plus the two slack diagonals; A = envelope_a_dense's structure (ones)."""
    iu = np.triu_indices(n)
    r = np.concatenate([iu[0], [n, n + 1]])
    c = np.concatenate([iu[1], [n, n + 1]])
    P = sp.csc_matrix((np.ones(len(r)), (r, c)), shape=(n + 2, n + 2))
    mask = _env_mask(n)
    rr, cc = np.nonzero(mask)
    A = sp.csc_matrix((np.ones(len(rr)), (rr, cc)), shape=mask.shape)
    return P, A


def _csc_order(n: int) -> np.ndarray:
    """Permutation from the row-major structural order of the envelope shape's A (the order
    of A[mask]) to its CSC data order (by column, rows ascending)."""
    rr, cc = np.nonzero(_env_mask(n))
    return np.lexsort((rr, cc))
