"""UD-factored form of the RHONN weight EKF (same filter as ekf.py).

Each neuron's weight covariance is kept as P_i = U_i D_i U_iᵀ, U_i unit upper triangular
(L, L) and D_i (L,) > 0, instead of P_i itself:

* measurement update (scalar e_i, regressor H = φ): Bierman's sequential update of U, D
  and the gain K_i = P_i H / (R_i + Hᵀ P_i H), W_i += ζ_i K_i e_i (as in ekf.py);
* time update P_i ← P_i + q I: Thornton's method for a general Q is a modified weighted
  Gram–Schmidt on [U_i | I] (≈ 2 L³ multiply-adds); for this diagonal Q it is the same
  result as L rank-one updates P + q e_k e_kᵀ (Agee–Turner), which for a unit vector e_k
  touch only columns ≤ k: ≈ L³/6.

P is never formed, so it is positive definite by construction as long as every D_j > 0
(every step only adds positive terms to D or scales it by β/α ∈ (0, 1]): no
symmetrisation and no ``eigh`` repair (which a microcontroller would not have).
Guards as ekf.py: non-finite or non-positive innovation → rejected; D_j ≥ ``p_floor``;
trace(P_i) > trace_max → U = I, D = p0 (counted); |W| ≤ w_max (counted).

Units: W in the state unit u, D in u² (like P), U dimensionless.
"""

from __future__ import annotations

import numpy as np

from controller.core.learning.ekf import EkfConfig, EkfCounters


def udu_factor(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """U (L, L) unit upper triangular and D (L,) with P = U diag(D) Uᵀ (P symmetric PD).

    Reverse-order Cholesky-type factorisation (Bierman 1977, algorithm "UD factor")."""
    P = np.array(P, dtype=np.float64)
    L = P.shape[0]
    U = np.eye(L)
    D = np.zeros(L)
    for j in range(L - 1, -1, -1):
        D[j] = P[j, j] - float(np.sum(U[j, j + 1:] ** 2 * D[j + 1:]))
        for i in range(j):
            U[i, j] = (P[i, j] - float(np.sum(U[i, j + 1:] * U[j, j + 1:] * D[j + 1:]))) / D[j]
    return U, D


class UdEkf:
    """n independent scalar-measurement EKFs in UD form sharing the regressor H (L,).

    Same interface as ekf.BatchedEkf (W, update, reset, counters, get_state/set_state;
    ``P`` is the reconstructed covariance, for diagnostics and checkpoints)."""

    def __init__(self, n: int, n_weights: int, cfg: EkfConfig,
                 w0: np.ndarray | None = None, dtype: type = np.float64) -> None:
        if len(cfg.r) != n or len(cfg.zeta) != n:
            raise ValueError(f"EKF r and zeta need {n} entries")
        self.n, self.L, self.cfg = n, n_weights, cfg
        self.dtype = dtype
        L = n_weights
        self.w0 = np.zeros((n, L), dtype) if w0 is None else np.array(w0, dtype=dtype)
        self.W = self.w0.copy()
        self.U = np.zeros((n, L, L), dtype)
        self.D = np.zeros((n, L), dtype)
        self._R = np.asarray(cfg.r, dtype=dtype)
        self._zeta = np.asarray(cfg.zeta, dtype=dtype)
        # (q, p_floor, trace_max, p0, w_max) rounded to the working dtype
        self._limits = tuple(float(dtype(v)) for v in (cfg.q, cfg.p_floor, cfg.trace_max,
                                                        cfg.p0, cfg.w_max))
        self.counters = EkfCounters()
        self.reset()

    @property
    def P(self) -> np.ndarray:
        """Covariances U D Uᵀ (n, L, L), float64 (a new array; not used by the filter)."""
        U = self.U.astype(np.float64)
        return np.einsum("nij,nj,nkj->nik", U, self.D.astype(np.float64), U)

    def reset(self) -> None:
        """Cold start: W = W0, U = I, D = p0, counters zeroed."""
        self.W[:] = self.w0
        self.U[:] = np.eye(self.L, dtype=self.dtype)
        self.D[:] = self.cfg.p0
        self.counters.reset()

    def update(self, h: np.ndarray, e: np.ndarray, learn: bool = True) -> bool:
        """One learning step with regressor h (L,) and errors e (n,) = x − χ.

        Returns True when the weights were updated, False when frozen or rejected."""
        c = self.counters
        if not learn:
            c.frozen += 1
            return False
        return self._update(h, e)

    def update_error(self, h: np.ndarray, x: np.ndarray, chi: np.ndarray,
                     e: np.ndarray) -> bool:
        """update(h, e) with e = x − χ written into e (n,) first (x measured state, χ the
        recorded prediction)."""
        np.subtract(x, chi, out=e)
        return self.update(h, e, True)

    def _update(self, h: np.ndarray, e: np.ndarray) -> bool:
        """Bierman measurement update, Agee–Turner time update, then the guards."""
        c, dt = self.counters, self.dtype
        h = np.asarray(h, dtype=dt)
        e = np.asarray(e, dtype=dt)
        if not (np.isfinite(h.sum()) and np.isfinite(e.sum())):
            c.rejected += 1
            return False
        n, L = self.n, self.L
        F = np.einsum("nij,i->nj", self.U, h)                 # Uᵀ h per neuron
        s = self._R + np.sum(self.D * F * F, axis=1)
        if not (np.isfinite(s.sum()) and s.min() > 0.0):
            c.rejected += 1
            return False
        q, pf, tm, p0, wm = self._limits
        for i in range(n):
            U, D, f = self.U[i], self.D[i], F[i]
            k = np.zeros(L, dt)
            alpha = self._R[i]
            for j in range(L):                                # Bierman
                vj = D[j] * f[j]
                beta = alpha
                alpha = alpha + f[j] * vj
                lam = -f[j] / beta
                D[j] = D[j] * (beta / alpha)
                col = U[:j, j].copy()
                U[:j, j] = col + lam * k[:j]
                k[:j] = k[:j] + vj * col
                k[j] = vj
            self.W[i] += (k / alpha) * (self._zeta[i] * e[i])
            for kk in range(L):                               # P + q e_k e_kᵀ
                f = np.zeros(L, dt)
                f[kk] = 1.0
                cq = dt(q)
                for j in range(kk, -1, -1):                   # Agee–Turner
                    p = f[j]
                    dj = D[j]
                    dn = dj + cq * p * p
                    bet = cq * p / dn
                    cq = cq * dj / dn
                    D[j] = dn
                    f[:j] = f[:j] - p * U[:j, j]
                    U[:j, j] = U[:j, j] + bet * f[:j]
        for i in range(n):                                    # guards
            np.maximum(self.D[i], pf, out=self.D[i])
            tr = float(np.sum(self.D[i] * np.sum(np.triu(self.U[i]) ** 2, axis=0)))
            if tr > tm:
                self.U[i] = np.eye(L, dtype=dt)
                self.D[i] = p0
                c.trace_resets += 1
        if np.abs(self.W).max() > wm:
            np.clip(self.W, -wm, wm, out=self.W)
            c.weight_clips += 1
        c.updates += 1
        return True

    def get_state(self) -> dict[str, np.ndarray]:
        """Copies of W (n, L) and P = U D Uᵀ (n, L, L) (same keys as BatchedEkf)."""
        return {"W": self.W.astype(np.float64), "P": self.P}

    def set_state(self, d: dict[str, np.ndarray]) -> None:
        """Restore W and P (P is factorised into U, D; shapes checked)."""
        W = np.asarray(d["W"], dtype=float)
        P = np.asarray(d["P"], dtype=float)
        if W.shape != self.W.shape or P.shape != (self.n, self.L, self.L):
            raise ValueError("EKF state shape mismatch")
        self.W[:] = W
        for i in range(self.n):
            U, D = udu_factor(P[i])
            self.U[i] = U
            self.D[i] = D
