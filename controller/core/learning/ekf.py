"""Guarded EKF weight learning for RHONN neurons (paper eq. 10–12).

One filter per neuron i (here: one per state, batched along axis 0):

    K_i = P_i H / (R_i + Hᵀ P_i H)            (scalar innovation covariance)
    W_i ← W_i + ζ_i K_i e_i                    (e_i = x_i − χ_i, eq. 10)
    P_i ← P_i − K_i Hᵀ P_i + Q_i

with H = φ (eq. 12; identical for every neuron, which is what makes batching cheap).

Guards (all counted, see ``counters``):
* non-finite H, e or innovation covariance → the update is skipped (``rejected``);
* P kept exactly symmetric (rank-1 update written as u uᵀ), its diagonal floored at
  ``p_floor``; every
  ``eig_check_every`` updates the eigenvalues are floored as well (``eig_repairs``), so P
  stays symmetric positive definite;
* trace(P_i) > ``trace_max`` → P_i back to P0 (``trace_resets``): bounds covariance wind-up
  when the regressor is not exciting;
* |W| ≤ ``w_max`` element-wise (``weight_clips``);
* learning frozen on request (``frozen``), e.g. while the sensors are invalid.

Units: W has the unit of the state it predicts (m/s or rad/s) because φ is dimensionless;
P, Q in (state unit)²; R in (state unit)².
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.core.config_schema import build_section


@dataclass(slots=True)
class EkfConfig:
    """EKF tuning (units per neuron: state unit u = m/s for vx, vy and rad/s for r).

    p0: initial weight covariance, u². q: weight random-walk covariance per step, u².
    r: measurement noise covariance per neuron, u² (one per state). zeta: learning rate, -.
    p_floor: diagonal/eigenvalue floor of P, u². trace_max: trace bound of P, u².
    w_max: weight bound, u. eig_check_every: steps between eigenvalue checks (0 = never).
    form: "standard" (P itself, this module) or "ud" (P = U D Uᵀ, Bierman–Thornton,
    ud_ekf.py: positive definite by construction, no eigenvalue repair).
    q_nis: innovation-adaptive process noise (standard form): when a neuron's normalised
    innovation squared e²/s exceeds q_nis, its Q is multiplied by min(q_boost_max,
    e²/(s·q_nis)) for that step — the covariance opens when the prediction error jumps
    (re-learning after a change of the car or the road). 0 = off. q_boost_max: cap, -.
    """

    p0: float = 1.0
    q: float = 1e-5
    r: tuple[float, ...] = (1e-2, 1e-2, 1e-3)
    zeta: tuple[float, ...] = (1.0, 1.0, 1.0)
    p_floor: float = 1e-9
    trace_max: float = 1e3
    w_max: float = 1e3
    eig_check_every: int = 200
    form: str = "standard"
    q_nis: float = 0.0
    q_boost_max: float = 100.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EkfConfig:
        """Build from a TOML table; unknown keys and wrong types raise ConfigError."""
        return build_section(cls, d, "rhonn.ekf")


class EkfCounters:
    """Diagnostics of the learning guards (monotonic counts since the last reset).
    One object per filter for its whole life: ``reset()`` zeroes it in place."""

    def __init__(self) -> None:
        self.extra: dict[str, int] = {}
        self.reset()

    def reset(self) -> None:
        """All counts to zero."""
        self.updates = self.rejected = self.frozen = 0
        self.trace_resets = self.eig_repairs = self.weight_clips = 0
        self.extra.clear()

    def as_dict(self) -> dict[str, int]:
        """Plain dict for logging / status frames."""
        return {
            "updates": self.updates, "rejected": self.rejected, "frozen": self.frozen,
            "trace_resets": self.trace_resets, "eig_repairs": self.eig_repairs,
            "weight_clips": self.weight_clips,
        }


class BatchedEkf:
    """n independent scalar-measurement EKFs sharing the regressor H (L,)."""

    def __init__(self, n: int, n_weights: int, cfg: EkfConfig,
                 w0: np.ndarray | None = None, dtype: type = np.float64) -> None:
        """dtype: working precision (np.float64 or np.float32) of W, P and every
        intermediate."""
        if len(cfg.r) != n or len(cfg.zeta) != n:
            raise ValueError(f"EKF r and zeta need {n} entries")
        self.n = n
        self.L = n_weights
        self.cfg = cfg
        self.dtype = dtype
        self.w0 = np.zeros((n, n_weights), dtype) if w0 is None else np.array(w0, dtype=dtype)
        self.W = self.w0.copy()
        self.P = np.zeros((n, n_weights, n_weights), dtype)
        self._R = np.asarray(cfg.r, dtype=dtype)
        self._zeta = np.asarray(cfg.zeta, dtype=dtype)
        self._diag = np.arange(n_weights)
        # Scratch buffers: the hot path allocates nothing of lasting size.
        self._ph = np.zeros((n, n_weights), dtype)
        self._s = np.zeros(n, dtype)
        self._k = np.zeros((n, n_weights), dtype)
        self._tmp = np.zeros((n, n_weights, n_weights), dtype)
        self._tr = np.zeros(n, dtype)
        # Writable view of the diagonals of all P_i (flat stride L + 1), shape (n, L).
        self._pdiag = self.P.reshape(n, -1)[:, :: n_weights + 1]
        self.counters = EkfCounters()
        self.reset()

    def __setstate__(self, state: dict[str, Any]) -> None:
        # copy.deepcopy and pickle: the diagonal view must point into this copy's P
        self.__dict__.update(state)
        self._pdiag = self.P.reshape(self.n, -1)[:, :: self.L + 1]

    def reset(self) -> None:
        """Cold start: W = W0, P = p0·I, counters zeroed."""
        self.W[:] = self.w0
        self.P[:] = 0.0
        self.P[:, self._diag, self._diag] = self.cfg.p0
        self.counters.reset()
        self._since_eig = 0

    def update(self, h: np.ndarray, e: np.ndarray, learn: bool = True) -> bool:
        """One learning step with regressor h (L,) and errors e (n,) = x − χ.

        Returns True when the weights were updated, False when frozen or rejected.
        """
        c = self.counters
        if not learn:
            c.frozen += 1
            return False
        # One reduction each is cheaper than elementwise isfinite + all on tiny arrays.
        if not (np.isfinite(h.sum()) and np.isfinite(e.sum())):
            c.rejected += 1
            return False
        P, ph, s, k = self.P, self._ph, self._s, self._k
        np.matmul(P, h, out=ph)                       # (n, L) = P_i H
        np.matmul(ph, h, out=s)                       # Hᵀ P_i H
        s += self._R
        if not (np.isfinite(s.sum()) and s.min() > 0.0):
            c.rejected += 1
            return False
        np.divide(ph, s[:, None], out=k)              # K_i
        q = self.cfg.q
        if self.cfg.q_nis > 0.0:
            # per neuron: Q_i = q · clip(e_i² / (s_i q_nis), 1, q_boost_max)
            q = q * np.clip(e * e / (s * self.cfg.q_nis), 1.0, self.cfg.q_boost_max)[:, None]
        # W_i += ζ_i K_i e_i
        self.W += k * (self._zeta * e)[:, None]
        # P_i ← P_i − (P_i H)(P_i H)ᵀ / s_i + Q, written as u uᵀ with u = P_i H / √s_i:
        # u_a·u_b == u_b·u_a bit for bit, so P stays exactly symmetric (no re-symmetrising).
        np.sqrt(s, out=s)
        np.divide(ph, s[:, None], out=ph)
        tmp = self._tmp
        np.multiply(ph[:, :, None], ph[:, None, :], out=tmp)
        P -= tmp
        self._pdiag += q
        self._guard()
        c.updates += 1
        return True

    def update_error(self, h: np.ndarray, x: np.ndarray, chi: np.ndarray,
                     e: np.ndarray) -> bool:
        """update(h, e) with e = x − χ written into e (n,) first (x measured state, χ the
        recorded prediction)."""
        np.subtract(x, chi, out=e)
        return self.update(h, e, True)

    def _guard(self) -> None:
        """Diagonal floor, trace bound (counted reset), weight bound, periodic eig floor."""
        cfg, c, P, d = self.cfg, self.counters, self.P, self._diag
        diag = self._pdiag
        if diag.min() < cfg.p_floor:
            np.maximum(diag, cfg.p_floor, out=diag)
        np.sum(diag, axis=1, out=self._tr)
        if self._tr.max() > cfg.trace_max:
            for i in range(self.n):
                if self._tr[i] > cfg.trace_max:
                    P[i] = 0.0
                    P[i, d, d] = cfg.p0
                    c.trace_resets += 1
        wmax = cfg.w_max
        if np.abs(self.W).max() > wmax:
            np.clip(self.W, -wmax, wmax, out=self.W)
            c.weight_clips += 1
        if cfg.eig_check_every > 0:
            self._since_eig += 1
            if self._since_eig >= cfg.eig_check_every:
                self._since_eig = 0
                self.enforce_spd()

    def enforce_spd(self) -> int:
        """Floor the eigenvalues of every P_i at p_floor; returns the number repaired."""
        repaired = 0
        for i in range(self.n):
            lam, vec = np.linalg.eigh(self.P[i])
            if not np.all(np.isfinite(lam)):
                self.P[i] = 0.0
                self.P[i, self._diag, self._diag] = self.cfg.p0
                repaired += 1
            elif lam[0] < self.cfg.p_floor:
                lam = np.maximum(lam, self.cfg.p_floor)
                self.P[i] = (vec * lam) @ vec.T
                self.P[i] = 0.5 * (self.P[i] + self.P[i].T)
                repaired += 1
        self.counters.eig_repairs += repaired
        return repaired

    def get_state(self) -> dict[str, np.ndarray]:
        """Copies of W (n, L) and P (n, L, L)."""
        return {"W": self.W.copy(), "P": self.P.copy()}

    def set_state(self, d: dict[str, np.ndarray]) -> None:
        """Restore W and P (shapes checked)."""
        W = np.asarray(d["W"], dtype=self.dtype)
        P = np.asarray(d["P"], dtype=self.dtype)
        if W.shape != self.W.shape or P.shape != self.P.shape:
            raise ValueError("EKF state shape mismatch")
        self.W[:] = W
        self.P[:] = P
